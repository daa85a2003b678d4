"""radical's binary ``.crf`` inverse response (``radical::RadiometricResponse::save``).

The file is radical's ``writeMat`` dump of a ``cv::Mat``, little-endian as written on x86::

    uint32 magic = 0xC4A1FDD9
    uint32 type  = OpenCV type code (radical writes CV_32FC3 = 21)
    uint32 dims  = 2
    uint32 rows, cols  (256 x 1 as radical's calibration produces; any rows * cols = 256 is accepted)
    rows * cols * channels values, interleaved per level, channel order BGR

Values are ``f^-1`` per level, scaled so that the maximum is 1. radical's calibration clamps the levels
outside its valid range to exactly 0 and 1 and sorts each channel, so its files are non-decreasing
with flat ends: the reader repairs such plateaus to strictly increasing (``meta["repaired"] = True``)
and rejects anything that actually decreases. The writer always writes ``CV_32FC3`` (radical reads
nothing else): a 1-channel response is written as three equal channels.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.fileio import atomic_write_bytes
from radiometry.formats import read_file
from radiometry.response import LEVELS, CameraResponse, repair_monotone

MAGIC = 0xC4A1FDD9
HEADER = struct.Struct("<5I")
_CV_DEPTHS = {5: np.dtype("<f4"), 6: np.dtype("<f8")}  # CV_32F, CV_64F
CV_32FC3 = 5 + ((3 - 1) << 3)


def _fail(path: Path, what: str) -> CalibrationFileError:
    return CalibrationFileError(f"{path}: {what}; pass a response saved by radical (.crf) or re-create it")


def read_radical_crf(path: str | os.PathLike) -> CameraResponse:
    """Read a radical ``.crf`` file as an RGB :class:`CameraResponse` (BGR in the file)."""
    path = Path(path)
    data = read_file(path, "the radical response")
    if len(data) < HEADER.size:
        raise _fail(path, f"truncated header ({len(data)} of {HEADER.size} bytes)")
    magic, cv_type, dims, rows, cols = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise _fail(path, f"not a radical cv::Mat file (magic 0x{magic:08X}, expected 0x{MAGIC:08X})")
    depth, channels = cv_type & 7, (cv_type >> 3) + 1
    if depth not in _CV_DEPTHS or channels not in (1, 3):
        raise _fail(path, f"holds a cv::Mat of type {cv_type} (depth {depth}, {channels} channels); "
                          "a response is float with 1 or 3 channels (CV_32FC3 = 21)")
    if dims != 2 or rows * cols != LEVELS:
        raise _fail(path, f"holds a {rows} x {cols} matrix (dims {dims}); a response has 256 levels")
    dtype = _CV_DEPTHS[depth]
    expected = HEADER.size + LEVELS * channels * dtype.itemsize
    if len(data) < expected:
        raise _fail(path, f"truncated: {len(data)} bytes, expected {expected}")
    if len(data) > expected:
        raise _fail(path, f"{len(data) - expected} unexpected bytes after the {LEVELS} levels")
    table = np.frombuffer(data, dtype=dtype, count=LEVELS * channels, offset=HEADER.size)
    table = table.astype(np.float64).reshape(LEVELS, channels)[:, ::-1]  # BGR -> RGB
    if not np.all(np.isfinite(table)):
        raise _fail(path, "contains NaN or infinite values")
    if np.any(table < 0):
        raise _fail(path, "contains negative irradiance")
    steps = np.diff(table, axis=0)
    if np.any(steps < 0):
        level = int(np.argwhere(steps < 0)[0, 0]) + 1
        raise _fail(path, f"the response decreases at level {level}; a response must be monotone")
    if np.any(table[-1] <= 0):
        raise _fail(path, "a channel is zero at level 255")
    repaired = bool(np.any(steps == 0))
    if repaired:
        table = repair_monotone(table)
    return CameraResponse.from_table(table, method="radical", source=str(path), repaired=repaired)


def write_radical_crf(path: str | os.PathLike, response: CameraResponse) -> Path:
    """Write ``response`` as a radical ``.crf`` (CV_32FC3, 256 x 1, BGR), atomically."""
    if not isinstance(response, CameraResponse):
        raise TypeError(f"response must be a CameraResponse, got {type(response).__name__}")
    table = response.channel_tables(3)[:, ::-1]  # RGB -> BGR; a 1-channel response is repeated
    payload = np.ascontiguousarray(table, dtype="<f4").tobytes()
    return atomic_write_bytes(path, HEADER.pack(MAGIC, CV_32FC3, 2, LEVELS, 1) + payload)


__all__ = ["read_radical_crf", "write_radical_crf", "MAGIC"]
