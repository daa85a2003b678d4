"""Is a trajectory camera-to-world, as the project expects, or its inverse (world-to-camera)?

A common mix-up between conventions: poses that are the inverse of camera-to-world fuse without an error, but the
map is visibly worse and half the samples land nowhere (issue 31: kitchen L1 21.9 against 15.0). The check needs
no map: for a few pairs of frames ``(i, j)`` spread over the sequence, the depth of frame ``i`` is back-projected,
moved into frame ``j`` by the poses (``T_j^-1 T_i``) and compared with frame ``j``'s depth; the fraction of
pixels that agree (within 3 cm + 3 % of the depth) is the pair's agreement. The same is done with every pose
inverted. Under the right convention the depth of two views of one scene agrees; under the wrong one it only
agrees where the motion is small. When the inverses agree far better (:data:`MARGIN` more and
:data:`RATIO` times as much, or :data:`MARGIN` more and :data:`MISS_RATIO` times fewer pixels disagreeing, over pairs
far enough apart for the two to differ), the poses are refused (:class:`PoseConventionError`) with the fix. The
check runs on ground truth (``--poses gt``) and on every pose file (``--poses FILE``: TUM, Redwood ``.log``,
7-Scenes pose files; :mod:`mapping.pose_files`).

Measured (agreement as given / inverted; with the poses inverted on purpose the two swap): the 7-Scenes kitchen
(100 frames, 4 pairs 10 frames apart) 0.87 / 0.38; the simulated sample room (30 frames) 0.84 / 0.55; Open3D's
living-room frames (5) 0.95 / 0.54; the repro room of ``repro/tsdf_segfault_room`` 0.09 / 0.11 (no overlap at
that step: no verdict, no alarm). Pairs 1 frame apart barely differ (kitchen 0.96 vs 0.91), which is why the
pairs are taken :data:`STEP` frames apart (fewer on short sequences).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from radiometry.errors import DatasetError, RadiomapError

log = logging.getLogger(__name__)

#: frames between the two of a pair (fewer when the sequence is short)
STEP = 10
#: pairs compared
PAIRS = 4
#: every STRIDE-th pixel of each row and column is back-projected
STRIDE = 8
#: depth agreement: metres + fraction of the depth
TOLERANCE = (0.03, 0.03)
#: the inverted poses must agree this much more (absolute fraction) ...
MARGIN = 0.2
#: ... and this many times as much as the poses as given, for a refusal ...
RATIO = 1.4
#: ... or disagree this many times less (a short sequence: the kitchen's frames 0-19 inverted in a file agree at
#: 0.71 as given and 0.95 inverted, 0.29 against 0.05 disagreeing)
MISS_RATIO = 2.0


class PoseConventionError(DatasetError):
    """Ground-truth poses that look like world-to-camera where camera-to-world is expected."""


@dataclass(frozen=True)
class ConventionCheck:
    """The mean depth agreement of the pairs under the poses as given and under their inverses."""

    given: float
    inverted: float
    pairs: tuple[tuple[int, int], ...]

    @property
    def looks_inverted(self) -> bool:
        return self.inverted >= self.given + MARGIN and (self.inverted >= RATIO * self.given
                                                         or 1 - self.given >= MISS_RATIO * (1 - self.inverted))


def depth_agreement(depth_i: np.ndarray, K_i: np.ndarray, depth_j: np.ndarray, K_j: np.ndarray,
                    i_to_j: np.ndarray, *, stride: int = STRIDE, tolerance: tuple[float, float] = TOLERANCE) -> float:
    """The fraction of frame ``i``'s valid depth pixels (every ``stride``-th) that land in frame ``j`` moved by
    ``i_to_j`` (4x4, camera i -> camera j) at a depth that agrees with ``depth_j``; 0 when ``i`` has no depth."""
    h, w = depth_i.shape
    v, u = np.mgrid[0:h:stride, 0:w:stride]
    z = depth_i[::stride, ::stride]
    ok = np.isfinite(z) & (z > 0)
    if not ok.any():
        return 0.0
    z, u, v = z[ok].astype(np.float64), u[ok], v[ok]
    points = np.stack([(u - K_i[0, 2]) / K_i[0, 0] * z, (v - K_i[1, 2]) / K_i[1, 1] * z, z])
    q = i_to_j[:3, :3] @ points + i_to_j[:3, 3:4]
    zq = q[2]
    front = zq > 1e-3
    safe = np.where(front, zq, 1.0)
    uq = np.round(K_j[0, 0] * q[0] / safe + K_j[0, 2])
    vq = np.round(K_j[1, 1] * q[1] / safe + K_j[1, 2])
    hj, wj = depth_j.shape
    inside = front & (uq >= 0) & (uq < wj) & (vq >= 0) & (vq < hj)
    seen = np.zeros_like(zq)
    seen[inside] = depth_j[vq[inside].astype(int), uq[inside].astype(int)]
    agree = inside & (seen > 0) & (np.abs(seen - zq) <= tolerance[0] + tolerance[1] * zq)
    return float(agree.sum()) / float(len(z))


def check_convention(frames, *, step: int = STEP, pairs: int = PAIRS) -> ConventionCheck | None:
    """Compare the depth agreement of pairs of ``frames`` (objects with ``depth``, ``K`` and ``pose``; indexable,
    e.g. a dataset; frames without a pose are skipped) under their poses and under the inverses. None when the
    sequence has fewer than 2 frames with poses."""
    n = len(frames)
    if n < 2:
        return None
    step = max(1, min(step, (n - 1) // 2 or 1))
    starts = sorted({int(s) for s in np.linspace(0, n - 1 - step, min(pairs, n - step))})
    given, inverted, used = [], [], []
    for i in starts:
        try:
            a, b = frames[i], frames[i + step]
        except RadiomapError:             # a bad frame is the run's to report, at its place in the sequence
            continue
        if a.pose is None or b.pose is None:
            continue
        Ta, Tb = np.asarray(a.pose, np.float64), np.asarray(b.pose, np.float64)
        if not (np.all(np.isfinite(Ta)) and np.all(np.isfinite(Tb))):
            continue
        try:
            given.append(depth_agreement(a.depth, a.K, b.depth, b.K, np.linalg.solve(Tb, Ta)))
            inverted.append(depth_agreement(a.depth, a.K, b.depth, b.K, Tb @ np.linalg.inv(Ta)))
        except np.linalg.LinAlgError:     # a singular pose is another check's to refuse
            continue
        used.append((i, i + step))
    if not used:
        return None
    return ConventionCheck(float(np.mean(given)), float(np.mean(inverted)), tuple(used))


def refuse_inverted_poses(frames, *, name: str = "the sequence", source: str = "its ground-truth poses") -> \
        ConventionCheck | None:
    """:class:`PoseConventionError` (one line, the numbers and the fix) when :func:`check_convention` finds that
    the poses look inverted; the check otherwise (logged at INFO)."""
    result = check_convention(frames)
    if result is None:
        return None
    log.info("%s: pose convention check: depth agreement %.2f as given, %.2f inverted (frame pairs %s)", name,
             result.given, result.inverted, list(result.pairs))
    if result.looks_inverted:
        pairs = ", ".join(f"{i}-{j}" for i, j in result.pairs)
        raise PoseConventionError(
            f"{name}: camera-to-world expected; {source} look like world-to-camera: the depth of frames {pairs} "
            f"agrees at {100 * result.given:.0f} % of the pixels under the poses as given and at "
            f"{100 * result.inverted:.0f} % under their inverses; invert each 4x4 pose (numpy.linalg.inv) in the "
            "file, or track with --poses icp")
    return result


__all__ = ["ConventionCheck", "MARGIN", "MISS_RATIO", "PAIRS", "PoseConventionError", "RATIO", "STEP", "check_convention",
           "depth_agreement", "refuse_inverted_poses"]
