"""Engel-style response calibration (radiometry.response.engel): accuracy on the independent test set of
curves (tests/response_curves.py), monotonicity, extrapolated levels, the exposure-design warning, inputs.

Accuracy: max ``|f^-1 - truth|`` over levels 5..250, % of the range, both normalised ``f^-1(255) = 1``.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
from response_curves import TIMES, curves, kink_curve, max_error_percent, render_brackets, scene

from radiometry.errors import CalibrationError
from radiometry.response.engel import equal_ratios, fit_response_engel, isotonic_increasing
from radiometry.response.fit import fit_response

#: the 12 bracket times moved by 2^(-0.35..0.35): exposure ratios that differ (as scripts/bench_calibration.py)
VARIED_TIMES = TIMES * 2.0 ** np.random.default_rng(5).uniform(-0.35, 0.35, TIMES.size)
SIZE = (240, 320)


@pytest.fixture(scope="module")
def radiance():
    return scene(*SIZE)


# measured at 320x240 (all pixels): gamma 0.75, s-curve 0.84, kink-4x 0.64, flat-then-steep 0.82, euroc 0.83
# (worst channel); Debevec with lambda 10 on the same stacks: 0.48, 0.73, 0.92, 1.76, 0.35
@pytest.mark.slow
@pytest.mark.parametrize("name", ["kink-4x", "flat-then-steep", "euroc", "gamma-2.2"])
def test_engel_is_within_one_percent_with_varied_exposure_ratios(radiance, name):
    table_set = curves()
    if name not in table_set:
        pytest.skip("the EuRoC pcalib in ../shared/data is absent")
    truth = table_set[name]
    images = render_brackets(truth, radiance, VARIED_TIMES)
    response = fit_response(images, VARIED_TIMES, method="engel")
    err = max_error_percent(response.inverse_table, truth)
    assert np.all(err <= 1.0), f"{name}: max error per channel {err} %"
    meta = response.meta
    assert meta["method"] == "engel" and meta["converged"] and meta["equal_ratios"] is None
    assert np.all(np.diff(response.inverse_table, axis=0) > 0) and response.inverse_table[-1].tolist() == [1.0] * 3
    assert meta["observed_range"] == [[1, 254]] * 3  # every level 1..254 is seen ...
    assert all(255 in levels and 0 in levels for levels in meta["extrapolated_levels"])  # ... 0 and 255 never
    assert meta["fit_rms_levels"] < 3.0  # measured 1.1 (kink-4x) .. 2.1 (gamma: steep f at the dark end)


@pytest.mark.slow
def test_engel_keeps_the_knee_that_debevec_rounds(radiance):
    truth = curves(include_euroc=False)["flat-then-steep"]
    images = render_brackets(truth, radiance, VARIED_TIMES)
    engel = max_error_percent(fit_response(images, VARIED_TIMES, method="engel").inverse_table, truth).max()
    debevec = max_error_percent(fit_response(images, VARIED_TIMES, method="debevec").inverse_table, truth).max()
    assert engel < 0.6 * debevec, (engel, debevec)  # measured 0.82 vs 1.76
    chosen = fit_response(images, VARIED_TIMES)       # the default, auto: loglog, which keeps the knee too
    assert chosen.meta["method"] == "loglog" and chosen.meta["chosen_by"] == "auto: the log-log fit"
    assert max_error_percent(chosen.inverse_table, truth).max() < 0.6 * debevec  # measured 0.73


def test_auto_takes_loglog_unless_debevecs_options_are_given():
    small = scene(40, 60)
    images = render_brackets(kink_curve(), small, TIMES)
    response = fit_response(images, TIMES)
    assert response.meta["method"] == "loglog" and "every exposure ratio is 2x" in response.meta["chosen_by"]
    np.testing.assert_array_equal(response.inverse_table, fit_response(images, TIMES, method="loglog").inverse_table)
    varied = render_brackets(kink_curve(), small, VARIED_TIMES)
    assert fit_response(varied, VARIED_TIMES).meta["method"] == "loglog"
    for option in ({"lam": "auto"}, {"samples": 20}, {"samples": 20, "lam": None}):
        chosen = fit_response(varied, VARIED_TIMES, **option)
        assert chosen.meta["method"] == "debevec" and "samples or lambda 'auto' given" in chosen.meta["chosen_by"]
    assert fit_response(varied, VARIED_TIMES, lam=None, samples=None).meta["method"] == "loglog"
    with pytest.raises(ValueError, match="lam=5 with method 'auto' is ambiguous: give method='loglog'"):
        fit_response(varied, VARIED_TIMES, lam=5)


def test_equal_ratios_are_detected_and_warned(radiance, caplog):
    assert equal_ratios(TIMES) == pytest.approx(2.0)
    assert equal_ratios(VARIED_TIMES) is None
    assert equal_ratios(np.array([1.0, 4.0])) == 4.0
    small = scene(40, 60)
    images = render_brackets(kink_curve(), small, TIMES)
    with caplog.at_level(logging.WARNING, logger="radiometry.response.engel"):
        response = fit_response_engel(images, TIMES, max_iter=50, solver="alternate")
    assert response.meta["equal_ratios"] == pytest.approx(2.0) and response.meta["solver"] == "alternate"
    assert "all 2x apart" in caplog.text and "periodic in ln E" in caplog.text
    # the alternation crawls along the ambiguity; the eigenproblem has no rounds to run out of
    assert response.meta["converged"] is False and "alternation did not converge in 50 rounds" in caplog.text
    assert fit_response_engel(images, TIMES, max_iter=50).meta["solver"] == "eigen"


# measured at 160x120: the two agree to 6e-7 (gamma: the eigenvector is increasing, no rounds) and 7e-7 (kink:
# levels 146/147 etc. are pooled, the alternation continues from the eigenvector for 7-14 rounds instead of 67-84)
@pytest.mark.parametrize("name", ["gamma-2.2", "kink-4x"])
def test_the_eigenproblem_is_the_fixed_point_of_the_alternation(name):
    truth = curves(include_euroc=False)[name]
    images = render_brackets(truth, scene(120, 160), VARIED_TIMES)
    eigen = fit_response_engel(images, VARIED_TIMES)
    alternate = fit_response_engel(images, VARIED_TIMES, solver="alternate")
    assert eigen.meta["solver"] == "eigen" and eigen.meta["converged"] and alternate.meta["converged"]
    assert np.abs(eigen.inverse_table - alternate.inverse_table).max() < 1e-5
    assert eigen.meta["pooled_levels"] == alternate.meta["pooled_levels"]
    assert eigen.meta["extrapolated_levels"] == alternate.meta["extrapolated_levels"]
    assert max(eigen.meta["iterations"]) < 0.5 * min(alternate.meta["iterations"])
    if name == "gamma-2.2":
        assert eigen.meta["iterations"] == [0, 0, 0] and eigen.meta["pooled_levels"] == [[], [], []]


def test_the_prior_keeps_a_varied_fit_within_one_percent():
    """The log-log curvature prior on Engel's energy (measured 160x120, kink-4x: 0.48/0.55/0.84 with weight 1,
    0.53/0.60/0.87 without); it does not rescue exact 2x brackets (see scripts/bench_calibration.py)."""
    truth = kink_curve()
    images = render_brackets(truth, scene(120, 160), VARIED_TIMES)
    response = fit_response_engel(images, VARIED_TIMES, prior=1.0)
    assert response.meta["prior"] == 1.0 and response.meta["converged"]
    assert np.all(max_error_percent(response.inverse_table, truth) <= 1.0)
    assert np.all(np.diff(response.inverse_table, axis=0) > 0)


def test_unobserved_levels_are_marked_extrapolated():
    # a low-contrast scene: only mid levels are ever seen
    radiance = np.exp(np.linspace(np.log(0.08), np.log(0.3), 200))[None, :, None] * np.ones((50, 1, 1))
    times = np.array([0.5, 0.7, 1.0, 1.5, 2.2])
    truth = kink_curve()
    images = render_brackets(truth, radiance, times)
    seen = np.unique(np.stack(images))
    response = fit_response_engel(images, times)
    lo, hi = response.meta["observed_range"][0]
    assert (lo, hi) == (int(seen[seen > 0].min()), int(seen[seen < 255].max()))
    assert 10 < lo and hi < 245
    extrapolated = response.meta["extrapolated_levels"][0]
    assert extrapolated == list(range(lo)) + list(range(hi + 1, 256))
    assert set(response.meta["unobserved_levels"][0]) >= set(range(1, lo)) | set(range(hi + 1, 255))
    table = response.inverse_table[:, 0]
    assert np.all(np.isfinite(table)) and np.all(np.diff(table) > 0) and table[0] >= 0
    # inside the observed span the shape is right (compared after a least-squares scale: the absolute scale
    # of this stack is only known through the extrapolated level 255)
    inside = np.arange(lo + 3, hi - 2)
    scale = np.dot(table[inside], truth[inside]) / np.dot(table[inside], table[inside])
    # measured 1.0 % of the observed range (about 100 observations per level at the top)
    assert np.abs(scale * table[inside] - truth[inside]).max() / truth[hi] < 0.015
    # above it the extrapolation continues the slope of the top observed levels (linear in f^-1)
    steps = np.diff(table[hi:])
    assert np.allclose(steps, steps[0])


def test_monotonicity_is_the_constrained_fit_not_a_repair(radiance):
    truth = kink_curve()
    images = render_brackets(truth, radiance, VARIED_TIMES)
    swapped = []
    for im in images:  # a camera whose levels 100 and 101 are swapped: the per-level means dip
        out = im.copy()
        out[im == 100], out[im == 101] = 101, 100
        swapped.append(out)
    response = fit_response(swapped, VARIED_TIMES, method="engel")
    for pooled in response.meta["pooled_levels"]:
        assert [100, 101] in pooled
    assert response.meta["ties_separated"] and response.meta["repaired"] is False
    table = response.inverse_table
    assert np.all(np.diff(table, axis=0) > 0)
    assert np.all(np.diff(table[100:102], axis=0) < 1e-5)  # pooled: one value (plus the 1e-6 step)
    assert np.all(max_error_percent(table, truth, (5, 95)) < 1.0)


def test_isotonic_increasing_matches_brute_force():
    rng = np.random.default_rng(3)
    for _ in range(20):
        values = np.cumsum(rng.normal(0.2, 1.0, 12))
        weights = rng.uniform(0.5, 3.0, 12)
        fitted, pooled = isotonic_increasing(values, weights)
        assert np.all(np.diff(fitted) >= -1e-12)
        for block in pooled:  # a pooled block holds its weighted mean
            assert np.allclose(fitted[block], np.average(values[block], weights=weights[block]))
        # no monotone perturbation does better (local optimality of the weighted least squares)
        cost = np.sum(weights * (fitted - values) ** 2)
        for _ in range(50):
            other = np.maximum.accumulate(fitted + rng.normal(0, 0.05, 12))
            assert np.sum(weights * (other - values) ** 2) >= cost - 1e-9
    fitted, pooled = isotonic_increasing(np.array([1.0, 3.0, 2.0, 4.0]), np.array([1.0, 1.0, 3.0, 1.0]))
    assert fitted.tolist() == [1.0, 2.25, 2.25, 4.0] and pooled == [[1, 2]]


def test_mask_and_grayscale(radiance):
    truth = curves(include_euroc=False)["gamma-2.2"]
    images = [im[..., 1] for im in render_brackets(truth, radiance, VARIED_TIMES)]
    mask = np.ones(SIZE, bool)
    mask[:, :100] = False
    garbage = [im.copy() for im in images]
    for im in garbage:
        im[:, :100] = np.random.default_rng(0).integers(0, 256, im[:, :100].shape)
    response = fit_response_engel(garbage, VARIED_TIMES, mask=mask, pixels=20000)
    assert response.channels == 1 and response.meta["masked"] and response.meta["pixels"] == [20000]
    assert max_error_percent(response.inverse_table, truth)[0] < 1.5


def test_bad_options():
    images = render_brackets(kink_curve(), scene(20, 30), TIMES[:3])
    t = TIMES[:3]
    with pytest.raises(ValueError, match="pixels must be a whole number >= 2"):
        fit_response_engel(images, t, pixels=1)
    with pytest.raises(ValueError, match="max_iter"):
        fit_response_engel(images, t, max_iter=0)
    for tol in (0.0, np.nan):
        with pytest.raises(ValueError, match="tol must be a positive number"):
            fit_response_engel(images, t, tol=tol)
    with pytest.raises(ValueError, match="levels must satisfy"):
        fit_response_engel(images, t, levels=(0, 254))
    with pytest.raises(ValueError, match="solver must be one of eigen, alternate"):
        fit_response_engel(images, t, solver="svd")
    for prior in (-1.0, np.inf):
        with pytest.raises(ValueError, match="prior must be a number >= 0"):
            fit_response_engel(images, t, prior=prior)
    with pytest.raises(ValueError, match="prior needs solver='eigen'"):
        fit_response_engel(images, t, prior=1.0, solver="alternate")
    with pytest.raises(TypeError, match="unexpected keyword argument 'lam'"):
        fit_response(images, t, method="engel", lam=3.0)
    with pytest.raises(CalibrationError, match="two exposures"):
        fit_response_engel([np.full((10, 10), 255, np.uint8)] * 3, [1.0, 2.0, 4.0])
