"""Redwood / Open3D layout (Choi, Zhou, Koltun; Open3D's RGBD test data).

::

    SEQ/color/*.jpg|png  (or image/ or rgb/)   colour
    SEQ/depth/*.png                            uint16 millimetres (1000 units per metre)
    SEQ/rgbd.match                             optional 'depth/NNNNN.png color/NNNNN.jpg' pairs;
                                               otherwise both folders are paired in sorted order
    SEQ/trajectory.log                         optional ground truth, Redwood .log: per frame a line
                                               'frame_id frame_id n_frames' then a 4 x 4 camera-to-world
    SEQ/camera_intrinsic.json | camera_primesense.json | ...   optional intrinsics (:data:`CAMERA_FILES`: Open3D
                                               camera JSON, intrinsic_matrix column-major, or a 3 x 3 text
                                               matrix); otherwise PrimeSense 525, 525, 319.5, 239.5 (a warning)

Redwood has no timestamps: frame N is given ``N / 30`` s.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapping.datasets._common import FileSequence, FrameFiles, check_pose, intrinsics_candidates, optional_file, \
    read_text, resolve_intrinsics
from radiometry.errors import DatasetError
from radiometry.fileio import atomic_write_text
from radiometry.images import IMAGE_EXTENSIONS
from radiometry.textlists import list_lines

log = logging.getLogger(__name__)

DEFAULT_INTRINSICS = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1.0]])
DEFAULT_DEPTH_SCALE = 1000.0
FRAME_RATE = 30.0
COLOUR_FOLDERS = ("color", "image", "rgb")
#: intrinsics files read from the folder (then its parent), in this order: Open3D's recorder writes
#: camera_intrinsic.json; tsdf-fusion / 3DMatch layouts hold camera-intrinsics.txt or intrinsics.K.txt
CAMERA_FILES = ("camera_intrinsic.json", "camera_primesense.json", "camera.json", "intrinsic.json",
                "intrinsics.json", "intrinsics.K.txt", "camera-intrinsics.txt", "intrinsics.txt")


def read_log_trajectory(path: str | os.PathLike) -> dict[int, np.ndarray]:
    """Read a Redwood ``.log`` trajectory -> ``{frame_id: camera-to-world (4, 4)}``.

    Malformed blocks raise :class:`DatasetError` naming the file and line."""
    path = Path(path)
    lines = read_text(path, "the trajectory").splitlines()
    rows = [(i + 1, ln.strip()) for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    if len(rows) % 5:
        lineno = rows[-(len(rows) % 5)][0]
        raise DatasetError(f"{path}:{lineno}: incomplete block; a .log trajectory holds per frame one line of "
                           "three ids and four lines of four numbers")
    poses: dict[int, np.ndarray] = {}
    for b in range(0, len(rows), 5):
        lineno, head = rows[b]
        parts = head.split()
        try:
            ids = [int(v) for v in parts]
        except ValueError:
            ids = []
        if len(ids) != 3:
            raise DatasetError(f"{path}:{lineno}: expected three integer ids (frame_id frame_id n), got {head!r}")
        matrix = []
        for lineno_r, text in rows[b + 1:b + 5]:
            try:
                vals = [float(v) for v in text.split()]
            except ValueError:
                raise DatasetError(f"{path}:{lineno_r}: not numbers: {text!r}") from None
            if len(vals) != 4:
                raise DatasetError(f"{path}:{lineno_r}: a matrix row needs 4 numbers, got {len(vals)}")
            matrix.append(vals)
        if ids[0] in poses:
            raise DatasetError(f"{path}:{lineno}: frame {ids[0]} appears twice")
        pose = check_pose(np.array(matrix), f"{path}:{rows[b + 1][0]}")
        if pose is not None:
            poses[ids[0]] = pose
    return poses


def write_log_trajectory(path: str | os.PathLike, poses: Sequence[np.ndarray]) -> Path:
    """Write camera-to-world poses as a Redwood ``.log`` file (frame ids 0..N-1), atomically."""
    out = []
    for i, p in enumerate(poses):
        out.append(f"{i} {i} {i + 1}")
        out.extend(" ".join(f"{v:.10g}" for v in row) for row in np.asarray(p, dtype=np.float64))
    return atomic_write_text(path, "\n".join(out) + "\n")


def _default_intrinsics(root: Path) -> tuple[np.ndarray, str]:
    log.warning("%s: no intrinsics file (%s); assuming the PrimeSense default (525, 525, 319.5, 239.5): pass "
                "--intrinsics fx,fy,cx,cy if this is another camera", root, ", ".join(CAMERA_FILES[:3]) + ", ...")
    return DEFAULT_INTRINSICS.copy(), "PrimeSense default (525, 525, 319.5, 239.5; assumed)"


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS)


class RedwoodDataset(FileSequence):
    """A Redwood/Open3D RGB-D folder (see the module documentation)."""

    format_name = "redwood"

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        return (path / "depth").is_dir() and any((path / c).is_dir() for c in COLOUR_FOLDERS)

    def __init__(self, path: str | Path, *, depth_scale: float | None = None, intrinsics=None,
                 frames: slice | Sequence[int] | None = None, trajectory: str | Path | None = None) -> None:
        root = Path(path)
        if not self.detect(root):
            raise DatasetError(f"{root}: not a Redwood/Open3D folder (needs depth/ and color/); "
                               "pass the sequence folder or --format")
        colour_dir = next(root / c for c in COLOUR_FOLDERS if (root / c).is_dir())
        match = optional_file(root / "rgbd.match", "frame pairing (rgbd.match)")
        pairs: list[tuple[Path, Path]] = []
        if match is not None:
            for lineno, line in list_lines(match):
                line = line.strip()
                if not line or line.startswith("#"):
                    continue
                parts = line.split()
                if len(parts) != 2:
                    raise DatasetError(f"{match}:{lineno}: expected 'depth_file colour_file', got {line!r}")
                pairs.append((root / parts[1], root / parts[0]))
        else:
            colours, depths = _images(colour_dir), _images(root / "depth")
            if len(colours) != len(depths):
                raise DatasetError(f"{root}: {len(colours)} colour images but {len(depths)} depth images and no "
                                   "rgbd.match to pair them; add rgbd.match or remove the extra images")
            pairs = list(zip(colours, depths))
        gt: dict[int, np.ndarray] = {}
        traj = Path(trajectory) if trajectory is not None else root / "trajectory.log"
        if trajectory is not None and not traj.is_file():
            raise DatasetError(f"{traj}: no such trajectory file")
        if optional_file(traj, "ground-truth trajectory") is not None:
            gt = read_log_trajectory(traj)
            if gt and max(gt) >= len(pairs):
                raise DatasetError(f"{traj}: has a pose for frame {max(gt)} but the sequence has {len(pairs)} "
                                   "frames; is it the trajectory of this sequence?")
        self.trajectory_file = traj if traj.is_file() else None
        files = [FrameFiles(index=i, timestamp=i / FRAME_RATE, rgb=c, depth=d, pose=gt.get(i))
                 for i, (c, d) in enumerate(pairs)]
        self.intrinsics_option = intrinsics  # a file given by --intrinsics has its image size checked
        K, self.intrinsics_source = resolve_intrinsics(
            intrinsics, intrinsics_candidates(root, CAMERA_FILES, parent=True), lambda: _default_intrinsics(root))
        super().__init__(root, files, K, depth_scale=DEFAULT_DEPTH_SCALE if depth_scale is None else depth_scale,
                         frames=frames)
