"""The log-log prior fit for brackets at one exposure ratio (radiometry.response.loglog): accuracy on kinked curves
of the independent test set (tests/response_curves.py) at exact 2x steps, where Debevec's prior rounds the knee;
monotonicity, extrapolated levels, mask, options.

Accuracy: max ``|f^-1 - truth|`` over levels 5..250, % of the range, both normalised ``f^-1(255) = 1``.
"""

from __future__ import annotations

import numpy as np
import pytest
from response_curves import TIMES, break_curves, curves, kink_curve, max_error_percent, render_brackets, scene

from radiometry.response.fit import fit_response
from radiometry.response.loglog import fit_response_loglog, prior_rows

VARIED_TIMES = TIMES * 2.0 ** np.random.default_rng(5).uniform(-0.35, 0.35, TIMES.size)


@pytest.fixture(scope="module")
def radiance():
    return scene(120, 160)


# measured at 160x120 (R/G/B), scene and noise seeds 0/1/2: kink-4x 0.49/0.61/0.42, 0.29/0.74/0.54,
# 0.46/0.34/0.45; flat-then-steep 0.66/0.86/0.58, 0.77/0.82/0.89, 0.64/0.66/0.71. Debevec (lambda 10) on the
# same stacks: 1.03-1.35 and 1.66-1.98.
@pytest.mark.slow
@pytest.mark.parametrize("name", ["kink-4x", "flat-then-steep"])
def test_a_knee_at_exact_2x_steps_is_within_one_percent(radiance, name):
    truth = curves(include_euroc=False)[name]
    images = render_brackets(truth, radiance, TIMES)
    response = fit_response_loglog(images, TIMES)
    err = max_error_percent(response.inverse_table, truth)
    assert np.all(err <= 1.0), f"{name}: max error per channel {err} %"
    debevec = max_error_percent(fit_response(images, TIMES, method="debevec").inverse_table, truth)
    assert err.max() < 0.7 * debevec.min(), (err, debevec)
    meta = response.meta
    assert meta["method"] == "loglog" and meta["equal_ratios"] == pytest.approx(2.0) and meta["lambda"] == 0.1
    assert meta["smooth"] == 5e-3 and meta["repaired"] is False
    table = response.inverse_table
    assert np.all(np.diff(table, axis=0) > 0) and table[-1].tolist() == [1.0] * 3
    # the clean ceiling at 255 costs the margin of the level detection (issue 28): the top 2 levels are extrapolated
    assert all(lo == 1 and 250 <= hi <= 254 for lo, hi in meta["observed_range"]), meta["observed_range"]
    assert all(0 in levels and 255 in levels for levels in meta["extrapolated_levels"])
    assert meta["fit_rms_levels"] < 3.0  # measured 1.2 at 640x480


@pytest.mark.slow
def test_varied_ratios_are_within_one_percent_too(radiance):
    """Measured 160x120, kink-4x: 0.42/0.32/0.32 % (640x480, every curve: 0.24-0.73 %)."""
    truth = kink_curve()
    images = render_brackets(truth, radiance, VARIED_TIMES)
    response = fit_response_loglog(images, VARIED_TIMES)
    assert response.meta["equal_ratios"] is None
    assert np.all(max_error_percent(response.inverse_table, truth) <= 1.0)


@pytest.fixture(scope="module")
def break_radiance():
    return scene(240, 320, seed=3)


#: measured, 320x240, scene and noise seed 3 (640x480 seed 7 in docs/guides/calibrate.md): varied 0.50 / 0.84 / 0.52 / 0.36 / 0.30
#: / 0.45 / 0.26; exact 2x 1.53 / 2.20 / 0.64 / 0.55 / 0.37 / 0.54 / 0.33 (order of break_curves)
BREAK_2X_LIMIT = {"dark-kink-4x@60": 2.0, "dark-flat-40-55": 2.8}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(break_curves()))
def test_curves_built_to_break_the_prior(break_radiance, name):
    """Curves the weights were not chosen on. Varied ratios: within 1 % each. Exact 2x: within 1 % except where a
    kink or flat stretch lies in the darkest octaves (a few levels an octave), where the prior that suppresses the
    periodic ambiguity also flattens the real feature: the known failure, bounded here so that it cannot grow."""
    truth = break_curves()[name]
    varied = fit_response(render_brackets(truth, break_radiance, VARIED_TIMES, seed=3), VARIED_TIMES)
    assert varied.meta["method"] == "loglog"
    assert max_error_percent(varied.inverse_table, truth).max() <= 1.0
    exact = fit_response(render_brackets(truth, break_radiance, TIMES, seed=3), TIMES)
    assert max_error_percent(exact.inverse_table, truth).max() <= BREAK_2X_LIMIT.get(name, 1.0)


def test_a_gamma_curve_costs_the_prior_nothing():
    """The rows vanish on every power law (the elasticity is constant); they weight dark levels more."""
    levels = np.arange(1, 255)
    g = 2.2 * np.log(levels / 255.0)
    rows = prior_rows(levels)
    assert rows.shape == (252, 254)
    assert np.abs(rows @ g).max() < 1e-9
    wiggle = np.sin(2 * np.pi * g / np.log(2.0))  # a factor periodic in ln E: the 2x ambiguity
    cost = (rows @ wiggle) ** 2
    assert cost[:60].sum() > 100 * cost[-60:].sum()
    gaps = np.array([1, 2, 3, 5, 8, 9, 10, 12])  # unobserved levels between: the rows use the true spacing
    assert np.abs(prior_rows(gaps) @ (2.2 * np.log(gaps))).max() < 1e-9


