"""The uint8 correction's AVX-512 kernels (radiometry/_ckernels_bucket.h, _ckernels_simd.h): byte for byte the scalar
path's output.

Every check compares three ways of correcting the same image: the default path (an AVX-512 kernel on whole
64-pixel blocks where the CPU has AVX-512 VBMI and GFNI, the scalar kernel on the rest), ``Corrector(simd=False)``
(the scalar kernel alone) and NumPy indexing of the fast path's tables, ``table[q + k[c, I]]`` (no kernel). The
tests marked with the ``kernel`` fixture run twice: as the default path chooses (the bucket kernel wherever its
plan applies) and with the bucket kernel turned off (the binary search). Tests that need a kernel to run skip on
CPUs without it; the fallback tests run everywhere. tests/test_correction_bucket.py tests the bucket plan itself;
``scripts/stress_correction_simd.py`` runs hundreds of random cases; a smaller loop of it runs here.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import build_without_simd

from radiometry import correction
from radiometry.correction import Corrector, simd_available
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "stress_correction_simd.py"
needs_simd = pytest.mark.skipif(not simd_available(), reason="this CPU (or build) has no AVX-512 VBMI/GFNI kernel")


def _stress():
    spec = importlib.util.spec_from_file_location("radiomap_script_stress_correction_simd", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def radial(h: int, w: int, vmin: float, channels: int = 3, centre=(0.5, 0.5)) -> LUTVignetting:
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((yy - centre[0] * h) ** 2 + (xx - centre[1] * w) ** 2) / ((h / 2) ** 2 + (w / 2) ** 2)
    planes = [1 - (1 - vmin) * np.clip(r2 * (1 + 0.1 * c), 0, 1) for c in range(channels)]
    return LUTVignetting(np.stack(planes, axis=2).astype(np.float32))


def s_curve(channels: int = 3) -> CameraResponse:
    x = np.linspace(0, 1, 256)
    cols = [x ** g * (1 + 0.2 * np.sin(np.pi * x)) for g in (2.0, 2.2, 1.8)[:channels]]
    return CameraResponse.from_table(np.stack(cols, axis=1) + 1e-4 * x[:, None])


def gammas(channels: int = 3) -> CameraResponse:
    """Gamma 2.0, 2.2, 1.8 per channel: tables the bucket kernel takes (tests/test_correction_bucket.py)."""
    x = np.linspace(0, 1, 256)
    return CameraResponse.from_table(np.stack([x ** g for g in (2.0, 2.2, 1.8)[:channels]], axis=1))


def three_ways(response, vignetting, img, scale=1.0, **kwargs):
    fast = Corrector(response, vignetting, **kwargs)
    scalar = Corrector(response, vignetting, simd=False, **kwargs)
    a, b = fast.correct(img, scale=scale), scalar.correct(img, scale=scale)
    c = _stress().table_lookup(fast, img, scale)
    assert a.dtype == np.uint8 and a.shape == img.shape
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    return fast, a


def ran_kernel(corrector, img, scale) -> bool:
    return _stress().kernel_run(corrector, img, scale) is not None


@pytest.fixture(params=["default", "search"])
def kernel(request, monkeypatch):
    """``default``: the kernel the default path chooses; ``search``: the bucket kernel turned off."""
    if request.param == "search":
        monkeypatch.setattr(correction, "_build_bucket_plan", lambda *args: None)
    return request.param


@needs_simd
@pytest.mark.parametrize("h, w", [(1, 64), (1, 65), (2, 33), (8, 8), (7, 13), (3, 100), (17, 129), (31, 97),
                                  (64, 64), (121, 161), (480, 640)])
@pytest.mark.parametrize("channels", [1, 3])
def test_kernel_matches_scalar_path_at_varied_sizes(h, w, channels, kernel):
    img = np.random.default_rng(h * w + channels).integers(0, 256, (h, w, channels), dtype=np.uint8)
    # every size here has at least one whole block of 64 pixels. The bucket kernel takes the gammas' tables and the
    # one-channel S-curve's; the three S-curves put too many thresholds in a bucket of one channel: search kernel
    for response, choice in [(gammas(channels), "bucket"), (s_curve(channels), "search" if channels == 3 else "bucket")]:
        fast, _ = three_ways(response, radial(h, w, 0.3, channels), img, 0.8)
        assert _stress().kernel_run(fast, img, 0.8) == ("search" if kernel == "search" else choice)


def test_images_smaller_than_a_block_take_the_scalar_path():
    for h, w in [(1, 1), (1, 63), (7, 9)]:
        img = np.random.default_rng(h * w).integers(0, 256, (h, w, 3), dtype=np.uint8)
        fast, _ = three_ways(s_curve(), radial(h, w, 0.4), img, 0.9)
        assert not ran_kernel(fast, img, 0.9)


@needs_simd
@pytest.mark.parametrize("scale", [0.005, 0.3, 1.0, 4.0, 50.0])
@pytest.mark.parametrize("vmin", [0.02, 0.2, 0.8, 0.99])
def test_every_level_at_extreme_gains(scale, vmin, kernel):
    h, w = 64, 256  # each row holds the 256 levels, shifted per row and channel: every level at every gain
    levels = (np.arange(w)[None, :, None] + 37 * np.arange(h)[:, None, None] + 85 * np.arange(3)) % 256
    img = levels.astype(np.uint8)
    fast, out = three_ways(CameraResponse.gamma(2.2), radial(h, w, vmin), img, scale)
    assert np.unique(out).size > 10  # the comparison above is not all on one clipped level
    if scale == 0.005:
        assert np.median(out) < 30
    if scale == 50.0:
        assert np.mean(out == 255) > 0.5
    # the kernel ran except where the thresholds span more than 16 bits (everything darkened, mild vignetting)
    assert ran_kernel(fast, img, scale) or (scale < 1 and vmin > 0.5)


@needs_simd
@pytest.mark.parametrize("vignetting", ["none", "one-channel", "three-channel"])
@pytest.mark.parametrize("shape", [(48, 80), (48, 80, 1), (48, 80, 3)])
def test_grayscale_shared_gain_and_flat_field(vignetting, shape, kernel):
    h, w = shape[:2]
    channels = shape[2] if len(shape) == 3 else 1
    if vignetting == "three-channel" and channels == 1:
        pytest.skip("a 3-channel model does not apply to a grayscale image")
    model = {"none": None, "one-channel": radial(h, w, 0.3, 1), "three-channel": radial(h, w, 0.3, 3)}[vignetting]
    img = np.random.default_rng(1).integers(0, 256, shape, dtype=np.uint8)
    fast, _ = three_ways(s_curve(1 if channels == 1 else 3), model, img, 0.7)
    assert ran_kernel(fast, img, 0.7)


@needs_simd
def test_both_forms_of_the_kernel_run(kernel):
    """The direct form (every index below 65535) and the clamped one (mild vignetting: longer tables), of the search
    kernel's plan; the default path runs the bucket kernel (its own two forms: tests/test_correction_bucket.py)."""
    h, w = 48, 64
    img = np.random.default_rng(2).integers(0, 256, (h, w, 3), dtype=np.uint8)
    forms = set()
    for response, vmin in [(s_curve(), 0.3), (CameraResponse.gamma(2.2), 0.8), (CameraResponse.gamma(1.0), 0.95)]:
        fast, _ = three_ways(response, radial(h, w, vmin), img, 1.0)
        forms.add(fast._simd_plan(h, w, 3, 1.0)[2])
    assert forms == {False, True}


