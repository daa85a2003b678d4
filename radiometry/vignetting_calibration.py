"""Vignetting calibration from a white-paper sweep (Alexandrov et al. 2016, Sec. IV), plus drift.

Recording: exposure (and white balance) fixed, the camera swept over an evenly lit white sheet so
that every part of the image sees the sheet many times. Then, per frame:

1. :func:`detect_sheet` finds the sheet: a flood fill seeded at the previous frame's sheet centre (the
   image centre at first; if that pixel is not on a bright region, the nearest bright region's most
   interior point). The fill uses a *floating* range on a lightly blurred grey image, so the smooth
   vignetting gradient passes while the sheet's edge stops it; its tolerance is a multiple of the
   sheet's own noise (robust std of neighbour differences around the seed). The region is cleaned
   morphologically and its border eroded (edge pixels mix sheet and background). A frame whose sheet
   is too small, too dark, or mostly saturated is skipped and counted.
2. :class:`VignettingAccumulator` maps the sheet's pixels to irradiance with ``f^-1`` (pixels with a
   channel ``>= saturation`` or ``<= dark`` excluded per channel) and accumulates per pixel and
   channel the count, sum and sum of squares (float64).

Beyond radical: light and exposure drift. If the light (or the sheet's angle to it, or an auto
exposure that was not quite off) changes the sheet's brightness by a factor ``s_t`` in frame ``t``,
a plain average mixes frames of different brightness in different parts of the image and bends
``V``. The model is ``E_t(x) = s_t V(x) L``. Alternating "V from the frames divided by their scales,
scales from V" is block coordinate descent on the least-squares problem in ``log``; it converges to
the solution of one linear system, which we solve directly (:func:`estimate_frame_scales`) on a
compact per-frame representation: the sums and counts of each frame's irradiance on a grid of
``block x block`` pixel cells (at most ~1200 cells per frame, float32 + uint16: ~22 kB per frame
at any resolution). Three robust re-weighting rounds follow so that a stain or glare does not bias
the scales. The full-resolution mean is then corrected by the mean scale of the frames that saw each
pixel: ``V(x) ~ sum_t E_t(x) / sum_t s_t`` over the frames observing ``x``, with the mean scale taken
per cell and interpolated bilinearly (exact where the sheet masks are constant over a cell, and the
masks' edges move a cell's frame set by a few frames out of hundreds).

The correction is on by default (``joint_scale=True``). On simulated 160x120 sweeps of an Xtion-like
camera it costs little in steady light (LUT error 0.17 instead of 0.11 levels: the paper's own texture
leaks a little into the scales) and saves a lot under drift (0.18 instead of 1.6 levels with the light
varying by +-10 %); ``joint_scale=False`` gives radical's plain average.

Fits (one function per method, :func:`fit_vignetting` dispatches): :func:`fit_vignetting_lut`,
:func:`fit_vignetting_polynomial` (centre fixed at the image centre by linear least squares, or free
by Levenberg-Marquardt initialised from the fixed-centre fit).
"""

from __future__ import annotations

import logging
import os
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError, CalibrationFileError, ImageError
from radiometry.fileio import save_model_file
from radiometry.images import IMAGE_EXTENSIONS, list_images, read_rgb
from radiometry.quorum import rule_text, too_little
from radiometry.response import CameraResponse, validate_inverse_table
from radiometry.vignetting import (LUTVignetting, PolynomialVignetting, VignettingModel, half_diagonal,
                                   read_model_file)

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".mjpeg", ".mjpg")
ACCUMULATION_KIND = "vignetting_accumulation"
REGIONS = ("top-left", "top", "top-right", "left", "centre", "right", "bottom-left", "bottom", "bottom-right")


# ==================================================================================================
# frame sources
# ==================================================================================================
class FrameSource:
    """An iterable of RGB uint8 frames (``(H, W, 3)``, or ``(H, W)`` grayscale) with a ``name``.

    ``length`` is the number of frames when known (``None`` for a live camera), for progress bars.
    """

    name: str = "frames"
    length: int | None = None

    def __iter__(self) -> Iterator[np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError


class FolderFrames(FrameSource):
    """The image files of a folder, in name order (or an explicit list of image files)."""

    def __init__(self, folder: str | os.PathLike | Sequence[str | os.PathLike]) -> None:
        if isinstance(folder, (str, os.PathLike)):
            self.paths = list_images(folder)
            self.name = str(folder)
            if not self.paths:
                raise ImageError(f"{folder}: no images ({', '.join(IMAGE_EXTENSIONS)}); check the folder")
        else:
            self.paths = [Path(p) for p in folder]
            self.name = str(self.paths[0]) if len(self.paths) == 1 else f"{len(self.paths)} images"
            if not self.paths:
                raise ValueError("the list of images is empty")
        self.length = len(self.paths)

    def __iter__(self) -> Iterator[np.ndarray]:
        for path in self.paths:
            yield read_rgb(path)


class VideoFrames(FrameSource):
    """The frames of a video file (decoded by OpenCV), converted to RGB."""

    def __init__(self, path: str | os.PathLike) -> None:
        import cv2

        self.path = Path(path)
        self.name = str(path)
        if not self.path.is_file():
            raise ImageError(f"{path}: no such video; check the path")
        cap = cv2.VideoCapture(str(self.path))
        try:
            if not cap.isOpened():
                raise ImageError(f"{path}: OpenCV cannot open the video (unknown codec or corrupt file); "
                                 "convert it to MJPG/H.264 or extract the frames to a folder")
            count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            cap.release()
        self.length = count if count > 0 else None

    def __iter__(self) -> Iterator[np.ndarray]:
        import cv2

        cap = cv2.VideoCapture(str(self.path))
        try:
            while True:
                ok, frame = cap.read()
                if not ok:
                    break
                yield _bgr_to_rgb(frame)
        finally:
            cap.release()


class CameraFrames(FrameSource):
    """A live camera (OpenCV capture index). Fix exposure and white balance in the camera first:
    radiomap cannot verify that through OpenCV. ``max_frames`` bounds the recording."""

    def __init__(self, index: int, *, max_frames: int | None = None, warmup: int = 10) -> None:
        if not isinstance(index, (int, np.integer)) or index < 0:
            raise ValueError(f"camera index must be a non-negative integer, got {index!r}")
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be positive, got {max_frames}")
        self.index = int(index)
        self.max_frames = max_frames
        self.warmup = int(warmup)
        self.name = f"camera {index}"
        self.length = max_frames

    def __iter__(self) -> Iterator[np.ndarray]:
        import cv2

        cap = cv2.VideoCapture(self.index)
        try:
            if not cap.isOpened():
                raise ImageError(f"cannot open camera {self.index}; check that it is connected and not in use, "
                                 "or record the sweep to a video or folder first")
            for _ in range(self.warmup):  # let the driver settle
                cap.read()
            n = 0
            while self.max_frames is None or n < self.max_frames:
                ok, frame = cap.read()
                if not ok:
                    break
                n += 1
                yield _bgr_to_rgb(frame)
        finally:
            cap.release()


class ArrayFrames(FrameSource):
    """Frames already in memory (RGB uint8 arrays)."""

    def __init__(self, frames: Iterable[np.ndarray], *, name: str = "arrays") -> None:
        self.frames = frames
        self.name = name
        self.length = len(frames) if hasattr(frames, "__len__") else None

    def __iter__(self) -> Iterator[np.ndarray]:
        for frame in self.frames:
            yield np.asarray(frame)


def _bgr_to_rgb(frame: np.ndarray) -> np.ndarray:
    import cv2

    if frame.ndim == 3 and frame.shape[2] == 3:
        return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)
    if frame.ndim == 3 and frame.shape[2] == 4:
        return cv2.cvtColor(frame, cv2.COLOR_BGRA2RGB)
    return frame


