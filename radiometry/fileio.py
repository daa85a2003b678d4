"""File boundary: images in RGB, depth in float32 metres, atomic writes, the model file format.

Everything that touches the disk goes through here so that errors name the file and the fix, colour
is converted from OpenCV's BGR exactly once, and no write ever leaves a half file where a good one stood.

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

from radiometry.errors import CalibrationFileError, ImageError, OutputError

log = logging.getLogger(__name__)

MODEL_FORMAT = "radiomap"
MODEL_FORMAT_VERSION = 1

_UMASK = os.umask(0o022)
os.umask(_UMASK)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")


# --------------------------------------------------------------------------------------------------
# atomic writes
# --------------------------------------------------------------------------------------------------
def _os_error_message(path: Path, exc: OSError) -> str:
    if exc.errno == errno.ENOSPC:
        return f"cannot write {path}: the disk is full; free some space or choose another output folder"
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"cannot write {path}: permission denied; choose a writable output folder"
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


def check_overwrite(path: str | os.PathLike, *, force: bool) -> None:
    """Refuse to replace an existing calibration unless ``force`` is given."""
    path = Path(path)
    if path.exists() and not force:
        raise OutputError(f"{path} exists; pass --force to overwrite it or choose another name")


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
    except OverflowError:
        return False
    return True


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
                    log.warning("%s: a calibration interrupted while it was being published was rolled back "
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
    backup, every file the set added is removed."""
    try:
        entries = json.loads((stage / _JOURNAL).read_text("utf-8"))["files"]
    except FileNotFoundError:  # the journal was never written: no rename had begun
        return
    except (ValueError, KeyError, TypeError):  # cut short while written: no rename had begun
        entries = []
    for name, existed in reversed(entries):
        backup = stage / _BACKUPS / name
        if existed:
            if backup.exists():
                os.replace(backup, dest / name)
        elif not (stage / name).exists():  # it was renamed into place: the set added it
            with contextlib.suppress(FileNotFoundError):
                (dest / name).unlink()
    (stage / _JOURNAL).unlink()


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
        """The destination of a path :meth:`path` returned (for records that name the published files)."""
        staged = Path(staged)
        dest = _STAGES.get(staged.parent)
        return dest / staged.name if dest is not None else staged

    # ---- commit / abort
    def _names(self, stage: Path) -> list[str]:
        names = sorted(e.name for e in os.scandir(stage) if e.is_file(follow_symlinks=False)
                       and not _TEMP_RE.match(e.name) and e.name != _JOURNAL)
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
        current = None
        try:
            plans = []
            for stage in self._order():
                dest = _STAGES[stage]
                names = self._names(stage)
                entries = []
                for name in names:
                    current = dest / name
                    _fsync_path(stage / name)
                    existed = _backup(dest / name, stage / _BACKUPS / name)
                    entries.append([name, existed])
                plans.append((stage, dest, names, entries))
            for stage, dest, names, entries in plans:
                current = dest / names[0] if names else dest
                self._committed.append((stage, dest))
                with open(stage / _JOURNAL, "w", encoding="utf-8") as fh:
                    json.dump({"pid": os.getpid(), "files": entries}, fh)
                    fh.flush()
                    os.fsync(fh.fileno())
                for name in names:
                    current = dest / name
                    os.replace(stage / name, dest / name)
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


