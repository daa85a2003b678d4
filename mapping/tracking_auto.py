"""The default tracker (``--tracker auto``): point-to-plane ICP, and a photometric tracker (Open3D's coloured ICP)
for the frames where geometry alone cannot fix the pose.

Point-to-plane ICP constrains only the motions that change the distance of surface points to their planes. A
frame that sees one wall (or a wall and a floor, a desk top) leaves directions free: its 6 x 6 Gauss-Newton
system is ill-conditioned or singular (Open3D: "Singular 6x6 linear system detected"), the pose slides along
the plane and the frame is lost or, worse, accepted at the wrong place. Per frame:

1. point-to-plane ICP (:class:`mapping.tracking.FrameToModelTracker`) from the motion model's prediction;
2. the conditioning of its system at the pose it found (:func:`icp_condition`: the 6 x 6 ``J^T J`` of the
   point-to-plane association, with the points centred and scaled to unit RMS radius so that the number does
   not depend on the scene's size or units; ``lambda_max / lambda_min``);
3. when ICP failed (an exception, a singular system, or its result failed the rules) or the condition number
   exceeds ``max_condition``, the ``fallback`` (coloured ICP, :class:`mapping.tracking_photometric.ColouredICPTracker`:
   depth and the colour the map holds; or hybrid odometry) from the same prediction; its pose is taken when it passes
   the same failure rules (judged by the point-to-plane association, as every tracker's), else ICP's result
   stands (a failure with both reasons when ICP failed too).

Optional (``photometric_margin``, off by default): ICP's pose is also doubted when the frame's colours agree less
with the map there than at the prediction by more than that fraction (:func:`photometric_error`), and the
fallback's pose taken when its colours agree better. Measured (with hybrid odometry as the fallback), it sent
18-44 % of the frames of the kitchen and the lamp shade to the fallback and made the kitchen's ATE worse (1.14
against 1.09 cm): off.

``max_condition`` and ``fallback`` were chosen by measurement on real recordings (docs/tracking.md,
``scripts/bench_tracking.py``). ``stats()`` counts the frames each method tracked (metrics.json ``tracking``).
"""

from __future__ import annotations

import logging

import numpy as np

from mapping.tracking import FrameToModelTracker, TrackingResult
from mapping.tracking_photometric import (ColouredICPTracker, HybridTracker, _PhotometricTracker, luminance,
                                          point_to_plane_association)

log = logging.getLogger(__name__)

#: condition number of the normalised point-to-plane system above which coloured ICP is tried (docs/tracking.md)
MAX_CONDITION = 100.0
#: the condition number is measured on every CONDITION_STEP-th pixel of every CONDITION_STEP-th row (a lamp-shade
#: frame: 8.09 against 8.11 on every pixel, 20 ms against 185 ms)
CONDITION_STEP = 3
#: the photometric tracker of step 3 (docs/tracking.md)
FALLBACK = "coloured-icp"


def photometric_error(intensity: np.ndarray, depth: np.ndarray, K: np.ndarray, view, view_intensity: np.ndarray,
                      T: np.ndarray, *, step: int = 4, depth_tol: float = 0.03, min_pixels: int = 200) -> float:
    """Mean absolute intensity difference between the frame's pixels (every ``step``-th, with depth) and the view's
    pixels they land on when moved by ``T`` (frame camera -> view camera), where the depths agree within
    ``max(depth_tol, depth_tol * z)``; inf with fewer than ``min_pixels`` such pixels. Compared between poses of
    one frame against one view, a common exposure factor cancels out of the comparison's direction."""
    rows, cols = depth.shape
    v, u = np.mgrid[0:rows:step, 0:cols:step]
    z = depth[v, u].astype(np.float64)
    keep = z > 0
    u, v, z = u[keep], v[keep], z[keep]
    p = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
    q = T[:3, :3] @ p + T[:3, 3:4]
    front = q[2] > 1e-6
    q, u, v = q[:, front], u[front], v[front]
    ui = np.rint(K[0, 0] * q[0] / q[2] + K[0, 2]).astype(np.int64)
    vi = np.rint(K[1, 1] * q[1] / q[2] + K[1, 2]).astype(np.int64)
    inside = (ui >= 0) & (ui < cols) & (vi >= 0) & (vi < rows)
    q, u, v, ui, vi = q[:, inside], u[inside], v[inside], ui[inside], vi[inside]
    dv = view.depth[vi, ui]
    agree = (dv > 0) & (np.abs(dv - q[2]) < np.maximum(depth_tol, depth_tol * q[2]))
    if np.count_nonzero(agree) < min_pixels:
        return float("inf")
    return float(np.mean(np.abs(intensity[v[agree], u[agree]] - view_intensity[vi[agree], ui[agree]])))


