"""Undo vignetting through the camera response: ``I' = f(scale * f^-1(I) / V(x))`` per channel.

:class:`Corrector` holds a :class:`~radiometry.response.CameraResponse` and (optionally) a
:class:`~radiometry.vignetting.VignettingModel` and offers

- :meth:`Corrector.irradiance`: ``f^-1(I) / V(x)``, float32, for fusion (exact up to float32 rounding);
- :meth:`Corrector.correct`: the corrected image. uint8 in -> uint8 out through a fast path (below);
  float (levels 0..255) or uint16 (0..65535, treated as 8-bit levels times 257) in -> float32 levels
  out by the exact formula.

``scale`` is an explicit brightness factor. With ``scale = 1`` the centre keeps its brightness and the
corners are brightened by ``1 / V``, so bright corner pixels clip at 255; ``scale < 1`` darkens the
result so that they do not (``scale = min V`` keeps every unsaturated input unsaturated).
:meth:`Corrector.suggest_scale` proposes the scale that keeps a given percentile of real images
unclipped.

uint8 fast path. Per pixel and channel the output depends only on ``log g(x) + log f^-1(I)``, the log of
the exposure the formula feeds to ``f``, with the gain ``g(x) = scale / V(x)``. Both terms are quantised
on one log grid: the gain to an integer ``q(x)`` (a uint16 map, once per (size, scale)), the exposure of
each level to an integer ``k(I)`` (256 entries per channel), so the sum indexes a one-dimensional uint8
table ``T[q(x) + k(I)] = round(f(exp(sum)))`` computed with the exact formula. The grid step is
``s = max(log(max g / min g) / (2 (gain_levels - 1)), log(exposure range) / 65536)``; each quantisation
moves the exposure by at most a relative ``s / 2`` (``< 4e-4`` in all for V down to 0.2 and the default
2048 gain levels), which moves the unrounded output by far less than a level: the rounded output
differs from the exactly rounded formula by at most 1 level, and only for values within that tiny margin
of a .5 boundary (``tests/test_correction.py`` checks both). Without a vignetting gradient (one gain) the
table holds the exact 256 outputs per channel. The table is small (about 55 kB per channel, instead of
0.5 MB for a table per quantised gain), so its look-ups hit the CPU cache: that, not memory traffic,
bounds the speed (``scripts/bench_correction.py``). Tables and gain maps are cached per size (a few
entries).

Where the CPU has AVX-512 (F, BW, VL, VBMI) and GFNI and the C kernels are in use, whole blocks of 64 pixels go
through one of two register kernels instead; both replace the table by the count of each channel's output thresholds
below the index (``table`` is non-decreasing along a channel's part) and look ``k`` up by in-register byte permutes,
and both are bit-identical to the scalar kernel (tests compare them):

- ``radiometry/_ckernels_bucket.h`` (:func:`_build_bucket_plan`), where each bucket of 256 index steps holds at most
  ``bucket_nmax`` (12) thresholds and the buckets holding two or more lie within 128 buckets (the response curves
  and presets measured; docs/performance.md): the count is a byte table of the index's high byte plus one compare
  per threshold of its bucket. 1.3-1.7x the search below.
- ``radiometry/_ckernels_simd.h`` (:func:`_build_simd_plan`) elsewhere: an 8-step binary search in registers.

They need a per-(size, scale) plan (the gain indices reordered, 2 bytes a value, and 2-4 kB of tables per channel)
and apply when the gain indices are 16-bit and a channel's thresholds span at most 65534 steps; elsewhere, and for
the last pixels short of a block, the scalar kernel runs. ``Corrector(simd=False)`` or ``RADIOMAP_SIMD=0`` keep the
scalar kernel (the Numba kernels, ``RADIOMAP_KERNELS=numba``, have no AVX-512 twin).
"""

from __future__ import annotations

import logging
import math
from collections import OrderedDict
from typing import Iterable

import numpy as np

from radiometry._native import simd_allowed
from radiometry.errors import ModelMismatchError
from radiometry.response import CameraResponse
from radiometry.vignetting import VignettingModel

log = logging.getLogger(__name__)

_LEVELS = np.arange(256, dtype=np.float32)


# --------------------------------------------------------------------------------------------------
# kernels: compiled C, or Numba's (compiled on first use, cached on disk)
# --------------------------------------------------------------------------------------------------
def _kernels():
    """The look-up kernels ``(lookup_rgb, lookup_shared, irradiance)``: compiled C (``radiometry._ckernels``), or
    Numba's (:mod:`radiometry._native` chooses)."""
    global _KERNELS
    if _KERNELS is None:
        from radiometry._native import compiled

        global _SIMD, _BUCKET
        c = compiled("radiometry._ckernels")
        _KERNELS = (c.lookup_rgb, c.lookup_shared, c.irradiance) if c is not None else _numba_kernels()
        _SIMD = c.correct_simd if c is not None and getattr(c, "simd", 0) else None
        _BUCKET = c.correct_bucket if _SIMD is not None and hasattr(c, "correct_bucket") else None
    return _KERNELS