def load_model_file(path: str | os.PathLike, kind: str, *,
                    max_version: int = MODEL_FORMAT_VERSION) -> tuple[dict, dict[str, np.ndarray]]:
    """Read a model archive written by :func:`save_model_file`, checking format, kind and version."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file; check the path of the {kind} model")
    fix = f"re-create the {kind} file with radiomap"
    _refuse_bare_npy(path, kind)
    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):  # a .npy array under another name (the check above)
            _refuse_bare_npy(path, kind, bare=True)
        with loaded as data:
            arrays = {name: data[name] for name in data.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, KeyError, zlib.error, NotImplementedError,
            RuntimeError, struct.error, UnicodeDecodeError, OverflowError, tokenize.TokenError, SyntaxError,
            MemoryError) as exc:
        # everything a corrupt, truncated or foreign .npz raises while its members are decompressed (a
        # mangled .npy header fails to tokenize, or claims an array too large to allocate); an object array
        # (pickled Python objects, refused by allow_pickle=False) is named as such
        if isinstance(exc, ValueError):
            check_real_arrays(path, {k: v for k, v in _npz_header_dtypes(path).items() if k != "meta"}, fix)
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


_NPY_MAGIC = b"\x93NUMPY"


def _refuse_bare_npy(path: Path, kind: str, *, bare: bool = False) -> None:
    """:class:`CalibrationFileError` when ``path`` is a single ``.npy`` array (its magic bytes, or ``bare``) where a
    model archive (``.npz``) is needed: np.load would return the array itself, not an archive."""
    if not bare:
        try:
            with open(path, "rb") as fh:
                bare = fh.read(len(_NPY_MAGIC)) == _NPY_MAGIC
        except OSError:
            return  # np.load reports it
    if bare:
        hint = " (a V array is read from a .npy file by reconstruct/correct --vignetting and compare --vignetting-lut)" \
            if kind == "vignetting" else ""
        raise CalibrationFileError(f"{path}: a bare .npy array, not a radiomap {kind} model file; pass the {kind} "
                                   f".npz that radiomap wrote{hint}")


# Model arrays hold real numbers: bool, signed and unsigned integers, floats. Anything else (complex, whose
# imaginary part a cast would drop; pickled objects; text; structured records; dates) is refused, here only.
_REAL_KINDS = "biuf"
_KIND_NAMES = {"c": "complex", "O": "pickled Python-object", "U": "text", "S": "byte-string", "V": "structured",
               "M": "date-time", "m": "time-delta"}


def check_real_arrays(path: str | os.PathLike, dtypes: Mapping[str | None, np.dtype], fix: str) -> None:
    """Raise :class:`CalibrationFileError` naming ``path`` (and the array) if a dtype is not real numeric.

    ``dtypes`` maps array names (None for a file holding one array) to their dtypes; ``fix`` ends the message.
    Every model loader goes through here: :func:`load_model_file`, :func:`load_array_file` (``.npy``)."""
    for name, dtype in dtypes.items():
        dtype = np.dtype(dtype)
        if dtype.kind in _REAL_KINDS and dtype.fields is None:
            continue
        what = f"array {name!r} holds" if name is not None else "holds"
        kind = "structured" if dtype.fields is not None else _KIND_NAMES.get(dtype.kind, "non-numeric")
        raise CalibrationFileError(f"{path}: {what} {kind} values ({dtype}) where real numbers (bool, integer or "
                                   f"float) are needed; {fix}")


def _npy_header_dtype(fh) -> np.dtype | None:
    """The dtype in a ``.npy`` header (without reading the data); None if the header cannot be parsed."""
    fmt = np.lib.format
    try:
        major, _minor = fmt.read_magic(fh)
        header = fmt.read_array_header_1_0 if major == 1 else fmt.read_array_header_2_0
        return np.dtype(header(fh)[2])
    except Exception:  # noqa: BLE001 - best effort: the caller falls back to its generic message
        return None


def _npz_header_dtypes(path: Path) -> dict[str, np.dtype]:
    """Member name -> dtype of the arrays of an ``.npz`` whose headers can be read (corrupt members skipped)."""
    out: dict[str, np.dtype] = {}
    try:
        with zipfile.ZipFile(path) as archive:
            for member in archive.namelist():
                with archive.open(member) as fh:
                    dtype = _npy_header_dtype(fh)
                if dtype is not None:
                    out[member.removesuffix(".npy")] = dtype
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, zlib.error, NotImplementedError, RuntimeError):
        pass
    return out


def load_array_file(path: str | os.PathLike, *, fix: str) -> np.ndarray:
    """Read a single-array ``.npy`` file (no pickle) holding real numbers; :class:`CalibrationFileError` naming
    the file and ending with ``fix`` otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CalibrationFileError(f"{path}: no such file; {fix}")
    try:
        array = np.load(path, allow_pickle=False)
    except ValueError as exc:
        try:
            with open(path, "rb") as fh:
                dtype = _npy_header_dtype(fh)
        except OSError:
            dtype = None
        if dtype is not None:
            check_real_arrays(path, {None: dtype}, fix)
        raise CalibrationFileError(f"{path}: not a NumPy .npy array or corrupt ({type(exc).__name__}); {fix}") from None
    except (OSError, EOFError, zipfile.BadZipFile, zlib.error, struct.error, UnicodeDecodeError, OverflowError,
            tokenize.TokenError, SyntaxError, MemoryError) as exc:
        raise CalibrationFileError(f"{path}: not a NumPy .npy array or corrupt ({type(exc).__name__}); {fix}") from None
    if not isinstance(array, np.ndarray):  # an .npz archive under a .npy name
        array.close()
        raise CalibrationFileError(f"{path}: an .npz archive of several arrays, not one .npy array; {fix}")
    check_real_arrays(path, {None: array.dtype}, fix)
    return array


