"""Poses from a file (``--poses FILE``): a trajectory another system estimated (ORB-SLAM, a T265, COLMAP, evo, an
earlier radiomap run) matched to a sequence's frames.

Three kinds, told apart by what the path is:

- a TUM trajectory (``timestamp tx ty tz qx qy qz qw``, camera-to-world; what radiomap writes as
  ``trajectory.txt``): each frame takes the pose nearest in time, one-to-one, within ``max_difference`` seconds
  (evo's ``sync.associate_trajectories``; :func:`mapping.metrics.associate_timestamps`); when the sequence's
  listed timestamps cannot date its frames (``listed_timestamps``, a TUM folder whose ``associations.txt`` stamps
  do not increase), each row takes the frame whose listed stamp it copies exactly, or the file is refused;
- a Redwood ``.log`` (``id id n`` then a 4 x 4 camera-to-world): by frame number (the frame's position in the full
  sequence, what :attr:`RGBDFrame.index` holds);
- a folder of 7-Scenes pose files (``frame-NNNNNN.pose.txt``): by frame number.

Frames without a pose are skipped (counted, with a warning); when too many lack one (``radiometry.quorum``'s rule:
fewer than 2 frames or 10 % of them keep a pose) the run is refused before it starts, naming the file and the fix.
"""

from __future__ import annotations

import logging
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radiometry.errors import DatasetError
from radiometry.quorum import rule_text, too_little

log = logging.getLogger(__name__)

#: the pose sources named by a word; anything else is a file or folder
POSE_KEYWORDS = ("icp", "gt")
#: the default largest time difference (seconds) between a frame and the trajectory pose it takes
DEFAULT_MAX_DIFFERENCE = 0.02
POSE_FILE_KINDS = ("tum", "redwood-log", "7scenes")
_SEVEN_SCENES_POSE = re.compile(r"^frame-(\d+)\.pose\.txt$", re.IGNORECASE)


class PoseFileError(DatasetError):
    """A trajectory given as ``--poses FILE`` cannot be read or does not fit the sequence."""


@dataclass(frozen=True)
class PoseTable:
    """The poses a file gives a sequence's selected frames: ``poses[i]`` (camera-to-world, or None: no pose) for
    the frame at position ``i``; ``matched`` frames have one."""

    source: Path
    kind: str
    poses: tuple
    max_difference: float | None = None

    def __len__(self) -> int:
        return len(self.poses)

    def __getitem__(self, i: int) -> np.ndarray | None:
        return self.poses[i]

    @property
    def matched(self) -> int:
        return sum(p is not None for p in self.poses)

    @property
    def reason(self) -> str:
        """A skipped frame's reason (frames.csv, metrics.json)."""
        return f"no pose in {self.source.name}"

    def describe(self) -> dict:
        return {"file": str(self.source), "kind": self.kind, "frames": len(self.poses), "matched": self.matched,
                **({} if self.max_difference is None else {"max_difference_s": self.max_difference})}

    def __str__(self) -> str:
        return str(self.source)


def is_pose_keyword(value) -> bool:
    return isinstance(value, str) and value in POSE_KEYWORDS


def pose_file_kind(path: str | os.PathLike) -> str:
    """Which kind of trajectory ``path`` is (:data:`POSE_FILE_KINDS`), or :class:`PoseFileError` naming it."""
    path = Path(path)
    if path.is_dir():
        if any(_SEVEN_SCENES_POSE.match(p.name) for p in path.iterdir()):
            return "7scenes"
        raise PoseFileError(f"{path}: a folder without frame-NNNNNN.pose.txt files; --poses takes icp, gt, a TUM "
                            "trajectory file, a Redwood .log or a folder of 7-Scenes pose files")
    if not path.is_file():
        raise PoseFileError(f"{path}: no such trajectory file or folder; --poses takes icp, gt, a TUM trajectory, a "
                            "Redwood .log or a folder of 7-Scenes pose files")
    return "redwood-log" if path.suffix.lower() == ".log" else "tum"


