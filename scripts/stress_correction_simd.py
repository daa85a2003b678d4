#!/usr/bin/env python
"""Stress the uint8 correction's AVX-512 kernels against the scalar path (issue 33): the same bytes on varied inputs.

Where the CPU has AVX-512 VBMI and GFNI, ``Corrector.correct`` runs ``radiometry._ckernels.correct_bucket``
(radiometry/_ckernels_bucket.h: bucket look-ups) where its plan applies, else ``correct_simd``
(radiometry/_ckernels_simd.h: a binary search of per-channel thresholds), and the scalar gather
``table[q + k[c, I]]`` elsewhere. Every case here corrects one image four ways and compares them byte for byte:

- the default path (an AVX-512 kernel on the whole 64-pixel blocks, the scalar kernel on the rest);
- the same with the bucket kernel turned off (the search kernel where it applies);
- ``Corrector(simd=False)``: the scalar C kernel (or Numba's);
- NumPy indexing of the same tables, ``table[q + k[c, I]]``, written here (independent of the kernels).

Cases are drawn per run: responses (gamma 0.3-3.5, S-curves, random increasing tables with near-flat runs, 1 or 3
channels), vignetting (none, or a radial LUT at the image's size falling to 0.02-1 with a random centre, 1 or 3
channels, sometimes noisy), sizes from 1x1 to 640x480 (mostly not multiples of 64 pixels), 1 or 3 image channels
((H, W), (H, W, 1), (H, W, 3)), scales 0.005-50 (all dark to all saturated), gain levels 2-65535 (65535 makes 32-bit
gain indices, past the AVX kernel: the scalar path then runs alone, which is checked too), images random,
constant, a ramp of all 256 levels, or mostly 0 and 255, given contiguous, strided or Fortran-ordered. Tables whose
thresholds span more than 16 bits (everything darkened under mild vignetting) also run the scalar path alone.

Prints a line per failing case and a summary (how many cases ran each AVX-512 kernel); exits 1 on any failure.
Usage::

    python scripts/stress_correction_simd.py --runs 500     # ~0.05-0.5 s per case
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

SIZES = [(1, 1), (1, 63), (1, 64), (1, 65), (2, 33), (7, 13), (8, 8), (3, 100), (17, 129), (31, 97), (64, 64),
         (45, 61), (100, 190), (120, 160), (121, 161), (240, 320), (480, 640)]


def random_response(rng: np.random.Generator, channels: int):
    from radiometry.response import CameraResponse

    x = np.arange(256) / 255.0
    kind = rng.integers(3)
    cols = []
    for _ in range(channels):
        if kind == 0:
            col = x ** rng.uniform(0.3, 3.5)
        elif kind == 1:
            col = x ** rng.uniform(1.5, 2.5) * (1 + rng.uniform(0, 0.3) * np.sin(np.pi * x))
        else:  # random increments, some tiny (near-flat runs: f^-1 must be strictly increasing)
            inc = rng.exponential(1.0, 255) * np.where(rng.random(255) > 0.1, 1.0, 1e-6)
            first = rng.uniform(0, 0.05)
            col = np.concatenate([[first], first + 1e-3 + np.cumsum(inc)])
        cols.append(col / col[-1] + (1e-4 * x if kind != 2 else 0))
    return CameraResponse.from_table(np.stack(cols, axis=1))


def random_vignetting(rng: np.random.Generator, h: int, w: int, channels: int):
    from radiometry.vignetting import LUTVignetting

    if rng.random() < 0.15:
        return None
    lh, lw = h, w  # at the image's size (a LUT is only resampled to the same aspect ratio)
    yy, xx = np.mgrid[0:lh, 0:lw]
    cy, cx = rng.uniform(0.3, 0.7) * lh, rng.uniform(0.3, 0.7) * lw
    r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (lh * lh + lw * lw) * 4
    vmin = rng.uniform(0.02, 1.0)
    planes = [1 - (1 - vmin) * np.clip(r2 * rng.uniform(0.5, 1.5), 0, 1) for _ in range(channels)]
    lut = np.stack(planes, axis=2)
    if rng.random() < 0.3:
        lut = lut * rng.uniform(0.97, 1.03, lut.shape)
    return LUTVignetting(np.clip(lut, 0.01, 1.0).astype(np.float32))


def random_image(rng: np.random.Generator, h: int, w: int, channels: int, gray2d: bool) -> np.ndarray:
    shape = (h, w) if gray2d else (h, w, channels)
    kind = rng.integers(4)
    if kind == 0:
        img = rng.integers(0, 256, shape, dtype=np.uint8)
    elif kind == 1:
        img = np.full(shape, rng.integers(0, 256), dtype=np.uint8)
    elif kind == 2:  # every level, shifted per row and channel
        img = ((np.arange(h * w * (1 if gray2d else channels)) * 7 + rng.integers(256)) % 256).astype(np.uint8)
        img = img.reshape(shape)
    else:
        img = np.where(rng.random(shape) < 0.5, 0, 255).astype(np.uint8)
    layout = rng.integers(3)
    if layout == 1:  # a strided view of a larger array
        big = np.zeros((h, 2 * w) + shape[2:], dtype=np.uint8)
        big[:, ::2] = img
        img = big[:, ::2]
    elif layout == 2:
        img = np.asfortranarray(img)
    return img


def random_case(rng: np.random.Generator) -> dict:
    h, w = SIZES[rng.integers(len(SIZES))] if rng.random() < 0.6 else (int(rng.integers(1, 90)),
                                                                     int(rng.integers(1, 150)))
    channels = 3 if rng.random() < 0.7 else 1
    gray2d = channels == 1 and rng.random() < 0.5
    rc = channels if rng.random() < 0.7 else 1
    vc = channels if rng.random() < 0.6 else 1
    return {"size": (h, w), "channels": channels, "gray2d": gray2d,
            "response": random_response(rng, rc), "vignetting": random_vignetting(rng, h, w, vc),
            "scale": float(np.exp(rng.uniform(np.log(0.005), np.log(50)))),
            "gain_levels": int(rng.choice([2, 16, 256, 2048, 2048, 4096, 65535])),
            "image": random_image(rng, h, w, channels, gray2d)}


def table_lookup(corrector, img: np.ndarray, scale: float) -> np.ndarray:
    """``table[q + k[c, I]]`` by NumPy indexing of the fast path's tables (no kernel)."""
    arr = img if img.ndim == 3 else img[:, :, None]
    h, w, ch = arr.shape
    q, k, table = corrector._fast_tables(h, w, ch, scale)
    levels = arr.reshape(-1, ch).astype(np.int64)
    idx = q.astype(np.int64) + k[np.arange(ch)[None, :], levels]
    out = table[idx].reshape(h, w, ch)
    return out if img.ndim == 3 else out[:, :, 0]