def open_frames(source: Any, *, max_frames: int | None = None) -> FrameSource:
    """A :class:`FrameSource` for a folder, a video file, an image file, a camera index (int or a string
    of digits), a list of image paths or a list of arrays; an existing source is returned as is."""
    if isinstance(source, FrameSource):
        return source
    if isinstance(source, (int, np.integer)) or (isinstance(source, str) and source.strip().isdigit()):
        return CameraFrames(int(source), max_frames=max_frames)
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if path.is_dir():
            return FolderFrames(path)
        if not path.exists():
            raise ImageError(f"{path}: no such folder, video or image; pass a folder of frames, a video file "
                             "or a camera index")
        if path.suffix.lower() in IMAGE_EXTENSIONS:
            return FolderFrames([path])
        return VideoFrames(path)
    if isinstance(source, np.ndarray):
        return ArrayFrames(source if source.ndim == 4 or (source.ndim == 3 and source.shape[2] not in (1, 3))
                           else [source])
    if isinstance(source, Sequence) and source and isinstance(source[0], (str, os.PathLike)):
        return FolderFrames(source)
    if isinstance(source, Iterable):
        return ArrayFrames(source)
    raise TypeError(f"source must be a folder, video, image, camera index or frames, got {type(source).__name__}")


# ==================================================================================================
# sheet detection
# ==================================================================================================
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


def detect_sheet(image: np.ndarray, seed: tuple[int, int] | None = None, *, saturation: int = 250,
                 dark: int = 20, min_area: float = 0.02, max_saturated: float = 0.2,
                 noise_factor: float = 4.0, max_noise: float = 3.0, border: int | None = None,
                 min_contrast: float = 1.5) -> SheetDetection:
    """Segment the white sheet in one frame (see the module doc).

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
    """
    import cv2

    img = np.asarray(image)
    if img.dtype != np.uint8 or img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3)):
        raise ValueError(f"image must be uint8 (H, W) or (H, W, 3), got {img.dtype} {img.shape}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
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
    fill_mask = np.zeros((h + 2, w + 2), np.uint8)
    flags = 4 | (255 << 8) | cv2.FLOODFILL_MASK_ONLY  # floating range: FLOODFILL_FIXED_RANGE not set
    cv2.floodFill(blurred, fill_mask, (sx, sy), 0, loDiff=tolerance, upDiff=tolerance, flags=flags)
    region = fill_mask[1:-1, 1:-1] > 0
    # a gradual edge may let the fill creep into a darker background: keep it within a plausible falloff
    seed_value = float(blurred[sy, sx])
    region &= blurred >= 0.4 * seed_value
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
        slope = np.hypot(cv2.Sobel(blurred, cv2.CV_32F, 1, 0, ksize=3),
                         cv2.Sobel(blurred, cv2.CV_32F, 0, 1, ksize=3)) / 8.0
        values = slope[inner][::4]
        centre = float(np.median(values))
        spread = 1.4826 * float(np.median(np.abs(values - centre)))
        steep = (slope > centre + max(6.0 * spread, 1.0)).astype(np.uint8)
        m[cv2.dilate(steep, np.ones((3, 3), np.uint8)) > 0] = 0
    n, labels, stats, _ = cv2.connectedComponentsWithStats(m, connectivity=4)
    if n <= 1:
        return SheetDetection("too small", tolerance=tolerance)
    keep = labels[sy, sx] if labels[sy, sx] > 0 else 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    mask = labels == keep
    used = int(np.count_nonzero(mask))
    if used < 0.5 * min_area * n_pixels:
        return SheetDetection("too small", area_fraction=used / n_pixels, tolerance=tolerance)
    dist = cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, 3)
    cy, cx = np.unravel_index(int(np.argmax(dist)), dist.shape)
    return SheetDetection("ok", mask=mask, centre=(int(cx), int(cy)), area_fraction=used / n_pixels,
                          saturated_fraction=sat_fraction, tolerance=tolerance)


# ==================================================================================================
# accumulation
# ==================================================================================================
def default_block(height: int, width: int, max_cells: int = 1200) -> int:
    """Cell size of the per-frame compact representation: at most ``max_cells`` cells per frame."""
    return max(1, int(np.ceil(np.sqrt(height * width / max_cells))))


def _accumulate_kernel():
    """One pass over a frame: per-pixel count/sum/sum of squares and per-cell sums (Numba, cached)."""
    global _ACCUMULATE
    if _ACCUMULATE is None:
        from numba import njit

        @njit(cache=True, nogil=True)
        def accumulate(img, mask, table, block, total, total_sq, count, cell_sum, cell_cnt):  # pragma: no cover
            h, w, ch = img.shape
            added = 0
            for y in range(h):
                cy = y // block
                for x in range(w):
                    if not mask[y, x]:
                        continue
                    cx = x // block
                    for c in range(ch):
                        e = table[c, img[y, x, c]]
                        if e == e:  # not NaN: a usable level
                            total[y, x, c] += e
                            total_sq[y, x, c] += e * e
                            count[y, x, c] += 1
                            cell_sum[cy, cx, c] += e
                            cell_cnt[cy, cx, c] += 1
                            added += 1
            return added

        _ACCUMULATE = accumulate
    return _ACCUMULATE


_ACCUMULATE = None


