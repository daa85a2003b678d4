"""The surface of a fused map as one kind of geometry: a triangle mesh (TSDF) or surfels as small discs."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class MapGeometry:
    """The surface of a map: a triangle mesh (TSDF) or surfels as small discs (6 triangles each).

    vertices (N, 3) float32 world, triangles (M, 3) int32, colours (N, 3) float32 map units, normals (N, 3)."""

    vertices: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray
    normals: np.ndarray
    kind: str = "mesh"

    def __len__(self) -> int:
        return int(self.vertices.shape[0])


def surfel_discs(position: np.ndarray, normal: np.ndarray, radius: np.ndarray, colour: np.ndarray, *,
                 sides: int = 6) -> MapGeometry:
    """Surfels as ``sides``-gons (centre + rim, ``sides`` triangles each) in their tangent planes, every
    vertex with the surfel's colour and normal: a mesh that ray casting can render."""
    p = np.asarray(position, np.float64).reshape(-1, 3)
    n = np.asarray(normal, np.float64).reshape(-1, 3)
    r = np.asarray(radius, np.float64).reshape(-1)
    c = np.asarray(colour, np.float32).reshape(-1, 3)
    count = p.shape[0]
    if count == 0:
        return MapGeometry(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32),
                           np.zeros((0, 3), np.float32), "surfel discs")
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(n[:, 0:1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    a = np.cross(n, helper)
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = np.cross(n, a)
    angles = 2 * np.pi * np.arange(sides) / sides
    rim = p[:, None, :] + r[:, None, None] * (np.cos(angles)[None, :, None] * a[:, None, :]
                                              + np.sin(angles)[None, :, None] * b[:, None, :])
    verts = np.concatenate([p[:, None, :], rim], axis=1).reshape(-1, 3)
    base = (np.arange(count) * (sides + 1))[:, None]
    k = np.arange(sides)
    fan = np.stack([np.zeros(sides, np.int64), 1 + k, 1 + (k + 1) % sides], axis=1)  # (sides, 3)
    tris = (base[:, None, :] + fan[None, :, :]).reshape(-1, 3)
    return MapGeometry(verts.astype(np.float32), tris.astype(np.int32), np.repeat(c, sides + 1, axis=0),
                       np.repeat(n.astype(np.float32), sides + 1, axis=0), "surfel discs")


def map_geometry(backend) -> MapGeometry:
    """The fused surface of a backend: the TSDF's marching-cubes mesh, or the stable surfels as discs."""
    if hasattr(backend, "extract_mesh"):
        mesh = backend.extract_mesh()
        return MapGeometry(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.int32),
                           np.asarray(mesh.colours, np.float32), np.asarray(mesh.normals, np.float32), "mesh")
    if hasattr(backend, "surfels"):
        s = backend.surfels(stable_only=True)
        return surfel_discs(s["position"], s["normal"], s["radius"], s["colour"])
    raise TypeError(f"cannot extract a surface from a {type(backend).__name__}: it has neither extract_mesh() "
                    "nor surfels()")
