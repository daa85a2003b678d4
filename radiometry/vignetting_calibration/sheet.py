"""Sheet detection: the white sheet in one frame of a sweep, found by a flood fill whose tolerance follows the
sheet's own noise (step 1 of :mod:`radiometry.vignetting_calibration`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SheetDetection:
    """The sheet in one frame: ``status`` is ``"ok"`` or why the frame is skipped (``"saturated"``,
    ``"too dark"``, ``"too small"``, ``"no sheet"``, ``"textured"``, ``"low contrast"``); ``mask`` (bool
    ``(H, W)``) and ``centre`` ``(x, y)`` are set when it is ``"ok"``."""

    status: str
    mask: np.ndarray | None = None
    centre: tuple[int, int] | None = None
    area_fraction: float = 0.0
    saturated_fraction: float = 0.0
    tolerance: float = 0.0

    @property
    def ok(self) -> bool:
        return self.status == "ok"


def _grey(image: np.ndarray) -> np.ndarray:
    if image.ndim == 2:
        return image.astype(np.float32)
    return image.astype(np.float32).mean(axis=2)


def _robust_noise(grey: np.ndarray, x: int, y: int, half: int) -> float:
    h, w = grey.shape
    patch = grey[max(0, y - half):min(h, y + half + 1), max(0, x - half):min(w, x + half + 1)]
    if patch.shape[0] < 3 or patch.shape[1] < 3:
        return 0.0
    d = np.concatenate([np.diff(patch, axis=0).ravel(), np.diff(patch, axis=1).ravel()])
    mad = float(np.median(np.abs(d - np.median(d))))
    return 1.4826 * mad


def _find_seed(blurred: np.ndarray, seed: tuple[int, int], min_pixels: int, dark: float) -> tuple[int, int] | None:
    """The seed if it lies on a bright region, else the most interior point of the nearest bright region."""
    import cv2

    h, w = blurred.shape
    x, y = seed
    high = float(np.percentile(blurred[::2, ::2], 99.0))  # a subsample is plenty for a percentile
    threshold = max(dark, 0.6 * high)
    if blurred[y, x] >= threshold:
        return seed
    bright = (blurred >= threshold).astype(np.uint8)
    n, labels, stats, centroids = cv2.connectedComponentsWithStats(bright, connectivity=4)
    best, best_d = None, np.inf
    for label in range(1, n):
        if stats[label, cv2.CC_STAT_AREA] < min_pixels:
            continue
        d = float(np.hypot(centroids[label, 0] - x, centroids[label, 1] - y))
        if d < best_d:
            best, best_d = label, d
    if best is None:
        return None
    comp = (labels == best).astype(np.uint8)
    dist = cv2.distanceTransform(comp, cv2.DIST_L2, 3)
    yy, xx = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return int(xx), int(yy)


def _fill(blurred: np.ndarray, sx: int, sy: int, tolerance: float) -> np.ndarray:
    """Flood fill with a floating range from ``(sx, sy)``, kept within a plausible fall-off of the seed's value."""
    import cv2

    h, w = blurred.shape
    fill_mask = np.zeros((h + 2, w + 2), np.uint8)
    flags = 4 | (255 << 8) | cv2.FLOODFILL_MASK_ONLY  # floating range: FLOODFILL_FIXED_RANGE not set
    cv2.floodFill(blurred, fill_mask, (sx, sy), 0, loDiff=tolerance, upDiff=tolerance, flags=flags)
    region = fill_mask[1:-1, 1:-1] > 0
    # a gradual edge may let the fill creep into a darker background: keep it within a plausible falloff
    return region & (blurred >= 0.4 * float(blurred[sy, sx]))


