"""Accumulation of sheet pixels in irradiance (step 2 of :mod:`radiometry.vignetting_calibration`): per pixel
and channel count, sum and sum of squares, plus each frame's cell sums for its drift scale; the session's
result (:class:`VignettingAccumulation`, saved and loaded as a radiomap model file) and its coverage report."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.fileio import save_model_file
from radiometry.response import CameraResponse, validate_inverse_table
from radiometry.vignetting import read_model_file
from radiometry.vignetting_calibration.scales import estimate_frame_scales, fill_nan_cells
from radiometry.vignetting_calibration.uncertainty import response_log_stderr

ACCUMULATION_KIND = "vignetting_accumulation"
REGIONS = ("top-left", "top", "top-right", "left", "centre", "right", "bottom-left", "bottom", "bottom-right")


def default_block(height: int, width: int, max_cells: int = 1200) -> int:
    """Cell size of the per-frame compact representation: at most ``max_cells`` cells per frame."""
    return max(1, int(np.ceil(np.sqrt(height * width / max_cells))))


def extrapolated_mask(response: CameraResponse, channels: int) -> np.ndarray:
    """Per level and channel (bool ``(256, C)``), False where the response says its value was extrapolated, not
    estimated from data (``meta["extrapolated_levels"]``, one list per channel, as the Engel and OpenCV fits record
    it): a sample at such a level would carry the guess into ``V``, so it is not accumulated."""
    keep = np.ones((256, channels), dtype=bool)
    lists = response.meta.get("extrapolated_levels")
    if not isinstance(lists, (list, tuple)) or not lists or not all(isinstance(v, (list, tuple)) for v in lists):
        return keep
    for c in range(channels):
        for level in lists[min(c, len(lists) - 1)]:
            if isinstance(level, (int, np.integer)) and 0 <= level < 256:
                keep[int(level), c] = False
    return keep


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
        usable = ((levels < self.saturation) & (levels > self.dark))[:, None] & extrapolated_mask(response, channels)
        self._table = np.ascontiguousarray(np.where(usable, self._lut, np.nan).T)  # (C, 256)
        self.count = np.zeros(self.shape, np.int32)
        self.sum = np.zeros(self.shape, np.float64)
        self.sumsq = np.zeros(self.shape, np.float64)
        # the odd frames (2nd, 4th, ...) again on their own: the two halves of the sweep, for the split-half figure
        self.odd_count = np.zeros(self.shape, np.int32)
        self.odd_sum = np.zeros(self.shape, np.float64)
        self.odd_sumsq = np.zeros(self.shape, np.float64)
        # the sheet's raw levels per channel (every masked pixel): a channel piling up below 255 is clipped
        self.level_hist = np.zeros((channels, 256), np.int64)
        self.grid = (-(-height // self.block), -(-width // self.block))
        self._cell_sums: list[np.ndarray] = []
        self._cell_counts: list[np.ndarray] = []
        self._indices: list[int] = []

    @property
    def frames(self) -> int:
        return len(self._cell_sums)

    def add(self, image: np.ndarray, mask: np.ndarray, *, index: int | None = None,
            sheet: np.ndarray | None = None) -> int:
        """Add one frame's sheet pixels (``mask``); ``index`` is its position in the source (default: the
        count of frames added so far); ``sheet``: the whole detected sheet, for the level histogram (default
        ``mask``). Returns the number of pixel-channel samples added."""
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
        img, mask = np.ascontiguousarray(img), np.ascontiguousarray(mask)
        added = _accumulate_kernel()(img, mask, self._table, self.block, self.sum, self.sumsq, self.count, cell_sum,
                                     cell_cnt)
        if self.frames % 2 == 1:
            _accumulate_kernel()(img, mask, self._table, self.block, self.odd_sum, self.odd_sumsq, self.odd_count,
                                 np.zeros_like(cell_sum), np.zeros_like(cell_cnt))
        levels = img[mask if sheet is None else np.asarray(sheet, dtype=bool)]
        for c in range(self.shape[2]):
            self.level_hist[c] += np.bincount(levels[:, c], minlength=256)
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
                                      response_table=self.response.inverse_table.copy(),
                                      response_stderr=response_log_stderr(self.response, ch),
                                      response_method=str(self.response.meta.get("method", "")),
                                      odd=(self.odd_count.copy(), self.odd_sum.copy(), self.odd_sumsq.copy()),
                                      level_hist=self.level_hist.copy())


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
    """The fused data of one calibration session (see :mod:`radiometry.vignetting_calibration`), ready for fitting.

    ``count``, ``sum``, ``sumsq``: ``(H, W, C)`` per pixel and channel, irradiance ``f^-1(I)``;
    ``cell_sums``/``cell_counts``: ``(T, gh, gw, C)`` per used frame on ``block``-pixel cells;
    ``frame_indices``: ``(T,)`` position of each used frame in the source; ``skipped``: reason -> number
    of skipped frames; ``response_table``: the response's ``f^-1`` used; ``response_stderr``: its own relative
    standard error per level and channel (``(256, C)``), when it carried one (``meta["inverse_stderr"]``).
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
    response_stderr: np.ndarray | None = None
    #: ``(count, sum, sumsq)`` of the odd frames alone (the 2nd, 4th, ... used), None when not collected
    odd: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    #: the sheet's raw levels per channel, ``(C, 256)``, None when not collected
    level_hist: np.ndarray | None = None
    #: how blocky the frames are (:func:`radiometry.response.levels.blockiness` of the first few used frames; above
    #: ``BLOCKY`` they are JPEG-compressed), None when not measured
    blockiness: float | None = None
    #: the response's ``meta["method"]`` ("gamma" or "linear": assumed, not calibrated; the budget then says its part
    #: is unknown), "" when not known
    response_method: str = ""
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
        if self.response_table is None:
            return None
        meta = {} if self.response_stderr is None else {"inverse_stderr": np.asarray(self.response_stderr).tolist()}
        if self.response_method:
            meta["method"] = self.response_method
        return CameraResponse(self.response_table, meta)

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

    def halves(self) -> tuple["VignettingAccumulation", "VignettingAccumulation"] | None:
        """The even and the odd frames of the sweep as two accumulations (None when the odd frames were not kept,
        e.g. an accumulation saved before they were, or fewer than 4 frames)."""
        if self.odd is None or self.frames_used < 4:
            return None
        odd_count, odd_sum, odd_sumsq = self.odd
        parts = []
        for which, (count, total, sq) in ((0, (self.count - odd_count, self.sum - odd_sum, self.sumsq - odd_sumsq)),
                                          (1, (odd_count, odd_sum, odd_sumsq))):
            pick = np.arange(which, self.frames_used, 2)
            parts.append(VignettingAccumulation(
                count=count.astype(np.int32), sum=np.maximum(total, 0.0), sumsq=np.maximum(sq, 0.0),
                cell_sums=self.cell_sums[pick], cell_counts=self.cell_counts[pick], block=self.block,
                frame_indices=self.indices()[pick], source=f"{self.source} ({'odd' if which else 'even'} frames)",
                response_table=self.response_table, response_stderr=self.response_stderr))
        return parts[0], parts[1]

    def clipped_channels(self, *, share: float = 0.02) -> list[tuple[int, int, float]]:
        """Channels whose sheet pixels pile up at their top level below 255: ``(channel, level, share)`` for each
        where at least ``share`` of the sheet's pixels sit within one level of the highest level seen (a smooth
        vignetted sheet has a thin tail there; a channel that saturates, e.g. white balance applied after the
        sensor clipped, a plateau)."""
        if self.level_hist is None:
            return []
        out = []
        for c, hist in enumerate(np.asarray(self.level_hist)):
            total = float(hist.sum())
            if total == 0:
                continue
            top = int(np.flatnonzero(hist)[-1])
            # the highest level holding a visible part of the sheet (a few stray pixels above do not count)
            cumulative = np.cumsum(hist[::-1])[::-1]
            top = int(np.flatnonzero(cumulative >= 1e-4 * total)[-1])
            pile = float(hist[max(top - 1, 0):top + 1].sum()) / total
            below = float(hist[max(top - 3, 0):max(top - 1, 0)].sum()) / total
            if pile >= share and pile >= 2.0 * below and top >= 64:  # a spike, not the top of a smooth spread
                out.append((c, top, pile))
        return out

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
            cell = fill_nan_cells(cell)
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
        if self.response_stderr is not None:
            arrays["response_stderr"] = np.asarray(self.response_stderr, dtype=np.float64)
        if self.odd is not None:
            arrays.update(odd_count=self.odd[0], odd_sum=self.odd[1], odd_sumsq=self.odd[2])
        if self.level_hist is not None:
            arrays["level_hist"] = np.asarray(self.level_hist, dtype=np.int64)
        meta = {"block": self.block, "skipped": self.skipped, "source": self.source}
        if self.blockiness is not None:     # kept, so that a fit of the saved accumulation still says "JPEG"
            meta["blockiness"] = float(self.blockiness)
        if self.response_method:
            meta["response_method"] = self.response_method
        return save_model_file(path, ACCUMULATION_KIND, arrays, meta)

    @classmethod
    def load(cls, path: str | os.PathLike) -> "VignettingAccumulation":
        meta, arrays = read_model_file(path, ACCUMULATION_KIND)
        try:
            acc = cls(count=arrays["count"].astype(np.int32), sum=arrays["sum"].astype(np.float64),
                      sumsq=arrays["sumsq"].astype(np.float64), cell_sums=arrays["cell_sums"].astype(np.float32),
                      cell_counts=arrays["cell_counts"].astype(np.uint16), block=int(meta["block"]),
                      frame_indices=arrays.get("frame_indices"),
                      skipped={str(k): int(v) for k, v in dict(meta.get("skipped", {})).items()},
                      source=str(meta.get("source", "")), response_table=arrays.get("response_table"),
                      response_stderr=arrays.get("response_stderr"),
                      odd=((arrays["odd_count"].astype(np.int32), arrays["odd_sum"].astype(np.float64),
                            arrays["odd_sumsq"].astype(np.float64))
                           if all(k in arrays for k in ("odd_count", "odd_sum", "odd_sumsq")) else None),
                      level_hist=None if "level_hist" not in arrays else arrays["level_hist"].astype(np.int64),
                      blockiness=None if meta.get("blockiness") is None else float(meta["blockiness"]),
                      response_method=str(meta.get("response_method", "")))
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
        if acc.odd is not None and (any(np.shape(a) != acc.count.shape for a in acc.odd)
                                    or np.any(acc.odd[0] < 0) or np.any(acc.odd[0] > acc.count)):
            raise CalibrationFileError(f"{path}: the odd frames' arrays do not match the counts; re-collect it")
        if acc.blockiness is not None and not (np.isfinite(acc.blockiness) and acc.blockiness > 0):
            raise CalibrationFileError(f"{path}: blockiness {acc.blockiness} is not a positive number; re-collect it")
        if acc.level_hist is not None and (np.shape(acc.level_hist) != (ch, 256) or np.any(acc.level_hist < 0)):
            raise CalibrationFileError(f"{path}: the level histogram is not (channels, 256); re-collect it")
        return acc
