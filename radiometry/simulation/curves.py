"""Camera response functions of the simulated camera: parametric families, tables, DSO ``pcalib.txt``.

:func:`crf_linear`, :func:`crf_gamma`, :func:`crf_s_curve` (parametric), :func:`crf_from_table` and
:func:`crf_from_pcalib` (tabulated) each give a :class:`~radiometry.response.CameraResponse` (the inverse
response ``f^-1``, ``f^-1(255) = 1``); :func:`make_crf` picks one by name from :data:`CRF_FAMILIES`, and
:data:`CRF_PRESETS` names the parameters of the simulator's cameras.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.formats.pcalib import read_pcalib
from radiometry.registry import Registry
from radiometry.response import LEVELS, CameraResponse
from radiometry.simulation._checks import per_channel


def crf_linear(*, channels: int = 3) -> CameraResponse:
    """A linear camera: ``f^-1(I) = I / 255``."""
    resp = CameraResponse.linear(channels)
    return CameraResponse(resp.inverse_table, {"method": "simulated", "family": "linear"})


def crf_gamma(gamma: float | Sequence[float] = 2.2, *, channels: int = 3) -> CameraResponse:
    """Gamma-like response ``f^-1(I) = (I / 255) ** gamma``, one ``gamma`` or one per channel."""
    g = per_channel(gamma, "gamma", channels)
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
    a = per_channel(contrast, "contrast", channels, low=0.1)
    m = per_channel(midpoint, "midpoint", channels)
    if np.any(m >= 1):
        raise ValueError(f"midpoint must be in (0, 1), got {midpoint!r}")
    g = per_channel(gamma, "gamma", channels)
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


def crf_from_pcalib(path: str | os.PathLike, *, channels: int = 3) -> CameraResponse:
    """The (monochrome) response of a DSO/TUM ``pcalib.txt`` (read by
    :func:`radiometry.formats.pcalib.read_pcalib`, normalised as DSO does), repeated for ``channels`` channels."""
    table = np.repeat(read_pcalib(path).inverse_table[:, :1].astype(np.float64), channels, axis=1)
    return CameraResponse(table, {"method": "simulated", "family": "pcalib", "source": str(path)})


def _check_params(family: str, params: Mapping[str, Any], allowed: set[str], required: set[str] = frozenset()) -> None:
    if not allowed and params:
        raise ValueError(f"crf family {family!r} takes no parameters, got {sorted(params)}")
    unknown = set(params) - allowed
    if unknown:
        raise ValueError(f"crf family {family!r} does not take {sorted(unknown)}; valid: {sorted(allowed)}")
    missing = set(required) - set(params)
    if missing:
        raise ValueError(f"crf family {family!r} needs {sorted(missing)}")


def _linear_from_params(channels: int, params: Mapping[str, Any]) -> CameraResponse:
    _check_params("linear", params, set())
    return crf_linear(channels=channels)


def _gamma_from_params(channels: int, params: Mapping[str, Any]) -> CameraResponse:
    _check_params("gamma", params, {"gamma"})
    return crf_gamma(params.get("gamma", 2.2), channels=channels)


def _s_curve_from_params(channels: int, params: Mapping[str, Any]) -> CameraResponse:
    _check_params("s_curve", params, {"contrast", "midpoint", "gamma"})
    return crf_s_curve(channels=channels, **params)


def _table_from_params(channels: int, params: Mapping[str, Any]) -> CameraResponse:
    _check_params("table", params, {"table", "source"}, required={"table"})
    return crf_from_table(params["table"], source=str(params.get("source", "table")))


def _pcalib_from_params(channels: int, params: Mapping[str, Any]) -> CameraResponse:
    _check_params("pcalib", params, {"path", "table"})
    if "table" in params:
        resp = CameraResponse.from_table(np.asarray(params["table"], dtype=np.float64))
        return CameraResponse(resp.inverse_table, {"method": "simulated", "family": "pcalib",
                                                   "source": str(params.get("path", ""))})
    if "path" not in params:
        raise ValueError("crf family 'pcalib' needs path=<pcalib.txt> (or table=...)")
    return crf_from_pcalib(params["path"], channels=channels)


#: family name -> builder ``(channels, params) -> CameraResponse`` that checks the family's parameters
CRF_FAMILIES = Registry("crf family", {
    "linear": _linear_from_params,
    "gamma": _gamma_from_params,
    "s_curve": _s_curve_from_params,
    "table": _table_from_params,
    "pcalib": _pcalib_from_params,
})


def make_crf(family: str, *, channels: int = 3, **params: Any) -> CameraResponse:
    """A response of one of :data:`CRF_FAMILIES`: ``linear``, ``gamma`` (``gamma``), ``s_curve`` (``contrast``,
    ``midpoint``, ``gamma``), ``table`` (``table``, 256 x C) or ``pcalib`` (``path``; ``table`` if given
    is used instead of the file, so that a saved camera does not depend on the file)."""
    return CRF_FAMILIES[family](channels, params)


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


__all__ = ["CRF_FAMILIES", "CRF_PRESETS", "crf_from_pcalib", "crf_from_table", "crf_gamma", "crf_linear",
           "crf_s_curve", "crf_spec_from_file", "make_crf"]
