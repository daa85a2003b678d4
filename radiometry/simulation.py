"""A simulated camera with every radiometric quantity known: CRF, vignetting, exposure, noise.

Image formation, per colour channel ``c`` (RGB) and pixel ``x``::

    E_c(x) = k * g_c * V_c(x) * L_c(x)           irradiance on the sensor, saturating at E = 1
    E'_c   = E_c + sqrt(E_c / full_well + read_noise^2) * N(0, 1)      shot + read noise
    I_c    = clip(round(f_c(E'_c)), 0, 255)      8-bit intensity (optionally JPEG-compressed)

``L`` is scene radiance (arbitrary linear units), ``k`` the exposure time in seconds, ``g_c`` the
white-balance gain, ``V_c`` the vignetting (1 at its maximum), ``f_c`` the camera response whose
inverse is a :class:`~radiometry.response.CameraResponse` (``f^-1(255) = 1``: irradiance 1 is the
saturation level). Shot noise is the Gaussian approximation of Poisson noise with ``full_well``
electrons at saturation; read noise is additive, in units of the saturation irradiance.

Building blocks, each usable on its own:

- CRFs: :func:`crf_linear`, :func:`crf_gamma`, :func:`crf_s_curve` (parametric), :func:`crf_from_table`
  and :func:`crf_from_pcalib` (tabulated); :func:`make_crf` dispatches on ``family``.
- Vignetting: :class:`VignettingSpec` (per-channel even polynomial with its own centre, times a smooth
  non-radial field; or a DSO ``vignette.png``; or lensfun ``pa`` coefficients via
  :func:`find_lensfun_vignetting`), :func:`vignetting_preset`.
- Exposure: :class:`AutoExposure`, :class:`AutoWhiteBalance` and the stateful
  :class:`ExposureController` that meters the previous frame like a camera does.
- :class:`CameraSpec` holds all parameters and round-trips through JSON; :class:`SimulatedCamera`
  turns radiance into images (:meth:`SimulatedCamera.capture`).

Conventions. Pixel ``(x, y)`` has its centre at ``(x, y)`` (OpenCV); vignetting centres are given as
fractions of the image size, ``x = cx * W - 0.5`` (so ``0.5`` is the image centre at any resolution)
and the radius is normalised by the half-diagonal ``R = 0.5 * sqrt(W^2 + H^2)`` as in
:mod:`radiometry.vignetting` and lensfun. Randomness only comes from a ``numpy.random.Generator``
passed explicitly.
"""

from __future__ import annotations

import json
import logging
import math
import os
import xml.etree.ElementTree as ET
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.fileio import atomic_write_json
from radiometry.response import LEVELS, CameraResponse

log = logging.getLogger(__name__)

CHANNELS = 3
CAMERA_FORMAT = "radiomap-camera"
CAMERA_FORMAT_VERSION = 1
# Rec. 601 luma weights: what a camera's metering calls "brightness"
_LUMA = np.array([0.299, 0.587, 0.114])


# ==================================================================================================
# camera response functions
# ==================================================================================================
def _per_channel(value: Any, name: str, channels: int, *, low: float = 0.0, strict: bool = True) -> np.ndarray:
    arr = np.array(value, dtype=np.float64, ndmin=1)
    if arr.shape == (1,):
        arr = np.repeat(arr, channels)
    if arr.shape != (channels,):
        raise ValueError(f"{name} must be one number or {channels} numbers (one per channel), got {value!r}")
    if not np.all(np.isfinite(arr)) or np.any(arr < low) or (strict and np.any(arr <= low)):
        bound = f"> {low}" if strict else f">= {low}"
        raise ValueError(f"{name} must be finite and {bound}, got {value!r}")
    return arr


def crf_linear(*, channels: int = 3) -> CameraResponse:
    """A linear camera: ``f^-1(I) = I / 255``."""
    resp = CameraResponse.linear(channels)
    return CameraResponse(resp.inverse_table, {"method": "simulated", "family": "linear"})


def crf_gamma(gamma: float | Sequence[float] = 2.2, *, channels: int = 3) -> CameraResponse:
    """Gamma-like response ``f^-1(I) = (I / 255) ** gamma``, one ``gamma`` or one per channel."""
    g = _per_channel(gamma, "gamma", channels)
    x = np.arange(LEVELS, dtype=np.float64) / (LEVELS - 1)
    table = x[:, None] ** g[None, :]
    return CameraResponse(table, {"method": "simulated", "family": "gamma", "gamma": g.tolist()})


def crf_s_curve(contrast: float | Sequence[float] = 5.0, midpoint: float | Sequence[float] = 0.5,
                gamma: float | Sequence[float] = 2.0, *, channels: int = 3) -> CameraResponse:
    """S-shaped response: a gamma encoding followed by a normalised logistic tone curve.

    ``f(E) = (s(a (E^(1/gamma) - m)) - s(-a m)) / (s(a (1 - m)) - s(-a m))`` with ``s`` the logistic
    function, ``a = contrast`` (steepness, > 0.1; small values approach a pure gamma) and ``m =
    midpoint`` in (0, 1). The inverse is analytic, so the table is exact. Each parameter is one
    number or one per channel (real cameras differ slightly per channel).
    """
    a = _per_channel(contrast, "contrast", channels, low=0.1)
    m = _per_channel(midpoint, "midpoint", channels)
    if np.any(m >= 1):
        raise ValueError(f"midpoint must be in (0, 1), got {midpoint!r}")
    g = _per_channel(gamma, "gamma", channels)
    z = np.arange(LEVELS, dtype=np.float64)[:, None] / (LEVELS - 1)
    s0 = 1.0 / (1.0 + np.exp(a * m))          # s(-a m)
    s1 = 1.0 / (1.0 + np.exp(-a * (1 - m)))   # s(a (1 - m))
    q = np.clip(s0 + z * (s1 - s0), 1e-300, 1 - 1e-16)
    y = m + np.log(q / (1 - q)) / a
    y[0] = 0.0
    y[-1] = 1.0
    table = np.clip(y, 0.0, 1.0) ** g
    return CameraResponse(table, {"method": "simulated", "family": "s_curve", "contrast": a.tolist(),
                                  "midpoint": m.tolist(), "gamma": g.tolist()})


def crf_from_table(table: Any, *, source: str = "table") -> CameraResponse:
    """A tabulated inverse response (256 values, or 256 x C); any positive scale, normalised here."""
    resp = CameraResponse.from_table(np.asarray(table, dtype=np.float64))
    return CameraResponse(resp.inverse_table, {"method": "simulated", "family": "table", "source": source})


