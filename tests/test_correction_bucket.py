"""The uint8 correction's bucket kernel (radiometry/_ckernels_bucket.h) and its plan
(``radiometry.correction._build_bucket_plan``): every index of synthetic tables built to reach each form of the plan
(direct and clamped, thresholds at bucket edges, levels below the shift, overflow past 16 bits, windows at 128 and
elsewhere, one to RM_BK_NMAX thresholds per bucket), the cases where it must decline (the search kernel or the scalar
path then runs, same bytes) and real response curves. Expected outputs are ``part[j]``, indexed here with NumPy.
tests/test_correction_simd.py compares whole images three ways with both kernels."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from radiometry import correction
from radiometry.correction import Corrector, _build_bucket_plan, simd_available
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_correction_simd import needs_simd, radial, three_ways  # noqa: E402

PARAMS = -64  # the plan row's parameters: n, w0, clamp, neg, under, over


def nmax() -> int:
    from radiometry._native import compiled

    c = compiled("radiometry._ckernels")
    if c is None or not hasattr(c, "bucket_nmax"):
        pytest.skip("the C kernels are not in use")
    return int(c.bucket_nmax)


def run_every_index(part: np.ndarray, q: np.ndarray, k: np.ndarray, levels: np.ndarray):
    """Plan and run the kernel on one channel (q per pixel, k per level, ``levels`` the image); returns the plan's
    parameters after checking the kernel's output against ``part[q + k[level]]`` on every whole block."""
    plan = _build_bucket_plan(q[:, None].astype(np.uint16), k[None, :].astype(np.uint32), part, [part.size], 1)
    assert plan is not None
    img = levels.astype(np.uint8)
    out = np.empty_like(img)
    done = correction._BUCKET(img, plan[0], plan[1], out, 1)
    assert done == img.size // 64 * 64
    want = part[q[:done].astype(np.int64) + k[levels[:done]].astype(np.int64)]
    np.testing.assert_array_equal(out[:done], want)
    return plan[1][0, PARAMS:PARAMS + 6].astype(int)


def every_j(size: int):
    """q = j for j = 0..size-1 (padded to whole blocks), k = 0 for every level, all images at level 0."""
    n = (size + 63) // 64 * 64
    return np.minimum(np.arange(n), size - 1), np.zeros(256, dtype=np.int64), np.zeros(n, dtype=np.int64)


def staircase(size: int, thresholds) -> np.ndarray:
    """A channel's table of ``size`` entries stepping up by one level at each threshold."""
    part = np.zeros(size, dtype=np.uint8)
    for t in sorted(thresholds):
        part[t:] += 1
    return part


