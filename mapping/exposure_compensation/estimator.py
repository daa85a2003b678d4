"""The per-frame exposure and white-balance estimator, against the map and frame to frame (see
:mod:`mapping.exposure_compensation`)."""

from __future__ import annotations

import logging
import math
import os
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.exposure import exposure_ratio
from radiometry.response import CameraResponse
from mapping.exposure_compensation.masks import _valid_depth, block_reduce, depth_edges, local_sums
from mapping.exposure_compensation.records import (FILE_FORMAT, SOURCES, ExposureRecord, _Observation, _Previous,
                                                   resolve_reference)

log = logging.getLogger(__name__)


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
    ``estimator(frame, irradiance, view, pose) -> k (3,)``; each call appends an :class:`ExposureRecord` to
    :attr:`records`. Frame-to-frame estimation needs the pose the frame is fused at: ``pose``, else ``view.pose``
    (the pose the backend rendered it at), else ``frame.pose`` (ground truth); without a pose only the map is
    used.

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
        from mapping.colour import FastForward
        from radiometry.api import as_vignetting

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
        self.vignetting = as_vignetting(vignetting)
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
    def __call__(self, frame, irradiance: np.ndarray | None = None, view: Any = None,
                 pose: np.ndarray | None = None) -> np.ndarray:
        """:class:`mapping.colour.IrradianceColour`'s ``exposure`` hook: estimate, record and return the frame's
        ``k`` (3,). ``irradiance`` (the colour model's ``f^-1(I) / V``) is not used: the estimator works with its
        own response and vignetting."""
        return self.estimate(frame, view, pose=pose).k.copy()

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
            # the anchor: the first frame with enough usable pixels defines the units of the map; a black, blown
            # out or empty first frame would anchor nothing, and every later frame would then fall back
            usable = int(np.count_nonzero(obs.usable))
            if usable < self.min_correspondences:
                record.source, record.fuse_colour = "fallback", False
                record.reason = (f"no anchor yet: {usable} usable pixels (need {self.min_correspondences}); the first "
                                 "frame with enough becomes the anchor (k = 1)")
                return self._store(record)
            record.reason = "first frame: the anchor (k = 1)" if not self.records else \
                f"the anchor (k = 1): the first frame with enough usable pixels ({usable})"
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
