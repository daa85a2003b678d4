"""The loader contract: every dataset format yields :class:`RGBDFrame` objects."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True, eq=False)
class RGBDFrame:
    """One colour + depth observation.

    rgb:   (H, W, 3) uint8, RGB order.
    depth: (H, W) float32 metres, 0 = no reading. Same size as ``rgb``.
    K:     (3, 3) float64 pinhole intrinsics of the colour image.
    pose:  (4, 4) float64 camera-to-world ground truth, or None.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    pose: np.ndarray | None = None
    name: str = ""

    @property
    def height(self) -> int:
        return int(self.rgb.shape[0])

    @property
    def width(self) -> int:
        return int(self.rgb.shape[1])


@runtime_checkable
class RGBDDataset(Protocol):
    """What the pipeline needs from a sequence (frame range and stride already applied).

    Optional: a class attribute ``thread_safe_reads = True`` declares that ``ds[i]`` may run in a background
    thread while the caller still uses the frame before it (each read returns new arrays, no state is shared with
    the caller's thread): :func:`mapping.pipeline.reconstruct` then reads frames ahead (:mod:`mapping.prefetch`).
    radiomap's own datasets declare it; a dataset without it is read in the caller's thread, one frame at a time.
    """

    name: str
    K: np.ndarray
    width: int
    height: int

    def __len__(self) -> int: ...

    def __getitem__(self, index: int) -> RGBDFrame: ...

    def ground_truth(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(timestamps (N,), camera-to-world poses (N, 4, 4)) of the selected frames, or None."""
        ...
