"""RGB-D sequence loaders, one file per format, behind one contract (:mod:`mapping.datasets.base`).

>>> ds = open_dataset("redkitchen/seq-01", frames=slice(0, 100, 2))   # doctest: +SKIP
>>> frame = ds[0]        # RGBDFrame: rgb uint8 (H, W, 3), depth float32 metres, K, pose or None

Formats are detected from the folder's content (``detect``, in the order of :data:`FORMATS`: the most
specific first) or named with ``format=``. Frames are read lazily, one at a time.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from mapping.datasets.base import RGBDDataset, RGBDFrame
from mapping.datasets.redwood import RedwoodDataset
from mapping.datasets.sevenscenes import SevenScenesDataset
from mapping.datasets.simulated import SimulatedDataset
from mapping.datasets.tum import TUMDataset
from radiometry.errors import DatasetError
from radiometry.registry import Registry

#: format name -> loader class; detection tries them in this order (simulated before its parent, TUM)
FORMATS = Registry("format", {
    "simulated": SimulatedDataset,
    "tum": TUMDataset,
    "7scenes": SevenScenesDataset,
    "redwood": RedwoodDataset,
})


def detect_format(path: str | os.PathLike) -> str:
    """The name of the first format in :data:`FORMATS` that recognises the folder."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(f"{path}: no such sequence folder; check the path")
    if not path.is_dir():
        raise DatasetError(f"{path}: is a file; pass the sequence folder")
    for name, cls in FORMATS.items():
        if cls.detect(path):
            return name
    raise DatasetError(
        f"{path}: unknown RGB-D layout; expected TUM (rgb.txt, depth.txt), 7-Scenes (frame-NNNNNN.color.*), "
        "Redwood (color/, depth/) or a radiomap simulation (radiomap_sequence.json); or pass --format "
        f"({', '.join(FORMATS)})")


def open_dataset(path: str | os.PathLike, *, format: str | None = None, depth_scale: float | None = None,
                 intrinsics=None, frames: slice | Sequence[int] | None = slice(None)) -> RGBDDataset:
    """Open an RGB-D sequence.

    path:        the sequence folder.
    format:      one of :data:`FORMATS`, or None to detect it.
    depth_scale: raw depth units per metre (default: the format's, e.g. 5000 TUM, 1000 7-Scenes/Redwood).
    intrinsics:  None (the format's file or default), a file (3 x 3, 'fx fy cx cy' or Open3D camera JSON),
                 ``"fx,fy,cx,cy"``, four numbers or a (3, 3) matrix.
    frames:      a slice (range and stride, e.g. ``slice(0, 100, 2)``) or explicit frame positions.
    """
    cls = FORMATS[detect_format(path) if format is None else format]
    dataset = cls(path, depth_scale=depth_scale, intrinsics=intrinsics, frames=frames)
    if depth_scale is not None:        # every format: the settings line names a given scale (intrinsics_text)
        dataset.depth_scale_source = "given"
    return dataset


def describe_dataset(dataset: RGBDDataset) -> dict:
    """What a results folder records about the sequence it was made from (config.json's "dataset"): the loader,
    the selected frames (their number, and for a file sequence a sha256 of their file names and the whole sequence's
    number, which a replay checks: :mod:`mapping.replay`), the image size, K, and, for a file sequence, its depth
    scale and where K came from."""
    from mapping.replay import frames_record

    source = getattr(dataset, "intrinsics_source", None)
    return {"class": type(dataset).__name__, "frames": len(dataset), **frames_record(dataset), "width": dataset.width,
            "height": dataset.height, "K": np.asarray(dataset.K).tolist(),
            "depth_scale": getattr(dataset, "depth_scale", None),
            "intrinsics_source": None if source is None else str(source)}


def intrinsics_text(dataset: RGBDDataset) -> str:
    """``intrinsics 615,615,320,240 (given)``: the intrinsics a run uses and where they came from (the option, a
    file of the sequence, the folder name, an assumed default), for the printed settings line; then the depth scale
    when it was given (``depth scale 1000 per metre (given)``) or detected."""
    K = np.asarray(dataset.K, dtype=np.float64)
    source = getattr(dataset, "intrinsics_source", None)
    source = "given" if source in (None, "option") else str(source)
    values = ",".join(f"{v:.6g}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))
    text = f"intrinsics {values} ({source})"
    scale_source = getattr(dataset, "depth_scale_source", None)
    if scale_source == "given":
        text += f", depth scale {dataset.depth_scale:g} per metre (given)"
    elif scale_source is not None:   # TUM: the scale and why (detected or TUM's)
        text += f", depth scale {scale_source}"
    return text


__all__ = ["FORMATS", "RGBDDataset", "RGBDFrame", "RedwoodDataset", "SevenScenesDataset", "SimulatedDataset",
           "TUMDataset", "describe_dataset", "detect_format", "intrinsics_text", "open_dataset"]
