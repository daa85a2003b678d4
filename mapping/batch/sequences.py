"""The sequence list of a batch and the names of the results folders: ``LIST`` holds one sequence folder a line
(blank lines and ``#`` comments skipped; a relative path is relative to the list's own folder), and each sequence
gets ``OUT/<name>/``, its folder's name made unique (``redkitchen/seq-01`` and ``chess/seq-01`` become
``redkitchen_seq-01`` and ``chess_seq-01``). A resumed batch keeps the names: :func:`folder_names` gives each
sequence the folder of ``OUT`` that records it before it names the others."""

from __future__ import annotations

import os
from pathlib import Path

from mapping.batch.resume import recorded_run, recorded_sequence
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


def folder_names(sequences: list[Path], out: str | os.PathLike) -> tuple[list[str], list[str]]:
    """A results folder name per sequence that is stable across resumes, and notes on the folders of ``out`` that
    no listed sequence takes (left as they are, out of the summary).

    A folder of ``out`` whose record (config.json, :func:`mapping.batch.resume.recorded_run`) names a listed
    sequence keeps that sequence (the name :func:`task_names` would give first, when several do); the other
    sequences are named by :func:`task_names`, never with the name of a folder that records another sequence."""
    out = Path(out)
    owners: dict[str, Path] = {}       # folder name -> the sequence its record names
    if out.is_dir():
        for entry in sorted(out.iterdir()):
            if entry.is_dir() and not entry.name.startswith(".") and entry.name not in RESERVED:
                made_from = recorded_sequence(recorded_run(entry))
                if made_from is not None:
                    owners[entry.name] = made_from
    fresh = dict(zip(sequences, task_names(sequences)))
    kept: dict[Path, str] = {}
    for name, made_from in sorted(owners.items(), key=lambda item: item[0] != fresh.get(item[1])):
        if made_from in fresh and made_from not in kept:
            kept[made_from] = name
    new = [s for s in sequences if s not in kept]
    named = dict(zip(new, task_names(new, taken=set(owners))))
    notes = [f"note: {out / name} holds the results of {made_from}, "
             + ("which the list does not name" if made_from not in fresh else
                f"which this batch reports from {out / kept[made_from]}")
             + "; left as it is, not in the summary" for name, made_from in owners.items()
             if kept.get(made_from) != name]
    return [kept.get(s) or named[s] for s in sequences], notes


def task_names(sequences: list[Path], taken: set[str] = frozenset()) -> list[str]:
    """A results folder name per sequence: the folder's name, with as many parent folders as it takes to tell
    sequences apart (joined by ``_``) and from the names ``taken``, and a number where even the whole paths agree
    that far."""
    depth = {s: 1 for s in sequences}

    def name(s: Path) -> str:
        parts = [p for p in s.parts if p not in ("/", "")]
        return "_".join(parts[-depth[s]:])

    for _ in range(max((len(s.parts) for s in sequences), default=1)):
        names = [name(s) for s in sequences]
        clashes = {s for s, n in zip(sequences, names)
                   if names.count(n) > 1 or n in RESERVED or n in taken or n.startswith(".")}
        if not clashes:
            return names
        for s in clashes:
            depth[s] = min(depth[s] + 1, len(s.parts))
    names, seen = [], set()
    for s in sequences:
        n, k = name(s), 2
        while n in seen or n in RESERVED or n in taken:
            n, k = f"{name(s)}-{k}", k + 1
        seen.add(n)
        names.append(n)
    return names


__all__ = ["RESERVED", "folder_names", "read_sequence_list", "task_names"]
