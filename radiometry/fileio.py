"""File boundary for writes: atomic writes, all-or-nothing publication of file sets, the model file format.

Every write goes through here so that errors name the file and the fix, and no write ever leaves a half
file where a good one stood. Images are read and written by :mod:`radiometry.images` (RGB, depth in metres),
single arrays and the real-number check of model arrays by :mod:`radiometry.arrays`.

Model files (response, vignetting, ...) share one versioned, self-describing format: a NumPy ``.npz``
archive (read with ``allow_pickle=False``) whose ``meta`` entry is a JSON document with at least
``{"format": "radiomap", "kind": <kind>, "version": <int>}``; the remaining entries are plain arrays.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import math
import os
import re
import shutil
import struct
import tempfile
import tokenize
import zipfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.arrays import check_real_arrays, npz_header_dtypes, refuse_bare_npy
from radiometry.errors import CalibrationFileError, OutputError

log = logging.getLogger(__name__)

MODEL_FORMAT = "radiomap"
MODEL_FORMAT_VERSION = 1

_UMASK = os.umask(0o022)
os.umask(_UMASK)


# --------------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------------
def _os_error_message(path: Path, exc: OSError) -> str:
    if exc.errno == errno.ENOSPC:
        return f"cannot write {path}: the disk is full; free some space or choose another output folder"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return f"cannot write {path}: permission denied; choose a writable output folder"
    if exc.errno == errno.EROFS:
        return f"cannot write {path}: the file system is read-only; choose a writable output folder"
    if exc.errno == errno.ENAMETOOLONG:
        return f"cannot write {path}: the name or path is too long; choose a shorter one"
    if exc.errno in (errno.EMFILE, errno.ENFILE):
        return (f"cannot write {path}: too many open files; raise the limit (ulimit -n) or close other programs, "
                "then run again")
    return f"cannot write {path}: {exc.strerror or exc}; choose another output folder"


def ensure_dir(path: str | os.PathLike) -> Path:
    """Create a folder (and parents) or raise :class:`OutputError` naming it."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise OutputError(f"output folder {path} is an existing file; choose a folder name")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(_os_error_message(path, exc)) from None
    if not os.access(path, os.W_OK):
        raise OutputError(f"cannot write into {path}: permission denied; choose a writable output folder")
    return path


def check_overwrite(path: str | os.PathLike, *companions: str | os.PathLike, force: bool) -> None:
    """Refuse to replace an existing calibration unless ``force`` is given; ``companions``: the files written beside
    it (plot, record, summaries), refused the same way (a run with another suffix, e.g. ``-o crf.txt`` after
    ``-o crf.npz``, would otherwise replace the first run's ``crf.json`` and ``crf.png`` without a word)."""
    if force:
        return
    path = Path(path)
    if path.exists():
        raise OutputError(f"{path} exists; pass --force to overwrite it or choose another name")
    for side in map(Path, companions):
        if side.exists():
            raise OutputError(f"{side} exists (written beside another output by an earlier run) and {path} would "
                              "replace it; pass --force to overwrite it or choose another name")


def check_outputs(pairs: Sequence[tuple[str | os.PathLike, str | os.PathLike]], *, fix_input: str,
                  fix_shared: str) -> None:
    """Refuse, before anything is written, ``(input, output)`` pairs where an output is one of the inputs (it would
    overwrite an original) or two inputs share one output (one result would silently replace the other).

    Raises :class:`OutputError` naming the first collision and ending with ``fix_input`` or ``fix_shared``."""
    inputs: dict[str, Path] = {}
    for source, _target in pairs:
        inputs.setdefault(_identity(source), Path(source))
    outputs: dict[str, Path] = {}
    for source, target in pairs:
        key = _identity(target)
        original = inputs.get(key) or next((p for p in inputs.values() if _same_file(p, target)), None)
        if original is not None:
            raise OutputError(f"{target} is the input {original}: writing it would overwrite the original; {fix_input}")
        first = outputs.setdefault(key, Path(source))
        if first != Path(source):
            raise OutputError(f"{first} and {source} would both be written to {target} (one result would replace "
                              f"the other); {fix_shared}")


