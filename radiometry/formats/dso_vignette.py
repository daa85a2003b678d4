"""DSO / TUM mono-VO photometric calibration: ``vignette.png``.

The file is a single-channel 16-bit PNG (8-bit is also read, as DSO does) of the calibration
resolution; DSO divides every pixel by the image maximum, so ``V = value / max`` and the stored
scale is arbitrary. radiomap writes ``round(V / max(V) * 65535)``.

DSO's method is for monochrome cameras: the file has one channel. Reading gives a 1-channel
:class:`LUTVignetting` (which radiomap applies to every channel of a colour image). Writing a
3-channel model stores **the mean of its channels** by default, logs the largest per-channel
deviation from that mean, and accepts ``channel=`` to store one channel instead (``"R"``, ``"G"``,
``"B"`` or 0..2): colour information beyond that cannot be represented in the format.

A zero pixel would make DSO divide by zero; such files are rejected (``V`` must be positive).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from radiometry.errors import CalibrationFileError, OutputError
from radiometry.fileio import atomic_write_bytes
from radiometry.formats import read_file
from radiometry.images import png_defect
from radiometry.vignetting import LUTVignetting, VignettingModel

log = logging.getLogger(__name__)

_CHANNEL_NAMES = {"R": 0, "G": 1, "B": 2}


def _check_png_header(path: Path, raw: np.ndarray) -> None:
    """Reject a PNG whose header or chunks promise more than the file holds before decoding it: a corrupt
    header can make the decoder allocate and scan gigabytes for seconds."""
    defect = png_defect(raw)
    if defect is not None:
        raise CalibrationFileError(f"{path}: {defect}; re-export the DSO vignette")


def read_dso_vignette(path: str | os.PathLike) -> LUTVignetting:
    """Read a DSO ``vignette.png`` (16- or 8-bit, one channel) as a 1-channel LUT, ``V = value / max``."""
    import cv2

    path = Path(path)
    raw = np.frombuffer(read_file(path, "the vignetting image"), dtype=np.uint8)
    _check_png_header(path, raw)
    img = None
    if raw.size:
        try:
            img = cv2.imdecode(raw, cv2.IMREAD_UNCHANGED)
        except cv2.error:
            img = None
    if img is None:
        raise CalibrationFileError(f"{path}: cannot decode the image (corrupt, truncated or not a PNG); "
                                   "re-export the DSO vignette")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim != 2:
        raise CalibrationFileError(f"{path}: has {img.shape[2]} channels; a DSO vignette is a single-channel "
                                   "(grayscale) 16-bit PNG: convert it to grey keeping 16 bits (ImageMagick: "
                                   "magick IN -colorspace Gray -depth 16 OUT.png), or keep per-channel vignetting "
                                   "in a radiomap .npz")
    if img.dtype not in (np.uint16, np.uint8):
        raise CalibrationFileError(f"{path}: pixel type {img.dtype}; a DSO vignette is 16-bit (or 8-bit)")
    peak = int(img.max())
    if peak == 0:
        raise CalibrationFileError(f"{path}: all pixels are 0; not a vignetting image")
    if int(img.min()) == 0:
        n = int(np.count_nonzero(img == 0))
        raise CalibrationFileError(f"{path}: {n} pixels are 0 (V = 0 cannot be corrected); "
                                   "re-export the vignette with V > 0 everywhere")
    lut = img.astype(np.float32) / np.float32(peak)
    return LUTVignetting(lut, info={"source": "DSO vignette.png", "file": path.name,
                                    "bit_depth": 16 if img.dtype == np.uint16 else 8})


def write_dso_vignette(model: VignettingModel, path: str | os.PathLike, *,
                       channel: str | int = "mean") -> Path:
    """Write ``model`` at its calibration resolution as a DSO 16-bit ``vignette.png`` (max = 65535).

    ``channel="mean"`` (default) stores the mean of the model's channels; ``"R"``, ``"G"``, ``"B"`` or an
    index stores one channel.
    """
    import cv2

    if not isinstance(model, VignettingModel):
        raise TypeError(f"model must be a VignettingModel, got {type(model).__name__}")
    v = model.evaluate().astype(np.float64)
    if isinstance(channel, str) and channel.lower() == "mean":
        mono = v.mean(axis=2)
        if v.shape[2] > 1:
            dev = float(np.max(np.abs(v / mono[:, :, None] - 1.0)))
            log.warning("DSO vignette.png has one channel: writing the mean of %d channels (largest per-channel "
                        "deviation from the mean %.2f%%)", v.shape[2], 100 * dev)
    else:
        index = _CHANNEL_NAMES.get(channel.upper()) if isinstance(channel, str) else channel
        if not isinstance(index, (int, np.integer)) or not 0 <= index < v.shape[2]:
            raise ValueError(f"channel must be 'mean', one of R/G/B or an index below {v.shape[2]}, got {channel!r}")
        mono = v[:, :, int(index)]
    img = np.clip(np.rint(mono / mono.max() * 65535.0), 1, 65535).astype(np.uint16)
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes uint16 PNG
        raise OutputError(f"{path}: OpenCV could not encode the vignette as PNG")
    return atomic_write_bytes(path, buf.tobytes())


__all__ = ["read_dso_vignette", "write_dso_vignette"]
