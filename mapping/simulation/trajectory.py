"""Camera trajectories: a smooth hand-held walk through a room and a white-paper sweep; TUM poses.

Poses are camera-to-world 4x4 float64 with OpenCV/TUM camera axes (x right, y down, z forward);
the world has z up. Every trajectory is a closed-form smooth function of time (sums of sinusoids),
so it is deterministic for a seed, C-infinity, and the same for any frame count prefix.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

_STREAM_TRAJECTORY = 202
_STREAM_PAPER = 303
_UP = np.array([0.0, 0.0, 1.0])


# ------------------------------------------------------------------------------------- rotations
def camera_rotation(forward: np.ndarray, *, up: np.ndarray = _UP, roll: float = 0.0) -> np.ndarray:
    """Camera-to-world rotation whose z axis is ``forward``, x axis horizontal-right (for ``roll = 0``)
    and y axis pointing down, rotated by ``roll`` radians about the viewing direction."""
    f = np.asarray(forward, dtype=np.float64)
    f = f / np.linalg.norm(f)
    right = np.cross(f, np.asarray(up, dtype=np.float64))
    n = np.linalg.norm(right)
    if n < 1e-9:
        raise ValueError("the viewing direction is parallel to 'up'; pass another up vector")
    right /= n
    down = np.cross(f, right)
    R = np.stack([right, down, f], axis=1)
    if roll:
        c, s = math.cos(roll), math.sin(roll)
        R = R @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R


def look_at(eye: Sequence[float], target: Sequence[float], *, up: Sequence[float] = (0, 0, 1),
            roll: float = 0.0) -> np.ndarray:
    """Camera-to-world pose at ``eye`` looking at ``target`` (OpenCV camera axes: x right, y down, z forward).

    ``up`` is the world's up direction: the camera's x axis is ``forward x up`` and its y axis points away
    from ``up`` (see :func:`camera_rotation`). The simulator's world has z up (the default); scenes built in
    camera-like world axes (y down) pass ``up=(0, -1, 0)``.
    """
    eye = np.asarray(eye, dtype=np.float64)
    T = np.eye(4)
    T[:3, :3] = camera_rotation(np.asarray(target, dtype=np.float64) - eye, up=np.asarray(up, float), roll=roll)
    T[:3, 3] = eye
    return T


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_y(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rotation_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(qx, qy, qz, qw)`` with ``qw >= 0`` of a rotation matrix (scipy's ``Rotation``)."""
    from mapping.metrics import matrix_to_quaternion

    return matrix_to_quaternion(np.asarray(R, dtype=np.float64).reshape(3, 3))


