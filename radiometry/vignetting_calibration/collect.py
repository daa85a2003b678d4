"""Collection: every frame of a source through sheet detection into the accumulator, with the frames skipped
counted by reason and a one-line error with the fix when the frames are no white-sheet sweep."""

from __future__ import annotations

import dataclasses
import logging
from collections import Counter
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError, ImageError
from radiometry.quorum import rule_text, too_little
from radiometry.response import CameraResponse
from radiometry.response.levels import blockiness
from radiometry.vignetting_calibration.accumulate import VignettingAccumulation, VignettingAccumulator
from radiometry.vignetting_calibration.sheet import detect_sheet
from radiometry.vignetting_calibration.sources import open_frames

log = logging.getLogger(__name__)

#: frames whose blockiness is measured (JPEG or not: the split-half figure misses JPEG's rounding of a static sheet)
BLOCKY_FRAMES = 8

#: the fix that ends every "these frames are no sweep" message
SWEEP_FIX = ("point the camera at an evenly lit white sheet that fills a good part of the view, on a darker "
             "background, and sweep it across the whole image")


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

    # the grey image sheet detection works on is the mean of the channels: its f^-1, roughly, is the channels' mean
    grey_inverse = response.inverse_table.mean(axis=1)
    acc: VignettingAccumulator | None = None
    skipped: Counter[str] = Counter()
    sizes: Counter[str] = Counter()      # frames per size ("WxH" or "WxH grey"): the first frame's must prevail
    first_size = ""
    seed: tuple[int, int] | None = None
    n_seen = 0
    sheet_pixels = near_ceiling = 0  # the sheet's pixels, and those left out as near the ceiling
    blocky: list[float] = []
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
            det = detect_sheet(frame, seed, saturation=saturation, dark=dark, inverse=grey_inverse, **detect_options)
            if not det.ok:
                skipped[det.status] += 1
                log.debug("frame %d skipped: %s", n_seen - 1, det.status)
                continue
            kept = _away_from_ceiling(frame, det.mask, saturation)
            sheet_pixels += int(np.count_nonzero(det.mask))
            near_ceiling += int(np.count_nonzero(det.mask & ~kept))
            acc.add(frame, kept, index=n_seen - 1, sheet=det.mask)
            if len(blocky) < BLOCKY_FRAMES:
                blocky.append(blockiness(frame[None] if frame.ndim == 3 else frame[None, :, :, None]))
            seed = det.centre
            if stop_when_covered and acc.covered(min_samples):  # type: ignore[arg-type]
                log.info("every pixel has %d samples after %d frames; stopping", min_samples, n_seen)
                break
    finally:
        bar.close()
    if acc is None:
        raise CalibrationError(f"{frames.name}: no frames; record a sweep over a white sheet")
    if sheet_pixels and near_ceiling > NEAR_CEILING_WARN * sheet_pixels:  # a sheet not clipped, but nearly: say so
        log.warning("%s: %.0f%% of the sheet's pixels were within %d levels of %d and left out (with %d px around "
                    "them) as possibly clipped; lower the exposure so that the sheet's brightest part stays below %d",
                    frames.name, 100.0 * near_ceiling / sheet_pixels, NEAR_CEILING, saturation, CEILING_RADIUS,
                    saturation - NEAR_CEILING)
    if len(sizes) > 1:
        _check_sizes(frames.name, sizes, first_size)
    if acc.frames == 0:
        raise CalibrationError(_no_frames_message(frames.name, n_seen, skipped, saturation))
    if too_little(acc.frames, n_seen):
        reasons = ", ".join(f"{k}: {v}" for k, v in skipped.most_common())
        raise CalibrationError(
            f"{frames.name}: a sheet was found in only {acc.frames} of {n_seen} frames ({reasons}); a model needs "
            f"{rule_text()}, so these are not a white-sheet sweep; {SWEEP_FIX}")
    if skipped.get("saturated", 0) > acc.frames:
        log.warning("%d of %d frames were skipped as saturated; lowering the exposure would use them",
                    skipped["saturated"], n_seen)
    result = acc.result(skipped=dict(skipped), source=frames.name)
    result = dataclasses.replace(result, blockiness=float(np.median(blocky)) if blocky else None, _cache={})
    clipped = result.clipped_channels()
    if clipped:
        names = ("R", "G", "B") if result.channels == 3 else ("grey",)
        what = ", ".join(f"{names[c]} at level {level} ({100 * share:.0f}% of the sheet's pixels)"
                         for c, level, share in clipped)
        raise CalibrationError(
            f"{frames.name}: the sheet saturates in {what}: a channel that clips (white balance applied after the "
            "sensor saturated, or overexposure) flattens V where the sheet is brightest; record the sweep with a "
            "shorter exposure or dimmer light so that every channel of the sheet stays below its ceiling")
    log.info("vignetting data: %d frames used, %d skipped %s", result.frames_used, result.frames_skipped,
             dict(skipped))
    return result


#: sheet pixels within NEAR_CEILING levels of the saturation level, and their neighbours within CEILING_RADIUS pixels,
#: are left out of a frame: a per-pixel cut keeps the pixels that noise pushed down and drops those it pushed up,
#: which biases the bright part of the sheet low (0.8 levels with auto exposure left on, measured)
NEAR_CEILING = 6
CEILING_RADIUS = 3
#: share of the sheet's pixels left out near the ceiling from which the sweep is warned about it (audit 2026-11-28: a
#: sheet at levels 233-249 lost 78 % of itself this way, and the coverage refusal that followed blamed the sweep)
NEAR_CEILING_WARN = 0.2


def _away_from_ceiling(frame: np.ndarray, mask: np.ndarray, saturation: int) -> np.ndarray:
    """``mask`` without the neighbourhoods of pixels near the saturation level (any channel)."""
    near = (frame >= saturation - NEAR_CEILING) if frame.ndim == 2 else (frame >= saturation - NEAR_CEILING).any(axis=2)
    near &= mask
    if not near.any():
        return mask
    import cv2

    size = 2 * CEILING_RADIUS + 1
    grown = cv2.dilate(near.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
    return mask & ~grown


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
                f"brightest part of the sheet stays below {saturation - NEAR_CEILING}, and record again")
    if reason == "too dark":
        return (f"{name}: the sheet is too dark in {count} of {n_seen} frames; raise the exposure or the light "
                "(the sheet's centre should be around 150-220) and record again")
    if reason == "textured":
        return (f"{name}: the view is textured or noisy, not a plain sheet, in {count} of {n_seen} frames; point "
                "the camera at an evenly lit plain white sheet (matte paper, no print) and record again")
    if reason == "low contrast":
        return (f"{name}: the plain region found is hardly brighter than its surroundings in {count} of {n_seen} "
                f"frames (a wall or a table, not a white sheet on a darker background); {SWEEP_FIX}")
    if reason == "different size":
        return f"{name}: the frames have different sizes; record the sweep at one resolution"
    return f"{name}: no white sheet found in any of the {n_seen} frames ({dict(skipped)}); {SWEEP_FIX}"
