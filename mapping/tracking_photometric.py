"""Photometric frame-to-model tracking on the colour the map holds: Open3D's hybrid RGB-D odometry (depth +
intensity) and coloured ICP (Park, Zhou and Koltun, ICCV 2017), beside point-to-plane ICP
(:mod:`mapping.tracking`).

Both align the frame to the map rendered at the last accepted pose (a :class:`mapping.fusion.base.ModelView`:
depth, colour in map units, vertex, normal), as point-to-plane ICP does, and share its state (motion model)
and failure rules: the fitness and inlier RMSE judged are those of the point-to-plane association at the final
pose (:func:`point_to_plane_fit`), so that "failed" means the same for every tracker.

The frame's colour (:func:`tracking_colour`) is in the map's units: raw levels without a response; with one,
irradiance ``f^-1(I) / V``, divided by the frame's exposure ``k`` when the map is exposure-compensated. The
map's ``k`` comes from :class:`mapping.exposure_compensation.ExposureEstimator` AFTER tracking (it needs the
pose); the tracker needs it BEFORE, so it estimates its own (:func:`estimate_exposure`): the per-channel
median ratio of 5 x 5 local means of the frame's irradiance and of the map's colour, at the frame's pixels
re-projected through their depth from the PREDICTED pose into the view, where depths agree. Estimating before
tracking (not jointly) keeps the photometric cost that of Open3D's kernels (they have no gain term); the
prediction is a few pixels off at most under the motion limits, which the 5 x 5 means and the median absorb
(the estimate is a gain, not a pose). When too few pixels agree, the last estimate is kept.

Intensity is the fixed luminance ``0.299 R + 0.587 G + 0.114 B`` of the map-unit colour times a fixed scale
that puts white at 1 (``1/255`` for raw levels, ``1 / f^-1(255)`` for irradiance), the range Open3D's kernels
and their default Huber deltas (intensity 0.1) are made for. Vignetting-corrected irradiance exceeds 1 in
the image corners, which the kernels do not mind.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from mapping._open3d import o3d, open3d_message
from mapping.tracking import (FrameToModelTracker, TrackingResult, _to_tensor, pyrdown_depth,
                              scaled_intrinsics)

log = logging.getLogger(__name__)

_NAN = float("nan")
LUMINANCE = np.array([0.299, 0.587, 0.114], dtype=np.float32)


@dataclass
class TrackingColour:
    """A frame's colour for tracking.

    colour:            (H, W, 3) float32 in map units, BEFORE any exposure division.
    scale:             intensity = luminance(colour / k) * scale (white at about 1).
    estimate_exposure: the map is exposure-compensated: the tracker divides by its own estimate of ``k``.
    usable:            (H, W) bool, pixels neither clipped nor black (the exposure estimate uses only these).
    """

    colour: np.ndarray
    scale: float
    estimate_exposure: bool
    usable: np.ndarray


def tracking_colour(colour_model, rgb: np.ndarray) -> TrackingColour:
    """The frame's colour in the units ``colour_model`` fuses, before any exposure division
    (:meth:`mapping.colour.ColourModel.unexposed`), with the pixels the exposure estimate may use (those
    :func:`mapping.exposure_compensation.masks.clipped_pixels` keeps, as the map's exposure estimate does)."""
    from mapping.exposure_compensation.masks import clipped_pixels

    rgb = np.asarray(rgb)
    usable = ~clipped_pixels(rgb)
    colour, white, estimate_exposure = colour_model.unexposed(rgb)
    return TrackingColour(colour, 1.0 / white, estimate_exposure, usable)


def luminance(colour: np.ndarray, scale: float) -> np.ndarray:
    """``(H, W, 3)`` colour -> ``(H, W)`` float32 intensity ``scale * (0.299 R + 0.587 G + 0.114 B)``."""
    return (np.asarray(colour, np.float32) @ (LUMINANCE * np.float32(scale))).astype(np.float32)


def _local_means(colour: np.ndarray, mask: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of ``colour`` over ``(2 r + 1)^2`` windows whose pixels are all in ``mask``, and where they are."""
    import cv2

    size = (2 * radius + 1, 2 * radius + 1)
    m = mask.astype(np.float32)
    count = cv2.boxFilter(m, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    sums = cv2.boxFilter(colour * m[..., None], -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT)
    full = count >= size[0] * size[1] - 0.5
    return sums / np.maximum(count, 1.0)[..., None], full


def estimate_exposure(colour: np.ndarray, usable: np.ndarray, depth: np.ndarray, K: np.ndarray, view,
                      frame_to_view: np.ndarray, *, radius: int = 2, step: int = 2, min_pixels: int = 200,
                      depth_tol: float = 0.03) -> np.ndarray | None:
    """The frame's exposure relative to the map's colour, ``k`` (3,), or None with fewer than ``min_pixels``
    agreeing pixels: the per-channel median of ``frame mean / map mean`` (local means, see module doc) at the
    frame's pixels (every ``step``-th) re-projected by ``frame_to_view`` (frame camera -> view camera) into the
    view, where the view's depth agrees within ``max(depth_tol, depth_tol * z)``."""
    f_mean, f_ok = _local_means(colour, usable & (depth > 0), radius)
    v_mean, v_ok = _local_means(np.asarray(view.colour, np.float32), view.depth > 0, radius)
    rows, cols = depth.shape
    v, u = np.mgrid[0:rows:step, 0:cols:step]
    z = depth[v, u]
    keep = f_ok[v, u] & (z > 0)
    u, v, z = u[keep], v[keep], z[keep]
    Kinv = np.linalg.inv(K)
    p = (Kinv @ np.stack([u * z, v * z, z]).astype(np.float64))
    q = frame_to_view[:3, :3] @ p + frame_to_view[:3, 3:4]
    front = q[2] > 1e-6
    uv = (K @ q[:, front])
    ui = np.rint(uv[0] / uv[2]).astype(np.int64)
    vi = np.rint(uv[1] / uv[2]).astype(np.int64)
    zq = q[2, front]
    inside = (ui >= 0) & (ui < view.depth.shape[1]) & (vi >= 0) & (vi < view.depth.shape[0])
    src = np.flatnonzero(front)[inside]
    ui, vi, zq = ui[inside], vi[inside], zq[inside]
    dv = view.depth[vi, ui]
    agree = v_ok[vi, ui] & (np.abs(dv - zq) < np.maximum(depth_tol, depth_tol * zq))
    if np.count_nonzero(agree) < min_pixels:
        return None
    a = f_mean[v[src[agree]], u[src[agree]]]
    b = v_mean[vi[agree], ui[agree]]
    good = np.all(b > 1e-6, axis=1) & np.all(a > 1e-6, axis=1)
    if np.count_nonzero(good) < min_pixels:
        return None
    k = np.median(a[good] / b[good], axis=0)
    return k if np.all(np.isfinite(k)) and np.all(k > 0) else None


class _PhotometricTracker(FrameToModelTracker):
    """What both photometric trackers share: the frame's intensity at the map's exposure and the judgement of
    the result by the point-to-plane association (module doc)."""

    needs_colour = True

    def __init__(self, *, intensity_huber_delta: float = 0.1, **options) -> None:
        super().__init__(**options)
        if not (intensity_huber_delta > 0 and np.isfinite(intensity_huber_delta)):
            raise ValueError(f"intensity_huber_delta must be a positive number, got {intensity_huber_delta}")
        self.intensity_huber_delta = float(intensity_huber_delta)
        self.exposure = np.ones(3)       # the last estimate of the frame's k against the map (first frame = 1)
        self.exposure_fallbacks = 0      # frames tracked with the previous estimate (too few agreeing pixels)

    def start(self, pose: np.ndarray) -> None:
        super().start(pose)
        self.exposure = np.ones(3)
        self.exposure_fallbacks = 0

    def _intensity(self, colour: TrackingColour, depth, K, view, T0) -> np.ndarray:
        c = colour.colour
        if colour.estimate_exposure:
            k = estimate_exposure(c, colour.usable, depth, K, view, T0)
            if k is None:
                self.exposure_fallbacks += 1
                log.debug("too few pixels agree with the map for an exposure estimate; keeping k = %s", self.exposure)
            else:
                self.exposure = k
            c = c / self.exposure.astype(np.float32)
        return luminance(c, colour.scale)

    def _track(self, depth, K, view, view_pose, init, colour) -> TrackingResult:
        if colour is None:
            raise ValueError(f"the {self.name} tracker needs the frame's colour (colour=tracking_colour(...))")
        failed, invalid_t, n_source = self._target(depth, view, init)
        if failed is not None:
            return failed
        view_pose = np.asarray(view_pose, dtype=np.float64)
        T0 = np.linalg.inv(view_pose) @ init
        intensity = self._intensity(colour, depth, K, view, T0)
        target_intensity = luminance(view.colour, colour.scale)
        try:
            T, iters = self._align(depth, intensity, K, view, invalid_t, target_intensity, T0)
        except RuntimeError as exc:  # Open3D raises when a step has no inlier or a singular system
            return TrackingResult(init, False, f"{self.name} found no correspondences ({open3d_message(exc)[:80]})")
        inliers, rmse = point_to_plane_fit(depth, K, view, invalid_t, T, depth_min=self.depth_min,
                                           depth_max=self.depth_max, depth_diff=self.depth_diff)
        return self._judge(view_pose @ T, init, inliers / n_source, rmse, iters)


def point_to_plane_fit(depth: np.ndarray, K: np.ndarray, view, invalid_t: np.ndarray, T: np.ndarray, *,
                       depth_min: float, depth_max: float, depth_diff: float) -> tuple[int, float]:
    """Inlier count and inlier RMSE (metres) of the projective point-to-plane association of ``depth`` moved by
    ``T`` (frame camera -> view camera) against ``view``: what point-to-plane ICP judges at its finest level
    (inlier: ``|n . (T p - q)| <= depth_diff``), evaluated without solving a step (a single plane would make
    that step singular)."""
    q, n, r = point_to_plane_association(depth, K, view, invalid_t, T, depth_min=depth_min, depth_max=depth_max)
    inl = np.abs(r) <= depth_diff
    count = int(np.count_nonzero(inl))
    return count, float(np.sqrt(np.mean(r[inl] ** 2))) if count else float("inf")


def point_to_plane_association(depth: np.ndarray, K: np.ndarray, view, invalid_t: np.ndarray, T: np.ndarray, *,
                               depth_min: float, depth_max: float,
                               step: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The projective association of ``depth`` moved by ``T`` against ``view``: the moved points ``(3, M)`` (view
    camera), the target normals ``(M, 3)`` they meet and the point-to-plane residuals ``(M,)``. ``step``: only
    every ``step``-th pixel of every ``step``-th row (from 0) of ``depth`` (the same points, in the same order, as
    a full-size image holding only those pixels)."""
    grid = depth[::step, ::step] if step > 1 else depth
    valid = (grid > depth_min) & (grid < depth_max)
    v, u = np.nonzero(valid)
    z = grid[v, u].astype(np.float64)
    if step > 1:
        v, u = v * step, u * step
    p = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z])
    q = T[:3, :3] @ p + T[:3, 3:4]
    front = q[2] > 1e-6
    q = q[:, front]
    ui = np.rint(K[0, 0] * q[0] / q[2] + K[0, 2]).astype(np.int64)
    vi = np.rint(K[1, 1] * q[1] / q[2] + K[1, 2]).astype(np.int64)
    inside = (ui >= 0) & (ui < depth.shape[1]) & (vi >= 0) & (vi < depth.shape[0])
    q, ui, vi = q[:, inside], ui[inside], vi[inside]
    keep = ~invalid_t[vi, ui]
    q, ui, vi = q[:, keep], ui[keep], vi[keep]
    normals = view.normal[vi, ui].astype(np.float64)
    r = np.einsum("ij,ji->i", normals, q - view.vertex[vi, ui].T.astype(np.float64))
    return q, normals, r


class HybridTracker(_PhotometricTracker):
    """Open3D's hybrid RGB-D odometry (depth + intensity; ``compute_odometry_result_hybrid``, as
    ``rgbd_odometry_multi_scale`` with ``Method.Hybrid``), frame to model: coarse to fine against the view's
    depth and intensity. The view's holes are filled in the intensity image (normalised Gaussian) so that its
    Sobel gradients do not see the map's silhouette as an edge; its depth keeps them (NaN)."""

    name = "hybrid"

    def _align(self, depth, intensity, K, view, invalid_t, target_intensity, T0):
        return hybrid_odometry(depth, intensity, K, np.where(invalid_t, 0, view.depth).astype(np.float32),
                               fill_holes(target_intensity, ~invalid_t), T0, iterations=self.iterations,
                               depth_diff=self.depth_diff, depth_huber_delta=self.huber_delta,
                               intensity_huber_delta=self.intensity_huber_delta, depth_min=self.depth_min,
                               depth_max=self.depth_max)


class ColouredICPTracker(_PhotometricTracker):
    """Open3D's coloured ICP (``registration.multi_scale_icp`` with ``TransformationEstimationForColoredICP``),
    frame to model: the frame's points with their intensity (as grey colour) against the view's points with
    normals and intensity (every ``pixel_step``-th pixel of each), at ``voxel_sizes`` (coarse to fine) with
    correspondences up to ``2, 1, 0.5 x depth_diff``."""

    name = "coloured-icp"

    def __init__(self, *, voxel_sizes: Sequence[float] = (0.08, 0.04, 0.02),
                 icp_iterations: Sequence[int] = (15, 8, 4), pixel_step: int = 2, **options) -> None:
        super().__init__(**options)
        if len(voxel_sizes) != len(icp_iterations) or list(voxel_sizes) != sorted(voxel_sizes, reverse=True) \
                or min(voxel_sizes) <= 0:
            raise ValueError(f"voxel_sizes must decrease, be positive and match icp_iterations, got {voxel_sizes} "
                             f"and {icp_iterations}")
        self.voxel_sizes = tuple(float(v) for v in voxel_sizes)
        self.icp_iterations = tuple(int(i) for i in icp_iterations)
        if not (isinstance(pixel_step, int) and pixel_step >= 1):
            raise ValueError(f"pixel_step must be a whole number >= 1, got {pixel_step!r}")
        self.pixel_step = pixel_step

    def _align(self, depth, intensity, K, view, invalid_t, target_intensity, T0):
        reg = o3d.t.pipelines.registration
        sub = np.zeros(depth.shape, bool)
        sub[::self.pixel_step, ::self.pixel_step] = True
        valid = (depth > self.depth_min) & (depth < self.depth_max) & sub
        v, u = np.nonzero(valid)
        z = depth[v, u].astype(np.float64)
        pts = np.stack([(u - K[0, 2]) * z / K[0, 0], (v - K[1, 2]) * z / K[1, 1], z], axis=1)
        source = _cloud(pts, intensity[v, u])
        tv = ~invalid_t & sub
        target = _cloud(view.vertex[tv], target_intensity[tv])
        target.point.normals = _to_tensor(view.normal[tv])
        n = len(self.voxel_sizes)
        dists = [self.depth_diff * f for f in (2.0, 1.0, 0.5)[:n]] + [self.depth_diff * 0.5] * max(0, n - 3)
        criteria = [reg.ICPConvergenceCriteria(relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=i)
                    for i in self.icp_iterations]
        result = reg.multi_scale_icp(source, target, o3d.utility.DoubleVector(list(self.voxel_sizes)), criteria,
                                     o3d.utility.DoubleVector(dists), o3d.core.Tensor(T0),
                                     reg.TransformationEstimationForColoredICP())
        return result.transformation.numpy().astype(np.float64), int(result.num_iterations)


def _cloud(points: np.ndarray, intensity: np.ndarray):
    cloud = o3d.t.geometry.PointCloud(_to_tensor(points))
    cloud.point.colors = _to_tensor(np.repeat(np.asarray(intensity, np.float32)[:, None], 3, axis=1))
    return cloud


def fill_holes(image: np.ndarray, valid: np.ndarray, *, sigma: float = 4.0) -> np.ndarray:
    """``image`` with pixels outside ``valid`` replaced by a normalised Gaussian average of the valid ones (the
    valid mean where none is near)."""
    import cv2

    if valid.all():
        return np.ascontiguousarray(image, np.float32)
    m = valid.astype(np.float32)
    num = cv2.GaussianBlur(np.where(valid, image, 0).astype(np.float32), (0, 0), sigma)
    den = cv2.GaussianBlur(m, (0, 0), sigma)
    mean = float(image[valid].mean()) if valid.any() else 0.0
    fill = np.where(den > 1e-3, num / np.maximum(den, 1e-3), mean)
    return np.where(valid, image, fill).astype(np.float32)


def hybrid_odometry(depth: np.ndarray, intensity: np.ndarray, K: np.ndarray, target_depth: np.ndarray,
                    target_intensity: np.ndarray, init_source_to_target: np.ndarray, *,
                    iterations: Sequence[int] = (6, 3, 1), depth_diff: float = 0.07, depth_huber_delta: float = 0.05,
                    intensity_huber_delta: float = 0.1, depth_min: float = 0.1, depth_max: float = 3.0,
                    relative_fitness: float = 1e-6, relative_rmse: float = 1e-6) -> tuple[np.ndarray, int]:
    """Coarse-to-fine hybrid (depth + intensity) odometry of a frame against a target image pair, Open3D's
    recipe (``RGBDOdometryMultiScaleHybrid``): depth pyramids by edge-preserving downsampling, intensity
    pyramids by Gaussian ``pyrDown``, Sobel gradients of the target per level, one
    ``compute_odometry_result_hybrid`` Gauss-Newton step per iteration, early stop on relative change.

    depth, target_depth: (H, W) float32 metres (0 = none); intensity, target_intensity: (H, W) float32.
    Returns ``(T (4, 4) float64 source -> target, iterations run)``; raises ``RuntimeError`` (Open3D) when a
    step finds no inlier.
    """
    import cv2

    levels = len(iterations)
    if levels < 1 or any(int(i) < 0 for i in iterations):
        raise ValueError(f"iterations must list non-negative counts per level, got {iterations}")
    src_d = np.where((depth > depth_min) & (depth < depth_max), depth, np.float32(np.nan)).astype(np.float32)
    tgt_d = np.where((target_depth > 0) & (target_depth < depth_max), target_depth,
                     np.float32(np.nan)).astype(np.float32)
    src_i = np.ascontiguousarray(intensity, np.float32)
    tgt_i = np.ascontiguousarray(target_intensity, np.float32)
    pyramid = []
    for level in range(levels):
        if level:
            src_d, tgt_d = pyrdown_depth(src_d, 2.0 * depth_diff), pyrdown_depth(tgt_d, 2.0 * depth_diff)
            src_i, tgt_i = cv2.pyrDown(src_i), cv2.pyrDown(tgt_i)
        Kt = o3d.core.Tensor(scaled_intrinsics(K, level))
        sd, td = o3d.t.geometry.Image(_to_tensor(src_d)), o3d.t.geometry.Image(_to_tensor(tgt_d))
        ti = o3d.t.geometry.Image(_to_tensor(tgt_i))
        tidx, tidy = ti.filter_sobel()
        tddx, tddy = td.filter_sobel()
        pyramid.append((sd.as_tensor(), td.as_tensor(), _to_tensor(src_i[..., None]), ti.as_tensor(),
                        tddx.as_tensor(), tddy.as_tensor(), tidx.as_tensor(), tidy.as_tensor(),
                        sd.create_vertex_map(Kt, _NAN).as_tensor(), Kt))
    T = o3d.core.Tensor(np.asarray(init_source_to_target, dtype=np.float64))
    fitness, rmse, n_iter = 1.0, 0.0, 0
    step = o3d.t.pipelines.odometry.compute_odometry_result_hybrid
    for level in reversed(range(levels)):
        sd, td, si, ti, tddx, tddy, tidx, tidy, sv, Kt = pyramid[level]
        for _ in range(int(iterations[levels - 1 - level])):
            result = step(sd, td, si, ti, tddx, tddy, tidx, tidy, sv, Kt, T, depth_diff, depth_huber_delta,
                          intensity_huber_delta)
            T = result.transformation @ T
            n_iter += 1
            new_fit, new_rmse = float(result.fitness), float(result.inlier_rmse)
            converged = (abs(fitness - new_fit) / max(fitness, 1e-12) < relative_fitness
                         and abs(rmse - new_rmse) / max(rmse, 1e-12) < relative_rmse)
            fitness, rmse = new_fit, new_rmse
            if converged:
                break
    return T.numpy().astype(np.float64), n_iter


__all__ = ["ColouredICPTracker", "HybridTracker", "TrackingColour", "estimate_exposure", "fill_holes",
           "hybrid_odometry", "luminance", "point_to_plane_association", "point_to_plane_fit",
           "tracking_colour"]
