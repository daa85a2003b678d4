"""TUM RGB-D layout (Sturm et al., IROS 2012).

::

    SEQ/rgb.txt            timestamp rgb/<timestamp>.png      ('#' comments)
    SEQ/depth.txt          timestamp depth/<timestamp>.png    (uint16, 5000 units per metre; 1000 detected:
                           :func:`recorder_depth_scale`)
    SEQ/groundtruth.txt    timestamp tx ty tz qx qy qz qw     (camera-to-world, optional)
    SEQ/associations.txt   optional (ORB-SLAM2's convention): 't_rgb rgb/X.png t_depth depth/X.png' per line;
                           when present it pairs the frames, in its order (see below)
    SEQ/intrinsics.txt     optional: 3 x 3 K (or 'fx fy cx cy'); also read: Open3D's camera_intrinsic.json,
                           intrinsics.K.txt, camera-intrinsics.txt (:data:`INTRINSICS_FILES`); otherwise by the
                           folder name (freiburg1/2/3, fr1/fr2/fr3), else fr1 with a warning

With ``associations.txt`` (what ORB-SLAM2's RGB-D examples read) its pairs are taken as listed, in the file's
order; when its colour timestamps do not increase (a recorder that wrote intervals instead of times) they
cannot order or date the frames: frame N is then given ``N / 30`` s, with a warning. Without it, colour and
depth are captured asynchronously: each colour frame is paired with the depth frame nearest in
time, one-to-one, and dropped when none lies within ``max_difference`` seconds (0.02 s, as evo's
``core/sync.py``). Ground truth is interpolated to the colour timestamps (linear position, slerp rotation)
between motion-capture samples at most ``gt_max_gap`` s apart.
"""

from __future__ import annotations

import logging
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapping.datasets._common import FileSequence, FrameFiles, data_lines, intrinsics_candidates, optional_file, \
    read_stamped_list, resolve_intrinsics
from mapping.metrics import associate_timestamps, interpolate_poses, read_tum_trajectory
from radiometry.errors import DatasetError, ImageError
from radiometry.images import read_depth

log = logging.getLogger(__name__)

#: the calibrated colour intrinsics of the three TUM RGB-D Kinects (fx, fy, cx, cy)
TUM_INTRINSICS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
DEFAULT_DEPTH_SCALE = 5000.0
#: the median depth (metres) of a recording read as millimetres for :func:`recorder_depth_scale` to detect it: a
#: camera's near range to 4 m (beyond, TUM's 5000 per metre gives a median over 0.8 m, as a room's)
MILLIMETRE_MEDIAN = (0.3, 4.0)
#: the frame rate assumed when a list's timestamps cannot date the frames
FRAME_RATE = 30.0


def tum_named_intrinsics(name: str) -> str | None:
    """The TUM Kinect a folder name names ('freiburg2' or 'fr2' as a word: rgbd_dataset_freiburg2_desk,
    fr2_desk, desk-fr2), or None."""
    for key in TUM_INTRINSICS:
        short = key.replace("reiburg", "r")
        if key in name or re.search(rf"(^|[^a-z0-9]){short}([^0-9]|$)", name.lower()):
            return key
    return None


def tum_default_intrinsics(root: Path) -> tuple[np.ndarray, str]:
    """Intrinsics of a TUM folder without an intrinsics file: by the 'freiburgN' / 'frN' in its name, else fr1
    (with a warning: an assumption)."""
    root = Path(root)
    key = tum_named_intrinsics(root.name)
    if key is not None:
        fx, fy, cx, cy = TUM_INTRINSICS[key]
        return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), f"TUM {key} (by the folder name)"
    fx, fy, cx, cy = TUM_INTRINSICS["freiburg1"]
    log.warning("%s: no intrinsics file (%s) and no 'freiburgN' in the folder name; assuming TUM freiburg1 "
                "intrinsics (%g, %g, %g, %g): pass --intrinsics fx,fy,cx,cy if this is another camera", root,
                ", ".join(("intrinsics.txt",) + INTRINSICS_FILES), fx, fy, cx, cy)
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), "TUM freiburg1 (assumed default)"


#: intrinsics files read from a TUM folder, in this order (after ``intrinsics.txt``)
INTRINSICS_FILES = ("camera_intrinsic.json", "intrinsics.K.txt", "camera-intrinsics.txt")


