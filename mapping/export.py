"""The results folder of a run: meshes, trajectory, histograms, metrics, summary; all writes atomic.

Layout (``radiomap reconstruct ... -o OUT``)::

    OUT/LOCK                         present while a process writes the folder: its pid (FolderLock)
    OUT/RUNNING                      present while the run is in progress (or was interrupted / crashed)
    OUT/.tmp-radiomap-PID-*/         with --force over a complete run: the new run, staged until it is complete and
                                     published as one set (mapping.publication; the previous run stands till then)
    OUT/.radiomap-files.json         the files the run wrote (removed by the next --force run)
    OUT/config.json                  the configuration the run started with (cli/_common.run_manifest)
    OUT/metrics.json                 "status": "running" -> "complete" | "interrupted" | "failed"
    OUT/trajectory.txt               estimated camera-to-world poses, TUM format
    OUT/mesh.ply                     the map's surface, colours in display units (response at k_ref), sRGB-encoded
    OUT/mesh.glb, OUT/mesh.obj       with --formats ply,glb,obj: the same mesh; the GLB stores the colours linear
                                     (sRGB-decoded), as glTF defines COLOR_0 (docs/outputs.md: which file for what)
    OUT/mesh_colours.npz             with --formats ...,npz: vertices, triangles and map-unit colours, for evaluation
    OUT/mesh_colourmap.*, OUT/mesh_colourmap_colours.npz, OUT/colour_map.json
                                     with --colour-map: the colour-map optimised mesh (when the held-out check kept
                                     it) and the stage's report (mapping.colour_map.write_colour_map)
    OUT/histogram.json, .npz         the colour-disagreement histogram with statistics
    OUT/histogram.png                its plot (paper Fig. 9 style)
    OUT/summary.txt                  the summary table printed at the end
"""

from __future__ import annotations

import atexit
import contextlib
import errno
import json
import logging
import math
import os
import shutil
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mapping.validation import DEFAULT_MESH_FORMATS, MESH_FORMATS, check_mesh_formats  # noqa: F401 - re-exported
from radiometry.errors import OutputError, RadiomapError
from radiometry.response import srgb_to_linear
from radiometry.fileio import (TEMP_TAG, atomic_path, atomic_write_bytes, atomic_write_json, atomic_write_text,
                               ensure_dir, pid_alive, remove_strays)

log = logging.getLogger(__name__)

RUNNING_MARKER = "RUNNING"
LOCK_NAME = "LOCK"
MANIFEST = ".radiomap-files.json"
#: The files a run writes (the layout above, the surfel backend's, exposure compensation's, a comparison's per
#: method). ``--force`` removes these and the files listed in the previous run's MANIFEST before a new run starts;
#: any other file in the folder (the user's notes, say) is left alone.
RESULT_NAMES = frozenset({
    RUNNING_MARKER, "config.json", "metrics.json", "trajectory.txt", "frames.csv", "summary.txt", "histogram.json",
    "groundtruth_tum.txt", "histogram.npz", "histogram.png", "mesh.ply", "mesh.glb", "mesh.obj", "mesh_colours.npz",
    "surfels.ply", "surfels_mesh.ply", "exposures.txt", "exposures.json", "compare_method.json", "colour_map.json",
    "mesh_colourmap.ply", "mesh_colourmap.glb", "mesh_colourmap.obj", "mesh_colourmap_colours.npz", "holdout.csv", MANIFEST})

_HELD: dict[str, "FolderLock"] = {}   # resolved folder -> the lock this process holds on it