# --------------------------------------------------------------------------------------------------
# images
# --------------------------------------------------------------------------------------------------
def _cv2():
    import cv2

    return cv2


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_MAX_PIXELS = 100_000_000
# deflate cannot compress better than ~1032:1, so a PNG much smaller than raw/1100 is lying about its size
_MAX_DEFLATE_RATIO = 1100


def png_defect(raw: np.ndarray | bytes) -> str | None:
    """Why a PNG cannot hold what its header claims (None when it can, or when the data is no PNG).

    Checked before decoding: a corrupt IHDR size or chunk length makes the decoder allocate and scan
    gigabytes for seconds on a file of a few bytes."""
    head = bytes(raw[:33])
    if not head.startswith(_PNG_SIGNATURE) or len(head) < 33 or head[12:16] != b"IHDR":
        return None
    size = len(raw)
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    bit_depth = max(head[24], 1)
    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(head[25], 4)
    raw_bytes = width * height * channels * bit_depth / 8
    if width == 0 or height == 0 or width * height > _MAX_PIXELS or raw_bytes > size * _MAX_DEFLATE_RATIO:
        return (f"the PNG header claims {width}x{height} pixels, which this {size}-byte file cannot hold "
                "(corrupt or truncated)")
    pos = 8
    data = raw if isinstance(raw, bytes) else raw.tobytes()
    while pos + 8 <= size:
        length = int.from_bytes(data[pos:pos + 4], "big")
        if length > 2**31 - 1 or pos + 12 + length > size:
            return (f"cannot decode the PNG: chunk {data[pos + 4:pos + 8]!r} at byte {pos} claims {length} bytes "
                    f"past the end of the {size}-byte file (corrupt or truncated)")
        if data[pos + 4:pos + 8] == b"IEND":
            break
        pos += 12 + length
    return None


# Huffman-coded JPEG needs at least one bit per 8x8 block: real encoders stay below ~600:1 on flat images
_MAX_JPEG_RATIO = 4096
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def jpeg_defect(raw: np.ndarray | bytes) -> str | None:
    """Why a JPEG cannot hold the image its start-of-frame claims (None when it can, or for no JPEG):
    the decoder would fill gigabytes of a made-up size for a file of a few bytes."""
    data = bytes(raw[:65536])
    size = len(raw)
    if not data.startswith(b"\xff\xd8"):
        return None
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None  # not a marker: let the decoder report the corruption
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0x01, *range(0xD0, 0xD8)):
            pos += 2
            continue
        if marker in (0xD9, 0xDA):  # end of image, start of scan: no frame header before it
            return None
        length = int.from_bytes(data[pos + 2:pos + 4], "big")
        if marker in _JPEG_SOF and pos + 10 <= len(data):
            height = int.from_bytes(data[pos + 5:pos + 7], "big")
            width = int.from_bytes(data[pos + 7:pos + 9], "big")
            components = max(data[pos + 9], 1)
            if width * height > _MAX_PIXELS or width * height * components > size * _MAX_JPEG_RATIO:
                return (f"the JPEG header claims {width}x{height} pixels, which this {size}-byte file cannot hold "
                        "(corrupt or truncated)")
            return None
        pos += 2 + length
    return None