class VignettingAccumulator:
    """Accumulates sheet pixels in irradiance: per pixel and channel count, sum, sum of squares (float64),
    plus per frame the cell sums and counts used to estimate its brightness scale."""

    def __init__(self, height: int, width: int, channels: int, response: CameraResponse, *,
                 block: int | None = None, saturation: int = 250, dark: int = 5) -> None:
        if channels not in (1, 3):
            raise ValueError(f"channels must be 1 or 3, got {channels}")
        self.shape = (int(height), int(width), int(channels))
        self.response = response
        self._lut = response.channel_tables(channels).astype(np.float64)  # ModelMismatchError if incompatible
        self.block = int(block) if block else default_block(height, width)
        if self.block < 1 or self.block > 255:
            raise ValueError(f"block must be in 1..255 pixels, got {block}")
        self.saturation, self.dark = int(saturation), int(dark)
        # f^-1 per channel and level, NaN for the levels that are not used (>= saturation, <= dark)
        levels = np.arange(256)
        usable = (levels < self.saturation) & (levels > self.dark)
        self._table = np.ascontiguousarray(np.where(usable[:, None], self._lut, np.nan).T)  # (C, 256)
        self.count = np.zeros(self.shape, np.int32)
        self.sum = np.zeros(self.shape, np.float64)
        self.sumsq = np.zeros(self.shape, np.float64)
        self.grid = (-(-height // self.block), -(-width // self.block))
        self._cell_sums: list[np.ndarray] = []
        self._cell_counts: list[np.ndarray] = []
        self._indices: list[int] = []

    @property
    def frames(self) -> int:
        return len(self._cell_sums)

    def add(self, image: np.ndarray, mask: np.ndarray, *, index: int | None = None) -> int:
        """Add one frame's sheet pixels (``mask``); ``index`` is its position in the source (default: the
        count of frames added so far). Returns the number of pixel-channel samples added."""
        img = np.asarray(image)
        if img.ndim == 2:
            img = img[:, :, None]
        if img.shape != self.shape or img.dtype != np.uint8:
            raise ValueError(f"frame must be uint8 of shape {self.shape}, got {img.dtype} {img.shape}")
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != self.shape[:2]:
            raise ValueError(f"mask must have shape {self.shape[:2]}, got {mask.shape}")
        gh, gw = self.grid
        cell_sum = np.zeros((gh, gw, self.shape[2]), np.float64)
        cell_cnt = np.zeros((gh, gw, self.shape[2]), np.int64)
        added = _accumulate_kernel()(np.ascontiguousarray(img), np.ascontiguousarray(mask), self._table, self.block,
                                     self.sum, self.sumsq, self.count, cell_sum, cell_cnt)
        self._cell_sums.append(cell_sum.astype(np.float32))
        self._cell_counts.append(cell_cnt.astype(np.uint16))
        self._indices.append(len(self._indices) if index is None else int(index))
        return int(added)

    def covered(self, min_samples: int) -> bool:
        """Whether every pixel has at least ``min_samples`` samples in every channel."""
        return bool(self.count.min() >= min_samples)

    def result(self, *, skipped: dict[str, int] | None = None, source: str = "") -> "VignettingAccumulation":
        gh, gw = self.grid
        ch = self.shape[2]
        if self._cell_sums:
            sums = np.stack(self._cell_sums)
            counts = np.stack(self._cell_counts)
        else:
            sums = np.zeros((0, gh, gw, ch), np.float32)
            counts = np.zeros((0, gh, gw, ch), np.uint16)
        return VignettingAccumulation(count=self.count.copy(), sum=self.sum.copy(), sumsq=self.sumsq.copy(),
                                      cell_sums=sums, cell_counts=counts, block=self.block,
                                      frame_indices=np.array(self._indices, dtype=np.int64),
                                      skipped=dict(skipped or {}), source=source,
                                      response_table=self.response.inverse_table.copy())


@dataclass(frozen=True)
class CoverageReport:
    """How many pixels have at least ``min_samples`` samples, overall and per image region (3 x 3 grid)."""

    min_samples: int
    fraction_below: float
    regions: dict[str, float]
    min_count: int
    median_count: float

    @property
    def complete(self) -> bool:
        return self.fraction_below == 0.0

    def thin_regions(self, threshold: float = 0.05) -> list[str]:
        """Regions with more than ``threshold`` of their pixels below ``min_samples``."""
        return [name for name in REGIONS if self.regions[name] > threshold]

    def __str__(self) -> str:
        head = (f"coverage: {100 * (1 - self.fraction_below):.1f}% of pixels have >= {self.min_samples} samples "
                f"(min {self.min_count}, median {self.median_count:.0f})")
        thin = self.thin_regions()
        if not thin:
            return head
        parts = ", ".join(f"{name} {100 * self.regions[name]:.0f}% below" for name in thin)
        return f"{head}; thin: {parts}; sweep the sheet over these regions"


@dataclass(frozen=True, eq=False)
class VignettingAccumulation:
    """The fused data of one calibration session (see the module doc), ready for fitting.

    ``count``, ``sum``, ``sumsq``: ``(H, W, C)`` per pixel and channel, irradiance ``f^-1(I)``;
    ``cell_sums``/``cell_counts``: ``(T, gh, gw, C)`` per used frame on ``block``-pixel cells;
    ``frame_indices``: ``(T,)`` position of each used frame in the source; ``skipped``: reason -> number
    of skipped frames.
    """

    count: np.ndarray
    sum: np.ndarray
    sumsq: np.ndarray
    cell_sums: np.ndarray
    cell_counts: np.ndarray
    block: int
    frame_indices: np.ndarray | None = None
    skipped: dict[str, int] = field(default_factory=dict)
    source: str = ""
    response_table: np.ndarray | None = None
    _cache: dict = field(default_factory=dict, repr=False, compare=False)

    # ---------------------------------------------------------------- basic properties
    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.count.shape)  # type: ignore[return-value]

    @property
    def resolution(self) -> tuple[int, int]:
        return self.count.shape[1], self.count.shape[0]

    @property
    def channels(self) -> int:
        return int(self.count.shape[2])

    @property
    def frames_used(self) -> int:
        return int(self.cell_sums.shape[0])

    def indices(self) -> np.ndarray:
        """Position of each used frame in the source, int64 ``(T,)`` (``0..T-1`` when unknown)."""
        if self.frame_indices is None:
            return np.arange(self.frames_used, dtype=np.int64)
        return np.asarray(self.frame_indices, dtype=np.int64)

    @property
    def frames_skipped(self) -> int:
        return int(sum(self.skipped.values()))

    @property
    def response(self) -> CameraResponse | None:
        return None if self.response_table is None else CameraResponse(self.response_table)

    def coverage(self) -> np.ndarray:
        """Samples per pixel (the minimum over channels), int32 ``(H, W)``."""
        return self.count.min(axis=2)

    def coverage_report(self, min_samples: int = 20) -> CoverageReport:
        if min_samples < 1:
            raise ValueError(f"min_samples must be at least 1, got {min_samples}")
        cov = self.coverage()
        below = cov < min_samples
        h, w = cov.shape
        ys = [0, h // 3, h - h // 3, h]
        xs = [0, w // 3, w - w // 3, w]
        regions = {}
        for i in range(3):
            for j in range(3):
                cell = below[ys[i]:ys[i + 1], xs[j]:xs[j + 1]]
                regions[REGIONS[3 * i + j]] = float(cell.mean()) if cell.size else 0.0
        return CoverageReport(int(min_samples), float(below.mean()), regions, int(cov.min()), float(np.median(cov)))

    def mean(self) -> np.ndarray:
        """Plain per-pixel mean irradiance (no drift correction), NaN where unobserved, float64."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(self.count > 0, self.sum / np.maximum(self.count, 1), np.nan)

    def std(self) -> np.ndarray:
        """Per-pixel standard deviation of the samples (NaN with fewer than 2 samples)."""
        n = np.maximum(self.count, 1)
        var = np.maximum(self.sumsq / n - (self.sum / n) ** 2, 0.0) * n / np.maximum(n - 1, 1)
        return np.where(self.count > 1, np.sqrt(var), np.nan)

    # ---------------------------------------------------------------- drift
    def frame_scales(self) -> np.ndarray:
        """Per-frame, per-channel brightness scales ``s_t`` (``(T, C)``, geometric mean 1), cached."""
        if "scales" not in self._cache:
            self._cache["scales"] = estimate_frame_scales(self.cell_sums, self.cell_counts)
        return self._cache["scales"]

    def scale_map(self) -> np.ndarray:
        """The mean scale of the frames that observed each pixel, float64 ``(H, W, C)`` (interpolated
        bilinearly from the cells)."""
        if "scale_map" not in self._cache:
            import cv2

            s = self.frame_scales()  # (T, C)
            counts = self.cell_counts.astype(np.float64)  # (T, gh, gw, C)
            num = np.einsum("tijc,tc->ijc", counts, s)
            den = counts.sum(axis=0)
            cell = np.where(den > 0, num / np.maximum(den, 1e-12), np.nan)
            cell = _fill_nan_cells(cell)
            b = self.block
            gh, gw, ch = cell.shape
            up = cv2.resize(cell.astype(np.float32), (gw * b, gh * b), interpolation=cv2.INTER_LINEAR)
            up = up.reshape(gh * b, gw * b, ch)[: self.shape[0], : self.shape[1]]
            self._cache["scale_map"] = up.astype(np.float64)
        return self._cache["scale_map"]

    def flat(self, *, joint_scale: bool = True) -> np.ndarray:
        """The per-pixel mean irradiance of the sheet (up to a constant), NaN where unobserved.

        ``joint_scale=True`` divides out the per-frame brightness drift (``mean / scale_map``)."""
        m = self.mean()
        if joint_scale and self.frames_used > 1:
            m = m / self.scale_map()
        return m

    # ---------------------------------------------------------------- persistence
    def save(self, path: str | os.PathLike) -> Path:
        """Write the accumulation (``.npz``, radiomap model format) so that sessions can be fitted and
        compared later (repeatability)."""
        arrays = {"count": self.count, "sum": self.sum, "sumsq": self.sumsq, "cell_sums": self.cell_sums,
                  "cell_counts": self.cell_counts, "frame_indices": self.indices()}
        if self.response_table is not None:
            arrays["response_table"] = self.response_table
        return save_model_file(path, ACCUMULATION_KIND, arrays,
                               {"block": self.block, "skipped": self.skipped, "source": self.source})

    @classmethod
    def load(cls, path: str | os.PathLike) -> "VignettingAccumulation":
        meta, arrays = read_model_file(path, ACCUMULATION_KIND)
        try:
            acc = cls(count=arrays["count"].astype(np.int32), sum=arrays["sum"].astype(np.float64),
                      sumsq=arrays["sumsq"].astype(np.float64), cell_sums=arrays["cell_sums"].astype(np.float32),
                      cell_counts=arrays["cell_counts"].astype(np.uint16), block=int(meta["block"]),
                      frame_indices=arrays.get("frame_indices"),
                      skipped={str(k): int(v) for k, v in dict(meta.get("skipped", {})).items()},
                      source=str(meta.get("source", "")), response_table=arrays.get("response_table"))
        except (KeyError, TypeError, ValueError, OverflowError, AttributeError) as exc:
            raise CalibrationFileError(f"{path}: incomplete vignetting accumulation ({exc}); re-collect it") from None
        if acc.sum.shape != acc.count.shape or acc.sumsq.shape != acc.count.shape or acc.count.ndim != 3:
            raise CalibrationFileError(f"{path}: inconsistent array shapes; re-collect the accumulation")
        h, w, ch = acc.count.shape
        grid = (-(-h // acc.block), -(-w // acc.block)) if 1 <= acc.block <= 255 else None
        frames = acc.cell_sums.shape[0] if acc.cell_sums.ndim == 4 else -1
        try:
            indices = acc.indices()
        except (TypeError, ValueError, OverflowError):
            indices = None
        if (ch not in (1, 3) or grid is None or acc.cell_sums.shape != (frames, *grid, ch)
                or acc.cell_counts.shape != acc.cell_sums.shape or indices is None or indices.shape != (frames,)
                or np.any(acc.count < 0) or not np.all(np.isfinite(acc.sum)) or not np.all(np.isfinite(acc.sumsq))
                or not np.all(np.isfinite(acc.cell_sums))):
            raise CalibrationFileError(f"{path}: inconsistent or non-finite accumulation arrays (block {acc.block}, "
                                       f"count {acc.count.shape}, cells {acc.cell_sums.shape}); re-collect it")
        if acc.response_table is not None:
            validate_inverse_table(acc.response_table, source=str(path))
        return acc


def _fill_nan_cells(cell: np.ndarray, iterations: int = 64) -> np.ndarray:
    """Fill NaN cells by repeatedly averaging valid 4-neighbours; any left over get the global mean."""
    import warnings

    out = cell.copy()
    for _ in range(iterations):
        nan = np.isnan(out)
        if not nan.any():
            break
        padded = np.pad(out, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
        neigh = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN neighbourhoods
            avg = np.nanmean(neigh, axis=0)
        grow = nan & ~np.isnan(avg)
        if not grow.any():
            break
        out[grow] = avg[grow]
    if np.isnan(out).any():
        fill = np.ones(out.shape[2]) if np.isnan(out).all() else np.nanmean(out, axis=(0, 1))
        out = np.where(np.isnan(out), np.broadcast_to(np.nan_to_num(fill, nan=1.0), out.shape), out)
    return out


def estimate_frame_scales(cell_sums: np.ndarray, cell_counts: np.ndarray, *, robust_rounds: int = 3,
                          min_fill: float = 0.5) -> np.ndarray:
    """Per-frame brightness scales ``s_t`` jointly with the (cell-level) vignetting, per channel.

    Model ``log m_tb = a_t + v_b`` with ``m_tb`` the mean irradiance of frame ``t`` in cell ``b`` (cells
    at least ``min_fill`` full), weights the cell counts. Alternating ``v`` and ``a`` (the textbook
    scheme) converges to the least-squares solution; we eliminate ``v`` and solve the ``T x T`` system
    for ``a`` directly (plus a tiny ridge for frames that share no cell with another), then re-weight
    with Tukey's biweight for ``robust_rounds`` rounds. Returns ``(T, C)`` with geometric mean 1.
    """
    sums = np.asarray(cell_sums, dtype=np.float64)
    counts = np.asarray(cell_counts, dtype=np.float64)
    n_frames = sums.shape[0]
    channels = sums.shape[-1]
    if n_frames == 0:
        return np.ones((0, channels))
    full = counts.reshape(n_frames, -1, channels).max(axis=(0, 1))  # pixels in a full cell, per channel
    scales = np.ones((n_frames, channels))
    for c in range(channels):
        s = sums[..., c].reshape(n_frames, -1)
        n = counts[..., c].reshape(n_frames, -1)
        ok = (n >= max(1.0, min_fill * full[c])) & (s > 0)
        cols = np.flatnonzero(ok.any(axis=0))
        if cols.size == 0:
            continue
        ok = ok[:, cols]
        y = np.where(ok, np.log(np.where(ok, s[:, cols], 1.0) / np.maximum(n[:, cols], 1.0)), 0.0)
        w0 = np.where(ok, n[:, cols], 0.0)
        w = w0.copy()
        a = np.zeros(n_frames)
        for round_ in range(robust_rounds + 1):
            a = _solve_log_scales(y, w)
            if round_ == robust_rounds:
                break
            wb = w.sum(axis=0)
            v = (w * (y - a[:, None])).sum(axis=0) / np.maximum(wb, 1e-12)
            res = np.where(ok, y - a[:, None] - v[None, :], 0.0)
            sigma = 1.4826 * np.median(np.abs(res[ok])) + 1e-9
            u = res / (4.685 * sigma)
            w = w0 * np.where(np.abs(u) < 1.0, (1.0 - u ** 2) ** 2, 0.0)
        scales[:, c] = np.exp(a - a.mean())
    return scales


def _solve_log_scales(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares for ``y_tb = a_t + v_b``: eliminate ``v`` (Schur complement) and solve for
    ``a`` with the gauge ``mean(a) = 0``."""
    wb = w.sum(axis=0)
    inv = np.where(wb > 0, 1.0 / np.maximum(wb, 1e-300), 0.0)
    wt = w.sum(axis=1)
    matrix = np.diag(wt) - (w * inv[None, :]) @ w.T
    rhs = (w * y).sum(axis=1) - (w * inv[None, :]) @ (w * y).sum(axis=0)
    n = matrix.shape[0]
    ridge = 1e-9 * max(float(np.mean(wt)), 1e-12)
    matrix = matrix + ridge * np.eye(n) + np.full((n, n), float(np.mean(wt)) / n)  # gauge: sum(a) = 0
    try:
        a = np.linalg.solve(matrix, rhs)
    except np.linalg.LinAlgError:
        a = np.linalg.lstsq(matrix, rhs, rcond=None)[0]
    return a - a.mean()


# ==================================================================================================
# collection
# ==================================================================================================
def collect_vignetting(source: Any, response: CameraResponse, *, min_samples: int | None = None,
                       stop_when_covered: bool = False, max_frames: int | None = None, block: int | None = None,
                       saturation: int = 250, dark: int = 20, progress: bool = True,
                       **detect_options: Any) -> VignettingAccumulation:
    """Segment the sheet in every frame of ``source`` and accumulate it in irradiance.

    ``source``: anything :func:`open_frames` takes. ``min_samples`` with ``stop_when_covered`` stops as
    soon as every pixel has that many samples. Raises :class:`CalibrationError` (with the fix) when no
    frame is usable: all saturated (the clipped flat-field case), too dark, or no sheet found. ``progress``:
    a progress bar on stderr when it is a terminal (:func:`radiometry.progress.progress_bar`).
    """
    if not isinstance(response, CameraResponse):
        raise TypeError(f"response must be a CameraResponse, got {type(response).__name__}")
    if min_samples is not None and min_samples < 1:
        raise ValueError(f"min_samples must be at least 1, got {min_samples}")
    if stop_when_covered and min_samples is None:
        raise ValueError("stop_when_covered needs min_samples")
    if max_frames is not None and max_frames < 1:
        raise ValueError(f"max_frames must be positive, got {max_frames}")
    frames = open_frames(source, max_frames=max_frames)
    from radiometry.progress import progress_bar

    acc: VignettingAccumulator | None = None
    skipped: Counter[str] = Counter()
    sizes: Counter[str] = Counter()      # frames per size ("WxH" or "WxH grey"): the first frame's must prevail
    first_size = ""
    seed: tuple[int, int] | None = None
    n_seen = 0
    total = frames.length if max_frames is None or frames.length is None else min(frames.length, max_frames)
    bar = progress_bar(frames, total=total, desc="vignetting frames", enabled=progress, leave=False)
    try:
        for frame in bar:
            if max_frames is not None and n_seen >= max_frames:
                break
            n_seen += 1
            frame = np.asarray(frame)
            if frame.dtype != np.uint8:
                raise ImageError(f"{frames.name}: frame {n_seen - 1} is {frame.dtype}; vignetting calibration "
                                 "needs 8-bit frames")
            if frame.ndim == 3 and frame.shape[2] == 1:
                frame = frame[:, :, 0]
            sizes[_size_text(frame)] += 1
            if acc is None:
                first_size = _size_text(frame)
                ch = 1 if frame.ndim == 2 else frame.shape[2]
                acc = VignettingAccumulator(frame.shape[0], frame.shape[1], ch, response, block=block,
                                            saturation=saturation)
            elif frame.shape[:2] != acc.shape[:2] or (frame.ndim == 2) != (acc.shape[2] == 1):
                skipped["different size"] += 1
                continue
            det = detect_sheet(frame, seed, saturation=saturation, dark=dark, **detect_options)
            if not det.ok:
                skipped[det.status] += 1
                log.debug("frame %d skipped: %s", n_seen - 1, det.status)
                continue
            acc.add(frame, det.mask, index=n_seen - 1)
            seed = det.centre
            if stop_when_covered and acc.covered(min_samples):  # type: ignore[arg-type]
                log.info("every pixel has %d samples after %d frames; stopping", min_samples, n_seen)
                break
    finally:
        bar.close()
    if acc is None:
        raise CalibrationError(f"{frames.name}: no frames; record a sweep over a white sheet")
    if len(sizes) > 1:
        _check_sizes(frames.name, sizes, first_size)
    if acc.frames == 0:
        raise CalibrationError(_no_frames_message(frames.name, n_seen, skipped, saturation))
    if too_little(acc.frames, n_seen):
        reasons = ", ".join(f"{k}: {v}" for k, v in skipped.most_common())
        raise CalibrationError(
            f"{frames.name}: a sheet was found in only {acc.frames} of {n_seen} frames ({reasons}); a model needs "
            f"{rule_text()}, so these are not a white-sheet sweep; {_SWEEP_FIX}")
    if skipped.get("saturated", 0) > acc.frames:
        log.warning("%d of %d frames were skipped as saturated; lowering the exposure would use them",
                    skipped["saturated"], n_seen)
    result = acc.result(skipped=dict(skipped), source=frames.name)
    log.info("vignetting data: %d frames used, %d skipped %s", result.frames_used, result.frames_skipped,
             dict(skipped))
    return result


#: the largest LUT denoising (pixels): beyond it the "fine" residual is a constant and OpenCV's kernel overflows
MAX_SMOOTH_SIGMA = 50.0
#: a model is fitted only when the sheet was seen at this fraction of the image at least (simulated sweeps of
#: 30-40 frames: 100 %; ordinary room frames where a plain wall passed for a sheet: 15 %)
MIN_OBSERVED_FRACTION = 0.5
_SWEEP_FIX = ("point the camera at an evenly lit white sheet that fills a good part of the view, on a darker "
              "background, and sweep it across the whole image")


def _size_text(frame: np.ndarray) -> str:
    return f"{frame.shape[1]}x{frame.shape[0]}" + (" grey" if frame.ndim == 2 else "")


def _check_sizes(name: str, sizes: Counter, first: str) -> None:
    """Frames of another size than the first are skipped; when they outnumber the first frame's size, the first
    frame was the odd one and the model would rest on the few: refuse with the counts."""
    listing = ", ".join(f"{n} at {size}" for size, n in sizes.most_common())
    if sizes[first] < max(n for size, n in sizes.items() if size != first):
        raise CalibrationError(f"{name}: the frames have different sizes ({listing}); the first frame's size "
                               f"({first}) is the rarer one; remove the frames of other sizes, or record the sweep at "
                               "one resolution")
    log.warning("%s: skipped %d frames of another size than the first (%s)", name,
                sum(sizes.values()) - sizes[first], listing)


def _no_frames_message(name: str, n_seen: int, skipped: Counter, saturation: int) -> str:
    reason, count = skipped.most_common(1)[0] if skipped else ("no sheet", n_seen)
    if reason == "saturated":
        return (f"{name}: the frames are saturated: the sheet is clipped (>= {saturation}) in {count} of {n_seen} "
                "frames, so they cannot measure vignetting; lower the exposure time (or the light) until the "
                "brightest part of the sheet stays below 250, and record again")
    if reason == "too dark":
        return (f"{name}: the sheet is too dark in {count} of {n_seen} frames; raise the exposure or the light "
                "(the sheet's centre should be around 150-220) and record again")
    if reason == "textured":
        return (f"{name}: the view is textured or noisy, not a plain sheet, in {count} of {n_seen} frames; point "
                "the camera at an evenly lit plain white sheet (matte paper, no print) and record again")
    if reason == "low contrast":
        return (f"{name}: the plain region found is hardly brighter than its surroundings in {count} of {n_seen} "
                f"frames (a wall or a table, not a white sheet on a darker background); {_SWEEP_FIX}")
    if reason == "different size":
        return f"{name}: the frames have different sizes; record the sweep at one resolution"
    return f"{name}: no white sheet found in any of the {n_seen} frames ({dict(skipped)}); {_SWEEP_FIX}"


# ==================================================================================================
# fits
# ==================================================================================================
def _observed(acc: VignettingAccumulation, joint_scale: bool, min_samples: int) -> tuple[np.ndarray, np.ndarray]:
    flat = acc.flat(joint_scale=joint_scale)
    weights = np.where(acc.count >= min_samples, acc.count, 0).astype(np.float64)
    flat = np.where(weights > 0, flat, np.nan)
    return flat, weights


def _poly_design(r2: np.ndarray) -> np.ndarray:
    return np.stack([np.ones_like(r2), r2, r2 ** 2, r2 ** 3], axis=1)


def _fit_channel_poly(xs: np.ndarray, ys: np.ndarray, d: np.ndarray, w: np.ndarray, resolution: tuple[int, int],
                      free: bool) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Fit ``d = s (1 + b1 r^2 + b2 r^4 + b3 r^6)`` to samples; returns ``s, b, centre, rms``."""
    from scipy.optimize import least_squares

    width, height = resolution
    radius = half_diagonal(resolution)
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    sw = np.sqrt(w)
    r2 = ((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / radius ** 2
    design = _poly_design(r2) * sw[:, None]
    coef, *_ = np.linalg.lstsq(design, d * sw, rcond=None)
    s = float(coef[0])
    if not s > 0:
        raise CalibrationError("the fitted vignetting is not positive at the image centre; the data do not look "
                               "like a flat field (check the response and the frames)")
    b = coef[1:] / s
    if free:
        # parameters: centre in units of R (well scaled), overall scale, b1..b3
        def residual(p):
            cx, cy, s_, b1, b2, b3 = p
            rr = ((xs - cx * radius) ** 2 + (ys - cy * radius) ** 2) / radius ** 2
            return sw * (d - s_ * (1.0 + rr * (b1 + rr * (b2 + rr * b3))))

        def jacobian(p):
            cx, cy, s_, b1, b2, b3 = p
            dx, dy = xs - cx * radius, ys - cy * radius
            rr = (dx * dx + dy * dy) / radius ** 2
            dp = b1 + rr * (2.0 * b2 + 3.0 * rr * b3)  # dP/d(rr)
            jac = np.empty((xs.size, 6))
            jac[:, 0] = sw * s_ * dp * (2.0 * dx / radius)
            jac[:, 1] = sw * s_ * dp * (2.0 * dy / radius)
            jac[:, 2] = -sw * (1.0 + rr * (b1 + rr * (b2 + rr * b3)))
            jac[:, 3] = -sw * s_ * rr
            jac[:, 4] = -sw * s_ * rr ** 2
            jac[:, 5] = -sw * s_ * rr ** 3
            return jac

        p0 = np.array([centre[0] / radius, centre[1] / radius, s, *b])
        sol = least_squares(residual, p0, jac=jacobian, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12,
                            max_nfev=2000)
        cx, cy, s, b1, b2, b3 = sol.x
        centre = np.array([cx * radius, cy * radius])
        b = np.array([b1, b2, b3])
        if not (-0.5 <= centre[0] <= width - 0.5 and -0.5 <= centre[1] <= height - 0.5) or not s > 0:
            raise CalibrationError(
                f"the free-centre fit put the optical centre at ({centre[0]:.1f}, {centre[1]:.1f}), outside the "
                f"{width}x{height} image: the data do not constrain it; cover the image more evenly or use "
                "--model poly-fixed-center")
        r2 = ((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / radius ** 2
    pred = s * (1.0 + r2 * (b[0] + r2 * (b[1] + r2 * b[2])))
    rms = float(np.sqrt(np.sum(w * (d - pred) ** 2) / np.sum(w)) / s)
    return float(s), np.asarray(b, dtype=np.float64), centre, rms


def fit_vignetting_polynomial(accumulation: VignettingAccumulation, *, fixed_centre: bool = False,
                              joint_scale: bool = True, min_samples: int = 1,
                              max_points: int = 200_000) -> PolynomialVignetting:
    """Polynomial model per channel, ``V = s_c (1 + b1 r^2 + b2 r^4 + b3 r^6)``, stored normalised (``V = 1``
    at its centre; ``s_c`` kept in ``info["fit_scale"]``).

    ``fixed_centre=True``: centre at the image centre, linear least squares weighted by the sample counts.
    ``fixed_centre=False``: centre free, Levenberg-Marquardt (``scipy.optimize.least_squares(method="lm")``)
    initialised from the fixed-centre fit. At most ``max_points`` pixels (a regular subsample) are used.
    """
    acc = accumulation
    flat, weights = _observed(acc, joint_scale, min_samples)
    h, w, ch = acc.shape
    step = max(1, int(np.ceil(np.sqrt(h * w / max_points))))
    yy, xx = np.mgrid[0:h:step, 0:w:step]
    coeffs, centres, scales, rms = [], [], [], []
    for c in range(ch):
        d = flat[::step, ::step, c]
        wt = weights[::step, ::step, c]
        sel = (wt > 0) & np.isfinite(d)
        if np.count_nonzero(sel) < 50:
            raise CalibrationError(f"channel {c}: only {np.count_nonzero(sel)} observed pixels; record a longer sweep")
        s, b, centre, err = _fit_channel_poly(xx[sel].astype(np.float64), yy[sel].astype(np.float64), d[sel],
                                              wt[sel], acc.resolution, free=not fixed_centre)
        coeffs.append(b)
        centres.append(centre)
        scales.append(s)
        rms.append(err)
    info = {"method": "poly-fixed-center" if fixed_centre else "poly", "joint_scale": bool(joint_scale),
            "fit_scale": scales, "fit_rms_relative": rms, "frames_used": acc.frames_used,
            "frames_skipped": acc.skipped, "source": acc.source}
    try:
        return PolynomialVignetting(np.array(coeffs), np.array(centres), acc.resolution, info=info)
    except ValueError as exc:
        raise CalibrationError(f"the fitted polynomial is not a valid vignetting ({exc}); the corners are probably "
                               "not covered: sweep the sheet into the corners, or use --model lut") from None


def fit_vignetting_lut(accumulation: VignettingAccumulation, *, joint_scale: bool = True, min_samples: int = 1,
                       smooth_sigma: float = 1.0) -> LUTVignetting:
    """Per-pixel, per-channel LUT: the session's (drift-corrected) mean flat, normalised and denoised.

    The flat ``D`` is factored as ``P(x) * q(x)`` with ``P`` a free-centre polynomial fit of the same data
    (fixed-centre if the free fit fails) and ``q = D / P`` what no radial model explains (the non-radial
    part and the noise). Then:

    - Denoising: ``q`` is averaged with count-weighted Gaussian weights of ``smooth_sigma`` pixels (``0``
      disables it). Smoothing ``q`` rather than ``D`` keeps the steep radial fall-off out of the average,
      so image borders and the edges of unobserved regions are not biased.
    - Unobserved pixels (fewer than ``min_samples`` samples) get ``P`` times ``q`` faded to 1 away from
      the observed region: never zero or NaN, and no seam. Pixels with only a few samples are pulled
      towards the local trend of ``q`` (with the weight of 3 samples), so a thinly covered corner does not
      carry single-frame noise into the LUT.
    - Normalisation: divided by the maximum of ``P * q_coarse`` (``q`` smoothed over 1 % of the image
      diagonal), so that one noisy pixel cannot set the scale; ``V`` is ~1 at the optical centre.
    """
    import cv2

    if smooth_sigma < 0:
        raise ValueError(f"smooth_sigma must be >= 0, got {smooth_sigma}")
    if not smooth_sigma <= MAX_SMOOTH_SIGMA:  # also NaN; OpenCV's Gaussian fails on huge kernels
        raise ValueError(f"smooth_sigma must be at most {MAX_SMOOTH_SIGMA:g} pixels, got {smooth_sigma}")
    acc = accumulation
    flat, weights = _observed(acc, joint_scale, min_samples)
    h, w, ch = acc.shape
    observed = weights > 0
    if observed.mean() < 0.05:
        raise CalibrationError(f"only {100 * observed.mean():.1f}% of the image was observed; sweep the sheet over "
                               "the whole image")
    try:
        poly = fit_vignetting_polynomial(acc, joint_scale=joint_scale, min_samples=min_samples)
    except CalibrationError:
        poly = fit_vignetting_polynomial(acc, fixed_centre=True, joint_scale=joint_scale, min_samples=min_samples)
    base = poly.evaluate(h, w).astype(np.float64) * np.asarray(poly.info["fit_scale"])[None, None, :]
    ratio = np.where(observed, flat / base, 0.0)
    big_sigma = 0.01 * float(np.hypot(h, w))

    def blur(a: np.ndarray, sigma: float) -> np.ndarray:
        if sigma <= 0:
            return a
        out = cv2.GaussianBlur(a.astype(np.float64), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return out.reshape(a.shape)

    with np.errstate(invalid="ignore", divide="ignore"):
        wc = blur(weights, big_sigma)
        coarse = blur(ratio * weights, big_sigma) / wc
        # away from the data the residual fades to 1 (the polynomial alone), with the weight of a tenth of
        # the typical pixel's samples
        prior = 0.1 * float(np.median(weights[observed]))
        faded = (blur(ratio * weights, big_sigma) + prior) / (wc + prior)
        # a pixel with few samples is pulled towards the local trend (the weight of `shrink` samples)
        shrink = 3.0
        trend = np.where(observed, coarse, faded)
        fine = (blur(ratio * weights, smooth_sigma) + shrink * trend) / (blur(weights, smooth_sigma) + shrink)
    q = np.where(observed, fine, faded)
    q_coarse = np.where(observed, coarse, faded)
    norm = np.array([float(np.max((base * q_coarse)[:, :, c][observed[:, :, c]])) for c in range(ch)])
    lut = base * q / norm
    lut = np.maximum(lut, 1e-3)
    info = {"method": "lut", "joint_scale": bool(joint_scale), "smooth_sigma": float(smooth_sigma),
            "filled_fraction": float(1.0 - observed.all(axis=2).mean()), "frames_used": acc.frames_used,
            "frames_skipped": acc.skipped, "source": acc.source, "base": poly.info["method"]}
    return LUTVignetting(lut.astype(np.float32), info=info)


MODELS = {
    "lut": lambda acc, **kw: fit_vignetting_lut(acc, **kw),
    "poly": lambda acc, **kw: fit_vignetting_polynomial(acc, fixed_centre=False, **kw),
    "poly-fixed-center": lambda acc, **kw: fit_vignetting_polynomial(acc, fixed_centre=True, **kw),
}


def fit_vignetting(accumulation: VignettingAccumulation, *, model: str = "lut", **options: Any) -> VignettingModel:
    """Fit a vignetting model: ``model`` is ``"lut"``, ``"poly"`` (free centre) or ``"poly-fixed-center"``;
    ``options`` go to the method (``joint_scale``, ``min_samples``, ...)."""
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    observed = float(np.mean(accumulation.count.max(axis=2) > 0))
    if observed < MIN_OBSERVED_FRACTION:  # the rest of V would be extrapolated from a corner of the image
        raise CalibrationError(
            f"{accumulation.source or 'the sweep'}: the sheet was seen at only {observed:.0%} of the image in "
            f"{accumulation.frames_used} frames; a model needs it swept over at least {MIN_OBSERVED_FRACTION:.0%} "
            f"(the rest would be guessed); {_SWEEP_FIX}")
    return MODELS[model](accumulation, **options)


def calibrate_vignetting(source: Any, response: CameraResponse, *, model: str = "lut", fit_options: dict | None = None,
                         **collect_options: Any) -> tuple[VignettingModel, VignettingAccumulation]:
    """Collect and fit in one call; returns the model and the accumulation (for reports and plots)."""
    if model not in MODELS:
        raise ValueError(f"model must be one of {', '.join(MODELS)}, got {model!r}")
    acc = collect_vignetting(source, response, **collect_options)
    return fit_vignetting(acc, model=model, **(fit_options or {})), acc


# ==================================================================================================
# evaluation in 8-bit levels
# ==================================================================================================
def vignetting_error_levels(estimate: np.ndarray | VignettingModel, truth: np.ndarray, response: CameraResponse, *,
                            level: float = 200.0, mask: np.ndarray | None = None) -> np.ndarray:
    """RMS error of an estimated ``V`` against the true one, in 8-bit intensity levels, per channel.

    A flat field whose centre (``V = 1``) images at ``level`` is observed as ``f(f^-1(level) V_true(x))``;
    the estimate predicts ``f(a f^-1(level) V_est(x))``, with ``a`` the median of ``V_true / V_est`` (the
    global scale of ``V`` is absorbed by exposure, so it is not counted). Returns the RMS over pixels
    (or over ``mask``) of the difference of the two, float64 ``(C,)``.
    """
    truth = np.asarray(truth, dtype=np.float64)
    if truth.ndim == 2:
        truth = truth[:, :, None]
    est = estimate.evaluate(truth.shape[0], truth.shape[1]) if isinstance(estimate, VignettingModel) else estimate
    est = np.asarray(est, dtype=np.float64)
    if est.ndim == 2:
        est = est[:, :, None]
    if est.shape[:2] != truth.shape[:2]:
        raise ValueError(f"estimate {est.shape} and truth {truth.shape} must have the same size")
    channels = max(est.shape[2], truth.shape[2])
    est = np.broadcast_to(est, (*truth.shape[:2], channels))
    truth = np.broadcast_to(truth, est.shape)
    sel = np.ones(truth.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    tables = response.channel_tables(channels).astype(np.float64)
    out = np.empty(channels)
    for c in range(channels):
        t, e = truth[:, :, c][sel], est[:, :, c][sel]
        a = float(np.median(t / e))
        base = float(np.interp(level, np.arange(256.0), tables[:, c]))
        obs = np.interp(base * t, tables[:, c], np.arange(256.0))
        pred = np.interp(a * base * e, tables[:, c], np.arange(256.0))
        out[c] = float(np.sqrt(np.mean((pred - obs) ** 2)))
    return out


def flat_rms_levels(model: VignettingModel, accumulation: VignettingAccumulation,
                    response: CameraResponse | None = None, *, joint_scale: bool = True,
                    min_samples: int = 1) -> np.ndarray:
    """How well ``model`` explains a session's mean flat image, in 8-bit levels, per channel.

    The observed flat is ``O(x) = f(E(x))`` with ``E`` the session's (drift-corrected) mean irradiance;
    the model predicts ``P(x) = f(a V(x))`` with ``a`` the median of ``E / V`` (the flat's brightness).
    Returns the RMS of ``P - O`` over pixels with at least ``min_samples`` samples (``(C,)``). With the
    model fitted on the same session this is the fit residual; on another session it is the paper's
    repeatability error (Fig. 6).
    """
    response = response or accumulation.response
    if response is None:
        raise ValueError("pass the response: the accumulation does not carry one")
    flat, weights = _observed(accumulation, joint_scale, min_samples)
    h, w, ch = accumulation.shape
    v = model.evaluate(h, w).astype(np.float64)
    v = np.broadcast_to(v, (h, w, ch))
    tables = response.channel_tables(ch).astype(np.float64)
    levels = np.arange(256.0)
    out = np.empty(ch)
    for c in range(ch):
        sel = (weights[:, :, c] > 0) & np.isfinite(flat[:, :, c])
        e, vv = flat[:, :, c][sel], v[:, :, c][sel]
        if e.size == 0:
            out[c] = np.nan
            continue
        a = float(np.median(e / vv))
        obs = np.interp(e, tables[:, c], levels)
        pred = np.interp(a * vv, tables[:, c], levels)
        out[c] = float(np.sqrt(np.mean((pred - obs) ** 2)))
    return out


def repeatability(accumulations: Sequence[VignettingAccumulation], response: CameraResponse, *,
                  models: Sequence[str] = ("poly", "poly-fixed-center", "lut"),
                  fit_options: dict | None = None) -> dict[str, np.ndarray]:
    """The paper's repeatability experiment (Fig. 6): fit each model on each of K sessions and measure
    :func:`flat_rms_levels` against each of the other K - 1.

    Returns ``{model: errors}`` with ``errors`` float64 ``(K * (K - 1), C)`` in 8-bit levels.
    """
    k = len(accumulations)
    if k < 2:
        raise ValueError(f"repeatability needs at least 2 sessions, got {k}")
    for name in models:
        if name not in MODELS:
            raise ValueError(f"model must be one of {', '.join(MODELS)}, got {name!r}")
    results: dict[str, list[np.ndarray]] = {name: [] for name in models}
    for i, acc in enumerate(accumulations):
        for name in models:
            model = fit_vignetting(acc, model=name, **(fit_options or {}))
            for j, other in enumerate(accumulations):
                if j != i:
                    results[name].append(flat_rms_levels(model, other, response))
    return {name: np.array(errs) for name, errs in results.items()}


__all__ = [
    "FrameSource", "FolderFrames", "VideoFrames", "CameraFrames", "ArrayFrames", "open_frames",
    "SheetDetection", "detect_sheet", "VignettingAccumulator", "VignettingAccumulation", "CoverageReport",
    "estimate_frame_scales", "collect_vignetting", "fit_vignetting", "fit_vignetting_lut",
    "fit_vignetting_polynomial", "calibrate_vignetting", "vignetting_error_levels", "flat_rms_levels",
    "repeatability", "MODELS",
]