def refuse_inputs(outputs: Sequence[str | os.PathLike], inputs: Sequence[str | os.PathLike], *,
                  fix: str = "choose another output name (-o); --force never replaces an input") -> None:
    """Refuse, before anything is written, to write any of ``outputs`` (a command's files, companions included)
    over one of ``inputs`` (the files it reads), with or without ``--force``: :class:`OutputError` naming both
    and ``fix``. The same file is recognised through another spelling of its path, a symbolic or a hard link."""
    names = {_identity(p): Path(p) for p in inputs}
    inodes = {}
    for p in inputs:
        with contextlib.suppress(OSError):
            st = os.stat(p)
            inodes[(st.st_dev, st.st_ino)] = Path(p)
    for out in outputs:
        original = names.get(_identity(out))
        if original is None:
            with contextlib.suppress(OSError):
                st = os.stat(out)
                original = inodes.get((st.st_dev, st.st_ino))
        if original is not None:
            raise OutputError(f"{out} is the input {original}: writing it would overwrite the original; {fix}")


def _identity(path: str | os.PathLike) -> str:
    return os.path.normcase(os.path.realpath(path))


def _same_file(a: Path, b: str | os.PathLike) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:  # the output does not exist yet
        return False


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it into place only if the block succeeds.

    The temporary name keeps the final suffix so that writers choosing a format by extension (OpenCV,
    trimesh, matplotlib) still work. On any exception the temporary file is removed and ``path`` is
    left exactly as it was.
    """
    path = Path(path)
    ensure_dir(path.parent if str(path.parent) else Path("."))
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}{TEMP_TAG}{os.getpid()}-", suffix=path.suffix,
                                   dir=path.parent)
    except OSError as exc:
        raise OutputError(_os_error_message(_published_name(path), exc)) from None
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp creates 0600; follow the user's umask like open() does
    try:
        yield tmp_path
        if not tmp_path.exists() or tmp_path.stat().st_size == 0 and not _allow_empty(path):
            raise OutputError(f"writing {_published_name(path)} produced no data; nothing was replaced")
        os.replace(tmp_path, path)
    except OSError as exc:
        raise OutputError(_os_error_message(_published_name(path), exc)) from None
    finally:
        with contextlib.suppress(OSError):
            tmp_path.unlink()


def _allow_empty(path: Path) -> bool:
    return path.suffix in (".txt", ".csv", ".log")


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """``obj`` as indented JSON, NaN and infinities as null (:func:`json_safe`), written atomically."""
    return atomic_write_text(path, json.dumps(json_safe(obj), indent=2, sort_keys=False, allow_nan=False) + "\n")


def json_safe(obj: Any) -> Any:
    """``obj`` with what JSON cannot hold made plain: NaN and infinities None, numpy scalars and arrays Python
    numbers and lists, paths strings, tuples lists, keys strings. Anything else not JSON-plain is a TypeError."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if obj is None or isinstance(obj, (bool, int, str)):
        return obj
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, np.generic):
        return json_safe(obj.item())
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    raise TypeError(f"cannot serialise {type(obj).__name__} to JSON")


# --------------------------------------------------------------------------------------------------
# publication of a set of files (a calibration and its companions): all or nothing
# --------------------------------------------------------------------------------------------------
#: Every temporary radiomap creates is named ``.<something>.tmp-radiomap-<pid>-<random>[<suffix>]`` (an atomic
#: write's file) or ``.tmp-radiomap-<pid>-<random>`` (a publication's staging folder): recognisable, and the pid
#: tells whether the process that made it still runs (:func:`remove_strays`).
TEMP_TAG = ".tmp-radiomap-"
_TEMP_RE = re.compile(r"^\.(?:.*\.)?tmp-radiomap-(\d+)-")
_JOURNAL = ".radiomap-journal.json"    # in a staging folder: its renames have begun (roll back if found)
_BACKUPS = ".radiomap-old"             # in a staging folder: hard links to the files the set replaces
_STAGES: dict[Path, Path] = {}         # staging folder -> destination folder, of this process's open sets