def read_pcalib_table(path: str | os.PathLike) -> np.ndarray:
    """The 256 inverse-response values of a DSO/TUM ``pcalib.txt`` (first line), float64 ``(256,)``,
    normalised as DSO does: ``(G - G[0]) / (G[255] - G[0])`` (so ``f^-1(0) = 0``, ``f^-1(255) = 1``).

    Uses :func:`radiometry.formats.pcalib.read_pcalib` when that reader is installed, else parses the
    first line here (256 numbers, strictly increasing; trailing lines are ignored as DSO does).
    """
    path = Path(path)
    try:
        from radiometry.formats.pcalib import read_pcalib  # type: ignore[import-not-found]
    except ImportError:
        read_pcalib = None
    if read_pcalib is not None:
        resp = read_pcalib(path)
        if isinstance(resp, CameraResponse):
            return np.asarray(resp.inverse_table[:, 0], dtype=np.float64)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file; check the path of the pcalib.txt response")
    try:
        first = path.read_text(encoding="utf-8", errors="replace").splitlines()[0]
        values = np.array([float(v) for v in first.split()], dtype=np.float64)
    except (IndexError, ValueError) as exc:
        raise CalibrationFileError(f"{path}, line 1: not a list of numbers ({exc}); a pcalib.txt starts "
                                   "with the 256 values of the inverse response") from None
    if values.size != LEVELS:
        raise CalibrationFileError(f"{path}, line 1: {values.size} values where 256 are needed; "
                                   "a pcalib.txt starts with the 256 values of the inverse response")
    if not np.all(np.isfinite(values)) or np.any(np.diff(values) <= 0) or values[-1] <= 0:
        raise CalibrationFileError(f"{path}, line 1: the inverse response is not strictly increasing "
                                   "and finite; re-export the calibration")
    return (values - values[0]) / (values[-1] - values[0])


def crf_from_pcalib(path: str | os.PathLike, *, channels: int = 3) -> CameraResponse:
    """The (monochrome) response of a DSO/TUM ``pcalib.txt``, repeated for ``channels`` channels."""
    table = np.repeat(read_pcalib_table(path)[:, None], channels, axis=1)
    return CameraResponse(table, {"method": "simulated", "family": "pcalib", "source": str(path)})


CRF_FAMILIES = ("linear", "gamma", "s_curve", "table", "pcalib")


def make_crf(family: str, *, channels: int = 3, **params: Any) -> CameraResponse:
    """Dispatch on ``family``: ``linear``, ``gamma`` (``gamma``), ``s_curve`` (``contrast``,
    ``midpoint``, ``gamma``), ``table`` (``table``, 256 x C) or ``pcalib`` (``path``; ``table`` if given
    is used instead of the file, so that a saved camera does not depend on the file)."""
    if family == "linear":
        _no_params(family, params)
        return crf_linear(channels=channels)
    if family == "gamma":
        _check_params(family, params, {"gamma"})
        return crf_gamma(params.get("gamma", 2.2), channels=channels)
    if family == "s_curve":
        _check_params(family, params, {"contrast", "midpoint", "gamma"})
        return crf_s_curve(channels=channels, **params)
    if family == "table":
        _check_params(family, params, {"table", "source"}, required={"table"})
        return crf_from_table(params["table"], source=str(params.get("source", "table")))
    if family == "pcalib":
        _check_params(family, params, {"path", "table"})
        if "table" in params:
            resp = CameraResponse.from_table(np.asarray(params["table"], dtype=np.float64))
            return CameraResponse(resp.inverse_table, {"method": "simulated", "family": "pcalib",
                                                       "source": str(params.get("path", ""))})
        if "path" not in params:
            raise ValueError("crf family 'pcalib' needs path=<pcalib.txt> (or table=...)")
        return crf_from_pcalib(params["path"], channels=channels)
    raise ValueError(f"unknown crf family {family!r}; valid names: {', '.join(CRF_FAMILIES)}")


def _no_params(family: str, params: Mapping[str, Any]) -> None:
    if params:
        raise ValueError(f"crf family {family!r} takes no parameters, got {sorted(params)}")


def _check_params(family: str, params: Mapping[str, Any], allowed: set[str], required: set[str] = frozenset()) -> None:
    unknown = set(params) - allowed
    if unknown:
        raise ValueError(f"crf family {family!r} does not take {sorted(unknown)}; valid: {sorted(allowed)}")
    missing = set(required) - set(params)
    if missing:
        raise ValueError(f"crf family {family!r} needs {sorted(missing)}")


def crf_spec_from_file(path: str | os.PathLike) -> dict[str, Any]:
    """A self-contained CRF spec (``family: table``) from a ``pcalib.txt`` or a radiomap ``.npz``."""
    path = Path(path)
    if path.suffix.lower() == ".txt":
        resp = crf_from_pcalib(path)
    else:
        resp = CameraResponse.load(path)
    return {"family": "table", "table": resp.inverse_table.tolist(), "source": str(path)}


CRF_PRESETS = {
    "linear": {"family": "linear"},
    "gamma": {"family": "gamma", "gamma": 2.2},
    # slightly different per channel, as measured responses are
    "s_curve": {"family": "s_curve", "contrast": [5.0, 5.4, 4.6], "midpoint": [0.5, 0.48, 0.52],
                "gamma": [1.9, 2.0, 2.15]},
}