def icp_condition(q: np.ndarray, normals: np.ndarray, *, max_points: int = 20000) -> float:
    """Condition number (``lambda_max / lambda_min``) of the point-to-plane Gauss-Newton matrix ``J^T J / M``
    of points ``q`` (3, M) on planes with ``normals`` (M, 3): rows ``[(q - c) / L x n, n]``, ``c`` the centroid
    and ``L`` the RMS distance to it. inf for fewer than 6 points or a singular matrix."""
    q = np.asarray(q, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if q.shape[1] < 6:
        return float("inf")
    step = max(1, q.shape[1] // max_points)
    p = q[:, ::step].T
    n = n[::step]
    norm = np.linalg.norm(n, axis=1, keepdims=True)
    p, n = p[norm[:, 0] > 0], n[norm[:, 0] > 0] / norm[norm[:, 0] > 0]
    if len(p) < 6:
        return float("inf")
    d = p - p.mean(axis=0)
    scale = np.sqrt(np.mean(np.sum(d * d, axis=1)))
    if not scale > 0:
        return float("inf")
    J = np.hstack([np.cross(d / scale, n), n])
    eig = np.linalg.eigvalsh(J.T @ J / len(J))
    return float(eig[-1] / eig[0]) if eig[0] > eig[-1] * 1e-15 else float("inf")


#: the photometric trackers the auto tracker may fall back to
FALLBACKS = {"hybrid": HybridTracker, "coloured-icp": ColouredICPTracker}


class AutoTracker(_PhotometricTracker):
    """Point-to-plane ICP with a photometric tracker (``fallback``: hybrid or coloured ICP) for ill-conditioned or
    failed frames (module doc); ``max_condition``: the threshold of step 3; other options as
    :class:`~mapping.tracking.FrameToModelTracker`'s."""

    name = "auto"

    def __init__(self, *, max_condition: float = MAX_CONDITION, fallback: str = FALLBACK,
                 photometric_margin: float | None = None, **options) -> None:
        super().__init__(**options)
        if not (max_condition > 1 and np.isfinite(max_condition)):
            raise ValueError(f"max_condition must be a finite number > 1, got {max_condition}")
        if fallback not in FALLBACKS:
            raise ValueError(f"fallback must be one of {', '.join(FALLBACKS)}, got {fallback!r}")
        if photometric_margin is not None and not (photometric_margin >= 0 and np.isfinite(photometric_margin)):
            raise ValueError(f"photometric_margin must be a number >= 0, got {photometric_margin}")
        self.max_condition = float(max_condition)
        self.photometric_margin = None if photometric_margin is None else float(photometric_margin)
        self.photometric_doubts = 0     # frames where ICP's pose made the colours agree less than the prediction
        self.fallback = fallback
        self._photometric = FALLBACKS[fallback](**options)   # only its alignment is used (the state is ours)
        self.counts = {"icp": 0, fallback: 0, "failed": 0}
        self.ill_conditioned = 0        # frames whose ICP system exceeded max_condition (or was singular)
        self.condition = float("nan")   # the last frame's condition number

    def start(self, pose: np.ndarray) -> None:
        super().start(pose)
        self.counts = {"icp": 0, self.fallback: 0, "failed": 0}
        self.ill_conditioned = 0
        self.photometric_doubts = 0

    def _photometric_intensity(self, colour) -> np.ndarray:
        """The frame's intensity at the map's exposure as last estimated (no new estimate)."""
        c = colour.colour / self.exposure.astype(np.float32) if colour.estimate_exposure else colour.colour
        return luminance(c, colour.scale)

    def _align(self, *args):
        return self._photometric._align(*args)

    def stats(self) -> dict:
        """Frames tracked by each method (metrics.json ``tracking``)."""
        return {"tracker": self.name, "frames_by_method": dict(self.counts), "ill_conditioned": self.ill_conditioned,
                "photometric_doubts": self.photometric_doubts,
                "max_condition": self.max_condition, "fallback": self.fallback}

    def _track(self, depth, K, view, view_pose, init, colour) -> TrackingResult:
        failed, invalid_t, _ = self._target(depth, view, init)
        if failed is not None:    # no map in view, too little depth: nothing to align
            self.counts["failed"] += 1
            return failed
        icp = FrameToModelTracker._track(self, depth, K, view, view_pose, init, None)
        T = np.linalg.inv(np.asarray(view_pose, dtype=np.float64)) @ (icp.pose if icp.ok else init)
        # every 3rd pixel of every 3rd row: the same number at a tenth of the cost
        q, normals, r = point_to_plane_association(depth, K, view, invalid_t, T, depth_min=self.depth_min,
                                                   depth_max=self.depth_max, step=CONDITION_STEP)
        inl = np.abs(r) <= self.depth_diff
        self.condition = icp_condition(q[:, inl], normals[inl])
        ill = not self.condition <= self.max_condition
        self.ill_conditioned += int(ill)
        if colour is None:
            raise ValueError("the auto tracker needs the frame's colour (colour=tracking_colour(...))")
        worse = False
        if self.photometric_margin is not None and icp.ok and not ill:
            # the colours judge ICP's move: sliding along a plane makes them agree less than at the prediction
            intensity = self._photometric_intensity(colour)
            target = luminance(view.colour, colour.scale)
            inv_view = np.linalg.inv(np.asarray(view_pose, dtype=np.float64))

            def colour_error(pose):
                return photometric_error(intensity, depth, K, view, target, inv_view @ pose)

            e_icp = colour_error(icp.pose)
            worse = e_icp > colour_error(init) * (1.0 + self.photometric_margin)
            self.photometric_doubts += int(worse)
        if icp.ok and not ill and not worse:
            self.counts["icp"] += 1
            return icp
        coloured = _PhotometricTracker._track(self, depth, K, view, view_pose, init, colour)
        log.debug("ICP %s (condition %.3g%s): %s %s", "ok" if icp.ok else icp.reason, self.condition,
                  ", colours agree less than at the prediction" if worse else "", self.fallback,
                  "ok" if coloured.ok else coloured.reason)
        if coloured.ok and (not worse or colour_error(coloured.pose) <= e_icp):
            self.counts[self.fallback] += 1
            return coloured
        if icp.ok:
            self.counts["icp"] += 1
            return icp
        self.counts["failed"] += 1
        icp.reason = f"{icp.reason}; {self.fallback}: {coloured.reason}"
        return icp


__all__ = ["AutoTracker", "MAX_CONDITION", "icp_condition"]
