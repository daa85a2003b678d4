"""Textured planar scenes with Lambertian shading: the geometry and the true radiance.

A :class:`TexturedScene` is a set of rectangular :class:`Face` objects, each with a baked albedo
texture, lit by a :class:`Lighting` (ambient plus softened point lights, no shadows). The outgoing
radiance of a point ``p`` with normal ``n`` is ``L(p) = albedo(p) / pi * E(p, n)``, independent of the
viewing direction, so a 3D map can converge to it; :meth:`TexturedScene.radiance_at` gives it at any
3D point (e.g. the vertices of a reconstructed mesh).

Face-local coordinates: ``p = origin + s * axis_s + t * axis_t`` with ``0 <= s <= size[0]`` and
``0 <= t <= size[1]`` metres; the visible side is the one ``normal = axis_s x axis_t`` points to.
Textures are sampled bilinearly at the texel centres: column ``x = s / texel_s - 0.5``, row
``y = (size_t - t) / texel_t - 0.5`` (row 0 at the top, so images appear upright and unmirrored when
seen from the front with ``axis_t`` up).
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


@dataclass(eq=False)
class Face:
    """A textured rectangle. ``axis_s``/``axis_t`` are orthonormal; ``texture`` float32 (h, w, 3)."""

    name: str
    origin: np.ndarray
    axis_s: np.ndarray
    axis_t: np.ndarray
    size: tuple[float, float]
    texture: np.ndarray

    def __post_init__(self) -> None:
        self.origin = np.asarray(self.origin, dtype=np.float64).reshape(3)
        self.axis_s = np.asarray(self.axis_s, dtype=np.float64).reshape(3)
        self.axis_t = np.asarray(self.axis_t, dtype=np.float64).reshape(3)
        if abs(np.linalg.norm(self.axis_s) - 1) > 1e-9 or abs(np.linalg.norm(self.axis_t) - 1) > 1e-9 \
                or abs(float(self.axis_s @ self.axis_t)) > 1e-9:
            raise ValueError(f"face {self.name!r}: axis_s and axis_t must be orthonormal")
        self.size = (float(self.size[0]), float(self.size[1]))
        if min(self.size) <= 0:
            raise ValueError(f"face {self.name!r}: size must be positive, got {self.size}")
        tex = np.asarray(self.texture, dtype=np.float32)
        if tex.ndim != 3 or tex.shape[2] != 3 or min(tex.shape[:2]) < 1:
            raise ValueError(f"face {self.name!r}: texture must be (h, w, 3), got {tex.shape}")
        self.texture = np.ascontiguousarray(tex)

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.axis_s, self.axis_t)

    def corners(self) -> np.ndarray:
        """(4, 3): (0,0), (S,0), (S,T), (0,T) in face coordinates."""
        s, t = self.size
        o, a, b = self.origin, self.axis_s, self.axis_t
        return np.stack([o, o + s * a, o + s * a + t * b, o + t * b])


@dataclass(frozen=True)
class PointLight:
    """An isotropic light: irradiance ``intensity * cos(theta) / (d^2 + softening^2)`` (the softening
    mimics a lamp of that size and keeps nearby surfaces from exploding)."""

    position: tuple[float, float, float]
    intensity: tuple[float, float, float]
    softening: float = 1.0


@dataclass(frozen=True)
class Lighting:
    """Ambient light (per channel) scaled by ``1 + sky * n_z`` (floors see more bounce light than
    ceilings) plus point lights. No shadows: ``E`` depends only on the point and its normal."""

    ambient: tuple[float, float, float] = (1.0, 1.0, 1.0)
    sky: float = 0.0
    lights: tuple[PointLight, ...] = ()

    def irradiance(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """``E(p, n)`` float32 ``(N, 3)`` for points and unit normals ``(N, 3)``."""
        p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        n = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
        amb = np.asarray(self.ambient, np.float32)
        out = (1.0 + np.float32(self.sky) * n[:, 2:3]) * amb[None, :]
        for light in self.lights:
            d = np.asarray(light.position, np.float32)[None, :] - p
            dist2 = np.einsum("ij,ij->i", d, d)
            cos_d = np.einsum("ij,ij->i", d, n)  # cos(theta) * |d|
            w = np.maximum(cos_d, 0.0) / (np.sqrt(dist2) * (dist2 + np.float32(light.softening) ** 2))
            out += w[:, None] * np.asarray(light.intensity, np.float32)[None, :]
        return out.astype(np.float32, copy=False)

    def to_dict(self) -> dict:
        return {"ambient": list(self.ambient), "sky": self.sky,
                "lights": [{"position": list(li.position), "intensity": list(li.intensity),
                            "softening": li.softening} for li in self.lights]}


class TexturedScene:
    """Faces + lighting, with a triangle mesh for ray casting (two triangles per face) and a flat
    texture atlas for vectorised bilinear look-ups."""

    def __init__(self, faces: list[Face], lighting: Lighting, *, name: str = "scene") -> None:
        if not faces:
            raise ValueError("a scene needs at least one face")
        self.name = name
        self.faces = list(faces)
        self.lighting = lighting
        F = len(self.faces)
        verts = np.concatenate([f.corners() for f in self.faces]).astype(np.float64)
        base = (np.arange(F) * 4)[:, None]
        tris = np.concatenate([base + np.array([[0, 1, 2]]), base + np.array([[0, 2, 3]])], axis=1).reshape(-1, 3)
        self.vertices = verts                                   # (4F, 3) float64
        self.triangles = tris.astype(np.int64)                  # (2F, 3)
        self.triangle_face = np.repeat(np.arange(F), 2)         # (2F,)
        sizes = np.array([f.size for f in self.faces])          # (F, 2)
        self.face_normals = np.stack([f.normal for f in self.faces])        # (F, 3)
        self.face_origins = np.stack([f.origin for f in self.faces])
        self.face_axes = np.stack([np.stack([f.axis_s, f.axis_t]) for f in self.faces])  # (F, 2, 3)
        self.face_sizes = sizes
        heights = np.array([f.texture.shape[0] for f in self.faces], dtype=np.int64)
        widths = np.array([f.texture.shape[1] for f in self.faces], dtype=np.int64)
        self._atlas = np.concatenate([f.texture.reshape(-1, 3) for f in self.faces], dtype=np.float32)
        if self._atlas.shape[0] >= 2**31:
            raise ValueError("the textures hold more than 2^31 texels; use a coarser texel size")
        offsets = np.concatenate([[0], np.cumsum(heights * widths)[:-1]])
        self._atlas_rows = self._atlas.view("V12").reshape(-1)    # one 12-byte element per texel: fast gathers
        # per face: 1/texel_s, 1/texel_t, size_t, w - 1, h - 1 (float32); w, offset (int32)
        self._tex_inv_s = (widths / sizes[:, 0]).astype(np.float32)
        self._tex_inv_t = (heights / sizes[:, 1]).astype(np.float32)
        self._tex_size_t = sizes[:, 1].astype(np.float32)
        self._tex_wm1 = (widths - 1).astype(np.float32)
        self._tex_hm1 = (heights - 1).astype(np.float32)
        self._tex_w = widths.astype(np.int32)
        self._tex_off = offsets.astype(np.int32)
        self.face_normals32 = self.face_normals.astype(np.float32)
        self._sizes32 = sizes.astype(np.float32)
        self._light_tables = self._lighting_tables()
        self._raycaster = None

    def _lighting_tables(self) -> tuple[np.ndarray, list[tuple[np.ndarray, np.ndarray, float]]]:
        """Per-face constants of the shading: on a plane, ``n . (l - p)`` is the light's height ``h``
        above the plane and ``|l - p|^2 = h^2 + (s - s0)^2 + (t - t0)^2`` with ``(s0, t0)`` the light's
        foot point in face coordinates, so irradiance needs only face ids and ``(s, t)``."""
        lit = self.lighting
        n = self.face_normals
        ambient = ((1.0 + lit.sky * n[:, 2:3]) * np.asarray(lit.ambient, np.float64)[None, :]).astype(np.float32)
        lights = []
        for light in lit.lights:
            rel = np.asarray(light.position, np.float64)[None, :] - self.face_origins
            h = np.einsum("ij,ij->i", rel, n)
            s0 = np.einsum("ij,ij->i", rel, self.face_axes[:, 0])
            t0 = np.einsum("ij,ij->i", rel, self.face_axes[:, 1])
            table = np.stack([s0, t0, h * h, np.maximum(h, 0.0)], axis=1).astype(np.float32)
            lights.append((table, np.asarray(light.intensity, np.float32), float(light.softening) ** 2))
        return ambient, lights

    def irradiance_on_faces(self, faces: np.ndarray, coords: np.ndarray) -> np.ndarray:
        """``E`` float32 ``(N, 3)`` at face coordinates; equal to ``lighting.irradiance(points, normals)``
        of the same points (computed from per-face constants, without 3D points)."""
        f = np.asarray(faces).reshape(-1).astype(np.int32, copy=False)
        c = np.asarray(coords, dtype=np.float32).reshape(-1, 2)
        ambient, lights = self._light_tables
        E = np.take(ambient, f, axis=0)
        for table, intensity, soft2 in lights:
            k = np.take(table, f, axis=0)
            ds = c[:, 0] - k[:, 0]
            ds *= ds
            dt = c[:, 1] - k[:, 1]
            dt *= dt
            ds += dt
            ds += k[:, 2]                      # squared distance to the light
            w = np.sqrt(ds)
            ds += np.float32(soft2)
            w *= ds
            np.divide(k[:, 3], w, out=w)       # h / (d (d^2 + softening^2)) = cos / (d^2 + softening^2)
            E += w[:, None] * intensity[None, :]
        return E

    # ------------------------------------------------------------------ ray casting
    @property
    def raycaster(self):
        """The Open3D ``RaycastingScene`` of the mesh (built on first use)."""
        if self._raycaster is None:
            from mapping._open3d import o3d

            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                o3d.core.Tensor(self.triangles.astype(np.uint32)))
            self._raycaster = scene
        return self._raycaster

    def cast(self, rays) -> dict[str, np.ndarray]:
        """Cast rays (float32 ``(..., 6)`` array or Open3D tensor); returns numpy ``t_hit``,
        ``primitive_ids`` (int32, -1 for a miss) and ``primitive_uvs``."""
        from mapping._open3d import o3d

        if not isinstance(rays, o3d.core.Tensor):
            rays = o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32))
        ans = self.raycaster.cast_rays(rays)
        prim = ans["primitive_ids"].numpy().view(np.int32)   # INVALID_ID (2^32 - 1) becomes -1
        return {"t_hit": ans["t_hit"].numpy(), "primitive_ids": prim, "primitive_uvs": ans["primitive_uvs"].numpy()}

    def occluded(self, rays: np.ndarray, *, tnear: float = 0.0, tfar: float = np.inf) -> np.ndarray:
        """Whether each ray hits anything between ``tnear`` and ``tfar`` (bool array)."""
        from mapping._open3d import o3d

        res = self.raycaster.test_occlusions(o3d.core.Tensor(np.ascontiguousarray(rays, dtype=np.float32)),
                                             tnear=float(tnear), tfar=float(tfar))
        return res.numpy().astype(bool)

    # ------------------------------------------------------------------ surface look-ups
    def hit_coordinates(self, triangles: np.ndarray, uvs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Face ids ``(N,)`` int32 and face coordinates ``(N, 2)`` float32 (s, t metres) from triangle
        ids and barycentric ``(u, v)`` (hit = (1-u-v) v0 + u v1 + v v2, as Open3D reports them).

        Face ``f`` is triangles ``2f`` with corners (0,0), (S,0), (S,T) and ``2f+1`` with (0,0),
        (S,T), (0,T), so ``(s, t) = (S (u+v), T v)`` and ``(S u, T (u+v))`` respectively.
        """
        tri = np.asarray(triangles).reshape(-1).astype(np.int32, copy=False)
        uv = np.asarray(uvs, dtype=np.float32).reshape(-1, 2)
        face = tri >> 1
        odd = (tri & 1).astype(bool)
        u, v = uv[:, 0], uv[:, 1]
        uv_sum = u + v
        coords = np.empty((tri.size, 2), np.float32)
        coords[:, 0] = np.where(odd, u, uv_sum)
        coords[:, 1] = np.where(odd, uv_sum, v)
        coords *= self._sizes32[face]
        return face, coords

    def face_points(self, faces: np.ndarray, coords: np.ndarray) -> np.ndarray:
        """World points ``(N, 3)`` of face coordinates."""
        f = np.asarray(faces, dtype=np.int64)
        c = np.asarray(coords, dtype=np.float64)
        return self.face_origins[f] + c[:, 0:1] * self.face_axes[f, 0] + c[:, 1:2] * self.face_axes[f, 1]

    def albedo_on_faces(self, faces: np.ndarray, coords: np.ndarray) -> np.ndarray:
        """Bilinear texture look-up: albedo float32 ``(N, 3)`` at face coordinates (clamped to the face)."""
        f = np.asarray(faces).reshape(-1).astype(np.int32, copy=False)
        c = np.asarray(coords, dtype=np.float32).reshape(-1, 2)
        wm1 = np.take(self._tex_wm1, f)
        hm1 = np.take(self._tex_hm1, f)
        w = np.take(self._tex_w, f)
        x = c[:, 0] * np.take(self._tex_inv_s, f)
        x -= 0.5
        np.clip(x, 0.0, wm1, out=x)
        y = np.take(self._tex_size_t, f)
        y -= c[:, 1]
        y *= np.take(self._tex_inv_t, f)
        y -= 0.5
        np.clip(y, 0.0, hm1, out=y)
        x0 = x.astype(np.int32)          # floor: x >= 0
        y0 = y.astype(np.int32)
        x -= x0
        y -= y0
        fx, fy = x[:, None], y[:, None]
        dx = (x0 < wm1).view(np.int8)                 # 0 at the last column
        dy = np.where(y0 < hm1, w, 0)                 # one row down, 0 at the last row
        i00 = y0 * w
        i00 += np.take(self._tex_off, f)
        i00 += x0
        rows = self._atlas_rows

        def gather(index: np.ndarray) -> np.ndarray:
            return np.take(rows, index).view(np.float32).reshape(-1, 3)

        top = gather(i00)
        right = gather(i00 + dx)
        right -= top
        right *= fx
        top += right
        i00 += dy
        bottom = gather(i00)
        right = gather(i00 + dx)
        right -= bottom
        right *= fx
        bottom += right
        bottom -= top
        bottom *= fy
        top += bottom
        return top

    def radiance_on_faces(self, faces: np.ndarray, coords: np.ndarray, *, light_scale: float = 1.0) -> np.ndarray:
        """True radiance float32 ``(N, 3)`` at face coordinates."""
        f = np.asarray(faces).reshape(-1).astype(np.int32, copy=False)
        rad = self.albedo_on_faces(f, coords)
        rad *= self.irradiance_on_faces(f, coords)
        rad *= np.float32(light_scale / np.pi)
        return rad

    def closest_surface(self, points: np.ndarray, normals: np.ndarray | None = None, *,
                        normal_search: float = 0.05) -> dict[str, np.ndarray]:
        """The scene surface each point belongs to: ``face`` (N,), ``coords`` (N, 2), ``points``
        (N, 3) on the surface and ``distance`` (N,).

        Without ``normals``: the closest surface point. With ``normals`` (e.g. of a reconstructed
        mesh): the nearest surface within ``normal_search`` metres along ``-n`` or ``+n`` whose normal
        agrees with ``n`` (so a point near a box edge, or just behind the surface, gets the face it
        lies on rather than a nearer perpendicular one); points where none is found fall back to the
        closest point.
        """
        from mapping._open3d import o3d

        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        ans = self.raycaster.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        tri = ans["primitive_ids"].numpy().view(np.int32).copy()
        uv = ans["primitive_uvs"].numpy().copy()
        if normals is not None:
            n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
            norm = np.linalg.norm(n, axis=1, keepdims=True)
            good = norm[:, 0] > 1e-9
            n = np.where(good[:, None], n / np.maximum(norm, 1e-12), 0.0)
            best_t = np.full(p.shape[0], np.inf)
            for sign in (-1.0, 1.0):
                hit = self.cast(np.concatenate([p, sign * n], axis=1))
                prim = hit["primitive_ids"]
                agree = np.zeros(p.shape[0], bool)
                ok = prim >= 0
                agree[ok] = np.einsum("ij,ij->i", self.face_normals[prim[ok] >> 1], n[ok]) > 0.5
                use = good & agree & (hit["t_hit"] <= normal_search) & (hit["t_hit"] < best_t)
                tri[use] = prim[use]
                uv[use] = hit["primitive_uvs"][use]
                best_t[use] = hit["t_hit"][use]
        faces, coords = self.hit_coordinates(tri, uv)
        surf = self.face_points(faces, coords)
        return {"face": faces, "coords": coords, "points": surf, "distance": np.linalg.norm(surf - p, axis=1)}

    def albedo_at(self, points: np.ndarray, normals: np.ndarray | None = None) -> np.ndarray:
        """True albedo float32 ``(N, 3)`` of the surface nearest to each 3D point (see
        :meth:`closest_surface`)."""
        s = self.closest_surface(points, normals)
        return self.albedo_on_faces(s["face"], s["coords"])

    def radiance_at(self, points: np.ndarray, normals: np.ndarray | None = None, *, light_scale: float = 1.0,
                    max_distance: float | None = None) -> np.ndarray:
        """True (view-independent) radiance float32 ``(N, 3)`` of the surface nearest to each point;
        NaN rows where that surface is farther than ``max_distance`` metres (if given)."""
        s = self.closest_surface(points, normals)
        out = self.radiance_on_faces(s["face"], s["coords"], light_scale=light_scale)
        if max_distance is not None:
            out[s["distance"] > max_distance] = np.nan
        return out

    # ------------------------------------------------------------------ export
    def dense_mesh(self, spacing: float = 0.04) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A finer triangulation for viewing: vertices (V, 3), triangles (T, 3) and the true radiance
        per vertex (V, 3), each face a grid of about ``spacing`` metres."""
        verts, tris, rad = [], [], []
        base = 0
        for i, f in enumerate(self.faces):
            ns = max(1, int(np.ceil(f.size[0] / spacing)))
            nt = max(1, int(np.ceil(f.size[1] / spacing)))
            s = np.linspace(0, f.size[0], ns + 1)
            t = np.linspace(0, f.size[1], nt + 1)
            S, T = np.meshgrid(s, t)
            coords = np.stack([S.ravel(), T.ravel()], axis=1)
            ids = np.full(coords.shape[0], i)
            verts.append(self.face_points(ids, coords))
            rad.append(self.radiance_on_faces(ids, coords))
            g = np.arange((nt + 1) * (ns + 1)).reshape(nt + 1, ns + 1)
            a, b, c, d = g[:-1, :-1], g[:-1, 1:], g[1:, 1:], g[1:, :-1]
            quads = np.stack([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], axis=2).reshape(-1, 3)
            tris.append(quads + base)
            base += coords.shape[0]
        return np.concatenate(verts), np.concatenate(tris), np.concatenate(rad)

    def write_mesh(self, path: str | os.PathLike, *, spacing: float = 0.04,
                   colour_scale: float | None = None) -> float:
        """Write a PLY mesh with per-vertex true radiance as colour (linear, ``radiance /
        colour_scale`` clipped to [0, 1]; default scale: the 99.5th percentile). Returns the scale."""
        from mapping._open3d import o3d
        from radiometry.errors import OutputError
        from radiometry.fileio import atomic_path

        v, t, rad = self.dense_mesh(spacing)
        scale = float(np.percentile(rad, 99.5)) if colour_scale is None else float(colour_scale)
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(t.astype(np.int32)))
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.clip(rad / max(scale, 1e-12), 0.0, 1.0).astype(np.float64))
        mesh.compute_vertex_normals()
        with atomic_path(path) as tmp:
            if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False, compressed=False):
                raise OutputError(f"cannot write the mesh {path}; choose another output folder")
        return scale

    def checksum(self, *, textures: bool = True) -> str:
        """SHA-1 of the geometry (rounded to 1e-6 m) and, optionally, of the textures (every 61st texel,
        rounded to 1e-4: enough to notice a different generator, cheap for millions of texels)."""
        h = hashlib.sha1()
        h.update(np.round(self.vertices, 6).astype(np.float64).tobytes())
        if textures:
            h.update(np.round(self._atlas[::61].astype(np.float64), 4).tobytes())
        return h.hexdigest()