def random_table(rng, size: int, start: int, sparse: int, dense: int) -> np.ndarray:
    """A non-decreasing table starting at level ``start`` (thresholds at index 0), ``sparse`` thresholds spread over
    the whole table at least 200 steps apart, then ``dense`` random ones in its last quarter (two or more per bucket
    there, as the bright end of a real response has), some of them equal (steps of two levels)."""
    gaps = size * 3 // 4 // max(sparse, 1)
    spread = [int(g) for g in np.arange(1, sparse + 1) * gaps + rng.integers(-gaps // 8, gaps // 8 + 1, sparse)]
    crowd = rng.integers(size * 3 // 4, size, dense)
    return (start + staircase(size, spread + list(crowd))).astype(np.uint8)


@needs_simd
@pytest.mark.parametrize("size, start, sparse, dense, seed", [(65536, 0, 60, 150, 0), (20000, 17, 40, 100, 1),
                                                             (300, 0, 20, 60, 2), (65536, 3, 0, 0, 3),
                                                             (40000, 0, 50, 150, 4), (1000, 5, 30, 100, 5)])
def test_every_index_of_random_tables(size, start, sparse, dense, seed):
    """Random tables with a flat start, outputs above 0 at index 0 (thresholds at 0), never reaching 255 or
    saturating (equal thresholds); short tables scaled up by ``s`` (j' = j << s)."""
    part = random_table(np.random.default_rng(seed), size, start, sparse, dense)
    params = run_every_index(part, *every_j(size))
    assert params[2] == 0  # the direct form


def test_uniformly_spread_thresholds_decline_the_bucket_plan():
    """Thresholds spread evenly over 65536 steps put two in a bucket here and there across more than 128 buckets:
    no bucket plan, the search kernel's applies (same bytes: tests/test_correction_simd.py)."""
    size = 65536
    part = np.sort(np.random.default_rng(6).integers(0, 256, size)).astype(np.uint8)
    q, k = np.arange(size)[:, None].astype(np.uint16), np.zeros((1, 256), dtype=np.uint32)
    assert _build_bucket_plan(q, k, part, [size], 1) is None
    assert correction._build_simd_plan(q, k, part, [size], 1) is not None


@needs_simd
def test_thresholds_on_bucket_edges_and_full_buckets():
    """Thresholds at multiples of 256 (counted by base alone), at 255 steps into a bucket, and buckets holding the most
    thresholds the kernel takes (RM_BK_NMAX), in a window at 128 and in one that is not."""
    m = nmax()
    size = 65536
    for start in (128, 40):  # the buckets holding several thresholds begin at 128 (the top-bit window) or at 40
        full = [256 * (start + 5) + 1 + 20 * i for i in range(m)]  # m thresholds in one bucket
        edges = [256 * b for b in range(1, 30, 3)] + [256 * 31 + 255, 256 * (start + 60) + 7, 256 * (start + 60) + 9]
        part = staircase(size, full + edges)
        q = np.arange(size)
        k = np.zeros(256, dtype=np.int64)
        params = run_every_index(part, q, k, np.zeros(size, dtype=np.int64))
        assert params[0] == m and params[1] == (128 if start == 128 else start + 5)


@needs_simd
@pytest.mark.parametrize("first", [1000, 1])
def test_clamped_form_levels_below_the_shift_and_overflow(first):
    """A table longer than 65536 entries: j' = j - S leaves 16 bits on both sides (levels whose k is below S, sums
    past 65535); every (q, level) pair of a grid, compared with the table."""
    size = 90000
    part = staircase(size, [first, first + 300, first + 301, 30000, 60000, first + 65000])
    k = np.zeros(256, dtype=np.int64)
    k[:18] = 5000 * np.arange(18)  # non-decreasing; j = q + k covers 0..89999
    k[18:] = k[17]
    q = np.tile(np.arange(5000), 18)
    levels = np.repeat(np.arange(18), 5000)
    params = run_every_index(part, q, k, levels)
    assert params[2] == 1  # the clamped form
    assert params[5] == 6  # over: every threshold
    if first > 1:
        assert params[3] > 0  # levels below the shift (their sums can fall below 0)


@needs_simd
def test_clamped_plan_needs_k_non_decreasing():
    """The clamped form finds the levels below S by their number, so k must be non-decreasing: a table where it is
    not gets no bucket plan (the search kernel's plan still applies)."""
    size = 90000
    part = staircase(size, [1000, 30000, 60000, 66000])
    k = np.zeros(256, dtype=np.int64)
    k[:18] = 5000 * np.arange(18)
    k[18:] = k[17]
    k[5] = 0  # a level above the first ones with k below S: not non-decreasing
    q = np.tile(np.arange(5000), 18)[:, None].astype(np.uint16)
    assert _build_bucket_plan(q, k[None, :].astype(np.uint32), part, [size], 1) is None
    assert correction._build_simd_plan(q, k[None, :].astype(np.uint32), part, [size], 1) is not None


def test_clamped_plan_with_every_level_below_the_shift_is_declined_not_an_error():
    """When every level's k lies below the shift S (the largest gain index dwarfs k's range), the kernel's byte
    count of such levels would be 256: the plan is declined (it raised OverflowError; review, 2026-11-28)."""
    n = 66048
    q = (np.arange(n) * 65000 // (n - 1)).astype(np.uint16)[:, None]
    k = np.linspace(0, 1000, 256).astype(np.uint32)[None, :]
    part = staircase(65000 + 1001, [30000, 40000, 50000, 60000, 65500])
    assert _build_bucket_plan(q, k, part, [part.size], 1) is None


def test_plan_declines_too_many_thresholds_per_bucket_or_a_wide_window():
    m = nmax()
    size = 65536
    crowded = staircase(size, [256 * 100 + 1 + 2 * i for i in range(m + 1)])  # m + 1 in one bucket
    spread = staircase(size, [256 * 10 + 1, 256 * 10 + 2, 256 * 200 + 1, 256 * 200 + 2])  # 2-threshold buckets 190 apart
    q = np.arange(size)[:, None].astype(np.uint16)
    k = np.zeros((1, 256), dtype=np.uint32)
    for part in (crowded, spread):
        assert _build_bucket_plan(q, k, part, [size], 1) is None
        assert correction._build_simd_plan(q, k, part, [size], 1) is not None  # the search kernel's plan applies


@needs_simd
def test_a_declined_plan_falls_back_to_the_search_kernel_with_the_same_bytes(monkeypatch):
    """A steep knee under mild vignetting (flat-then-steep curve: 16 thresholds in a bucket) runs the search kernel;
    an image wider than the bucket plan's reach (gain_levels past 16 bits) runs the scalar path alone."""
    from response_curves import flat_then_steep_curve

    h, w = 48, 64
    img = np.random.default_rng(8).integers(0, 256, (h, w, 3), dtype=np.uint8)
    curve = CameraResponse.from_table(np.stack([flat_then_steep_curve()] * 3, axis=1))
    fast, _ = three_ways(curve, radial(h, w, 0.9), img, 1.0)
    assert fast._simd_choice(h, w, 3, 1.0)[0] == "search"
    fast, _ = three_ways(curve, radial(h, w, 0.3), img, 0.8, gain_levels=65535)
    assert fast._simd_choice(h, w, 3, 0.8) == (None, None)


def real_curves():
    from response_curves import EUROC_PCALIB, gamma_curve, kink_curve, read_pcalib, s_curve

    curves = {"gamma-2.2": gamma_curve(2.2), "gamma-1": gamma_curve(1.0), "s-curve": s_curve(),
              "kink-4x": kink_curve()}
    if EUROC_PCALIB.exists():
        curves["euroc (measured)"] = read_pcalib(EUROC_PCALIB)
    return curves


@needs_simd
@pytest.mark.parametrize("vmin, scale", [(0.3, 0.8), (0.3, 1.0), (0.8, 1.0)])
def test_real_response_curves_take_the_bucket_kernel(vmin, scale):
    """The test set of response curves (tests/response_curves.py, the EuRoC camera's measured one among them) under
    strong and mild vignetting at 640x480, same bytes as the scalar path: the bucket kernel runs on all but the
    toe-and-shoulder S-curve under strong vignetting (14 thresholds in a bucket of its steep middle: the search
    kernel runs)."""
    h, w = 480, 640
    img = np.random.default_rng(9).integers(0, 256, (h, w, 3), dtype=np.uint8)
    vignetting = radial(h, w, vmin)
    kinds = {}
    for name, curve in real_curves().items():
        response = CameraResponse.from_table(np.stack([curve] * 3, axis=1))
        fast, _ = three_ways(response, vignetting, img, scale)
        kinds[name] = fast._simd_choice(h, w, 3, scale)[0]
    expected = {name: "search" if name == "s-curve" and vmin < 0.5 else "bucket" for name in kinds}
    assert kinds == expected


@needs_simd
def test_simulator_presets_take_the_bucket_kernel():
    from radiometry.simulation import CameraSpec, SimulatedCamera

    h, w = 120, 160
    img = np.random.default_rng(10).integers(0, 256, (h, w, 3), dtype=np.uint8)
    for preset in ("xtion", "asymmetric", "ideal"):
        camera = SimulatedCamera(CameraSpec.preset(preset, width=w, height=h))
        model = LUTVignetting(camera.vignetting) if camera.vignetting is not None else None
        fast, _ = three_ways(camera.response, model, img, 0.8)
        assert fast._simd_choice(h, w, 3, 0.8)[0] == "bucket", preset


def test_bucket_kernel_arguments_are_checked():
    from radiometry._native import compiled

    c = compiled("radiometry._ckernels")
    if c is None or not hasattr(c, "correct_bucket"):
        pytest.skip("the C kernels are not in use")
    m, width = int(c.bucket_nmax), 1024 + 128 * (int(c.bucket_nmax) - 1) + 64
    img, out = np.zeros(192, np.uint8), np.zeros(192, np.uint8)
    qplan, plan = np.zeros((1, 3, 128), np.uint8), np.zeros((3, width), np.uint8)
    with pytest.raises(ValueError, match="qplan"):
        c.correct_bucket(img, np.zeros((2, 3, 128), np.uint8), plan, out, 3)  # more blocks than pixels
    with pytest.raises(ValueError, match="plan"):
        c.correct_bucket(img, qplan, np.zeros((3, width - 1), np.uint8), out, 3)
    with pytest.raises(ValueError, match="img"):
        c.correct_bucket(img[:191], qplan, plan, out, 3)
    with pytest.raises(ValueError, match="out"):
        c.correct_bucket(img, qplan, plan, np.zeros(191, np.uint8), 3)
    bad = plan.copy()
    bad[1, PARAMS] = m + 1
    with pytest.raises(ValueError, match="thresholds per bucket"):
        c.correct_bucket(img, qplan, bad, out, 3)
    if simd_available():
        assert c.correct_bucket(img, qplan, plan, out, 3) == 64
