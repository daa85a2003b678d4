"""The IN-MEMORY dataset: :class:`ArrayDataset`, RGB-D frames already in memory (made by code, not read).

The other homes of made-up data: :mod:`radiometry.simulation` is the simulated camera (response, vignetting,
exposure, noise); :mod:`mapping.simulation` renders simulated scenes and sequences with it and writes them
to folders with their ground truth; :mod:`mapping.datasets.simulated` reads those folders. The analytic box
room of the unit tests (``tests/box_room.py``) returns an :class:`ArrayDataset`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from mapping.datasets.base import RGBDFrame
from radiometry.errors import DatasetError


class ArrayDataset:
    """A dataset over frames held in memory (implements ``RGBDDataset``)."""

    #: ``ds[i]`` only returns a stored frame: safe from another thread (:mod:`mapping.prefetch`)
    thread_safe_reads = True

    def __init__(self, frames: Sequence[RGBDFrame], *, name: str = "arrays") -> None:
        frames = list(frames)
        if not frames:
            raise DatasetError(f"{name}: the sequence has no frames")
        h, w = frames[0].rgb.shape[:2]
        for f in frames:
            if f.rgb.shape[:2] != (h, w) or f.depth.shape != (h, w):
                raise DatasetError(f"{name}: frame {f.index} is {f.rgb.shape[1]}x{f.rgb.shape[0]} (depth "
                                   f"{f.depth.shape[::-1]}) while the sequence is {w}x{h}")
        self.frames = frames
        self.name = name
        self.K = np.asarray(frames[0].K, dtype=np.float64)
        self.width, self.height = int(w), int(h)

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, index: int) -> RGBDFrame:
        return self.frames[index]

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        known = [f for f in self.frames if f.pose is not None]
        if not known:
            return None
        return np.array([f.timestamp for f in known]), np.stack([f.pose for f in known])


__all__ = ["ArrayDataset"]
