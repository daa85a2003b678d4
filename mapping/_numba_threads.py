"""The threading layer of radiomap's parallel Numba kernels, chosen once before any of them runs.

Numba tries TBB first, and the TBB that Open3D loads is older than Numba accepts: a NumbaWarning on stderr in
every run, then the workqueue layer, which is not thread-safe. OpenMP is thread-safe and ships with Numba's
wheels; a layer the user chose (NUMBA_THREADING_LAYER) is kept, and so is Numba's default where its OpenMP
layer cannot load (no libgomp). Every module with a ``parallel=True`` kernel imports this one first.
"""

from __future__ import annotations

import os

import numba

if "NUMBA_THREADING_LAYER" not in os.environ:
    try:
        from numba.np.ufunc import omppool  # noqa: F401
    except ImportError:
        pass
    else:
        numba.config.THREADING_LAYER = "omp"
