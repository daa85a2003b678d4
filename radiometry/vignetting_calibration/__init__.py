"""Vignetting calibration from a white-paper sweep (Alexandrov et al. 2016, Sec. IV), plus drift.

Recording: exposure (and white balance) fixed, the camera swept over an evenly lit white sheet so
that every part of the image sees the sheet many times. Then, per frame:

1. :func:`detect_sheet` finds the sheet: a flood fill seeded at the previous frame's sheet centre (the
   image centre at first; if that pixel is not on a bright region, the nearest bright region's most
   interior point). The fill uses a *floating* range on a lightly blurred grey image, so the smooth
   vignetting gradient passes while the sheet's edge stops it; its tolerance is a multiple of the
   sheet's own noise (robust std of neighbour differences around the seed). The region is cleaned
   morphologically and its border eroded (edge pixels mix sheet and background). A frame whose sheet
   is too small, too dark, or mostly saturated is skipped and counted.
2. :class:`VignettingAccumulator` maps the sheet's pixels to irradiance with ``f^-1`` (pixels with a
   channel ``>= saturation`` or ``<= dark`` excluded per channel, and levels where the response was
   extrapolated rather than fitted, as its ``meta["extrapolated_levels"]`` records) and accumulates per pixel
   and channel the count, sum and sum of squares (float64).

Beyond radical: light and exposure drift. If the light (or the sheet's angle to it, or an auto
exposure that was not quite off) changes the sheet's brightness by a factor ``s_t`` in frame ``t``,
a plain average mixes frames of different brightness in different parts of the image and bends
``V``. The model is ``E_t(x) = s_t V(x) L``. Alternating "V from the frames divided by their scales,
scales from V" is block coordinate descent on the least-squares problem in ``log``; it converges to
the solution of one linear system, which we solve directly (:func:`estimate_frame_scales`) on a
compact per-frame representation: the sums and counts of each frame's irradiance on a grid of
``block x block`` pixel cells (at most ~1200 cells per frame, float32 + uint16: ~22 kB per frame
at any resolution). Three robust re-weighting rounds follow so that a stain or glare does not bias
the scales. The full-resolution mean is then corrected by the mean scale of the frames that saw each
pixel: ``V(x) ~ sum_t E_t(x) / sum_t s_t`` over the frames observing ``x``, with the mean scale taken
per cell and interpolated bilinearly (exact where the sheet masks are constant over a cell, and the
masks' edges move a cell's frame set by a few frames out of hundreds).

The correction is on by default (``joint_scale=True``). On simulated 160x120 sweeps of an Xtion-like
camera it costs little in steady light (LUT error 0.17 instead of 0.11 levels: the paper's own texture
leaks a little into the scales) and saves a lot under drift (0.18 instead of 1.6 levels with the light
varying by +-10 %); ``joint_scale=False`` gives radical's plain average.

Fits (one function per method, :func:`fit_vignetting` dispatches): :func:`fit_vignetting_lut`,
:func:`fit_vignetting_polynomial` (centre fixed at the image centre by linear least squares, or free
by Levenberg-Marquardt initialised from the fixed-centre fit).

Modules, one job each: :mod:`~radiometry.vignetting_calibration.sources` (folder, video, camera, arrays),
:mod:`~radiometry.vignetting_calibration.sheet` (step 1), :mod:`~radiometry.vignetting_calibration.accumulate`
(step 2), :mod:`~radiometry.vignetting_calibration.scales` (drift), :mod:`~radiometry.vignetting_calibration.collect`
(a source through steps 1 and 2), :mod:`~radiometry.vignetting_calibration.fit` (the models),
:mod:`~radiometry.vignetting_calibration.evaluate` (errors in 8-bit levels, repeatability),
:mod:`~radiometry.vignetting_calibration.uncertainty` (the LUT's standard error and error budget).
"""

from radiometry.vignetting_calibration.accumulate import (CoverageReport, VignettingAccumulation,
                                                          VignettingAccumulator)
from radiometry.vignetting_calibration.collect import collect_vignetting
from radiometry.vignetting_calibration.evaluate import (calibration_summary, flat_rms_levels, model_centre,
                                                        repeatability, vignetting_error_levels)
from radiometry.vignetting_calibration.fit import (MAX_SMOOTH_SIGMA, MODELS, fit_vignetting, fit_vignetting_lut,
                                                   fit_vignetting_polynomial)
from radiometry.vignetting_calibration.scales import estimate_frame_scales
from radiometry.vignetting_calibration.sheet import SheetDetection, detect_sheet
from radiometry.vignetting_calibration.sources import (ArrayFrames, CameraFrames, FolderFrames, FrameSource,
                                                       VideoFrames, open_frames)

__all__ = [
    "FrameSource", "FolderFrames", "VideoFrames", "CameraFrames", "ArrayFrames", "open_frames",
    "SheetDetection", "detect_sheet", "VignettingAccumulator", "VignettingAccumulation", "CoverageReport",
    "estimate_frame_scales", "collect_vignetting", "fit_vignetting", "fit_vignetting_lut",
    "fit_vignetting_polynomial", "vignetting_error_levels", "flat_rms_levels", "repeatability", "MODELS",
    "MAX_SMOOTH_SIGMA", "calibration_summary", "model_centre",
]