@needs_simd
@pytest.mark.parametrize("layout", ["strided", "fortran", "transposed", "negative-step"])
def test_non_contiguous_images(layout, kernel):
    rng = np.random.default_rng(3)
    base = rng.integers(0, 256, (96, 130, 3), dtype=np.uint8)
    img = {"strided": base[::2, ::2], "fortran": np.asfortranarray(base[:48, :65]),
           "transposed": base[:65, :48].transpose(1, 0, 2), "negative-step": base[:48, ::-2]}[layout]
    assert not img.flags.c_contiguous
    h, w = img.shape[:2]
    three_ways(s_curve(), radial(h, w, 0.3), img, 0.8)


def test_gain_levels_past_16_bits_fall_back_to_the_scalar_kernel():
    h, w = 48, 64
    img = np.random.default_rng(4).integers(0, 256, (h, w, 3), dtype=np.uint8)
    fast, _ = three_ways(s_curve(), radial(h, w, 0.3), img, 0.8, gain_levels=65535)
    assert fast._simd_plan(h, w, 3, 0.8) is None  # q is uint32: no plan, the scalar kernel did it all


@pytest.mark.parametrize("how", ["env", "argument", "no-kernel", "kernel-declines"])
def test_dispatch_falls_back_to_the_scalar_path(monkeypatch, how):
    h, w = 48, 64
    img = np.random.default_rng(5).integers(0, 256, (h, w, 3), dtype=np.uint8)
    expected = Corrector(s_curve(), radial(h, w, 0.3), simd=False).correct(img, scale=0.8)
    calls = []
    correction._kernels()
    kernel, bucket = correction._SIMD, correction._BUCKET

    def spy(*args):
        calls.append(args[4])
        return kernel(*args) if kernel is not None else 0

    def bucket_spy(*args):
        calls.append(args[4])
        return bucket(*args) if bucket is not None else 0

    monkeypatch.setattr(correction, "_SIMD", spy)
    monkeypatch.setattr(correction, "_BUCKET", bucket_spy)
    kwargs = {}
    if how == "env":
        monkeypatch.setenv("RADIOMAP_SIMD", "0")
        assert not simd_available()
    elif how == "argument":
        kwargs["simd"] = False
    elif how == "no-kernel":  # a CPU without AVX-512 VBMI/GFNI, or the Numba kernels
        monkeypatch.setattr(correction, "_SIMD", None)
        assert not simd_available()
    else:  # the C kernel's own CPU check said no: it corrected 0 pixels
        monkeypatch.setattr(correction, "_SIMD", lambda *args: calls.append(args[4]) or 0)
        monkeypatch.setattr(correction, "_BUCKET", lambda *args: calls.append(args[4]) or 0)
    out = Corrector(s_curve(), radial(h, w, 0.3), **kwargs).correct(img, scale=0.8)
    np.testing.assert_array_equal(out, expected)
    assert calls == ([3] if how == "kernel-declines" else [])


