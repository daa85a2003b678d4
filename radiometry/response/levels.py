"""Which levels of a bracketed stack carry the response: saturation and dark floors found from the data, and the
pixels a compressed or resampled image smears.

Real camera pipelines put more between the sensor and the file than ``f``: white balance applied after the sensor
clips (a gain below 1 makes a channel saturate at, say, level 241 instead of 255), noise after the response (the
saturated pixels then read 250..255 instead of 255), JPEG (8x8 block noise, ringing and 4:2:0 chroma subsampling at
edges). A fit that takes levels 1..254 as data then treats a pile of saturated pixels as observations of their
level, and ``f^-1`` climbs or bends over the top levels. This module finds, per channel:

- the **ceiling**: a pixel whose level does not rise when the exposure grows by at least :data:`MIN_RATIO` has
  stopped responding. For each level ``a`` the share of such stalled observations (level ``b <= a + 1`` in the next
  exposure at least 1.4x longer) is 0 for a responding level and near 1 for a saturated one. The ceiling is the
  lowest level from which half or more of the observations stall; the valid range ends :data:`MARGIN` levels below
  the lowest level, within :data:`SPREAD` levels under the ceiling, where the stalled share exceeds
  :data:`ONSET` (saturated pixels spread below the ceiling by noise after the response or JPEG);
- the **floor**: the same going down: an observation whose level does not fall when the exposure shrinks by 1.4x
  (black level clamped, a pedestal); the valid range starts :data:`MARGIN` levels above the highest such level.

:func:`edge_mask` drops the pixels within :data:`EDGE_RADIUS` pixels of a strong edge in any exposure: there JPEG's
ringing and chroma subsampling mix the colours of both sides (and a camera that moved between exposures mixes
them too); flat and smoothly shaded regions keep their levels.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from radiometry.errors import TooFewLevelsError

if TYPE_CHECKING:
    from radiometry.response.model import CameraResponse

log = logging.getLogger(__name__)

#: the smallest exposure ratio between the two observations a stall test compares
MIN_RATIO = 1.4
#: share of stalled observations at which a level counts as saturated (ceiling) or clamped (floor: a black level
#: clamp stalls every observation; the noise-dominated darkest levels of a gamma curve stall 50-66 %, and are kept)
STALLED = 0.5
STUCK = 0.8
#: share of stalled observations from which the valid range is cut below the ceiling
ONSET = 0.05
#: how far below the ceiling (levels) saturated pixels may spread and still be cut
SPREAD = 16
#: share of the saturated readings on one level for an exact pile (a clean ceiling: no margin needed below it)
PILE_SHARE = 0.995
#: levels kept clear of the ceiling's onset and the floor, plus NOISE_MARGIN times the saturated readings' noise
MARGIN = 2
NOISE_MARGIN = 3.0
#: observations a level needs before its stalled share is judged
MIN_COUNT = 20
#: the fewest levels a channel needs between floor and ceiling for a fit
MIN_LEVELS = 32
#: pixels sampled for the stall test
MAX_PIXELS = 300_000
#: a strong edge: a 3x3 Laplacian above this many levels; pixels within EDGE_RADIUS of one are dropped
EDGE_LEVELS = 24
EDGE_RADIUS = 4
#: a pixel stalls between two exposures when its level at or above STALL_FROM rises by no more than STALL_TOLERANCE
#: levels in an exposure at least MIN_RATIO longer (noise after the response spreads the ceiling by a few levels)
STALL_FROM = 128
STALL_TOLERANCE = 4
#: the edge mask is not used when it would keep less than this share of the usable pixels
MIN_KEPT = 0.2
CHANNEL_NAMES = {1: ("Y",), 3: ("R", "G", "B")}


@dataclass(frozen=True)
class ChannelLevels:
    """The usable levels of one channel: ``low..high`` inclusive; ``ceiling``/``floor`` the level where the channel
    saturates / clamps (None: not seen in the stack)."""

    low: int
    high: int
    ceiling: int | None
    floor: int | None
    #: the one level every saturated pixel reads, when they all read one (no noise after the response): then a pixel
    #: below it is responding, however close
    pile: int | None = None

    def as_dict(self) -> dict:
        return {"low": self.low, "high": self.high, "saturates_at": self.ceiling, "floor_at": self.floor,
                "pile": self.pile}


def _pairs(times: np.ndarray, longer: bool) -> list[tuple[int, int]]:
    """Pairs (j, k): k the closest exposure at least MIN_RATIO longer (``longer``) or shorter than j."""
    order = np.argsort(times)
    out = []
    for pos, j in enumerate(order):
        others = order[pos + 1:] if longer else order[:pos][::-1]
        for k in others:
            ratio = times[k] / times[j] if longer else times[j] / times[k]
            if ratio >= MIN_RATIO:
                out.append((int(j), int(k)))
                break
    return out


def _stalled_share(values: np.ndarray, pairs: list[tuple[int, int]], up: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per level of the first exposure of each pair: observations and the share that stalled."""
    count = np.zeros(256)
    stalled = np.zeros(256)
    for j, k in pairs:
        a = values[j].astype(np.int16)
        b = values[k].astype(np.int16)
        stall = (b <= a + 1) if up else (b >= a)
        count += np.bincount(a, minlength=256)
        stalled += np.bincount(a, weights=stall.astype(np.float64), minlength=256)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(count > 0, stalled / np.maximum(count, 1), 0.0)
    return count, share


