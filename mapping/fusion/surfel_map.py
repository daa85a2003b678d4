"""Surfel storage (:class:`SurfelMap`, struct-of-arrays with amortised growth and block summaries), the
per-frame pass over it (:func:`cull`: the unstable rule and the surfels in view, skipping blocks out of view;
:func:`remove_unstable`), and the surfel PLY writer, for :mod:`mapping.fusion.surfel`.

- :func:`cull`: one pass over the map (transform, depth and image-bounds test) that writes only the surfels
  in view into preallocated buffers; NumPy would build several full-size temporaries per frame. Blocks of
  the map outside the view and with no surfel due for the unstable rule are skipped whole.
- :func:`remove_unstable`: the unstable-surfel rule over the whole map (inside :func:`cull` per frame).
- :func:`fold_rows`: rows into their blocks' summaries.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from numba import njit

from radiometry.fileio import atomic_path


class SurfelMap:
    """Struct-of-arrays surfel storage with amortised growth and compaction.

    Arrays have ``capacity`` rows; rows ``0 .. size-1`` are in use, some of them dead (confidence -1) until
    :meth:`compact` removes them. ``created``/``updated`` are integration counters (0 for the first frame
    integrated), not frame indices; :class:`SurfelBackend` maps them back to frame indices.

    Blocks of ``BLOCK`` consecutive rows (surfels made in the same frames, so mostly close together) carry
    conservative summaries that let the per-frame pass over the map skip whole blocks: the bounding box of
    their positions (``block_lo``/``block_hi``) and ``block_oldest``, no later than the last update of any
    of their live surfels below ``stable_confidence`` (the ones the unstable rule may remove). Rows added
    by :meth:`append` are folded in; rows written in place (:meth:`claim`) are folded in by
    :meth:`note_rows`; a kernel that moves a surfel widens its block's box; :meth:`compact` recomputes them.
    Other writes to positions or confidences must call :meth:`note_rows` for the rows they changed.
    """

    BLOCK_SHIFT = 10
    BLOCK = 1 << BLOCK_SHIFT  # rows per block
    NEVER = np.iinfo(np.int32).max  # block_oldest of a block without unstable surfels

    FIELDS: tuple[tuple[str, tuple[int, ...], type], ...] = (
        ("position", (3,), np.float32),
        ("normal", (3,), np.float32),
        ("radius", (), np.float32),
        ("confidence", (), np.float32),
        ("colour", (3,), np.float32),
        ("created", (), np.int32),
        ("updated", (), np.int32),
    )

    def __init__(self, capacity: int = 1 << 16, *, stable_confidence: float = np.inf) -> None:
        if int(capacity) < 1:
            raise ValueError(f"capacity must be a positive number of surfels, got {capacity}")
        self._size = 0
        self._dead = 0
        self.stable_confidence = float(stable_confidence)
        self._arrays: dict[str, np.ndarray] = {
            name: np.zeros((int(capacity),) + shape, dtype=dtype) for name, shape, dtype in self.FIELDS}
        blocks = self._blocks_for(int(capacity))
        self.block_lo = np.full((blocks, 3), np.inf, np.float32)
        self.block_hi = np.full((blocks, 3), -np.inf, np.float32)
        self.block_oldest = np.full(blocks, self.NEVER, np.int32)

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
        """Bytes of the surfel fields (``capacity`` rows)."""
        return int(sum(a.nbytes for a in self._arrays.values()))

    @property
    def block_nbytes(self) -> int:
        """Bytes of the block summaries."""
        return int(self.block_lo.nbytes + self.block_hi.nbytes + self.block_oldest.nbytes)

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
        blocks, have = self._blocks_for(new_cap), self.block_oldest.shape[0]
        self.block_lo = np.concatenate([self.block_lo, np.full((blocks - have, 3), np.inf, np.float32)])
        self.block_hi = np.concatenate([self.block_hi, np.full((blocks - have, 3), -np.inf, np.float32)])
        self.block_oldest = np.concatenate([self.block_oldest, np.full(blocks - have, self.NEVER, np.int32)])

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
        self.note_rows(sl.start, sl.stop)
        return np.arange(sl.start, sl.stop)

    def claim(self, count: int) -> int:
        """Count ``count`` more rows in (capacity grown as needed) and return the first; the caller fills them
        through :meth:`array` (the fusion kernels write new surfels in place) and then calls
        :meth:`note_rows`."""
        self.reserve(count)
        first = self._size
        self._size += int(count)
        return first

    def note_rows(self, start: int, stop: int) -> None:
        """Fold rows ``start .. stop-1`` (written or changed) into their blocks' summaries (see the class doc)."""
        if stop > start:
            fold_rows(self._arrays["position"], self._arrays["confidence"], self._arrays["updated"], int(start),
                      int(stop), self.BLOCK_SHIFT, self.stable_confidence, self.block_lo, self.block_hi,
                      self.block_oldest)

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
        self.block_lo.fill(np.inf)
        self.block_hi.fill(-np.inf)
        self.block_oldest.fill(self.NEVER)
        self.note_rows(0, k)

    @classmethod
    def _blocks_for(cls, capacity: int) -> int:
        return (capacity + cls.BLOCK - 1) >> cls.BLOCK_SHIFT


