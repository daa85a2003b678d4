"""Surfel storage (:class:`SurfelMap`, struct-of-arrays with amortised growth) and the surfel PLY writer, for
:mod:`mapping.fusion.surfel`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from radiometry.fileio import atomic_path


class SurfelMap:
    """Struct-of-arrays surfel storage with amortised growth and compaction.

    Arrays have ``capacity`` rows; rows ``0 .. size-1`` are in use, some of them dead (confidence -1) until
    :meth:`compact` removes them. ``created``/``updated`` are integration counters (0 for the first frame
    integrated), not frame indices; :class:`SurfelBackend` maps them back to frame indices.
    """

    FIELDS: tuple[tuple[str, tuple[int, ...], type], ...] = (
        ("position", (3,), np.float32),
        ("normal", (3,), np.float32),
        ("radius", (), np.float32),
        ("confidence", (), np.float32),
        ("colour", (3,), np.float32),
        ("created", (), np.int32),
        ("updated", (), np.int32),
    )

    def __init__(self, capacity: int = 1 << 16) -> None:
        if int(capacity) < 1:
            raise ValueError(f"capacity must be a positive number of surfels, got {capacity}")
        self._size = 0
        self._dead = 0
        self._arrays: dict[str, np.ndarray] = {
            name: np.zeros((int(capacity),) + shape, dtype=dtype) for name, shape, dtype in self.FIELDS}

    # sizes ------------------------------------------------------------------------------------------
    @property
    def capacity(self) -> int:
        return int(self._arrays["radius"].shape[0])

    @property
    def size(self) -> int:
        """Rows in use, dead ones included."""
        return self._size

    @property
    def dead(self) -> int:
        return self._dead

    def __len__(self) -> int:
        """Live surfels."""
        return self._size - self._dead

    @property
    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self._arrays.values()))

    # raw arrays (full capacity) for the kernels ----------------------------------------------------------
    def array(self, name: str) -> np.ndarray:
        return self._arrays[name]

    def __getattr__(self, name: str) -> np.ndarray:
        arrays = self.__dict__.get("_arrays")
        if arrays is not None and name in arrays:
            return arrays[name][: self._size]
        raise AttributeError(name)

    def live_mask(self) -> np.ndarray:
        return self._arrays["confidence"][: self._size] >= 0

    # changes --------------------------------------------------------------------------------------------
    def reserve(self, extra: int) -> None:
        """Make room for ``extra`` more rows, doubling the capacity as needed."""
        need = self._size + int(extra)
        cap = self.capacity
        if need <= cap:
            return
        new_cap = max(need, 2 * cap)
        for name, arr in self._arrays.items():
            grown = np.zeros((new_cap,) + arr.shape[1:], dtype=arr.dtype)
            grown[: self._size] = arr[: self._size]
            self._arrays[name] = grown

    def append(self, position, normal, radius, confidence, colour, created, updated=None) -> np.ndarray:
        """Append surfels (world frame; normals unit length); returns their row indices."""
        position = np.asarray(position, dtype=np.float32).reshape(-1, 3)
        m = position.shape[0]
        values = {
            "position": position,
            "normal": np.asarray(normal, dtype=np.float32).reshape(-1, 3),
            "radius": np.asarray(radius, dtype=np.float32).reshape(-1),
            "confidence": np.asarray(confidence, dtype=np.float32).reshape(-1),
            "colour": np.asarray(colour, dtype=np.float32).reshape(-1, 3),
        }
        for name, val in values.items():
            if val.shape[0] != m:
                raise ValueError(f"{name} must have one row per surfel ({m}), got shape {val.shape}")
        if np.any(values["confidence"] < 0):
            raise ValueError("confidence must be >= 0 (negative marks dead surfels)")
        created_arr = np.broadcast_to(np.asarray(created, dtype=np.int32), (m,))
        updated_arr = created_arr if updated is None else np.broadcast_to(np.asarray(updated, dtype=np.int32), (m,))
        self.reserve(m)
        sl = slice(self._size, self._size + m)
        for name, val in values.items():
            self._arrays[name][sl] = val
        self._arrays["created"][sl] = created_arr
        self._arrays["updated"][sl] = updated_arr
        self._size += m
        return np.arange(sl.start, sl.stop)

    def kill(self, rows: np.ndarray) -> int:
        """Mark rows dead; returns how many were alive."""
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        conf = self._arrays["confidence"]
        alive = rows[conf[rows] >= 0]
        conf[alive] = -1.0
        self._dead += int(alive.size)
        return int(alive.size)

    def note_dead(self, count: int) -> None:
        """Account for rows a kernel marked dead in place."""
        self._dead += int(count)

    def compact(self) -> None:
        """Drop dead rows, keeping the order of the live ones (creation order, spatially coherent)."""
        if self._dead == 0:
            return
        keep = np.flatnonzero(self._arrays["confidence"][: self._size] >= 0)
        k = keep.size
        for arr in self._arrays.values():
            arr[:k] = arr[keep]
        self._size = k
        self._dead = 0


# --------------------------------------------------------------------------------------------------
# PLY
# --------------------------------------------------------------------------------------------------
_PLY_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                       ("red", "u1"), ("green", "u1"), ("blue", "u1"), ("radius", "<f4"), ("confidence", "<f4")])
_PLY_TYPES = {"f4": "float", "u1": "uchar"}


def write_surfel_ply(path: str | Path, positions: np.ndarray, normals: np.ndarray, colours: np.ndarray,
                     radius: np.ndarray, confidence: np.ndarray, *, comment: str = "radiomap surfel map") -> Path:
    """Write surfels as a binary little-endian PLY point cloud, atomically.

    Vertex properties: ``x y z nx ny nz`` (float), ``red green blue`` (uchar, display levels), ``radius``
    and ``confidence`` (float). Readable by Open3D, trimesh, CloudCompare and MeshLab.
    """
    n = int(np.shape(positions)[0])
    colours = np.asarray(colours)
    if colours.shape != (n, 3) or colours.dtype != np.uint8:
        raise ValueError(f"colours must be uint8 of shape ({n}, 3), got {colours.dtype} {colours.shape}")
    rec = np.empty(n, dtype=_PLY_DTYPE)
    pos = np.asarray(positions, dtype=np.float32).reshape(n, 3)
    nrm = np.asarray(normals, dtype=np.float32).reshape(n, 3)
    for i, a in enumerate("xyz"):
        rec[a] = pos[:, i]
        rec["n" + a] = nrm[:, i]
    for i, c in enumerate(("red", "green", "blue")):
        rec[c] = colours[:, i]
    rec["radius"] = np.asarray(radius, dtype=np.float32).reshape(n)
    rec["confidence"] = np.asarray(confidence, dtype=np.float32).reshape(n)
    props = "".join(f"property {_PLY_TYPES[_PLY_DTYPE[name].str.lstrip('<|')]} {name}\n" for name in _PLY_DTYPE.names)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment {comment}\nelement vertex {n}\n{props}end_header\n")
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(header.encode("ascii"))
            fh.write(rec.tobytes())
    return Path(path)


# --------------------------------------------------------------------------------------------------
# the backend
# --------------------------------------------------------------------------------------------------
