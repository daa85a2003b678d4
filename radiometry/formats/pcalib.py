"""TUM / DSO photometric calibration ``pcalib.txt`` (inverse response of one channel).

The first line holds the 256 values of ``G^-1(I)`` for I = 0..255, in 0..255 units, separated by
spaces; anything after them on that line, and every further line, is ignored (DSO's files end with
``vis_exponent: 1.0``). DSO requires the values to be strictly increasing and then rescales them to
``255 (G - G[0]) / (G[255] - G[0])``. The reader applies that same rescaling (so ``f^-1(0) = 0``), which
keeps our interpretation identical to DSO's; the writer writes exactly those rescaled values.

Measured files are not always monotone: a calibration fitted per level can dip by a little where the data are
thin (near saturation, or a flat stretch of the response). Such a file is loaded through a documented repair:
:func:`isotonic_repair`, the least-squares non-decreasing fit (pool adjacent violators: every run of levels that
dips is replaced by its mean), then the levels pooled into one value separated by 1e-6 of the range so that the
table is strictly increasing. A warning states how many levels changed and by how much (in 0..255 units and in
% of the range). A repair that would move a value by more than :data:`MAX_REPAIR` of the range is refused: that
file is no response. ``read_pcalib(path, strict=True)`` refuses any dip, as DSO does.

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


#: the largest change (fraction of the range) the repair of a dipping pcalib may make to any value
MAX_REPAIR = 0.02


def isotonic_repair(values: np.ndarray, *, min_step: float = 1e-6) -> np.ndarray:
    """The non-decreasing sequence closest to ``values`` in least squares (pool adjacent violators, equal
    weights), then made strictly increasing by separating pooled levels by ``min_step`` of the range (the
    separation is centred on the pooled mean). float64, the shape of ``values`` (1-D)."""
    y = np.asarray(values, dtype=np.float64)
    means: list[float] = []
    sizes: list[int] = []
    for v in y:
        means.append(float(v))
        sizes.append(1)
        while len(means) > 1 and means[-2] >= means[-1]:  # ties pooled too, then separated
            n = sizes[-2] + sizes[-1]
            m = (means[-2] * sizes[-2] + means[-1] * sizes[-1]) / n
            means[-2:] = [m]
            sizes[-2:] = [n]
    step = min_step * max(float(y.max() - y.min()), 1e-12)
    out = np.empty_like(y)
    i = 0
    for m, n in zip(means, sizes):
        out[i:i + n] = m + step * (np.arange(n) - (n - 1) / 2.0)
        i += n
    return out


def read_pcalib(path: str | os.PathLike, *, strict: bool = False) -> CameraResponse:
    """Read a DSO/TUM ``pcalib.txt`` as a 1-channel :class:`CameraResponse` (DSO's normalisation).

    A file that dips is repaired (:func:`isotonic_repair`, with a warning; ``meta["repaired"]`` records the
    levels changed and the largest change) unless ``strict`` (then refused, as DSO does) or unless the repair
    would move a value by more than :data:`MAX_REPAIR` of the range."""
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
    meta: dict = {}
    if np.any(steps <= 0):
        level = int(np.flatnonzero(steps <= 0)[0]) + 1
        if strict:
            raise _fail(path, f"not strictly increasing at level {level} (DSO rejects such files too)")
        if table[-1] < table[0] and np.mean(steps < 0) > 0.5:   # mostly decreasing: not noise a repair could mend
            raise _fail(path, f"the values decrease ({table[0]:g} at level 0 to {table[-1]:g} at 255): a reversed "
                              "file, or the forward response instead of its inverse?")
        repaired = isotonic_repair(table)
        span = float(repaired[-1] - repaired[0])
        change = np.abs(repaired - table)
        if not span > 0 or float(change.max()) > MAX_REPAIR * span:
            worst = 100.0 * float(change.max()) / span if span > 0 else float("inf")
            raise _fail(path, f"not strictly increasing at level {level}, and making it monotone would move a value "
                              f"by {worst:.1f}% of the range (more than {100 * MAX_REPAIR:g}%): not a response")
        changed = np.flatnonzero(change > 1e-9 * span)
        log.warning("%s: not strictly increasing (first at level %d); repaired by isotonic regression (pool adjacent "
                    "violators): %d levels changed (%d..%d), at most by %.4g of 0..255 (%.3f%% of the range); "
                    "read it with strict=True to refuse such files", path, level, changed.size, int(changed[0]),
                    int(changed[-1]), 255.0 * float(change.max()) / span, 100.0 * float(change.max()) / span)
        meta["repaired"] = {"method": "isotonic (pool adjacent violators)", "levels": changed.tolist(),
                            "max_change_fraction": float(change.max()) / span}
        table = repaired
    table = (table - table[0]) / (table[-1] - table[0])
    if not np.all(np.isfinite(table)) or np.any(np.diff(table) <= 0):
        raise _fail(path, "the values are too close together to be told apart")
    return CameraResponse.from_table(table[:, None], method="pcalib", source=str(path), **meta)


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


__all__ = ["MAX_REPAIR", "isotonic_repair", "read_pcalib", "write_pcalib"]