# --------------------------------------------------------------------------------------------------
# the pass over the map (Numba, compiled on first use, cached on disk)
# --------------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def cull(pos, nrm, conf, t_upd, n, block_lo, block_hi, block_oldest, shift, rot, trans, fx, fy, cx, cy, width,
         height, min_conf, max_depth, now, c_stable, window, out_idx, out_pc, out_nc, out_px, out_removed):
    """Surfels in view: camera-frame position/normal and continuous pixel coordinates; and the unstable rule.

    The one pass over the map per frame, block by block (``1 << shift`` rows, summaries of
    :class:`~mapping.fusion.surfel_map.SurfelMap`): a block whose bounding box lies outside the view and
    that holds no unstable surfel old enough for the rule (``block_oldest``) is skipped whole; the others
    are processed surfel by surfel, and their ``block_oldest`` is made exact. First the unstable rule
    (ElasticFusion: ``time - lastUpdate > 20 && conf < threshold``) with ``now`` the last integrated frame:
    a live surfel with ``conf < c_stable`` not updated for more than ``window`` frames is marked dead
    (confidence -1) and counted in ``out_removed[0]``. Then surfel ``i`` is kept when ``conf[i] >=
    min_conf``, ``0 < z <= max_depth`` in the camera frame, and its centre projects inside the image, i.e.
    pixel coordinates in ``[-0.5, width - 0.5) x [-0.5, height - 0.5)`` (pixel centres at integers).
    ``rot``/``trans`` map world to camera. Returns the number of surfels written, in row order.
    """
    r00 = rot[0, 0]; r01 = rot[0, 1]; r02 = rot[0, 2]
    r10 = rot[1, 0]; r11 = rot[1, 1]; r12 = rot[1, 2]
    r20 = rot[2, 0]; r21 = rot[2, 1]; r22 = rot[2, 2]
    t0 = trans[0]; t1 = trans[1]; t2 = trans[2]
    umax = width - 0.5
    vmax = height - 0.5
    v = 0
    removed = 0
    size = 1 << shift
    never = np.iinfo(np.int32).max
    for b in range((n + size - 1) >> shift):
        expiring = block_oldest[b] != never and now - np.int64(block_oldest[b]) > window
        in_view = _box_in_view(block_lo, block_hi, b, rot, trans, fx, fy, cx, cy, width, height, max_depth)
        if not (expiring or in_view):
            continue
        oldest = never
        for i in range(b << shift, min(n, (b + 1) << shift)):
            c = conf[i]
            if c < c_stable and c >= 0.0:
                if now - t_upd[i] > window:
                    conf[i] = -1.0
                    removed += 1
                    continue
                oldest = min(oldest, t_upd[i])
            if c < min_conf or not in_view:
                continue
            x = np.float64(pos[i, 0])
            y = np.float64(pos[i, 1])
            z = np.float64(pos[i, 2])
            zc = r20 * x + r21 * y + r22 * z + t2
            if zc <= 1e-6 or zc > max_depth:
                continue
            xc = r00 * x + r01 * y + r02 * z + t0
            u = fx * xc / zc + cx
            if u < -0.5 or u >= umax:
                continue
            yc = r10 * x + r11 * y + r12 * z + t1
            w = fy * yc / zc + cy
            if w < -0.5 or w >= vmax:
                continue
            nx = np.float64(nrm[i, 0])
            ny = np.float64(nrm[i, 1])
            nz = np.float64(nrm[i, 2])
            out_idx[v] = i
            out_pc[v, 0] = xc
            out_pc[v, 1] = yc
            out_pc[v, 2] = zc
            out_nc[v, 0] = r00 * nx + r01 * ny + r02 * nz
            out_nc[v, 1] = r10 * nx + r11 * ny + r12 * nz
            out_nc[v, 2] = r20 * nx + r21 * ny + r22 * nz
            out_px[v, 0] = u
            out_px[v, 1] = w
            v += 1
        block_oldest[b] = oldest
    out_removed[0] = removed
    return v


