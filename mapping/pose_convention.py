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

Quaternions written scalar-first. A TUM row is ``timestamp tx ty tz qx qy qz qw``; a file converted from EuRoC's
ground truth (``q_w q_x q_y q_z``), Eigen's ``w()`` first or a ROS tool often has ``qw qx qy qz`` there instead.
Read as TUM, every rotation is another one (the translation is right), the map fuses with exit 0, and even the ATE
is 0 (it aligns the positions only). For poses read from quaternions (``--poses FILE`` of the TUM kind, a TUM
folder's ``groundtruth.txt`` with ``--poses gt``) the same pairs are also compared with the quaternions read
scalar-first (:func:`scalar_first_reading`: ``(a, b, c, d)`` as read becomes ``(b, c, d, a)``), as they are and
inverted. When one of those agrees far better than the poses as given (the same :data:`MARGIN` and :data:`RATIO`
or :data:`MISS_RATIO`), the file is refused naming it, with the awk line that reorders its columns (and, when the
scalar-first reading agrees far better inverted than not, the inversion too). Measured on the kitchen's real
ground truth as a TUM file (as given / inverted / scalar-first / scalar-first inverted):

==================================  =========================  =========================
kitchen frames                      correct file               file written qw qx qy qz
==================================  =========================  =========================
0:100 (pairs 10 apart)              0.87 / 0.38 / 0.52 / 0.37  0.50 / 0.50 / 0.87 / 0.38
0:100:5                             0.61 / 0.07 / 0.13 / 0.09  0.12 / 0.18 / 0.61 / 0.07
50:70                               0.81 / 0.10 / 0.29 / 0.11  0.41 / 0.26 / 0.81 / 0.10
0:20 (1.5 degrees, 2 cm in all)     0.95 / 0.71 / 0.69 / 0.69  0.93 / 0.80 / 0.95 / 0.71
==================================  =========================  =========================

Written scalar-first AND inverted: 0:100 0.45 / 0.32 / 0.38 / 0.87, 0:100:5 0.09 / 0.05 / 0.07 / 0.61 (refused with
both fixes); 0:20 0.77 / 0.79 / 0.71 / 0.95 (0.18 more: below :data:`MARGIN`, accepted). The simulated room (14
frames): correct 0.87 / 0.41 / 0.31 / 0.17, written scalar-first 0.64 / 0.43 / 0.87 / 0.41 (refused). The repro
room: 0.09 / 0.11 / 0.00 / 0.07 (no overlap, no verdict). radiomap's own ICP trajectory.txt given back (frames
0:40): the RealSense office 0.55 / 0.27 / 0.27 / 0.32, the lamp shade 0.95 / 0.98 / 0.97 / 0.97 (accepted). Not
caught: a sequence that barely rotates, such as the kitchen's frames 0:20 (0.93 against 0.95): each relative
rotation keeps its angle under the wrong reading and only its axis turns, so small motions hardly change the depth; yet the colours are visibly worse (L1 29.4 against 20.1,
ATE 0 cm both). No file-only hint is used: how upright the camera stays (spread of its y axis) is 0.0014 correct
and 0.0018 scalar-first on the kitchen's 100 frames, and both readings of a first pose near the identity are
plausible (a half turn about x is OpenGL's camera frame), so neither tells the order.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

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
    """Ground-truth poses that look like world-to-camera where camera-to-world is expected, or a TUM file whose
    quaternions look scalar-first."""


def _far_better(other: float, given: float) -> bool:
    """``other`` agrees far better than ``given``: :data:`MARGIN` more and :data:`RATIO` times as much, or
    :data:`MARGIN` more and :data:`MISS_RATIO` times fewer pixels disagreeing."""
    return other >= given + MARGIN and (other >= RATIO * given or 1 - given >= MISS_RATIO * (1 - other))


#: the readings a check compares, in its order of preference on a tie
READINGS = ("as given", "inverted", "scalar-first", "scalar-first, inverted")


@dataclass(frozen=True)
class ConventionCheck:
    """The mean depth agreement of the pairs under the poses as given and under their inverses; for poses read
    from quaternions, also with the quaternions read scalar-first (``scalar_first``) and that inverted."""

    given: float
    inverted: float
    pairs: tuple[tuple[int, int], ...]
    scalar_first: float | None = None
    scalar_first_inverted: float | None = None

    def agreement(self) -> dict[str, float]:
        """``{reading: agreement}`` for the readings this check compared (:data:`READINGS`)."""
        values = (self.given, self.inverted, self.scalar_first, self.scalar_first_inverted)
        return {name: v for name, v in zip(READINGS, values) if v is not None}

    @property
    def verdict(self) -> str:
        """The reading the depth supports (:data:`READINGS`): another than ``"as given"`` only when it agrees far
        better than the poses as given (:func:`_far_better`); among the scalar-first ones, ``"scalar-first,
        inverted"`` only when it agrees far better than ``"scalar-first"``."""
        readings = self.agreement()
        best = max(readings, key=lambda k: (readings[k], -READINGS.index(k)))
        if best == "as given" or not _far_better(readings[best], self.given):
            return "as given"
        if best == "scalar-first, inverted" and not _far_better(readings[best], self.scalar_first):
            return "scalar-first"
        return best

    @property
    def looks_inverted(self) -> bool:
        return self.verdict in ("inverted", "scalar-first, inverted")

    @property
    def looks_scalar_first(self) -> bool:
        return self.verdict.startswith("scalar-first")


def scalar_first_reading(pose: np.ndarray) -> np.ndarray:
    """The pose a TUM row gives when its quaternion columns, read here as ``qx qy qz qw``, are really
    ``qw qx qy qz``: the rotation's quaternion ``(a, b, c, d)`` becomes ``(b, c, d, a)`` (its sign does not
    matter); the translation stays."""
    from mapping.metrics import matrix_to_quaternion, quaternion_to_matrix

    pose = np.array(pose, dtype=np.float64)
    q = matrix_to_quaternion(pose[:3, :3])
    pose[:3, :3] = quaternion_to_matrix(q[[1, 2, 3, 0]])
    return pose


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


def check_convention(frames, *, step: int = STEP, pairs: int = PAIRS, quaternions: bool = False
                     ) -> ConventionCheck | None:
    """Compare the depth agreement of pairs of ``frames`` (objects with ``depth``, ``K`` and ``pose``; indexable,
    e.g. a dataset; frames without a pose are skipped) under their poses and under the inverses; with
    ``quaternions`` (poses read from a TUM file) also with the quaternions read scalar-first
    (:func:`scalar_first_reading`), as they are and inverted. None when the sequence has fewer than 2 frames with
    poses."""
    n = len(frames)
    if n < 2:
        return None
    step = max(1, min(step, (n - 1) // 2 or 1))
    starts = sorted({int(s) for s in np.linspace(0, n - 1 - step, min(pairs, n - step))})
    agreement, used = [], []
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
        readings = [(Ta, Tb)]
        if quaternions:
            readings.append((scalar_first_reading(Ta), scalar_first_reading(Tb)))
        try:
            row = []
            for A, B in readings:
                row.append(depth_agreement(a.depth, a.K, b.depth, b.K, np.linalg.solve(B, A)))
                row.append(depth_agreement(a.depth, a.K, b.depth, b.K, B @ np.linalg.inv(A)))
        except np.linalg.LinAlgError:     # a singular pose is another check's to refuse
            continue
        agreement.append(row)
        used.append((i, i + step))
    if not used:
        return None
    mean = [float(v) for v in np.mean(agreement, axis=0)]
    return ConventionCheck(mean[0], mean[1], tuple(used), *mean[2:])


def reorder_command(path: Path) -> str:
    """The awk line that rewrites the TUM file ``path`` with its last four columns ``qw qx qy qz`` reordered to
    ``qx qy qz qw`` (comments and blank lines kept), into ``<name>_xyzw<suffix>`` beside it."""
    import shlex

    path = Path(path)
    try:
        commas = any("," in line for line in path.read_text(errors="replace").splitlines()
                     if not line.lstrip().startswith("#"))
    except OSError:
        commas = False
    fields = "-F'[ ,]+' " if commas else ""
    fixed = path.with_name(f"{path.stem}_xyzw{path.suffix}")
    return (f"awk {fields}'/^#/ || !NF {{print; next}} {{print $1, $2, $3, $4, $6, $7, $8, $5}}' "
            f"{shlex.quote(str(path))} > {shlex.quote(str(fixed))}")


def refuse_inverted_poses(frames, *, name: str = "the sequence", source: str = "its ground-truth poses",
                          quaternion_file=None) -> ConventionCheck | None:
    """:class:`PoseConventionError` (one line, the numbers and the fix) when :func:`check_convention` finds that
    the poses look inverted or, with ``quaternion_file`` (the TUM file the poses were read from), that its
    quaternions look scalar-first (``qw qx qy qz``); the check otherwise (logged at INFO)."""
    result = check_convention(frames, quaternions=quaternion_file is not None)
    if result is None:
        return None
    figures = ", ".join(f"{v:.2f} {k}" for k, v in result.agreement().items())
    log.info("%s: pose convention check: depth agreement %s (frame pairs %s)", name, figures, list(result.pairs))
    pairs = ", ".join(f"{i}-{j}" for i, j in result.pairs)
    if result.looks_scalar_first:
        inverted = result.verdict == "scalar-first, inverted"
        best = result.scalar_first_inverted if inverted else result.scalar_first
        raise PoseConventionError(
            f"{quaternion_file}: the quaternions look scalar-first (qw qx qy qz) where a TUM trajectory has "
            f"qx qy qz qw: the depth of frames {pairs} of {name} agrees at {100 * result.given:.0f} % of the "
            f"pixels as given and at {100 * best:.0f} % with the last four columns read as qw qx qy qz"
            + (" and the poses inverted (they also look world-to-camera)" if inverted else "")
            + f"; reorder the columns to qx qy qz qw: {reorder_command(Path(quaternion_file))}"
            + ("; then invert each pose (camera-to-world expected)" if inverted else ""))
    if result.looks_inverted:
        raise PoseConventionError(
            f"{name}: camera-to-world expected; {source} look like world-to-camera: the depth of frames {pairs} "
            f"agrees at {100 * result.given:.0f} % of the pixels under the poses as given and at "
            f"{100 * result.inverted:.0f} % under their inverses; invert each 4x4 pose (numpy.linalg.inv) in the "
            "file, or track with --poses icp")
    return result


__all__ = ["ConventionCheck", "MARGIN", "MISS_RATIO", "PAIRS", "PoseConventionError", "RATIO", "READINGS", "STEP",
           "check_convention", "depth_agreement", "refuse_inverted_poses", "reorder_command", "scalar_first_reading"]
