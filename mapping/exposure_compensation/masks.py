"""Pixel masks and local means for exposure estimation: depth edges, clipped pixels, windowed sums, block means
(see :mod:`mapping.exposure_compensation`)."""

from __future__ import annotations

import logging

import numpy as np


log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------------
# pixel masks
# --------------------------------------------------------------------------------------------------
def depth_edges(depth: np.ndarray, *, relative: float = 0.04, absolute: float = 0.01, dilation: int = 2) -> np.ndarray:
    """Pixels at or near a depth discontinuity, bool ``(H, W)``.

    A valid pixel is an edge when a 4-neighbour differs by more than ``absolute + relative * depth``
    metres, or is a hole (depth 0: depth shadows and dropouts lie along silhouettes); the edge set is then
    grown by ``dilation`` pixels (a square structuring element). Invalid pixels are not edges (they are
    excluded anyway).
    """
    d = np.asarray(depth, dtype=np.float32)
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W) metres, got shape {d.shape}")
    d = _valid_depth(d)
    if not (relative >= 0 and absolute >= 0):
        raise ValueError(f"relative and absolute must be >= 0, got {relative}, {absolute}")
    if int(dilation) < 0:
        raise ValueError(f"dilation must be a whole number of pixels >= 0, got {dilation}")
    valid = d > 0
    tol = absolute + relative * d
    edge = np.zeros(d.shape, dtype=bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        da, db = d[a], d[b]
        va, vb = valid[a], valid[b]
        step = np.abs(da - db)
        e_a = va & (~vb | (step > tol[a]))
        e_b = vb & (~va | (step > tol[b]))
        edge[a] |= e_a
        edge[b] |= e_b
    if dilation > 0 and edge.any():
        import cv2

        kernel = np.ones((2 * int(dilation) + 1, 2 * int(dilation) + 1), np.uint8)
        edge = cv2.dilate(edge.view(np.uint8), kernel).astype(bool)
    return edge


def _valid_depth(depth: np.ndarray) -> np.ndarray:
    """Depth with NaN, inf and negative values set to 0 (invalid); the array itself when all are valid."""
    ok = np.isfinite(depth) & (depth >= 0)
    return depth if ok.all() else np.where(ok, depth, np.float32(0)).astype(np.float32)


def clipped_pixels(rgb: np.ndarray, *, high: int = 254, dark: int = 3) -> np.ndarray:
    """Pixels that do not measure irradiance, bool ``(H, W)``: any channel ``>= high`` (saturated) or every
    channel ``<= dark`` (black)."""
    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"rgb must be uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
    if not (0 <= dark < high <= 255):
        raise ValueError(f"need 0 <= dark < high <= 255, got dark={dark}, high={high}")
    import cv2

    rgb = np.ascontiguousarray(rgb)
    unsaturated = cv2.inRange(rgb, (0, 0, 0), (high - 1,) * 3)     # every channel < high (255 where true)
    black = cv2.inRange(rgb, (0, 0, 0), (dark,) * 3)                 # every channel <= dark
    return (unsaturated == 0) | (black > 0)


def local_sums(values: np.ndarray, mask: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Sums of ``values`` (H, W[, C]) over the pixels of ``mask`` in each ``(2 radius + 1)^2`` window (zero
    outside the image): ``(sums float32 like values, counts float32 (H, W))``."""
    import cv2

    vals = np.asarray(values, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    if vals.shape[:2] != m.shape:
        raise ValueError(f"mask {m.shape} must match values {vals.shape[:2]}")
    if not (isinstance(radius, (int, np.integer)) and radius >= 0):
        raise ValueError(f"radius must be a whole number of pixels >= 0, got {radius!r}")
    mf = m.astype(np.float32)
    weighted = np.where(m if vals.ndim == 2 else m[:, :, None], vals, np.float32(0))  # no inf * 0
    if radius == 0:
        return weighted, mf
    size = (2 * int(radius) + 1, 2 * int(radius) + 1)
    return (cv2.boxFilter(weighted, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT),
            cv2.boxFilter(mf, -1, size, normalize=False, borderType=cv2.BORDER_CONSTANT))


def local_mean(values: np.ndarray, mask: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` (H, W[, C]) over the pixels of ``mask`` in each ``(2 radius + 1)^2`` window:
    ``(mean float32 (0 where the window holds no masked pixel), counts float32 (H, W))``; ``radius = 0``
    gives the masked values themselves."""
    sums, count = local_sums(values, mask, radius)
    safe = np.maximum(count, 1.0)
    mean = sums / (safe if sums.ndim == 2 else safe[:, :, None])
    mean[count < 0.5] = 0.0
    return mean, count


def block_reduce(values: np.ndarray, factor: int, how: str = "mean") -> np.ndarray:
    """``values`` (H, W[, C]) reduced over ``factor x factor`` blocks (the last partial rows and columns are
    dropped): ``"mean"`` (float32), ``"all"`` or ``"any"`` (bool)."""
    import cv2

    if how not in ("mean", "all", "any"):
        raise ValueError(f"how must be one of mean, all, any; got {how!r}")
    a = np.asarray(values)
    if factor == 1:
        return a.astype(np.float32, copy=False) if how == "mean" else a.astype(bool, copy=False)
    h, w = a.shape[0] // factor, a.shape[1] // factor
    crop = np.ascontiguousarray(a[:h * factor, :w * factor], dtype=np.float32)
    # INTER_AREA with an integer factor is the exact block mean (and far faster than a NumPy reshape-mean)
    mean = cv2.resize(crop, (w, h), interpolation=cv2.INTER_AREA)
    if how == "mean":
        return mean
    return mean >= np.float32(1 - 1e-6) if how == "all" else mean > 0