def exact_pile(values: np.ndarray, pairs: list[tuple[int, int]], ceiling: int) -> int | None:
    """The level that (nearly) every saturated reading takes, or None when they spread (noise, JPEG): the most common
    longer-exposure level of the pairs stalled at or above ``ceiling``, if it holds :data:`PILE_SHARE` of them."""
    tops = []
    for j, k in pairs:
        a = values[j].astype(np.int16)
        b = values[k].astype(np.int16)
        tops.append(b[(a >= ceiling) & (b <= a + 1)])
    top = np.concatenate(tops) if tops else np.empty(0, np.int16)
    if top.size < MIN_COUNT:
        return None
    counts = np.bincount(top, minlength=256)
    level = int(np.argmax(counts))
    return level if counts[level] >= PILE_SHARE * top.size else None


def ceiling_noise(values: np.ndarray, pairs: list[tuple[int, int]], ceiling: int) -> float:
    """The noise (levels, a robust standard deviation) of the saturated readings: of the level differences between
    two exposures of pixels saturated in both (at or above ``ceiling`` and not rising), divided by sqrt 2. Zero for
    a camera whose saturated pixels read one level; about the noise added after the response otherwise."""
    diffs = []
    for j, k in pairs:
        a = values[j].astype(np.int16)
        b = values[k].astype(np.int16)
        both = (a >= ceiling - 1) & (b >= ceiling - 1) & (b <= a + STALL_TOLERANCE)
        diffs.append((b - a)[both])
    d = np.concatenate(diffs) if diffs else np.empty(0)
    if d.size < MIN_COUNT:
        return 0.0
    mad = float(np.median(np.abs(d - np.median(d))))
    return 1.4826 * mad / math.sqrt(2.0)