def quaternion_to_rotation(q: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a quaternion ``(qx, qy, qz, qw)`` (normalised first; scipy's ``Rotation``)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=np.float64).reshape(4)).as_matrix()


def pose_to_tum(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(t (3,), q (4,))`` with ``q = (qx, qy, qz, qw)``, ``qw >= 0``."""
    T = np.asarray(pose, dtype=np.float64)
    return T[:3, 3].copy(), rotation_to_quaternion(T[:3, :3])


def tum_to_pose(t: Sequence[float], q: Sequence[float]) -> np.ndarray:
    """Camera-to-world 4x4 from a translation and a ``(qx, qy, qz, qw)`` quaternion."""
    T = np.eye(4)
    T[:3, :3] = quaternion_to_rotation(q)
    T[:3, 3] = np.asarray(t, dtype=np.float64)
    return T


def motion_per_frame(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (metres) and rotation (degrees) between consecutive poses, each ``(N-1,)``."""
    P = np.asarray(poses, dtype=np.float64)
    trans = np.linalg.norm(np.diff(P[:, :3, 3], axis=0), axis=1)
    rel = np.einsum("nji,njk->nik", P[:-1, :3, :3], P[1:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    return trans, np.degrees(np.arccos(cos))


# ------------------------------------------------------------------------------ hand-held walk
@dataclass(frozen=True)
class HandheldMotion:
    """Shape of a hand-held trajectory.

    speed:     time scale (1 = about 1.5-2.5 cm and 1 degree per frame at 30 Hz).
    pitch:     mean downward tilt in radians (negative looks down: floor, furniture and walls).
    turn_time: seconds per full turn of the slow yaw drift (the camera looks all around the room).
    tremor:    scale of the 2-6 Hz hand tremor (1 = ~1 mm and ~0.1 degree).
    """

    speed: float = 1.0
    pitch: float = -0.38
    turn_time: float = 20.0
    tremor: float = 1.0

    def __post_init__(self) -> None:
        if not (0 < self.speed <= 10):
            raise ValueError(f"speed must be within (0, 10], got {self.speed!r}")
        if not (-1.2 <= self.pitch <= 0.5):
            raise ValueError(f"pitch must be within [-1.2, 0.5] radians, got {self.pitch!r}")
        if not (self.turn_time > 0):
            raise ValueError(f"turn_time must be positive seconds, got {self.turn_time!r}")
        if not (0 <= self.tremor <= 10):
            raise ValueError(f"tremor must be within [0, 10], got {self.tremor!r}")


def _sines(rng: np.random.Generator, k: int, freq: tuple[float, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    w = rng.uniform(0.5, 1.0, size=k)
    return w / w.sum(), rng.uniform(*freq, size=k), rng.uniform(0, 2 * np.pi, size=k)


def handheld_trajectory(n_frames: int, *, bounds: tuple[Sequence[float], Sequence[float]], seed: int,
                        fps: float = 30.0, motion: HandheldMotion = HandheldMotion()) -> np.ndarray:
    """Poses ``(N, 4, 4)`` of a person walking slowly inside the box ``bounds = (lo, hi)`` (metres,
    world z up), looking around and slightly down, with hand tremor. Positions stay strictly inside
    ``bounds`` (the sinusoid amplitudes sum to 95 % of the half extent)."""
    if not (isinstance(n_frames, (int, np.integer)) and n_frames >= 1):
        raise ValueError(f"n_frames must be a whole number >= 1, got {n_frames!r}")
    if not (fps > 0):
        raise ValueError(f"fps must be positive, got {fps!r}")
    lo, hi = np.asarray(bounds[0], float), np.asarray(bounds[1], float)
    if lo.shape != (3,) or hi.shape != (3,) or np.any(hi < lo):
        raise ValueError(f"bounds must be ((x, y, z) low, (x, y, z) high), got {bounds!r}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM_TRAJECTORY]))
    t = np.arange(n_frames, dtype=np.float64) / fps * motion.speed
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    pos = np.repeat(centre[None, :], n_frames, axis=0)
    for axis, freq in ((0, (0.04, 0.13)), (1, (0.04, 0.13)), (2, (0.05, 0.2))):
        w, f, ph = _sines(rng, 3, freq)
        pos[:, axis] += 0.95 * half[axis] * (w[None, :] * np.sin(2 * np.pi * f[None, :] * t[:, None] + ph)).sum(1)
    direction = rng.choice([-1.0, 1.0])
    yaw = rng.uniform(0, 2 * np.pi) + direction * 2 * np.pi * t / motion.turn_time
    for amp, freq in ((0.45, (0.05, 0.12)), (0.2, (0.12, 0.3))):
        yaw += amp * np.sin(2 * np.pi * rng.uniform(*freq) * t + rng.uniform(0, 2 * np.pi))
    pitch = motion.pitch + 0.14 * np.sin(2 * np.pi * rng.uniform(0.05, 0.15) * t + rng.uniform(0, 2 * np.pi))
    roll = 0.05 * np.sin(2 * np.pi * rng.uniform(0.05, 0.2) * t + rng.uniform(0, 2 * np.pi))
    if motion.tremor > 0:
        tt = np.arange(n_frames, dtype=np.float64) / fps   # tremor is physiological: not time-scaled
        for _ in range(3):
            f = rng.uniform(2.0, 6.0)
            pos += motion.tremor * 0.0007 * np.sin(2 * np.pi * f * tt[:, None] + rng.uniform(0, 2 * np.pi, 3))
            yaw += motion.tremor * 0.0012 * np.sin(2 * np.pi * rng.uniform(2.0, 6.0) * tt + rng.uniform(0, 6.3))
            pitch += motion.tremor * 0.0012 * np.sin(2 * np.pi * rng.uniform(2.0, 6.0) * tt + rng.uniform(0, 6.3))
        pos = np.clip(pos, lo, hi)
    poses = np.repeat(np.eye(4)[None], n_frames, axis=0)
    for i in range(n_frames):
        fwd = np.array([math.cos(pitch[i]) * math.cos(yaw[i]), math.cos(pitch[i]) * math.sin(yaw[i]),
                        math.sin(pitch[i])])
        poses[i, :3, :3] = camera_rotation(fwd, roll=roll[i])
        poses[i, :3, 3] = pos[i]
    return poses


def room_trajectory(room, n_frames: int, *, seed: int, fps: float = 30.0,
                    motion: HandheldMotion = HandheldMotion()) -> np.ndarray:
    """:func:`handheld_trajectory` inside ``room.camera_bounds``."""
    return handheld_trajectory(n_frames, bounds=room.camera_bounds, seed=seed, fps=fps, motion=motion)


# ------------------------------------------------------------------------------ paper sweep
@dataclass(frozen=True)
class PaperSweep:
    """How the camera sweeps over the sheet.

    heights:   camera height above the desk, min and max metres (varies smoothly).
    turns:     turns of the spiral the sheet centre draws in the image (None: one per 50 frames, >= 3).
    overscan:  how far beyond the image border the sheet centre goes, as a fraction of the image size.
    yaw_deg:   amplitude of the rotation about the vertical axis; tilt_deg: of the tilt.
    """

    heights: tuple[float, float] = (0.32, 0.48)
    turns: float | None = None
    overscan: float = 0.12
    yaw_deg: float = 20.0
    tilt_deg: float = 3.0

    def __post_init__(self) -> None:
        if not (0.05 <= self.heights[0] <= self.heights[1] <= 5.0):
            raise ValueError(f"heights must be (min, max) metres with 0.05 <= min <= max <= 5, got {self.heights!r}")
        if self.turns is not None and not (0.5 <= self.turns <= 100):
            raise ValueError(f"turns must be within [0.5, 100] or None, got {self.turns!r}")
        if not (0 <= self.overscan <= 0.5):
            raise ValueError(f"overscan must be within [0, 0.5], got {self.overscan!r}")
        if not (0 <= self.yaw_deg <= 90 and 0 <= self.tilt_deg <= 20):
            raise ValueError("yaw_deg must be within [0, 90] and tilt_deg within [0, 20]")


def sheet_image_path(n_frames: int, width: int, height: int, sweep: PaperSweep = PaperSweep()) -> np.ndarray:
    """Image position ``(N, 2)`` of the sheet centre: a rounded-square spiral from the image centre
    out to (and past) the corners and back, so the sheet passes over every pixel many times."""
    s = (np.arange(n_frames) + 0.5) / n_frames
    turns = sweep.turns if sweep.turns is not None else max(3.0, n_frames / 50.0)
    theta = 2 * np.pi * turns * s
    r = 1.0 - np.abs(1.0 - 2.0 * s)                     # out, then back in
    r = 0.15 + 0.85 * r
    e = 0.5                                             # superellipse exponent: reaches the corners
    cu, su = np.cos(theta), np.sin(theta)
    u = (width / 2) * (1 + sweep.overscan) * np.sign(cu) * np.abs(cu) ** e * r
    v = (height / 2) * (1 + sweep.overscan) * np.sign(su) * np.abs(su) ** e * r
    return np.stack([(width - 1) / 2 + u, (height - 1) / 2 + v], axis=1)


def paper_trajectory(n_frames: int, K: np.ndarray, width: int, height: int, *, seed: int,
                     sheet_centre: Sequence[float] = (0.0, 0.0, 0.0),
                     sweep: PaperSweep = PaperSweep()) -> np.ndarray:
    """Poses ``(N, 4, 4)`` of a camera looking down at a sheet lying at ``sheet_centre`` (desk plane
    ``z = sheet_centre[2]``), placed so the sheet centre appears at :func:`sheet_image_path`."""
    if not (isinstance(n_frames, (int, np.integer)) and n_frames >= 1):
        raise ValueError(f"n_frames must be a whole number >= 1, got {n_frames!r}")
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM_PAPER]))
    K = np.asarray(K, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    C = np.asarray(sheet_centre, dtype=np.float64)
    uv = sheet_image_path(n_frames, width, height, sweep)
    s = np.arange(n_frames) / max(n_frames, 1)
    h_lo, h_hi = sweep.heights
    hs = h_lo + (h_hi - h_lo) * (0.5 + 0.5 * np.sin(2 * np.pi * rng.uniform(1.5, 2.5) * s + rng.uniform(0, 6.3)))
    yaw0 = rng.uniform(0, 2 * np.pi)
    yaw = yaw0 + math.radians(sweep.yaw_deg) * np.sin(2 * np.pi * rng.uniform(1.0, 2.0) * s + rng.uniform(0, 6.3))
    tx = math.radians(sweep.tilt_deg) * np.sin(2 * np.pi * rng.uniform(1.0, 3.0) * s + rng.uniform(0, 6.3))
    ty = math.radians(sweep.tilt_deg) * np.sin(2 * np.pi * rng.uniform(1.0, 3.0) * s + rng.uniform(0, 6.3))
    R0 = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])   # looking straight down
    poses = np.repeat(np.eye(4)[None], n_frames, axis=0)
    for i in range(n_frames):
        R = _rot_z(yaw[i]) @ _rot_x(tx[i]) @ _rot_y(ty[i]) @ R0
        w = R @ (Kinv @ np.array([uv[i, 0], uv[i, 1], 1.0]))
        scale = (C[2] - (C[2] + hs[i])) / w[2]          # w[2] < 0: the ray goes down
        poses[i, :3, :3] = R
        poses[i, :3, 3] = C - scale * w
    return poses
