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


#: pixels per image compared by :func:`_check_brightness_order`; pairs of exposures closer than this ratio are not
#: compared (noise can make either look brighter); a level difference of more than STEP counts as darker/brighter
ORDER_PIXELS = 50_000
ORDER_RATIO = 1.25
ORDER_STEP = 2


class TimesOrderError(ValueError):
    """The images' brightness does not rise with their exposure times. ``pairs``: ``(shorter, longer)`` indices of
    the images whose longer exposure is darker, of ``compared`` pairs; :meth:`message` names them (by file when
    given the names)."""

    def __init__(self, pairs: list[tuple[int, int]], compared: int, times: np.ndarray) -> None:
        self.pairs, self.compared, self.times = pairs, compared, np.asarray(times, dtype=np.float64)
        self.inverted = len(pairs) >= 2 * (compared - len(pairs))
        super().__init__(self.message())

    def message(self, names: Sequence[str] | None = None) -> str:
        count = f"{len(self.pairs)} of {self.compared} pairs disagree"
        if self.inverted:
            return (f"times are inverted: the images with the longest times are the darkest ({count}); pass exposure "
                    "times in seconds, not 1/t (in image_list.txt the second column is seconds, the third 1/t)")

        def name(k: int) -> str:
            return f"the image given {self.times[k]:g} s" if names is None else f"{names[k]} ({self.times[k]:g} s)"

        which = "; ".join(f"{name(b)} is darker than {name(a)}" for a, b in self.pairs[:3])
        return (f"the times look out of order: the images' brightness does not rise with their exposure times "
                f"({which}{'; ...' if len(self.pairs) > 3 else ''}: {count}); check which time belongs to which "
                "image in the times file")


def _darker_pairs(stack: np.ndarray, times: np.ndarray) -> tuple[list[tuple[int, int]], int]:
    """The ``(shorter, longer)`` pairs of exposures (at least :data:`ORDER_RATIO` apart) in which most of the pixels
    that change are darker in the longer one, and the number of pairs compared. Pixel by pixel rather than by the
    image mean: a swap of two exposures among many barely moves the means' order statistics."""
    n_img = stack.shape[0]
    flat = stack.reshape(n_img, -1)
    step = max(1, flat.shape[1] // ORDER_PIXELS)
    sample = flat[:, ::step].astype(np.int16)
    darker, compared = [], 0
    for a in range(n_img):
        for b in range(n_img):
            if not times[b] >= ORDER_RATIO * times[a]:
                continue
            down = int(np.count_nonzero(sample[b] < sample[a] - ORDER_STEP))
            up = int(np.count_nonzero(sample[b] > sample[a] + ORDER_STEP))
            if down + up < max(100, sample.shape[1] // 100):  # too few pixels change (saturated or dark in both)
                continue
            compared += 1
            if down > up:
                darker.append((a, b))
    return darker, compared


def _check_brightness_order(stack: np.ndarray, times: np.ndarray) -> None:
    """Longer exposures must be brighter: reject times that are inverted (e.g. a 1/t column) or out of order (two
    images' times swapped): :class:`TimesOrderError`."""
    darker, compared = _darker_pairs(stack, times)
    if darker:
        raise TimesOrderError(darker, compared, times)


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
