"""Frame-to-model tracking: coarse-to-fine projective point-to-plane ICP (KinectFusion), Open3D tensor kernels.

The tracker aligns a frame's depth (source) to the map rendered at a known pose (target: a
:class:`mapping.fusion.base.ModelView` with vertex and normal maps in that camera's frame). It knows nothing
about how the map is stored, so the TSDF and the surfel backends share it.

Per pyramid level (coarse to fine; the target maps are subsampled by 2 per level, the source depth
likewise), each iteration is one Gauss-Newton step of ``open3d.t.pipelines.odometry.
compute_odometry_result_point_to_plane``: projective association (source point -> target pixel), residual
``n . (T p - q)``, associations with ``|residual| > depth_diff`` rejected, Huber weights. Iterations stop
early when fitness and RMSE change by less than the relative tolerances (as Open3D's multi-scale loop).

Failure: the frame is rejected (``ok=False``, the caller must not fuse it) when the model shows too little
(no view, too few target pixels), the inlier fraction of the frame's valid pixels is below ``min_fitness``,
the inlier RMSE exceeds ``max_rmse``, Open3D finds no inlier at all, or the estimated motion since the last
accepted frame exceeds ``max_translation`` / ``max_rotation_deg`` per elapsed frame.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from mapping._open3d import o3d, open3d_message
from mapping.fusion.base import ModelView
from mapping.metrics import rotation_angle
from mapping.surface_maps import maps as surface_maps, vertex_map

log = logging.getLogger(__name__)

MOTION_MODELS = ("constant_velocity", "previous")


@dataclass
class TrackingResult:
    """The outcome of tracking one frame."""

    pose: np.ndarray                 # camera-to-world; the initial guess when tracking failed
    ok: bool
    reason: str = ""                 # why the frame was rejected ("" when ok)
    fitness: float = 0.0             # inlier fraction of the frame's valid depth pixels (finest level)
    inlier_rmse: float = float("inf")  # metres, point-to-plane, finest level
    iterations: int = 0
    translation: float = 0.0         # metres moved since the last accepted frame
    rotation_deg: float = 0.0        # degrees turned since the last accepted frame
    initial_pose: np.ndarray | None = field(default=None, repr=False)


def _to_tensor(array: np.ndarray):
    return o3d.core.Tensor.from_numpy(np.ascontiguousarray(array, dtype=np.float32))


def _nan_invalid(points: np.ndarray, invalid: np.ndarray) -> np.ndarray:
    """A copy with x = NaN where ``invalid`` (Open3D's kernel skips a target pixel whose vertex x or normal x
    is NaN; zeros would count as inliers with a zero residual and inflate the fitness)."""
    out = np.array(points, dtype=np.float32, copy=True)
    out[..., 0][invalid] = np.nan
    return out


def pyrdown_depth(depth: np.ndarray, diff: float) -> np.ndarray:
    """Half-resolution depth (pixel (u, v) <- (2u, 2v)): an edge-preserving 5x5 Gaussian average of the
    neighbours within ``diff`` metres of the centre (NaN where the centre has no depth). Averaging matters
    for noisy sensors: the coarse ICP levels see less noise than with plain subsampling."""
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    out = np.empty(((depth.shape[0] + 1) // 2, (depth.shape[1] + 1) // 2), np.float32)
    from mapping._native import pyrdown

    return pyrdown()(depth, np.float32(diff), out)


def scaled_intrinsics(K: np.ndarray, level: int) -> np.ndarray:
    """Intrinsics of pyramid ``level`` (images subsampled by ``2**level``, pixel (u, v) <- (2u, 2v))."""
    s = 0.5 ** level
    Kl = np.asarray(K, dtype=np.float64).copy()
    Kl[:2, :] *= s
    Kl[2] = [0.0, 0.0, 1.0]
    return Kl


def _coarse_targets(target_depth: np.ndarray, K: np.ndarray, levels: int, depth_diff: float) -> list:
    """Target vertex and normal maps of pyramid levels 1.. from a rendered depth (Open3D's recipe:
    edge-preserving downsampling; normals of the bilaterally smoothed vertex map)."""
    d = np.where(target_depth > 0, target_depth, np.float32(np.nan)).astype(np.float32)
    out = [None]
    for level in range(1, levels):
        d = pyrdown_depth(d, 2.0 * depth_diff)
        vertex, normal = surface_maps(d, scaled_intrinsics(K, level))   # Open3D's, on every core
        out.append((_to_tensor(vertex), _to_tensor(normal)))
    return out


def icp_point_to_plane(depth: np.ndarray, K: np.ndarray, target_vertex: np.ndarray, target_normal: np.ndarray,
                       init_source_to_target: np.ndarray, *, iterations: Sequence[int] = (6, 3, 1),
                       target_depth: np.ndarray | None = None,
                       depth_diff: float = 0.07, huber_delta: float = 0.05, depth_min: float = 0.1,
                       depth_max: float = 3.0, relative_fitness: float = 1e-6, relative_rmse: float = 1e-6
                       ) -> tuple[np.ndarray, float, float, int]:
    """Coarse-to-fine projective point-to-plane ICP of a depth map against vertex/normal maps.

    depth:           (H, W) float32 metres of the source (0 = invalid).
    target_vertex:   (H, W, 3) float32 target points in the target camera frame, NaN (x) where none.
    target_normal:   (H, W, 3) float32 target normals (the sign does not matter).
    target_depth:    the target's depth (H, W), 0 where none: coarser levels are built from it (edge-preserving
                     downsampling, smoothed normals); without it they subsample the vertex and normal maps.
    init_source_to_target: (4, 4) initial transform (source camera -> target camera).
    iterations:      Gauss-Newton steps per level, coarsest first (``len`` = number of levels).

    Returns ``(T (4, 4) float64, inlier count at the finest level, inlier RMSE metres, iterations run)``.
    Raises ``RuntimeError`` when a step finds no inlier at all.
    """
    levels = len(iterations)
    if levels < 1 or any(int(i) < 0 for i in iterations):
        raise ValueError(f"iterations must list non-negative counts per level, got {iterations}")
    src = np.where((depth > depth_min) & (depth < depth_max), depth, np.float32(np.nan)).astype(np.float32)
    tv, tn = _to_tensor(target_vertex), _to_tensor(target_normal)
    coarse = _coarse_targets(target_depth, K, levels, depth_diff) if target_depth is not None else None
    pyramid = []
    for level in range(levels):
        step = 2 ** level
        Kl = scaled_intrinsics(K, level)
        if level == 0:
            tgt_v, tgt_n = tv, tn
        else:
            src = pyrdown_depth(src, 2.0 * depth_diff)
            if coarse is not None:
                tgt_v, tgt_n = coarse[level]
            else:
                tgt_v, tgt_n = tv[::step, ::step].contiguous(), tn[::step, ::step].contiguous()
        pyramid.append((_to_tensor(vertex_map(src, Kl)), tgt_v, tgt_n, o3d.core.Tensor(Kl)))

    T = o3d.core.Tensor(np.asarray(init_source_to_target, dtype=np.float64))
    fitness, rmse2 = 1.0, 0.0
    inliers, n_iter = 0, 0
    odometry = o3d.t.pipelines.odometry
    for level in reversed(range(levels)):
        src_v, tgt_v, tgt_n, Kt = pyramid[level]
        rows, cols = int(src_v.shape[0]), int(src_v.shape[1])
        for _ in range(int(iterations[levels - 1 - level])):
            result = odometry.compute_odometry_result_point_to_plane(src_v, tgt_v, tgt_n, Kt, T, depth_diff,
                                                                     huber_delta)
            T = result.transformation @ T
            n_iter += 1
            new_fit, new_rmse2 = float(result.fitness), float(result.inlier_rmse)
            inliers = int(round(new_fit * rows * cols))
            converged = (abs(fitness - new_fit) / max(fitness, 1e-12) < relative_fitness
                         and abs(rmse2 - new_rmse2) / max(rmse2, 1e-12) < relative_rmse)
            fitness, rmse2 = new_fit, new_rmse2
            if converged:
                break
    return T.numpy().astype(np.float64), inliers, float(np.sqrt(max(rmse2, 0.0))), n_iter


class FrameToModelTracker:
    """Tracks frames against the map rendered at the last accepted pose; keeps the motion model's state.

    >>> tracker = FrameToModelTracker()                       # doctest: +SKIP
    >>> tracker.start(first_pose)
    >>> result = tracker.track(frame.depth, frame.K, view, view_pose)
    >>> if result.ok: fuse at result.pose
    """

    name = "icp"
    needs_colour = False   # whether track() needs the frame's colour (the pipeline passes it then)

    def __init__(self, *, iterations: Sequence[int] = (6, 3, 1), depth_diff: float = 0.07,
                 huber_delta: float = 0.05, depth_min: float = 0.1, depth_max: float = 3.0,
                 motion_model: str = "constant_velocity", min_fitness: float = 0.25, max_rmse: float = 0.03,
                 max_translation: float = 0.3, max_rotation_deg: float = 30.0, min_view_pixels: int = 1000) -> None:
        if motion_model not in MOTION_MODELS:
            raise ValueError(f"motion_model must be one of {', '.join(MOTION_MODELS)}, got {motion_model!r}")
        for name, value in (("depth_diff", depth_diff), ("huber_delta", huber_delta), ("depth_max", depth_max),
                            ("max_translation", max_translation), ("max_rotation_deg", max_rotation_deg),
                            ("max_rmse", max_rmse)):
            if not (value > 0 and np.isfinite(value)):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if not 0 <= min_fitness < 1:
            raise ValueError(f"min_fitness must be in [0, 1), got {min_fitness}")
        self.iterations = tuple(int(i) for i in iterations)
        self.depth_diff = float(depth_diff)
        self.huber_delta = float(huber_delta)
        self.depth_min = float(depth_min)
        self.depth_max = float(depth_max)
        self.motion_model = motion_model
        self.min_fitness = float(min_fitness)
        self.max_rmse = float(max_rmse)
        self.max_translation = float(max_translation)
        self.max_rotation_deg = float(max_rotation_deg)
        self.min_view_pixels = int(min_view_pixels)
        self._last: np.ndarray | None = None       # last accepted pose
        self._velocity = np.eye(4)                 # last accepted inter-frame motion (per frame)
        self._elapsed = 1                          # frames since the last accepted one

    # ---------------------------------------------------------------- state
    def start(self, pose: np.ndarray) -> None:
        """Set the first frame's pose (the map's origin)."""
        self._last = np.asarray(pose, dtype=np.float64).copy()
        self._velocity = np.eye(4)
        self._elapsed = 1

    @property
    def last_pose(self) -> np.ndarray | None:
        return None if self._last is None else self._last.copy()

    def predict(self) -> np.ndarray:
        """The initial guess for the next frame: the last pose, advanced by the last velocity per elapsed frame
        under the constant-velocity model."""
        if self._last is None:
            raise RuntimeError("call start(pose) before tracking")
        if self.motion_model == "previous":
            return self._last.copy()
        step = np.linalg.matrix_power(self._velocity, self._elapsed) if self._elapsed > 1 else self._velocity
        return self._last @ step

    def _accept(self, pose: np.ndarray) -> None:
        motion = np.linalg.inv(self._last) @ pose
        if self._elapsed > 1:  # average motion per frame over a gap (small-motion approximation)
            motion = _fractional_motion(motion, 1.0 / self._elapsed)
        self._velocity = motion
        self._last = pose.copy()
        self._elapsed = 1

    def skip(self) -> None:
        """Count a frame that was not tracked (e.g. no depth): the next prediction spans one more frame."""
        self._elapsed += 1

    # ---------------------------------------------------------------- tracking
    def track(self, depth: np.ndarray, K: np.ndarray, view: ModelView | None, view_pose: np.ndarray,
              colour=None) -> TrackingResult:
        """Align ``depth`` to ``view`` (the map rendered at ``view_pose``); update the state when accepted.
        ``colour``: the frame's colour in map units (a :class:`mapping.tracking_photometric.TrackingColour`) for
        the trackers whose :attr:`needs_colour` is True; point-to-plane ICP uses depth only."""
        init = self.predict()
        result = self.align(depth, K, view, view_pose, init, colour=colour)
        if result.ok:
            self._accept(result.pose)
        else:
            self._elapsed += 1
        return result

    def align(self, depth: np.ndarray, K: np.ndarray, view: ModelView | None, view_pose: np.ndarray,
              init: np.ndarray, *, colour=None) -> TrackingResult:
        """One alignment from the initial pose ``init`` (camera-to-world) under the failure rules, without
        changing the motion model's state (:meth:`start` must have been called: the motion limits count from
        the last accepted pose; a photometric tracker keeps the exposure it estimates). :meth:`track` is this from :meth:`predict`; the tracking study calls it from
        perturbed poses."""
        init = np.asarray(init, dtype=np.float64)
        result = self._track(depth, K, view, view_pose, init, colour)
        result.initial_pose = init
        return result

    def _target(self, depth, view, init) -> tuple[TrackingResult | None, np.ndarray | None, int]:
        """The checks before any alignment: a failed result (or None), the target's invalid pixels and the
        frame's valid depth pixels."""
        if view is None or view.vertex is None or view.normal is None:
            return TrackingResult(init, False, "no model view (the map is empty here)"), None, 0
        n = view.normal
        invalid_t = (view.depth <= 0) | ((n[..., 0] == 0) & (n[..., 1] == 0) & (n[..., 2] == 0))
        n_target = invalid_t.size - int(np.count_nonzero(invalid_t))
        if n_target < self.min_view_pixels:
            return TrackingResult(init, False, f"too little of the map in view ({n_target} pixels)"), None, 0
        valid_s = (depth > self.depth_min) & (depth < self.depth_max)
        n_source = int(np.count_nonzero(valid_s))
        if n_source < self.min_view_pixels:
            return TrackingResult(init, False, f"too few valid depth pixels ({n_source})"), None, 0
        return None, invalid_t, n_source

    def _track(self, depth, K, view, view_pose, init, colour) -> TrackingResult:
        failed, invalid_t, n_source = self._target(depth, view, init)
        if failed is not None:
            return failed
        view_pose = np.asarray(view_pose, dtype=np.float64)
        T0 = np.linalg.inv(view_pose) @ init
        try:
            T, inliers, rmse, iters = icp_point_to_plane(
                depth, K, _nan_invalid(view.vertex, invalid_t), np.ascontiguousarray(view.normal, np.float32), T0,
                iterations=self.iterations, depth_diff=self.depth_diff, huber_delta=self.huber_delta,
                depth_min=self.depth_min, depth_max=self.depth_max,
                target_depth=view.depth)
        except RuntimeError as exc:  # Open3D raises when a step has no inlier
            return TrackingResult(init, False, f"ICP found no correspondences ({open3d_message(exc)[:80]})")
        return self._judge(view_pose @ T, init, inliers / n_source, rmse, iters)

    def _judge(self, pose: np.ndarray, init: np.ndarray, fitness: float, rmse: float, iters: int) -> TrackingResult:
        """The failure rules on an alignment's pose, point-to-plane fitness and inlier RMSE (module doc)."""
        motion = np.linalg.inv(self._last) @ pose
        trans = float(np.linalg.norm(motion[:3, 3]))
        rot = float(np.degrees(rotation_angle(motion[:3, :3])))
        out = TrackingResult(pose, True, "", fitness, rmse, iters, trans, rot)
        gap = self._elapsed
        if not np.all(np.isfinite(pose)):
            out.ok, out.reason, out.pose = False, "ICP diverged (non-finite pose)", init
        elif fitness < self.min_fitness:
            out.ok, out.reason = False, f"fitness {fitness:.2f} < {self.min_fitness:g}"
        elif rmse > self.max_rmse:
            out.ok, out.reason = False, f"inlier RMSE {rmse * 100:.1f} cm > {self.max_rmse * 100:g} cm"
        elif trans > self.max_translation * gap:
            out.ok, out.reason = False, f"implausible motion {trans:.2f} m > {self.max_translation * gap:g} m"
        elif rot > self.max_rotation_deg * gap:
            out.ok, out.reason = False, f"implausible rotation {rot:.1f} deg > {self.max_rotation_deg * gap:g} deg"
        if not out.ok:
            out.pose = init
        return out


def _fractional_motion(T: np.ndarray, fraction: float) -> np.ndarray:
    """``T ** fraction`` for a rigid motion (axis-angle scaling of the rotation, linear translation)."""
    R = T[:3, :3]
    angle = float(rotation_angle(R))
    out = np.eye(4)
    if angle < 1e-9:
        out[:3, :3] = np.eye(3)
    else:
        axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]]) / (2 * np.sin(angle))
        a = angle * fraction
        Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
        out[:3, :3] = np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx
    out[:3, 3] = T[:3, 3] * fraction
    return out
