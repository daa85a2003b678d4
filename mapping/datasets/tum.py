"""TUM RGB-D layout (Sturm et al., IROS 2012).

::

    SEQ/rgb.txt            timestamp rgb/<timestamp>.png      ('#' comments)
    SEQ/depth.txt          timestamp depth/<timestamp>.png    (uint16, 5000 units per metre)
    SEQ/groundtruth.txt    timestamp tx ty tz qx qy qz qw     (camera-to-world, optional)
    SEQ/intrinsics.txt     optional: 3 x 3 K (or 'fx fy cx cy'); otherwise by the folder name
                           (freiburg1/2/3) or fr1

Colour and depth are captured asynchronously: each colour frame is paired with the depth frame nearest in
time, one-to-one, and dropped when none lies within ``max_difference`` seconds (0.02 s, as evo's
``core/sync.py``). Ground truth is interpolated to the colour timestamps (linear position, slerp rotation)
between motion-capture samples at most ``gt_max_gap`` s apart.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapping.datasets._common import FileSequence, FrameFiles, optional_file, read_intrinsics_file, \
    read_stamped_list, resolve_intrinsics
from mapping.metrics import associate_timestamps, interpolate_poses, read_tum_trajectory
from radiometry.errors import DatasetError

log = logging.getLogger(__name__)

#: the calibrated colour intrinsics of the three TUM RGB-D Kinects (fx, fy, cx, cy)
TUM_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
DEFAULT_DEPTH_SCALE = 5000.0


def tum_default_intrinsics(root: Path) -> tuple[np.ndarray, str]:
    """Intrinsics of a TUM folder: ``intrinsics.txt`` if present, else by the 'freiburgN' in its name, else fr1."""
    root = Path(root)
    own = optional_file(root / "intrinsics.txt", "camera intrinsics")
    if own is not None:
        return read_intrinsics_file(own), str(own)
    for key, (fx, fy, cx, cy) in TUM_INTRINSICS.items():
        if key in root.name or key.replace("reiburg", "r") + "_" in root.name:
            return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), f"TUM {key}"
    fx, fy, cx, cy = TUM_INTRINSICS["freiburg1"]
    log.info("%s: no intrinsics.txt and no 'freiburgN' in the name; assuming TUM freiburg1 intrinsics", root)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), "TUM freiburg1 (default)"


class TUMDataset(FileSequence):
    """A TUM RGB-D sequence folder (see the module documentation for the layout)."""

    format_name = "tum"

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)  # a list that exists but is no file is refused by __init__, not taken for another layout
        return os.path.lexists(path / "rgb.txt") and os.path.lexists(path / "depth.txt")

    def __init__(self, path: str | Path, *, depth_scale: float | None = None, intrinsics=None,
                 frames: slice | Sequence[int] | None = None, max_difference: float = 0.02,
                 gt_max_gap: float = 0.1) -> None:
        root = Path(path)
        if not self.detect(root):
            raise DatasetError(f"{root}: not a TUM RGB-D folder (needs rgb.txt and depth.txt); "
                               "pass the sequence folder or --format")
        rgb_list = read_stamped_list(optional_file(root / "rgb.txt", "colour list"))
        depth_list = read_stamped_list(optional_file(root / "depth.txt", "depth list"))
        if not rgb_list or not depth_list:
            empty = "rgb.txt" if not rgb_list else "depth.txt"
            raise DatasetError(f"{root / empty}: lists no frames; the sequence is empty; list one 'timestamp "
                               f"filename' line per {'colour' if empty == 'rgb.txt' else 'depth'} image, or pass a "
                               "complete sequence folder")
        rgb_t = np.array([r[0] for r in rgb_list])
        depth_t = np.array([d[0] for d in depth_list])
        ia, ib = associate_timestamps(rgb_t, depth_t, max_difference=max_difference)
        if len(ia) == 0:
            raise DatasetError(f"{root}: no colour frame has a depth frame within {max_difference} s; "
                               "check rgb.txt and depth.txt (same clock?)")
        if len(ia) < len(rgb_list):
            log.warning("%s: %d of %d colour frames have no depth frame within %g s and are dropped; %d frames kept",
                        root, len(rgb_list) - len(ia), len(rgb_list), max_difference, len(ia))
        self.pairing = {"max_difference": max_difference, "paired": int(len(ia)), "colour_frames": len(rgb_list),
                        "depth_frames": len(depth_list)}

        gt_poses = None
        gt_file = optional_file(root / "groundtruth.txt", "ground truth")
        if gt_file is not None:
            gt_t, gt_p = read_tum_trajectory(gt_file)
            if len(gt_t):
                valid, poses = interpolate_poses(gt_t, gt_p, rgb_t[ia], max_gap=gt_max_gap,
                                                 max_difference=max_difference)
                gt_poses = [p if v else None for v, p in zip(valid, poses)]
        files = []
        for k, (a, b) in enumerate(zip(ia, ib)):
            files.append(FrameFiles(index=k, timestamp=float(rgb_t[a]), rgb=root / rgb_list[a][1],
                                    depth=root / depth_list[b][1],
                                    pose=None if gt_poses is None else gt_poses[k]))
        K, self.intrinsics_source = resolve_intrinsics(intrinsics, (), lambda: tum_default_intrinsics(root))
        super().__init__(root, files, K, depth_scale=DEFAULT_DEPTH_SCALE if depth_scale is None else depth_scale,
                         frames=frames)