def _read_encoded(path: Path, what: str) -> np.ndarray:
    """Decode an image file (OpenCV, BGR, any depth) or raise :class:`ImageError` naming it."""
    cv2 = _cv2()
    try:
        if not path.is_file():
            raise ImageError(f"{path}: no such {what}; check the path")
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise ImageError(f"{path}: cannot read the {what} ({exc.strerror or exc}); check the path and "
                         "its permissions") from None
    if data.size == 0:
        raise ImageError(f"{path}: empty file; replace it with a valid image")
    defect = png_defect(data) or jpeg_defect(data)
    if defect is not None:
        raise ImageError(f"{path}: {defect}; replace it")
    try:
        img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise ImageError(f"{path}: cannot decode the {what} (corrupt, truncated or not an image); replace it")
    return img


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read a colour image as RGB uint8 ``(H, W, 3)``; grayscale files give ``(H, W)``.

    16-bit images are scaled to 8 bits. Raises :class:`ImageError` naming the file when it is missing,
    unreadable or truncated.
    """
    cv2 = _cv2()
    path = Path(path)
    img = _read_encoded(path, "image")
    if img.dtype == np.uint16:
        img = (img >> 8).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise ImageError(f"{path}: unsupported pixel type {img.dtype}; convert it to 8-bit")
    if img.ndim == 3:
        if img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
        elif img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        elif img.shape[2] == 1:
            img = img[:, :, 0]
        else:
            raise ImageError(f"{path}: {img.shape[2]} channels; expected 1, 3 or 4")
    return np.ascontiguousarray(img)


def read_depth(path: str | os.PathLike, scale: float) -> np.ndarray:
    """Read a 16-bit depth image and return float32 metres (``raw / scale``; 0 stays 0 = invalid)."""
    path = Path(path)
    if scale <= 0 or not np.isfinite(scale):
        raise ValueError(f"depth scale must be a positive number, got {scale}")
    img = _read_encoded(path, "depth image")
    if img.ndim == 3:
        raise ImageError(f"{path}: depth image has {img.shape[2]} channels; expected a single-channel 16-bit PNG")
    if img.dtype not in (np.uint16, np.float32):
        raise ImageError(f"{path}: depth must be 16-bit (got {img.dtype}); save depth as 16-bit PNG")
    depth = img.astype(np.float32) / np.float32(scale)
    depth[~np.isfinite(depth)] = 0.0
    return depth


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write an RGB (or grayscale) uint8/uint16 image atomically; the format follows the suffix."""
    cv2 = _cv2()
    image = np.asarray(image)
    if image.ndim == 3 and image.shape[2] == 3:
        image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    path = Path(path)
    ok, buf = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise OutputError(f"cannot encode {path} as {path.suffix}; use .png")
    return atomic_write_bytes(path, buf.tobytes())


def write_depth(path: str | os.PathLike, depth_m: np.ndarray, scale: float) -> Path:
    """Write float32 metres as a 16-bit PNG (``round(depth * scale)``, clipped to the uint16 range)."""
    raw = np.clip(np.round(np.nan_to_num(depth_m) * scale), 0, 65535).astype(np.uint16)
    return write_image(path, raw)


def list_images(folder: str | os.PathLike) -> list[Path]:
    """Image files in a folder, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ImageError(f"{folder}: no such folder; check the path")
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file())
