"""Numba kernels of :mod:`mapping.colour` (compiled on first use, cached on disk).

The response's inverse table ``t_0 < ... < t_255`` (per channel, already divided by ``k_ref``) is inverted
exactly: a uniform bucket index over ``[t_0, t_255]`` gives the segment to start from, a short scan finishes,
then linear interpolation inside the segment (``inv_slope = 1 / (t_{j+1} - t_j)``).

:func:`l1` repeats the look-up of :func:`forward` for its two inputs on purpose: folded into a shared
``@njit(inline="always")`` helper it ran 4-6x slower (26-40 ms instead of ~6 ms for 88k pairs; Numba 0.68).
"""

from __future__ import annotations

from numba import njit, prange

import mapping._numba_threads  # noqa: F401  (the threading layer, before any parallel kernel runs)


@njit(cache=True, nogil=True)
def forward(x, tables, inv_slope, starts, lo, inv_width, out):  # pragma: no cover - compiled
    """Display levels of irradiance ``x`` (N, C) into ``out`` (N, C)."""
    nb = starts.shape[0] - 1
    for c in range(x.shape[1]):
        t0 = tables[0, c]
        tmax = tables[255, c]
        low = lo[c]
        iw = inv_width[c]
        for i in range(x.shape[0]):
            e = x[i, c]
            if e > t0 and e < tmax:
                q = (e - low) * iw
                b = 0 if not q >= 0 else (nb if q > nb else int(q))  # a bucket of the table, always
                j = starts[b, c]
                while tables[j + 1, c] <= e:
                    j += 1
                out[i, c] = j + (e - tables[j, c]) * inv_slope[j, c]
            elif e >= tmax:
                out[i, c] = 255.0
            else:  # below f^-1(0), or NaN
                out[i, c] = 0.0
    return out


@njit(cache=True, nogil=True, parallel=True)
def l1(a, b, tables, inv_slope, starts, lo, inv_width, out):  # pragma: no cover - compiled
    """``out[i] = sum_c |level(a[i, c]) - level(b[i, c])|``: the display-unit L1 distance of two (N, C)
    irradiance arrays. Rows in parallel (each row's sum in the same channel order as a serial pass: the
    result does not depend on the number of threads)."""
    nb = starts.shape[0] - 1
    for i in prange(a.shape[0]):
        out[i] = 0.0
        for c in range(a.shape[1]):
            t0 = tables[0, c]
            tmax = tables[255, c]
            e = a[i, c]
            if e > t0 and e < tmax:
                q = (e - lo[c]) * inv_width[c]
                k = 0 if not q >= 0 else (nb if q > nb else int(q))
                j = starts[k, c]
                while tables[j + 1, c] <= e:
                    j += 1
                la = j + (e - tables[j, c]) * inv_slope[j, c]
            elif e >= tmax:
                la = 255.0
            else:
                la = 0.0
            e = b[i, c]
            if e > t0 and e < tmax:
                q = (e - lo[c]) * inv_width[c]
                k = 0 if not q >= 0 else (nb if q > nb else int(q))
                j = starts[k, c]
                while tables[j + 1, c] <= e:
                    j += 1
                lb = j + (e - tables[j, c]) * inv_slope[j, c]
            elif e >= tmax:
                lb = 255.0
            else:
                lb = 0.0
            out[i] += abs(la - lb)
    return out
