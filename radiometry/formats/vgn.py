"""radical's ``.vgn`` vignetting files (Alexandrov et al.'s C++ toolbox), both forms.

Layout (from radical's ``src/radical/*_vignetting_model.cpp`` and ``mat_io.cpp``): one ASCII header
line, then one serialised ``cv::Mat``, all little-endian::

    NonparametricVignettingModel\\n                 (LUT form)
    PolynomialVignettingModel <degree> <width> <height>\\n   (polynomial form, degree 3)

    uint32 magic = 0xC4A1FDD9, uint32 type (cv::Mat type), uint32 dims (2), uint32 rows, uint32 cols,
    rows * cols * elemSize bytes of data, row-major, channels interleaved.

- LUT: ``CV_32FC3`` (type 21), ``rows = height``, ``cols = width``, ``V`` per pixel in **BGR** order.
- Polynomial: ``CV_64FC3`` (type 22), a 1 x 5 (or 5 x 1) row of ``(cx, cy, b1, b2, b3)``, each a BGR
  triple; ``V = 1 + b1 d^2 + b2 d^4 + b3 d^6`` with ``d`` the distance to ``(cx, cy)`` **in pixels** at
  the calibration resolution (radiomap normalises ``r`` by the half-diagonal ``R``, so
  ``b_k(radiomap) = b_k(radical) * R^(2k)``). Pixel centres sit at integer coordinates in both.

radical has no per-channel scale: a :class:`PolynomialVignetting` with ``scale != 1`` is written
normalised (``V = 1`` at each centre; the difference is a per-channel brightness, which exposure and
white balance absorb) and a warning is logged. One-channel models are written as three equal channels.
"""

from __future__ import annotations

import logging
import os
import struct
from pathlib import Path

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.fileio import atomic_write_bytes
from radiometry.formats import read_file
from radiometry.vignetting import LUTVignetting, PolynomialVignetting, VignettingModel, half_diagonal

log = logging.getLogger(__name__)

MAGIC = 0xC4A1FDD9
CV_32FC3 = 21
CV_64FC3 = 22
LUT_HEADER = "NonparametricVignettingModel"
POLY_HEADER = "PolynomialVignettingModel"
POLY_DEGREE = 3
_MAT_HEADER = struct.Struct("<5I")
_MAX_HEADER_LINE = 256


def _mat_bytes(array: np.ndarray, cv_type: int) -> bytes:
    rows, cols = array.shape[:2]
    return _MAT_HEADER.pack(MAGIC, cv_type, 2, rows, cols) + np.ascontiguousarray(array).tobytes()


def write_radical_vgn(model: VignettingModel, path: str | os.PathLike) -> Path:
    """Write ``model`` as a radical ``.vgn`` file (LUT or polynomial form), atomically.

    A :class:`PolynomialVignetting` keeps its polynomial form; any other model is written as a LUT at
    its calibration resolution.
    """
    if not isinstance(model, VignettingModel):
        raise TypeError(f"model must be a VignettingModel, got {type(model).__name__}")
    if isinstance(model, PolynomialVignetting):
        if not np.allclose(model.scale, 1.0, rtol=0, atol=1e-12):
            log.warning("radical .vgn has no per-channel scale: writing the polynomial normalised to V = 1 at "
                        "its centre (scale %s dropped)", np.round(model.scale, 6).tolist())
        width, height = model.resolution
        radius = half_diagonal(model.resolution)
        coeffs = np.broadcast_to(model.coefficients, (3, 3))
        centres = np.broadcast_to(model.centres, (3, 2))
        rgb = np.empty((5, 3), dtype=np.float64)  # rows: cx, cy, b1, b2, b3; columns: channels RGB
        rgb[0], rgb[1] = centres[:, 0], centres[:, 1]
        for k in range(3):
            rgb[2 + k] = coeffs[:, k] / radius ** (2 * (k + 1))
        mat = rgb[:, ::-1].reshape(1, 5, 3)  # BGR, a 1 x 5 CV_64FC3 row as radical's fitter writes it
        header = f"{POLY_HEADER} {POLY_DEGREE} {width} {height}\n".encode("ascii")
        return atomic_write_bytes(path, header + _mat_bytes(mat.astype("<f8"), CV_64FC3))
    lut = model.evaluate()
    if lut.shape[2] == 1:
        lut = np.repeat(lut, 3, axis=2)
    header = f"{LUT_HEADER}\n".encode("ascii")
    return atomic_write_bytes(path, header + _mat_bytes(lut[:, :, ::-1].astype("<f4"), CV_32FC3))