def channel_levels(values: np.ndarray, times: np.ndarray, limits: tuple[int, int] = (1, 254)) -> ChannelLevels:
    """The usable levels of one channel: ``values`` ``(P, N)`` uint8 (P exposures of N pixels), within ``limits``."""
    lo, hi = limits
    ceiling = floor = pile = None
    pairs_up = _pairs(times, longer=True)
    if pairs_up:
        count, share = _stalled_share(values, pairs_up, up=True)
        judged = count >= MIN_COUNT
        stalled = np.flatnonzero(judged & (share >= STALLED) & (np.arange(256) >= 64))
        if stalled.size:
            ceiling = int(stalled[0])
            onset = ceiling
            for level in range(ceiling - 1, max(ceiling - SPREAD, 64) - 1, -1):
                if not judged[level] or share[level] < ONSET:  # too few to judge: no evidence of saturation
                    break
                onset = level
            pile = exact_pile(values, pairs_up, ceiling)
            if pile is not None:  # every saturated pixel reads `pile`: the levels below it are all responding
                hi = min(hi, pile - 1)
            else:
                noise = ceiling_noise(values, pairs_up, ceiling)
                hi = min(hi, onset - MARGIN - int(math.ceil(NOISE_MARGIN * noise)))
    pairs_down = _pairs(times, longer=False)
    if pairs_down:
        count, share = _stalled_share(values, pairs_down, up=False)
        judged = count >= MIN_COUNT
        stuck = np.flatnonzero(judged & (share >= STUCK) & (np.arange(256) < 64) & (np.arange(256) >= 1))
        bottom = np.flatnonzero(judged & (np.arange(256) >= 1))
        if stuck.size and bottom.size and stuck[0] == bottom[0]:
            # the highest level of the run of clamped levels that starts at the bottom of the judged levels
            run = stuck[0]
            for level in stuck[1:]:
                if level > run + 1:
                    break
                run = level
            floor = int(run)
            lo = max(lo, floor + 1 + MARGIN)
    return ChannelLevels(int(lo), int(hi), ceiling, floor, pile)


def stalled_observations(values: np.ndarray, times: np.ndarray, pile: int | None = None) -> np.ndarray:
    """``(P, N)`` boolean, True where a pixel has stopped responding: from the shortest exposure in which its level
    (at least :data:`STALL_FROM`) rises by no more than :data:`STALL_TOLERANCE` in an exposure at least
    :data:`MIN_RATIO` longer, in that exposure and every longer one. This catches the saturated pixels that a level
    cut cannot: under JPEG's chroma subsampling a saturated channel beside an unsaturated one reads well below its
    ceiling, and it reads so in every longer exposure too. ``pile``: the level every saturated pixel reads (an exact
    ceiling, :func:`exact_pile`): a pixel whose longer exposure reads it has reached the ceiling there, not before,
    and is not taken as stalled."""
    n_img, n_pix = values.shape
    first = np.full(n_pix, np.inf)
    for j, k in _pairs(times, longer=True):
        a = values[j].astype(np.int16)
        b = values[k].astype(np.int16)
        stall = (a >= STALL_FROM) & (b <= a + STALL_TOLERANCE)
        if pile is not None:
            stall &= b != pile
        first = np.where(stall, np.minimum(first, times[j]), first)
    return times[:, None] >= first[None, :]


def detect_levels(stack: np.ndarray, times: np.ndarray, valid: np.ndarray | None = None,
                  limits: tuple[int, int] = (1, 254), *, seed: int = 0) -> list[ChannelLevels]:
    """Per channel, the usable levels of a stack ``(P, H, W, C)`` uint8 (``valid``: flat boolean ``(H*W,)``).

    Raises :class:`~radiometry.errors.TooFewLevelsError` (a CalibrationError) when a channel keeps fewer than
    :data:`MIN_LEVELS` levels (every exposure saturated or dark there), naming the channel and the fix."""
    n_img, h, w, n_ch = stack.shape
    flat = stack.reshape(n_img, h * w, n_ch)
    idx = np.arange(h * w) if valid is None else np.flatnonzero(valid)
    if idx.size > MAX_PIXELS:
        idx = np.sort(np.random.default_rng(seed).choice(idx, MAX_PIXELS, replace=False))
    names = CHANNEL_NAMES.get(n_ch, tuple(str(c) for c in range(n_ch)))
    out = []
    for c in range(n_ch):
        values = flat[:, idx, c]
        levels = channel_levels(values, times, limits)
        usable = (values >= levels.low) & (values <= levels.high)
        seen = np.unique(values[usable]) if usable.any() else np.empty(0)
        if levels.high - levels.low + 1 < MIN_LEVELS or seen.size < MIN_LEVELS:
            what = (f"saturates at level {levels.ceiling}" if levels.ceiling is not None and levels.ceiling < 128
                    else f"shows only {seen.size} usable levels")
            if levels.high < levels.low:  # nothing left: every level cut as saturated, dark or stalled
                raise TooFewLevelsError(
                    f"channel {names[c]} {what} (no usable levels: every observation looks saturated, dark or stops "
                    "brightening with the exposure time)", "check that the times file gives each image its own "
                    "exposure time, then add exposures that fill the range", sep=": ")
            raise TooFewLevelsError(
                f"channel {names[c]} {what} (usable {levels.low}..{levels.high}): too few levels are constrained "
                "to fit a response", "add exposures that fill the range (shorter ones if most pixels are saturated, "
                "longer ones if most are dark)")
        out.append(levels)
    return out


