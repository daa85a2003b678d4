"""The checks of a bracketed stack that every response method shares: images and times (:func:`_as_stack`), the
brightness order of the times, the levels and the mask a fit uses; :func:`equal_ratios` (whether every exposure
ratio is the same, which leaves Engel's and Debevec's fits a periodic ambiguity).

Below the methods (:mod:`~radiometry.response.fit`, :mod:`~radiometry.response.engel`, ...), so that they share
these without importing each other.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def _as_stack(images: Sequence[np.ndarray], times: Sequence[float] | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Check images and times; return ``(P, H, W, C)`` uint8 and float64 ``(P,)`` times (input order)."""
    try:
        images = list(images)
    except TypeError:
        raise TypeError(f"images must be a list of arrays, got {type(images).__name__}") from None
    if len(images) < 2:
        raise ValueError(f"images must hold at least 2 exposures, got {len(images)}; pass a bracketed stack")
    arrays = []
    for k, img in enumerate(images):
        arr = np.asarray(img)
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[:, :, 0]
        if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[2] != 3):
            raise ValueError(f"images[{k}] must be (H, W) grayscale or (H, W, 3) RGB, got shape {arr.shape}")
        if arr.dtype != np.uint8:
            if np.issubdtype(arr.dtype, np.integer) and arr.size and arr.min() >= 0 and arr.max() <= 255:
                arr = arr.astype(np.uint8)
            else:
                raise TypeError(f"images[{k}] must be uint8 (levels 0..255), got {arr.dtype}; "
                                "convert 16-bit images with (img >> 8).astype(np.uint8)")
        arrays.append(arr)
    shape = arrays[0].shape
    for k, arr in enumerate(arrays):
        if arr.shape != shape:
            raise ValueError(f"images must all have the same shape: images[0] is {shape}, "
                             f"images[{k}] is {arr.shape}")
    stack = np.stack(arrays)
    if stack.ndim == 3:
        stack = stack[..., None]
    t = np.asarray(times, dtype=np.float64).ravel() if not isinstance(times, (str, bytes)) else None
    if t is None:
        raise TypeError("times must be a sequence of exposure times in seconds")
    if t.size != len(arrays):
        raise ValueError(f"times must have one exposure time per image: {len(arrays)} images, {t.size} times")
    if not np.all(np.isfinite(t)) or np.any(t <= 0):
        raise ValueError(f"times must be positive finite seconds, got {t.tolist()}")
    if np.unique(t).size < 2:
        raise ValueError(f"times must contain at least two different exposure times, got {t.tolist()}; give each "
                         "image its own exposure time, and capture the bracket at two or more different exposures")
    return stack, t


def _check_brightness_order(stack: np.ndarray, times: np.ndarray) -> None:
    """Longer exposures must be brighter: reject times that are clearly inverted (e.g. a 1/t column)."""
    means = stack.reshape(stack.shape[0], -1).mean(axis=1)
    concordant = discordant = 0
    for a in range(len(times)):
        for b in range(a + 1, len(times)):
            if times[a] == times[b] or abs(means[a] - means[b]) < 1.0:
                continue
            if (times[a] < times[b]) == (means[a] < means[b]):
                concordant += 1
            else:
                discordant += 1
    if discordant > 0 and discordant >= 2 * concordant:
        raise ValueError(
            "times are inverted: the images with the longest times are the darkest "
            f"({discordant} of {concordant + discordant} pairs disagree); pass exposure times in seconds, "
            "not 1/t (in image_list.txt the second column is seconds, the third 1/t)")


def _check_levels(levels) -> tuple[int, int]:
    """The (low, high) intensity levels a fit uses, checked."""
    try:
        lo, hi = (int(v) for v in levels)
    except (TypeError, ValueError):
        raise TypeError(f"levels must be a pair (low, high) of intensity levels, got {levels!r}") from None
    if not (1 <= lo and hi <= 254 and hi - lo >= 16):
        raise ValueError(f"levels must satisfy 1 <= low, high <= 254 and span at least 16 levels, got {levels!r}")
    return lo, hi


def _check_mask(mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray | None:
    if mask is None:
        return None
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"mask must have the image shape {shape}, got {m.shape}")
    if m.dtype != bool:
        raise TypeError(f"mask must be a boolean array (True = usable pixel), got {m.dtype}")
    if not m.any():
        raise ValueError("mask excludes every pixel; True marks the pixels to use")
    return m


def equal_ratios(times: np.ndarray, *, tolerance: float = 0.02) -> float | None:
    """The common ratio of consecutive distinct exposure times if they are all equal within ``tolerance``
    (relative), else None."""
    distinct = np.unique(np.asarray(times, dtype=np.float64))
    if distinct.size < 2:
        return None
    with np.errstate(invalid="ignore", divide="ignore"):  # bad times (<= 0, NaN): the fitter refuses them by name
        ratios = distinct[1:] / distinct[:-1]
        if distinct.size == 2:
            return float(ratios[0])
        spread = np.abs(np.log(ratios / ratios.mean()))
    if np.all(spread <= tolerance):
        return float(ratios.mean())
    return None
