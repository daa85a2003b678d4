"""The sequence list of a batch and the names of the results folders: ``LIST`` holds one sequence folder a line
(blank lines and ``#`` comments skipped; a relative path is relative to the list's own folder), and each sequence
gets ``OUT/<name>/``, its folder's name made unique (``redkitchen/seq-01`` and ``chess/seq-01`` become
``redkitchen_seq-01`` and ``chess_seq-01``)."""

from __future__ import annotations

import os
from pathlib import Path

from mapping.batch.runner import LOGS, BatchError
from radiometry.textlists import list_lines

#: names a sequence's results folder may not take in OUT (the batch's own files)
RESERVED = frozenset({LOGS, "summary.csv", "index.html"})


def read_sequence_list(path: str | os.PathLike) -> list[Path]:
    """The sequence folders ``path`` lists (absolute), or a :class:`BatchError` naming the line of a folder that
    does not exist or is listed twice, or the list when it names none."""
    path = Path(path)
    try:
        lines = list_lines(path)
    except OSError as exc:
        raise BatchError(f"{path}: cannot read the sequence list ({exc.strerror or exc})") from None
    sequences: dict[Path, int] = {}
    for number, line in lines:
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        folder = Path(os.path.abspath(path.parent / Path(text).expanduser()))
        if not folder.is_dir():
            raise BatchError(f"{path}, line {number}: {folder} is not a folder; list one sequence folder a line "
                             "(relative paths are relative to the list's folder)")
        if folder in sequences:
            raise BatchError(f"{path}, line {number}: {folder} is listed twice (first on line {sequences[folder]})")
        sequences[folder] = number
    if not sequences:
        raise BatchError(f"{path}: lists no sequence folder (one folder a line, '#' starts a comment)")
    return list(sequences)


def task_names(sequences: list[Path]) -> list[str]:
    """A results folder name per sequence: the folder's name, with as many parent folders as it takes to tell
    sequences apart (joined by ``_``), and a number where even the whole paths agree that far."""
    depth = {s: 1 for s in sequences}

    def name(s: Path) -> str:
        parts = [p for p in s.parts if p not in ("/", "")]
        return "_".join(parts[-depth[s]:])

    for _ in range(max((len(s.parts) for s in sequences), default=1)):
        names = [name(s) for s in sequences]
        clashes = {s for s, n in zip(sequences, names) if names.count(n) > 1 or n in RESERVED or n.startswith(".")}
        if not clashes:
            return names
        for s in clashes:
            depth[s] = min(depth[s] + 1, len(s.parts))
    names, seen = [], set()
    for s in sequences:
        n, k = name(s), 2
        while n in seen or n in RESERVED:
            n, k = f"{name(s)}-{k}", k + 1
        seen.add(n)
        names.append(n)
    return names


__all__ = ["RESERVED", "read_sequence_list", "task_names"]