def _published_name(path: Path) -> Path:
    """``path`` as the user will see it: a file in a staging folder is named by its destination."""
    dest = _STAGES.get(path.parent)
    return dest / path.name if dest is not None else path


def pid_alive(pid: int) -> bool:
    """True when a process with this id runs (or may run: one of another user)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except (OverflowError, ValueError):
        return False
    return not _zombie(pid)


def _zombie(pid: int) -> bool:
    """True when ``pid`` has exited but its parent has not reaped it yet (``State: Z`` in /proc, Linux): it holds
    nothing (a batch worker killed a moment ago), so its locks and temporaries are stale."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("State:"):
                    return line.split()[1] in ("Z", "X")
    except (OSError, IndexError):
        return False
    return False


def remove_strays(folder: str | os.PathLike) -> list[str]:
    """Remove the temporaries of radiomap processes that no longer run from ``folder``; return their names.

    Atomic-write files and publication staging folders are recognised by name (``TEMP_TAG`` and the pid); a
    staging folder that holds a journal was killed half-way through its renames: the files it replaced are put
    back first (:class:`FileSet`), so the folder holds the old set again. Temporaries of live processes (a
    concurrent run) are left alone."""
    folder = Path(folder)
    removed: list[str] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for entry in entries:
        match = _TEMP_RE.match(entry.name)
        if match is None or pid_alive(int(match.group(1))):
            continue
        path = Path(entry.path)
        try:
            if entry.is_dir(follow_symlinks=False):
                if (path / _JOURNAL).is_file():
                    _roll_back(path, folder)
                    log.warning("%s: a result interrupted while it was being published was rolled back "
                                "(the previous files are in place again)", folder)
                shutil.rmtree(path)
            else:
                path.unlink()
        except OSError as exc:
            log.warning("could not remove the stray temporary %s: %s", path, exc)
            continue
        removed.append(entry.name)
    if removed:
        log.info("removed %d temporaries of interrupted runs from %s: %s", len(removed), folder, ", ".join(removed))
    return removed


def _roll_back(stage: Path, dest: Path) -> None:
    """Undo the renames of a staging folder whose journal lists them: every replaced file is restored from its
    backup, every file the set added is removed; a moved entry (a folder, or a name the set retired) is moved back
    from the backups, the new one it was replaced by back into the staging folder."""
    try:
        entries = json.loads((stage / _JOURNAL).read_text("utf-8"))["files"]
    except FileNotFoundError:  # the journal was never written: no rename had begun
        return
    except (ValueError, KeyError, TypeError):  # cut short while written: no rename had begun
        entries = []
    for name, existed, *moved in reversed(entries):
        backup = stage / _BACKUPS / name
        if moved:
            if existed and not os.path.lexists(backup):   # not moved yet: the previous entry is in place
                continue
            if os.path.lexists(dest / name) and not os.path.lexists(stage / name):  # the new one was moved in
                os.rename(dest / name, stage / name)
            if existed:
                os.rename(backup, dest / name)
        elif existed:
            if backup.exists():
                os.replace(backup, dest / name)
        elif not (stage / name).exists():  # it was renamed into place: the set added it
            with contextlib.suppress(FileNotFoundError):
                (dest / name).unlink()
    (stage / _JOURNAL).unlink()


def published_path(path: str | os.PathLike) -> Path:
    """``path`` under the name it is (or will be) published as: a path inside a staging folder of this process
    (at any depth, through nested staging folders) is named by its destination, relative if it was given
    relative; any other path is returned as is."""
    path = Path(path)
    for _ in range(8):
        for stage, dest in list(_STAGES.items()):
            for form in (lambda p: Path(os.path.normpath(p)), lambda p: Path(os.path.abspath(p))):
                inside, top = form(path), form(stage)
                if inside == top or top in inside.parents:
                    path = form(dest) / inside.relative_to(top)
                    break
            else:
                continue
            break
        else:
            break
    return path


