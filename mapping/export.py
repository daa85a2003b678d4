"""The results folder of a run: meshes, trajectory, histograms, metrics, summary; all writes atomic.

Layout (``radiomap reconstruct ... -o OUT``)::

    OUT/RUNNING                      present while the run is in progress (or was interrupted / crashed)
    OUT/config.json                  the configuration the run started with (cli/_common.run_manifest)
    OUT/metrics.json                 "status": "running" -> "complete" | "interrupted" | "failed"
    OUT/trajectory.txt               estimated camera-to-world poses, TUM format
    OUT/mesh.ply, OUT/mesh.glb       the map's surface, colours in display units (response at k_ref); the GLB
                                     stores them linear (sRGB-decoded), as glTF defines COLOR_0
    OUT/mesh_colours.npz             vertices, triangles and map-unit colours (irradiance), for evaluation
    OUT/histogram.json, .npz         the colour-disagreement histogram with statistics
    OUT/histogram.png                its plot (paper Fig. 9 style)
    OUT/summary.txt                  the summary table printed at the end
"""

from __future__ import annotations

import json
import logging
import os
import struct
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from radiometry.errors import OutputError, RadiomapError
from radiometry.fileio import atomic_path, atomic_write_bytes, atomic_write_json, atomic_write_text, ensure_dir

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
    """Write a vertex-coloured triangle mesh: ``stem.<fmt>`` for each format (display colours; PLY and OBJ via
    trimesh, GLB by :func:`glb_bytes` with linear COLOR_0)
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
        if fmt == "glb":  # trimesh would store the display (sRGB) bytes in COLOR_0, which glTF defines as linear
            atomic_write_bytes(path, glb_bytes(vertices, triangles, shown, normals=kwargs.get("vertex_normals")))
        else:
            with atomic_path(path) as tmp:
                mesh.export(tmp, file_type=fmt)
        out[f"mesh_{fmt}"] = path
    return out


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear light (IEC 61966-2-1), float64."""
    v = np.asarray(encoded, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


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
    colours = np.ascontiguousarray(srgb_decode(np.asarray(display, dtype=np.float64) / 255.0), dtype="<f4")
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
