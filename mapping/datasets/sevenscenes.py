"""Microsoft 7-Scenes layout (Shotton et al., CVPR 2013).

::

    SEQ/[frames/]frame-NNNNNN.color.png|jpg   colour (640 x 480)
    SEQ/[frames/]frame-NNNNNN.depth.png       uint16 millimetres (1000 units per metre); 0 and 65535 = none
    SEQ/[frames/]frame-NNNNNN.pose.txt        4 x 4 camera-to-world (the KinectFusion poses shipped as truth)
    SEQ/camera-intrinsics.txt                 optional 3 x 3 K (or intrinsics.K.txt, camera_intrinsic.json);
                                              otherwise fx = fy = 585, cx = 320, cy = 240 (a warning)

7-Scenes has no timestamps: frame N is given ``N / 30`` s (the Kinect's 30 Hz). Non-finite poses (lost
KinectFusion frames) count as "no ground truth" for that frame.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapping.datasets._common import FileSequence, FrameFiles, optional_file, resolve_intrinsics
from radiometry.errors import DatasetError

log = logging.getLogger(__name__)

DEFAULT_INTRINSICS = np.array([[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1.0]])
DEFAULT_DEPTH_SCALE = 1000.0
FRAME_RATE = 30.0
#: intrinsics files read from the folder, its frames/ and its parent, in this order (tsdf-fusion's
#: camera-intrinsics.txt, 3DMatch's / SUN3D's intrinsics.K.txt, Open3D's camera_intrinsic.json)
INTRINSICS_FILES = ("camera-intrinsics.txt", "intrinsics.K.txt", "camera_intrinsic.json")
_COLOUR = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)


def _default_intrinsics(root: Path) -> tuple[np.ndarray, str]:
    log.warning("%s: no intrinsics file (%s); assuming 7-Scenes' Kinect (585, 585, 320, 240): pass --intrinsics "
                "fx,fy,cx,cy if this is another camera", root, ", ".join(INTRINSICS_FILES))
    return DEFAULT_INTRINSICS.copy(), "7-Scenes default (585, 585, 320, 240; assumed)"


def _frame_folder(path: Path) -> Path | None:
    for folder in (path, path / "frames"):
        if folder.is_dir() and any(_COLOUR.match(p.name) for p in folder.iterdir()):
            return folder
    return None


class SevenScenesDataset(FileSequence):
    """A 7-Scenes sequence folder (``seq-NN``), or a folder holding ``frames/`` and ``camera-intrinsics.txt``."""

    format_name = "7scenes"

    @classmethod
    def detect(cls, path: Path) -> bool:
        path = Path(path)
        return path.is_dir() and _frame_folder(path) is not None

    def __init__(self, path: str | Path, *, depth_scale: float | None = None, intrinsics=None,
                 frames: slice | Sequence[int] | None = None) -> None:
        root = Path(path)
        folder = _frame_folder(root) if root.is_dir() else None
        if folder is None:
            raise DatasetError(f"{root}: no frame-NNNNNN.color.* files here or in {root / 'frames'}; "
                               "pass a 7-Scenes sequence folder or --format")
        files = []
        for p in sorted(folder.iterdir()):
            m = _COLOUR.match(p.name)
            if not m:
                continue
            number = int(m.group(1))
            stem = f"frame-{m.group(1)}"
            depth = folder / f"{stem}.depth.png"
            if not depth.is_file():
                raise DatasetError(f"{p}: no matching depth image {depth.name}; every colour frame needs one")
            pose = folder / f"{stem}.pose.txt"
            files.append(FrameFiles(index=number, timestamp=number / FRAME_RATE, rgb=p, depth=depth,
                                    pose_file=optional_file(pose, "pose"), name=stem))
        files.sort(key=lambda f: f.index)
        numbers = [f.index for f in files]
        if len(set(numbers)) != len(numbers):
            raise DatasetError(f"{folder}: two colour images share a frame number; keep one format per frame")
        self.intrinsics_option = intrinsics  # a file given by --intrinsics has its image size checked
        K, self.intrinsics_source = resolve_intrinsics(
            intrinsics, [base / name for name in INTRINSICS_FILES for base in (root, folder, root.parent)],
            lambda: _default_intrinsics(root))
        super().__init__(root, files, K, depth_scale=DEFAULT_DEPTH_SCALE if depth_scale is None else depth_scale,
                         frames=frames, invalid_raw_depth=65535)