def _fsync_path(path: Path, *, directory: bool = False) -> None:
    fd = os.open(path, os.O_RDONLY | (os.O_DIRECTORY if directory else 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


class FileSet:
    """Files published together or not at all: see :func:`publish_set`."""

    def __init__(self, primary: Path | None) -> None:
        self.primary = None if primary is None else Path(primary)
        self._stages: dict[Path, Path] = {}   # destination folder -> staging folder
        self._committed: list[tuple[Path, Path]] = []
        self._kept: set[Path] = set()         # staging folders whose roll-back failed: the next run finishes it
        self._retired: dict[Path, set[str]] = {}   # staging folder -> names its commit moves out of the destination

    def path(self, final: str | os.PathLike) -> Path:
        """Where to write the file (or file-name prefix) ``final``: the same name in a staging folder beside it."""
        final = Path(final)
        dest = final.parent if str(final.parent) else Path(".")
        key = Path(os.path.abspath(dest))
        stage = self._stages.get(key)
        if stage is None:
            ensure_dir(dest)
            remove_strays(dest)
            try:
                stage = Path(tempfile.mkdtemp(prefix=f"{TEMP_TAG}{os.getpid()}-", dir=dest))
            except OSError as exc:
                raise OutputError(_os_error_message(final, exc)) from None
            self._stages[key] = stage
            _STAGES[stage] = dest
        return stage / final.name

    def final(self, staged: str | os.PathLike) -> Path:
        """The destination of a path :meth:`path` returned, or of any path inside a staging folder (for records
        that name the published files)."""
        staged = Path(staged)
        dest = _STAGES.get(staged.parent)
        if dest is not None:
            staged = dest / staged.name
        return published_path(staged) if any(TEMP_TAG in part for part in staged.parts) else staged

    def retire(self, final: str | os.PathLike) -> None:
        """Remove ``final`` (a file or a folder of the previous set that the new one does not replace) as part of
        the commit: moved away with the renames, put back if they are rolled back."""
        final = Path(final)
        stage = self.path(final).parent
        self._retired.setdefault(stage, set()).add(final.name)

    # ---- commit / abort
    def _names(self, stage: Path) -> list[str]:
        """The files and folders staged in ``stage`` (the model last)."""
        names = sorted(e.name for e in os.scandir(stage) if (e.is_file(follow_symlinks=False) or
                       e.is_dir(follow_symlinks=False)) and not _TEMP_RE.match(e.name)
                       and e.name not in (_JOURNAL, _BACKUPS))
        if self.primary is not None and _same_folder(_STAGES[stage], self.primary.parent) and \
                self.primary.name in names:  # the model last: its companions are in place before it changes
            names.remove(self.primary.name)
            names.append(self.primary.name)
        return names

    def _order(self) -> list[Path]:
        """Staging folders, the primary file's last."""
        stages = list(self._stages.values())
        if self.primary is not None:
            stages.sort(key=lambda s: _same_folder(_STAGES[s], self.primary.parent))
        return stages

    def commit(self) -> None:
        """Rename the staged files into place (a folder, or a name replaced by one, is moved: the previous entry
        into the backups first), after the names :meth:`retire` moves away, the model last; a journal lists them
        until the last rename (the commit point)."""
        current = None
        try:
            plans = []
            for stage in self._order():
                dest = _STAGES[stage]
                entries = [[name, True, "moved"] for name in sorted(self._retired.get(stage, ()))
                           if os.path.lexists(dest / name)]
                for name in self._names(stage):
                    current = dest / name
                    if (stage / name).is_dir() or ((dest / name).is_dir() and not (dest / name).is_symlink()):
                        entries.append([name, os.path.lexists(dest / name), "moved"])
                        continue
                    _fsync_path(stage / name)
                    entries.append([name, _backup(dest / name, stage / _BACKUPS / name)])
                plans.append((stage, dest, entries))
            for stage, dest, entries in plans:
                current = dest / entries[0][0] if entries else dest
                self._committed.append((stage, dest))
                with open(stage / _JOURNAL, "w", encoding="utf-8") as fh:
                    json.dump({"pid": os.getpid(), "files": entries}, fh)
                    fh.flush()
                    os.fsync(fh.fileno())
                for name, existed, *moved in entries:
                    current = dest / name
                    if not moved:
                        os.replace(stage / name, dest / name)
                        continue
                    if existed:
                        (stage / _BACKUPS).mkdir(exist_ok=True)
                        os.rename(dest / name, stage / _BACKUPS / name)
                    if os.path.lexists(stage / name):
                        os.rename(stage / name, dest / name)
                current = dest
                _fsync_path(dest, directory=True)
        except OSError as exc:
            raise OutputError(_os_error_message(current, exc)) from None
        for stage, _dest in self._committed:  # the commit point: from here on the new set stands
            with contextlib.suppress(OSError):
                (stage / _JOURNAL).unlink()
        self._committed.clear()

    def abort(self) -> None:
        """Put back what a failed commit replaced and remove every staging folder (never raises)."""
        for stage, dest in reversed(self._committed):
            try:
                _roll_back(stage, dest)
            except OSError as exc:  # the next run in this folder retries (remove_strays)
                self._kept.add(stage)
                log.warning("could not roll back the publication in %s: %s", dest, exc)
        self._committed.clear()

    def cleanup(self) -> None:
        for stage in self._stages.values():
            if stage not in self._kept:
                shutil.rmtree(stage, ignore_errors=True)
            _STAGES.pop(stage, None)
        self._stages.clear()


def _same_folder(a: Path, b: Path) -> bool:
    return os.path.abspath(a if str(a) else ".") == os.path.abspath(b if str(b) else ".")


def _backup(path: Path, backup: Path) -> bool:
    """Hard-link ``path`` (if it exists) to ``backup``, a copy where links are not supported; True if it existed."""
    try:
        backup.parent.mkdir(exist_ok=True)
        os.link(path, backup)
    except FileNotFoundError:
        return False
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.EXDEV, errno.EMLINK, errno.ENOTSUP, errno.EOPNOTSUPP):
            raise
        shutil.copy2(path, backup)
    return True


@contextlib.contextmanager
def publish_set(primary: str | os.PathLike | None = None) -> Iterator[FileSet]:
    """Publish a calibration and its companions (figures, JSON, summaries) together or not at all.

    Write every file to ``fs.path(final)`` (the same name in a hidden staging folder beside ``final``); when the
    block succeeds every file is renamed into place, ``primary`` (the model) last. If the block or the renames
    fail (disk full, Ctrl-C), the files the set replaced are put back and nothing of the new set remains: the
    old set stands byte for byte. A process killed during the renames leaves a journal that the next
    publication into the folder (:func:`remove_strays`) rolls back; stray temporaries of dead processes are
    removed there too. SIGINT/SIGTERM wait while the renames run (a few system calls)::

        with publish_set(out) as fs:
            model.save(fs.path(out))
            save_figure(fig, fs.path(out.with_suffix(".png")))
    """
    fs = FileSet(None if primary is None else Path(primary))
    try:
        yield fs
        with _signals_deferred():
            try:
                fs.commit()
            except BaseException:
                fs.abort()
                raise
    except OutputError as exc:
        raise OutputError(_unstage(str(exc))) from None
    except OSError as exc:  # a writer that does not go through atomic_path
        name = _published_name(Path(exc.filename)) if exc.filename else primary or "the output"
        raise OutputError(_os_error_message(Path(name), exc)) from None
    finally:
        fs.cleanup()


def _unstage(message: str) -> str:
    for stage, dest in _STAGES.items():
        message = message.replace(str(stage) + os.sep, str(dest) + os.sep)
    return message


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Block SIGINT and SIGTERM (delivered when the block ends) in the main thread, where Python handles them."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread() or not hasattr(signal, "pthread_sigmask"):
        yield
        return
    blocked = {signal.SIGINT, signal.SIGTERM}
    old = signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


# --------------------------------------------------------------------------------------------------
# model files
# --------------------------------------------------------------------------------------------------
def save_model_file(path: str | os.PathLike, kind: str, arrays: Mapping[str, np.ndarray],
                    meta: Mapping[str, Any] | None = None, *, version: int = MODEL_FORMAT_VERSION) -> Path:
    """Write a model archive atomically: ``arrays`` plus a JSON ``meta`` describing them."""
    header = {"format": MODEL_FORMAT, "kind": kind, "version": int(version)}
    header.update(dict(meta or {}))
    header["arrays"] = {name: {"shape": list(np.shape(a)), "dtype": str(np.asarray(a).dtype)}
                        for name, a in arrays.items()}
    payload = {name: np.asarray(a) for name, a in arrays.items()}
    if "meta" in payload:
        raise ValueError("'meta' is reserved in model files; rename that array")
    payload["meta"] = np.array(json.dumps(json_safe(header)))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **payload)
    return Path(path)