def kernel_run(corrector, img: np.ndarray, scale: float) -> str | None:
    """The AVX-512 kernel ``corrector.correct(img)`` runs: ``"bucket"``, ``"search"`` or None (the scalar path)."""
    from radiometry.correction import simd_available

    arr = img if img.ndim == 3 else img[:, :, None]
    h, w, ch = arr.shape
    if not simd_available() or h * w < 64:
        return None
    return corrector._simd_choice(h, w, ch, scale)[0]


def without_bucket():
    """A context in which new Correctors never use the bucket kernel (its plan is None): the search kernel runs."""
    from contextlib import contextmanager

    from radiometry import correction

    @contextmanager
    def ctx():
        saved = correction._build_bucket_plan
        correction._build_bucket_plan = lambda *args: None
        try:
            yield
        finally:
            correction._build_bucket_plan = saved

    return ctx()


def check(case: dict) -> tuple[bool, str | None, str]:
    """``(passed, kernel, detail)`` for one case; ``kernel``: the AVX-512 kernel of the default path, or None."""
    from radiometry.correction import Corrector

    img, scale = case["image"], case["scale"]
    args, kw = (case["response"], case["vignetting"]), {"gain_levels": case["gain_levels"]}
    fast = Corrector(*args, **kw)
    a = fast.correct(img, scale=scale)
    with without_bucket():
        searched = Corrector(*args, **kw)
        d = searched.correct(img, scale=scale)
    b = Corrector(*args, simd=False, **kw).correct(img, scale=scale)
    c = table_lookup(fast, img, scale)
    ok = (a.dtype == np.uint8 and a.shape == img.shape and np.array_equal(a, b) and np.array_equal(a, c)
          and np.array_equal(d, c))
    detail = "" if ok else (f"differs at {int(np.sum(a != c))} values from the table, {int(np.sum(a != b))} from "
                            f"the scalar path, search kernel at {int(np.sum(d != c))}")
    return ok, kernel_run(fast, img, scale), detail


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    from radiometry.correction import simd_available

    rng = np.random.default_rng(args.seed)
    failures = 0
    ran = {"bucket": 0, "search": 0, None: 0}
    start = time.perf_counter()
    for run in range(args.runs):
        case = random_case(rng)
        ok, kernel, detail = check(case)
        ran[kernel] += 1
        if not ok:
            failures += 1
            img = case["image"]
            print(f"case {run}: FAILED {detail} (size {case['size']}, image {img.shape} {img.strides}, scale "
                  f"{case['scale']:.4g}, gain_levels {case['gain_levels']})")
    print(f"{args.runs} cases, {failures} failed; AVX-512 kernel run (available here: {simd_available()}): bucket "
          f"{ran['bucket']}, search {ran['search']}, none {ran[None]}; {time.perf_counter() - start:.1f} s")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