def _process_start(pid: int) -> str | None:
    """When the process started (clock ticks since boot, Linux), to tell a reused pid from the lock's owner."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        return None


class FolderLock:
    """One radiomap run at a time writes a folder: ``FOLDER/LOCK`` holds the owner's pid, created atomically
    (a hard link of the written record, which fails like ``O_EXCL`` when LOCK exists) and removed when the run
    ends (:meth:`release`, or at exit).

    A second run gets a one-line :class:`OutputError` naming the folder and the owner's pid. A lock whose owner
    no longer runs (killed: SIGKILL, a crash, a power cut) is taken over with a warning. The same process may
    lock a folder again (a second run in one Python session)."""

    def __init__(self, folder: str | os.PathLike, *, what: str = "run") -> None:
        self.folder = ensure_dir(folder)
        self.path = self.folder / LOCK_NAME
        self.key = os.path.realpath(self.folder)
        previous = _HELD.pop(self.key, None)
        if previous is not None:          # this process locked it before (and did not release): it stays ours
            previous.released = True
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
        record = {"pid": os.getpid(), "start": _process_start(os.getpid()), "host": socket.gethostname(),
                  "what": what, "started": time.strftime("%Y-%m-%dT%H:%M:%S%z")}
        # the record is written to a temporary first and hard-linked to LOCK: like O_EXCL, the link fails if LOCK
        # exists, and a LOCK that exists is never empty or half written
        draft = self.path.with_name(f".{LOCK_NAME}{TEMP_TAG}{os.getpid()}-draft")
        try:
            draft.write_text(json.dumps(record))
            for _attempt in range(20):
                try:
                    _create_exclusive(self.path, draft)
                except FileExistsError:
                    self._take_over_if_stale()
                    continue
                break
            else:
                raise OutputError(f"cannot lock {self.folder}: {self.path} keeps changing; remove it if no radiomap "
                                  "run writes the folder")
        except OSError as exc:
            raise OutputError(f"cannot lock {self.folder} ({exc.filename}: {exc.strerror}); choose a writable "
                              "output folder") from None
        finally:
            with contextlib.suppress(OSError):
                draft.unlink()
        self.released = False
        _HELD[self.key] = self

    def _owner(self) -> dict:
        try:
            owner = json.loads(self.path.read_text())
            return owner if isinstance(owner, dict) else {}
        except FileNotFoundError:
            return {"gone": True}
        except (OSError, ValueError):  # written half by a process killed in between: no live owner wrote it
            return {}

    def _take_over_if_stale(self) -> None:
        """Remove the lock of an owner that no longer runs (the caller retries), or raise naming a live owner."""
        owner = self._owner()
        if owner.get("gone"):
            return
        pid = owner.get("pid")
        same_host = owner.get("host") in (None, socket.gethostname())
        if owner.get("pid") == os.getpid() and owner.get("start") == _process_start(os.getpid()):
            alive = False      # our own, left by a lock object of this process that was never released
        elif isinstance(pid, int) and same_host:
            alive = pid_alive(pid) and (owner.get("start") is None or owner.get("start") == _process_start(pid))
        else:
            alive = not same_host or not owner and self._young()
        if alive:
            where = "" if same_host else f" on {owner.get('host')}"
            raise OutputError(f"{self.folder} is in use by another radiomap {owner.get('what', 'run')} (pid {pid}"
                              f"{where}, started {owner.get('started', '?')}); wait for it to finish or choose "
                              f"another output folder (remove {self.path} if that process is gone)")
        stale = self.path.with_name(f".{LOCK_NAME}{TEMP_TAG}{os.getpid()}-stale")
        try:
            os.rename(self.path, stale)       # atomic: of two runs taking over, one wins, the other retries
        except FileNotFoundError:
            return
        try:
            moved = json.loads(stale.read_text())
        except (OSError, ValueError):
            moved = {}
        if isinstance(moved, dict) and moved.get("pid") not in (pid, None):  # a run took it over meanwhile: undo
            with contextlib.suppress(OSError):
                os.link(stale, self.path)
            with contextlib.suppress(OSError):
                stale.unlink()
            return
        if owner.get("pid") != os.getpid():
            log.warning("%s: taking over the lock of radiomap pid %s (started %s), which no longer runs", self.folder,
                        pid if pid is not None else "?", owner.get("started", "?"))
        with contextlib.suppress(OSError):
            stale.unlink()

    def _young(self) -> bool:
        """An unreadable lock file written in the last seconds may be a live owner's, still being written."""
        try:
            return time.time() - self.path.stat().st_mtime < 5
        except OSError:
            return False

    def release(self) -> None:
        """Remove the lock (once; a lock this process took again since is left alone)."""
        if self.released:
            return
        self.released = True
        if _HELD.get(self.key) is self:
            del _HELD[self.key]
            with contextlib.suppress(OSError):
                self.path.unlink()

    def __enter__(self) -> "FolderLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