def check_model_suffix(path: str | os.PathLike, model: str, writers: Mapping[str, str]) -> Path:
    """``path`` if it names a ``.npz`` file (what a model's own ``save`` writes), else ValueError naming the writer of
    ``writers`` (suffix -> function) for its suffix: a model saved as ``x.crf`` or ``v.png`` would otherwise be a zip
    under a foreign format's name that no reader (radical, DSO, radiomap's by suffix) can read back."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix != ".npz":
        writer = writers.get(suffix)
        raise ValueError(f"path {str(path)!r}: {model}.save writes radiomap's .npz only, not "
                         f"{suffix or 'a name without a suffix'}; "
                         + (f"write {suffix} with {writer}" if writer else "name the file .npz"))
    return path


def load_model_file(path: str | os.PathLike, kind: str, *,
                    max_version: int = MODEL_FORMAT_VERSION) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a model archive written by :func:`save_model_file`, checking format, kind and version."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file; check the path of the {kind} model")
    fix = f"re-create the {kind} file with radiomap"
    refuse_bare_npy(path, kind)
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):  # a .npy array under another name (the check above)
            refuse_bare_npy(path, kind, bare=True)
        with loaded as data:
            arrays = {name: data[name] for name in data.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError, zlib.error, NotImplementedError,
            RuntimeError, struct.error, UnicodeDecodeError, OverflowError, tokenize.TokenError, SyntaxError,
            MemoryError) as exc:
        # everything a corrupt, truncated or foreign .npz raises while its members are decompressed (a
        # mangled .npy header fails to tokenize, or claims an array too large to allocate); an object array
        # (pickled Python objects, refused by allow_pickle=False) is named as such
        if isinstance(exc, ValueError):
            check_real_arrays(path, {k: v for k, v in npz_header_dtypes(path).items() if k != "meta"}, fix)
        raise CalibrationFileError(
            f"{path}: not a radiomap {kind} file or corrupt ({type(exc).__name__}); re-create it with radiomap"
        ) from None
    if "meta" not in arrays:
        raise CalibrationFileError(f"{path}: no 'meta' entry, not a radiomap {kind} file; re-create it")
    try:
        meta = json.loads(str(arrays.pop("meta")))
    except (json.JSONDecodeError, TypeError) as exc:
        raise CalibrationFileError(f"{path}: corrupt 'meta' entry ({exc}); re-create the file") from None
    except RecursionError:
        raise CalibrationFileError(f"{path}: corrupt 'meta' entry (nested too deeply); re-create the file") from None
    if not isinstance(meta, dict) or meta.get("format") != MODEL_FORMAT:
        raise CalibrationFileError(f"{path}: not a radiomap model file; re-create it with radiomap")
    if meta.get("kind") != kind:
        raise CalibrationFileError(
            f"{path}: holds a '{meta.get('kind')}' model where a '{kind}' model is needed; pass the right file")
    version = meta.get("version")
    if not isinstance(version, int) or version < 1 or version > max_version:
        raise CalibrationFileError(
            f"{path}: format version {version!r} is not supported (this radiomap reads up to {max_version}); "
            "upgrade radiomap or re-create the file")
    check_real_arrays(path, {name: a.dtype for name, a in arrays.items()}, fix)
    return meta, arrays
