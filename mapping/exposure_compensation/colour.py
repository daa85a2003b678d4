"""The colour model that fuses exposure-compensated irradiance and masks clipped pixels (see
:mod:`mapping.exposure_compensation`)."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.response import CameraResponse
from mapping.exposure_compensation.estimator import ExposureEstimator
from mapping.exposure_compensation.masks import clipped_pixels
from mapping.exposure_compensation.records import resolve_reference

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------------
# the colour model
# --------------------------------------------------------------------------------------------------
class CompensatedColour:
    """A :class:`mapping.colour.ColourModel` that fuses exposure-compensated irradiance and masks clipped
    pixels (wraps an :class:`~mapping.colour.IrradianceColour`; see the module doc).

    base:             the irradiance colour model (its response, vignetting and ``reference_exposure``, the
                      fixed display reference of the histogram); left as it is.
    estimator:        an :class:`ExposureEstimator`, or None to build one from ``base`` with ``**options``.
    compensate:       False: no exposure estimation, only the clipped-pixel mask (an ablation).
    mask_clipped:     mark clipped pixels invalid (:attr:`FrameColour.valid`).
    clip_high, dark_level: :func:`clipped_pixels` thresholds.
    export_reference: ``"median"``, ``"first"``, or a number / three numbers (relative to the first frame)
                      for :meth:`display_for_export`.

    :meth:`to_map` returns a :class:`mapping.colour.FrameColour` whose ``valid`` is None (every pixel may be
    fused) or bool (H, W) (False: clipped, or every pixel when the frame's exposure estimate fell back, with the
    ``reason``); the frame's :class:`ExposureRecord` is ``estimator.last``. After the run the pipeline exports
    the mesh through :meth:`display_for_export` and calls :meth:`save_results` (``exposures.txt``,
    ``exposures.json``).
    """

    def __init__(self, base, estimator: ExposureEstimator | None = None, *, compensate: bool = True,
                 mask_clipped: bool = True, clip_high: int = 254, dark_level: int = 3,
                 export_reference: str | float | Sequence[float] = "median", **options: Any) -> None:
        from mapping.colour import IrradianceColour

        if not isinstance(base, IrradianceColour):
            raise TypeError(f"base must be an IrradianceColour (exposure compensation acts on irradiance), got "
                            f"{type(base).__name__}; pass a response")
        if estimator is not None and options:
            raise ValueError(f"pass either an estimator or its options, not both (got options {sorted(options)})")
        if not (0 <= dark_level < clip_high <= 255):
            raise ValueError(f"need 0 <= dark_level < clip_high <= 255, got {dark_level}, {clip_high}")
        self.base = base
        self.compensate = bool(compensate)
        self.estimator = None
        if self.compensate:
            self.estimator = estimator if estimator is not None else ExposureEstimator(base.response, base.vignetting,
                                                                                   **options)
        elif estimator is not None or options:
            raise ValueError("compensate=False takes no estimator or estimator options")
        self.mask_clipped = bool(mask_clipped)
        self.clip_high, self.dark_level = int(clip_high), int(dark_level)
        resolve_reference(export_reference)  # validates it now rather than at the end of a run
        self.export_reference = export_reference
        suffix = "+exposure" if self.compensate else "+clip-mask"
        self.name = f"{base.name}{suffix}"

    @property
    def reference_exposure(self) -> float:
        return self.base.reference_exposure

    @property
    def response(self) -> CameraResponse:
        return self.base.response

    @property
    def vignetting(self):
        return self.base.vignetting

    def to_map(self, frame, view: Any = None, pose: np.ndarray | None = None):
        """The frame's irradiance divided by its exposure estimated against ``view`` (the map at ``pose``), with
        the pixels that may be fused."""
        from mapping.colour import FrameColour, divide_exposure

        E = self.base.to_map(frame, view, pose).colour
        if self.estimator is not None:
            record = self.estimator.estimate(frame, view, pose=pose)
            E = divide_exposure(E, record.k)
            if not record.fuse_colour:
                return FrameColour(E, np.zeros(E.shape[:2], dtype=bool),
                                   "colour rejected: the exposure estimate fell back")
        if self.mask_clipped:
            clipped = clipped_pixels(frame.rgb, high=self.clip_high, dark=self.dark_level)
            if clipped.any():
                return FrameColour(E, ~clipped, "colour rejected: every pixel clipped or black")
        return FrameColour(E)

    def to_display(self, colour: np.ndarray) -> np.ndarray:
        """Display levels at the fixed reference (the histogram's units during the run)."""
        return self.base.to_display(colour)

    def display_l1(self, map_colour: np.ndarray, sample_colour: np.ndarray) -> np.ndarray:
        """Display-unit L1 distances of (N, 3) map-unit pairs (the base model's, at the fixed reference)."""
        return self.base.display_l1(map_colour, sample_colour)

    def predict_observed(self, map_colour: np.ndarray, rgb: np.ndarray, valid: np.ndarray):
        """The base model's prediction: the held-out frame's exposure is fitted afresh against the render (the
        estimator never saw the frame)."""
        return self.base.predict_observed(map_colour, rgb, valid)

    def unexposed(self, rgb: np.ndarray) -> tuple[np.ndarray, float, bool]:
        colour, white, exposed = self.base.unexposed(rgb)
        return colour, white, exposed or self.compensate

    def display_exposure(self) -> np.ndarray:
        return np.asarray(self.export_reference_k(), dtype=np.float64).reshape(-1) * np.ones(3)

    def from_display(self, levels: np.ndarray) -> np.ndarray:
        k = self.display_exposure().astype(np.float32)
        return (self.base.response.inverse(np.asarray(levels, dtype=np.float32)) / k).astype(np.float32)

    def frame_exposures(self) -> dict[int, np.ndarray] | None:
        if self.estimator is None:
            return None
        return {int(r.index): np.asarray(r.k, dtype=np.float64).reshape(-1) * np.ones(3)
                for r in self.estimator.records if r.source != "fallback"}

    def export_reference_k(self) -> np.ndarray:
        """The export reference exposure (3,) relative to the first frame (resolved from the estimates)."""
        if self.estimator is None:
            return resolve_reference(self.export_reference)
        return self.estimator.reference(self.export_reference)

    def display_for_export(self):
        """``(N, 3)`` map units -> display levels at the export reference: ``f(E * k_ref_c)``."""
        scale = (self.export_reference_k() / self.base.reference_exposure).astype(np.float32)

        def to_display(colour: np.ndarray) -> np.ndarray:
            return self.base.to_display(np.asarray(colour, dtype=np.float32) * scale)

        return to_display

    def describe(self) -> dict:
        doc = dict(self.base.describe())
        doc["name"] = self.name
        doc["exposure"] = None
        doc["exposure_compensation"] = self.compensate
        doc["clip_mask"] = {"enabled": self.mask_clipped, "high": self.clip_high, "dark": self.dark_level}
        doc["histogram_reference"] = f"first frame x {self.base.reference_exposure:g}"
        doc["export_reference"] = {"kind": self.export_reference if isinstance(self.export_reference, str)
                                   else "given", "k": self.export_reference_k().tolist()}
        if self.estimator is not None:
            doc["exposure"] = {"estimator": "median ratio against the map (frame to frame at start-up)",
                               "settings": self.estimator.settings(), "summary": self.estimator.summary()}
        return doc

    def save_results(self, folder: str | os.PathLike) -> dict[str, Path]:
        """Write the per-frame estimates (``exposures.txt``, ``exposures.json``); nothing without compensation."""
        if self.estimator is None:
            return {}
        return self.estimator.save(folder, export_reference=self.export_reference_k(),
                                   histogram_reference=f"first frame x {self.base.reference_exposure:g}")


def make_compensated_colour(response: CameraResponse, vignetting=None, *, compensate: bool = True,
                            reference_exposure: float = 1.0, export_reference: str | float | Sequence[float] = "median",
                            mask_clipped: bool = True, **options: Any) -> CompensatedColour:
    """An :class:`~mapping.colour.IrradianceColour` of ``response`` and ``vignetting`` wrapped in a
    :class:`CompensatedColour` (``options``: :class:`ExposureEstimator` keywords)."""
    from mapping.colour import IrradianceColour

    base = IrradianceColour(response, vignetting, reference_exposure=reference_exposure)
    return CompensatedColour(base, compensate=compensate, mask_clipped=mask_clipped,
                             export_reference=export_reference, **options)
