"""Radiometric correction step of the pipeline: a frame's uint8 RGB -> map units, and map units -> display.

A :class:`ColourModel` decides what a map stores:

- :class:`RawIntensity`: the intensity levels themselves (0..255 as float32); display is the identity.
  This is the "no correction" baseline of the paper's Fig. 9.
- :class:`IrradianceColour`: relative irradiance ``f^-1(I) / V(x) / k`` (``k`` the frame's exposure, 1
  unless an ``exposure`` estimator is plugged in); display is ``f(E * k_ref)``: the response at a reference
  exposure, so maps fused with different corrections are compared in the same 8-bit units.

The pipeline calls ``to_map(frame, view, pose)`` with the map already rendered at the frame's pose (``view``,
a :class:`mapping.fusion.base.ModelView`, or None) and the pose the frame is fused at, so that a model can
estimate per-frame quantities against the map (exposure compensation divides by a per-frame ``k`` estimated
from it). It returns a :class:`FrameColour`: the colour, and which pixels may be fused (with the reason when
none may).
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, runtime_checkable

import numpy as np

from mapping.datasets.base import RGBDFrame
from radiometry.errors import ModelMismatchError
from radiometry.api import as_vignetting
from radiometry.response import CameraResponse

log = logging.getLogger(__name__)


@dataclass
class FrameColour:
    """What a colour model makes of one frame.

    colour: (H, W, 3) float32 map units.
    valid:  None (every pixel may be fused) or bool (H, W): the pixels whose colour measures irradiance (the
            pipeline fuses neither colour nor geometry elsewhere).
    reason: why no pixel may be fused, when ``valid`` leaves none (the frame is then skipped with it).
    """

    colour: np.ndarray
    valid: np.ndarray | None = None
    reason: str = ""


@runtime_checkable
class ColourModel(Protocol):
    """How a run turns frames into map colours and map colours into display levels."""

    name: str

    def to_map(self, frame: RGBDFrame, view: Any = None, pose: np.ndarray | None = None) -> FrameColour:
        """The frame's colour in map units (``view``: the map rendered at ``pose``, the pose the frame is fused
        at; either may be None)."""
        ...

    def to_display(self, colour: np.ndarray) -> np.ndarray:
        """Map units ``(..., 3)`` -> float32 display levels in [0, 255] (same shape)."""
        ...

    def display_l1(self, map_colour: np.ndarray, sample_colour: np.ndarray) -> np.ndarray:
        """``sum_c |to_display(a) - to_display(b)|`` per row of two (N, 3) map-unit arrays, float32 (N,)."""
        ...

    def display_for_export(self) -> Callable[[np.ndarray], np.ndarray]:
        """The conversion the exported mesh's colours go through (after the run; e.g. at the sequence's median
        exposure)."""
        ...

    def save_results(self, folder: str | os.PathLike) -> dict[str, Path]:
        """Write what the model learnt during the run (e.g. per-frame exposures) into ``folder``."""
        ...

    def describe(self) -> dict:
        """What metrics.json and config.json record about the model."""
        ...

    def predict_observed(self, map_colour: np.ndarray, rgb: np.ndarray,
                         valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The 8-bit image a camera records of a render ``map_colour`` (H, W, 3) map units, at the exposure of the
        frame ``rgb`` (uint8 (H, W, 3)) fitted over its ``valid`` pixels (bool (H, W)):
        ``(predicted float32 levels (H, W, 3), gain float64 (3,))`` (:mod:`mapping.holdout`)."""
        ...

    def unexposed(self, rgb: np.ndarray) -> tuple[np.ndarray, float, bool]:
        """A uint8 (H, W, 3) frame in map units BEFORE any exposure division, for a tracker that estimates the
        exposure itself (:mod:`mapping.tracking_photometric`): ``(colour float32 (H, W, 3), white: the map units
        of level 255, whether the map's colours are divided by a per-frame exposure)``."""
        ...

    def display_exposure(self) -> np.ndarray | None:
        """The exposure ``k`` (3,) at which :meth:`display_for_export` shows irradiance (``f(E k)``), or None when
        the map holds raw levels (display is the identity)."""
        ...

    def from_display(self, levels: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`display_for_export`: display levels ``(..., 3)`` -> map units, float32."""
        ...

    def frame_exposures(self) -> dict[int, np.ndarray] | None:
        """Each fused frame's exposure (3,) as the run estimated it, by frame index (fallback frames left out),
        or None when the model divides by no estimated per-frame exposure."""
        ...


class RawIntensity:
    """No correction: the map averages intensity levels (0..255 as float32); display is the identity."""

    name = "none"

    def to_map(self, frame: RGBDFrame, view: Any = None, pose: np.ndarray | None = None) -> FrameColour:
        return FrameColour(frame.rgb.astype(np.float32))

    def to_display(self, colour: np.ndarray) -> np.ndarray:
        return np.clip(np.asarray(colour, dtype=np.float32), 0.0, 255.0)

    def display_l1(self, map_colour: np.ndarray, sample_colour: np.ndarray) -> np.ndarray:
        return np.abs(self.to_display(map_colour) - self.to_display(sample_colour)).sum(axis=1)

    def display_for_export(self) -> Callable[[np.ndarray], np.ndarray]:
        return self.to_display

    def save_results(self, folder: str | os.PathLike) -> dict[str, Path]:
        return {}

    def unexposed(self, rgb: np.ndarray) -> tuple[np.ndarray, float, bool]:
        return np.asarray(rgb).astype(np.float32), 255.0, False

    def display_exposure(self) -> None:
        return None

    def from_display(self, levels: np.ndarray) -> np.ndarray:
        return np.asarray(levels, dtype=np.float32)

    def frame_exposures(self) -> None:
        return None

    def describe(self) -> dict:
        return {"name": self.name, "map_units": "intensity levels 0..255", "display": "identity"}

    def predict_observed(self, map_colour: np.ndarray, rgb: np.ndarray,
                         valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``clip(k_c * level)``: a per-channel gain in level space (the raw map's only exposure model), fitted as
        the median of observed / rendered levels."""
        from mapping.holdout import fit_gain

        gain = fit_gain(rgb, map_colour, valid)
        return np.clip(np.asarray(map_colour, dtype=np.float32) * gain.astype(np.float32), 0.0, 255.0), gain


# --------------------------------------------------------------------------------------------------
# a fast, exact response.forward for large arrays (np.interp costs ~70 ns per value)
# --------------------------------------------------------------------------------------------------
_BUCKETS = 4096


def _kernels():
    from mapping._native import colour_kernels

    return colour_kernels()


class FastForward:
    """``response.forward`` at a fixed exposure ``k_ref`` for (..., C) float32 arrays: exact piecewise-linear
    inversion of the table (a uniform bucket index finds the segment, a short scan finishes), ~20x faster
    than ``np.interp``. Values at or below ``f^-1(0)`` give 0, at or above ``f^-1(255)`` give 255."""

    def __init__(self, response: CameraResponse, *, reference_exposure: float = 1.0) -> None:
        if not (reference_exposure > 0 and np.isfinite(reference_exposure)):
            raise ValueError(f"reference_exposure must be a positive number, got {reference_exposure}")
        self.response = response
        self.reference_exposure = float(reference_exposure)
        # E * k_ref >= t  <=>  E >= t / k_ref: fold k_ref into the table
        tables = np.ascontiguousarray(response.channel_tables(3).astype(np.float64) / reference_exposure)
        self._tables = tables.astype(np.float32)
        t32 = self._tables.astype(np.float64)
        lo, hi = t32[0], t32[-1]
        width = (hi - lo) / _BUCKETS
        self._lo = lo.astype(np.float32)
        self._inv_width = (1.0 / width).astype(np.float32)
        starts = np.empty((_BUCKETS + 1, 3), dtype=np.int32)
        for c in range(3):
            edges = lo[c] + width[c] * np.arange(_BUCKETS + 1)
            # the last table index j with t_j <= edge, in [0, 254]
            starts[:, c] = np.clip(np.searchsorted(t32[:, c], edges, side="right") - 1, 0, 254)
        self._starts = starts
        # a segment of zero width in float32 is never the one a value falls in (the scan skips it)
        self._inv_slope = (1.0 / np.maximum(np.diff(t32, axis=0), 1e-30)).astype(np.float32)

    def __call__(self, irradiance: np.ndarray) -> np.ndarray:
        arr = np.asarray(irradiance, dtype=np.float32)
        if arr.shape[-1:] != (3,):
            raise ModelMismatchError(f"colours must have 3 channels in the last axis, got shape {arr.shape}")
        flat = np.ascontiguousarray(arr.reshape(-1, 3))
        out = np.empty_like(flat)
        if flat.size:
            _kernels().forward(flat, self._tables, self._inv_slope, self._starts, self._lo, self._inv_width, out)
        return out.reshape(arr.shape)

    def l1(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """``sum_c |forward(a) - forward(b)|`` per row of two (N, 3) arrays, float32 (N,), in one pass."""
        a = np.ascontiguousarray(a, dtype=np.float32)
        b = np.ascontiguousarray(b, dtype=np.float32)
        if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
            raise ValueError(f"a and b must be matching (N, 3) arrays, got {a.shape} and {b.shape}")
        out = np.empty(a.shape[0], np.float32)
        if a.size:
            _kernels().l1(a, b, self._tables, self._inv_slope, self._starts, self._lo, self._inv_width, out)
        return out


# --------------------------------------------------------------------------------------------------
# irradiance
# --------------------------------------------------------------------------------------------------
ExposureFn = Callable[[RGBDFrame, np.ndarray, Any, "np.ndarray | None"], "float | np.ndarray"]


def divide_exposure(irradiance: np.ndarray, k: Any) -> np.ndarray:
    """``irradiance / k`` in place (float32), ``k`` a positive scalar or three per-channel gains."""
    k = np.asarray(k, dtype=np.float32).reshape(-1)
    if k.size not in (1, 3) or not np.all(np.isfinite(k)) or np.any(k <= 0):
        raise ValueError(f"the exposure estimate must be a positive scalar or 3 gains, got {k}")
    irradiance /= k if k.size == 3 else k[0]
    return irradiance


class IrradianceColour:
    """Fuse relative irradiance ``f^-1(I) / V / k``; display through ``f(E * k_ref)``.

    response:           the camera response (:class:`CameraResponse`, 1 or 3 channels).
    vignetting:         None (no vignetting correction), a :class:`radiometry.vignetting.VignettingModel`
                        (polynomial or LUT) or an array V (H, W[, C]) taken as a LUT.
    exposure:           None (k = 1 for every frame) or ``exposure(frame, irradiance, view, pose) -> k`` (a
                        scalar or three per-channel gains; ``view`` the map rendered at ``pose``, the pose the
                        frame is fused at): a per-frame exposure estimate.
    reference_exposure: ``k_ref`` of the display conversion.

    ``f^-1(I) / V`` is :meth:`radiometry.correction.Corrector.irradiance` (a uint8 table look-up).
    """

    def __init__(self, response: CameraResponse, vignetting=None, *, exposure: ExposureFn | None = None,
                 reference_exposure: float = 1.0, name: str | None = None) -> None:
        from radiometry.correction import Corrector

        if not isinstance(response, CameraResponse):
            raise TypeError(f"response must be a CameraResponse, got {type(response).__name__}")
        self.response = response
        self.vignetting = as_vignetting(vignetting)
        self.exposure = exposure
        self.reference_exposure = float(reference_exposure)
        self._forward = FastForward(response, reference_exposure=reference_exposure)
        self.corrector = Corrector(response, self.vignetting)
        self.name = name or ("response+vignetting" if vignetting is not None else "response")

    def irradiance(self, rgb: np.ndarray) -> np.ndarray:
        """``f^-1(I) / V`` of a uint8 (H, W, 3) image, float32."""
        rgb = np.asarray(rgb)
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
        return self.corrector.irradiance(rgb)

    def to_map(self, frame: RGBDFrame, view: Any = None, pose: np.ndarray | None = None) -> FrameColour:
        E = self.irradiance(frame.rgb)
        if self.exposure is not None:
            E = divide_exposure(E, self.exposure(frame, E, view, pose))
        return FrameColour(E)

    def to_display(self, colour: np.ndarray) -> np.ndarray:
        return self._forward(colour)

    def unexposed(self, rgb: np.ndarray) -> tuple[np.ndarray, float, bool]:
        white = float(np.mean(self.response.channel_tables(3)[-1]))
        return self.irradiance(rgb), white, self.exposure is not None

    def display_exposure(self) -> np.ndarray:
        return np.full(3, self.reference_exposure, dtype=np.float64)

    def from_display(self, levels: np.ndarray) -> np.ndarray:
        return (self.response.inverse(np.asarray(levels, dtype=np.float32)) / np.float32(self.reference_exposure)
                ).astype(np.float32)

    def frame_exposures(self) -> None:
        return None

    def display_l1(self, map_colour: np.ndarray, sample_colour: np.ndarray) -> np.ndarray:
        """Display-unit L1 distances of (N, 3) map-unit pairs, fused (no temporaries)."""
        return self._forward.l1(map_colour, sample_colour)

    def display_for_export(self) -> Callable[[np.ndarray], np.ndarray]:
        return self.to_display

    def save_results(self, folder: str | os.PathLike) -> dict[str, Path]:
        return {}

    def predict_observed(self, map_colour: np.ndarray, rgb: np.ndarray,
                         valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``f(k_c V(x) E_map)``: the exposure ``k_c`` fitted as the median of ``(f^-1(I) / V) / E_map``, the
        render pushed back through the vignetting and the response."""
        from mapping.holdout import fit_gain

        E = np.asarray(map_colour, dtype=np.float32)
        gain = fit_gain(self.irradiance(rgb), E, valid)
        h, w = E.shape[:2]
        v = self.corrector.gain_map(h, w)  # 1 / V, (H, W, 1 or 3)
        scale = (gain / self.reference_exposure).astype(np.float32)
        return self._forward(E * scale / v), gain

    def describe(self) -> dict:
        vig = None if self.vignetting is None else repr(self.vignetting)
        return {"name": self.name, "map_units": "relative irradiance f^-1(I)/V/k",
                "display": f"response.forward(E * {self.reference_exposure:g})",
                "response": repr(self.response), "vignetting": vig,
                "exposure": None if self.exposure is None else getattr(self.exposure, "__name__",
                                                                       type(self.exposure).__name__)}


def make_colour_model(response: CameraResponse | None = None, vignetting=None, *,
                      reference_exposure: float = 1.0) -> RawIntensity | IrradianceColour:
    """No response: raw intensities. A response (and optionally a vignetting model): irradiance.

    A vignetting model without a response is rejected: dividing intensities by V is not a correction
    (V acts on irradiance); pass the response, or ``CameraResponse.gamma()`` as the documented assumption."""
    if response is None:
        if vignetting is not None:
            raise ValueError("vignetting correction needs the camera response (V acts on irradiance, not on "
                             "intensities); pass response=, e.g. CameraResponse.gamma() if it is unknown")
        return RawIntensity()
    return IrradianceColour(response, vignetting, reference_exposure=reference_exposure)