def recorder_depth_scale(depth_file: Path) -> tuple[float | None, str]:
    """The depth scale of a TUM-layout folder that does not say it (ORB-SLAM2-style recordings, what RealSense and
    Azure Kinect recorders write, with or without ``associations.txt``): TUM's own depth images hold the Kinect's
    millimetres times 5 (5000 per metre), so nearly all their values are multiples of 5 (the shared TUM frame:
    99.95 %); a recorder that writes millimetres (1000 per metre) does not (the RealSense office: 20 %).
    Returns ``(1000, why)`` with a warning when fewer than half of the first frame's valid values are multiples of
    5 and, read as millimetres, their median lies in :data:`MILLIMETRE_MEDIAN` (the office: 1.2 m); else
    ``(None, why)`` (TUM's 5000): depth simulated at 5000 per metre is not in multiples of 5 either, but its median
    is then a room's (the box room: 2.5 m at 5000, 12 m as millimetres)."""
    try:
        raw = read_depth(depth_file, 1.0)   # the raw values (units per metre 1)
    except (ImageError, ValueError):   # an unreadable image is reported when the frame is read
        return None, "5000 per metre (TUM's)"
    values = raw[raw > 0]
    if values.size < 1000:
        return None, "5000 per metre (TUM's; too little depth to check)"
    share = float(np.mean(values % 5 == 0))
    median_mm = float(np.median(values)) / 1000.0
    if share >= 0.5:
        return None, f"5000 per metre (TUM's: {100 * share:.0f} % of the values multiples of 5)"
    if not MILLIMETRE_MEDIAN[0] <= median_mm <= MILLIMETRE_MEDIAN[1]:
        return None, (f"5000 per metre (TUM's; {100 * share:.0f} % multiples of 5, but a median of "
                      f"{median_mm:.2g} m as millimetres)")
    log.warning("%s: %.0f %% of the depth values are multiples of 5 (TUM's Kinect data at 5000 per metre: ~100 %%); "
                "read as millimetres, 1000 per metre, as RealSense / ORB-SLAM2 recordings write them (median depth "
                "%.2f m; %.2f m at TUM's 5000); pass --depth-scale to override", depth_file, 100 * share, median_mm,
                median_mm / 5)
    return 1000.0, "1000 per metre (detected: depth in millimetres)"


def read_associations(path: Path) -> list[tuple[float, str, float, str, int]]:
    """ORB-SLAM2's ``associations.txt``: ``t_rgb rgb_file t_depth depth_file`` per line (``#`` comments), in the
    file's order; malformed lines raise :class:`DatasetError` naming the file and line."""
    rows = []
    for lineno, line, parts in data_lines(path, "the frame pairs"):
        if len(parts) != 4:
            raise DatasetError(f"{path}:{lineno}: expected 'rgb_timestamp rgb_file depth_timestamp depth_file' "
                               f"(ORB-SLAM2's associations), got {len(parts)} entries ({line!r}); fix or remove it")
        try:
            t_rgb, t_depth = float(parts[0]), float(parts[2])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: timestamps {parts[0]!r}, {parts[2]!r} are not numbers; fix the "
                               "line or remove the file") from None
        if not (np.isfinite(t_rgb) and np.isfinite(t_depth)):
            raise DatasetError(f"{path}:{lineno}: timestamps must be finite, got {line!r}")
        rows.append((t_rgb, parts[1], t_depth, parts[3], lineno))
    if not rows:
        raise DatasetError(f"{path}: lists no frame pairs; list one 't_rgb rgb_file t_depth depth_file' line per "
                           "frame or remove the file")
    names = [r[1] for r in rows]
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise DatasetError(f"{path}: colour image {twice} is listed twice; each frame must appear once")
    return rows