def _read_mat(path: Path, data: bytes, offset: int, expected_type: int) -> np.ndarray:
    if len(data) - offset < _MAT_HEADER.size:
        raise CalibrationFileError(f"{path}: truncated after the header line (no matrix); re-export the model")
    magic, cv_type, dims, rows, cols = _MAT_HEADER.unpack_from(data, offset)
    if magic != MAGIC:
        raise CalibrationFileError(f"{path}: no serialised cv::Mat after the header line (bad magic "
                                   f"0x{magic:08X}); not a radical .vgn file")
    if cv_type != expected_type:
        raise CalibrationFileError(f"{path}: matrix type {cv_type}, expected {expected_type} for this model; "
                                   "not a radical .vgn file")
    if dims != 2 or rows == 0 or cols == 0:
        raise CalibrationFileError(f"{path}: matrix of {dims} dimensions and size {rows}x{cols}; expected a "
                                   "non-empty 2-D matrix")
    itemsize = 4 if expected_type == CV_32FC3 else 8
    need = rows * cols * 3 * itemsize
    have = len(data) - offset - _MAT_HEADER.size
    if have != need:
        what = "truncated" if have < need else "has trailing bytes"
        raise CalibrationFileError(f"{path}: {what}: a {rows}x{cols} matrix needs {need} bytes of data, "
                                   f"found {have}; re-export the model")
    dtype = "<f4" if itemsize == 4 else "<f8"
    arr = np.frombuffer(data, dtype=dtype, count=rows * cols * 3, offset=offset + _MAT_HEADER.size)
    return arr.reshape(rows, cols, 3).astype(np.float64 if itemsize == 8 else np.float32)


def read_radical_vgn(path: str | os.PathLike) -> VignettingModel:
    """Read a radical ``.vgn`` file (LUT or polynomial form) into an RGB :class:`VignettingModel`.

    Raises :class:`CalibrationFileError` naming the file for a missing, truncated or malformed file,
    NaN/inf values, or a ``V`` that is not strictly positive.
    """
    path = Path(path)
    data = read_file(path, "the vignetting model")
    newline = data.find(b"\n", 0, _MAX_HEADER_LINE)
    if newline < 0:
        raise CalibrationFileError(f"{path}: no header line; a radical .vgn file starts with "
                                   f"'{LUT_HEADER}' or '{POLY_HEADER} 3 W H'")
    try:
        fields = data[:newline].decode("ascii").split()
    except UnicodeDecodeError:
        fields = []
    name = fields[0] if fields else ""
    source = {"source": "radical .vgn", "file": path.name}
    try:
        if name == LUT_HEADER and len(fields) == 1:
            bgr = _read_mat(path, data, newline + 1, CV_32FC3)
            return LUTVignetting(bgr[:, :, ::-1], info=source)
        if name == POLY_HEADER and len(fields) == 4:
            try:
                degree, width, height = (int(v) for v in fields[1:])
            except ValueError:
                raise CalibrationFileError(f"{path}: bad header {data[:newline]!r}; expected "
                                           f"'{POLY_HEADER} 3 WIDTH HEIGHT'") from None
            if degree != POLY_DEGREE:
                raise CalibrationFileError(f"{path}: polynomial of degree {degree}; radical and radiomap use "
                                           f"degree {POLY_DEGREE}; re-export a degree-{POLY_DEGREE} model from "
                                           "radical or re-calibrate with 'radiomap vignetting --model poly'")
            if width < 1 or height < 1:
                raise CalibrationFileError(f"{path}: image size {width}x{height} in the header is not positive")
            mat = _read_mat(path, data, newline + 1, CV_64FC3)
            if mat.shape[0] * mat.shape[1] != 5:
                raise CalibrationFileError(f"{path}: polynomial matrix is {mat.shape[0]}x{mat.shape[1]}; "
                                           "expected 5 entries (cx, cy, b1, b2, b3)")
            rgb = mat.reshape(5, 3)[:, ::-1]
            radius = half_diagonal((width, height))
            coeffs = np.stack([rgb[2 + k] * radius ** (2 * (k + 1)) for k in range(3)], axis=1)
            centres = np.stack([rgb[0], rgb[1]], axis=1)
            return PolynomialVignetting(coeffs, centres, (width, height), info=source)
    except (ValueError, TypeError) as exc:
        raise CalibrationFileError(f"{path}: invalid vignetting model: {exc}; re-calibrate or re-export it") from None
    raise CalibrationFileError(f"{path}: header {data[:min(newline, 60)]!r} is not a radical vignetting model; "
                               f"expected '{LUT_HEADER}' or '{POLY_HEADER} 3 W H'")


__all__ = ["read_radical_vgn", "write_radical_vgn"]
