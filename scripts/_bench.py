"""Single-core benchmarking, shared by ``bench_correction.py`` and ``bench_response.py``.

Import it before NumPy: importing limits BLAS, OpenMP and Numba to one thread (the variables are read when
those libraries load); :func:`pin_to_one_core` then pins the process, so the numbers are single-core numbers.
"""

from __future__ import annotations

import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")


def pin_to_one_core() -> str:
    """Pin this process to its lowest CPU; says what was done, for the report."""
    if hasattr(os, "sched_setaffinity"):
        cpu = min(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {cpu})
        return f"pinned to CPU {cpu}"
    return "not pinned (no sched_setaffinity on this platform)"