@njit(cache=True, nogil=True)
def _box_in_view(block_lo, block_hi, b, rot, trans, fx, fy, cx, cy, width, height, max_depth):
    """False when block ``b``'s bounding box (widened by 1 mm plus a millionth of its coordinates, far more
    than rounding) lies wholly on the outer side of one of the bounds :func:`cull` tests: nearer than 1e-6,
    farther than ``max_depth``, left of -0.5, right of ``width - 0.5``, above -0.5 or below ``height - 0.5``
    (the image-side tests as planes through the camera centre, valid for points in front of it)."""
    if not (block_lo[b, 0] <= block_hi[b, 0]):
        return False  # no live surfel was ever folded in
    zmin = np.inf
    zmax = -np.inf
    left = -np.inf
    right = np.inf
    top = -np.inf
    bottom = np.inf
    x0, x1 = _widened(block_lo[b, 0], block_hi[b, 0])
    y0, y1 = _widened(block_lo[b, 1], block_hi[b, 1])
    z0, z1 = _widened(block_lo[b, 2], block_hi[b, 2])
    for corner in range(8):
        px = x1 if corner & 1 else x0
        py = y1 if corner & 2 else y0
        pz = z1 if corner & 4 else z0
        xc = rot[0, 0] * px + rot[0, 1] * py + rot[0, 2] * pz + trans[0]
        yc = rot[1, 0] * px + rot[1, 1] * py + rot[1, 2] * pz + trans[1]
        zc = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
        zmin = min(zmin, zc)
        zmax = max(zmax, zc)
        left = max(left, fx * xc + (cx + 0.5) * zc)  # u >= -0.5 needs this >= 0
        right = min(right, fx * xc + (cx + 0.5 - width) * zc)  # u < width - 0.5 needs this < 0
        top = max(top, fy * yc + (cy + 0.5) * zc)
        bottom = min(bottom, fy * yc + (cy + 0.5 - height) * zc)
    return not (zmax <= 1e-6 or zmin > max_depth or left < 0.0 or right > 0.0 or top < 0.0 or bottom > 0.0)


@njit(cache=True, nogil=True, inline="always")
def _widened(lo, hi):
    pad = 1e-3 + 1e-6 * max(abs(np.float64(lo)), abs(np.float64(hi)))
    return np.float64(lo) - pad, np.float64(hi) + pad


@njit(cache=True, nogil=True)
def fold_rows(pos, conf, t_upd, start, stop, shift, c_stable, block_lo, block_hi, block_oldest):
    """Fold map rows ``start .. stop-1`` into their blocks' summaries (``1 << shift`` rows per block): live
    positions widen the bounding box, live surfels below ``c_stable`` lower ``block_oldest`` to their last
    update (:class:`~mapping.fusion.surfel_map.SurfelMap`)."""
    for i in range(start, stop):
        c = conf[i]
        if c < 0.0:
            continue
        b = i >> shift
        for a in range(3):
            block_lo[b, a] = min(block_lo[b, a], pos[i, a])
            block_hi[b, a] = max(block_hi[b, a], pos[i, a])
        if c < c_stable and t_upd[i] < block_oldest[b]:
            block_oldest[b] = t_upd[i]


@njit(cache=True, nogil=True)
def remove_unstable(conf, t_upd, n, tick, c_stable, window):
    """Mark dead (confidence -1) the live surfels below ``c_stable`` not updated for more than ``window``
    frames (ElasticFusion: ``time - lastUpdate > 20 && conf < threshold``); returns how many."""
    removed = 0
    for i in range(n):
        c = conf[i]
        if c >= 0.0 and c < c_stable and tick - t_upd[i] > window:
            conf[i] = -1.0
            removed += 1
    return removed


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
