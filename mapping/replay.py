"""What a replay (``radiomap reconstruct|compare --config RUN/config.json``) checks against the run it replays.

A run records in its config.json, beside its options, the content of every input file it read (``"inputs"``: per
option its absolute path, sha256 and size in bytes, :func:`input_records`) and the frames of its sequence
(``"dataset"``: their number, a sha256 of their file names and one of their ground-truth poses, :func:`frames_record`,
beside the K and depth scale the sequence gave, e.g. from its own intrinsics file). A replay takes from the file
only what the command line does not give; for every recorded file and for the sequence it takes from there, it
hashes the file (or lists the frames) again and refuses, in one line naming the file, what changed and the fix,
when they differ (:class:`ReplayInputChangedError`): paths alone would let a replay of a run whose response was
overwritten, or whose sequence grew, give other results with exit 0. Giving the option (or SEQUENCE) on the command
line accepts the file (the sequence) as it is now; an old config.json without these records still replays, with
a note that it cannot be checked.

The cost: every input file is read once per process (a digest is kept per path, size, modification time and
inode); the sequence check lists file names and reads the ground truth (about 22 ms per 100 7-Scenes frames), not
the images (a frame overwritten under the same name is not noticed).
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from radiometry.errors import RadiomapError

#: config.json's key of the input files' records
INPUTS_KEY = "inputs"
_CHUNK = 1 << 20
_DIGESTS: dict[tuple, str] = {}


class ReplayInputChangedError(RadiomapError):
    """An input of a replayed run (a recorded file, the sequence's frames) differs from what the recorded run read."""


def _file_digest(path: Path) -> tuple[str, int]:
    st = path.stat()
    key = (str(path), st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev)
    if key not in _DIGESTS:
        h = hashlib.sha256()
        with open(path, "rb") as f:
            while chunk := f.read(_CHUNK):
                h.update(chunk)
        _DIGESTS[key] = h.hexdigest()
    return _DIGESTS[key], st.st_size


def file_record(path: str | os.PathLike) -> dict[str, Any]:
    """``{"path", "sha256", "bytes"}`` of a file; of a folder (7-Scenes pose files, ``*.pose.txt``) the sha256 of
    its pose files' names and digests in name order, ``bytes`` their total size and ``files`` their number."""
    path = Path(os.path.abspath(os.fspath(path)))
    if path.is_dir():
        h, total, count = hashlib.sha256(), 0, 0
        for p in sorted(q for q in path.iterdir() if q.name.endswith(".pose.txt") and q.is_file()):
            digest, size = _file_digest(p)
            h.update(f"{p.name}\t{digest}\n".encode())
            total, count = total + size, count + 1
        return {"path": str(path), "sha256": h.hexdigest(), "bytes": total, "files": count}
    digest, size = _file_digest(path)
    return {"path": str(path), "sha256": digest, "bytes": size}


def input_records(values: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The records of the options in ``values`` ({option: value}) whose value names an existing file (a text, e.g.
    ``--intrinsics FILE``, or a path) or, given as a path, a folder (of pose files): what config.json keeps under
    :data:`INPUTS_KEY`."""
    out = {}
    for name, value in values.items():
        if (isinstance(value, (str, os.PathLike)) and os.path.isfile(value)) or \
                (isinstance(value, os.PathLike) and os.path.isdir(value)):
            out[name] = file_record(value)
    return out


def _short(digest: str | None) -> str:
    return "?" if not digest else digest[:12]


def check_inputs(config: str | os.PathLike, recorded: Mapping[str, Any], current: Mapping[str, Any],
                 spellings: Mapping[str, str]) -> None:
    """Refuse (:class:`ReplayInputChangedError`) when a file ``recorded`` by the run replayed from ``config`` differs
    from ``current`` (the records of the same options now, :func:`input_records`); ``spellings``: the options to
    check (those the replay took from ``config``) -> their spelling for the message."""
    for name, spelling in spellings.items():
        before = recorded.get(name)
        if not isinstance(before, Mapping) or "sha256" not in before:
            continue
        path = before.get("path", "?")
        now = current.get(name)
        fix = (f"restore it, give {spelling} {path} on the command line to use it as it is now, or run anew without "
               "--config")
        if now is None:
            raise ReplayInputChangedError(f"{config}: {spelling} {path} is gone since the recorded run read it "
                                          f"(sha256 {_short(before['sha256'])}, {before.get('bytes')} bytes); {fix}")
        if now.get("sha256") == before["sha256"]:
            continue
        what = f"sha256 {_short(before['sha256'])} recorded, {_short(now.get('sha256'))} now"
        if now.get("bytes") != before.get("bytes"):
            what += f"; {before.get('bytes')} bytes recorded, {now.get('bytes')} now"
        if "files" in before and now.get("files") != before.get("files"):
            what += f"; {before['files']} pose files recorded, {now.get('files')} now"
        raise ReplayInputChangedError(f"{config}: {spelling} {path} changed since the recorded run read it ({what}); "
                                      f"{fix}")


def frame_names(dataset) -> list[str] | None:
    """The selected frames' colour and depth file names relative to the sequence folder, or None for a dataset
    that is not read from files."""
    files = getattr(dataset, "frame_files", None)
    root = getattr(dataset, "root", None)
    if files is None or root is None:
        return None

    def rel(p) -> str:
        try:
            return Path(p).relative_to(root).as_posix()
        except ValueError:
            return Path(p).as_posix()
    return [f"{rel(f.rgb)}\t{rel(f.depth)}" for f in files]


def frames_record(dataset) -> dict[str, Any]:
    """What config.json's ``dataset`` records of the frames: ``frame_names_sha256`` (None when the dataset is not
    read from files), ``sequence_frames`` (the whole sequence's, before ``--frames`` selected some) and
    ``ground_truth_sha256`` (of the selected frames' ground-truth times and poses as float64; None without them)."""
    digest = _names_digest(dataset)
    return {"frame_names_sha256": digest, "sequence_frames": getattr(dataset, "total_frames", None),
            "ground_truth_sha256": None if digest is None else _ground_truth_digest(dataset)}


def _names_digest(dataset) -> str | None:
    names = frame_names(dataset)
    # names read from non-UTF-8 lists keep their bytes as surrogates (radiometry.textlists): hash those bytes
    return None if names is None else hashlib.sha256("\n".join(names).encode("utf-8", "surrogateescape")).hexdigest()


def _ground_truth_digest(dataset) -> str | None:
    import numpy as np

    truth = dataset.ground_truth()
    if truth is None:
        return None
    h = hashlib.sha256()
    for array in truth:
        h.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    return h.hexdigest()


def selection_record(sequence: str | os.PathLike, frames, format: str | None) -> dict[str, Any]:
    """What selected the frames (config.json's ``dataset.selected_with``): the sequence folder (absolute), ``--frames``
    as ``A:B:S`` (None: every frame) and ``--format``. A replay compares the recorded frames only while the options
    it takes from the file still say this (a hand-edited ``parameters.frames`` selects other frames on purpose)."""
    from mapping.export import frame_range_text

    text = frame_range_text(frames) if isinstance(frames, slice) or frames is None else str(frames)
    return {"sequence": os.path.abspath(os.fspath(sequence)), "frames": text, "format": format}


def check_frames(expected: Mapping[str, Any] | None, dataset) -> None:
    """Refuse (:class:`ReplayInputChangedError`) when the frames a replay selected differ from the recorded run's:
    ``expected`` is ``{"config": path, "sequence": path, "frames": N, "frame_names_sha256": hex or None, "K": 3 x 3
    or None, "depth_scale": number or None, "ground_truth_sha256": hex or None}`` (None: nothing to check, the
    sequence or --frames was given on the command line; a None value is not compared: K when --intrinsics was given,
    the depth scale when --depth-scale was)."""
    if not expected:
        return
    config, sequence = expected.get("config"), expected.get("sequence")
    fix = (f"restore the sequence, give SEQUENCE ({sequence}) or --frames on the command line to fuse it as it is "
           "now, or run anew without --config")
    n, recorded = len(dataset), expected.get("frames")
    if isinstance(recorded, int) and recorded != n:
        raise ReplayInputChangedError(f"{config}: the sequence {sequence} now gives {n} frames where the recorded run "
                                      f"had {recorded} (frames were added or removed); {fix}")
    digest = expected.get("frame_names_sha256")
    if digest:
        now = _names_digest(dataset)
        if now is not None and now != digest:
            raise ReplayInputChangedError(f"{config}: the sequence {sequence} gives {n} frames as recorded but their "
                                          f"file names differ (sha256 {_short(digest)} recorded, {_short(now)} now); "
                                          f"{fix}")
    _check_camera(expected, dataset, config, sequence)
    digest = expected.get("ground_truth_sha256")
    if digest:
        now = _ground_truth_digest(dataset)
        if now != digest:
            raise ReplayInputChangedError(
                f"{config}: the ground-truth poses of the sequence {sequence} differ from the recorded run's (sha256 "
                f"{_short(digest)} recorded, {_short(now)} now); restore them, give SEQUENCE ({sequence}) on the "
                "command line to use them as they are now, or run anew without --config")


def _check_camera(expected: Mapping[str, Any], dataset, config, sequence) -> None:
    """The intrinsics and depth scale the sequence gives now against the recorded ones (a file of the sequence, e.g.
    camera-intrinsics.txt, that changed)."""
    import numpy as np

    K = expected.get("K")
    if K is not None:
        now = np.asarray(dataset.K, dtype=np.float64)
        before = np.asarray(K, dtype=np.float64)
        if before.shape != now.shape or not np.allclose(before, now, rtol=1e-9, atol=0):
            def text(m):
                return ",".join(f"{v:.6g}" for v in (m[0, 0], m[1, 1], m[0, 2], m[1, 2])) if m.shape == (3, 3) \
                    else "?"
            raise ReplayInputChangedError(f"{config}: the sequence {sequence} now gives intrinsics {text(now)} where "
                                          f"the recorded run had {text(before)} (its intrinsics file changed); restore "
                                          "it, give --intrinsics on the command line, or run anew without --config")
    scale, now_scale = expected.get("depth_scale"), getattr(dataset, "depth_scale", None)
    if isinstance(scale, (int, float)) and isinstance(now_scale, (int, float)) and \
            not np.isclose(scale, now_scale, rtol=1e-9, atol=0):
        raise ReplayInputChangedError(f"{config}: the sequence {sequence} now gives depth scale {now_scale:g} where "
                                      f"the recorded run had {scale:g}; restore it, give --depth-scale on the command "
                                      "line, or run anew without --config")


def unchecked_note(config: str | os.PathLike, doc: Mapping[str, Any]) -> str | None:
    """The one-line note for a config.json written before inputs were recorded (nothing to check), else None."""
    if INPUTS_KEY in doc:
        return None
    return (f"note: {config} records no digests of its input files or frames (written by an older radiomap): the "
            "replay cannot check that they are unchanged")


__all__ = ["INPUTS_KEY", "ReplayInputChangedError", "check_frames", "check_inputs", "file_record", "frame_names",
           "frames_record", "input_records", "selection_record", "unchecked_note"]
