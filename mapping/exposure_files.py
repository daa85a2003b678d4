"""Known exposures (``--exposures FILE``): per-frame exposure x gain a camera recorded, matched to a sequence.

Many cameras record their exposure (RealSense frame metadata, machine-vision cameras, TUM monoVO's ``times.txt``).
Given, it removes what self-calibration cannot separate from the data alone (a tilt of V against an exposure
drift, :mod:`radiometry.self_calibration_ambiguity`). Three layouts, told apart by their columns (``#`` comments
and blank lines skipped; :mod:`radiometry.textlists` reads the text):

- radiomap's own ``exposures.txt`` (``index timestamp k_r k_g k_b correspondences source``, what ``reconstruct``
  and ``self-calibrate`` write): matched by frame number (the ``index`` column);
- a plain list ``timestamp k`` or ``timestamp k_r k_g k_b``: matched by timestamp;
- TUM monoVO ``times.txt`` (``id timestamp exposure_ms``): matched by timestamp.

Values are exposure time x gain in any unit (only ratios matter); one value per frame means the same for every
channel (white balance fixed), three are per channel (exposure x white-balance gain). Matching by timestamp
takes, for each frame, the row nearest in time, one-to-one, within ``max_difference`` seconds (as ``--poses
FILE``); when no row is that near but the file has exactly one row per frame of the sequence (counted from its
first frame, before ``--frames``), the rows are taken in order (a warning says so). Frames without a value are
fitted (counted, with a warning); when too few have one (``radiometry.quorum``), the run stops naming the file. A
command that fits none (``reconstruct``, ``compare``: ``every_frame``) stops, in one message, when any frame lacks one.
The rows matched (``KnownExposures.rows``) are then checked against the images by the commands
(:mod:`mapping.exposure_alignment`): a list off by a frame or more is refused.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radiometry.errors import DatasetError
from radiometry.quorum import rule_text, too_little

log = logging.getLogger(__name__)

EXPOSURE_FILE_KINDS = ("radiomap", "plain", "tum-monovo")


class ExposureFileError(DatasetError):
    """An exposure list given as ``--exposures FILE`` cannot be read or does not fit the sequence."""


@dataclass(frozen=True)
class KnownExposures:
    """The exposures a file gives a sequence's selected frames: ``values`` ``(F, 3)`` (NaN: not known) for the
    frame at position ``i``; ``per_channel``: the file gave one value per channel; ``how``: how rows were matched."""

    source: Path
    kind: str
    values: np.ndarray
    per_channel: bool
    how: str
    #: the file's row matched to each frame (-1: none), the file's values (N, 3) and timestamps (N,) in its order
    #: (what :mod:`mapping.exposure_alignment` shifts); None when not known
    rows: np.ndarray | None = None
    file_values: np.ndarray | None = None
    file_stamps: np.ndarray | None = None

    @property
    def known(self) -> np.ndarray:
        return np.all(np.isfinite(self.values), axis=1)

    @property
    def matched(self) -> int:
        return int(np.count_nonzero(self.known))

    def describe(self) -> str:
        what = "per channel" if self.per_channel else "one value per frame, white balance assumed fixed"
        return (f"{self.source} ({self.kind}, {what}; {self.matched} of {len(self.values)} frames, "
                f"matched {self.how})")

    def __str__(self) -> str:
        return str(self.source)


def read_exposure_file(path: str | os.PathLike) -> tuple[str, np.ndarray, np.ndarray, np.ndarray, bool]:
    """``(kind, frame numbers or None, timestamps, values (N, 3), per_channel)`` of an exposure list."""
    from radiometry.textlists import list_lines

    path = Path(path)
    if path.is_dir():
        raise ExposureFileError(f"{path}: a folder; --exposures takes a file (exposures.txt, 'timestamp k' lines "
                                "or TUM monoVO times.txt)")
    try:
        lines = list_lines(path)
    except FileNotFoundError:
        raise ExposureFileError(f"{path}: no such exposure file; check --exposures") from None
    except OSError as exc:
        raise ExposureFileError(f"{path}: cannot read the exposure file ({exc.strerror or exc})") from None
    rows, kind = [], None
    expected = "'timestamp k', 'timestamp k_r k_g k_b', 'id timestamp exposure_ms' or radiomap's exposures.txt"
    for lineno, line in lines:
        parts = line.split()
        if not parts or parts[0].startswith("#"):
            continue
        this = {7: "radiomap", 2: "plain", 4: "plain", 3: "tum-monovo"}.get(len(parts))
        if this is None:
            raise ExposureFileError(f"{path}:{lineno}: expected {expected}, got {len(parts)} columns: {line[:80]!r}")
        if kind is not None and (this != kind or len(parts) != width):
            raise ExposureFileError(f"{path}:{lineno}: {len(parts)} columns where line(s) before had {width}; "
                                    "one layout per file")
        kind, width = this, len(parts)
        try:
            numbers = [float(v) for v in (parts[:5] if kind == "radiomap" else parts)]
        except ValueError:
            raise ExposureFileError(f"{path}:{lineno}: not numbers: {line[:80]!r}") from None
        values = numbers[2:5] if kind == "radiomap" else numbers[2:3] if kind == "tum-monovo" else numbers[1:]
        if not all(np.isfinite(v) and v > 0 for v in values) or not np.isfinite(numbers[0 if kind == "plain" else 1]):
            raise ExposureFileError(f"{path}:{lineno}: exposures must be finite and > 0 (and the timestamp finite), "
                                    f"got {line[:80]!r}")
        rows.append(numbers)
    if not rows:
        raise ExposureFileError(f"{path}: no exposure rows (expected {expected})")
    a = np.array(rows, dtype=np.float64)
    if kind == "radiomap":
        return kind, a[:, 0].astype(np.int64), a[:, 1], a[:, 2:5], True
    if kind == "tum-monovo":
        return kind, a[:, 0].astype(np.int64), a[:, 1], np.repeat(a[:, 2:3], 3, axis=1), False
    per_channel = a.shape[1] == 4
    return kind, None, a[:, 0], (a[:, 1:4] if per_channel else np.repeat(a[:, 1:2], 3, axis=1)), per_channel


def match_exposure_file(dataset, path: str | os.PathLike, *, max_difference: float = 0.02,
                        every_frame: str | None = None) -> KnownExposures:
    """The exposures ``path`` gives the frames of ``dataset`` (module doc); :class:`ExposureFileError` when too few
    frames get one, or, with ``every_frame`` (the command that fits none, e.g. ``"reconstruct"``), when any lacks one."""
    from mapping.metrics import associate_timestamps
    from mapping.pose_files import _frame_keys

    path = Path(path)
    kind, numbers, stamps, values, per_channel = read_exposure_file(path)
    frame_stamps, frame_numbers = _frame_keys(dataset)
    n = len(frame_stamps)
    out = np.full((n, 3), np.nan)
    rows = np.full(n, -1, dtype=np.int64)
    if kind == "radiomap":
        order = np.argsort(numbers, kind="stable")       # shifts step through the frame numbers
        numbers, stamps, values = numbers[order], stamps[order], values[order]
        by_number = {int(k): r for r, k in enumerate(numbers)}
        for i, number in enumerate(frame_numbers):
            if int(number) in by_number:
                rows[i] = by_number[int(number)]
                out[i] = values[rows[i]]
        how = "by frame number"
    else:
        ia, ib = associate_timestamps(frame_stamps, stamps, max_difference=max_difference)
        out[ia] = values[ib]
        rows[ia] = ib
        how = f"by timestamp within {max_difference:g} s"
        total = getattr(dataset, "total_frames", None)
        if len(ia) == 0 and total is not None and len(values) == total and frame_numbers.max() < total:
            out = values[frame_numbers]
            rows = frame_numbers.astype(np.int64)
            how = "in order (one row per frame; the timestamps do not match the sequence's)"
            log.warning("%s: no timestamp matches the sequence's within %g s; its %d rows are taken in order, one "
                        "per frame", path, max_difference, len(values))
    if kind != "radiomap" and "in order" not in how and np.any(np.diff(stamps) < 0):
        rows = None                     # rows out of time order: a shift by rows means nothing
    table = KnownExposures(path, kind, out, per_channel, how, rows, values, stamps)
    matched = table.matched
    count = f" (the file has {len(values)} rows, the sequence {total} frames)" if kind != "radiomap" and (
        total := getattr(dataset, "total_frames", None)) is not None else ""
    if every_frame is not None and matched < n:
        raise ExposureFileError(f"{path}: {n - matched} of {n} frames have no exposure ({how}){count}; {every_frame} "
                                "needs one per frame (radiomap self-calibrate fits the missing ones and writes them all "
                                "to its exposures.txt)")
    if too_little(matched, n):
        raise ExposureFileError(f"{path}: {n - matched} of {n} frames have no exposure ({how}){count}; a run needs "
                                f"{rule_text()} with one; check that the list belongs to this sequence and uses its "
                                "clock, or give one row per frame")
    if matched < n:
        log.warning("%s: %d of %d frames have no exposure in the file; theirs are fitted", path, n - matched, n)
    return table


__all__ = ["EXPOSURE_FILE_KINDS", "ExposureFileError", "KnownExposures", "match_exposure_file",
           "read_exposure_file"]
