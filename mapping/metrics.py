"""Trajectories: TUM-format I/O, timestamp association, pose interpolation and the absolute trajectory error.

ATE follows Sturm et al. (TUM RGB-D benchmark) and evo: associate estimated and ground-truth poses by
timestamp (nearest, one-to-one, within ``max_difference`` seconds), align the estimated positions to the
ground truth with Horn's closed form (Umeyama's SVD: rotation + translation, optionally scale), then take
statistics of the remaining position errors. Poses are camera-to-world (4, 4) float64.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from radiometry.errors import DatasetError
from radiometry.fileio import atomic_write_text


# --------------------------------------------------------------------------------------------------
# association (evo core/sync.py, TUM associate.py)
# --------------------------------------------------------------------------------------------------
def associate_timestamps(stamps_a: np.ndarray, stamps_b: np.ndarray, *, max_difference: float = 0.02,
                         offset_b: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Pair each stamp of ``a`` with the nearest stamp of ``b`` (shifted by ``offset_b``), one-to-one.

    A pair is kept when the time difference is at most ``max_difference`` seconds; when two stamps of ``a``
    want the same stamp of ``b``, the closer pair wins (as TUM's ``associate.py``). Returns index arrays
    ``(ia, ib)`` sorted by ``ia``.
    """
    if max_difference < 0 or not np.isfinite(max_difference):
        raise ValueError(f"max_difference must be a non-negative number of seconds, got {max_difference}")
    a = np.asarray(stamps_a, dtype=np.float64).ravel()
    b = np.asarray(stamps_b, dtype=np.float64).ravel() + offset_b
    if a.size == 0 or b.size == 0:
        return np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    order = np.argsort(b, kind="stable")
    bs = b[order]
    pos = np.searchsorted(bs, a)
    lo = np.clip(pos - 1, 0, bs.size - 1)
    hi = np.clip(pos, 0, bs.size - 1)
    pick = np.where(np.abs(bs[lo] - a) <= np.abs(bs[hi] - a), lo, hi)
    diff = np.abs(bs[pick] - a)
    ia = np.flatnonzero(diff <= max_difference + 1e-12)
    ib = order[pick[ia]]
    # one-to-one: for duplicates of ib keep the closest
    if ib.size != np.unique(ib).size:
        by_diff = np.lexsort((ia, diff[ia]))
        _, first = np.unique(ib[by_diff], return_index=True)
        keep = np.sort(by_diff[first])
        ia, ib = ia[keep], ib[keep]
    return ia, ib