# ==================================================================================================
# vignetting
# ==================================================================================================
def pixel_grid(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Column and row pixel-centre coordinates, float64 ``(W,)`` and ``(H,)``."""
    return np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64)


def polynomial_for_corner(corner: float) -> tuple[float, float, float]:
    """Coefficients ``(b1, b2, b3)`` of a monotone cos^4-like fall-off that reaches ``corner`` at r = 1."""
    if not 0.05 <= corner <= 1.0:
        raise ValueError(f"corner must be within [0.05, 1] (V at the image corner), got {corner}")
    d = 1.0 - corner
    return (-1.1 * d, 0.15 * d, -0.05 * d)


def polynomial_vignetting(width: int, height: int, coeffs: Any, centres: Any) -> np.ndarray:
    """``1 + b1 r^2 + b2 r^4 + b3 r^6`` per channel, not normalised, float64 ``(H, W, C)``.

    ``coeffs`` is ``(C, 3)``; ``centres`` ``(C, 2)`` fractions of the image size (0.5 = centre).
    """
    b = np.array(coeffs, dtype=np.float64, ndmin=2)
    c = np.array(centres, dtype=np.float64, ndmin=2)
    if b.ndim != 2 or b.shape[1] != 3:
        raise ValueError(f"coeffs must have shape (C, 3), got {np.shape(coeffs)}")
    if c.shape != (b.shape[0], 2):
        raise ValueError(f"centres must have shape ({b.shape[0]}, 2) to match coeffs, got {np.shape(centres)}")
    xs, ys = pixel_grid(width, height)
    radius = 0.5 * math.hypot(width, height)
    out = np.empty((height, width, b.shape[0]), dtype=np.float64)
    for ch in range(b.shape[0]):
        cx, cy = c[ch, 0] * width - 0.5, c[ch, 1] * height - 0.5
        r2 = ((xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2) / radius**2
        out[:, :, ch] = 1.0 + r2 * (b[ch, 0] + r2 * (b[ch, 1] + r2 * b[ch, 2]))
    return out


def nonradial_field(width: int, height: int, terms: Sequence[Sequence[float]]) -> np.ndarray:
    """A smooth multiplicative field ``1 + sum_k a_k cos(pi (fx_k u + px_k)) cos(pi (fy_k v + py_k))``.

    ``u = (x + 0.5) / W`` and ``v = (y + 0.5) / H`` run over (0, 1); each term is ``(a, fx, fy, px,
    py)``. Low orders (``fx, fy`` <= 2) and amplitudes of a few percent give the gentle asymmetric
    shading of a real lens/sensor stack that no radial polynomial can fit. float64 ``(H, W)``.
    """
    u = (np.arange(width, dtype=np.float64) + 0.5) / width
    v = (np.arange(height, dtype=np.float64) + 0.5) / height
    out = np.ones((height, width), dtype=np.float64)
    for term in terms:
        if len(term) != 5:
            raise ValueError(f"a non-radial term is (amplitude, fx, fy, phase_x, phase_y), got {term!r}")
        a, fx, fy, px, py = (float(t) for t in term)
        out += a * np.cos(np.pi * (fy * v + py))[:, None] * np.cos(np.pi * (fx * u + px))[None, :]
    return out


def _read_vignette_png(path: Path) -> np.ndarray:
    try:
        from radiometry.formats.dso_vignette import read_dso_vignette
    except ImportError:
        read_dso_vignette = None
    if read_dso_vignette is not None:
        lut = np.asarray(read_dso_vignette(path).lut, dtype=np.float64)
        return lut[:, :, 0] if lut.ndim == 3 else lut
    import cv2

    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file; check the path of the vignette.png")
    raw = np.fromfile(path, dtype=np.uint8)
    img = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED) if raw.size else None
    if img is None or img.ndim != 2 or img.dtype not in (np.uint8, np.uint16) or img.max() == 0 or img.min() == 0:
        raise CalibrationFileError(f"{path}: not a single-channel 8/16-bit vignetting image with V > 0; "
                                   "re-export the DSO vignette")
    return img.astype(np.float64) / float(img.max())


def vignette_map_from_png(path: str | os.PathLike, width: int, height: int) -> np.ndarray:
    """A DSO ``vignette.png`` resampled to ``width x height``: centre-cropped to the target aspect
    ratio first (no stretching), then resized (area for shrinking, bilinear for enlarging); float64
    ``(H, W)`` with maximum 1."""
    import cv2

    src = _read_vignette_png(Path(path))
    sh, sw = src.shape
    target = width / height
    if sw / sh > target:  # too wide: crop columns
        cw = max(1, int(round(sh * target)))
        x0 = (sw - cw) // 2
        src = src[:, x0:x0 + cw]
    elif sw / sh < target:
        ch = max(1, int(round(sw / target)))
        y0 = (sh - ch) // 2
        src = src[y0:y0 + ch, :]
    interp = cv2.INTER_AREA if src.shape[1] > width else cv2.INTER_LINEAR
    out = cv2.resize(np.ascontiguousarray(src), (width, height), interpolation=interp).astype(np.float64)
    return out / out.max()


VIGNETTING_KINDS = ("polynomial", "dso", "none")


@dataclass(frozen=True)
class VignettingSpec:
    """Everything that defines a simulated vignetting field; resolution independent.

    kind:      ``polynomial`` (per-channel ``1 + b1 r^2 + b2 r^4 + b3 r^6`` about its own centre),
               ``dso`` (a ``vignette.png`` map, the same for every channel) or ``none``.
    coeffs:    ``(3, 3)`` ``b1, b2, b3`` per RGB channel; ``r`` normalised by the half-diagonal.
    centres:   ``(3, 2)`` optical centre per channel as fractions of (width, height); 0.5 = centre.
    nonradial: terms ``(a, fx, fy, px, py)`` of :func:`nonradial_field`, multiplied onto any kind.
    path:      the ``vignette.png`` for ``kind="dso"``.
    source:    provenance (preset name, lensfun lens, file), informational.

    :meth:`render` gives ``V`` float32 ``(H, W, 3)``, each channel normalised to a maximum of 1.
    """

    kind: str = "polynomial"
    coeffs: tuple = ((0.0, 0.0, 0.0),) * 3
    centres: tuple = ((0.5, 0.5),) * 3
    nonradial: tuple = ()
    path: str | None = None
    source: str = ""

    def __post_init__(self) -> None:
        if self.kind not in VIGNETTING_KINDS:
            raise ValueError(f"vignetting kind must be one of {', '.join(VIGNETTING_KINDS)}, got {self.kind!r}")
        coeffs = np.array(self.coeffs, dtype=np.float64, ndmin=2)
        if coeffs.shape == (1, 3):
            coeffs = np.repeat(coeffs, 3, axis=0)
        if coeffs.shape != (3, 3) or not np.all(np.isfinite(coeffs)):
            raise ValueError(f"coeffs must be 3 finite numbers or (3, 3) per channel, got {self.coeffs!r}")
        centres = np.array(self.centres, dtype=np.float64, ndmin=2)
        if centres.shape == (1, 2):
            centres = np.repeat(centres, 3, axis=0)
        if centres.shape != (3, 2) or not np.all(np.isfinite(centres)):
            raise ValueError(f"centres must be (cx, cy) or (3, 2) per channel, got {self.centres!r}")
        terms = tuple(tuple(float(v) for v in t) for t in self.nonradial)
        for t in terms:
            if len(t) != 5 or not all(np.isfinite(t)):
                raise ValueError(f"a non-radial term is 5 finite numbers (a, fx, fy, px, py), got {t!r}")
        if sum(abs(t[0]) for t in terms) >= 0.5:
            raise ValueError("the non-radial amplitudes must sum to less than 0.5 (a few percent is realistic)")
        if self.kind == "dso" and not self.path:
            raise ValueError("vignetting kind 'dso' needs path=<vignette.png>")
        object.__setattr__(self, "coeffs", tuple(tuple(r) for r in coeffs.tolist()))
        object.__setattr__(self, "centres", tuple(tuple(r) for r in centres.tolist()))
        object.__setattr__(self, "nonradial", terms)
        if self.path is not None:
            object.__setattr__(self, "path", str(self.path))

    def render(self, width: int, height: int) -> np.ndarray:
        """``V`` for a ``width x height`` image: float32 ``(H, W, 3)``, maximum 1 per channel."""
        width, height = _check_size(width, height)
        if self.kind == "none":
            base = np.ones((height, width, 3), dtype=np.float64)
        elif self.kind == "dso":
            base = np.repeat(vignette_map_from_png(self.path, width, height)[:, :, None], 3, axis=2)
        else:
            base = polynomial_vignetting(width, height, self.coeffs, self.centres)
        if self.nonradial:
            base = base * nonradial_field(width, height, self.nonradial)[:, :, None]
        low = float(base.min())
        if low <= 0.01:
            raise ValueError(f"these vignetting parameters give V = {low:.3g} <= 0.01 inside the image "
                             f"({self.source or self.kind}); use a milder fall-off")
        base /= base.reshape(-1, 3).max(axis=0)
        return base.astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "coeffs": [list(r) for r in self.coeffs],
                "centres": [list(r) for r in self.centres], "nonradial": [list(t) for t in self.nonradial],
                "path": self.path, "source": self.source}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "VignettingSpec":
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown vignetting fields {sorted(unknown)}; valid: {sorted(known)}")
        return cls(**dict(data))

    @classmethod
    def polynomial(cls, corner: float | Sequence[float] = 0.5, *, centres: Any = (0.5, 0.5),
                   nonradial: Sequence[Sequence[float]] = (), source: str = "") -> "VignettingSpec":
        """Fall-off to ``corner`` (one value or one per channel) at r = 1 (the corners of a centred
        model) with the shape of :func:`polynomial_for_corner`."""
        corners = _per_channel(corner, "corner", 3)
        return cls("polynomial", tuple(polynomial_for_corner(c) for c in corners), centres,
                   tuple(nonradial), None, source)

    @classmethod
    def dso(cls, path: str | os.PathLike, *, nonradial: Sequence[Sequence[float]] = ()) -> "VignettingSpec":
        return cls("dso", path=str(path), nonradial=tuple(nonradial), source=f"DSO {Path(path).name}")

    @classmethod
    def lensfun(cls, entry: "LensfunVignetting", *, centres: Any = (0.5, 0.5),
                nonradial: Sequence[Sequence[float]] = ()) -> "VignettingSpec":
        """lensfun's ``pa`` model (``r = 1`` at the half-diagonal, as here), the same for all channels."""
        return cls("polynomial", ((entry.k1, entry.k2, entry.k3),) * 3, centres, tuple(nonradial), None,
                   entry.describe())


def vignetting_preset(name: str) -> VignettingSpec:
    """Named vignetting fields.

    - ``xtion``: strong, like the Asus Xtion of the paper: corners at ~0.5 (R 0.52, G 0.50, B 0.45),
      the blue centre shifted by (+8, +5) pixels at 640 x 480, red/green centres off by ~2 pixels, and
      a non-radial field of ~3 % amplitude.
    - ``asymmetric``: the ``xtion`` fall-off and centres times a strong non-radial field (a horizontally
      elongated fall-off and a diagonal saddle, as mechanical vignetting or a tilted sensor give): the best
      free-centre polynomial misses it by 2.5 % RMS and 7 % at worst (``xtion``: 0.4 % and 1.3 %). The
      demo's camera: the LUT's advantage over the polynomial shows (the paper's point).
    - ``mild``: corners at ~0.8, centred, a 1 % non-radial field.
    - ``none``: ``V = 1``.
    Centres are stored as fractions of the image size, so the spec is resolution independent (the
    shifts are ~1.25 % of the width and ~1 % of the height at any resolution).
    """
    if name in ("xtion", "asymmetric"):
        sx, sy = 1.0 / 640.0, 1.0 / 480.0
        nonradial = ((0.018, 1.0, 0.0, 0.35, 0.0), (0.012, 0.0, 1.0, 0.0, 0.2), (0.010, 1.0, 1.0, 0.1, 0.6),
                     (0.006, 2.0, 1.0, 0.4, 0.3))
        if name == "asymmetric":
            nonradial += ((-0.05, 2.0, 0.0, 0.0, 0.0), (0.04, 1.0, 1.0, 0.0, 0.0))
        return VignettingSpec.polynomial(
            (0.52, 0.50, 0.45),
            centres=((0.5 + 2 * sx, 0.5 - 1 * sy), (0.5 + 1 * sx, 0.5 + 1 * sy), (0.5 + 8 * sx, 0.5 + 5 * sy)),
            nonradial=nonradial, source=f"preset {name}")
    if name == "mild":
        return VignettingSpec.polynomial(0.8, nonradial=((0.006, 1.0, 0.0, 0.3, 0.0), (0.004, 0.0, 1.0, 0.0, 0.25)),
                                         source="preset mild")
    if name == "none":
        return VignettingSpec("none", source="preset none")
    raise ValueError(f"unknown vignetting preset {name!r}; valid names: {', '.join(VIGNETTING_PRESETS)}")


VIGNETTING_PRESETS = ("xtion", "asymmetric", "mild", "none")


# ---------------------------------------------------------------------------------------- lensfun
@dataclass(frozen=True)
class LensfunVignetting:
    """One ``<vignetting model="pa">`` entry of the lensfun database."""

    maker: str
    model: str
    focal: float
    aperture: float
    distance: float
    k1: float
    k2: float
    k3: float
    file: str

    def describe(self) -> str:
        name = self.model if self.model.lower().startswith(self.maker.lower()) else f"{self.maker} {self.model}"
        return f"lensfun {name} @ {self.focal:g} mm f/{self.aperture:g}"

    def corner(self) -> float:
        """``V`` at r = 1 (the corner of a centred image)."""
        return 1.0 + self.k1 + self.k2 + self.k3


def default_lensfun_db() -> Path | None:
    """Where the lensfun XML database is: ``$RADIOMAP_LENSFUN_DB``, ``../shared/data/lensfun/db``
    beside a source checkout, or the system's lensfun data folder; None if none exists."""
    candidates = []
    if os.environ.get("RADIOMAP_LENSFUN_DB"):
        candidates.append(Path(os.environ["RADIOMAP_LENSFUN_DB"]))
    repo = Path(__file__).resolve().parents[1]
    candidates += [repo.parent / "shared" / "data" / "lensfun" / "db",
                   Path("/usr/share/lensfun/version_1"), Path("/usr/share/lensfun")]
    for c in candidates:
        if c.is_dir() and any(c.glob("*.xml")):
            return c
    return None


@lru_cache(maxsize=4)
def _lensfun_entries(db: str) -> tuple[LensfunVignetting, ...]:
    path = Path(db)
    files = sorted(path.glob("*.xml")) if path.is_dir() else [path]
    out: list[LensfunVignetting] = []
    for xml in files:
        try:
            root = ET.parse(xml).getroot()
        except (ET.ParseError, OSError) as exc:
            raise CalibrationFileError(f"{xml}: not a readable lensfun XML file ({exc}); check the database") from None
        for lens in root.iter("lens"):
            maker = next((e.text or "" for e in lens.findall("maker") if "lang" not in e.attrib), "")
            model = next((e.text or "" for e in lens.findall("model") if "lang" not in e.attrib), "")
            for calib in lens.findall("calibration"):
                for v in calib.findall("vignetting"):
                    if v.get("model") != "pa":
                        continue
                    try:
                        out.append(LensfunVignetting(
                            maker.strip(), model.strip(), float(v.get("focal", "nan")),
                            float(v.get("aperture", "nan")), float(v.get("distance", "inf")),
                            float(v.get("k1", 0)), float(v.get("k2", 0)), float(v.get("k3", 0)), xml.name))
                    except ValueError as exc:
                        raise CalibrationFileError(f"{xml}: a vignetting entry of {model!r} has a bad number "
                                                   f"({exc}); check the database") from None
    return tuple(out)


def lensfun_vignetting_entries(db: str | os.PathLike | None = None) -> list[LensfunVignetting]:
    """All ``pa`` vignetting entries of a lensfun database folder (or one XML file)."""
    if db is None:
        db = default_lensfun_db()
        if db is None:
            raise CalibrationFileError("no lensfun database found; pass db=<folder of lensfun *.xml> or set "
                                       "RADIOMAP_LENSFUN_DB")
    db = Path(db)
    if not db.exists():
        raise CalibrationFileError(f"{db}: no such lensfun database; pass the folder holding the *.xml files")
    return list(_lensfun_entries(str(db.resolve())))


def find_lensfun_vignetting(lens: str, *, focal: float | None = None, aperture: float | None = None,
                            distance: float | None = None,
                            db: str | os.PathLike | None = None) -> LensfunVignetting:
    """The entry of the lens whose name contains ``lens`` (case-insensitive, maker + model), nearest to
    ``focal`` (mm), then ``aperture`` (f-number), then ``distance``; without them the widest aperture
    at the shortest focal length (the strongest vignetting of that lens). Several lenses matching is
    fine when they are the same model; otherwise the first in sorted order is used and logged."""
    if not lens or not isinstance(lens, str):
        raise ValueError(f"lens must be a non-empty part of a lens name, got {lens!r}")
    needle = lens.lower()
    entries = [e for e in lensfun_vignetting_entries(db) if needle in f"{e.maker} {e.model}".lower()]
    if not entries:
        raise ValueError(f"no lensfun lens with vignetting data matches {lens!r}; try a shorter part of the "
                         "name, e.g. 'EF-S 18-55'")
    models = sorted({(e.maker, e.model) for e in entries})
    if len(models) > 1:
        log.info("%d lenses match %r; using %s %s", len(models), lens, *models[0])
    entries = [e for e in entries if (e.maker, e.model) == models[0]]

    def key(e: LensfunVignetting) -> tuple[float, float, float]:
        kf = abs(e.focal - focal) if focal is not None else e.focal
        ka = abs(e.aperture - aperture) if aperture is not None else e.aperture
        kd = abs(math.log(max(e.distance, 1e-3)) - math.log(distance)) if distance is not None else 0.0
        return (kf, ka, kd)

    return min(entries, key=key)


# ==================================================================================================
# exposure control
# ==================================================================================================
@dataclass(frozen=True)
class AutoExposure:
    """A camera-like auto-exposure loop.

    It meters the mean brightness (Rec. 601 luma of the 8-bit image) of the last frame, converts it
    to irradiance with the camera's (green) inverse response, and moves ``log2(k)`` a fraction
    ``smoothing`` of the way towards the exposure that would put the brightness at ``target``
    (fraction of 255), at most ``max_step_ev`` stops per frame, not at all inside ``deadband_ev``,
    clamped to ``[min_time, max_time]`` seconds. The new exposure takes effect ``latency`` frames
    after the metered one (1 = the next frame).
    """

    target: float = 0.45
    smoothing: float = 0.3
    max_step_ev: float = 0.5
    deadband_ev: float = 0.08
    min_time: float = 5e-5
    max_time: float = 1.0 / 30.0
    latency: int = 1

    def __post_init__(self) -> None:
        _check_range("target", self.target, 0.02, 0.98)
        _check_range("smoothing", self.smoothing, 1e-3, 1.0)
        _check_range("max_step_ev", self.max_step_ev, 1e-3, 10.0)
        _check_range("deadband_ev", self.deadband_ev, 0.0, 2.0)
        if not (0 < self.min_time < self.max_time and np.isfinite(self.max_time)):
            raise ValueError(f"need 0 < min_time < max_time, got min_time={self.min_time}, max_time={self.max_time}")
        if not (isinstance(self.latency, int) and 1 <= self.latency <= 10):
            raise ValueError(f"latency must be a whole number of frames in 1..10, got {self.latency!r}")


@dataclass(frozen=True)
class AutoWhiteBalance:
    """Grey-world auto white balance with a lag: per frame, ``log g_c`` moves a fraction
    ``smoothing`` towards the gains that equalise the channel means of the (pre-gain) irradiance of
    unsaturated pixels, at most ``max_step`` (natural log) per frame, green fixed at 1, gains clamped
    to ``[min_gain, max_gain]``."""

    smoothing: float = 0.1
    max_step: float = 0.05
    min_gain: float = 0.4
    max_gain: float = 3.0

    def __post_init__(self) -> None:
        _check_range("smoothing", self.smoothing, 1e-3, 1.0)
        _check_range("max_step", self.max_step, 1e-4, 2.0)
        if not (0 < self.min_gain <= 1.0 <= self.max_gain and np.isfinite(self.max_gain)):
            raise ValueError(f"need 0 < min_gain <= 1 <= max_gain, got {self.min_gain}, {self.max_gain}")


def _check_range(name: str, value: float, low: float, high: float) -> None:
    if not (isinstance(value, (int, float)) and np.isfinite(value) and low <= value <= high):
        raise ValueError(f"{name} must be a number within [{low}, {high}], got {value!r}")


class ExposureController:
    """Exposure time and white-balance gains of a camera, frame by frame.

    Use: read :attr:`exposure_time` and :attr:`gains`, capture a frame with them, then call
    :meth:`observe` with the 8-bit image; the controller updates the settings of a later frame as a
    camera's AE/AWB loop would. Without ``auto_exposure``/``auto_white_balance`` the respective
    settings stay fixed.
    """

    def __init__(self, response: CameraResponse, *, exposure_time: float, gains: Sequence[float] = (1.0, 1.0, 1.0),
                 auto_exposure: AutoExposure | None = None,
                 auto_white_balance: AutoWhiteBalance | None = None) -> None:
        if not (np.isfinite(exposure_time) and exposure_time > 0):
            raise ValueError(f"exposure_time must be a positive number of seconds, got {exposure_time!r}")
        self.response = response
        self.auto_exposure = auto_exposure
        self.auto_white_balance = auto_white_balance
        k = float(exposure_time)
        if auto_exposure is not None:
            k = float(np.clip(k, auto_exposure.min_time, auto_exposure.max_time))
        self._k = k
        self._g = _per_channel(gains, "gains", 3).copy()
        self._sched_k = self._k
        self._sched_g = self._g.copy()
        self._frame = 0
        self._pending: deque[tuple[int, float, np.ndarray]] = deque()
        tables = response.channel_tables(3).astype(np.float64)
        self._tables = tables
        self._target_e = None if auto_exposure is None else float(
            np.interp(auto_exposure.target * 255.0, np.arange(LEVELS), tables[:, 1]))

    @property
    def exposure_time(self) -> float:
        return self._k

    @property
    def gains(self) -> np.ndarray:
        return self._g.copy()

    def settings(self) -> tuple[float, np.ndarray]:
        """``(exposure_time, gains (3,))`` for the next frame."""
        return self._k, self._g.copy()

    def observe(self, image: np.ndarray) -> None:
        """Meter an 8-bit RGB frame captured with the current settings and advance one frame."""
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"image must be uint8 (H, W, 3) RGB, got {img.dtype} {img.shape}")
        step = max(1, int(min(img.shape[:2]) // 120))
        sample = img[::step, ::step].reshape(-1, 3)
        used_k, used_g = self._k, self._g
        new_k, new_g = self._sched_k, self._sched_g.copy()
        if self.auto_exposure is not None:
            new_k = self._next_exposure(sample, used_k)
        if self.auto_white_balance is not None:
            new_g = self._next_gains(sample, used_g)
        self._sched_k, self._sched_g = new_k, new_g
        latency = self.auto_exposure.latency if self.auto_exposure is not None else 1
        self._pending.append((self._frame + latency, new_k, new_g))
        self._frame += 1
        while self._pending and self._pending[0][0] <= self._frame:
            _, self._k, self._g = self._pending.popleft()

    def _next_exposure(self, sample: np.ndarray, used_k: float) -> float:
        ae = self.auto_exposure
        brightness = float(sample.astype(np.float64).mean(axis=0) @ _LUMA)
        measured = max(float(np.interp(brightness, np.arange(LEVELS), self._tables[:, 1])), 1e-6)
        error_ev = math.log2(self._target_e / measured)
        base = math.log2(self._sched_k)
        if abs(error_ev) <= ae.deadband_ev:
            return self._sched_k
        wanted = math.log2(used_k) + error_ev
        move = float(np.clip(ae.smoothing * (wanted - base), -ae.max_step_ev, ae.max_step_ev))
        return float(np.clip(2.0 ** (base + move), ae.min_time, ae.max_time))

    def _next_gains(self, sample: np.ndarray, used_g: np.ndarray) -> np.ndarray:
        awb = self.auto_white_balance
        ok = np.all((sample > 8) & (sample < 247), axis=1)
        if np.count_nonzero(ok) < 50:
            return self._sched_g.copy()
        valid = sample[ok]
        irr = np.stack([self._tables[valid[:, c], c] for c in range(3)], axis=1)
        raw = irr.mean(axis=0) / used_g
        if np.any(raw <= 0):
            return self._sched_g.copy()
        wanted = np.log(raw[1] / raw)
        base = np.log(self._sched_g)
        move = np.clip(awb.smoothing * (wanted - base), -awb.max_step, awb.max_step)
        g = np.exp(base + move)
        g[1] = 1.0
        return np.clip(g, awb.min_gain, awb.max_gain)


# ==================================================================================================
# the camera
# ==================================================================================================
def _check_size(width: Any, height: Any) -> tuple[int, int]:
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))) \
            or width < 2 or height < 2:
        raise ValueError(f"width and height must be whole numbers >= 2, got {width!r} x {height!r}")
    return int(width), int(height)