def read_pose_file(path: str | os.PathLike) -> tuple[str, np.ndarray, list[np.ndarray]]:
    """``(kind, keys, poses)``: timestamps (TUM) or frame numbers (``.log``, 7-Scenes) and camera-to-world poses."""
    from mapping.datasets._common import read_pose_matrix_file
    from mapping.datasets.redwood import read_log_trajectory
    from mapping.metrics import read_tum_trajectory

    path = Path(path)
    kind = pose_file_kind(path)
    if kind == "tum":
        stamps, poses = read_tum_trajectory(path)
        keys, poses = np.asarray(stamps, dtype=np.float64), list(poses)
    elif kind == "redwood-log":
        table = read_log_trajectory(path)
        keys, poses = np.array(sorted(table), dtype=np.int64), [table[k] for k in sorted(table)]
    else:
        found = {}
        for p in path.iterdir():
            m = _SEVEN_SCENES_POSE.match(p.name)
            if m:
                pose = read_pose_matrix_file(p)
                if pose is not None:   # 7-Scenes marks lost frames with inf
                    found[int(m.group(1))] = pose
        keys, poses = np.array(sorted(found), dtype=np.int64), [found[k] for k in sorted(found)]
    if len(poses) == 0:
        raise PoseFileError(f"{path}: holds no pose; pass the trajectory of this sequence")
    return kind, keys, poses


def _frame_keys(dataset) -> tuple[np.ndarray, np.ndarray]:
    """The selected frames' timestamps and frame numbers (without reading images when the dataset lists its
    files)."""
    files = getattr(dataset, "frame_files", None)
    if files is not None:
        return (np.array([f.timestamp for f in files], dtype=np.float64),
                np.array([f.index for f in files], dtype=np.int64))
    frames = [dataset[i] for i in range(len(dataset))]
    return (np.array([f.timestamp for f in frames], dtype=np.float64),
            np.array([f.index for f in frames], dtype=np.int64))


#: a trajectory's timestamp equals a listed one when they differ by less (ORB-SLAM2 writes 6 decimals)
LISTED_STAMP_TOLERANCE = 1e-6


def _exact_rows(clock: np.ndarray, keys: np.ndarray) -> dict[int, int] | None:
    """``{frame number: row}`` when the rows' timestamps equal ``clock`` (by frame number) row by row from frame
    0 (a trajectory of every frame, or of the first ones: listed stamps may repeat, the office's frames 22 and 23
    are 2.4e-7 s apart), or when each equals exactly one of ``clock`` and the rows follow its order (lost frames
    left out); else None."""
    if len(keys) <= len(clock) and np.all(np.abs(clock[:len(keys)] - keys) <= LISTED_STAMP_TOLERANCE):
        return {i: i for i in range(len(keys))}
    rows = {}
    for row, key in enumerate(keys):
        hits = np.flatnonzero(np.abs(clock - key) <= LISTED_STAMP_TOLERANCE)
        if len(hits) != 1 or int(hits[0]) in rows:
            return None
        rows[int(hits[0])] = row
    return rows if list(rows) == sorted(rows) else None


def _match_listed(path: Path, listed: np.ndarray, numbers: np.ndarray, keys: np.ndarray) -> dict[int, int]:
    """``{position of a selected frame: row of the trajectory}`` when every row's timestamp copies exactly one of
    the list's colour timestamps (``listed``, by frame number; ORB-SLAM2's CameraTrajectory.txt) or of the frames'
    dates (frame / 30 s: radiomap's trajectory.txt), in order; else :class:`PoseFileError`. A list whose stamps do
    not increase cannot date the frames, so matching by the nearest time gives frames another frame's pose (the
    office with its ORB-SLAM2 trajectory: frame 0 took frame 13's)."""
    from mapping.datasets.tum import FRAME_RATE

    listed = np.asarray(listed, dtype=np.float64)
    rows = _exact_rows(listed, keys)
    if rows is None:
        rows = _exact_rows(np.arange(len(listed)) / FRAME_RATE, keys)
    if rows is None:
        raise PoseFileError(
            f"{path}: cannot be matched to the frames: the sequence's listed colour timestamps do not increase (not "
            f"times; frames are dated frame / {FRAME_RATE:g} s), so poses cannot be matched by the nearest time, and "
            f"the file's {len(keys)} timestamps are not, in order, copies of the listed ones nor of the frames' "
            "dates; give the trajectory with the list's own timestamps (ORB-SLAM2's CameraTrajectory.txt), "
            "radiomap's trajectory.txt of this sequence, or a Redwood .log (pose N = frame N)")
    return {i: rows[int(n)] for i, n in enumerate(numbers) if int(n) in rows}