def _pile(meta: dict, channel: int) -> int | None:
    """Channel ``channel``'s exact ceiling from :func:`prepare`'s meta (None without detection)."""
    found = meta.get("level_detection")
    return None if not found else found[channel].get("pile")


def describe(levels: list[ChannelLevels]) -> str:
    """One line for the summary, e.g. ``R saturates at 241, B at 249; levels used R 3..237, G 3..252, B 3..245``."""
    names = CHANNEL_NAMES.get(len(levels), tuple(str(c) for c in range(len(levels))))
    sat = [f"{n} at {lv.ceiling}" for n, lv in zip(names, levels) if lv.ceiling is not None and lv.ceiling < 254]
    floors = [f"{n} at {lv.floor}" for n, lv in zip(names, levels) if lv.floor is not None and lv.floor > 2]
    parts = []
    if sat:
        parts.append("saturates " + ", ".join(sat))
    if floors:
        parts.append("dark floor " + ", ".join(floors))
    used = ", ".join(f"{n} {lv.low}..{lv.high}" for n, lv in zip(names, levels))
    return "; ".join(parts + [f"levels used {used} (the others extrapolated)"])


#: block-boundary to in-block ratio of small level steps above which a stack is taken for JPEG-compressed
#: (measured: PNG 0.99-1.01, JPEG q95 1.08-1.14, q92 1.18-1.27, q75 1.38-1.47)
BLOCKY = 1.05
#: fewest small steps across block boundaries (per image and direction) for a ratio to count: below it the ratio
#: of uncompressed noise strays past BLOCKY (measured on uncompressed random stacks: called JPEG 42 % of the time
#: at 16x16, 20 % at 64x48 (~340 steps), never from 160x120 (~2,300) up); a stack too small to tell counts as not JPEG
MIN_BOUNDARY_STEPS = 1500


def blockiness(stack: np.ndarray) -> float:
    """How much the level steps between neighbouring pixels grow at 8-pixel block boundaries (JPEG's 8x8 blocks):
    the median over exposures and both directions of the mean small step (< 8 levels) across boundaries over the
    mean inside blocks. About 1 for an uncompressed image, above :data:`BLOCKY` for JPEG below quality ~98; 1 when
    the images are too small to tell (fewer than :data:`MIN_BOUNDARY_STEPS` small steps across boundaries)."""
    ratios = []
    for img in stack:
        grey = img.astype(np.float32).mean(axis=-1)
        for axis in (0, 1):
            d = np.abs(np.diff(grey, axis=axis))
            boundary = (np.arange(d.shape[axis]) % 8) == 7
            across = np.take(d, np.flatnonzero(boundary), axis=axis)
            inside = np.take(d, np.flatnonzero(~boundary), axis=axis)
            across, inside = across[across < 8], inside[inside < 8]
            if across.size >= MIN_BOUNDARY_STEPS and inside.size:
                ratios.append((across.mean() + 1e-3) / (inside.mean() + 1e-3))
    return float(np.median(ratios)) if ratios else 1.0


