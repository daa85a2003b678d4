"""Vertex and normal maps of depth images as Open3D computes them, on every core (issue 33).

The tracker's targets and the ray-cast view need, per depth image (NaN where there is none), its vertex map and
the normals of its bilaterally smoothed vertex map: Open3D's recipe, ``img.create_vertex_map(K)`` and
``img.filter_bilateral(5, 5.0, 10.0).create_vertex_map(K).create_normal_map()``. Open3D runs each of these on one
thread (~8 ms per 640x480 frame here, the largest single-threaded stage left of the ray cast). Here:

- the vertex and normal maps come from our C kernels (``mapping._ckernels.vertex_map``, ``normal_map``): Open3D
  0.20's float32 operations in the same order, hence the same bits (including Open3D's floor of 1e-5 on a
  normal's length, found by comparing), on every OpenMP thread;
- the bilateral filter stays Open3D's (its IPP kernel, which we do not reproduce), run on horizontal bands in
  parallel threads (Open3D releases the GIL), each band with two rows of its neighbours: the filter reads a 5x5
  window, so every output pixel sees the same input as in one call: the same bits (tests/test_surface_maps.py
  compares both with Open3D's whole-image calls on varied images).

Without the compiled kernels (``RADIOMAP_KERNELS=numba``, no C compiler) Open3D's calls run as before.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from mapping._open3d import o3d

_NAN = float("nan")
#: the bilateral filter's parameters (Open3D's tracking recipe: kernel 5, value sigma 5, distance sigma 10)
BILATERAL = (5, 5.0, 10.0)
#: rows each band reads beyond its own on both sides (the 5x5 window's reach)
HALO = BILATERAL[0] // 2
#: images with fewer rows are filtered in one call
MIN_SPLIT_ROWS = 64

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _c():
    from mapping._native import _c as compiled_kernels

    c = compiled_kernels()
    return c if c is not None and hasattr(c, "normal_map") else None


def _threads() -> int:
    from mapping._native import get_num_threads

    try:
        return max(1, int(get_num_threads()))
    except Exception:  # noqa: BLE001 - no kernels at all: one band
        return 1


def _executor() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            _pool = ThreadPoolExecutor(max_workers=4, thread_name_prefix="radiomap-bilateral")
        return _pool


def _forget_pool_in_child() -> None:
    """A forked child has none of the pool's threads (nor a usable lock): it makes its own when it needs one."""
    global _pool, _pool_lock
    _pool, _pool_lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool_in_child)


def _intrinsics(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be a 3x3 intrinsic matrix, got shape {K.shape}")
    return K


def _depth(depth) -> np.ndarray:
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W) float32 metres, got shape {depth.shape}")
    return depth


def _image(array: np.ndarray):
    """``array`` as an Open3D image (sharing its memory)."""
    return o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(np.ascontiguousarray(array)))


def vertex_map(depth: np.ndarray, K) -> np.ndarray:
    """(H, W, 3) float32 camera-frame points of ``depth`` (H, W) float32 (NaN where none: NaN points), as
    Open3D's ``Image.create_vertex_map(K, nan)``."""
    depth, K = _depth(depth), _intrinsics(K)
    c = _c()
    if depth.size == 0:     # a side of 0 (Open3D's calls fail on one)
        return np.full(depth.shape + (3,), np.nan, np.float32)
    if c is None:
        return _image(depth).create_vertex_map(o3d.core.Tensor(K), _NAN).as_tensor().numpy()
    return c.vertex_map(depth, K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.empty(depth.shape + (3,), np.float32))


def _normal_map(points: np.ndarray) -> np.ndarray:
    """Open3D's ``create_normal_map(nan)`` of a vertex map (H, W, 3) float32."""
    c = _c()
    if points.size == 0:
        return points.copy()
    if c is None:
        return _image(points).create_normal_map(_NAN).as_tensor().numpy()
    return c.normal_map(points, np.empty_like(points))


def bilateral(depth: np.ndarray) -> np.ndarray:
    """Open3D's ``filter_bilateral(5, 5.0, 10.0)`` of ``depth`` (H, W) float32, on bands in parallel threads
    (module doc); the same bits as one call."""
    depth = _depth(depth)
    if depth.size == 0:
        return depth.copy()
    rows = depth.shape[0]
    parts = min(_threads(), 4, rows // (MIN_SPLIT_ROWS // 2)) if rows >= MIN_SPLIT_ROWS else 1

    def band(lo: int, hi: int) -> np.ndarray:
        a, b = max(0, lo - HALO), min(rows, hi + HALO)
        out = _image(depth[a:b]).filter_bilateral(*BILATERAL).as_tensor().numpy()
        return out.reshape(b - a, depth.shape[1])[lo - a:hi - a]

    if parts <= 1:
        return band(0, rows)
    cuts = [rows * i // parts for i in range(parts + 1)]
    futures = [_submit(band, cuts[i], cuts[i + 1]) for i in range(1, parts)]
    first = band(cuts[0], cuts[1])      # the calling thread takes the first band
    return np.concatenate([first] + [band(cuts[i + 1], cuts[i + 2]) if f is None else f.result()
                                     for i, f in enumerate(futures)])


def _submit(fn, *args):
    """``fn(*args)`` submitted to the band pool, or None when the pool takes no more work: once the interpreter
    has begun to shut down (a non-daemon thread still mapping after the main thread ended, an atexit handler)
    ThreadPoolExecutor refuses new futures and the caller filters that band itself (the same bits)."""
    try:
        return _executor().submit(fn, *args)
    except RuntimeError:
        return None


def smoothed_normals(depth: np.ndarray, K) -> np.ndarray:
    """(H, W, 3) float32 normals of the bilaterally smoothed vertex map of ``depth`` (NaN where none), as
    ``img.filter_bilateral(5, 5.0, 10.0).create_vertex_map(K, nan).create_normal_map(nan)``."""
    return _normal_map(vertex_map(bilateral(depth), K))


def maps(depth: np.ndarray, K) -> tuple[np.ndarray, np.ndarray]:
    """``(vertex_map(depth, K), smoothed_normals(depth, K))``."""
    return vertex_map(depth, K), smoothed_normals(depth, K)


__all__ = ["bilateral", "maps", "smoothed_normals", "vertex_map"]
