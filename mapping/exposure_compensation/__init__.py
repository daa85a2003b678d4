"""Exposure and white-balance compensation during mapping (Alexandrov et al., IROS 2016, Sec. V).

Cameras with automatic exposure (AE) and white balance (AWB) change ``k`` in ``I = f(k V(x) L)`` from frame
to frame, per channel (a white-balance gain is a per-channel exposure). Fusing ``f^-1(I) / V`` as it is
then averages the same surface at different brightnesses. :class:`ExposureEstimator` estimates every
frame's ``k = (k_r, k_g, k_b)`` and :class:`CompensatedColour` fuses ``f^-1(I) / V / k`` instead.

How a frame's exposure is estimated
-----------------------------------
*Against the map (the anchor).* The pipeline renders the map at the frame's pose before fusing it (the
``view``). Where the rendered depth agrees with the frame's depth, both see the same surface point, and
``radiometry.exposure.exposure_ratio`` gives the median over those pixels of
``k_frame / k_pred = f^-1(I) V_map / (f^-1(I_map) V(x))``, where ``I_map = f(E_map * k_pred)`` is the
map's colour expressed in display levels at the predicted exposure ``k_pred`` (the last accepted
estimate) and ``V_map = 1`` (map colours are vignetting-free). Used are only pixels that are

- neither dark nor near saturation: ``low <= I < high`` in every channel of the frame's pixel, and the
  same test on both sides of the ratio (the frame's and the map's levels at ``k_pred``) inside
  ``exposure_ratio`` (clipped levels no longer measure irradiance);
- away from depth discontinuities of the frame AND of the rendered map (:func:`depth_edges`: a large local
  depth step, or a hole, within ``edge_dilation`` pixels; colour and depth are misregistered by a few
  pixels on real sensors, a wrong pose shows first at silhouettes, and a ray cast mixes colours with
  unobserved voxels at the border of what the map has seen);
- where map and frame depth agree within ``max(depth_abs_tol, depth_rel_tol * depth)``.

Both sides of each ratio are local means of ``f^-1(I) / V`` over the same usable pixels of a
``(2 r + 1)^2`` window (:func:`local_sums`), because the map's colour is a low-pass image of the scene
(voxels, trilinear interpolation) while the frame is sharp: on textured surfaces the median of sharp /
blurred is not 1. Measured on the simulated room with the true exposures fused (so that any error is the
estimator's): single pixels +0.5 % per frame, 5 x 5 means of ``f^-1(I) / V`` -0.03 %. A per-frame bias
matters because the map inherits it: fused with +0.7 %, the estimates drifted by 4 % over 50 frames.
Images 640 pixels wide or more are first reduced to ``width // 320``-square block means (a block is usable
when all its pixels are): on the real kitchen sequence the histogram mean moved from 30.41 to 30.42; both
estimates together then take ~35 ms per 640 x 480 frame on this project's 2-core test machine.

*Frame to frame (start-up and cross-check).* The last accepted frame is re-projected through its depth and
the relative pose into the current frame (bilinear look-up of the local means, which are irradiance, so the
interpolation is linear in it; the same depth and intensity filters), giving
``k_frame / k_prev``. It is used while the map covers less than ``min_map_coverage`` of the frame's valid
depth (the first frames, the camera entering unmapped space) and recorded as a cross-check otherwise
(``ExposureRecord.disagreement``: the largest per-channel relative difference of the two estimates).

*Robustness.* The anchor (k = 1) is the first frame with at least ``min_correspondences`` usable pixels: a
black or blown-out first frame falls back (not fused) instead of anchoring a map no later frame could be
compared with. A frame whose estimate has fewer than ``min_correspondences`` usable pixels in a channel,
or jumps by more than ``max_jump`` (or less than ``1 / max_jump``) against the last accepted estimate in
any channel, FALLS BACK: its ``k`` is the last accepted one, it is counted
(:attr:`ExposureEstimator.fallbacks`) and, by default (``fuse_fallback=False``), its colour is not fused
at all (:attr:`CompensatedColour.last_valid_mask` is all False; the pipeline then skips the frame), because
a frame 4x over-exposed and divided by the previous ``k`` would brighten the map fourfold where it is not
clipped. The limit is per processed frame: with a frame stride a real auto-exposure ramp can exceed it, so
a jump that lasts (``confirm_frames`` consecutive implausible estimates, each within ``confirm_tolerance``
of the one before) is accepted as a real change of exposure; an isolated glitch never is.

Clipped pixels
--------------
:class:`CompensatedColour` also marks pixels that do not measure irradiance, i.e. any channel
``>= clip_high`` (254) or all channels ``<= dark_level``, in :attr:`CompensatedColour.last_valid_mask`;
the pipeline zeroes the depth of those pixels before fusion (Open3D's integration has no per-pixel
colour weight; zero depth is its "no measurement"), so they add neither colour nor geometry from this
frame. The same pixels therefore leave the disagreement histogram: it counts samples averaged into the
map, and these are not.

Reference exposure (display units)
----------------------------------
The map stores ``f^-1(I) / V / k`` in first-frame units. Display levels are ``f(E * k_ref)``:

- During the run (the disagreement histogram) ``k_ref`` is FIXED: the wrapped colour model's
  ``reference_exposure`` (default 1, i.e. the first frame's exposure), known before the sequence is
  seen, so that runs with and without compensation are measured in the same kind of units.
- For the exported mesh (after the run), ``export_reference`` is ``"median"`` (default: the per-channel
  median of the sequence's accepted estimates, i.e. the map looks like a typical frame of the sequence),
  ``"first"`` (the first frame's exposure), a number or three numbers relative to the first frame.

User-facing summary
-------------------
``radiomap reconstruct SEQ --response crf.npz [--vignetting v.npz] --exposure-compensation`` estimates
every frame's exposure and white balance against the map and fuses exposure-normalised irradiance. It is
ON by default whenever a response is given (irradiance fusion; a camera without auto exposure simply
gets estimates close to 1) and can be switched off with ``--no-exposure-compensation``; without a
response (raw-intensity fusion) it is not available. The per-frame estimates are written to
``exposures.txt`` (``index timestamp k_r k_g k_b correspondences source``) and ``exposures.json``
(everything, including both estimates, their disagreement and the fallback reasons). The histogram is in
display levels at the first frame's exposure, the mesh at the median exposure of the sequence
(``--mesh-exposure first|median|VALUE``). Frames whose estimate is implausible (a jump of more than 2x
against the last accepted frame, or too few usable pixels) are not fused and are counted; clipped pixels
(a channel >= 254, or all channels <= 3) are never fused. Measured: on a simulated room with auto exposure
and auto white balance (160 x 120, 50 frames, exposures falling to 0.34x / 0.50x / 0.63x in R / G / B) the
per-frame estimates are within 0.18 % of the truth (median; 0.38 % at worst) and the colour disagreement
halves (mean 43.0 -> 21.9, p90 85 -> 45); on the real 7-Scenes kitchen (100 frames, response assumed
gamma 2.2, no vignetting model) the mean drops from 41.5 to 30.4 and the p90 from 91 to 73
(``scripts/bench_exposure_redkitchen.py``).
"""

from mapping.exposure_compensation.colour import CompensatedColour, make_compensated_colour
from mapping.exposure_compensation.estimator import ExposureEstimator
from mapping.exposure_compensation.masks import block_reduce, clipped_pixels, depth_edges, local_mean, local_sums
from mapping.exposure_compensation.records import (SOURCES, ExposureRecord, exposure_errors, parse_reference,
                                                   read_exposures, resolve_reference)

__all__ = ["CompensatedColour", "ExposureEstimator", "ExposureRecord", "SOURCES", "clipped_pixels", "depth_edges",
           "block_reduce", "exposure_errors", "local_mean", "local_sums", "make_compensated_colour", "parse_reference",
           "read_exposures", "resolve_reference"]