@needs_simd
def test_simd_true_overrides_the_environment(monkeypatch):
    monkeypatch.setenv("RADIOMAP_SIMD", "0")
    h, w = 48, 64
    img = np.random.default_rng(6).integers(0, 256, (h, w, 3), dtype=np.uint8)
    calls = []
    bucket, search = correction._BUCKET, correction._SIMD
    monkeypatch.setattr(correction, "_BUCKET", lambda *args: calls.append(1) or bucket(*args))
    monkeypatch.setattr(correction, "_SIMD", lambda *args: calls.append(1) or search(*args))
    out = Corrector(s_curve(), radial(h, w, 0.3), simd=True).correct(img, scale=0.8)
    np.testing.assert_array_equal(out, Corrector(s_curve(), radial(h, w, 0.3), simd=False).correct(img, scale=0.8))
    assert calls == [1]


@needs_simd
def test_kernel_on_synthetic_tables_every_index():
    """Every index j of a channel's table, through the kernel alone: random non-decreasing outputs with long flat
    runs, outputs that start above 0 and never reach 255, thresholds at index 0 and past the last index."""
    from radiometry.correction import _build_simd_plan

    rng = np.random.default_rng(7)
    for size, lo, hi in [(65535, 0, 255), (20000, 17, 200), (300, 0, 255), (65535, 3, 3), (40000, 0, 254)]:
        part = np.sort(rng.integers(lo, hi + 1, size)).astype(np.uint8)
        part[:size // 7] = lo  # a long flat run at the start
        n = ((size + 63) // 64) * 64  # one value per index j (q = j, k = 0), padded to whole blocks
        q = np.minimum(np.arange(n), size - 1).astype(np.uint16)[:, None]
        k = np.zeros((1, 256), dtype=np.uint32)
        plan = _build_simd_plan(q, k, part, [size], 1)
        assert plan is not None and not plan[2]
        img = np.zeros(n, dtype=np.uint8)
        out = np.empty(n, dtype=np.uint8)
        assert correction._SIMD(img, plan[0], plan[1], out, 1, plan[2]) == n
        np.testing.assert_array_equal(out, part[q[:, 0]])


def test_kernel_arguments_are_checked():
    from radiometry._native import compiled

    c = compiled("radiometry._ckernels")
    if c is None or not hasattr(c, "correct_simd"):
        pytest.skip("the C kernels are not in use")
    img, out = np.zeros(192, np.uint8), np.zeros(192, np.uint8)
    qplan, plan = np.zeros((1, 3, 64), np.uint16), np.zeros((3, 1792), np.uint8)
    with pytest.raises(ValueError, match="qplan"):
        c.correct_simd(img, np.zeros((2, 3, 64), np.uint16), plan, out, 3, False)  # more blocks than pixels
    with pytest.raises(ValueError, match="plan"):
        c.correct_simd(img, qplan, np.zeros((3, 1280), np.uint8), out, 3, False)
    with pytest.raises(ValueError, match="img"):
        c.correct_simd(img[:191], qplan, plan, out, 3, False)
    with pytest.raises(ValueError, match="out"):
        c.correct_simd(img, qplan, plan, np.zeros(191, np.uint8), 3, False)


@pytest.mark.parametrize("seed", [0, 1])
def test_stress_loop(seed):
    """A short run of scripts/stress_correction_simd.py (the script runs hundreds)."""
    module = _stress()
    rng = np.random.default_rng(100 + seed)
    ran = {"bucket": 0, "search": 0, None: 0}
    for _ in range(40):
        ok, kernel, detail = module.check(module.random_case(rng))
        assert ok, detail
        ran[kernel] += 1
    assert (ran["bucket"] > 5 and ran["search"] > 2) or not simd_available(), ran


@pytest.mark.slow
def test_a_build_without_the_kernel_corrects_with_the_scalar_path(tmp_path):
    """``-DRM_NO_SIMD``: what a compiler other than GCC / Clang or a CPU other than x86 builds. The module says
    ``simd = 0``, ``correct_simd`` and ``correct_bucket`` correct no pixel, and its scalar kernels give the same
    bytes."""
    built = build_without_simd(tmp_path, "radiometry")
    repo = SCRIPT.parents[1]
    script = ("import sys, importlib.util, numpy as np; "
              "spec = importlib.util.spec_from_file_location('radiometry._ckernels', sys.argv[1]); "
              "c = importlib.util.module_from_spec(spec); spec.loader.exec_module(c); "
              "from radiometry.correction import Corrector; from radiometry.response import CameraResponse; "
              "from radiometry.vignetting import LUTVignetting; "
              "v = LUTVignetting(np.linspace(0.3, 1, 48 * 64).reshape(48, 64).astype(np.float32)); "
              "cor = Corrector(CameraResponse.gamma(2.2), v); img = np.arange(48 * 64 * 3).astype(np.uint8); "
              "q, k, t = cor._fast_tables(48, 64, 3, 0.8); qp, plan, clamp = cor._simd_plan(48, 64, 3, 0.8); "
              "out = np.empty_like(img); done = c.correct_simd(img, qp, plan, out, 3, clamp); "
              "ref = np.empty_like(img); c.lookup_shared(img, q.reshape(-1), k, t, ref, 3); "
              "want = cor.correct(img.reshape(48, 64, 3), scale=0.8).reshape(-1); "
              "bq, bp = cor._bucket_plan(48, 64, 3, 0.8); done2 = c.correct_bucket(img, bq, bp, out, 3); "
              "print(c.simd, done, done2, ref.tobytes() == want.tobytes())")
    run = subprocess.run([sys.executable, "-c", script, str(built)], cwd=repo, capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["0", "0", "0", "True"]


@needs_simd
@pytest.mark.parametrize("gap, applies", [(65533, True), (65534, False)])
def test_clamped_form_at_the_edge_of_16_bits(gap, applies):
    """A table longer than 65535 entries (the clamped form, indices moved to start 1 below the first threshold): a
    second threshold ``gap`` steps above the first. 65533 lands on 65534, the largest index; 65534 would land on
    65535, the never-reached marker, so no plan (the scalar path runs).
    Found by scripts/stress_correction_simd.py (seed 0, case 341) before the check was exact."""
    from radiometry.correction import _build_simd_plan

    size, first = 70000, 1000
    part = np.zeros(size, dtype=np.uint8)
    part[first:] = 1
    part[first + gap:] = 2
    levels = np.repeat(np.arange(14), 5000)  # j = q + k[I] = q + 5000 I covers 0..69999
    q = (np.arange(levels.size) % 5000).astype(np.uint16)[:, None]
    k = np.zeros((1, 256), dtype=np.uint32)
    k[0, :14] = 5000 * np.arange(14)
    plan = _build_simd_plan(q, k, part, [size], 1)
    if not applies:
        assert plan is None
        return
    assert plan is not None and plan[2]  # the clamped form
    img = levels.astype(np.uint8)
    out = np.empty_like(img)
    done = correction._SIMD(img, plan[0], plan[1], out, 1, plan[2])
    assert done == img.size // 64 * 64
    np.testing.assert_array_equal(out[:done], part[q[:done, 0].astype(np.int64) + k[0, levels[:done]]])
    assert {1, 2} <= set(np.unique(out[:done]))  # both thresholds crossed


def test_one_corrector_over_changing_sizes_scales_and_settings(monkeypatch):
    """Corrector.correct keeps the last size's kernel choice for the next call (_fast_path): a change of size, scale,
    channels, ``RADIOMAP_SIMD`` or ``simd`` between calls must not reuse it."""
    fast = Corrector(gammas(), radial(96, 128, 0.3))
    rng = np.random.default_rng(8)
    calls = []
    bucket = correction._BUCKET
    if bucket is not None:
        monkeypatch.setattr(correction, "_BUCKET", lambda *args: calls.append(args[0].size) or bucket(*args))
    steps = [((96, 128, 3), 0.8, None), ((48, 64, 3), 0.8, None), ((96, 128, 3), 0.5, None), ((96, 128, 3), 0.8, "0"),
             ((96, 128, 3), 0.8, None), ((96, 128, 3), 0.8, "off")]
    for shape, scale, env in steps:
        if env is None:
            monkeypatch.delenv("RADIOMAP_SIMD", raising=False)
        else:
            monkeypatch.setenv("RADIOMAP_SIMD", env)
        img = rng.integers(0, 256, shape, dtype=np.uint8)
        calls.clear()
        expected = Corrector(gammas(), radial(96, 128, 0.3), simd=False).correct(img, scale=scale)
        np.testing.assert_array_equal(fast.correct(img, scale=scale), expected)
        assert calls == ([img.size] if env is None and simd_available() else [])
    fast.simd = False
    calls.clear()
    fast.correct(img, scale=0.8)
    assert calls == []
    with pytest.raises(correction.ModelMismatchError, match="1 channels|3 channels"):
        fast.correct(img[:, :, 0], scale=0.8)  # grayscale against a 3-channel vignetting model, after a hit


def test_a_new_model_on_a_used_corrector_is_checked_and_used():
    """Reassigning ``vignetting`` or ``response`` clears every cached table and the last kernel choice: an
    incompatible model raises, a compatible one is applied (not the old one's tables)."""
    gray = np.random.default_rng(9).integers(0, 256, (48, 64), dtype=np.uint8)
    fast = Corrector(gammas(1), radial(48, 64, 0.3, channels=1))
    fast.correct(gray, scale=0.8)
    fast.vignetting = radial(48, 64, 0.3)  # 3 channels: does not apply to a grayscale image
    with pytest.raises(correction.ModelMismatchError):
        fast.correct(gray, scale=0.8)
    mild = radial(48, 64, 0.6, channels=1)
    fast.vignetting = mild
    expected = Corrector(gammas(1), mild, simd=False).correct(gray, scale=0.8)
    np.testing.assert_array_equal(fast.correct(gray, scale=0.8), expected)
    fast.response = s_curve(1)
    expected = Corrector(s_curve(1), mild, simd=False).correct(gray, scale=0.8)
    np.testing.assert_array_equal(fast.correct(gray, scale=0.8), expected)


@pytest.mark.slow
def test_the_alternatives_benchmark_times_prototypes_that_give_the_same_bytes():
    """``scripts/bench_correction_alternatives.py`` (the designs issue 33 suggested for CPUs without AVX-512 VBMI,
    docs/performance.md): its bit-identical prototypes must give the scalar gather's bytes, or their speed says
    nothing; the folded-table bound is marked as a bound."""
    import shutil
    import subprocess
    import sys

    if not (shutil.which("cc") or shutil.which("gcc") or shutil.which("clang")):
        pytest.skip("no C compiler on PATH: the script compiles its prototypes")
    script = SCRIPT.parent / "bench_correction_alternatives.py"
    done = subprocess.run([sys.executable, str(script), "--calls", "2", "--repeats", "1"], capture_output=True,
                          text=True, cwd=SCRIPT.parents[1], timeout=600)
    assert done.returncode == 0, done.stderr
    rows = {line.split()[0]: line for line in done.stdout.splitlines() if line.startswith("  ")}
    assert "same output" in rows["no-check"], done.stdout
    assert "a speed bound only" in rows["small-table"], done.stdout
    assert "avx2-gather" not in rows or "same output" in rows["avx2-gather"], done.stdout
