"""The response test set (tests/response_curves.py) is what it claims: shapes, knees, renderer, real curve."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import shared_path
from response_curves import (
    TIMES,
    curves,
    flat_then_steep_curve,
    kink_curve,
    max_error_percent,
    read_pcalib,
    render_brackets,
    scene,
)


def test_every_curve_is_a_normalised_increasing_table():
    table_set = curves(include_euroc=False)
    assert set(table_set) == {"gamma-2.2", "s-curve", "kink-4x", "flat-then-steep"}
    for name, table in table_set.items():
        assert table.shape == (256,) and table.dtype == np.float64, name
        assert table[0] == 0.0 and table[-1] == 1.0 and np.all(np.diff(table) > 0), name


def test_the_knees_are_where_they_are_said_to_be():
    steps = np.diff(kink_curve())  # steps[k] = f^-1(k + 1) - f^-1(k)
    assert steps[181] / steps[178] == pytest.approx(4.0)
    assert np.allclose(steps[:180], steps[0]) and np.allclose(steps[181:], steps[181])
    steps = np.diff(flat_then_steep_curve())
    assert steps[190] < 0.2 * steps[170]  # near flat in 185..200
    assert steps[210] > 20 * steps[190] and steps[210] > 4 * steps[170]  # then steep
    assert flat_then_steep_curve()[200] < 0.5  # the top 55 levels hold more than half of the range


def test_renderer_without_noise_is_the_curve_rounded():
    table = kink_curve()
    radiance = np.linspace(0.0, 1.2, 500)[None, :, None]  # 0 .. beyond saturation at t = 1
    (image,) = render_brackets(table, radiance, np.array([1.0]), full_well=1e12, read_noise=0.0)
    assert image.dtype == np.uint8 and image.shape == (1, 500)
    expected = np.rint(np.interp(np.minimum(radiance[0, :, 0], 1.0), table, np.arange(256)))
    assert np.array_equal(image[0], expected.astype(np.uint8))
    assert image[0, -1] == 255 and image[0, 0] == 0


def test_brackets_cover_every_level_and_saturate_some_pixels():
    radiance = scene(60, 80)
    images = render_brackets(curves(include_euroc=False)["gamma-2.2"], radiance)
    assert len(images) == len(TIMES) == 12 and np.allclose(TIMES[1:] / TIMES[:-1], 2.0)
    stack = np.stack(images)
    assert stack.shape == (12, 60, 80, 3)
    seen = np.unique(stack)
    assert seen.size == 256  # every level, 0 and 255 included
    assert np.all(stack[:, :6, :6] == 255)  # the lamp saturates every exposure
    assert 0.2 < (stack[-1] == 255).mean() < 0.9  # the longest exposure clips much, not all


def test_noise_is_there():
    radiance = np.full((50, 50, 1), 0.3)
    a, b = render_brackets(kink_curve(), radiance, np.array([1.0, 1.0]))
    assert a.std() > 0.5 and not np.array_equal(a, b)


def test_max_error_percent():
    truth = kink_curve()
    off = truth.copy()
    off[200] += 0.02
    off[252] += 0.5  # outside 5..250
    assert max_error_percent(off, truth).tolist() == pytest.approx([2.0])
    assert max_error_percent(np.stack([off, truth], 1), np.stack([truth, truth], 1)).tolist() == pytest.approx(
        [2.0, 0.0])
    assert max_error_percent(off, truth, (5, 199)).tolist() == [0.0]


def test_euroc_curve_matches_the_project_reader():
    path = shared_path("vignetting", "euroc_mt9v034_752x480", "pcalib.txt")
    from radiometry.formats.pcalib import read_pcalib as project_reader

    ours = read_pcalib(path)
    theirs = project_reader(path).inverse_table[:, 0]
    assert np.all(np.diff(ours) > 0) and ours[0] == 0.0 and ours[-1] == 1.0
    # the project's model keeps f^-1(0) (0 in this file) and normalises at 255: the same table
    assert np.abs(ours - theirs).max() < 1e-9
    assert "euroc" in curves()


@pytest.mark.slow
def test_bench_calibration_script_runs_on_a_tiny_scene(capsys):
    import importlib.util

    spec = importlib.util.spec_from_file_location("radiomap_script_bench_calibration",
                                                  Path(__file__).resolve().parents[1] / "scripts" /
                                                  "bench_calibration.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    rows = script.run((96, 72), ["varied"], ["debevec", "engel"])
    assert [(r["curve"], r["method"]) for r in rows][:2] == [("gamma-2.2", "debevec"), ("gamma-2.2", "engel")]
    assert len(rows) == 2 * len(curves()) and all(np.isfinite(r["worst 5..250 [%]"]) for r in rows)
    assert all(0 < r["worst 5..250 [%]"] < 10 for r in rows)
    import logging

    level = logging.getLogger("radiometry").level
    assert script.main(["--size", "96x72", "--design", "2x", "--methods", "debevec"]) == 0
    assert logging.getLogger("radiometry").level == level     # the script leaves the caller's logging alone
    out = capsys.readouterr().out
    assert "response calibration vs truth (96x72, 12 exposures" in out and "max err 5..240 [%] R/G/B" in out


def _bench_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("radiomap_script_bench_calibration_bound",
                                                  Path(__file__).resolve().parents[1] / "scripts" /
                                                  "bench_calibration.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    return script


def test_the_ambiguity_bound_stays_inside_the_exact_2x_family():
    """Every exposure ``E t_j`` (t_j = 2^j) seen through the truth reads back through the chosen member as ``E' t_j``
    with one ``E'`` per pixel: the member predicts every exact-2x bracket as well as the truth does."""
    script = _bench_script()
    truth = flat_then_steep_curve()
    member = script.ambiguity_bound(truth, "second", "hat", False)
    assert np.all(np.diff(member) > 0) and member[-1] == 1.0
    assert np.abs(member - truth)[5:251].max() > 0.01  # a different curve ...
    ln_e = np.random.default_rng(0).uniform(np.log(2.0 ** -4), np.log(0.9), 200)
    j = np.arange(-3, 1)
    x = np.exp(ln_e[:, None] + j[None, :] * np.log(2.0))
    z = np.interp(x, truth, np.arange(256.0))
    ok = (z > 8) & (z < 254)
    recovered = np.log(np.interp(z, np.arange(256.0), member)) - j[None, :] * np.log(2.0)
    spread = [np.ptp(r[m]) for r, m in zip(recovered, ok) if m.sum() >= 2]
    assert len(spread) > 100 and np.max(spread) < 0.01  # ... that the brackets cannot tell from it


@pytest.mark.slow
def test_the_smoothness_prior_of_debevec_cannot_reach_one_percent_at_exact_2x():
    """The figures behind issue 15's unmet 1 %: with infinite data Debevec's prior still picks a member 1.4 % (kink
    4x) and 2.2 % (flat then steep) off, while a log-log curvature prior's member is within 0.6 % on every curve
    (and exact on a gamma curve, which it does not bend)."""
    script = _bench_script()
    rows = {r["prior (infinite data, exact 2x)"]: r for r in script.ambiguity_rows()}
    debevec = rows["Debevec's: (ln f^-1)'' squared, hat-weighted"]
    loglog = rows["log-log curvature absolute (L1)"]
    assert debevec["kink-4x"] > 1.0 and debevec["flat-then-steep"] > 1.5
    assert debevec["gamma-2.2"] < 0.1
    assert all(v < 0.7 for k, v in loglog.items() if k != "prior (infinite data, exact 2x)")
    assert loglog["gamma-2.2"] < 1e-3
