"""The Numba twin of the depth pyramid's C kernel ``mapping._ckernels.pyrdown`` (:func:`mapping.tracking.pyrdown_depth`).

Chosen by :mod:`mapping._native` when the C kernels are not in use; kept apart from :mod:`mapping.tracking` so that
the kernel choice does not import the tracker (and the tracker imports the choice).
"""

from __future__ import annotations

import numpy as np

_pyrdown_kernel = None


def numba_pyrdown():
    """The Numba twin of ``mapping._ckernels.pyrdown`` (compiled on first use, cached on disk)."""
    global _pyrdown_kernel
    if _pyrdown_kernel is None:
        import numba

        @numba.njit(cache=True, nogil=True)
        def pyrdown(depth, diff, out):  # pragma: no cover - compiled
            # 5x5 Gaussian (1 4 6 4 1)^2 around (2y, 2x), over the valid neighbours within ``diff`` of the
            # centre (edge-preserving, as Open3D's PyrDownDepth); NaN where the centre is invalid
            w1 = (1.0, 4.0, 6.0, 4.0, 1.0)
            diff = np.float32(diff)
            rows, cols = depth.shape
            for y in range(out.shape[0]):
                for x in range(out.shape[1]):
                    cy, cx = 2 * y, 2 * x
                    c = depth[cy, cx]
                    if not (c > 0):
                        out[y, x] = np.nan
                        continue
                    s = 0.0
                    ws = 0.0
                    for dy in range(-2, 3):
                        yy = cy + dy
                        if yy < 0 or yy >= rows:
                            continue
                        for dx in range(-2, 3):
                            xx = cx + dx
                            if xx < 0 or xx >= cols:
                                continue
                            d = depth[yy, xx]
                            if d > 0 and abs(d - c) < diff:
                                w = w1[dy + 2] * w1[dx + 2]
                                s += w * d
                                ws += w
                    out[y, x] = s / ws if ws > 0 else np.nan  # no neighbour within diff (diff <= 0, inf)
            return out

        _pyrdown_kernel = pyrdown
    return _pyrdown_kernel