class TUMDataset(FileSequence):
    """A TUM RGB-D sequence folder (see the module documentation for the layout)."""

    format_name = "tum"
    #: the colour timestamps as listed (by frame number) when they cannot date the frames, else None
    listed_timestamps = None

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)  # a list that exists but is no file is refused by __init__, not taken for another layout
        return (os.path.lexists(path / "rgb.txt") and os.path.lexists(path / "depth.txt")) \
            or os.path.lexists(path / "associations.txt")

    def __init__(self, path: str | Path, *, depth_scale: float | None = None, intrinsics=None,
                 frames: slice | Sequence[int] | None = None, max_difference: float = 0.02,
                 gt_max_gap: float = 0.1) -> None:
        root = Path(path)
        if not self.detect(root):
            raise DatasetError(f"{root}: not a TUM RGB-D folder (needs rgb.txt and depth.txt, or associations.txt); "
                               "pass the sequence folder or --format")
        associations = optional_file(root / "associations.txt", "frame pairs (associations.txt)")
        if associations is not None:
            rows = read_associations(associations)
            rgb_t = np.array([r[0] for r in rows])
            pairs = [(r[1], r[3]) for r in rows]
            late = int(np.count_nonzero(np.diff(rgb_t) <= 0))
            if late:
                log.warning("%s: %d of %d colour timestamps do not increase (not times); frames kept in the file's "
                            "order, frame N dated N / %g s", associations, late, len(rows), FRAME_RATE)
                self.listed_timestamps = rgb_t   # what a trajectory writer (ORB-SLAM2) copies: --poses FILE
                rgb_t = np.arange(len(rows)) / FRAME_RATE
            self.pairing = {"associations": str(associations), "paired": len(rows),
                            "timestamps": "as listed" if not late else f"frame / {FRAME_RATE:g} s (listed ones "
                                                                         "do not increase)"}
        else:
            rgb_list = read_stamped_list(optional_file(root / "rgb.txt", "colour list"))
            depth_list = read_stamped_list(optional_file(root / "depth.txt", "depth list"))
            if not rgb_list or not depth_list:
                empty = "rgb.txt" if not rgb_list else "depth.txt"
                raise DatasetError(f"{root / empty}: lists no frames; the sequence is empty; list one 'timestamp "
                                   f"filename' line per {'colour' if empty == 'rgb.txt' else 'depth'} image, or "
                                   "pass a complete sequence folder")
            all_t = np.array([r[0] for r in rgb_list])
            depth_t = np.array([d[0] for d in depth_list])
            ia, ib = associate_timestamps(all_t, depth_t, max_difference=max_difference)
            if len(ia) == 0:
                raise DatasetError(f"{root}: no colour frame has a depth frame within {max_difference} s; "
                                   "check rgb.txt and depth.txt (same clock?)")
            if len(ia) < len(rgb_list):
                log.warning("%s: %d of %d colour frames have no depth frame within %g s and are dropped; %d frames "
                            "kept", root, len(rgb_list) - len(ia), len(rgb_list), max_difference, len(ia))
            self.pairing = {"max_difference": max_difference, "paired": int(len(ia)),
                            "colour_frames": len(rgb_list), "depth_frames": len(depth_list)}
            rgb_t = all_t[ia]
            pairs = [(rgb_list[a][1], depth_list[b][1]) for a, b in zip(ia, ib)]

        gt_poses = None
        gt_file = optional_file(root / "groundtruth.txt", "ground truth")
        self.ground_truth_file = gt_file   # its quaternions: mapping.pose_convention checks their order
        if gt_file is not None:
            gt_t, gt_p = read_tum_trajectory(gt_file)
            if len(gt_t):
                valid, poses = interpolate_poses(gt_t, gt_p, rgb_t, max_gap=gt_max_gap,
                                                 max_difference=max_difference)
                gt_poses = [p if v else None for v, p in zip(valid, poses)]
        files = []
        for k, (rgb_name, depth_name) in enumerate(pairs):
            files.append(FrameFiles(index=k, timestamp=float(rgb_t[k]), rgb=root / rgb_name, depth=root / depth_name,
                                    pose=None if gt_poses is None else gt_poses[k]))
        self.intrinsics_option = intrinsics  # a file given by --intrinsics has its image size checked
        K, self.intrinsics_source = resolve_intrinsics(
            intrinsics, intrinsics_candidates(root, ("intrinsics.txt",) + INTRINSICS_FILES),
            lambda: tum_default_intrinsics(root))
        self.depth_scale_source = "given" if depth_scale is not None else "5000 per metre (TUM's)"
        if depth_scale is None and files:
            depth_scale, self.depth_scale_source = recorder_depth_scale(files[0].depth)
        super().__init__(root, files, K, depth_scale=DEFAULT_DEPTH_SCALE if depth_scale is None else depth_scale,
                         frames=frames)