def default_intrinsics(width: int, height: int, *, focal: float | None = None) -> np.ndarray:
    """Pinhole ``K`` of a Kinect/Xtion-like camera: ``fx = fy = 525 * W / 640`` (a 62 degree horizontal
    field of view) unless ``focal`` is given, principal point at the image centre ``((W-1)/2, (H-1)/2)``."""
    width, height = _check_size(width, height)
    f = 525.0 * width / 640.0 if focal is None else float(focal)
    if not (np.isfinite(f) and f > 0):
        raise ValueError(f"focal must be a positive number of pixels, got {focal!r}")
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class CameraSpec:
    """All parameters of a simulated camera; JSON round-trip with :meth:`to_dict`/:meth:`from_dict`,
    :meth:`save`/:meth:`load`.

    crf:            ``{"family": ..., **params}`` for :func:`make_crf`.
    vignetting:     :class:`VignettingSpec`.
    exposure_time:  initial (or fixed) exposure in seconds.
    gains:          initial (or fixed) white-balance gains (R, G, B).
    auto_exposure / auto_white_balance: controllers, or None for fixed settings.
    full_well:      electrons at saturation (shot noise ~ sqrt(E / full_well)); None = no shot noise.
    read_noise:     standard deviation of the additive read noise, in units of the saturation level.
    jpeg_quality:   1..100 to pass every frame through JPEG, None for lossless frames.
    """

    width: int = 640
    height: int = 480
    crf: dict = field(default_factory=lambda: dict(CRF_PRESETS["s_curve"]))
    vignetting: VignettingSpec = field(default_factory=lambda: vignetting_preset("xtion"))
    exposure_time: float = 0.01
    gains: tuple = (1.0, 1.0, 1.0)
    auto_exposure: AutoExposure | None = field(default_factory=AutoExposure)
    auto_white_balance: AutoWhiteBalance | None = None
    full_well: float | None = 6000.0
    read_noise: float = 0.0015
    jpeg_quality: int | None = None
    name: str = "custom"

    def __post_init__(self) -> None:
        _check_size(self.width, self.height)
        if not isinstance(self.crf, Mapping) or "family" not in self.crf:
            raise ValueError(f"crf must be a mapping with a 'family' key, got {self.crf!r}")
        if self.crf["family"] not in CRF_FAMILIES:
            raise ValueError(f"unknown crf family {self.crf['family']!r}; valid names: {', '.join(CRF_FAMILIES)}")
        object.__setattr__(self, "crf", _plain(dict(self.crf)))
        if isinstance(self.vignetting, Mapping):
            object.__setattr__(self, "vignetting", VignettingSpec.from_dict(self.vignetting))
        if not isinstance(self.vignetting, VignettingSpec):
            raise TypeError(f"vignetting must be a VignettingSpec, got {type(self.vignetting).__name__}")
        if not (np.isfinite(self.exposure_time) and self.exposure_time > 0):
            raise ValueError(f"exposure_time must be a positive number of seconds, got {self.exposure_time!r}")
        object.__setattr__(self, "gains", tuple(_per_channel(self.gains, "gains", 3).tolist()))
        for name, cls in (("auto_exposure", AutoExposure), ("auto_white_balance", AutoWhiteBalance)):
            value = getattr(self, name)
            if isinstance(value, Mapping):
                object.__setattr__(self, name, cls(**value))
            elif value is not None and not isinstance(value, cls):
                raise TypeError(f"{name} must be {cls.__name__} or None, got {type(value).__name__}")
        if self.full_well is not None and not (np.isfinite(self.full_well) and self.full_well > 0):
            raise ValueError(f"full_well must be a positive number of electrons or None, got {self.full_well!r}")
        if not (np.isfinite(self.read_noise) and self.read_noise >= 0):
            raise ValueError(f"read_noise must be >= 0, got {self.read_noise!r}")
        if self.jpeg_quality is not None and not (isinstance(self.jpeg_quality, int) and 1 <= self.jpeg_quality <= 100):
            raise ValueError(f"jpeg_quality must be a whole number in 1..100 or None, got {self.jpeg_quality!r}")

    # ---------------------------------------------------------------- construction
    @classmethod
    def preset(cls, name: str = "xtion", *, width: int = 640, height: int = 480, **overrides: Any) -> "CameraSpec":
        """Named cameras: ``xtion`` (S-shaped CRF differing per channel, strong vignetting with a
        shifted blue centre and a non-radial field, auto exposure and white balance, shot and read
        noise), ``mild`` (gamma 2.2, mild vignetting, auto exposure, noise) and ``ideal`` (linear,
        no vignetting, no noise, fixed exposure); ``asymmetric`` is ``xtion`` with a strong non-radial
        vignetting field (the demo's camera). ``overrides`` replace any field."""
        if name in ("xtion", "asymmetric"):
            spec = cls(width, height, dict(CRF_PRESETS["s_curve"]), vignetting_preset(name), 0.01,
                       (1.0, 1.0, 1.0), AutoExposure(), AutoWhiteBalance(), 6000.0, 0.0015, None, name)
        elif name == "mild":
            spec = cls(width, height, dict(CRF_PRESETS["gamma"]), vignetting_preset("mild"), 0.01,
                       (1.0, 1.0, 1.0), AutoExposure(), None, 10000.0, 0.001, None, "mild")
        elif name == "ideal":
            spec = cls(width, height, dict(CRF_PRESETS["linear"]), vignetting_preset("none"), 0.01,
                       (1.0, 1.0, 1.0), None, None, None, 0.0, None, "ideal")
        else:
            raise ValueError(f"unknown camera preset {name!r}; valid names: {', '.join(CAMERA_PRESETS)}")
        return replace(spec, **overrides) if overrides else spec

    def replace(self, **changes: Any) -> "CameraSpec":
        return replace(self, **changes)

    def response(self) -> CameraResponse:
        params = {k: v for k, v in self.crf.items() if k != "family"}
        return make_crf(self.crf["family"], **params)

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": CAMERA_FORMAT, "version": CAMERA_FORMAT_VERSION, "name": self.name,
            "width": self.width, "height": self.height, "crf": _plain(self.crf),
            "vignetting": self.vignetting.to_dict(), "exposure_time": self.exposure_time,
            "gains": list(self.gains),
            "auto_exposure": None if self.auto_exposure is None else _dc_dict(self.auto_exposure),
            "auto_white_balance": None if self.auto_white_balance is None else _dc_dict(self.auto_white_balance),
            "full_well": self.full_well, "read_noise": self.read_noise, "jpeg_quality": self.jpeg_quality,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "CameraSpec":
        data = dict(data)
        fmt, version = data.pop("format", CAMERA_FORMAT), data.pop("version", CAMERA_FORMAT_VERSION)
        if fmt != CAMERA_FORMAT:
            raise ValueError(f"not a radiomap camera description (format {fmt!r})")
        if not isinstance(version, int) or version > CAMERA_FORMAT_VERSION:
            raise ValueError(f"camera description version {version!r} is newer than this radiomap reads "
                             f"({CAMERA_FORMAT_VERSION}); upgrade radiomap")
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown camera fields {sorted(unknown)}; valid: {sorted(known)}")
        if isinstance(data.get("vignetting"), Mapping):
            data["vignetting"] = VignettingSpec.from_dict(data["vignetting"])
        return cls(**data)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, text: str) -> "CameraSpec":
        return cls.from_dict(json.loads(text))

    def save(self, path: str | os.PathLike) -> Path:
        """Write the camera description as JSON, atomically."""
        return atomic_write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "CameraSpec":
        path = Path(path)
        if not path.is_file():
            raise CalibrationFileError(f"{path}: no such camera description; check the path")
        try:
            return cls.from_dict(json.loads(path.read_text(encoding="utf-8")))
        except (json.JSONDecodeError, ValueError, TypeError) as exc:
            raise CalibrationFileError(f"{path}: not a valid radiomap camera description ({exc}); "
                                       "re-create it with radiomap simulate") from None