def _numba_kernels():
    """Compile (or load from Numba's cache) the Numba twins of the C kernels. Indices are computed in unsigned
    32-bit arithmetic: signed indices make Numba emit wrap-around checks that halve the throughput."""
    from numba import njit

    @njit(cache=True, nogil=True, boundscheck=False)
    def lookup_rgb(img, q, k, table, out):  # pragma: no cover - compiled
        # img, out, q: flat (N * 3), a gain index per value; k: (3, 256) offsets; table: flat uint8
        for p in range(img.size // 3):
            b = 3 * p
            out[b] = table[np.uint32(q[b]) + np.uint32(k[0, img[b]])]
            out[b + 1] = table[np.uint32(q[b + 1]) + np.uint32(k[1, img[b + 1]])]
            out[b + 2] = table[np.uint32(q[b + 2]) + np.uint32(k[2, img[b + 2]])]

    @njit(cache=True, nogil=True, boundscheck=False)
    def lookup_shared(img, q, k, table, out, channels):  # pragma: no cover - compiled
        # one gain index per pixel for every channel: q flat (N,); img/out flat (N * C)
        for p in range(q.size):
            level = np.uint32(q[p])
            b = p * channels
            for c in range(channels):
                out[b + c] = table[level + np.uint32(k[c, img[b + c]])]

    @njit(cache=True, nogil=True, boundscheck=False)
    def irradiance_kernel(img, lut, gain, out):  # pragma: no cover - compiled
        # img (N, C) uint8; lut (C, 256) float32; gain (N, Cg) float32, Cg in {1, C}; out (N, C) float32
        n, ch = img.shape
        shared = gain.shape[1] == 1
        for p in range(n):
            for c in range(ch):
                g = gain[p, 0] if shared else gain[p, c]
                out[p, c] = lut[c, np.uint32(img[p, c])] * g

    return lookup_rgb, lookup_shared, irradiance_kernel


_KERNELS = None
_SIMD = None
_BUCKET = None

#: lanes of a 512-bit register in the order vpunpck[lh]bw put the bytes of a 64-byte plane into two words vectors
_UNPACK_ORDER = np.array([16 * lane + half + x for half in (0, 8) for lane in range(4) for x in range(8)])


def simd_available() -> bool:
    """Whether :meth:`Corrector.correct` can run its uint8 AVX-512 kernel here: the C extension is in use and the
    CPU has AVX-512 (F, BW, VL, VBMI) and GFNI. ``RADIOMAP_SIMD=0`` turns it off (the scalar kernels, same output)."""
    return _simd_kernel() is not None and simd_allowed()


def _simd_kernel():
    """``radiometry._ckernels.correct_simd`` when the C kernels are in use and this CPU runs it, else None."""
    _kernels()
    return _SIMD


def _build_simd_plan(q: np.ndarray, k: np.ndarray, table: np.ndarray, sizes: list[int], channels: int):
    """The AVX-512 kernel's data (radiometry/_ckernels_simd.h), ``(qplan, plan, clamp)``, or None where it does not
    apply (32-bit q; an output not non-decreasing along its part of ``table``; thresholds spanning more than
    65534 steps).

    ``qplan`` (blocks of 64 pixels, C, 64) uint16 holds the gain indices in unpack order. Per channel, with ``j`` the
    index into the channel's part of ``table``, the output is the number of thresholds ``t[m] <= j`` (``t[m]``: the
    first j whose output is >= m, m = 1..255). The kernel computes ``j`` in 16 bits: ``q + k1[I]`` when every j is
    below 65535 (``clamp`` False), else ``clamp(j - L, 0, 65534)`` as ``min((q + k1[I]) -sat k2[I], 65534)`` with
    ``L = t[1] - 1``, ``k1 = max(k - L, 0)``, ``k2 = max(L - k, 0)`` and the thresholds moved by ``-L`` (thresholds no
    j reaches become 0xFFFF: never counted). ``plan`` (C, 1792) uint8: k1's low and high bytes, the thresholds as the
    words of an 8-step binary search built least-significant bit first (levels 0..5 at 32 words each, 6: 64, 7: 128),
    then k2's low and high bytes."""
    if q.dtype != np.uint16:
        return None
    plan = np.zeros((channels, 1792), dtype=np.uint8)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    qmax = int(q.max()) if q.size else 0
    rels, thresholds = [], []
    for c in range(channels):
        part = table[starts[c]:starts[c + 1]].astype(np.int64)
        rel = k[c].astype(np.int64) - starts[c]
        if np.any(np.diff(part) < 0) or rel.min() < 0 or qmax + rel.max() >= part.size:
            return None
        rels.append(rel)
        thresholds.append(np.searchsorted(part, np.arange(1, 256), side="left"))  # t[m] at m - 1; part.size: never
    clamp = max(qmax + int(rel.max()) for rel in rels) > 65534
    for c in range(channels):
        rel, t = rels[c], thresholds[c].astype(np.int64)
        jmax = qmax + int(rel.max())
        shift = max(int(t[0]) - 1, 0) if clamp else 0
        never = t > jmax  # beyond every j: never counted
        if np.any((t - shift > 65534) & ~never):  # a threshold the 16-bit index cannot reach (0xFFFF: never)
            return None
        t = np.where(never, 0xFFFF, t - shift)
        k1, k2 = np.clip(rel - shift, 0, 65534), np.clip(shift - rel, 0, 65535)
        plan[c, :256], plan[c, 256:512] = k1 & 255, k1 >> 8
        plan[c, 1280:1536], plan[c, 1536:] = k2 & 255, k2 >> 8
        words = np.zeros(384, dtype=np.uint16)  # levels 0..5 at 32 * d, 6 at 192, 7 at 256
        for d in range(8):
            base = 32 * d if d < 7 else 256
            for p in range(1 << d):  # p: the bits found so far, bit e = step e's answer = bit 7 - e of the count
                prefix = sum(((p >> e) & 1) << (7 - e) for e in range(d))
                words[base + p] = t[prefix + (1 << (7 - d)) - 1]
        plan[c, 512:1280] = words.view(np.uint8)
    pixels = q.shape[0]
    blocks = pixels // 64
    qv = np.broadcast_to(q[:blocks * 64], (blocks * 64, channels)) if q.shape[1] == 1 else q[:blocks * 64]
    qplan = np.ascontiguousarray(qv.reshape(blocks, 64, channels).transpose(0, 2, 1)[:, :, _UNPACK_ORDER])
    for arr in (qplan, plan):
        arr.setflags(write=False)
    return qplan, plan, clamp

def _aligned_empty(size: int) -> np.ndarray:
    """An uninitialised uint8 array of ``size`` bytes starting on a 64-byte boundary (the AVX-512 kernels' loads and
    stores then never straddle two cache lines)."""
    buf = np.empty(size + 63, dtype=np.uint8)
    start = -buf.ctypes.data % 64
    return buf[start:start + size]


def _best_shift(t: np.ndarray, s: int, highest: int, lowest: int) -> int:
    """The shift S in lowest..highest that puts the fewest thresholds ``(t - S) << s`` in one bucket of 256 steps,
    and among those one whose buckets with two or more thresholds are all in 128..255 (the kernel's cheapest
    window), else the highest."""
    shifts = np.arange(highest, lowest - 1, -1)
    tt = (t[None, :] - shifts[:, None]) << s
    inside = (tt > 0) & (tt & 255 != 0)
    occupancy = np.zeros((shifts.size, 257), dtype=np.int64)
    np.add.at(occupancy, (np.nonzero(inside)[0], (tt[inside] >> 8)), 1)
    most = occupancy.max(axis=1)
    low_multi = (occupancy[:, :128] >= 2).any(axis=1)
    return int(shifts[np.lexsort((np.arange(shifts.size), low_multi, most))[0]])


def _bucket_channel(part: np.ndarray, rel: np.ndarray, qmax: int, nmax: int):
    """One channel's part of :func:`_build_bucket_plan`: ``(row, s)`` (the channel's plan bytes and the shift of its
    gain indices) or None where the bucket kernel does not apply. ``part``: the channel's table (non-decreasing),
    ``rel``: k relative to it (int64, 256), ``qmax``: the largest gain index of the channel."""
    jmax, kmin = qmax + int(rel.max()), int(rel.min())
    t = np.searchsorted(part, np.arange(1, 256), side="left")
    t = t[t <= jmax]  # the thresholds some j reaches (the others are never counted)
    clamp = jmax - kmin > 65535
    if not clamp:  # every j' = (j - S) << s in 0..65535: S at most the smallest k, s as large as that allows (<= 8)
        s = next(s for s in range(8, -1, -1) if (jmax - kmin) << s <= 65535)
        highest, lowest = kmin, jmax - (65535 >> s)
    else:  # j' leaves 16 bits: S below the first positive threshold, j' < 0 counts #{t = 0}, j' > 65535 all
        pos = t[t > 0]
        first, last = (int(pos.min()), int(pos.max())) if pos.size else (1, 1)
        s = next((s for s in range(8, -1, -1) if (last - first + 1) << s <= 65535 and qmax << s <= 65535), None)
        if s is None:
            return None
        highest, lowest = first - 1, last - (65535 >> s)
    shift = _best_shift(t, s, highest, max(lowest, highest - (255 >> s)))
    kk = np.clip((rel - shift) << s, -65536, 65535)
    neg = int(np.sum(kk < 0))
    if np.any(kk[:neg] >= 0) or np.any(kk[neg:] < 0):  # k not non-decreasing: the levels below S are no prefix
        return None
    if neg > 255:  # every level below S: the kernel's byte compare with ``neg`` cannot say so
        return None
    tt = (t - shift) << s
    base = np.searchsorted(np.sort(tt), 256 * np.arange(256), side="right")
    inside = tt[(tt > 0) & (tt & 255 != 0)]  # thresholds inside a bucket (at 256 b: in base[b])
    buckets, lows = inside >> 8, (inside & 255) - 1
    occupancy = np.bincount(buckets, minlength=256)
    n = int(occupancy.max())
    if n > nmax:
        return None
    lt = np.full((max(n, 1), 256), 255, dtype=np.uint8)  # L_i[b]: 255 = none
    order = np.lexsort((lows, buckets))
    buckets, lows = buckets[order], lows[order]
    rank = np.arange(buckets.size) - np.searchsorted(buckets, buckets, side="left")
    lt[rank, buckets] = lows
    row = np.full(1024 + 128 * (nmax - 1) + 64, 255, dtype=np.uint8)
    row[:256], row[256:512] = kk & 255, (kk >> 8) & 255
    row[512:768], row[768:1024] = base, lt[0]
    w0 = 0
    if n >= 2:  # L_2..L_n over a window of 128 buckets w0..w0+127 holding every bucket with 2 thresholds or more
        multi = np.flatnonzero(occupancy >= 2)
        if multi[-1] - multi[0] > 127:
            return None
        w0 = min(int(multi[0]), 128)
        row[1024:1024 + 128 * (n - 1)] = lt[1:, w0:w0 + 128].reshape(-1)
    params = 1024 + 128 * (nmax - 1)
    row[params:params + 6] = [n, w0, clamp, neg, int(np.sum(t == 0)), t.size]
    return row, s


def _build_bucket_plan(q: np.ndarray, k: np.ndarray, table: np.ndarray, sizes: list[int], channels: int):
    """The bucket kernel's data (radiometry/_ckernels_bucket.h), ``(qplan, plan)``, or None where it does not apply
    (32-bit q; an output not non-decreasing along its part of ``table``; the thresholds that matter spanning more
    than 16 bits; a bucket of 256 steps holding more than ``bucket_nmax`` thresholds; the buckets holding two or
    more spanning more than 128 buckets; k not non-decreasing in the level where the index leaves 16 bits).

    ``qplan`` (blocks of 64 pixels, C, 128) uint8 holds each channel's ``q << s``, low bytes then high bytes.
    ``plan`` (C, bytes): per channel ``(k - S) << s`` (low, high bytes), base, L_1..L_n and the parameters, as the
    header of _ckernels_bucket.h describes (:func:`_bucket_channel`)."""
    from radiometry._native import compiled

    c_mod = compiled("radiometry._ckernels")
    if q.dtype != np.uint16 or c_mod is None or not hasattr(c_mod, "bucket_nmax"):
        return None
    starts = np.concatenate([[0], np.cumsum(sizes)])
    rows, shifts = [], []
    for c in range(channels):
        part = table[starts[c]:starts[c + 1]]
        rel = k[c].astype(np.int64) - starts[c]
        col = q[:, c if q.shape[1] > 1 else 0]
        qmax = int(col.max()) if col.size else 0
        if np.any(np.diff(part.astype(np.int16)) < 0) or rel.min() < 0 or qmax + rel.max() >= part.size:
            return None
        got = _bucket_channel(part, rel, qmax, int(c_mod.bucket_nmax))
        if got is None:
            return None
        rows.append(got[0])
        shifts.append(got[1])
    blocks = q.shape[0] // 64
    qplan = _aligned_empty(blocks * channels * 128).reshape(blocks, channels, 2, 64)
    for c in range(channels):
        col = (q[:blocks * 64, c if q.shape[1] > 1 else 0].astype(np.uint32) << shifts[c]).reshape(blocks, 64)
        qplan[:, c, 0], qplan[:, c, 1] = col & 255, col >> 8
    qplan, plan = qplan.reshape(blocks, channels, 128), np.stack(rows)
    for arr in (qplan, plan):
        arr.setflags(write=False)
    return qplan, plan

# --------------------------------------------------------------------------------------------------
# input normalisation
# --------------------------------------------------------------------------------------------------
def _as_hwc(image: np.ndarray) -> tuple[np.ndarray, bool]:
    """``(H, W, C)`` view of an image and whether it was 2-D."""
    arr = np.asarray(image)
    if arr.ndim == 2:
        return arr[:, :, None], True
    if arr.ndim == 3 and arr.shape[2] in (1, 3):
        return arr, False
    raise ValueError(f"image must have shape (H, W), (H, W, 1) or (H, W, 3), got {arr.shape}")


def _float_levels(arr: np.ndarray) -> np.ndarray:
    if arr.dtype == np.uint16:
        return arr.astype(np.float32) / np.float32(257.0)
    if np.issubdtype(arr.dtype, np.floating):
        return arr.astype(np.float32, copy=False)
    if np.issubdtype(arr.dtype, np.integer):
        if arr.size and (arr.min() < 0 or arr.max() > 255):
            raise ValueError(f"integer images must be uint8 or uint16 levels, got {arr.dtype} values in "
                             f"[{arr.min()}, {arr.max()}]")
        return arr.astype(np.float32)
    raise TypeError(f"image must be uint8, uint16 or float (levels 0..255), got dtype {arr.dtype}")


def _dark_floor(inv: np.ndarray, largest_log_gain: float) -> float:
    """The smallest positive ``f^-1`` level worth a place in the fast path's table: darker exposures stay
    below level 0.5 even at the largest gain, so they round to level 0 like exposure 0."""
    half = 0.5 * (inv[0] + inv[1]) if inv[1] > inv[0] else inv[0]
    positive = inv[inv > 0]
    floor = max(half * np.exp(-largest_log_gain), positive.min() if positive.size else 1.0)
    return float(min(floor, inv[-1]))


class Corrector:
    """Apply a response and a vignetting model to images (see the module doc).

    Parameters
    ----------
    response : the camera's :class:`CameraResponse` (1 or 3 channels).
    vignetting : a :class:`VignettingModel`, or ``None`` for no vignetting (``V = 1``). A 1-channel
        model (DSO) serves all channels of a colour image.
    gain_levels : number of quantised gains of the uint8 fast path (2..65535).
    simd : the uint8 fast path's AVX-512 kernel (:func:`simd_available`): ``None`` (default) uses it where the CPU
        has it unless ``RADIOMAP_SIMD=0``; ``False`` never. Same output either way (bit-identical).
    """

    def __init__(self, response: CameraResponse, vignetting: VignettingModel | None = None, *,
                 gain_levels: int = 2048, cache_size: int = 4, simd: bool | None = None) -> None:
        if not isinstance(response, CameraResponse):
            raise TypeError(f"response must be a CameraResponse, got {type(response).__name__}")
        if vignetting is not None and not isinstance(vignetting, VignettingModel):
            raise TypeError(f"vignetting must be a VignettingModel or None, got {type(vignetting).__name__}")
        if not (isinstance(gain_levels, (int, np.integer)) and 2 <= gain_levels <= 65535):
            raise ValueError(f"gain_levels must be an integer in 2..65535, got {gain_levels!r}")
        if cache_size < 1:
            raise ValueError(f"cache_size must be at least 1, got {cache_size}")
        self.response = response
        self.vignetting = vignetting
        self.gain_levels = int(gain_levels)
        self._cache_size = int(cache_size)
        self._gains: OrderedDict[tuple[int, int], np.ndarray] = OrderedDict()
        self._tables: OrderedDict[tuple[int, int, int, float], tuple] = OrderedDict()
        self._plans: OrderedDict[tuple[int, int, int, float], tuple | None] = OrderedDict()
        self._bucket_plans: OrderedDict[tuple[int, int, int, float], tuple | None] = OrderedDict()
        self._last: tuple | None = None  # (key, parts) of the last uint8 correction (_fast_path)
        self.simd = simd

    def __repr__(self) -> str:
        return f"Corrector({self.response!r}, {self.vignetting!r})"

    def __setattr__(self, name: str, value) -> None:
        super().__setattr__(name, value)
        if name in ("response", "vignetting", "gain_levels") and "_last" in self.__dict__:
            for cache in (self._gains, self._tables, self._plans, self._bucket_plans):
                cache.clear()  # a new model: every table, plan and gain map was made for the old one
            self._last = None

    # ---------------------------------------------------------------- cached per-size data
    def _remember(self, cache: OrderedDict, key, value):
        cache[key] = value
        cache.move_to_end(key)
        while len(cache) > self._cache_size:
            cache.popitem(last=False)
        return value

    def _check_channels(self, channels: int) -> None:
        if self.vignetting is not None and self.vignetting.channels not in (1, channels):
            raise ModelMismatchError(
                f"the vignetting model has {self.vignetting.channels} channels but the image has {channels}; "
                "use a 1-channel model for grayscale images (or convert the images to RGB)")
        self.response.channel_tables(channels)  # raises ModelMismatchError when incompatible

    def gain_map(self, height: int, width: int) -> np.ndarray:
        """``1 / V`` at ``height x width``, float32 ``(H, W, Cv)``, cached (read-only)."""
        key = (int(height), int(width))
        hit = self._gains.get(key)
        if hit is not None:
            self._gains.move_to_end(key)
            return hit
        if self.vignetting is None:
            gain = np.ones((height, width, 1), dtype=np.float32)
        else:
            v = self.vignetting.evaluate(int(height), int(width)).astype(np.float64)
            gain = (1.0 / v).astype(np.float32)
        gain.setflags(write=False)
        return self._remember(self._gains, key, gain)

    def _fast_tables(self, height: int, width: int, channels: int,
                     scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(q, k, table)`` of the uint8 fast path (module doc): ``out = table[q[pixel, c] + k[c, I]]``.

        ``q`` is the quantised log gain, uint16 (uint32 past 65536 steps) ``(H * W, Cv)``; ``k`` (uint32
        ``(C, 256)``) holds each level's quantised log exposure plus its channel's place in ``table``, or
        the start of a run of zeros for levels too dark to reach level 0.5 at the largest gain."""
        return self._table_parts(height, width, channels, scale)[:3]

    def _table_parts(self, height: int, width: int, channels: int, scale: float) -> tuple:
        """``(q, k, table, sizes)``: :meth:`_fast_tables` and the size of each channel's part of ``table``."""
        key = (int(height), int(width), int(channels), float(scale))
        hit = self._tables.get(key)
        if hit is not None:
            self._tables.move_to_end(key)
            return hit
        log_g = np.log(self.gain_map(height, width).astype(np.float64) * scale)
        lo, hi = float(log_g.min()), float(log_g.max())
        tables = self.response.channel_tables(channels).astype(np.float64)  # (256, C): f^-1, also f's knots
        flat = hi - lo <= 1e-12
        if flat:  # one gain: the exact outputs of the 256 levels
            step, q = 1.0, np.zeros(log_g.shape, dtype=np.int64)
        else:
            floors = [_dark_floor(tables[:, c], hi) for c in range(channels)]
            spans = [np.log(tables[-1, c] / floors[c]) for c in range(channels)]
            step = max((hi - lo) / (2 * (self.gain_levels - 1)), max(spans) / 65536)
            q = np.rint((log_g - lo) / step).astype(np.int64)
        n_q = int(q.max()) + 1
        k = np.empty((channels, 256), dtype=np.uint32)
        parts, start = [], 0
        for c in range(channels):
            inv = tables[:, c]
            if flat:
                exposure = np.exp(lo) * inv
                k[c] = start + np.arange(256)
            else:
                usable = inv >= floors[c]
                ln_min = np.log(inv[usable].min())
                k_c = np.rint((np.log(np.where(usable, inv, 1.0)) - ln_min) / step).astype(np.int64)
                exposure = np.concatenate([np.zeros(n_q), np.exp(lo + ln_min + step * np.arange(n_q + k_c.max()))])
                k[c] = np.where(usable, start + n_q + k_c, start)
            part = np.clip(np.rint(np.interp(exposure, inv, _LEVELS.astype(np.float64))), 0, 255).astype(np.uint8)
            parts.append(part)
            start += part.size
        table = np.concatenate(parts)
        q = np.ascontiguousarray(q.reshape(-1, q.shape[2]).astype(np.uint16 if n_q <= 65536 else np.uint32))
        for arr in (q, k, table):
            arr.setflags(write=False)
        return self._remember(self._tables, key, (q, k, table, [part.size for part in parts]))

    def _simd_plan(self, height: int, width: int, channels: int, scale: float):
        """``(qplan, plan, clamp)`` of the AVX-512 kernel (:func:`_build_simd_plan`), cached, or None where it does not
        apply."""
        return self._cached_plan(self._plans, _build_simd_plan, height, width, channels, scale)

    def _simd_choice(self, height: int, width: int, channels: int, scale: float) -> tuple[str | None, tuple | None]:
        """The AVX-512 kernel :meth:`correct` runs on the whole blocks of 64 pixels and its data: ``("bucket",
        plan)`` (:func:`_build_bucket_plan`) where it applies, else ``("search", plan)`` (:func:`_build_simd_plan`),
        else ``(None, None)`` (the scalar kernel alone)."""
        plan = self._bucket_plan(height, width, channels, scale)
        if plan is not None:
            return "bucket", plan
        plan = self._simd_plan(height, width, channels, scale)
        return ("search", plan) if plan is not None else (None, None)

    def _bucket_plan(self, height: int, width: int, channels: int, scale: float):
        """``(qplan, plan)`` of the bucket kernel (:func:`_build_bucket_plan`), cached, or None where it does not
        apply."""
        return self._cached_plan(self._bucket_plans, _build_bucket_plan, height, width, channels, scale)

    def _cached_plan(self, cache: OrderedDict, build, height: int, width: int, channels: int, scale: float):
        """``build(q, k, table, sizes, channels)`` for this size and scale, kept in ``cache`` (None too: a plan that
        does not apply is not tried again)."""
        key = (int(height), int(width), int(channels), float(scale))
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
        q, k, table, sizes = self._table_parts(height, width, channels, scale)
        return self._remember(cache, key, build(q, k, table, sizes, channels))

    # ---------------------------------------------------------------- public API
    def irradiance(self, image: np.ndarray) -> np.ndarray:
        """``f^-1(I) / V(x)`` as float32 of the image's shape (``(H, W)`` stays ``(H, W)``).

        uint8 images use a table look-up; float (levels) and uint16 images interpolate ``f^-1``.
        """
        arr, flat = _as_hwc(image)
        h, w, ch = arr.shape
        self._check_channels(ch)
        gain = self.gain_map(h, w)
        if arr.dtype == np.uint8:
            lut = np.ascontiguousarray(self.response.channel_tables(ch).T)  # (C, 256) float32
            out = np.empty((h * w, ch), dtype=np.float32)
            _kernels()[2](np.ascontiguousarray(arr).reshape(-1, ch), lut, gain.reshape(-1, gain.shape[2]), out)
            out = out.reshape(h, w, ch)
        else:
            e = self.response.inverse(_float_levels(arr))
            out = (e * gain).astype(np.float32, copy=False)
        return out[:, :, 0] if flat else out

    def correct(self, image: np.ndarray, *, scale: float = 1.0) -> np.ndarray:
        """``f(scale * f^-1(I) / V(x))``: uint8 -> uint8 (fast path), float/uint16 -> float32 levels."""
        scale = self._check_scale(scale)
        arr, flat = _as_hwc(image)
        h, w, ch = arr.shape
        if arr.dtype != np.uint8:
            out = self.correct_exact(arr, scale=scale)
            return out[:, :, 0] if flat else out
        kind, plan, q, k, table = self._fast_path(h, w, ch, scale)
        src = np.ascontiguousarray(arr).reshape(-1)
        dst = np.empty(src.size, dtype=np.uint8)  # a 64-byte aligned one: no faster (measured)
        done = 0  # pixels corrected by an AVX-512 kernel; the scalar kernels do the rest
        if kind == "bucket":
            done = _BUCKET(src, plan[0], plan[1], dst, ch)
        elif kind == "search":
            done = _SIMD(src, plan[0], plan[1], dst, ch, plan[2])
        if done < h * w:
            rest, qs = slice(done * ch, None), slice(done * q.shape[1], None)
            lookup_rgb, lookup_shared, _ = _kernels()
            if q.shape[1] == ch == 3:
                lookup_rgb(src[rest], q.reshape(-1)[qs], k, table, dst[rest])
            else:
                lookup_shared(src[rest], q.reshape(-1)[qs], k, table, dst[rest], ch)
        return dst.reshape(h, w) if flat else dst.reshape(h, w, ch)

    def _fast_path(self, height: int, width: int, channels: int, scale: float) -> tuple:
        """``(kind, plan, q, k, table)`` of the uint8 fast path: the AVX-512 kernel and its plan
        (:meth:`_simd_choice`; ``(None, None)`` where the scalar kernel does it all) and :meth:`_fast_tables`. The last
        one is kept for the next call (a sequence of frames of one size), so that call checks nothing again."""
        use_simd = self.simd is not False and _simd_kernel() is not None and (self.simd or simd_allowed())
        key = (height, width, channels, scale, use_simd)
        last = self._last  # read once: another thread may replace it meanwhile
        if last is not None and last[0] == key:
            return last[1]
        self._check_channels(channels)
        q, k, table = self._fast_tables(height, width, channels, scale)
        kind, plan = self._simd_choice(height, width, channels, scale) if use_simd else (None, None)
        parts = (kind, plan, q, k, table)
        self._last = (key, parts)
        return parts

    def correct_exact(self, image: np.ndarray, *, scale: float = 1.0) -> np.ndarray:
        """The exact float formula ``f(scale * f^-1(I) / V(x))`` in float32 levels (not rounded).

        The reference for :meth:`correct`; slower (no tables).
        """
        scale = self._check_scale(scale)
        arr, flat = _as_hwc(image)
        h, w, ch = arr.shape
        self._check_channels(ch)
        levels = arr if arr.dtype == np.uint8 else _float_levels(arr)
        e = self.response.inverse(levels).astype(np.float64) * (self.gain_map(h, w).astype(np.float64) * scale)
        out = self.response.forward(e.astype(np.float32))
        return out[:, :, 0] if flat else out

    def suggest_scale(self, images: np.ndarray | Iterable[np.ndarray] | None = None, *,
                      percentile: float = 99.0, height: int | None = None, width: int | None = None) -> float:
        """A ``scale`` for :meth:`correct` that keeps ``percentile`` % of corrected values unclipped.

        With ``images`` (one image or an iterable of images of the scene), the scale is
        ``1 / P(f^-1(I) / V)`` over all their pixels and channels, with ``P`` the percentile. Without
        images it is the worst case of a white object seen everywhere: the ``100 - percentile``
        percentile of ``V`` at ``height x width`` (default: the calibration resolution). Values above 1
        brighten; the result is never clipped below by anything but the data.
        """
        if not (0 < percentile <= 100):
            raise ValueError(f"percentile must be in (0, 100], got {percentile}")
        if images is None:
            if self.vignetting is None:
                return 1.0
            if height is None or width is None:
                width, height = self.vignetting.resolution
            v = self.vignetting.evaluate(int(height), int(width))
            return float(np.percentile(v, 100.0 - percentile))
        if isinstance(images, np.ndarray):
            images = [images]
        values = [self.irradiance(img).ravel() for img in images]
        if not values:
            raise ValueError("images is empty; pass at least one image or None")
        high = float(np.percentile(np.concatenate(values), percentile))
        if not high > 0:
            raise ValueError("the images are black (irradiance percentile is 0); cannot suggest a scale")
        return 1.0 / high

    @staticmethod
    def _check_scale(scale: float) -> float:
        try:
            value = float(scale)
        except (TypeError, ValueError):
            raise TypeError(f"scale must be a number, got {scale!r}") from None
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"scale must be a positive finite number, got {scale!r}; use e.g. 0.8 to avoid "
                             "clipping at the corners")
        return value


def correct_reference_numpy(image: np.ndarray, response: CameraResponse, vignetting_map: np.ndarray, *,
                            scale: float = 1.0) -> np.ndarray:
    """The straightforward NumPy implementation of ``f(scale * f^-1(I) / V)`` for uint8 RGB images.

    The peer the benchmark (``scripts/bench_correction.py``) compares :meth:`Corrector.correct` with:
    a table look-up for ``f^-1``, a float division by the precomputed ``V`` map, ``np.interp`` for
    ``f``, rounding. ``vignetting_map`` is float32 ``(H, W, C)``.
    """
    channels = image.shape[2]
    tables = response.channel_tables(channels)
    out = np.empty(image.shape, dtype=np.uint8)
    for c in range(channels):
        e = tables[:, c][image[:, :, c]] * scale / vignetting_map[:, :, min(c, vignetting_map.shape[2] - 1)]
        out[:, :, c] = np.clip(np.rint(np.interp(e, tables[:, c], _LEVELS)), 0, 255)
    return out


def corrected_relative_stderr(vignetting: VignettingModel, height: int, width: int, *,
                              image: np.ndarray | None = None, response: CameraResponse | None = None) -> np.ndarray:
    """Relative standard error of the corrected irradiance ``f^-1(I) / V(x)`` per pixel and channel, float32
    ``(height, width, C)`` (opt-in; the correction itself never computes it).

    Without ``image``: the calibration's part, the relative standard error of ``V`` carried by a LUT fitted by
    radiomap (:attr:`radiometry.vignetting.LUTVignetting.stderr`), resampled to the size; the same for every
    frame. With ``image`` (uint8) and ``response``: that combined in quadrature with the image's own 8-bit
    quantisation, ``f^-1'(I) / (sqrt(12) f^-1(I))`` (infinite at level 0, where ``f^-1 = 0``).
    ValueError when the model carries no standard error (a polynomial, a foreign format, an older file)."""
    from radiometry.vignetting import LUTVignetting

    if not isinstance(vignetting, LUTVignetting) or vignetting.stderr is None:
        raise ValueError(f"{type(vignetting).__name__} carries no standard error; only a LUT fitted by radiomap "
                         "vignetting (saved as .npz) has one")
    se = vignetting.evaluate_stderr(height, width).astype(np.float64)
    if image is None:
        return se.astype(np.float32)
    if response is None:
        raise ValueError("pass the response with the image: the quantisation error is f^-1'(I) / f^-1(I)")
    img, _ = _as_hwc(np.asarray(image))
    if img.dtype != np.uint8 or img.shape[:2] != (height, width):
        raise ValueError(f"image must be uint8 of size {width}x{height}, got {img.dtype} {img.shape}")
    ch = se.shape[2]
    tables = response.channel_tables(ch).astype(np.float64)
    with np.errstate(divide="ignore"):
        quant = np.gradient(tables, axis=0) / (np.sqrt(12.0) * tables)  # (256, C)
    q = np.stack([quant[img[:, :, min(c, img.shape[2] - 1)], c] for c in range(ch)], axis=-1)
    return np.hypot(se, q).astype(np.float32)


__all__ = ["Corrector", "correct_reference_numpy", "corrected_relative_stderr", "simd_available"]