def match_pose_file(dataset, path: str | os.PathLike, *, max_difference: float = DEFAULT_MAX_DIFFERENCE
                    ) -> PoseTable:
    """The poses ``path`` gives the frames of ``dataset`` (module doc); :class:`PoseFileError` when too few match."""
    from mapping.metrics import associate_timestamps

    if not (isinstance(max_difference, (int, float)) and np.isfinite(max_difference) and max_difference >= 0):
        raise ValueError(f"--poses-max-difference must be a non-negative number of seconds, got {max_difference!r}")
    path = Path(path)
    kind, keys, poses = read_pose_file(path)
    stamps, numbers = _frame_keys(dataset)
    out: list[np.ndarray | None] = [None] * len(stamps)
    listed = getattr(dataset, "listed_timestamps", None)
    if kind == "tum" and listed is not None:   # the list's stamps cannot date the frames: match them as copied
        for a, b in _match_listed(path, listed, numbers, keys).items():
            out[a] = np.array(poses[b], dtype=np.float64)
        how = "no pose with their listed timestamp"
        fix = "check that the trajectory belongs to this sequence"
    elif kind == "tum":
        ia, ib = associate_timestamps(stamps, keys, max_difference=max_difference)
        for a, b in zip(ia, ib):
            out[a] = np.array(poses[b], dtype=np.float64)
        how = f"no pose within {max_difference:g} s of their timestamps"
        fix = ("check that the trajectory belongs to this sequence and uses its clock (radiomap writes the frames' "
               f"timestamps; TUM lists' own), or raise --poses-max-difference (now {max_difference:g} s)")
    else:
        by_number = {int(k): p for k, p in zip(keys, poses)}
        for i, number in enumerate(numbers):
            if int(number) in by_number:
                out[i] = np.array(by_number[int(number)], dtype=np.float64)
        how = "no pose for their frame numbers"
        fix = ("check that the trajectory belongs to this sequence (frame N of the file is the sequence's frame N, "
               "counted from 0 before --frames)")
    table = PoseTable(path, kind, tuple(out), max_difference if kind == "tum" and listed is None else None)
    n, matched = len(out), table.matched
    if too_little(matched, n):
        raise PoseFileError(f"{path}: {n - matched} of {n} frames have {how}; a run needs {rule_text()} with a "
                            f"pose; {fix}")
    if matched < n:
        log.warning("%s: %d of %d frames have %s and are skipped", path, n - matched, n, how)
    _refuse_inverted(dataset, table)
    return table


class _FramesWithPoses:
    """The frames of ``dataset`` with the poses of ``table`` in place of their own (for the convention check)."""

    def __init__(self, dataset, table: PoseTable):
        self.dataset, self.table = dataset, table

    def __len__(self) -> int:
        return len(self.table)

    def __getitem__(self, i: int):
        from types import SimpleNamespace

        frame = self.dataset[i]
        return SimpleNamespace(depth=frame.depth, K=frame.K, pose=self.table[i])


def _refuse_inverted(dataset, table: PoseTable) -> None:
    """A file of world-to-camera poses is refused like such ground truth (:mod:`mapping.pose_convention`): as
    given it fuses without an error and a good-looking ATE (the kitchen inverted, 20 frames: ATE 2 cm, L1 72.9
    against 45.3); so is a TUM file whose quaternions look scalar-first (``qw qx qy qz``)."""
    from mapping.pose_convention import refuse_inverted_poses

    name = getattr(dataset, "root", None) or getattr(dataset, "name", "the sequence")
    refuse_inverted_poses(_FramesWithPoses(dataset, table), name=str(name), source=f"the poses of {table.source}",
                          quaternion_file=table.source if table.kind == "tum" else None)


def resolve_poses(value, dataset, *, max_difference: float = DEFAULT_MAX_DIFFERENCE):
    """``"icp"`` or ``"gt"`` as they are, a path as the :class:`PoseTable` it gives ``dataset``."""
    if is_pose_keyword(value):
        return value
    if isinstance(value, PoseTable):
        return value
    if isinstance(value, (str, os.PathLike)):
        return match_pose_file(dataset, value, max_difference=max_difference)
    raise ValueError(f"poses must be 'icp', 'gt' or a trajectory file, got {value!r}")


def pose_source_name(value) -> str:
    """How a pose source is named in summaries: ``icp``, ``gt`` or the file's path."""
    return value if is_pose_keyword(value) else str(value)


__all__ = ["DEFAULT_MAX_DIFFERENCE", "POSE_FILE_KINDS", "POSE_KEYWORDS", "PoseFileError", "PoseTable",
           "is_pose_keyword", "match_pose_file", "pose_file_kind", "pose_source_name", "read_pose_file",
           "resolve_poses"]
