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

*Robustness.* A frame whose estimate has fewer than ``min_correspondences`` usable pixels in a channel,
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

README-ready text
-----------------
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

from __future__ import annotations

import logging
import math
import os
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.exposure import exposure_ratio
from radiometry.response import CameraResponse

log = logging.getLogger(__name__)

SOURCES = ("reference", "map", "frame", "fallback")
EXPORT_REFERENCES = ("median", "first")
FILE_FORMAT = {"format": "radiomap", "kind": "exposure-estimates", "version": 1}


# --------------------------------------------------------------------------------------------------
# pixel masks
# --------------------------------------------------------------------------------------------------
def depth_edges(depth: np.ndarray, *, relative: float = 0.04, absolute: float = 0.01, dilation: int = 2) -> np.ndarray:
    """Pixels at or near a depth discontinuity, bool ``(H, W)``.

    A valid pixel is an edge when a 4-neighbour differs by more than ``absolute + relative * depth``
    metres, or is a hole (depth 0: depth shadows and dropouts lie along silhouettes); the edge set is then
    grown by ``dilation`` pixels (a square structuring element). Invalid pixels are not edges (they are
    excluded anyway).
    """
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W) metres, got shape {d.shape}")
    d = _valid_depth(d)
    if not (relative >= 0 and absolute >= 0):
        raise ValueError(f"relative and absolute must be >= 0, got {relative}, {absolute}")
    if int(dilation) < 0:
        raise ValueError(f"dilation must be a whole number of pixels >= 0, got {dilation}")
    valid = d > 0
    tol = absolute + relative * d
    edge = np.zeros(d.shape, dtype=bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        da, db = d[a], d[b]
        va, vb = valid[a], valid[b]
        step = np.abs(da - db)
        e_a = va & (~vb | (step > tol[a]))
        e_b = vb & (~va | (step > tol[b]))
        edge[a] |= e_a
        edge[b] |= e_b
    if dilation > 0 and edge.any():
        import cv2

        kernel = np.ones((2 * int(dilation) + 1, 2 * int(dilation) + 1), np.uint8)
        edge = cv2.dilate(edge.view(np.uint8), kernel).astype(bool)
    return edge


def _valid_depth(depth: np.ndarray) -> np.ndarray:
    """Depth with NaN, inf and negative values set to 0 (invalid); the array itself when all are valid."""
    ok = np.isfinite(depth) & (depth >= 0)
    return depth if ok.all() else np.where(ok, depth, np.float32(0)).astype(np.float32)


def clipped_pixels(rgb: np.ndarray, *, high: int = 254, dark: int = 3) -> np.ndarray:
    """Pixels that do not measure irradiance, bool ``(H, W)``: any channel ``>= high`` (saturated) or every
    channel ``<= dark`` (black)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
    if not (0 <= dark < high <= 255):
        raise ValueError(f"need 0 <= dark < high <= 255, got dark={dark}, high={high}")
    import cv2

    rgb = np.ascontiguousarray(rgb)
    unsaturated = cv2.inRange(rgb, (0, 0, 0), (high - 1,) * 3)     # every channel < high (255 where true)
    black = cv2.inRange(rgb, (0, 0, 0), (dark,) * 3)                 # every channel <= dark
    return (unsaturated == 0) | (black > 0)


def local_sums(values: np.ndarray, mask: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Sums of ``values`` (H, W[, C]) over the pixels of ``mask`` in each ``(2 radius + 1)^2`` window (zero
    outside the image): ``(sums float32 like values, counts float32 (H, W))``."""
    import cv2

    vals = np.asarray(values, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    if vals.shape[:2] != m.shape:
        raise ValueError(f"mask {m.shape} must match values {vals.shape[:2]}")
    if not (isinstance(radius, (int, np.integer)) and radius >= 0):
        raise ValueError(f"radius must be a whole number of pixels >= 0, got {radius!r}")
    mf = m.astype(np.float32)
    weighted = np.where(m if vals.ndim == 2 else m[:, :, None], vals, np.float32(0))  # no inf * 0
    if radius == 0:
        return weighted, mf
    size = (2 * int(radius) + 1, 2 * int(radius) + 1)
    return (cv2.boxFilter(weighted, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT),
            cv2.boxFilter(mf, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT))


def local_mean(values: np.ndarray, mask: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` (H, W[, C]) over the pixels of ``mask`` in each ``(2 radius + 1)^2`` window:
    ``(mean float32 (0 where the window holds no masked pixel), counts float32 (H, W))``; ``radius = 0``
    gives the masked values themselves."""
    sums, count = local_sums(values, mask, radius)
    safe = np.maximum(count, 1.0)
    mean = sums / (safe if sums.ndim == 2 else safe[:, :, None])
    mean[count < 0.5] = 0.0
    return mean, count


def block_reduce(values: np.ndarray, factor: int, how: str = "mean") -> np.ndarray:
    """``values`` (H, W[, C]) reduced over ``factor x factor`` blocks (the last partial rows and columns are
    dropped): ``"mean"`` (float32), ``"all"`` or ``"any"`` (bool)."""
    import cv2

    if how not in ("mean", "all", "any"):
        raise ValueError(f"how must be one of mean, all, any; got {how!r}")
    a = np.asarray(values)
    if factor == 1:
        return a.astype(np.float32, copy=False) if how == "mean" else a.astype(bool, copy=False)
    h, w = a.shape[0] // factor, a.shape[1] // factor
    crop = np.ascontiguousarray(a[:h * factor, :w * factor], dtype=np.float32)
    # INTER_AREA with an integer factor is the exact block mean (and far faster than a NumPy reshape-mean)
    mean = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
    if how == "mean":
        return mean
    return mean >= np.float32(1 - 1e-6) if how == "all" else mean > 0


# --------------------------------------------------------------------------------------------------
# records
# --------------------------------------------------------------------------------------------------
@dataclass
class ExposureRecord:
    """The exposure estimate of one frame (relative to the first fused frame; one row of exposures.txt).

    k:               (3,) the exposure the frame's irradiance was divided by.
    source:          ``reference`` (the first frame, k = 1), ``map``, ``frame`` (frame to frame) or ``fallback``.
    correspondences: usable pixels of the chosen estimate (fewest over the channels; 0 for reference/fallback).
    map_k, frame_k:  (3,) the two estimates (NaN when not available), with their correspondence counts.
    map_coverage:    fraction of the frame's valid depth (off edges) on which the map agrees with it.
    disagreement:    max over channels of ``|map_k / frame_k - 1|`` (NaN unless both exist).
    reason:          why a frame fell back (or why a jump was accepted); "" otherwise.
    fuse_colour:     False when the frame's colour must not be fused (a fallback frame).
    """

    index: int
    timestamp: float
    k: np.ndarray
    source: str
    correspondences: int = 0
    map_k: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    map_correspondences: int = 0
    frame_k: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    frame_correspondences: int = 0
    map_coverage: float = 0.0
    disagreement: float = math.nan
    reason: str = ""
    fuse_colour: bool = True

    def to_dict(self) -> dict:
        def arr(a):
            return [None if not np.isfinite(v) else float(v) for v in np.asarray(a, float)]

        return {"index": int(self.index), "timestamp": float(self.timestamp), "k": arr(self.k),
                "source": self.source, "correspondences": int(self.correspondences),
                "map_k": arr(self.map_k), "map_correspondences": int(self.map_correspondences),
                "frame_k": arr(self.frame_k), "frame_correspondences": int(self.frame_correspondences),
                "map_coverage": float(self.map_coverage),
                "disagreement": None if not np.isfinite(self.disagreement) else float(self.disagreement),
                "reason": self.reason, "fuse_colour": bool(self.fuse_colour)}


@dataclass
class _Observation:
    """One frame as the estimator sees it."""

    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    pose: np.ndarray | None
    irr: np.ndarray        # f^-1(I) / V, float32 (H, W, 3) (block means when downsampled)
    usable: np.ndarray     # valid depth, off depth edges, every channel within [low, high)
    radius: int
    V: np.ndarray | None
    factor: int = 1        # downsampling of depth, irr, usable, V and K relative to rgb
    _sums: tuple[np.ndarray, np.ndarray] | None = None

    def usable_sums(self) -> tuple[np.ndarray, np.ndarray]:
        """:func:`local_sums` of ``irr`` over the usable pixels (computed once)."""
        if self._sums is None:
            self._sums = local_sums(self.irr, self.usable, self.radius)
        return self._sums


@dataclass
class _Previous:
    """What frame-to-frame estimation keeps of the last accepted frame."""

    depth: np.ndarray
    K: np.ndarray
    pose: np.ndarray
    k: np.ndarray
    sums: np.ndarray       # local sums of f^-1(I) / V over usable pixels (H, W, 3)
    count: np.ndarray      # their pixel counts (H, W)
    selected: np.ndarray   # usable pixels with a well-filled window
    V: np.ndarray | None


def resolve_reference(kind: str | float | Sequence[float], estimates: np.ndarray | None = None) -> np.ndarray:
    """A reference exposure ``(3,)`` relative to the first frame: ``"median"`` (the per-channel median of
    ``estimates`` (N, 3), ones when there are none), ``"first"`` (ones), or one / three positive numbers."""
    if isinstance(kind, str):
        if kind == "first":
            return np.ones(3)
        if kind == "median":
            est = np.ones((0, 3)) if estimates is None else np.asarray(estimates, dtype=np.float64).reshape(-1, 3)
            return np.median(est, axis=0) if len(est) else np.ones(3)
        raise ValueError(f"the exposure reference must be one of {', '.join(EXPORT_REFERENCES)} or positive "
                         f"numbers, got {kind!r}")
    try:
        values = np.asarray(kind, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TypeError(f"the exposure reference must be 'median', 'first' or numbers, got {kind!r}") from None
    if values.size not in (1, 3) or not np.all(np.isfinite(values)) or np.any(values <= 0):
        raise ValueError(f"the exposure reference must be one positive number or three (R, G, B), got {kind!r}")
    return np.broadcast_to(values, (3,)).copy()


def parse_reference(text: str | float | Sequence[float]) -> str | float | list[float]:
    """The ``--mesh-exposure`` option (reconstruct): ``"median"``, ``"first"``, ``"0.8"`` or ``"0.8,1,1.2"`` (R, G, B);
    validated with :func:`resolve_reference`."""
    if isinstance(text, str):
        value = text.strip().lower()
        if value not in EXPORT_REFERENCES:
            try:
                numbers = [float(v) for v in value.split(",")]
            except ValueError:
                raise ValueError(f"the exposure reference must be median, first, a number or r,g,b numbers, got "
                                 f"{text!r}") from None
            value = numbers[0] if len(numbers) == 1 else numbers
        resolve_reference(value)
        return value
    resolve_reference(text)
    return text


# --------------------------------------------------------------------------------------------------
# the estimator
# --------------------------------------------------------------------------------------------------
def _check_positive(name: str, value: float, *, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name} must be a {'non-negative' if allow_zero else 'positive'} number, got {value!r}")
    return v


class ExposureEstimator:
    """Per-frame, per-channel exposure of incoming frames relative to the map (see the module doc).

    Call it as the ``exposure`` hook of :class:`mapping.colour.IrradianceColour`:
    ``estimator(frame, irradiance, view) -> k (3,)``; each call appends an :class:`ExposureRecord` to
    :attr:`records`. Frame-to-frame estimation needs the pose the frame is fused at: ``view.pose`` when the
    pipeline sets it, else ``frame.pose`` (ground truth); without a pose only the map is used.

    response, vignetting: the camera model the colour model corrects with (vignetting: a
                        :class:`~radiometry.vignetting.VignettingModel`, an array V (H, W[, C]) or None).
    low, high:          usable levels ``low <= I < high`` (every channel) in the frame and in the map's
                        display levels at the predicted exposure.
    min_correspondences: fewest usable pixels per channel for an estimate.
    min_map_coverage:   the map is preferred over frame-to-frame once it agrees with at least this fraction
                        of the frame's usable depth.
    max_jump:           an estimate outside ``[1 / max_jump, max_jump]`` times the last accepted one (any
                        channel) is implausible and falls back.
    confirm_frames, confirm_tolerance: an implausible estimate is accepted when it is the last of this many
                        consecutive implausible ones each within this relative tolerance of the one before
                        (a lasting change, e.g. an exposure ramp seen with a frame stride; None: never).
    depth_abs_tol, depth_rel_tol: map/frame (and frame/frame) depth agreement, metres and fraction of depth.
    edge_relative, edge_absolute, edge_dilation: :func:`depth_edges` parameters.
    downsample:         the estimate works on ``s x s`` block means (a block is usable when all its pixels
                        are); None: ``max(1, width // 320)`` (2 for 640 x 480), 1: full resolution.
    smoothing_radius:   both sides of a ratio are local means over ``(2 r + 1)^2`` windows (of the possibly
                        downsampled image) of the same usable pixels (:func:`local_sums`); None:
                        ``max(2, round(width / 160))`` of the downsampled width; 0: single pixels.
    min_fill:           fraction of a window that must be usable for its pixel to be a correspondence.
    frame_to_frame:     estimate frame to frame as well (start-up and cross-check).
    max_samples:        at most this many correspondences (a regular subsample) per estimate.
    fuse_fallback:      fuse the colour of fallback frames (divided by the last accepted k) instead of
                        rejecting it.

    Why local means, and why of ``f^-1(I) / V`` rather than of ``f^-1(I)``: see the module doc (the map is
    low-passed, the frame is sharp; dividing by V before averaging keeps a curved V from biasing the mean).
    """

    def __init__(self, response: CameraResponse, vignetting=None, *, low: float = 12, high: float = 245,
                 min_correspondences: int = 200, min_map_coverage: float = 0.3, max_jump: float = 2.0,
                 confirm_frames: int | None = 3, confirm_tolerance: float = 0.2, depth_abs_tol: float = 0.02,
                 depth_rel_tol: float = 0.03, edge_relative: float = 0.04, edge_absolute: float = 0.01,
                 edge_dilation: int = 2, downsample: int | None = None, smoothing_radius: int | None = None,
                 min_fill: float = 0.6,
                 frame_to_frame: bool = True, max_samples: int = 20000, fuse_fallback: bool = False) -> None:
        from mapping.colour import FastForward, as_vignetting_model

        if not isinstance(response, CameraResponse):
            raise TypeError(f"response must be a CameraResponse, got {type(response).__name__}")
        if not (0 <= low < high <= 256):
            raise ValueError(f"need 0 <= low < high <= 256, got low={low}, high={high}")
        if not (isinstance(min_correspondences, (int, np.integer)) and min_correspondences >= 1):
            raise ValueError(f"min_correspondences must be a whole number >= 1, got {min_correspondences!r}")
        if not (0 <= min_map_coverage <= 1):
            raise ValueError(f"min_map_coverage must be a fraction in [0, 1], got {min_map_coverage!r}")
        if not (_check_positive("max_jump", max_jump) > 1):
            raise ValueError(f"max_jump must be > 1 (e.g. 2 for a factor of two per frame), got {max_jump!r}")
        if confirm_frames is not None and not (isinstance(confirm_frames, (int, np.integer)) and confirm_frames >= 2):
            raise ValueError(f"confirm_frames must be a whole number >= 2 or None (never), got {confirm_frames!r}")
        if not (isinstance(max_samples, (int, np.integer)) and max_samples >= min_correspondences):
            raise ValueError(f"max_samples must be a whole number >= min_correspondences ({min_correspondences}), "
                             f"got {max_samples!r}")
        if smoothing_radius is not None and not (isinstance(smoothing_radius, (int, np.integer))
                                                 and 0 <= smoothing_radius <= 50):
            raise ValueError(f"smoothing_radius must be a whole number of pixels in 0..50 or None (auto), got "
                             f"{smoothing_radius!r}")
        if downsample is not None and not (isinstance(downsample, (int, np.integer)) and 1 <= downsample <= 16):
            raise ValueError(f"downsample must be a whole factor in 1..16 or None (auto), got {downsample!r}")
        if not (0 < min_fill <= 1):
            raise ValueError(f"min_fill must be a fraction in (0, 1], got {min_fill!r}")
        if not (isinstance(edge_dilation, (int, np.integer)) and edge_dilation >= 0):
            raise ValueError(f"edge_dilation must be a whole number of pixels >= 0, got {edge_dilation!r}")
        self.response = response
        self.vignetting = as_vignetting_model(vignetting)
        self.low, self.high = float(low), float(high)
        self.min_correspondences = int(min_correspondences)
        self.min_map_coverage = float(min_map_coverage)
        self.max_jump = float(max_jump)
        self.confirm_frames = None if confirm_frames is None else int(confirm_frames)
        self.confirm_tolerance = _check_positive("confirm_tolerance", confirm_tolerance)
        self.depth_abs_tol = _check_positive("depth_abs_tol", depth_abs_tol)
        self.depth_rel_tol = _check_positive("depth_rel_tol", depth_rel_tol, allow_zero=True)
        self.edge_relative = _check_positive("edge_relative", edge_relative, allow_zero=True)
        self.edge_absolute = _check_positive("edge_absolute", edge_absolute, allow_zero=True)
        self.edge_dilation = int(edge_dilation)
        self.smoothing_radius = None if smoothing_radius is None else int(smoothing_radius)
        self.downsample = None if downsample is None else int(downsample)
        self.min_fill = float(min_fill)
        self.frame_to_frame = bool(frame_to_frame)
        self.max_samples = int(max_samples)
        self.fuse_fallback = bool(fuse_fallback)
        self._forward = FastForward(response)
        self._v_cache: dict[tuple[int, int], np.ndarray] = {}
        self.reset()

    def reset(self) -> None:
        """Forget the sequence (records, anchor, previous frame)."""
        self.records: list[ExposureRecord] = []
        self._k_accepted: np.ndarray | None = None
        self._previous: _Previous | None = None
        self._jumps: list[np.ndarray] = []

    def factor_for(self, width: int) -> int:
        """The downsampling factor used for images ``width`` pixels wide."""
        if self.downsample is not None:
            return self.downsample
        return max(1, int(width) // 320)

    def radius_for(self, width: int) -> int:
        """The smoothing radius used for images ``width`` pixels wide."""
        if self.smoothing_radius is not None:
            return self.smoothing_radius
        return max(2, int(round(width / 160)))

    # ---------------------------------------------------------------- results
    @property
    def fallbacks(self) -> int:
        """How many frames fell back to the previous estimate."""
        return sum(r.source == "fallback" for r in self.records)

    @property
    def last(self) -> ExposureRecord | None:
        return self.records[-1] if self.records else None

    def estimates(self) -> np.ndarray:
        """``(N, 3)`` the k of every recorded frame."""
        return np.array([r.k for r in self.records], dtype=np.float64).reshape(-1, 3)

    def accepted(self) -> np.ndarray:
        """bool ``(N,)``: frames whose estimate was measured (not a fallback)."""
        return np.array([r.source != "fallback" for r in self.records], dtype=bool)

    def reference(self, kind: str | float | Sequence[float] = "median") -> np.ndarray:
        """A reference exposure ``(3,)`` relative to the first frame (:func:`resolve_reference` of this
        sequence's accepted estimates)."""
        return resolve_reference(kind, self.estimates()[self.accepted()])

    def summary(self) -> dict:
        """Counts by source, fallbacks by reason, the cross-check disagreement and the range of k."""
        sources = Counter(r.source for r in self.records)
        reasons = Counter(r.reason.split(" (")[0] for r in self.records if r.source == "fallback")
        dis = np.array([r.disagreement for r in self.records], dtype=np.float64)
        dis = dis[np.isfinite(dis)]
        k = self.estimates()
        return {"frames": len(self.records), "sources": {s: int(sources.get(s, 0)) for s in SOURCES},
                "fallbacks": self.fallbacks, "fallback_reasons": dict(reasons),
                "fallback_frames": [int(r.index) for r in self.records if r.source == "fallback"],
                "cross_check_frames": int(dis.size),
                "disagreement_median": float(np.median(dis)) if dis.size else None,
                "disagreement_p90": float(np.percentile(dis, 90)) if dis.size else None,
                "k_min": k.min(axis=0).tolist() if len(k) else None,
                "k_max": k.max(axis=0).tolist() if len(k) else None}

    def settings(self) -> dict:
        return {"low": self.low, "high": self.high, "min_correspondences": self.min_correspondences,
                "min_map_coverage": self.min_map_coverage, "max_jump": self.max_jump,
                "confirm_frames": self.confirm_frames, "confirm_tolerance": self.confirm_tolerance,
                "depth_abs_tol": self.depth_abs_tol, "depth_rel_tol": self.depth_rel_tol,
                "edge_relative": self.edge_relative, "edge_absolute": self.edge_absolute,
                "edge_dilation": self.edge_dilation, "downsample": self.downsample or "auto",
                "smoothing_radius": "auto" if self.smoothing_radius is None else self.smoothing_radius,
                "min_fill": self.min_fill, "frame_to_frame": self.frame_to_frame,
                "max_samples": self.max_samples, "fuse_fallback": self.fuse_fallback,
                "vignetting": None if self.vignetting is None else repr(self.vignetting),
                "response": repr(self.response)}

    # ---------------------------------------------------------------- the hook
    def __call__(self, frame, irradiance: np.ndarray | None = None, view: Any = None) -> np.ndarray:
        """The ``exposure`` hook: estimate, record and return the frame's ``k`` (3,). ``irradiance`` (the colour
        model's ``f^-1(I) / V``) is not used: the estimator works with its own response and vignetting."""
        return self.estimate(frame, view).k.copy()

    def estimate(self, frame, view: Any = None, *, pose: np.ndarray | None = None) -> ExposureRecord:
        """Estimate the exposure of ``frame`` (an :class:`~mapping.datasets.base.RGBDFrame`) against ``view``
        (the map rendered at its pose, a :class:`~mapping.fusion.base.ModelView`, or None) and record it.

        ``pose`` (camera-to-world) is the pose the frame is fused at; default ``view.pose``, else ``frame.pose``."""
        rgb = np.asarray(frame.rgb)
        depth = _valid_depth(np.asarray(frame.depth, dtype=np.float32))
        if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"frame.rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
        if depth.shape != rgb.shape[:2]:
            raise ValueError(f"frame.depth {depth.shape} must match frame.rgb {rgb.shape[:2]}")
        if pose is None:
            pose = getattr(view, "pose", None)
        if pose is None:
            pose = getattr(frame, "pose", None)
        if pose is not None:
            pose = np.asarray(pose, dtype=np.float64)
            if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
                pose = None
        K = np.asarray(frame.K, dtype=np.float64)
        obs = self._observe(rgb, depth, K, pose)
        record = ExposureRecord(int(frame.index), float(frame.timestamp), np.ones(3), "reference")

        if self._k_accepted is None:
            # the anchor: the first frame defines the units of the map
            record.reason = "first frame: the anchor (k = 1)"
            self._accept(record, np.ones(3), obs)
            return self._store(record)

        k_pred = self._k_accepted
        if view is not None and getattr(view, "depth", None) is not None:
            record.map_k, record.map_correspondences, record.map_coverage = self._from_map(obs, view, k_pred)
        if self.frame_to_frame and self._previous is not None and pose is not None:
            record.frame_k, record.frame_correspondences = self._from_previous(obs)
        map_ok = record.map_correspondences >= self.min_correspondences
        f2f_ok = record.frame_correspondences >= self.min_correspondences
        if map_ok and f2f_ok:
            record.disagreement = float(np.max(np.abs(record.map_k / record.frame_k - 1.0)))

        if map_ok and (record.map_coverage >= self.min_map_coverage or not f2f_ok):
            candidate, source, count = record.map_k, "map", record.map_correspondences
        elif f2f_ok:
            candidate, source, count = record.frame_k, "frame", record.frame_correspondences
        else:
            self._jumps.clear()
            return self._store(self._fallback(
                record, f"too few correspondences (map {record.map_correspondences}, frame to frame "
                        f"{record.frame_correspondences}; need {self.min_correspondences} per channel)"))

        jump = candidate / k_pred
        if np.all(jump <= self.max_jump) and np.all(jump >= 1.0 / self.max_jump):
            self._jumps.clear()
        else:
            self._jumps.append(candidate.copy())
            worst = float(jump[np.argmax(np.abs(np.log(jump)))])
            recent = self._jumps[-self.confirm_frames:] if self.confirm_frames else []
            # a change that lasts: the last confirm_frames candidates form a smooth run (each within
            # confirm_tolerance of the one before; an auto-exposure ramp), unlike isolated glitches
            confirmed = (self.confirm_frames is not None and len(recent) == self.confirm_frames
                         and all(np.all(np.abs(np.log(b / a)) <= math.log1p(self.confirm_tolerance))
                                 for a, b in zip(recent[:-1], recent[1:])))
            if not confirmed:
                return self._store(self._fallback(
                    record, f"implausible jump (x{worst:.3g} against the last accepted estimate; limit "
                            f"x{self.max_jump:g})"))
            record.reason = f"jump x{worst:.3g} accepted after {self.confirm_frames} consistent frames"
            self._jumps.clear()
        record.source, record.correspondences = source, int(count)
        self._accept(record, candidate, obs)
        return self._store(record)

    # ---------------------------------------------------------------- internals
    def _observe(self, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, pose) -> "_Observation":
        """Per-frame arrays both estimates need: f^-1(I) / V and the usable pixels, downsampled by ``factor``
        (block means; a block is usable when all its pixels are), and K for that resolution."""
        h, w = depth.shape
        factor = self.factor_for(w)
        V = self._vignetting_map(h, w)
        irr = self.response.inverse(rgb)
        if V is not None:
            irr /= V                                            # f^-1(I) / V
        edges = depth_edges(depth, relative=self.edge_relative, absolute=self.edge_absolute,
                            dilation=self.edge_dilation)
        usable = (depth > 0) & ~edges & self._levels_ok(rgb)
        if factor > 1:
            usable = block_reduce(usable, factor, "all")
            irr = block_reduce(irr, factor)
            depth = block_reduce(depth, factor)
            V = self._vignetting_map(h, w, factor)
            K = K.copy()
            K[:2, :2] /= factor
            K[:2, 2] = (K[:2, 2] - (factor - 1) / 2.0) / factor   # pixel centres of the blocks
        return _Observation(rgb=rgb, depth=depth, K=K, pose=pose, irr=irr, usable=usable,
                            radius=self.radius_for(depth.shape[1]), V=V, factor=factor)

    def _levels_ok(self, rgb: np.ndarray) -> np.ndarray:
        """Pixels whose every channel is within ``[low, high)``, bool (H, W)."""
        import cv2

        lo, hi = int(math.ceil(self.low)), int(math.ceil(self.high)) - 1
        if hi < lo:
            return np.zeros(rgb.shape[:2], dtype=bool)
        return cv2.inRange(np.ascontiguousarray(rgb), (lo,) * 3, (min(hi, 255),) * 3) > 0

    def _store(self, record: ExposureRecord) -> ExposureRecord:
        self.records.append(record)
        if record.source == "fallback":
            log.info("frame %d: exposure falls back to %s: %s", record.index, np.round(record.k, 4), record.reason)
        return record

    def _accept(self, record: ExposureRecord, k: np.ndarray, obs: "_Observation") -> None:
        record.k = np.asarray(k, dtype=np.float64).copy()
        self._k_accepted = record.k.copy()
        if self.frame_to_frame and obs.pose is not None:
            sums, count = obs.usable_sums()
            sel = obs.usable & (count >= self.min_fill * (2 * obs.radius + 1) ** 2)
            self._previous = _Previous(depth=obs.depth, K=obs.K, pose=obs.pose, k=record.k.copy(), sums=sums,
                                       count=count, selected=sel, V=obs.V)

    def _fallback(self, record: ExposureRecord, reason: str) -> ExposureRecord:
        record.source, record.reason = "fallback", reason
        record.k = self._k_accepted.copy()
        record.correspondences = 0
        record.fuse_colour = self.fuse_fallback
        return record

    def _vignetting_map(self, height: int, width: int, factor: int = 1) -> np.ndarray | None:
        """V (H, W, C) for an image size, block-averaged by ``factor`` (cached)."""
        if self.vignetting is None:
            return None
        key = (int(height), int(width), int(factor))
        if key not in self._v_cache:
            if factor == 1:
                V = np.asarray(self.vignetting.evaluate(height, width), dtype=np.float32)
                V = V if V.ndim == 3 else V[:, :, None]
            else:
                V = block_reduce(self._vignetting_map(height, width), factor)
            if len(self._v_cache) > 4:
                self._v_cache.clear()
            self._v_cache[key] = V
        return self._v_cache[key]

    def _subsample(self, idx: np.ndarray) -> np.ndarray:
        if idx.size <= self.max_samples:
            return idx
        return idx[::int(math.ceil(idx.size / self.max_samples))]

    def _ratio(self, e1: np.ndarray, e2: np.ndarray, v1, v2) -> tuple[np.ndarray, int]:
        """``radiometry.exposure.exposure_ratio`` of two sets of (local mean) irradiance ``f^-1(I) / V``
        (N, 3) observed where the vignetting is ``v1``, ``v2`` (None: 1). They are passed as the float levels
        ``f(e v)`` with ``v``, which exposure_ratio maps back to ``e`` (an exact round trip: both directions
        are piecewise linear) and checks against ``low``/``high``."""
        l1 = self._forward(e1 if v1 is None else e1 * v1)
        l2 = self._forward(e2 if v2 is None else e2 * v2)
        ratio, n_used = exposure_ratio(l1, l2, v1, v2, self.response, low=self.low, high=self.high,
                                       min_count=self.min_correspondences)
        return ratio, int(n_used.min())

    def _from_map(self, obs: "_Observation", view, k_pred: np.ndarray) -> tuple[np.ndarray, int, float]:
        """``k`` from the rendered map: (k (3,), usable correspondences (fewest channel), coverage)."""
        full = obs.rgb.shape[:2]
        map_depth = _valid_depth(np.asarray(view.depth, dtype=np.float32))
        if map_depth.shape != full:
            raise ValueError(f"view.depth {map_depth.shape} must match the frame's depth {full}")
        e_map = np.asarray(view.colour, dtype=np.float32)
        if e_map.shape != full + (3,):
            raise ValueError(f"view.colour {e_map.shape} must be (H, W, 3) like the frame, {full}")
        # the map's own silhouettes and the borders of what it has seen (a ray cast interpolates colours there
        # with unobserved, black voxels) and invalid colours are not compared
        import cv2

        finite = cv2.inRange(np.ascontiguousarray(e_map), (0.0, 0.0, 0.0), (3e38, 3e38, 3e38)) > 0  # not NaN/inf/<0
        map_ok = (map_depth > 0) & finite
        map_ok &= ~depth_edges(map_depth, relative=self.edge_relative, absolute=self.edge_absolute,
                               dilation=self.edge_dilation)
        if obs.factor > 1:
            e_map = block_reduce(np.where(map_ok[:, :, None], e_map, np.float32(0)), obs.factor)
            map_depth = block_reduce(map_depth, obs.factor)
            map_ok = block_reduce(map_ok, obs.factor, "all")
        depth = obs.depth
        tol = np.maximum(self.depth_abs_tol, self.depth_rel_tol * depth)
        agree = obs.usable & map_ok & (np.abs(map_depth - depth) <= tol)
        n_usable = int(np.count_nonzero(obs.usable))
        coverage = float(np.count_nonzero(agree)) / n_usable if n_usable else 0.0
        if np.count_nonzero(agree) < self.min_correspondences:
            return np.full(3, np.nan), int(np.count_nonzero(agree)), coverage
        # The map's colour enters at the predicted exposure, as display levels; exposure_ratio drops what is
        # dark or near saturation there (on the local means: a per-pixel cut on the map, noisy while few
        # frames are fused, keeps its darker samples near the threshold and biases the ratio up).
        area = (2 * obs.radius + 1) ** 2
        s_frame, count = local_sums(obs.irr, agree, obs.radius)
        s_map, _ = local_sums(e_map, agree, obs.radius)
        sel = agree & (count >= self.min_fill * area)
        idx = self._subsample(np.flatnonzero(sel))
        if idx.size < self.min_correspondences:
            return np.full(3, np.nan), int(idx.size), coverage
        c = count.reshape(-1)[idx][:, None]
        m_frame = s_frame.reshape(-1, 3)[idx] / c
        m_map = s_map.reshape(-1, 3)[idx] * (k_pred.astype(np.float32) / c)
        v_frame = None if obs.V is None else obs.V.reshape(-1, obs.V.shape[2])[idx]
        ratio, n = self._ratio(m_frame, m_map, v_frame, None)
        return ratio * k_pred, n, coverage

    def _from_previous(self, obs: "_Observation") -> tuple[np.ndarray, int]:
        """``k`` from the last accepted frame re-projected into this one: (k (3,), correspondences)."""
        prev = self._previous
        h, w = obs.depth.shape
        idx = self._subsample(np.flatnonzero(prev.selected))
        if idx.size < self.min_correspondences:
            return np.full(3, np.nan), 0
        ys, xs = np.divmod(idx, prev.depth.shape[1])
        z = prev.depth.reshape(-1)[idx].astype(np.float64)
        Kp, K = prev.K, obs.K
        pts = np.stack([(xs - Kp[0, 2]) / Kp[0, 0] * z, (ys - Kp[1, 2]) / Kp[1, 1] * z, z], axis=1)
        T = np.linalg.solve(obs.pose, prev.pose)  # previous camera -> current camera
        q = pts @ T[:3, :3].T + T[:3, 3]
        Z = q[:, 2]
        front = Z > 1e-6
        u = np.full(Z.shape, -1.0)
        v = np.full(Z.shape, -1.0)
        u[front] = K[0, 0] * q[front, 0] / Z[front] + K[0, 2]
        v[front] = K[1, 1] * q[front, 1] / Z[front] + K[1, 2]
        inside = front & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        u, v, Z, src = u[inside], v[inside], Z[inside], idx[inside]
        sums, count = obs.usable_sums()
        sel = obs.usable & (count >= self.min_fill * (2 * obs.radius + 1) ** 2)
        ui, vi = np.rint(u).astype(np.intp), np.rint(v).astype(np.intp)
        d_cur = obs.depth[vi, ui]
        u0 = np.minimum(np.floor(u).astype(np.intp), w - 2)
        v0 = np.minimum(np.floor(v).astype(np.intp), h - 2)
        ok = (np.abs(d_cur - Z) <= np.maximum(self.depth_abs_tol, self.depth_rel_tol * d_cur)) & (d_cur > 0) \
            & sel[v0, u0] & sel[v0, u0 + 1] & sel[v0 + 1, u0] & sel[v0 + 1, u0 + 1]
        u, v, u0, v0, ui, vi, src = u[ok], v[ok], u0[ok], v0[ok], ui[ok], vi[ok], src[ok]
        if src.size < self.min_correspondences:
            return np.full(3, np.nan), int(src.size)
        # bilinear look-up of the current frame's local means of irradiance (linear, unlike levels)
        a = (u - u0)[:, None].astype(np.float32)
        b = (v - v0)[:, None].astype(np.float32)

        def mean(y, x):
            return sums[y, x] / count[y, x][:, None]

        cur = ((1 - a) * (1 - b) * mean(v0, u0) + a * (1 - b) * mean(v0, u0 + 1)
               + (1 - a) * b * mean(v0 + 1, u0) + a * b * mean(v0 + 1, u0 + 1))
        v_cur = v_prev = None
        if obs.V is not None:
            v_cur = obs.V[vi, ui]
        if prev.V is not None:
            v_prev = prev.V.reshape(-1, prev.V.shape[2])[src]
        prev_mean = prev.sums.reshape(-1, 3)[src] / prev.count.reshape(-1)[src][:, None]
        ratio, n = self._ratio(cur, prev_mean, v_cur, v_prev)
        return ratio * prev.k, n

    # ---------------------------------------------------------------- files
    def to_json(self, *, export_reference: np.ndarray | None = None, histogram_reference: Any = None) -> dict:
        doc = dict(FILE_FORMAT)
        doc.update({"anchor": "the first fused frame (k = 1); k_c multiplies irradiance f^-1(I)/V of channel c",
                    "histogram_reference": histogram_reference,
                    "export_reference": None if export_reference is None else np.asarray(export_reference).tolist(),
                    "settings": self.settings(), "summary": self.summary(),
                    "frames": [r.to_dict() for r in self.records]})
        return doc

    def to_text(self) -> str:
        lines = ["# radiomap per-frame exposure estimates, relative to the first fused frame (k = 1)\n",
                 "# index timestamp k_r k_g k_b correspondences source\n"]
        for r in self.records:
            lines.append(f"{r.index} {r.timestamp:.6f} {r.k[0]:.6f} {r.k[1]:.6f} {r.k[2]:.6f} "
                         f"{r.correspondences} {r.source}\n")
        return "".join(lines)

    def save(self, folder: str | os.PathLike, *, export_reference: np.ndarray | None = None,
             histogram_reference: Any = None) -> dict[str, Path]:
        """Write ``exposures.txt`` and ``exposures.json`` into ``folder`` (atomically)."""
        from radiometry.fileio import atomic_write_json, atomic_write_text, ensure_dir

        folder = ensure_dir(folder)
        return {"exposures_txt": atomic_write_text(folder / "exposures.txt", self.to_text()),
                "exposures_json": atomic_write_json(folder / "exposures.json", self.to_json(
                    export_reference=export_reference, histogram_reference=histogram_reference))}


def read_exposures(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read ``exposures.txt`` or ``exposures.json``: ``{"index", "timestamp", "k" (N, 3), "correspondences",
    "source"}`` arrays."""
    import json

    from radiometry.errors import CalibrationFileError

    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such exposure file; run radiomap reconstruct with "
                                   "--exposure-compensation")
    if path.suffix.lower() == ".json":
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise CalibrationFileError(f"{path}:{exc.lineno}: invalid JSON ({exc.msg}); re-run the reconstruction") \
                from None
        if not isinstance(doc, dict) or doc.get("kind") != FILE_FORMAT["kind"] or "frames" not in doc:
            raise CalibrationFileError(f"{path}: not a radiomap exposure-estimates file")
        rows = doc["frames"]
        return {"index": np.array([r["index"] for r in rows], dtype=np.int64),
                "timestamp": np.array([r["timestamp"] for r in rows], dtype=np.float64),
                "k": np.array([r["k"] for r in rows], dtype=np.float64).reshape(-1, 3),
                "correspondences": np.array([r["correspondences"] for r in rows], dtype=np.int64),
                "source": np.array([r["source"] for r in rows], dtype=object)}
    idx, ts, ks, ns, srcs = [], [], [], [], []
    for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 7 or parts[6] not in SOURCES:
            raise CalibrationFileError(f"{path}:{lineno}: expected 'index timestamp k_r k_g k_b correspondences "
                                       f"source', got {line!r}")
        try:
            idx.append(int(parts[0]))
            ts.append(float(parts[1]))
            ks.append([float(v) for v in parts[2:5]])
            ns.append(int(parts[5]))
        except ValueError:
            raise CalibrationFileError(f"{path}:{lineno}: not numbers: {line!r}") from None
        srcs.append(parts[6])
    return {"index": np.array(idx, dtype=np.int64), "timestamp": np.array(ts), "k": np.array(ks).reshape(-1, 3),
            "correspondences": np.array(ns, dtype=np.int64), "source": np.array(srcs, dtype=object)}


# --------------------------------------------------------------------------------------------------
# evaluation against ground truth
# --------------------------------------------------------------------------------------------------
def exposure_errors(estimated: np.ndarray, truth: np.ndarray, *, use: np.ndarray | None = None,
                    skip_first: int = 0) -> dict:
    """Relative errors of per-frame exposure estimates against ground truth, both normalised to frame 0.

    estimated: ``(N, 3)`` estimates ``k_i`` (any common scale); truth: ``(N, 3)`` true effective exposures
    ``k_i * g_ic`` (or ``(N, 4)`` rows ``k, g_r, g_g, g_b`` as in ``truth/exposures.txt``). The error of
    frame ``i``, channel ``c`` is ``(est_ic / est_0c) / (true_ic / true_0c) - 1``.
    use: optional bool ``(N,)``, the frames to evaluate (e.g. non-fallback); skip_first: leave out the first
    frames (start-up) from ``median``/``max``.

    Returns ``{"errors": (N, 3) array, "median", "max", "p90" (of |error| over the evaluated frames and
    channels), "median_per_frame" (median over frames of the worst channel), "drift" (the mean signed
    error of the last quarter of the evaluated frames minus that of the first quarter, per channel: a
    trend, not noise), "final" (mean |error| of the last 5 evaluated frames), "frames" (evaluated)}``.
    """
    est = np.asarray(estimated, dtype=np.float64)
    tru = np.asarray(truth, dtype=np.float64)
    if tru.ndim == 2 and tru.shape[1] == 4:
        tru = tru[:, :1] * tru[:, 1:]
    if est.ndim != 2 or est.shape[1] != 3 or tru.shape != est.shape:
        raise ValueError(f"estimated and truth must both be (N, 3) (truth may be (N, 4) k, g_r, g_g, g_b), got "
                         f"{est.shape} and {np.shape(truth)}")
    if est.shape[0] == 0:
        raise ValueError("no frames to evaluate")
    if not (np.all(np.isfinite(est)) and np.all(est > 0) and np.all(np.isfinite(tru)) and np.all(tru > 0)):
        raise ValueError("estimated and truth must be positive finite exposures")
    err = (est / est[0]) / (tru / tru[0]) - 1.0
    sel = np.ones(est.shape[0], dtype=bool) if use is None else np.asarray(use, dtype=bool).copy()
    if sel.shape != (est.shape[0],):
        raise ValueError(f"use must be a bool array of shape ({est.shape[0]},), got {sel.shape}")
    sel[:max(int(skip_first), 0)] = False
    e = err[sel]
    if e.shape[0] == 0:
        raise ValueError("no frame left to evaluate (check use= and skip_first=)")
    a = np.abs(e)
    q = max(1, e.shape[0] // 4)
    return {"errors": err, "median": float(np.median(a)), "max": float(a.max()), "p90": float(np.percentile(a, 90)),
            "median_per_frame": float(np.median(a.max(axis=1))),
            "drift": (e[-q:].mean(axis=0) - e[:q].mean(axis=0)).tolist(),
            "final": float(a[-5:].mean()), "frames": int(e.shape[0])}


# --------------------------------------------------------------------------------------------------
# the colour model
# --------------------------------------------------------------------------------------------------
class CompensatedColour:
    """A :class:`mapping.colour.ColourModel` that fuses exposure-compensated irradiance and masks clipped
    pixels (wraps an :class:`~mapping.colour.IrradianceColour`; see the module doc).

    base:             the irradiance colour model (its response, vignetting and ``reference_exposure``, the
                      fixed display reference of the histogram; its ``exposure`` hook is set here).
    estimator:        an :class:`ExposureEstimator`, or None to build one from ``base`` with ``**options``.
    compensate:       False: no exposure estimation, only the clipped-pixel mask (an ablation).
    mask_clipped:     mark clipped pixels invalid (:attr:`last_valid_mask`).
    clip_high, dark_level: :func:`clipped_pixels` thresholds.
    export_reference: ``"median"``, ``"first"``, or a number / three numbers (relative to the first frame)
                      for :meth:`export_display`.

    After each :meth:`to_map`, :attr:`last_valid_mask` is None (every pixel may be fused) or bool (H, W):
    the pipeline zeroes the depth where it is False, and skips the frame with :attr:`last_reject_reason` when
    nothing is left. After the run the pipeline exports the mesh through :meth:`export_display` and calls
    :meth:`save_results` (``exposures.txt``, ``exposures.json``).
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
            base.exposure = self.estimator
        elif estimator is not None or options:
            raise ValueError("compensate=False takes no estimator or estimator options")
        self.mask_clipped = bool(mask_clipped)
        self.clip_high, self.dark_level = int(clip_high), int(dark_level)
        resolve_reference(export_reference)  # validates it now rather than at the end of a run
        self.export_reference = export_reference
        suffix = "+exposure" if self.compensate else "+clip-mask"
        self.name = f"{base.name}{suffix}"
        self.last_valid_mask: np.ndarray | None = None
        self.last_reject_reason: str | None = None
        self.last_record: ExposureRecord | None = None

    @property
    def reference_exposure(self) -> float:
        return self.base.reference_exposure

    @property
    def response(self) -> CameraResponse:
        return self.base.response

    @property
    def vignetting(self):
        return self.base.vignetting

    def to_map(self, frame, view: Any = None) -> np.ndarray:
        n_before = len(self.estimator.records) if self.estimator is not None else 0
        colour = self.base.to_map(frame, view)
        record = None
        if self.estimator is not None and len(self.estimator.records) > n_before:
            record = self.estimator.records[-1]
        self.last_record = record
        if record is not None and not record.fuse_colour:
            self.last_valid_mask = np.zeros(colour.shape[:2], dtype=bool)
            self.last_reject_reason = "colour rejected: the exposure estimate fell back"
        elif self.mask_clipped:
            clipped = clipped_pixels(frame.rgb, high=self.clip_high, dark=self.dark_level)
            self.last_valid_mask = ~clipped if clipped.any() else None
            self.last_reject_reason = "colour rejected: every pixel clipped or black"
        else:
            self.last_valid_mask = self.last_reject_reason = None
        return colour

    def to_display(self, colour: np.ndarray) -> np.ndarray:
        """Display levels at the fixed reference (the histogram's units during the run)."""
        return self.base.to_display(colour)

    def display_l1(self, map_colour: np.ndarray, sample_colour: np.ndarray) -> np.ndarray:
        """Display-unit L1 distances of (N, 3) map-unit pairs (the base model's, at the fixed reference)."""
        from mapping.colour import display_l1

        return display_l1(self.base, map_colour, sample_colour)

    def export_reference_k(self) -> np.ndarray:
        """The export reference exposure (3,) relative to the first frame (resolved from the estimates)."""
        if self.estimator is None:
            return resolve_reference(self.export_reference)
        return self.estimator.reference(self.export_reference)

    def export_display(self):
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


__all__ = ["CompensatedColour", "ExposureEstimator", "ExposureRecord", "SOURCES", "clipped_pixels", "depth_edges",
           "block_reduce", "exposure_errors", "local_mean", "local_sums", "make_compensated_colour", "parse_reference",
           "read_exposures", "resolve_reference"]