CAMERA_PRESETS = ("xtion", "asymmetric", "mild", "ideal")


def _dc_dict(obj: Any) -> dict[str, Any]:
    return {f.name: getattr(obj, f.name) for f in fields(obj)}


def _plain(obj: Any) -> Any:
    """Nested numpy values to plain JSON types."""
    if isinstance(obj, Mapping):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


@dataclass(frozen=True, eq=False)
class Capture:
    """One simulated frame.

    image:       uint8 ``(H, W, 3)`` RGB, what the camera delivers (after JPEG if enabled).
    intensity:   float32 ``(H, W, 3)`` ``f(signal)`` before 8-bit rounding (and before JPEG), in 0..255.
    signal:      float32 noisy irradiance ``E'`` (before the response).
    irradiance:  float32 noise-free ``E = k g V L``.
    exposure_time, gains: the settings used.
    """

    image: np.ndarray
    intensity: np.ndarray
    signal: np.ndarray
    irradiance: np.ndarray
    exposure_time: float
    gains: np.ndarray


class SimulatedCamera:
    """A camera built from a :class:`CameraSpec`: ``response`` (:class:`CameraResponse`) and
    ``vignetting`` (float32 ``(H, W, 3)``, read-only) are the ground truth."""

    def __init__(self, spec: CameraSpec | None = None) -> None:
        self.spec = spec if spec is not None else CameraSpec.preset("xtion")
        if not isinstance(self.spec, CameraSpec):
            raise TypeError(f"spec must be a CameraSpec, got {type(self.spec).__name__}")
        self.response = self.spec.response()
        if self.response.channels != 3:
            self.response = CameraResponse(np.repeat(self.response.inverse_table, 3, axis=1), self.response.meta)
        vig = self.spec.vignetting.render(self.spec.width, self.spec.height)
        vig.setflags(write=False)
        self.vignetting = vig

    @property
    def width(self) -> int:
        return self.spec.width

    @property
    def height(self) -> int:
        return self.spec.height

    def controller(self, *, auto_exposure: bool | AutoExposure | None = None,
                   auto_white_balance: bool | AutoWhiteBalance | None = None,
                   exposure_time: float | None = None, gains: Sequence[float] | None = None) -> ExposureController:
        """A fresh :class:`ExposureController` with the spec's settings; ``True``/``False`` switch a loop
        on (with the spec's or default parameters) or off, an instance replaces the parameters."""
        ae = _resolve_loop(auto_exposure, self.spec.auto_exposure, AutoExposure)
        awb = _resolve_loop(auto_white_balance, self.spec.auto_white_balance, AutoWhiteBalance)
        return ExposureController(self.response, exposure_time=self.spec.exposure_time if exposure_time is None
                                  else exposure_time, gains=self.spec.gains if gains is None else gains,
                                  auto_exposure=ae, auto_white_balance=awb)

    def _check_radiance(self, radiance: np.ndarray) -> np.ndarray:
        arr = np.asarray(radiance)
        if arr.shape != (self.height, self.width, 3):
            raise ValueError(f"radiance must have shape ({self.height}, {self.width}, 3) for this camera, "
                             f"got {arr.shape}")
        if not np.issubdtype(arr.dtype, np.floating):
            raise TypeError(f"radiance must be a float array, got {arr.dtype}")
        arr = arr.astype(np.float32, copy=False)
        if not np.all(np.isfinite(arr)) or float(arr.min(initial=0.0)) < 0:
            raise ValueError("radiance must be finite and >= 0")
        return arr

    def irradiance(self, radiance: np.ndarray, *, exposure_time: float, gains: Sequence[float] = (1, 1, 1)) -> np.ndarray:
        """Noise-free sensor irradiance ``E = k * g_c * V_c * L``, float32 ``(H, W, 3)``."""
        if not (np.isfinite(exposure_time) and exposure_time > 0):
            raise ValueError(f"exposure_time must be a positive number of seconds, got {exposure_time!r}")
        g = _per_channel(gains, "gains", 3)
        L = self._check_radiance(radiance)
        out = self.vignetting * (float(exposure_time) * g).astype(np.float32)
        out *= L
        return out

    def capture(self, radiance: np.ndarray, *, exposure_time: float | None = None,
                gains: Sequence[float] | None = None, rng: np.random.Generator | None = None,
                noise: bool = True, jpeg: bool = True) -> Capture:
        """Image of a radiance field ``(H, W, 3)`` with the given settings (the spec's by default).

        ``noise=True`` needs ``rng`` (a ``numpy.random.Generator``) when the spec has any noise;
        ``noise=False`` and ``jpeg=False`` give the exact, deterministic image formation.
        """
        k = self.spec.exposure_time if exposure_time is None else exposure_time
        g = self.spec.gains if gains is None else gains
        E = self.irradiance(radiance, exposure_time=k, gains=g)
        signal = E
        noisy = noise and (self.spec.full_well is not None or self.spec.read_noise > 0)
        if noisy:
            if not isinstance(rng, np.random.Generator):
                raise ValueError("noise=True needs rng=np.random.default_rng(seed) (or pass noise=False)")
            # Gaussian approximation of Poisson shot noise (variance E / full_well) plus read noise
            if self.spec.full_well is not None:
                std = E * np.float32(1.0 / self.spec.full_well)
                std += np.float32(self.spec.read_noise) ** 2
                np.sqrt(std, out=std)
            else:
                std = np.float32(self.spec.read_noise)
            signal = rng.standard_normal(E.shape, dtype=np.float32)
            signal *= std
            signal += E
            np.maximum(signal, 0.0, out=signal)
        intensity = self.response.forward(signal)
        image = np.clip(np.rint(intensity), 0, 255).astype(np.uint8)
        if jpeg and self.spec.jpeg_quality is not None:
            image = jpeg_roundtrip(image, self.spec.jpeg_quality)
        return Capture(image, intensity, signal.astype(np.float32, copy=False), E, float(k),
                       _per_channel(g, "gains", 3))