def detect_sheet(image: np.ndarray, seed: tuple[int, int] | None = None, *, saturation: int = 250,
                 dark: int = 20, min_area: float = 0.02, max_saturated: float = 0.2,
                 noise_factor: float = 4.0, max_noise: float = 3.0, border: int | None = None,
                 min_contrast: float = 1.5, inverse: np.ndarray | None = None) -> SheetDetection:
    """Segment the white sheet in one frame (see :mod:`radiometry.vignetting_calibration`).

    Parameters
    ----------
    image : RGB uint8 ``(H, W, 3)`` or grayscale ``(H, W)``.
    seed : ``(x, y)`` where the sheet was in the previous frame; default the image centre.
    saturation : a pixel with any channel ``>= saturation`` counts as saturated.
    dark : a sheet whose median grey level is below this is "too dark".
    min_area : the fewest pixels, as a fraction of the image, for a usable sheet.
    max_saturated : a sheet with more than this fraction of saturated pixels is "saturated".
    noise_factor : fill tolerance in units of the sheet's neighbour-difference noise.
    max_noise : a seed region noisier than this (robust neighbour-difference spread of the slightly blurred
        grey image, in levels) is no plain sheet but texture or random noise: ``"textured"``. Simulated
        sweeps measure 0.2-0.9; Gaussian noise of 40 levels around 128 measures 4.4.
    border : pixels eroded from the sheet's edge; default 1% of the larger image side (at least 2).
    min_contrast : when the background covers at least 10% of the image, the sheet's median grey level must be
        at least this many times the background's, else ``"low contrast"``: a white sheet on a darker background
        (simulated sweeps: 2.0-2.4) rather than a plain part of a room (a wall: 1.3).
    inverse : the response's ``f^-1`` of the grey level (``(256,)``), when known: the clean-up then compares
        slopes of ``ln f^-1`` (the vignetting's own ``d ln V / dx``, the same at every level) instead of slopes in
        levels, which a response with a knee makes several times steeper below the knee than above it.
    """
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
        raise ValueError(f"image must be uint8 (H, W) or (H, W, 3), got {img.dtype} {img.shape}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if inverse is not None and np.shape(inverse) != (256,):
        raise ValueError(f"inverse must be the 256 values of f^-1 of the grey level, got shape {np.shape(inverse)}")
    h, w = img.shape[:2]
    n_pixels = h * w
    if border is None:
        border = max(2, int(round(0.01 * max(h, w))))
    saturated = (img >= saturation) if img.ndim == 2 else (img >= saturation).any(axis=2)
    grey = _grey(img)
    blurred = cv2.GaussianBlur(grey, (0, 0), 1.0)
    if seed is None:
        seed = (w // 2, h // 2)
    seed = (int(np.clip(seed[0], 0, w - 1)), int(np.clip(seed[1], 0, h - 1)))
    found = _find_seed(blurred, seed, max(16, int(min_area * n_pixels)), dark)
    if found is None:
        return SheetDetection("no sheet")
    sx, sy = found
    sigma = _robust_noise(blurred, sx, sy, half=max(8, min(h, w) // 20))
    if sigma > max_noise:
        return SheetDetection("textured", tolerance=sigma)
    tolerance = max(1.0, noise_factor * sigma) + 0.5  # + the vignetting gradient between neighbours
    region = _fill(blurred, sx, sy, tolerance)
    # the previous frame's centre may lie on a bright patch of the background when the sheet has moved to a
    # corner: if a region of at least min_area is min_contrast times brighter than the one filled, that is the
    # sheet: fill from its most interior point instead
    level = float(np.median(blurred[region]))
    brighter = ((~region) & ~saturated & (blurred >= max(dark, min_contrast * level))).astype(np.uint8)
    if np.count_nonzero(brighter) >= max(16, min_area * n_pixels):
        n, labels, stats, _ = cv2.connectedComponentsWithStats(brighter, connectivity=4)
        largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        if stats[largest, cv2.CC_STAT_AREA] >= max(16, min_area * n_pixels):
            dist = cv2.distanceTransform((labels == largest).astype(np.uint8), cv2.DIST_L2, 3)
            sy, sx = (int(v) for v in np.unravel_index(int(np.argmax(dist)), dist.shape))
            sigma = _robust_noise(blurred, sx, sy, half=max(8, min(h, w) // 20))
            if sigma > max_noise:
                return SheetDetection("textured", tolerance=sigma)
            tolerance = max(1.0, noise_factor * sigma) + 0.5
            region = _fill(blurred, sx, sy, tolerance)
    area = int(np.count_nonzero(region))
    if area < min_area * n_pixels:
        return SheetDetection("too small", area_fraction=area / n_pixels, tolerance=tolerance)
    sat_fraction = float(np.count_nonzero(region & saturated)) / area
    if sat_fraction > max_saturated:
        return SheetDetection("saturated", area_fraction=area / n_pixels, saturated_fraction=sat_fraction,
                              tolerance=tolerance)
    sheet_level = float(np.median(grey[region][::4]))
    if sheet_level < dark:
        return SheetDetection("too dark", area_fraction=area / n_pixels, saturated_fraction=sat_fraction,
                              tolerance=tolerance)
    outside = ~region
    if np.count_nonzero(outside) >= 0.1 * n_pixels \
            and sheet_level < min_contrast * max(float(np.median(grey[outside][::4])), 1.0):
        # a white sheet on a darker background (simulated sweeps: 2.0-2.4x); a wall in a room: 1.3x
        return SheetDetection("low contrast", area_fraction=area / n_pixels, saturated_fraction=sat_fraction,
                              tolerance=tolerance)
    # clean-up: close small holes (specks on the paper), open thin leaks, erode the edge
    m = region.astype(np.uint8)
    small = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    m = cv2.morphologyEx(m, cv2.MORPH_CLOSE, small)
    m = cv2.morphologyEx(m, cv2.MORPH_OPEN, small)
    # a border of `border` pixels round the image is kept: the sheet often fills the frame
    m = cv2.copyMakeBorder(m, border, border, border, border, cv2.BORDER_REPLICATE)
    m = cv2.erode(m, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * border + 1, 2 * border + 1)))
    m = m[border:-border, border:-border]
    if np.any(saturated):  # neighbours of clipped pixels suffer blooming and compression artefacts
        m[cv2.dilate(saturated.astype(np.uint8), small) > 0] = 0
    # the blurred tail of an edge just outside the image (or a shadow's) is darker without any edge to
    # erode from: drop pixels whose local slope is far steeper than the sheet's own (vignetting + noise)
    inner = m > 0
    if np.count_nonzero(inner) > 100:
        if inverse is None:
            field, floor = blurred, 1.0  # levels; the floor: one level per pixel
        else:
            table = np.asarray(inverse, dtype=np.float64)
            linear = np.interp(blurred, np.arange(256.0), table / table[-1])
            field, floor = np.log(np.maximum(linear, 1e-4)).astype(np.float32), 0.005  # 0.5 % per pixel
        slope = np.hypot(cv2.Sobel(field, cv2.CV_32F, 1, 0, ksize=3),
                         cv2.Sobel(field, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
        values = slope[inner][::4]
        centre = float(np.median(values))
        spread = 1.4826 * float(np.median(np.abs(values - centre)))
        steep = (slope > centre + max(6.0 * spread, floor)).astype(np.uint8)
        m[cv2.dilate(steep, np.ones((3, 3), np.uint8)) > 0] = 0
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=4)
    if n <= 1:
        return SheetDetection("too small", tolerance=tolerance)
    # the seed's piece, unless the clean-up cut it off as a crumb (a seed in the image's corner): then the largest
    largest = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    at_seed = labels[sy, sx]
    keep = at_seed if at_seed > 0 and stats[at_seed, cv2.CC_STAT_AREA] >= 0.5 * stats[largest, cv2.CC_STAT_AREA] \
        else largest
    mask = labels == keep
    used = int(np.count_nonzero(mask))
    if used < 0.5 * min_area * n_pixels:
        return SheetDetection("too small", area_fraction=used / n_pixels, tolerance=tolerance)
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)
    cy, cx = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return SheetDetection("ok", mask=mask, centre=(int(cx), int(cy)), area_fraction=used / n_pixels,
                          saturated_fraction=sat_fraction, tolerance=tolerance)
