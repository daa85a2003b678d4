"""The mapping kernels in the implementation :mod:`radiometry._native` chooses (compiled C or Numba).

:func:`tsdf_kernels` and :func:`colour_kernels` return a namespace with the functions of
:mod:`mapping.fusion._tsdf_kernels` and :mod:`mapping._colour_kernels` (same names, arguments and results);
:func:`pyrdown` the depth pyramid's kernel. Numba is imported only when its kernels run.
"""

from __future__ import annotations

from functools import lru_cache
from types import SimpleNamespace

import numpy as np

from radiometry._native import choice, compiled, unusable

_TSDF = ("colour_pairs", "finish_view", "refine", "range_fragments", "surface_colour", "fill_block_table", "raycast_depth",
         "integrate_u16")


def _c():
    return compiled("mapping._ckernels")


@lru_cache(maxsize=None)
def _tsdf(use_c: bool):
    if not use_c:
        from mapping.fusion import _tsdf_kernels

        return _tsdf_kernels
    c = _c()

    def hit_bounds(depth, Rc, o, fx, fy, cx, cy, block_size):
        lo, hi = np.empty(3, np.int64), np.empty(3, np.int64)
        c.hit_bounds(depth, Rc, o, fx, fy, cx, cy, block_size, lo, hi)
        return lo, hi

    return SimpleNamespace(hit_bounds=hit_bounds, **{name: getattr(c, name) for name in _TSDF})


@lru_cache(maxsize=None)
def _colour(use_c: bool):
    if not use_c:
        from mapping import _colour_kernels

        return _colour_kernels
    c = _c()
    return SimpleNamespace(forward=c.forward, l1=c.l1)


@lru_cache(maxsize=None)
def _pyrdown(use_c: bool):
    if use_c:
        return _c().pyrdown
    from mapping._pyramid_kernels import numba_pyrdown

    return numba_pyrdown()


def tsdf_kernels():
    """The TSDF backend's kernels (:mod:`mapping.fusion._tsdf_kernels`)."""
    return _tsdf(_c() is not None)


def colour_kernels():
    """The display look-ups of :class:`mapping.colour.FastForward` (:mod:`mapping._colour_kernels`)."""
    return _colour(_c() is not None)


def pyrdown():
    """The depth pyramid's kernel ``pyrdown(depth, diff, out)`` (:func:`mapping.tracking.pyrdown_depth`)."""
    return _pyrdown(_c() is not None)


def get_num_threads() -> int:
    """Threads of the parallel kernels in use (OpenMP's for C, Numba's otherwise)."""
    c = _c()
    if c is not None:
        return c.get_num_threads()
    import numba

    return numba.get_num_threads()


def set_num_threads(n: int) -> None:
    """Set the threads of the parallel kernels in use (for the calling thread, as OpenMP and Numba do)."""
    c = _c()
    if c is not None:
        c.set_num_threads(int(n))
        return
    import numba

    numba.set_num_threads(int(n))


def summary() -> str:
    """Which kernels run, for ``radiomap --version``: e.g. ``C (OpenMP, 2 threads)``, or Numba and why."""
    try:
        wanted = choice()
        if wanted == "numba":
            return "Numba (RADIOMAP_KERNELS=numba)"
        problems = [why for why in (unusable("mapping._ckernels"), unusable("radiometry._ckernels")) if why]
        if problems and wanted == "c":
            return f"none usable: RADIOMAP_KERNELS=c but {'; '.join(problems)}"
        if len(problems) == 2:
            return f"Numba ({'; '.join(problems)}: reinstall with a C compiler, pip install -e .)"
        if problems:
            return f"C and Numba ({problems[0]}: reinstall with pip install -e . to use C for all)"
        c = _c()
        n = c.get_num_threads()
        return f"C (OpenMP, {n} thread{'s' if n != 1 else ''})" if c.openmp else "C (no OpenMP: one thread)"
    except Exception as exc:  # noqa: BLE001 - --version must answer whatever the installation's state
        return f"none usable: {exc}"
