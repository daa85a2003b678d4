"""The results folder of a run: meshes, trajectory, histograms, metrics, summary; all writes atomic.

Layout (``radiomap reconstruct ... -o OUT``)::

    OUT/RUNNING                      present while the run is in progress (or was interrupted / crashed)
    OUT/config.json                  the configuration the run started with (cli/_common.run_manifest)
    OUT/metrics.json                 "status": "running" -> "complete" | "interrupted" | "failed"
    OUT/trajectory.txt               estimated camera-to-world poses, TUM format
    OUT/mesh.ply, OUT/mesh.glb       the map's surface, colours in display units (response at k_ref)
    OUT/mesh_colours.npz             vertices, triangles and map-unit colours (irradiance), for evaluation
    OUT/histogram.json, .npz         the colour-disagreement histogram with statistics
    OUT/histogram.png                its plot (paper Fig. 9 style)
    OUT/summary.txt                  the summary table printed at the end
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from radiometry.errors import OutputError, RadiomapError
from radiometry.fileio import atomic_path, atomic_write_json, atomic_write_text, ensure_dir

log = logging.getLogger(__name__)

RUNNING_MARKER = "RUNNING"
MESH_FORMATS = ("ply", "glb", "obj")


class ResultsFolder:
    """A run's output folder; marked incomplete (``RUNNING``) until :meth:`complete` is called.

    An existing folder holding results (``metrics.json`` or ``RUNNING``) is refused unless ``force``."""

    def __init__(self, path: str | os.PathLike, *, force: bool = False) -> None:
        self.path = Path(path)
        if self.path.is_dir() and not force and any((self.path / n).exists() for n in ("metrics.json", RUNNING_MARKER)):
            raise OutputError(f"{self.path} already holds the results of a run; pass --force to overwrite them or "
                              "choose another output folder")
        ensure_dir(self.path)
        self.started = time.time()
        atomic_write_text(self.path / RUNNING_MARKER,
                          f"started {time.strftime('%Y-%m-%dT%H:%M:%S%z')} pid {os.getpid()}\n"
                          "this run has not finished (interrupted or crashed if no process runs it)\n")

    def file(self, name: str) -> Path:
        return self.path / name

    @property
    def complete_flag(self) -> bool:
        return not (self.path / RUNNING_MARKER).exists()

    def complete(self) -> None:
        """Remove the ``RUNNING`` marker: every result is in place."""
        try:
            (self.path / RUNNING_MARKER).unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            raise OutputError(f"cannot remove {self.path / RUNNING_MARKER}: {exc.strerror}") from None

    def write_json(self, name: str, obj) -> Path:
        return atomic_write_json(self.path / name, obj)

    def write_text(self, name: str, text: str) -> Path:
        return atomic_write_text(self.path / name, text)


def is_complete(folder: str | os.PathLike) -> bool:
    """True when a results folder exists and its run finished (no ``RUNNING`` marker)."""
    folder = Path(folder)
    return folder.is_dir() and (folder / "metrics.json").is_file() and not (folder / RUNNING_MARKER).exists()


def display_colours_uint8(colours: np.ndarray, to_display: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """Map-unit colours (N, 3) -> uint8 display colours through ``to_display``."""
    if len(colours) == 0:
        return np.zeros((0, 3), np.uint8)
    shown = np.asarray(to_display(np.asarray(colours, dtype=np.float32)), dtype=np.float32)
    return np.clip(np.rint(np.nan_to_num(shown)), 0, 255).astype(np.uint8)


def write_mesh(folder: Path, vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray,
               to_display: Callable[[np.ndarray], np.ndarray], *, normals: np.ndarray | None = None,
               formats: tuple[str, ...] = ("ply", "glb"), stem: str = "mesh") -> dict[str, Path]:
    """Write a vertex-coloured triangle mesh: ``stem.<fmt>`` for each format (display colours, via trimesh)
    and ``stem_colours.npz`` (vertices, triangles, map-unit colours, display colours).

    Returns ``{"mesh_<fmt>": path, "mesh_colours": path}``; an empty mesh writes only the ``.npz``."""
    import trimesh

    bad = [f for f in formats if f not in MESH_FORMATS]
    if bad:
        raise ValueError(f"mesh formats must be among {', '.join(MESH_FORMATS)}, got {bad}")
    folder = Path(folder)
    vertices = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    colours = np.asarray(colours, dtype=np.float32).reshape(-1, 3)
    if len(colours) != len(vertices):
        raise ValueError(f"colours must have one row per vertex ({len(vertices)}), got {len(colours)}")
    shown = display_colours_uint8(colours, to_display)
    out: dict[str, Path] = {}
    npz = folder / f"{stem}_colours.npz"
    with atomic_path(npz) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, vertices=vertices, triangles=triangles.astype(np.int32), colours=colours,
                                display=shown)
    out["mesh_colours"] = npz
    if len(vertices) == 0 or len(triangles) == 0:
        log.warning("the map has no surface to export (no voxel observed often enough); wrote only %s", npz)
        return out
    rgba = np.concatenate([shown, np.full((len(shown), 1), 255, np.uint8)], axis=1)
    kwargs = {}
    if normals is not None and len(normals) == len(vertices):
        kwargs["vertex_normals"] = np.asarray(normals, dtype=np.float32)
    mesh = trimesh.Trimesh(vertices=vertices, faces=triangles, vertex_colors=rgba, process=False, **kwargs)
    for fmt in formats:
        path = folder / f"{stem}.{fmt}"
        with atomic_path(path) as tmp:
            mesh.export(tmp, file_type=fmt)
        out[f"mesh_{fmt}"] = path
    return out


def read_mesh_colours(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Read ``mesh_colours.npz`` (vertices, triangles, colours in map units, display uint8)."""
    path = Path(path)
    if not path.is_file():
        raise RadiomapError(f"{path}: no such mesh file; run 'radiomap reconstruct' first")
    with np.load(path, allow_pickle=False) as data:
        return {k: data[k] for k in data.files}
