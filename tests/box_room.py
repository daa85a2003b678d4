"""Test helper: :func:`box_room_sequence`, an analytic scene with exact geometry, radiance, vignetting and
response for unit tests of tracking and fusion (made up in memory; not library code).

The box room is the inside of an axis-aligned box (``[-w/2, w/2] x [-h/2, h/2] x [0, d]``) whose walls carry a
smooth, view-independent radiance pattern; the camera starts near the origin looking along +z (towards a
corner region, so that three non-parallel planes constrain ICP) and moves along a gentle arc. Depth is the
exact ray-box intersection; colour is ``f(k * V(x) * L)`` through the given response. Nothing touches the disk.
The sequence is a :class:`mapping.datasets.in_memory.ArrayDataset`; the library's simulator (rendered rooms
written to folders) is :mod:`mapping.simulation`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mapping.datasets.base import RGBDFrame
from mapping.datasets.in_memory import ArrayDataset
from mapping.simulation.trajectory import look_at

#: the box room's world "up" for :func:`look_at`: +y (the camera's image y axis points to world -y)
BOX_UP = (0.0, 1.0, 0.0)


class BoxRoom:
    """The inside of an axis-aligned box with a smooth radiance pattern on its walls."""

    def __init__(self, size=(3.0, 2.4, 3.2), *, seed: int = 0) -> None:
        self.lo = np.array([-size[0] / 2, -size[1] / 2, 0.0])
        self.hi = np.array([size[0] / 2, size[1] / 2, size[2]])
        rng = np.random.default_rng(seed)
        self._freq = rng.uniform(2.0, 6.0, size=(3, 3))     # per channel, per axis
        self._phase = rng.uniform(0, 2 * np.pi, size=(3, 3))
        self._base = rng.uniform(0.35, 0.6, size=3)

    def intersect(self, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Distance along ``dirs`` from ``origins`` (inside the box) to the wall; (N,)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            t_hi = (self.hi - origins) / dirs
            t_lo = (self.lo - origins) / dirs
        t = np.where(dirs > 0, t_hi, np.where(dirs < 0, t_lo, np.inf))
        return t.min(axis=1)

    def radiance(self, points: np.ndarray) -> np.ndarray:
        """True radiance (N, 3) at wall points: smooth stripes, in (0.1, 1)."""
        p = np.asarray(points, float)
        out = np.empty((len(p), 3))
        for c in range(3):
            wave = np.sin(p @ self._freq[c] + self._phase[c].sum())
            out[:, c] = self._base[c] + 0.25 * wave
        return np.clip(out, 0.1, 1.0)


def radial_vignetting(height: int, width: int, strength: float) -> np.ndarray:
    """``V = 1 - strength * r^2`` (r = 1 at the half diagonal), float32 (H, W, 3)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = ((u - (width - 1) / 2) ** 2 + (v - (height - 1) / 2) ** 2) / (((width - 1) / 2) ** 2 + ((height - 1) / 2) ** 2)
    V = (1.0 - strength * r2).astype(np.float32)
    return np.repeat(V[:, :, None], 3, axis=2)


def box_room_sequence(*, n_frames: int = 12, width: int = 160, height: int = 120, step: float = 0.02,
                      turn_deg: float = 0.8, response=None, vignetting: np.ndarray | None = None,
                      exposure: float | Sequence[float] = 1.0, depth_noise: float = 0.0, seed: int = 0,
                      room: BoxRoom | None = None) -> tuple[ArrayDataset, BoxRoom]:
    """An analytic RGB-D sequence in a :class:`BoxRoom`; returns ``(dataset, room)``.

    step, turn_deg: camera motion per frame (metres sideways along x, degrees of yaw).
    response:       a :class:`radiometry.response.CameraResponse` (default linear).
    vignetting:     V (H, W, 3) applied to the image (default none).
    exposure:       ``k`` per frame (a scalar or one per frame); the image is ``f(k * V * L)``.
    depth_noise:    Gaussian depth noise, metres (0 = exact).
    """
    from radiometry.response import CameraResponse

    room = room or BoxRoom(seed=seed)
    response = response or CameraResponse.linear()
    ks = np.broadcast_to(np.asarray(exposure, dtype=np.float64), (n_frames,))
    f = 0.8 * width
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays_cam = np.stack([(u - K[0, 2]) / f, (v - K[1, 2]) / f, np.ones_like(u)], axis=-1).reshape(-1, 3)
    rng = np.random.default_rng(seed)
    V = np.ones((height, width, 3), np.float32) if vignetting is None else np.asarray(vignetting, np.float32)
    frames = []
    for i in range(n_frames):
        eye = np.array([-0.4 + step * i, 0.1, 0.6])
        yaw = np.radians(-20.0 + turn_deg * i)
        target = eye + np.array([np.sin(yaw) * 2.0 + 0.6, 0.35, np.cos(yaw) * 2.0])
        pose = look_at(eye, target, up=BOX_UP)
        dirs = rays_cam @ pose[:3, :3].T
        t = room.intersect(np.broadcast_to(pose[:3, 3], dirs.shape), dirs)
        points = pose[:3, 3] + t[:, None] * dirs
        depth = t.reshape(height, width)  # rays have unit camera-z, so t is the z-depth
        if depth_noise > 0:
            depth = depth + rng.normal(0, depth_noise, depth.shape)
        L = room.radiance(points).reshape(height, width, 3)
        rgb = response.forward((ks[i] * V * L).astype(np.float32), dtype=np.uint8)
        frames.append(RGBDFrame(index=i, timestamp=i / 30.0, rgb=rgb, depth=depth.astype(np.float32), K=K,
                                pose=pose, name=f"box{i:03d}"))
    return ArrayDataset(frames, name="box-room"), room
