"""Numba kernels of :mod:`mapping.colour` (compiled on first use, cached on disk).

The response's inverse table ``t_0 < ... < t_255`` (per channel, already divided by ``k_ref``) is inverted
exactly: a uniform bucket index over ``[t_0, t_255]`` gives the segment to start from, a short scan finishes,
then linear interpolation inside the segment (``inv_slope = 1 / (t_{j+1} - t_j)``).
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True, inline="always")
def _level(e, c, tables, inv_slope, starts, low, inv_width, t0, tmax, nb):  # pragma: no cover - compiled
    """The display level (0..255, fractional) of irradiance ``e`` in channel ``c``; 0 below f^-1(0) or NaN."""
    if e > t0 and e < tmax:
        b = int((e - low) * inv_width)
        if b > nb:
            b = nb
        j = starts[b, c]
        while tables[j + 1, c] <= e:
            j += 1
        return j + (e - tables[j, c]) * inv_slope[j, c]
    if e >= tmax:
        return 255.0
    return 0.0


@njit(cache=True, nogil=True)
def forward(x, tables, inv_slope, starts, lo, inv_width, out):  # pragma: no cover - compiled
    """Display levels of irradiance ``x`` (N, C) into ``out`` (N, C)."""
    nb = starts.shape[0] - 1
    for c in range(x.shape[1]):
        t0, tmax, low, iw = tables[0, c], tables[255, c], lo[c], inv_width[c]
        for i in range(x.shape[0]):
            out[i, c] = _level(x[i, c], c, tables, inv_slope, starts, low, iw, t0, tmax, nb)
    return out


@njit(cache=True, nogil=True)
def l1(a, b, tables, inv_slope, starts, lo, inv_width, out):  # pragma: no cover - compiled
    """``out[i] = sum_c |level(a[i, c]) - level(b[i, c])|``: the display-unit L1 distance of two (N, C)
    irradiance arrays, in one pass over each channel."""
    nb = starts.shape[0] - 1
    n = a.shape[0]
    for i in range(n):
        out[i] = 0.0
    for c in range(a.shape[1]):
        t0, tmax, low, iw = tables[0, c], tables[255, c], lo[c], inv_width[c]
        for i in range(n):
            la = _level(a[i, c], c, tables, inv_slope, starts, low, iw, t0, tmax, nb)
            lb = _level(b[i, c], c, tables, inv_slope, starts, low, iw, t0, tmax, nb)
            out[i] += abs(la - lb)
    return out