def _create_exclusive(path: Path, draft: Path) -> None:
    """``path`` with the content of ``draft``, or FileExistsError: a hard link; where the file system has none,
    ``O_EXCL`` and a write (an empty LOCK read meanwhile counts as a live owner's for a few seconds)."""
    try:
        os.link(draft, path)
    except OSError as exc:
        if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.EXDEV):
            raise
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        with os.fdopen(fd, "w") as fh:
            fh.write(draft.read_text())


@atexit.register
def _release_all() -> None:
    for lock in list(_HELD.values()):
        lock.release()


class ResultsFolder:
    """A run's output folder: locked while the run writes it (:class:`FolderLock`), marked incomplete
    (``RUNNING``, and ``"status": "running"`` in ``metrics.json``) until :meth:`complete` is called.

    An existing folder holding results (``metrics.json``, ``RUNNING`` or a MANIFEST) is refused unless ``force``, and so
    is one holding files named like results without any of those (the user's own: nothing is removed); with
    ``force`` the previous run's files (:data:`RESULT_NAMES` and those its ``.radiomap-files.json`` lists) are
    removed before the new run starts, so that no file of the previous run (a TSDF mesh beside new surfels, an
    old ``metrics.json`` saying "complete") outlives it; other files in the folder are left alone. When the run
    ends (:meth:`complete` or :meth:`release`) ``.radiomap-files.json`` lists every file it wrote.

    A run that writes results folders inside its own (a comparison: one per method) makes them with
    :meth:`subfolder`; they are listed under ``"folders"``, and ``force`` cleans each listed (or known,
    :attr:`result_folders`) subfolder by the same rule and removes it when nothing else is left in it.

    Subclasses set the class attributes below for another kind of run: a comparison
    (:class:`mapping.compare.ComparisonFolder`), the demo (:class:`mapping.demo.DemoFolder`: an empty or new folder
    only, its own folders removed whole by ``force``) and a simulated sequence
    (:class:`mapping.simulation.sequences.SequenceFolder`: ``force`` removes only a simulation's files)."""

    #: the kind of run (the lock's record and the RUNNING marker)
    what = "run"
    #: a folder holding one of these holds results (of this kind of run or, MANIFEST, of another): refused
    #: without ``force``, so that no run removes another kind's listed files unasked
    markers: tuple[str, ...] = ("metrics.json", RUNNING_MARKER, MANIFEST)
    #: the refusal without ``force``, after the folder's name
    refusal = "already holds the results of a run; pass --force to overwrite them or choose another output folder"
    #: the refusal without ``force`` of a folder holding anything else (but the lock), after the folder's name
    #: (None: other files are no obstacle)
    refusal_other: str | None = None
    #: the files such a run writes, names or glob patterns (removed with ``force``, with those the previous run's
    #: MANIFEST lists)
    result_names: frozenset[str] = RESULT_NAMES
    #: the results folders such a run writes inside its own (cleaned with ``force``, as MANIFEST-listed ones)
    result_folders: frozenset[str] = frozenset()
    #: the folders such a run writes whole (removed with everything in them by ``force``)
    owned_folders: frozenset[str] = frozenset()
    #: ``force`` removes the previous run's files even where no marker shows one (False: such a folder is written
    #: into as it is, with a warning, so that files of another kind that happen to share a name are kept)
    clean_unmarked: bool = True
    #: list the files the run wrote in MANIFEST when it ends (False: a fixed layout, :attr:`result_names`)
    listing: bool = True
    #: written with ``"status": "running"`` when the run starts (None: no status file)
    status_file: str | None = "metrics.json"

    def __init__(self, path: str | os.PathLike, *, force: bool = False) -> None:
        self.path = Path(path)
        if self.path.exists() and not self.path.is_dir():
            raise OutputError(f"output folder {self.path} is an existing file; choose a folder name")
        self.folders: list[str] = []   # results folders made inside by :meth:`subfolder`
        self.lock = FolderLock(self.path, what=self.what)
        try:
            marked = any((self.path / n).exists() for n in self.markers)
            if not force and marked and (self.path / RUNNING_MARKER).exists():   # no result: an unfinished run
                raise OutputError(f"{self.path} holds an unfinished {self.what} (interrupted or failed: {RUNNING_MARKER} "
                                  "is there, no complete result); pass --force to replace it or choose another output "
                                  "folder")
            if not force and marked:
                raise OutputError(f"{self.path} {self.refusal}")
            if not force and self.refusal_other is not None and self._holds_anything():
                raise OutputError(f"{self.path} {self.refusal_other}")
            foreign = [] if force or marked or not self.clean_unmarked else self._unmarked_results()
            if foreign:
                raise OutputError(f"{self.path} holds {foreign[0]}, which no {self.what} of radiomap wrote there (no "
                                  f"{self.markers[0]}); move it away, choose another output folder, or pass --force to "
                                  "overwrite it")
            remove_strays(self.path)
            if marked or self.clean_unmarked:
                self._remove_previous_run()
            elif self._holds_anything():
                log.warning("%s is not empty and holds no earlier %s; writing into it anyway (--force)", self.path,
                            self.what)
            self.started = time.time()
            self._before = self._inodes()
            self._mark_running()
        except BaseException:
            self.lock.release()
            raise

    def _mark_running(self) -> None:
        """Write the ``RUNNING`` marker and the status file saying "running" (a subclass that keeps the previous
        result until it publishes the new one skips them while that result stands)."""
        atomic_write_text(self.path / RUNNING_MARKER,
                          f"{self.what} started {time.strftime('%Y-%m-%dT%H:%M:%S%z')} pid {os.getpid()}\n"
                          f"this {self.what} has not finished (interrupted or crashed if no process runs it)\n")
        if self.status_file is not None:
            atomic_write_json(self.path / self.status_file, {"status": "running", "pid": os.getpid(), "started":
                                                             time.strftime("%Y-%m-%dT%H:%M:%S%z")})

    def _holds_anything(self) -> bool:
        return any(entry.name != LOCK_NAME for entry in os.scandir(self.path))

    def _unmarked_results(self) -> list[str]:
        """The entries of the folder named like this kind's results (that ``force`` would remove or replace), sorted;
        in a folder no run marked they are the user's own."""
        names = {n for n in self.result_names if not _is_pattern(n) and (self.path / n).is_file()}
        names |= {m.name for n in self.result_names if _is_pattern(n) for m in self.path.glob(n) if m.is_file()}
        names |= {n + "/" for n in self.result_folders | self.owned_folders if (self.path / n).is_dir()}
        return sorted(names)

    def _remove_previous_run(self) -> None:
        removed = _remove_results(self.path, self.result_names, self.result_folders, self.owned_folders,
                                  listed=self.listing)
        if removed:
            log.info("%s: removed the previous run's %s", self.path, ", ".join(removed))

    def subfolder(self, name: str) -> "ResultsFolder":
        """A results folder ``name`` inside this one for a part of the run (``force``: it is this run's); listed
        in this folder's MANIFEST so that the next ``force`` run removes it."""
        if not _own_name(name):
            raise ValueError(f"a results subfolder must be a plain folder name, got {name!r}")
        if name not in self.folders:
            self.folders.append(name)
        return ResultsFolder(self.path / name, force=True)

    def _inodes(self) -> dict[str, tuple[int, int]]:
        out = {}
        for entry in os.scandir(self.path):
            if entry.is_file(follow_symlinks=False):
                st = entry.stat(follow_symlinks=False)
                out[entry.name] = (st.st_ino, st.st_mtime_ns)
        return out

    def _write_manifest(self) -> None:
        """``.radiomap-files.json``: the files this run wrote (every write is atomic: a new inode)."""
        try:
            written = sorted(name for name, ident in self._inodes().items()
                             if self._before.get(name) != ident and name not in (LOCK_NAME, MANIFEST))
            record = {"files": written}
            if self.folders:
                record["folders"] = sorted(self.folders)
            atomic_write_json(self.path / MANIFEST, record)
        except (OSError, OutputError) as exc:
            log.warning("could not list the files of the run in %s: %s", self.path / MANIFEST, exc)

    def file(self, name: str) -> Path:
        return self.path / name

    def complete(self) -> None:
        """Remove the ``RUNNING`` marker: every result is in place."""
        if self.listing:
            self._write_manifest()
        try:
            (self.path / RUNNING_MARKER).unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise OutputError(f"cannot remove {self.path / RUNNING_MARKER}: {exc.strerror}") from None

    def release(self) -> None:
        """The run is over (complete or not): list its files and unlock the folder."""
        if self.listing and not self.lock.released:
            self._write_manifest()
        self.lock.release()

    def __enter__(self) -> "ResultsFolder":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def write_json(self, name: str, obj) -> Path:
        return atomic_write_json(self.path / name, obj)

    def write_text(self, name: str, text: str) -> Path:
        return atomic_write_text(self.path / name, text)