@pytest.mark.slow
def test_mask_grayscale_and_unobserved_levels():
    truth = curves(include_euroc=False)["gamma-2.2"]
    radiance = scene(120, 160)
    images = [im[..., 1] for im in render_brackets(truth, radiance, TIMES)]
    mask = np.ones((120, 160), bool)
    mask[:, :40] = False
    garbage = [im.copy() for im in images]
    for im in garbage:
        im[:, :40] = np.random.default_rng(0).integers(0, 256, im[:, :40].shape)
    response = fit_response_loglog(garbage, TIMES, mask=mask, pixels=5000)
    assert response.channels == 1 and response.meta["masked"] and response.meta["pixels"] == [5000]
    assert max_error_percent(response.inverse_table, truth)[0] < 1.5
    # a low-contrast scene: only mid levels are seen; the rest is extrapolated and listed
    narrow = np.exp(np.linspace(np.log(0.08), np.log(0.3), 200))[None, :, None] * np.ones((50, 1, 1))
    times = np.array([0.5, 1.0, 2.0])
    stack = render_brackets(kink_curve(), narrow, times)
    fitted = fit_response_loglog(stack, times)
    lo, hi = fitted.meta["observed_range"][0]
    assert 10 < lo and hi < 245
    assert fitted.meta["extrapolated_levels"][0] == list(range(lo)) + list(range(hi + 1, 256))
    assert np.all(np.isfinite(fitted.inverse_table)) and np.all(np.diff(fitted.inverse_table[:, 0]) > 0)


@pytest.mark.slow
def test_monotonicity_is_a_constraint_of_the_fit_not_a_repair(radiance):
    truth = kink_curve()
    images = render_brackets(truth, radiance, TIMES)
    swapped = []
    for im in images:  # a camera whose levels 100 and 101 are swapped: the data put 101 below 100
        out = im.copy()
        out[im == 100], out[im == 101] = 101, 100
        swapped.append(out)
    weak = fit_response_loglog(swapped, TIMES, lam=1e-4, smooth=0.0)  # nearly no prior: the free minimum dips
    assert weak.meta["pooled_levels"] == [[[100, 101]]] * 3
    assert weak.meta["repaired"] is False and weak.meta["ties_separated"]
    assert np.all(np.diff(weak.inverse_table, axis=0) > 0)
    assert np.all(np.diff(weak.inverse_table[100:102], axis=0) < 1e-5)  # tied: one value (plus the 1e-6 step)
    assert np.all(max_error_percent(weak.inverse_table, truth, (5, 95)) < 1.0)  # measured 0.23-0.37
    default = fit_response_loglog(swapped, TIMES)  # the default prior smooths the swap away (measured 0.04-0.11)
    assert default.meta["pooled_levels"] == [[]] * 3
    assert np.all(max_error_percent(default.inverse_table, truth, (5, 95)) < 0.5)


@pytest.mark.slow
def test_bad_options():
    images = render_brackets(kink_curve(), scene(20, 30), TIMES[:3])
    for lam in (0.0, -1.0, np.nan, True, "auto"):
        with pytest.raises(ValueError, match="lam must be a positive number"):
            fit_response_loglog(images, TIMES[:3], lam=lam)
    for smooth in (-1.0, np.inf, "yes"):
        with pytest.raises(ValueError, match="smooth must be a number >= 0"):
            fit_response_loglog(images, TIMES[:3], smooth=smooth)
    with pytest.raises(ValueError, match="pixels must be a whole number >= 2"):
        fit_response_loglog(images, TIMES[:3], pixels=1)
    with pytest.raises(ValueError, match="levels must satisfy"):
        fit_response_loglog(images, TIMES[:3], levels=(0, 254))


@pytest.mark.slow
def test_a_singular_hessian_states_no_error_rather_than_zero(radiance, monkeypatch, caplog):
    """Where the energy's Hessian is singular (a direction the brackets and the prior leave undetermined), the fit
    records no ``inverse_stderr`` (and says why) instead of a standard error of 0; the vignetting budget then
    falls back to the curve's roughness, as for any response without one. Well-posed fits keep theirs: the
    diagonally scaled Hessian's condition number, measured, is 9e10-3e11 on 24 curves x 2 designs, 3.5e8-4.5e10 on
    memorial and 2.3e12-7.3e13 on taipei (lam 0.1 to 30; unscaled taipei at lam 30 reaches 5e15), against the
    threshold 1/eps = 4.5e15."""
    import radiometry.response.loglog as ll
    from radiometry.response import relative_stderr

    singular = np.diag([1.0, 2.0, 0.0, 3.0])
    args = (np.zeros(3, np.intp), np.array([10, 20, 30]), 1, np.array([10, 20, 30, 40]), np.zeros(3))
    assert ll._log_covariance(singular, *args) is None
    nearly = np.eye(4)
    nearly[:2, :2] = [[1.0, 1.0], [1.0, 1.0 + 4e-16]]                       # two rows equal to 4e-16
    assert ll._log_covariance(nearly, *args) is None
    assert ll._log_covariance(np.diag([1.0, 2.0, 3.0e-17, 3.0]), *args) is not None   # wide scales, not singular
    images = render_brackets(kink_curve(), radiance, TIMES)
    fine = fit_response_loglog(images, TIMES)
    assert relative_stderr(fine) is not None and fine.meta["inverse_stderr_source"].startswith("loglog:")
    monkeypatch.setattr(ll, "_log_covariance", lambda *a: None)
    with caplog.at_level("WARNING", logger="radiometry.response.loglog"):
        response = fit_response_loglog(images, TIMES)
    assert "inverse_stderr" not in response.meta and relative_stderr(response) is None
    assert response.meta["inverse_stderr_source"].startswith("none: the energy's Hessian is singular in channel(s) 0, 1, 2")
    assert "no standard error stated" in caplog.text
    assert np.array_equal(response.inverse_table, fine.inverse_table)