def edge_mask(stack: np.ndarray, valid: np.ndarray | None = None) -> tuple[np.ndarray | None, float]:
    """Pixels away from strong edges in every exposure and channel: ``(mask (H, W) or None, share dropped)``.

    ``None`` (no mask) when the stack is flat everywhere or the mask would keep less than :data:`MIN_KEPT` of the
    usable pixels (a scene of fine texture: then every pixel is used, as before)."""
    import cv2

    n_img, h, w, n_ch = stack.shape
    edges = np.zeros((h, w), bool)
    for j in range(n_img):
        for c in range(n_ch):
            img = np.ascontiguousarray(stack[j, :, :, c]).astype(np.float32)
            # the 3x3 Laplacian: zero on a ramp (a smooth gradient keeps its pixels), large across a step
            edges |= np.abs(cv2.Laplacian(img, cv2.CV_32F, ksize=1)) > EDGE_LEVELS
    if not edges.any():
        return None, 0.0
    size = 2 * EDGE_RADIUS + 1
    near = cv2.dilate(edges.astype(np.uint8), np.ones((size, size), np.uint8)).astype(bool)
    keep = ~near
    base = np.ones((h, w), bool) if valid is None else valid.reshape(h, w)
    kept = float((keep & base).sum()) / max(float(base.sum()), 1.0)
    if kept < MIN_KEPT:
        log.info("edge mask not used: it would keep %.0f%% of the pixels", 100 * kept)
        return None, 0.0
    return keep, 1.0 - kept


def prepare(stack: np.ndarray, times: np.ndarray, valid: np.ndarray | None, limits, *, edges: bool | str = "auto",
            seed: int = 0) -> tuple[list[tuple[int, int]], np.ndarray | None, dict]:
    """For a fit: per-channel ``(low, high)`` levels, the flat usable mask (None = all) and the meta entries.

    ``limits`` ``"auto"``: levels found from the data (:func:`detect_levels` within 1..254); a pair ``(low, high)``:
    those levels for every channel, as given (nothing detected). ``edges``: drop the pixels near strong edges
    (True), keep them (False), or ``"auto"``: drop them when the stack looks JPEG-compressed (:func:`blockiness`)."""
    meta: dict = {}
    if isinstance(edges, str):
        if edges != "auto":
            raise ValueError(f"edges must be True, False or 'auto', got {edges!r}")
        meta["blockiness"] = round(blockiness(stack), 3)
        edges = meta["blockiness"] > BLOCKY
    if edges:
        keep, dropped = edge_mask(stack, valid)
        if keep is not None:
            valid = keep.ravel() if valid is None else (valid & keep.ravel())
        meta["edge_pixels_dropped"] = round(dropped, 4)
    if isinstance(limits, str):
        if limits != "auto":
            raise ValueError(f"levels must be 'auto' or a pair (low, high), got {limits!r}")
        found = detect_levels(stack, times, valid, seed=seed)
        meta["level_detection"] = [lv.as_dict() for lv in found]
        meta["saturation_levels"] = [lv.ceiling for lv in found]
        meta["levels_summary"] = describe(found)
        per_channel = [(lv.low, lv.high) for lv in found]
    else:
        per_channel = [tuple(limits)] * stack.shape[3]
    return per_channel, valid, meta


def declared(response: CameraResponse, channels: int) -> list[tuple[int, int]]:
    """The levels a response declares constrained per channel (``meta["declared_levels"]``, else its observed range,
    else 5..250)."""
    given = response.meta.get("declared_levels") or response.meta.get("observed_range")
    if isinstance(given, list) and len(given) in (1, channels):
        pairs = [(max(int(lo), 1), min(int(hi), 254)) for lo, hi in given]
        return pairs * channels if len(pairs) == 1 else pairs
    return [(5, 250)] * channels


__all__ = ["declared", "blockiness", "ChannelLevels", "channel_levels", "detect_levels", "describe", "edge_mask", "prepare"]