def _own_name(name) -> bool:
    """A name a MANIFEST may list: a plain entry of the folder itself (no path, not the lock)."""
    return isinstance(name, str) and name not in ("", ".", "..", LOCK_NAME) and name == Path(name).name


def _manifest_entries(folder: Path) -> tuple[set[str], set[str]]:
    """The files and the results folders the MANIFEST of ``folder`` lists (none if it is missing or unreadable)."""
    try:
        listed = json.loads((folder / MANIFEST).read_text())
        return ({n for n in listed.get("files", []) if _own_name(n)},
                {n for n in listed.get("folders", []) if _own_name(n)})
    except (OSError, ValueError, AttributeError, TypeError):
        return set(), set()


def _remove_results(folder: Path, names, folders, owned=(), *, listed: bool = True) -> list[str]:
    """Remove a previous run's results from ``folder``: the folders ``owned`` with everything in them, the files
    ``names`` (or glob patterns) and, if ``listed``, those its MANIFEST lists, and every results folder
    (``folders`` and the MANIFEST's) cleaned by the same rule under its own lock (a live run in it is refused),
    then removed unless files not its own remain. The names removed (folders with a ``/``)."""
    files, subs = _manifest_entries(folder) if listed else (set(), set())
    removed = []
    for name in sorted(owned):
        sub = folder / name
        if not sub.is_dir() or sub.is_symlink():
            continue
        try:
            shutil.rmtree(sub)
        except OSError as exc:
            raise OutputError(f"cannot remove {sub} of the previous run ({exc.strerror or exc}); remove it by hand "
                              "or choose another output folder") from None
        removed.append(name + "/")
    files |= {match.name for pattern in names if _is_pattern(pattern) for match in folder.glob(pattern)}
    names = {name for name in names if not _is_pattern(name)}
    for name in sorted(set(folders) | subs):
        sub = folder / name
        if not sub.is_dir() or sub.is_symlink():
            continue
        with FolderLock(sub):
            gone = bool(remove_strays(sub)) | bool(_remove_results(sub, RESULT_NAMES, ()))
        try:
            sub.rmdir()
        except OSError:  # the user's files are left, and the folder with them
            if gone:
                log.info("%s: kept the folder of the previous run for the files not its own", sub)
        else:
            gone = True
        if gone:
            removed.append(name + "/")
    for name in sorted(set(names) | files):
        try:
            (folder / name).unlink()
        except FileNotFoundError:
            continue
        except IsADirectoryError:
            log.warning("%s: %s is a folder, not a result file of the previous run; left alone", folder, name)
            continue
        except OSError as exc:
            raise OutputError(f"cannot remove {folder / name} of the previous run ({exc.strerror}); remove "
                              "it by hand or choose another output folder") from None
        removed.append(name)
    return removed


