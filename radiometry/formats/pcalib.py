"""TUM / DSO photometric calibration ``pcalib.txt`` (inverse response of one channel).

The first line holds the 256 values of ``G^-1(I)`` for I = 0..255, in 0..255 units, separated by
spaces; anything after them on that line, and every further line, is ignored (DSO's files end with
``vis_exponent: 1.0``). DSO requires the values to be strictly increasing and then rescales them to
``255 (G - G[0]) / (G[255] - G[0])``. The reader applies that same rescaling (so ``f^-1(0) = 0``), which
keeps our interpretation identical to DSO's; the writer writes exactly those rescaled values.

pcalib has one channel. Writing a 3-channel response needs ``channel=``: an index (0 = R, 1 = G, 2 = B)
or ``"mean"``; without it the mean of the normalised channels is written with a :class:`UserWarning`.
"""

from __future__ import annotations

import logging
import os
import re
import warnings
from pathlib import Path

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.fileio import atomic_write_text
from radiometry.formats import read_file
from radiometry.response import LEVELS, CameraResponse

log = logging.getLogger(__name__)

_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)


def _fail(path: Path, what: str) -> CalibrationFileError:
    return CalibrationFileError(f"{path}: {what}; a pcalib.txt holds 256 strictly increasing inverse-response "
                                "values (0..255) on its first line")


def read_pcalib(path: str | os.PathLike) -> CameraResponse:
    """Read a DSO/TUM ``pcalib.txt`` as a 1-channel :class:`CameraResponse` (DSO's normalisation)."""
    path = Path(path)
    try:
        text = read_file(path, "the pcalib.txt").decode("utf-8")
    except UnicodeDecodeError:
        raise _fail(path, "not a text file") from None
    lines = text.splitlines()
    if not lines or not lines[0].strip():
        raise _fail(path, "the first line is empty")
    values: list[float] = []
    for token in lines[0].split():
        if _NUMBER.fullmatch(token):
            values.append(float(token))
        elif _NON_FINITE.fullmatch(token):
            raise _fail(path, f"value {len(values) + 1} is {token!r}, not a finite number")
        else:
            break  # trailing text after the values
    if len(values) != LEVELS:
        raise _fail(path, f"found {len(values)} numbers at the start of the first line, expected {LEVELS}")
    table = np.array(values, dtype=np.float64)
    if not np.all(np.isfinite(table)):
        raise _fail(path, "a value overflows (not a finite number)")
    steps = np.diff(table)
    if np.any(steps <= 0):
        level = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise _fail(path, f"not strictly increasing at level {level} (DSO rejects such files too)")
    table = (table - table[0]) / (table[-1] - table[0])
    if not np.all(np.isfinite(table)) or np.any(np.diff(table) <= 0):
        raise _fail(path, "the values are too close together to be told apart")
    return CameraResponse.from_table(table[:, None], method="pcalib", source=str(path))


def write_pcalib(path: str | os.PathLike, response: CameraResponse, *, channel: int | str | None = None) -> Path:
    """Write ``response`` as a DSO/TUM ``pcalib.txt`` (atomic).

    ``channel``: for a 3-channel response, 0/1/2 (R/G/B) or ``"mean"``; ``None`` writes the mean with a
    ``UserWarning``. Values are ``255 (f^-1 - f^-1(0)) / (1 - f^-1(0))``, as DSO will use them.
    """
    if not isinstance(response, CameraResponse):
        raise TypeError(f"response must be a CameraResponse, got {type(response).__name__}")
    table = response.inverse_table
    if response.channels == 1:
        if channel not in (None, 0, "mean"):
            raise ValueError(f"channel must be None, 0 or 'mean' for a 1-channel response, got {channel!r}")
        curve = table[:, 0]
    elif channel is None or channel == "mean":
        if channel is None:
            warnings.warn("pcalib.txt holds one channel: writing the mean of the R, G and B responses; "
                          "pass channel=0/1/2 to write one of them", UserWarning, stacklevel=2)
        curve = table.mean(axis=1)
    elif isinstance(channel, (int, np.integer)) and not isinstance(channel, bool) and 0 <= channel < 3:
        curve = table[:, int(channel)]
    else:
        raise ValueError(f"channel must be 0, 1, 2 (R, G, B), 'mean' or None, got {channel!r}")
    if curve[0] > 1e-3:
        log.warning("pcalib stores f^-1(0) = 0: the offset %.4g of level 0 is dropped (DSO rescales so)", curve[0])
    scaled = 255.0 * (curve - curve[0]) / (curve[-1] - curve[0])
    text = " ".join(f"{v:.6f}" for v in scaled)
    if np.any(np.diff(np.array(text.split(), dtype=np.float32)) <= 0):
        raise ValueError("the response has steps below pcalib's precision (1e-6 of 255); "
                         "repair it with CameraResponse.from_table(..., repair=True) first")
    return atomic_write_text(path, text + " \n")


__all__ = ["read_pcalib", "write_pcalib"]
