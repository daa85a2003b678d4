"""Ray-cast rendering of a :class:`~mapping.simulation.scene.TexturedScene` into depth and radiance.

A pinhole camera with intrinsics ``K`` and a camera-to-world pose (OpenCV/TUM axes: x right, y
down, z forward) casts one ray per pixel through the pixel centre ``(u, v)`` (integer coordinates,
as in OpenCV): direction ``R K^-1 [u, v, 1]``. Because that direction has unit depth in the camera
frame, Open3D's ``t_hit`` is the depth ``z`` itself. With ``supersample = n`` each pixel's radiance
is the mean of ``n x n`` rays spread over its footprint (a box filter, like a sensor pixel); depth
and surface attributes come from the centre ray.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapping.simulation.scene import TexturedScene


@dataclass(frozen=True, eq=False)
class RenderResult:
    """Per-pixel rendering of one view (``H x W``).

    depth:    float32 z in metres along the optical axis, 0 where the ray hit nothing.
    radiance: float32 (H, W, 3) true radiance (0 where nothing was hit).
    albedo:   float32 (H, W, 3).
    normal:   float32 (H, W, 3) world-frame surface normal (0 where nothing was hit).
    points:   float32 (H, W, 3) world-frame hit points.
    face:     int32 face index, -1 for no hit; triangle: int32 triangle index, -1 for no hit.
    cos_incidence: float32 |cos| of the angle between the viewing ray and the normal.
    """

    depth: np.ndarray
    radiance: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray
    points: np.ndarray
    face: np.ndarray
    triangle: np.ndarray
    cos_incidence: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        return self.face >= 0


def check_pose(pose: np.ndarray) -> np.ndarray:
    T = np.asarray(pose, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"pose must be a finite 4x4 camera-to-world matrix, got shape {T.shape}")
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise ValueError("pose rotation must be orthonormal with determinant +1")
    return T


def check_intrinsics(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0 \
            or K[2, 2] != 1 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0:
        raise ValueError(f"K must be a 3x3 pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]], got {K.tolist()}")
    return K


class Renderer:
    """Renders a scene for one camera geometry (``K``, ``width x height``) at any pose."""

    def __init__(self, scene: TexturedScene, K: np.ndarray, width: int, height: int, *, supersample: int = 1) -> None:
        if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer))
                and width >= 2 and height >= 2):
            raise ValueError(f"width and height must be whole numbers >= 2, got {width!r} x {height!r}")
        if not (isinstance(supersample, (int, np.integer)) and 1 <= supersample <= 8):
            raise ValueError(f"supersample must be a whole number in 1..8, got {supersample!r}")
        self.scene = scene
        self.K = check_intrinsics(K)
        self.width, self.height = int(width), int(height)
        self.supersample = int(supersample)
        n = self.supersample
        offs = (np.arange(n) + 0.5) / n - 0.5
        self._sub_offsets = [(dx, dy) for dy in offs for dx in offs] if n > 1 else []
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        kinv = np.linalg.inv(self.K)
        dirs = np.stack([u, v, np.ones_like(u)], axis=-1) @ kinv.T
        self._ray_length = np.linalg.norm(dirs, axis=-1).reshape(-1).astype(np.float32)   # |K^-1 [u, v, 1]|

    def rays(self, pose: np.ndarray, *, offset: tuple[float, float] = (0.0, 0.0)):
        """Open3D tensor ``(H, W, 6)`` of rays through the pixel centres (shifted by ``offset`` pixels),
        directions with unit camera-frame depth. Open3D's ``create_rays_pinhole`` puts pixel ``(u, v)``
        at ``u + 0.5`` (pixel corners at integers), so the principal point is shifted by half a pixel to
        follow the OpenCV convention used everywhere in radiomap."""
        from mapping._open3d import o3d

        T = check_pose(pose)
        K = self.K.copy()
        K[0, 2] += 0.5 - offset[0]
        K[1, 2] += 0.5 - offset[1]
        world_to_cam = np.eye(4)
        world_to_cam[:3, :3] = T[:3, :3].T
        world_to_cam[:3, 3] = -T[:3, :3].T @ T[:3, 3]
        return o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(K), o3d.core.Tensor(world_to_cam), self.width, self.height)

    def render(self, pose: np.ndarray, *, light_scale: float = 1.0) -> RenderResult:
        """Depth, radiance and surface attributes seen from ``pose`` (camera-to-world 4x4)."""
        H, W = self.height, self.width
        N = H * W
        scene = self.scene
        rays_t = self.rays(pose)
        hit = scene.cast(rays_t)
        rays = rays_t.numpy().reshape(N, 6)
        tri = hit["primitive_ids"].reshape(N)
        t_hit = hit["t_hit"].reshape(N)
        uv = hit["primitive_uvs"].reshape(N, 2)
        all_hit = bool(tri.min() >= 0)
        idx = slice(None) if all_hit else np.flatnonzero(tri >= 0)
        faces, coords = scene.hit_coordinates(tri[idx], uv[idx])
        th = t_hit[idx]
        points = rays[idx, 3:] * th[:, None]
        points += rays[0, :3]
        normals = np.take(scene.face_normals32, faces, axis=0)
        albedo = scene.albedo_on_faces(faces, coords)
        rad = scene.irradiance_on_faces(faces, coords)
        rad *= albedo
        rad *= np.float32(light_scale / np.pi)
        # |cos| between ray and normal = (camera's distance to the face plane) / (distance to the point)
        eye = np.asarray(pose, dtype=np.float64)[:3, 3]
        plane_dist = np.abs(np.einsum("ij,ij->i", scene.face_normals, eye[None, :] - scene.face_origins))
        cos = np.take(plane_dist.astype(np.float32), faces)
        cos /= th
        cos /= self._ray_length[idx]
        np.minimum(cos, 1.0, out=cos)
        if self._sub_offsets:
            acc = np.zeros((N, 3), np.float32)
            for off in self._sub_offsets:
                sub = scene.cast(self.rays(pose, offset=off))
                p2 = sub["primitive_ids"].reshape(N)
                j = np.flatnonzero(p2 >= 0)
                f2, c2 = scene.hit_coordinates(p2[j], sub["primitive_uvs"].reshape(N, 2)[j])
                acc[j] += scene.radiance_on_faces(f2, c2, light_scale=light_scale)
            rad = (acc / np.float32(len(self._sub_offsets)))[idx]
        if all_hit:
            depth = t_hit.astype(np.float32, copy=False)
            face = faces.astype(np.int32, copy=False)
            triangle = tri.astype(np.int32)
            out = (rad, albedo, normals, points.astype(np.float32, copy=False), cos.astype(np.float32, copy=False))
        else:
            depth = np.zeros(N, np.float32)
            depth[idx] = th
            face = np.full(N, -1, np.int32)
            face[idx] = faces
            triangle = np.full(N, -1, np.int32)
            triangle[idx] = tri[idx]
            out = []
            for arr in (rad, albedo, normals, points, cos):
                full = np.zeros((N,) + arr.shape[1:], np.float32)
                full[idx] = arr
                out.append(full)
        rad, albedo, normals, points, cos = out
        return RenderResult(depth.reshape(H, W), rad.reshape(H, W, 3), albedo.reshape(H, W, 3),
                            normals.reshape(H, W, 3), points.reshape(H, W, 3), face.reshape(H, W),
                            triangle.reshape(H, W), cos.reshape(H, W))

    def project(self, points: np.ndarray, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates ``(N, 2)`` (OpenCV convention) and depths ``(N,)`` of world points."""
        T = check_pose(pose)
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        cam = (p - T[:3, 3]) @ T[:3, :3]
        uvw = cam @ self.K.T
        return uvw[:, :2] / uvw[:, 2:3], cam[:, 2]