def _is_pattern(name: str) -> bool:
    return any(ch in name for ch in "*?[")


def is_complete(folder: str | os.PathLike) -> bool:
    """True when a results folder exists and its run finished (no ``RUNNING`` marker, ``metrics.json`` says so)."""
    folder = Path(folder)
    if not (folder.is_dir() and (folder / "metrics.json").is_file() and not (folder / RUNNING_MARKER).exists()):
        return False
    try:
        return json.loads((folder / "metrics.json").read_text()).get("status") == "complete"
    except (OSError, ValueError, AttributeError):
        return False


def display_colours_uint8(colours: np.ndarray, to_display: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Map-unit colours (N, 3) -> uint8 display colours through ``to_display``."""
    if len(colours) == 0:
        return np.zeros((0, 3), np.uint8)
    shown = np.asarray(to_display(np.asarray(colours, dtype=np.float32)), dtype=np.float32)
    return np.clip(np.rint(np.nan_to_num(shown)), 0, 255).astype(np.uint8)


def write_mesh(folder: Path, vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray,
               to_display: Callable[[np.ndarray], np.ndarray], *, normals: np.ndarray | None = None,
               formats: tuple[str, ...] = DEFAULT_MESH_FORMATS, stem: str = "mesh") -> dict[str, Path]:
    """Write a vertex-coloured triangle mesh: ``stem.<fmt>`` for each format (display colours; PLY and OBJ via
    trimesh, GLB by :func:`glb_bytes` with linear COLOR_0), and with ``"npz"`` among the formats ``stem_colours.npz``
    (vertices, triangles, map-unit colours, display colours: for evaluation; nothing in radiomap reads it back).

    Returns ``{"mesh_<fmt>": path, "mesh_colours": path}``; an empty mesh writes only the ``.npz`` (when asked)."""
    import trimesh

    formats = check_mesh_formats(formats)
    folder = Path(folder)
    vertices = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    colours = np.asarray(colours, dtype=np.float32).reshape(-1, 3)
    if len(colours) != len(vertices):
        raise ValueError(f"colours must have one row per vertex ({len(vertices)}), got {len(colours)}")
    shown = display_colours_uint8(colours, to_display)
    out: dict[str, Path] = {}
    if "npz" in formats:
        npz = folder / f"{stem}_colours.npz"
        with atomic_path(npz) as tmp:
            with open(tmp, "wb") as fh:
                np.savez_compressed(fh, vertices=vertices, triangles=triangles.astype(np.int32), colours=colours,
                                    display=shown)
        out["mesh_colours"] = npz
    if len(vertices) == 0 or len(triangles) == 0:
        log.warning("the map has no surface to export (no voxel observed often enough); %s",
                    f"wrote only {out['mesh_colours']}" if out else "no mesh written")
        return out
    rgba = np.concatenate([shown, np.full((len(shown), 1), 255, np.uint8)], axis=1)
    kwargs = {}
    if normals is not None and len(normals) == len(vertices):
        kwargs["vertex_normals"] = np.asarray(normals, dtype=np.float32)
    mesh = trimesh.Trimesh(vertices=vertices, faces=triangles, vertex_colors=rgba, process=False, **kwargs)
    for fmt in (f for f in formats if f != "npz"):
        path = folder / f"{stem}.{fmt}"
        if fmt == "glb":  # trimesh would store the display (sRGB) bytes in COLOR_0, which glTF defines as linear
            atomic_write_bytes(path, glb_bytes(vertices, triangles, shown, normals=kwargs.get("vertex_normals")))
        else:
            with atomic_path(path) as tmp:
                mesh.export(tmp, file_type=fmt)
        out[f"mesh_{fmt}"] = path
    return out


_GLB_MAGIC, _GLB_JSON, _GLB_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
_FLOAT, _UINT32, _ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 5126, 5125, 34962, 34963


def glb_bytes(vertices: np.ndarray, triangles: np.ndarray, display: np.ndarray, *,
              normals: np.ndarray | None = None) -> bytes:
    """A binary glTF 2.0 file of a vertex-coloured triangle mesh whose colours follow the specification.

    glTF defines ``COLOR_0`` as linear: the display colours (uint8, sRGB-encoded, as in the PLY) are decoded with
    the sRGB transfer function and stored as float32, so a viewer that encodes its output as sRGB shows the
    PLY's colours. The material is unlit (``KHR_materials_unlit``, used but not required: the map's colours are
    already what the scene looks like), falling back to a white, non-metallic, fully rough surface."""
    positions = np.ascontiguousarray(vertices, dtype="<f4").reshape(-1, 3)
    indices = np.ascontiguousarray(triangles, dtype="<u4").reshape(-1)
    colours = np.ascontiguousarray(srgb_to_linear(np.asarray(display, dtype=np.float64) / 255.0), dtype="<f4")
    attributes = [("POSITION", positions)]
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        good = np.isfinite(length) & (length > 1e-12)
        unit = np.where(good, n / np.where(good, length, 1.0), np.array([0.0, 0.0, 1.0]))  # glTF: unit length
        attributes.append(("NORMAL", np.ascontiguousarray(unit, dtype="<f4")))
    attributes.append(("COLOR_0", colours.reshape(-1, 3)))
    blobs, views, accessors = [], [], []
    offset = 0
    for data, target in [(indices, _ELEMENT_ARRAY_BUFFER)] + [(a, _ARRAY_BUFFER) for _, a in attributes]:
        raw = data.tobytes()
        views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(raw), "target": target})
        raw += b"\0" * (-len(raw) % 4)
        blobs.append(raw)
        offset += len(raw)
    accessors.append({"bufferView": 0, "componentType": _UINT32, "count": int(indices.size), "type": "SCALAR"})
    for k, (name, data) in enumerate(attributes, start=1):
        accessor = {"bufferView": k, "componentType": _FLOAT, "count": int(len(data)), "type": "VEC3"}
        if name == "POSITION":  # required for POSITION
            accessor.update(min=[float(v) for v in data.min(axis=0)], max=[float(v) for v in data.max(axis=0)])
        accessors.append(accessor)
    doc = {
        "asset": {"version": "2.0", "generator": "radiomap"},
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "map"}],
        "meshes": [{"name": "map", "primitives": [{
            "attributes": {name: k for k, (name, _) in enumerate(attributes, start=1)},
            "indices": 0, "material": 0, "mode": 4}]}],
        "materials": [{"name": "vertex colours (linear COLOR_0), unlit",
                       "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0], "metallicFactor": 0.0,
                                                "roughnessFactor": 1.0},
                       "extensions": {"KHR_materials_unlit": {}}}],
        "buffers": [{"byteLength": offset}], "bufferViews": views, "accessors": accessors,
    }
    text = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    binary = b"".join(blobs)
    total = 12 + 8 + len(text) + 8 + len(binary)
    return b"".join([struct.pack("<III", _GLB_MAGIC, 2, total), struct.pack("<II", len(text), _GLB_JSON), text,
                     struct.pack("<II", len(binary), _GLB_BIN), binary])


def read_mesh_colours(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read ``mesh_colours.npz`` (vertices, triangles, colours in map units, display uint8)."""
    path = Path(path)
    if not path.is_file():
        raise RadiomapError(f"{path}: no such mesh file; run 'radiomap reconstruct' first")
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


# ---------------------------------------------------------------- config.json values
def frame_range_text(frames: slice | None) -> str | None:
    """``slice`` -> ``"A:B:S"`` (the ``--frames`` syntax, :class:`FrameRange` reads it back); None -> None."""
    if frames is None or frames == slice(None):
        return None
    text = f"{'' if frames.start is None else frames.start}:{'' if frames.stop is None else frames.stop}"
    return text if frames.step is None else f"{text}:{frames.step}"


def plain_value(value: Any) -> Any:
    """A parameter value as plain JSON that the option reads back: Paths absolute strings, slices ``A:B:S``,
    tuples lists; anything else that is not JSON-plain is a TypeError (never a Python repr)."""
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            raise TypeError(f"{value!r} is not a finite number; config.json holds plain JSON")
        return value
    if isinstance(value, os.PathLike):
        return os.path.abspath(os.fspath(value))
    if isinstance(value, slice):
        return frame_range_text(value)
    if isinstance(value, (list, tuple)):
        return [plain_value(v) for v in value]
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        return plain_value(value.item())
    raise TypeError(f"cannot record a {type(value).__name__} ({value!r}) in config.json as plain JSON")