def _resolve_loop(value: Any, from_spec: Any, cls: type) -> Any:
    if value is None:
        return from_spec
    if value is True:
        return from_spec if from_spec is not None else cls()
    if value is False:
        return None
    if isinstance(value, cls):
        return value
    raise TypeError(f"expected True, False, None or a {cls.__name__}, got {value!r}")


def jpeg_roundtrip(image: np.ndarray, quality: int) -> np.ndarray:
    """Encode an RGB uint8 image as JPEG at ``quality`` (1..100) and decode it again (OpenCV)."""
    import cv2

    if not (isinstance(quality, (int, np.integer)) and 1 <= quality <= 100):
        raise ValueError(f"quality must be a whole number in 1..100, got {quality!r}")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 RGB
        raise RuntimeError("OpenCV could not encode the frame as JPEG")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


__all__ = [
    "AutoExposure", "AutoWhiteBalance", "CAMERA_PRESETS", "CRF_FAMILIES", "CRF_PRESETS", "CameraSpec", "Capture",
    "ExposureController", "LensfunVignetting", "SimulatedCamera", "VIGNETTING_PRESETS", "VignettingSpec",
    "crf_from_pcalib", "crf_from_table", "crf_gamma", "crf_linear", "crf_s_curve", "crf_spec_from_file",
    "default_intrinsics", "default_lensfun_db", "find_lensfun_vignetting", "jpeg_roundtrip",
    "lensfun_vignetting_entries", "make_crf", "nonradial_field", "polynomial_for_corner", "polynomial_vignetting",
    "read_pcalib_table", "vignette_map_from_png", "vignetting_preset",
]
