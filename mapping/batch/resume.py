"""What a batch checks in ``OUT`` before it runs anything, so that a resumed batch reports only results made by
this batch's command and options (docs/guides/batch.md, "What resume guarantees"):

- :func:`recorded_run`: the record of the run that made a results folder (its ``config.json``, or the ``run`` of a
  self-calibration's ``self_calibration.json``): the command, the sequence and the options;
- :func:`changed_options`: the options that differ between a folder's record and this batch's (the place and
  the progress bar do not count), and the input digests when both records hold them;
- :func:`refusal`: the one-line refusal for the complete folders a batch would otherwise skip although they were
  made by another command, from another sequence or with other options;
- :func:`damage`: why a finished folder is not whole: a file its run listed (``.radiomap-files.json``, its results
  folders' too) or the command needs is missing, empty or, a JSON file, unreadable.

Nothing here writes; :mod:`mapping.batch.runner` and :mod:`mapping.batch.sequences` act on the answers.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from mapping.replay import INPUTS_KEY

#: the record of a run: (file in its folder, key of the record in it; None: the whole file)
RECORDS = (("config.json", None), ("self_calibration.json", "run"))
#: parameters that say where a run read and wrote, not what it computed (compared apart: the sequence)
PLACE = frozenset({"sequence", "output"})
#: recorded options that do not change a run's results (self-calibrate's figures: --no-plots), never compared
NO_EFFECT = frozenset({"plots"})
#: the list of files a run wrote (:data:`mapping.export.MANIFEST`; spelled here so that nothing heavy is imported)
FILE_LIST = ".radiomap-files.json"


def recorded_run(folder: str | os.PathLike) -> dict | None:
    """The record of the run that made ``folder`` (``command``, ``parameters`` with ``sequence``, ...), or None
    when the folder holds none that reads."""
    folder = Path(folder)
    for name, key in RECORDS:
        try:
            doc = json.loads((folder / name).read_text(encoding="utf-8"))
        except (OSError, ValueError, UnicodeDecodeError, RecursionError):
            continue
        if key is not None:
            doc = doc.get(key) if isinstance(doc, dict) else None
        if isinstance(doc, dict) and isinstance(doc.get("parameters"), dict):
            return doc
    return None


def recorded_sequence(record: dict | None) -> Path | None:
    """The sequence folder a record names (absolute), or None."""
    value = (record or {}).get("parameters", {}).get("sequence")
    return Path(os.path.abspath(value)) if isinstance(value, str) and value else None


def _plain(value: Any) -> Any:
    """``value`` as JSON reads it back (tuples as lists, paths as text), to compare a record with a new run."""
    return json.loads(json.dumps(value, default=str))


def changed_options(old: dict, new: dict) -> list[tuple[str, Any, Any]]:
    """``(name, old value, new value)`` of every option the records ``old`` (a folder's) and ``new`` (this
    batch's) both hold with different values, the place (:data:`PLACE`) left out; an option one record does not
    hold (written by an older radiomap) is not compared. The input files' recorded contents (``inputs``, where both
    records hold a file's sha256) and top-level entries named ``*digest*`` or ``*sha256*``
    that both hold are compared too (the contents of the input files, where a record keeps them)."""
    a, b = _plain(old.get("parameters") or {}), _plain(new.get("parameters") or {})
    changed = [(k, a[k], b[k]) for k in a if k in b and k not in PLACE | NO_EFFECT and a[k] != b[k]]
    for key in old:
        if ("digest" in key or "sha256" in key) and key in new and _plain(old[key]) != _plain(new[key]):
            changed.append((key, "recorded contents", "other contents"))
    # the input files' contents (mapping.replay: "inputs", per option its path, sha256 and size), where both hold one
    before, now = old.get(INPUTS_KEY), new.get(INPUTS_KEY)
    if isinstance(before, dict) and isinstance(now, dict):
        for name, record in before.items():
            digest = record.get("sha256") if isinstance(record, dict) else None
            other = now.get(name).get("sha256") if isinstance(now.get(name), dict) else None
            if digest and other and digest != other and name not in {k for k, _, _ in changed}:
                changed.append((name, f"{record.get('path', '?')} (sha256 {digest[:12]})",
                                f"other contents (sha256 {other[:12]})"))
    return changed


def option_text(name: str) -> str:
    """The command-line spelling of a recorded option (``voxel_size`` -> ``--voxel-size``)."""
    return name if name.startswith("-") or "digest" in name or "sha256" in name else "--" + name.replace("_", "-")


def _value_text(value: Any) -> str:
    if value is None:
        return "not given"
    if isinstance(value, list):
        return ",".join(map(str, value)) or "none"
    return str(value)


def mismatch(folder: Path, command: str, sequence: Path, record: dict | None, new: dict | None) -> str | None:
    """Why the complete ``folder`` is not a result of ``command`` on ``sequence`` with the options of the record
    ``new`` (this batch's; None: the command and the sequence only): another command, another sequence, other
    options (old -> new); None when it is."""
    if record is None:
        return None
    if record.get("command") not in (None, command):
        return f"it holds a {record['command']} run, not {command}"
    made_from = recorded_sequence(record)
    if made_from is not None and made_from != Path(os.path.abspath(sequence)):
        return f"it holds the results of {made_from}, not of {sequence}"
    changed = [] if new is None else changed_options(record, new)
    if changed:
        return "made with other options (" + "; ".join(f"{option_text(k)} {_value_text(o)} -> {_value_text(n)}"
                                                       for k, o, n in changed) + ")"
    return None


def refusal(found: list[tuple[Path, str]]) -> str | None:
    """One line refusing a batch whose complete folders ``found`` (folder, :func:`mismatch`) it would otherwise
    skip and report as its own; None when there are none."""
    if not found:
        return None
    (folder, why), rest = found[0], found[1:]
    more = f"; so do {len(rest)} more ({', '.join(f.name for f, _ in rest)})" if rest else ""
    return (f"{folder}: complete, but {why}{more}; resuming would report those results as this batch's: give "
            "another -o for the new results, or --force to run the complete sequences again with this batch's options")


def listed_outputs(folder: Path) -> tuple[list[str], list[str]]:
    """The files and the results folders the run of ``folder`` listed in its ``.radiomap-files.json`` (none when
    it has no such list)."""
    try:
        doc = json.loads((folder / FILE_LIST).read_text(encoding="utf-8"))
    except (OSError, ValueError, UnicodeDecodeError, RecursionError):
        return [], []

    def own(names) -> list[str]:
        return [n for n in (names if isinstance(names, list) else []) if isinstance(n, str) and n == Path(n).name
                and n not in ("", ".", "..")]

    return (own(doc.get("files")), own(doc.get("folders"))) if isinstance(doc, dict) else ([], [])


def damage(folder: str | os.PathLike, required: tuple[str, ...] | list[str] = ()) -> str | None:
    """Why the finished results folder ``folder`` is not whole, naming the file (``mesh.ply is missing``,
    ``none/histogram.json is empty``), or None: every file its run listed and every name in ``required`` is
    there and not empty, every JSON file among them reads, and so does each results folder the run listed (by
    its own list)."""
    folder = Path(folder)
    files, folders = listed_outputs(folder)
    for name in dict.fromkeys([*required, *files]):
        path = folder / name
        try:
            size = path.stat().st_size
        except OSError:
            return f"{name} is missing"
        if not path.is_file():
            return f"{name} is not a file"
        if size == 0:
            return f"{name} is empty"
        if path.suffix == ".json":
            try:
                json.loads(path.read_text(encoding="utf-8"))
            except (OSError, ValueError, UnicodeDecodeError, RecursionError):
                return f"{name} does not read as JSON"
    for name in folders:
        if not (folder / name).is_dir():
            return f"{name}/ is missing"
        why = damage(folder / name)
        if why is not None:
            return f"{name}/{why}"
    return None


__all__ = ["FILE_LIST", "PLACE", "RECORDS", "changed_options", "damage", "listed_outputs", "mismatch",
           "option_text", "recorded_run", "recorded_sequence", "refusal"]
