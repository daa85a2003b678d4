"""The methods a comparison fuses: no correction, the response alone, the response with a polynomial or a LUT
vignetting model from a white-paper calibration or with a LUT self-calibrated from an RGB-D sequence
(``self``: the ``vignetting.npz`` of ``radiomap self-calibrate``), each but the first optionally with exposure
compensation (``+ec``).

Equal brightness (``brightness="mean"``, the default of :func:`mapping.compare.compare`). Where ``V = 1`` is put
is a convention (the optical centre), yet it sets the brightness of the corrected images: ``f^-1(I) / V`` is
brighter than the raw image by ``1 / mean(V)`` on average (~1.2 for an Xtion), and through the S-shaped response a
brighter display changes every L1 distance. Methods are compared at equal brightness: each vignetting model is
rescaled per channel to an image mean of 1 (:func:`equal_brightness`: a
:class:`~radiometry.vignetting.LUTVignetting` of ``V / mean(V)``), so the corrected irradiance displays, on
average, at the raw image's levels and only the *shape* of each correction differs. ``brightness="calibrated"``
uses the models as calibrated (``V = 1`` at the centre).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting, PolynomialVignetting, VignettingModel

BASE_METHODS = ("none", "response", "poly", "lut", "self")
EC_SUFFIX = "+ec"
METHOD_NAMES = BASE_METHODS + tuple(m + EC_SUFFIX for m in BASE_METHODS[1:])
DEFAULT_METHODS = ("none", "poly", "lut")
LABELS = {"none": "no correction", "response": "response only", "poly": "polynomial vignetting",
          "lut": "LUT vignetting", "self": "self-calibrated vignetting"}
#: how a method's missing model is supplied (the error names it)
MODEL_SOURCES = {"poly": "--vignetting-poly", "lut": "--vignetting-lut",
                 "self": "--vignetting-self: the vignetting.npz that 'radiomap self-calibrate' writes"}
BRIGHTNESS = ("mean", "calibrated")


@dataclass(frozen=True, eq=False)
class Method:
    """One way of turning frames into map colours.

    name:        short identifier (``none``, ``response``, ``poly``, ``lut``, ``self``, each but ``none`` with
                 ``+ec``);
                 also the name of the method's results folder.
    label:       what the figures call it.
    response:    the camera response, or None for raw intensities (no correction).
    vignetting:  a vignetting model, or None.
    exposure_compensation: divide each frame's irradiance by its estimated exposure.
    """

    name: str
    label: str
    response: CameraResponse | None = None
    vignetting: VignettingModel | None = None
    exposure_compensation: bool = False

    def __post_init__(self) -> None:
        if self.response is None and (self.vignetting is not None or self.exposure_compensation):
            raise ValueError(f"method {self.name!r}: vignetting correction and exposure compensation act on "
                             "irradiance and need the camera response")
        if not self.name or any(ch in self.name for ch in "/\\ "):
            raise ValueError(f"method name must be a non-empty word usable as a folder name, got {self.name!r}")

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "label": self.label,
                "response": None if self.response is None else repr(self.response),
                "vignetting": None if self.vignetting is None else repr(self.vignetting),
                "vignetting_model": None if self.vignetting is None else self.vignetting.info.get("method"),
                "exposure_compensation": self.exposure_compensation}


def make_methods(response: CameraResponse | None, *, vignetting_poly: VignettingModel | None = None,
                 vignetting_lut: VignettingModel | None = None, vignetting_self: LUTVignetting | None = None,
                 exposure_compensation: bool = False, names: Sequence[str] | None = None) -> list[Method]:
    """The methods to compare, in order.

    vignetting_self: a LUT self-calibrated from a sequence (:func:`mapping.self_calibration.run_self_calibration`),
    for the ``self`` methods. names: among :data:`METHOD_NAMES`; default ``none, poly, lut`` plus ``poly+ec,
    lut+ec`` when ``exposure_compensation``. A method whose model is not given is an error naming the missing
    option.
    """
    if names is None:
        names = list(DEFAULT_METHODS)
        if exposure_compensation:
            names += ["poly" + EC_SUFFIX, "lut" + EC_SUFFIX]
    names = list(names)
    if not names:
        raise ValueError("names must list at least one method")
    bad = [n for n in names if n not in METHOD_NAMES]
    if bad:
        raise ValueError(f"unknown method(s) {', '.join(map(repr, bad))}; valid: {', '.join(METHOD_NAMES)} "
                         "('none' cannot be exposure-compensated: raw intensities are not linear in exposure)")
    if len(set(names)) != len(names):
        raise ValueError(f"names must not repeat a method, got {names}")
    models = {"poly": vignetting_poly, "lut": vignetting_lut, "self": vignetting_self}
    out = []
    for name in names:
        base = name.removesuffix(EC_SUFFIX)
        ec = name.endswith(EC_SUFFIX)
        if base == "none":
            out.append(Method("none", LABELS["none"]))
            continue
        if response is None:
            raise ValueError(f"method {name!r} needs the camera response (--response)")
        vig = models.get(base)
        if base in models and vig is None:
            raise ValueError(f"method {name!r} needs the {base} vignetting model ({MODEL_SOURCES[base]})")
        if vig is not None:
            _check_model_kind(base, vig)
        label = LABELS[base] + (" + exposure comp." if ec else "")
        out.append(Method(name, label, response, vig, ec))
    return out


def _check_model_kind(base: str, model: VignettingModel) -> None:
    """The ``poly`` method needs a polynomial model and ``lut`` and ``self`` a look-up table: a model of the other
    kind would be compared under the wrong label (ValueError: a model object passed as an argument)."""
    problem = _kind_mismatch(base, model)
    if problem is not None:
        source = model.info.get("source") if isinstance(getattr(model, "info", None), dict) else None
        where = f"--vignetting-{base}"
        raise ValueError(f"{where} holds {problem[0]}{f' ({source})' if source else ''}, {problem[1]}")


def _kind_mismatch(base: str, model: VignettingModel) -> tuple[str, str] | None:
    """None if ``model`` is of the kind the method ``base`` (``poly``, ``lut``, ``self``) needs; else (what it holds,
    the fix)."""
    wanted = {"poly": PolynomialVignetting, "lut": LUTVignetting, "self": LUTVignetting}[base]
    if isinstance(model, wanted):
        return None
    kind = "polynomial" if isinstance(model, PolynomialVignetting) else "look-up table (LUT)" \
        if isinstance(model, LUTVignetting) else type(model).__name__
    other = "lut" if base == "poly" else "poly"
    if base == "self":
        return (f"a {kind} vignetting model", "not the look-up table 'radiomap self-calibrate' writes (its "
                "vignetting.npz); pass a polynomial as --vignetting-poly")
    return (f"a {kind} vignetting model", f"not a {'polynomial' if base == 'poly' else 'look-up table'}; pass it as "
            f"--vignetting-{other}, or calibrate the other kind with 'radiomap vignetting --model {base}'")


def load_method_vignetting(path: str | Path, base: str) -> VignettingModel:
    """The vignetting model file of the method ``base`` (``poly``, ``lut`` or ``self``; ``--vignetting-poly/-lut/
    -self``): a file :func:`radiometry.api.read_vignetting` reads (a V array ``.npy`` is a LUT). A model of the
    other kind is a :class:`~radiometry.errors.CalibrationFileError` naming the file and the fix."""
    from radiometry.api import read_vignetting

    if base not in ("poly", "lut", "self"):
        raise ValueError(f"base must be 'poly', 'lut' or 'self', got {base!r}")
    model = read_vignetting(path)
    problem = _kind_mismatch(base, model)
    if problem is not None:
        raise CalibrationFileError(f"{path}: --vignetting-{base} holds {problem[0]}, {problem[1]}")
    return model


def equal_brightness(model: VignettingModel, height: int, width: int) -> LUTVignetting:
    """``V / mean(V)`` per channel at ``height x width`` as a LUT (see the module doc, "Equal brightness")."""
    v = model.evaluate(int(height), int(width)).astype(np.float64)
    mean = v.reshape(-1, v.shape[2]).mean(axis=0)
    info = {**model.info, "normalised": "per-channel image mean 1", "channel_means": mean.tolist(),
            "from": repr(model)}
    return LUTVignetting((v / mean).astype(np.float32), info=info)
