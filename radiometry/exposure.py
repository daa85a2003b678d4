"""Exposure ratio of two observations from pixel correspondences (Alexandrov et al., Sec. V).

For a scene point seen at pixel ``x1`` with exposure ``k1`` and at ``x2`` with ``k2``,
``I_i = f(k_i V(x_i) L)``, so every correspondence gives ``k1 / k2 = f^-1(I1) V(x2) / (f^-1(I2) V(x1))``.
:func:`exposure_ratio` takes the median of these per-pixel ratios, per channel (white balance acts as
a per-channel exposure), ignoring pixels that are near saturation or too dark in either observation:
their intensities no longer measure irradiance.
"""

from __future__ import annotations

import numpy as np

from radiometry.response import CameraResponse


def _as_nc(name: str, values: np.ndarray | float | None, n: int, channels: int) -> np.ndarray:
    if values is None:
        return np.ones((n, 1), dtype=np.float64)
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full((n, 1), float(arr))
    elif arr.ndim == 1:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[0] != n or arr.shape[1] not in (1, channels):
        raise ValueError(f"{name} must have shape ({n},), ({n}, 1) or ({n}, {channels}) to match the "
                         f"intensities, got {np.shape(values)}")
    return arr


def exposure_ratio(intensity1: np.ndarray, intensity2: np.ndarray, vignetting1: np.ndarray | float | None,
                   vignetting2: np.ndarray | float | None, response: CameraResponse, *,
                   mask: np.ndarray | None = None, low: float = 10, high: float = 250,
                   min_count: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Median exposure ratio ``k1 / k2`` of two observations, per channel.

    Parameters
    ----------
    intensity1, intensity2 : ``(N, C)`` (or ``(N,)`` for grayscale) intensities of N corresponding
        pixels in observation 1 and 2: uint8, or float levels 0..255.
    vignetting1, vignetting2 : ``V`` at those pixels, ``(N, C)``, ``(N, 1)``, ``(N,)``, a scalar, or
        ``None`` for no vignetting.
    response : the camera response (1 or C channels).
    mask : optional ``(N,)`` bool, correspondences to consider.
    low, high : a correspondence is used in a channel only if ``low <= I < high`` in both observations
        (dark pixels are dominated by noise and quantisation, bright ones may be clipped).
    min_count : fewest usable correspondences for a channel's ratio.

    Returns
    -------
    ratio : float64 ``(C,)``, the median of ``k1/k2`` per channel; ``NaN`` for a channel with fewer than
        ``min_count`` usable correspondences (never an exception: a frame pair without overlap is a normal
        event in a sequence, and the caller decides what to do with it).
    n_used : int64 ``(C,)``, the number of correspondences used per channel (0 when none qualified).
    """
    i1 = np.asarray(intensity1)
    i2 = np.asarray(intensity2)
    if i1.shape != i2.shape:
        raise ValueError(f"intensity1 and intensity2 must have the same shape, got {i1.shape} and {i2.shape}")
    if i1.ndim == 1:
        i1, i2 = i1[:, None], i2[:, None]
    if i1.ndim != 2:
        raise ValueError(f"intensities must have shape (N, C) or (N,), got {np.shape(intensity1)}")
    for name, arr in (("intensity1", i1), ("intensity2", i2)):
        if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
            raise TypeError(f"{name} must be integer or float levels, got dtype {arr.dtype}")
    if not (0 <= low < high <= 256):
        raise ValueError(f"need 0 <= low < high <= 256, got low={low}, high={high}")
    if min_count < 1:
        raise ValueError(f"min_count must be at least 1, got {min_count}")
    n, channels = i1.shape
    v1 = _as_nc("vignetting1", vignetting1, n, channels)
    v2 = _as_nc("vignetting2", vignetting2, n, channels)
    if mask is None:
        keep = np.ones(n, dtype=bool)
    else:
        keep = np.asarray(mask, dtype=bool)
        if keep.shape != (n,):
            raise ValueError(f"mask must have shape ({n},), got {keep.shape}")
    ratio = np.full(channels, np.nan)
    n_used = np.zeros(channels, dtype=np.int64)
    if n == 0:
        return ratio, n_used
    f1 = np.nan_to_num(i1.astype(np.float64), nan=-1.0)
    f2 = np.nan_to_num(i2.astype(np.float64), nan=-1.0)
    valid = keep[:, None] & (f1 >= low) & (f1 < high) & (f2 >= low) & (f2 < high)
    valid &= np.isfinite(v1) & np.isfinite(v2) & (v1 > 0) & (v2 > 0)
    tables = response.channel_tables(channels)
    for c in range(channels):
        sel = valid[:, c]
        e1 = np.interp(f1[sel, c], np.arange(256.0), tables[:, c])
        e2 = np.interp(f2[sel, c], np.arange(256.0), tables[:, c])
        a1 = v1[sel, min(c, v1.shape[1] - 1)]
        a2 = v2[sel, min(c, v2.shape[1] - 1)]
        good = (e1 > 0) & (e2 > 0)
        count = int(np.count_nonzero(good))
        n_used[c] = count
        if count >= min_count:
            ratio[c] = float(np.median(e1[good] * a2[good] / (e2[good] * a1[good])))
    return ratio, n_used


__all__ = ["exposure_ratio"]
