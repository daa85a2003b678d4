"""A structured-light depth sensor (Kinect v1 / Asus Xtion-like) applied to rendered depth.

From the true depth ``z`` of a rendering it produces what such a sensor reports (float32 metres,
0 = no reading):

- axial noise growing with distance, ``sigma(z) = sigma0 + sigma2 * (z - z_ref)^2`` (Nguyen, Izadi and
  Lovell 2012: 0.0012 + 0.0019 (z - 0.4)^2 m for a Kinect), drawn per pixel;
- disparity quantisation: the sensor measures disparity ``d = f b / z`` in 1/``subpixel`` pixel steps of
  its own infrared camera (``focal`` pixels, independent of the colour image's resolution), so depth
  steps grow as ``z^2 / (f b subpixel)`` (about 3 mm at 1 m, 1.1 cm at 2 m, 4.6 cm at 4 m);
- the range limits ``[z_min, z_max]``;
- holes where the surface is seen at grazing angles (probability rising linearly in ``cos`` from 0 at
  ``grazing_deg[0]`` to 1 at ``grazing_deg[1]`` between the ray and the normal), in the projector's
  shadow (points the IR projector, ``baseline`` metres to the right of the camera, cannot see: ray
  cast), on the far side of depth edges (a band of ``edge_px`` pixels, each dropped with
  ``edge_drop`` probability), and a sparse random ``dropout``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapping.simulation.render import RenderResult


@dataclass(frozen=True)
class DepthSensor:
    """Parameters of the structured-light depth model (defaults: Kinect v1 / Xtion)."""

    z_min: float = 0.4
    z_max: float = 6.0
    sigma0: float = 0.0012
    sigma2: float = 0.0019
    z_ref: float = 0.4
    baseline: float = 0.075
    subpixel: float = 8.0
    focal: float = 580.0
    grazing_deg: tuple[float, float] = (72.0, 84.0)
    projector_shadow: bool = True
    edge_threshold: float = 0.04
    edge_px: int = 1
    edge_drop: float = 0.7
    dropout: float = 0.002

    def __post_init__(self) -> None:
        if not (0 < self.z_min < self.z_max):
            raise ValueError(f"need 0 < z_min < z_max, got {self.z_min}, {self.z_max}")
        if self.sigma0 < 0 or self.sigma2 < 0:
            raise ValueError("sigma0 and sigma2 must be >= 0")
        if self.baseline <= 0 or self.subpixel <= 0 or self.focal <= 0:
            raise ValueError("baseline, subpixel and focal must be positive")
        g0, g1 = self.grazing_deg
        if not (0 < g0 < g1 <= 90):
            raise ValueError(f"grazing_deg must be (start, end) with 0 < start < end <= 90, got {self.grazing_deg!r}")
        if not (0 <= self.edge_drop <= 1 and 0 <= self.dropout < 1 and self.edge_px >= 0 and self.edge_threshold > 0):
            raise ValueError("edge_drop and dropout must be probabilities, edge_px >= 0, edge_threshold > 0")

    def sigma(self, z: np.ndarray) -> np.ndarray:
        """Axial noise standard deviation (metres) at depth ``z``."""
        z = np.asarray(z, dtype=np.float32)
        return np.float32(self.sigma0) + np.float32(self.sigma2) * (z - np.float32(self.z_ref)) ** 2

    def quantise(self, z: np.ndarray) -> np.ndarray:
        """Depth rounded to the nearest representable disparity step (0 stays 0)."""
        z = np.asarray(z, dtype=np.float32)
        fb = np.float32(self.focal * self.baseline * self.subpixel)
        out = np.zeros_like(z)
        pos = z > 0
        d = np.maximum(np.rint(fb / z[pos]), 1.0)
        out[pos] = fb / d
        return out

    def step(self, z: np.ndarray | float) -> np.ndarray:
        """Depth quantisation step (metres) at depth ``z``."""
        return np.asarray(z, dtype=np.float64) ** 2 / (self.focal * self.baseline * self.subpixel)

    def measure(self, render: RenderResult, *, rng: np.random.Generator,
                pose: np.ndarray | None = None, scene=None) -> np.ndarray:
        """Sensor depth (float32 metres, 0 = hole) from a rendering. ``pose`` and ``scene`` enable the
        projector-shadow test; without them that hole source is skipped."""
        if not isinstance(rng, np.random.Generator):
            raise ValueError("rng must be a numpy Generator, e.g. np.random.default_rng(seed)")
        z = render.depth.astype(np.float32)
        H, W = z.shape
        valid = z > 0
        # hole probability per pixel: the largest of the grazing-angle ramp (linear in cos between the
        # two angles), the edge drop on the far side of depth discontinuities, and the random dropout
        c0, c1 = np.cos(np.radians(self.grazing_deg)).astype(np.float32)
        p_hole = np.float32(c0) - render.cos_incidence
        p_hole *= np.float32(1.0 / (c0 - c1))
        np.clip(p_hole, self.dropout, 1.0, out=p_hole)
        if self.edge_px > 0:
            far = np.zeros((H, W), bool)
            zz = np.where(valid, z, np.float32(np.inf))
            thr = np.float32(1.0 + self.edge_threshold)
            far[:, 1:] |= zz[:, 1:] > zz[:, :-1] * thr
            far[:, :-1] |= zz[:, :-1] > zz[:, 1:] * thr
            far[1:, :] |= zz[1:, :] > zz[:-1, :] * thr
            far[:-1, :] |= zz[:-1, :] > zz[1:, :] * thr
            if self.edge_px > 1:
                import cv2

                k = 2 * self.edge_px - 1
                far = cv2.dilate(far.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
                # the dilation also reaches edge_px - 1 pixels into the near surface: keep the band on the
                # far side (pixels with a nearer surface within edge_px pixels)
                nearest = cv2.erode(zz, np.ones((k + 2, k + 2), np.uint8))
                far &= zz > nearest * thr
            np.maximum(p_hole, np.where(far, np.float32(self.edge_drop), np.float32(0.0)), out=p_hole)
        holes = rng.random((H, W), dtype=np.float32) < p_hole
        if self.projector_shadow and pose is not None and scene is not None:
            holes |= self._projector_shadow(render, np.asarray(pose, float), scene)
        noisy = z + self.sigma(z) * rng.standard_normal((H, W), dtype=np.float32)
        out = self.quantise(np.where(valid & ~holes, noisy, 0.0).astype(np.float32))
        out[(out < self.z_min) | (out > self.z_max)] = 0.0
        return out

    def _projector_shadow(self, render: RenderResult, pose: np.ndarray, scene) -> np.ndarray:
        """Pixels whose surface point the projector cannot see (occluded or facing away from it)."""
        H, W = render.depth.shape
        valid = render.face.reshape(-1) >= 0
        all_valid = bool(valid.all())
        idx = slice(None) if all_valid else np.flatnonzero(valid)
        projector = (pose[:3, 3] + pose[:3, 0] * self.baseline).astype(np.float32)
        p = render.points.reshape(-1, 3)[idx]
        n = render.normal.reshape(-1, 3)[idx]
        rays = np.empty((p.shape[0], 6), np.float32)
        np.subtract(projector[None, :], p, out=rays[:, 3:])
        facing = np.einsum("ij,ij->i", rays[:, 3:], n) > 0
        np.multiply(n, np.float32(1e-3), out=rays[:, :3])
        rays[:, :3] += p
        occ = scene.occluded(rays, tnear=1e-4, tfar=0.999)
        occ |= ~facing
        if all_valid:
            return occ.reshape(H, W)
        shadow = np.zeros(H * W, bool)
        shadow[idx] = occ
        return shadow.reshape(H, W)