# --------------------------------------------------------------------------------------------------
# rotations
# --------------------------------------------------------------------------------------------------
def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Quaternions ``(..., 4)`` in TUM order ``qx qy qz qw`` (scipy's scalar-last order) -> rotation matrices
    ``(..., 3, 3)``, normalised first (a zero quaternion gives the identity): scipy's ``Rotation``."""
    from scipy.spatial.transform import Rotation

    q = np.asarray(q, dtype=np.float64)
    flat = q.reshape(-1, 4).copy()
    flat[np.linalg.norm(flat, axis=1) == 0] = (0.0, 0.0, 0.0, 1.0)
    if len(flat) == 0:
        return np.zeros(q.shape[:-1] + (3, 3))
    return Rotation.from_quat(flat).as_matrix().reshape(q.shape[:-1] + (3, 3))


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` -> unit quaternions ``(..., 4)`` as ``qx qy qz qw``, ``qw >= 0``:
    scipy's ``Rotation``."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, dtype=np.float64)
    m = R.reshape(-1, 3, 3)
    if len(m) == 0:
        return np.zeros(R.shape[:-2] + (4,))
    q = Rotation.from_matrix(m).as_quat()
    q *= np.where(q[:, 3:4] < 0, -1.0, 1.0)
    return q.reshape(R.shape[:-2] + (4,))


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """The rotation angle (radians) of rotation matrices ``(..., 3, 3)``."""
    R = np.asarray(R, dtype=np.float64)
    cos = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.arccos(np.clip(cos, -1.0, 1.0))


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray, *,
                      max_gap: float = 0.1, max_difference: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Poses at ``query`` times: linear in position, spherical-linear in rotation between the two bracketing
    poses when they are at most ``max_gap`` s apart; otherwise the nearest pose within ``max_difference`` s.

    Returns ``(valid (M,) bool, poses (M, 4, 4))`` (invalid rows are identity)."""
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    query = np.asarray(query, dtype=np.float64)
    out = np.repeat(np.eye(4)[None], len(query), axis=0)
    valid = np.zeros(len(query), dtype=bool)
    if len(stamps) == 0:
        return valid, out
    order = np.argsort(stamps)
    stamps, poses = stamps[order], poses[order]
    from scipy.spatial.transform import Rotation, Slerp

    rotations = Rotation.from_matrix(poses[:, :3, :3])
    pos = np.searchsorted(stamps, query)   # stamps[p - 1] < t <= stamps[p]: the bracketing poses are p - 1 and p
    for j, (t, p) in enumerate(zip(query, pos)):
        if 0 < p < len(stamps) and stamps[p] - stamps[p - 1] <= max_gap:
            t0, t1 = stamps[p - 1], stamps[p]
            a = (t - t0) / (t1 - t0)
            out[j, :3, :3] = Slerp([t0, t1], rotations[[p - 1, p]])(t).as_matrix()   # the shorter arc
            out[j, :3, 3] = (1 - a) * poses[p - 1, :3, 3] + a * poses[p, :3, 3]
            valid[j] = True
            continue
        near = [k for k in (p - 1, p) if 0 <= k < len(stamps)]
        k = min(near, key=lambda k: abs(stamps[k] - t))
        if abs(stamps[k] - t) <= max_difference:
            out[j] = poses[k]
            valid[j] = True
    return valid, out


# --------------------------------------------------------------------------------------------------
# TUM trajectory files: "timestamp tx ty tz qx qy qz qw"
# --------------------------------------------------------------------------------------------------
def read_tum_trajectory(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory -> ``(stamps (N,), camera-to-world poses (N, 4, 4))``.

    Comment lines start with ``#``; commas are accepted as separators. Malformed rows raise
    :class:`DatasetError` naming the file and the line."""
    path = Path(path)
    try:
        from radiometry.textlists import read_list_text  # byte-order marks, CRLF, non-UTF-8 bytes

        text = read_list_text(path)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read the trajectory ({exc.strerror}); check the path") from None
    stamps, rows = [], []
    for lineno, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise DatasetError(f"{path}:{lineno}: TUM trajectory files must have 8 entries per row "
                               f"(timestamp tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            values = [float(v) for v in parts]
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: not numbers: {line!r}") from None
        if not np.all(np.isfinite(values)):
            raise DatasetError(f"{path}:{lineno}: non-finite value in {line!r}")
        q = np.array(values[4:8])
        if not 0.9 < np.linalg.norm(q) < 1.1:
            raise DatasetError(f"{path}:{lineno}: quaternion {values[4:8]} is not of unit length; "
                               "the columns must be tx ty tz qx qy qz qw")
        stamps.append(values[0])
        rows.append(values[1:])
    arr = np.asarray(rows, dtype=np.float64).reshape(-1, 7)
    poses = np.repeat(np.eye(4)[None], len(arr), axis=0)
    if len(arr):
        poses[:, :3, :3] = quaternion_to_matrix(arr[:, 3:7])
        poses[:, :3, 3] = arr[:, :3]
    return np.asarray(stamps, dtype=np.float64), poses


def format_tum_trajectory(stamps: np.ndarray, poses: np.ndarray) -> str:
    stamps = np.asarray(stamps, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(stamps) != len(poses):
        raise ValueError(f"stamps and poses must have one entry per pose, got {len(stamps)} and {len(poses)}")
    q = matrix_to_quaternion(poses[:, :3, :3]) if len(poses) else np.zeros((0, 4))
    lines = ["# timestamp tx ty tz qx qy qz qw (camera-to-world)"]
    for t, p, qq in zip(stamps, poses, q):
        lines.append(f"{t:.6f} " + " ".join(f"{v:.9f}" for v in (*p[:3, 3], *qq)))
    return "\n".join(lines) + "\n"


def write_tum_trajectory(path: str | os.PathLike, stamps: np.ndarray, poses: np.ndarray) -> Path:
    """Write camera-to-world poses as a TUM trajectory, atomically."""
    return atomic_write_text(path, format_tum_trajectory(stamps, poses))


# --------------------------------------------------------------------------------------------------
# alignment and ATE
# --------------------------------------------------------------------------------------------------
def umeyama_alignment(source: np.ndarray, target: np.ndarray, *, with_scale: bool = False
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``R, t, s`` with ``target ~ s R source + t`` (Umeyama 1991; Horn's closed form).

    ``source`` and ``target`` are (N, 3) corresponding points, N >= 3 and not collinear for a unique
    rotation (fewer points give the best translation-only fit)."""
    src = np.asarray(source, dtype=np.float64)
    dst = np.asarray(target, dtype=np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3:
        raise ValueError(f"source and target must be matching (N, 3) arrays, got {src.shape} and {dst.shape}")
    n = len(src)
    if n == 0:
        raise ValueError("cannot align empty trajectories")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    if n < 3:
        return np.eye(3), mu_d - mu_s, 1.0
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / (xs ** 2).sum(1).mean()) if with_scale else 1.0
    t = mu_d - s * R @ mu_s
    return R, t, s


@dataclass
class ATEResult:
    rmse: float
    mean: float
    median: float
    max: float
    pairs: int
    alignment: str
    scale: float = 1.0

    def to_dict(self) -> dict:
        return asdict(self)


def absolute_trajectory_error(est_stamps: np.ndarray, est_poses: np.ndarray, gt_stamps: np.ndarray,
                              gt_poses: np.ndarray, *, max_difference: float = 0.02,
                              align: str = "se3") -> ATEResult:
    """ATE of an estimated trajectory against ground truth (positions, metres).

    ``align``: ``"se3"`` (Horn: rotation + translation, the TUM benchmark's default), ``"sim3"`` (with scale,
    for monocular methods) or ``"none"``."""
    aligns = ("se3", "sim3", "none")
    if align not in aligns:
        raise ValueError(f"align must be one of {', '.join(aligns)}, got {align!r}")
    ie, ig = associate_timestamps(est_stamps, gt_stamps, max_difference=max_difference)
    if len(ie) == 0:
        raise ValueError(f"no estimated pose lies within {max_difference} s of a ground-truth pose; "
                         "check that both trajectories use the same clock")
    est = np.asarray(est_poses, dtype=np.float64)[ie, :3, 3]
    gt = np.asarray(gt_poses, dtype=np.float64)[ig, :3, 3]
    scale = 1.0
    if align != "none":
        R, t, scale = umeyama_alignment(est, gt, with_scale=(align == "sim3"))
        est = scale * est @ R.T + t
    err = np.linalg.norm(est - gt, axis=1)
    return ATEResult(rmse=float(np.sqrt(np.mean(err ** 2))), mean=float(err.mean()),
                     median=float(np.median(err)), max=float(err.max()), pairs=int(len(err)),
                     alignment=align, scale=float(scale))
