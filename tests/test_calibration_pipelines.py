"""Calibration through real camera pipelines (issue 28): white balance after the sensor clips, JPEG, noise after the
response; the truth-free quality figures; vignetting sweeps through the same pipelines.

Every stack is made by ``tests/camera_pipelines.py`` (its own sensor, white balance, response and OpenCV's JPEG;
nothing from radiometry touches a pixel) over curves from real cameras (the EuRoC pcalib) and curves built to
break the method (a knee, a near-flat stretch). Figures measured at 320x240 are in the docstrings; the bounds leave
room for other noise draws. docs/calibration_pipelines.md has the whole table (scripts/bench_calibration.py
--pipelines).
"""

from __future__ import annotations

import numpy as np
import pytest

from camera_pipelines import PIPELINES, ceiling_level, max_error_scale_free, render, sweep
from radiometry.errors import CalibrationError
from radiometry.response import CameraResponse
from radiometry.response.fit import fit_response
from radiometry.response.quality import assess
from response_curves import TIMES, curves, scene

VARIED = TIMES * 2.0 ** np.random.default_rng(5).uniform(-0.35, 0.35, TIMES.size)
DESIGNS = {"2x": TIMES, "varied": VARIED}


@pytest.fixture(scope="module")
def radiance():
    return scene(240, 320, seed=1)


def _fit(curve, pipeline, design, radiance, **options):
    table = curves()[curve]
    times = DESIGNS[design]
    images = render(table, radiance, times, seed=2, **PIPELINES[pipeline])
    return table, images, times, fit_response(images, times, **options)


@pytest.mark.slow
@pytest.mark.parametrize("design", ["2x", "varied"])
@pytest.mark.parametrize("curve", ["gamma-2.2", "kink-4x", "euroc"])
def test_white_balance_after_the_clip_is_found_per_channel_and_fitted_below_it(curve, design, radiance):
    """Measured (max error %, R/G/B): gamma 0.38/0.38/0.44 (2x), kink 0.49/0.48/0.48, EuRoC 0.41/0.33/0.49; before
    issue 28 the same stacks were off by 77-95 % at the top (saturated pixels taken as data)."""
    if curve == "euroc" and "euroc" not in curves():
        pytest.skip("../shared/data (EuRoC pcalib) is absent")
    table, _, _, response = _fit(curve, "wb-after-clip", design, radiance)
    declared = response.meta["declared_levels"]
    gains = PIPELINES["wb-after-clip"]["gains"]
    for c, (lo, hi) in enumerate(declared):
        assert hi <= ceiling_level(table, gains[c]), (c, hi)  # never above the channel's true saturation
    assert declared[0][1] < declared[1][1] - 8  # red (gain 0.88) is cut well below green
    assert "R at" in response.meta["levels_summary"] and "saturates" in response.meta["levels_summary"]
    err = max_error_scale_free(response.inverse_table, table, declared)
    assert np.all(err <= 1.0), err


@pytest.mark.slow
@pytest.mark.parametrize("design", ["2x", "varied"])
@pytest.mark.parametrize("pipeline", ["wb-jpeg92", "post-noise", "jpeg75"])
def test_jpeg_and_noise_after_the_response_stay_within_one_percent_on_gamma(pipeline, design, radiance):
    """Measured: wb-jpeg92 0.45/0.42/0.52 (2x), 0.36/0.21/0.38 (varied); post-noise 0.59/0.73/0.57, 0.50/0.49/0.46;
    jpeg75 0.77/0.75/0.83, 0.53/0.64/0.62 (before: 60-86 %)."""
    table, _, _, response = _fit("gamma-2.2", pipeline, design, radiance)
    err = max_error_scale_free(response.inverse_table, table, response.meta["declared_levels"])
    assert np.all(err <= 1.0), err


@pytest.mark.slow
@pytest.mark.parametrize("design", ["2x", "varied"])
def test_the_euroc_curve_through_jpeg_with_white_balance(design, radiance):
    """Measured: 0.50 / 0.42 / 0.60 % (2x), 0.48 / 0.48 / 0.91 % (varied). Before the outliers were left out blue
    was 2.19 / 2.35 % at its top declared level (234): a few saturated pixels that JPEG reads below the ceiling
    (about 100 of 111,000 observations, each an exposure the curve would put at or above 242); the declared levels
    stay below every true ceiling."""
    if "euroc" not in curves():
        pytest.skip("../shared/data (EuRoC pcalib) is absent")
    table, _, _, response = _fit("euroc", "wb-jpeg92", design, radiance)
    gains = PIPELINES["wb-jpeg92"]["gains"]
    declared = response.meta["declared_levels"]
    assert all(hi <= ceiling_level(table, gains[c]) for c, (_, hi) in enumerate(declared)), declared
    assert response.meta["outliers_dropped"][2][0] > 0 and not response.meta["deblur"]
    err = max_error_scale_free(response.inverse_table, table, declared)
    assert np.all(err <= 1.0), err


@pytest.mark.slow
@pytest.mark.parametrize("curve, pipeline, bound", [("flat-then-steep", "wb-jpeg92", 2.6), ("kink-4x", "jpeg75", 1.7),
                                                    ("s-curve", "jpeg75", 1.4)])
def test_where_it_fails_knees_under_jpeg_stay_bounded(curve, pipeline, bound, radiance):
    """Documented failures: a knee (slope x50 at level 200, or x4 at 180) blurred by JPEG's level noise: measured
    flat-then-steep 2.21 / 1.69 / 2.25 % at level 200, kink 1.30 / 0.84 / 1.38 % at 180; the s-curve under q75
    1.08 / 0.53 / 0.61 % (3.86 % in blue before the outliers were left out). Bounded so that they cannot grow
    silently (docs/calibration_pipelines.md)."""
    table, _, _, response = _fit(curve, pipeline, "2x", radiance)
    err = max_error_scale_free(response.inverse_table, table, response.meta["declared_levels"])
    assert np.all(err <= bound), err


@pytest.mark.slow
@pytest.mark.parametrize("curve, bound", [("kink-4x", 1.3), ("flat-then-steep", 1.65)])
def test_knees_under_noise_after_the_response_with_the_opt_in_deblur(curve, bound, radiance):
    """Noise after the response (1.5 levels, Gaussian) with ``deblur=True`` (opt-in): the fit's bias measured on
    stacks simulated from it and taken off (radiometry/response/deblur.py). Measured: the worst channel at the knee
    kink 1.45 -> 1.22 % (0.87 / 1.22 / 0.77), flat-then-steep 1.74 -> 1.54 % (0.94 / 1.54 / 0.58): better, still
    above 1 %, and not the default (it costs other rows: docs/calibration_pipelines.md). The noise it measured
    (1.5 levels added to the sensor's own) is recorded."""
    table, images, times, plain = _fit(curve, "post-noise", "2x", radiance)
    response = fit_response(images, times, deblur=True)
    assert response.meta["deblur"] and all(1.0 < v < 4.0 for v in response.meta["level_noise"])
    before = max_error_scale_free(plain.inverse_table, table, plain.meta["declared_levels"])
    err = max_error_scale_free(response.inverse_table, table, response.meta["declared_levels"])
    assert err.max() < before.max() and np.all(err <= bound), (before, err)


def test_outliers_are_the_saturated_readings_and_the_wild_ones():
    """A unit check of the leave-one-out rule on a made-up channel (linear curve, three exposures 2x apart): a pixel
    whose third exposure the curve puts above the ceiling but which reads below it (JPEG's rounding of a saturated
    block), and one observation 30 levels off, are the outliers; noise of 1 level is not."""
    from radiometry.response.deblur import leave_one_out_levels, outliers

    rng = np.random.default_rng(0)
    table = np.linspace(0.0, 1.0, 256)
    n_pix = 400
    e = rng.uniform(0.05, 0.2, n_pix)  # at most level 204 in the longest exposure
    e[7] = 0.29  # pixel 7 would reach level 296 in the longest: saturated, but read at 230
    log_t = np.log([1.0, 2.0, 4.0])
    pix = np.repeat(np.arange(n_pix), 3)
    img = np.tile(np.arange(3), n_pix)
    z = np.clip(np.rint(255 * e[pix] * np.exp(log_t[img]) + rng.normal(0, 1, pix.size)), 0, 255).astype(np.intp)
    z[3 * 7 + 2] = 230
    z[3 * 11 + 1] += 30
    drop = outliers(table, pix, img, z, n_pix, log_t, ceiling=240.0)
    pred = leave_one_out_levels(table, pix, img, z, n_pix, log_t)
    assert drop[3 * 7 + 2] and pred[3 * 7 + 2] > 240 and drop[3 * 11 + 1]
    assert drop.sum() <= 0.02 * drop.size + 3  # noise of 1 level is data, not outliers


def test_the_level_noise_is_measured_from_the_residuals():
    """The deblur's noise estimate on a made-up channel with Gaussian noise of 2 levels after a linear curve (three
    exposures 2x apart): within 20 % of 2 at levels 60-100 (measured 2.05-2.34; the pixel's own weight in its
    irradiance and the rounding taken out). A known limit, measured: it overstates the noise where the pixel's
    irradiance estimate is itself noisy, by 20-80 % at levels 100-200 here (three exposures). An estimator that
    models that noise (tried: 1.8-2.4 at levels 30-170) made the deblurred fits worse on the pipelines (kink
    post-noise 2.05 % instead of 0.98 %), so this one is kept and deblur is not the default."""
    from radiometry.response.deblur import level_noise, pixel_log_irradiance

    rng = np.random.default_rng(1)
    table = np.linspace(1e-4, 1.0, 256)
    n_pix = 3000
    e = rng.uniform(0.05, 0.2, n_pix)
    log_t = np.log([1.0, 2.0, 4.0])
    pix = np.repeat(np.arange(n_pix), 3)
    img = np.tile(np.arange(3), n_pix)
    z = np.clip(np.rint(255 * e[pix] * np.exp(log_t[img]) + rng.normal(0, 2.0, pix.size)), 1, 254).astype(np.intp)
    ln_e = pixel_log_irradiance(np.log(table), pix, img, z, n_pix, log_t)
    sigma = level_noise(table, ln_e, pix, img, z, log_t, (20, 230))
    assert np.all(np.abs(sigma[60:100] - 2.0) < 0.4), sigma[60:100:10]
    assert np.all((sigma[100:200] > 1.8) & (sigma[100:200] < 3.8)), sigma[100:200:20]


@pytest.mark.slow
def test_the_clean_camera_keeps_its_accuracy(radiance):
    table, _, _, response = _fit("kink-4x", "clean", "2x", radiance)
    err = max_error_scale_free(response.inverse_table, table, response.meta["declared_levels"])
    assert np.all(err <= 0.8), err
    assert all(hi >= 250 for _, hi in response.meta["declared_levels"])  # a clean ceiling costs at most a few levels


def test_debevec_also_finds_the_ceiling(radiance):
    table, _, _, response = _fit("gamma-2.2", "wb-after-clip", "2x", radiance, method="debevec")
    declared = response.meta["declared_levels"]
    assert declared[0][1] <= ceiling_level(table, PIPELINES["wb-after-clip"]["gains"][0])
    err = max_error_scale_free(response.inverse_table, table, declared)
    assert np.all(err <= 1.5), err


@pytest.mark.slow
def test_explicit_levels_switch_the_detection_off(radiance):
    table, _, _, response = _fit("gamma-2.2", "clean", "2x", radiance, method="loglog", levels=(1, 254), edges=False)
    assert "levels_summary" not in response.meta and response.meta["levels"] == [1, 254]


def test_a_channel_saturated_in_every_exposure_stops_with_the_fix():
    """Red saturated everywhere (gain 1 but radiance far above the well in every exposure): one line, the channel
    and what to record instead."""
    rng = np.random.default_rng(0)
    radiance = np.exp(rng.uniform(-2, 2, (60, 80, 3))) * np.array([1e4, 1.0, 1.0])
    images = render(curves()["gamma-2.2"], radiance, TIMES[6:], seed=3)
    with pytest.raises(CalibrationError, match=r"channel R .*add exposures"):
        fit_response(images, TIMES[6:])


# ------------------------------------------------------------------------------------------------ quality figures
@pytest.mark.slow
def test_the_quality_figure_separates_good_from_broken(radiance):
    """Measured (gamma 2.2, 320x240): a good fit 2.1 levels held-out RMS (0.96x the images' noise), split-half
    0.3 %; a camera that moved 1-2 px between exposures 18.5 levels (8.4x); the wrong response (the kink curve given
    for a gamma camera) 40.7 (18.6x)."""
    table, images, times, response = _fit("gamma-2.2", "clean", "2x", radiance)
    good = assess(images, times, response, method="auto")
    assert good["grade"] == "good", good["summary"]
    assert good["holdout_refit"] == len(good["holdout_per_exposure"]) == 6  # six of the twelve, refitted without each
    rng = np.random.default_rng(3)
    moved = [np.roll(im, tuple(rng.integers(-2, 3, 2)), axis=(0, 1)) for im in images]
    broken = assess(moved, times, fit_response(moved, times), method=None)
    assert broken["grade"] == "broken" and broken["holdout_over_noise"] > 3 * good["holdout_over_noise"]
    wrong = assess(images, times, CameraResponse.from_table(curves()["kink-4x"]))
    assert wrong["grade"] == "broken" and "do not use" in wrong["summary"]


@pytest.mark.slow
def test_short_sparse_and_single_channel_stacks_get_a_quality_figure(radiance):
    """Review findings: a 2-exposure stack, 3 exposures 16x apart (leaving the middle one out leaves a 256x gap) and
    (H, W, 1) images are judged without refits where refits cannot stand, never refused or called broken for it; such
    a prediction is in-sample, said so and never good (audit: a 2-exposure stack read "held-out prediction")."""
    table = curves()["gamma-2.2"]
    images = render(table, radiance, TIMES, seed=2)
    for pick in ([4, 8], [2, 6, 10]):
        sub, times = [images[k] for k in pick], TIMES[pick]
        q = assess(sub, times, fit_response(sub, times), method="auto")
        assert q["holdout_refit"] == 0 and q["grade"] not in ("broken", "good"), q["summary"]
        assert q["prediction"] == "in-sample (too few exposures to hold one out)", q
        assert "in-sample prediction (too few exposures to hold one out)" in q["summary"]
    grey = [im[:, :, 1:2] for im in images[3:9]]
    q = assess(grey, TIMES[3:9], fit_response(grey, TIMES[3:9]), method="auto")
    assert q["grade"] == "good" and len(q["split_half_percent"]) == 1, q["summary"]


@pytest.mark.slow
def test_the_quality_figure_of_a_jpeg_stack_is_good(radiance):
    _, images, times, response = _fit("gamma-2.2", "wb-jpeg92", "2x", radiance)
    q = assess(images, times, response, method=None)
    assert q["grade"] == "good", q["summary"]


def test_a_bend_in_the_curve_is_found_and_said():
    """bends() on tables with a known shape: a x4 kink at level 150 is found there; gamma 2.2 and the EuRoC curve
    (no bend from level 32 up: ratios 1.2-1.3) are not flagged; below level 32 gamma's own curvature is ignored."""
    from radiometry.response.quality import bend_text, bends

    levels = np.arange(256, dtype=np.float64)
    slope = np.where(levels < 150, 1.0, 4.0)
    kink = np.cumsum(slope)
    kink /= kink[-1]
    found = bends(CameraResponse(np.stack([kink] * 3, axis=1)), [(1, 254)] * 3)
    assert [b["channel"] for b in found] == [0, 1, 2]
    assert all(abs(b["level"] - 150) <= 3 and b["ratio"] > 3 for b in found), found
    assert "R at level" in bend_text(found) and "PNG or raw" in bend_text(found)
    for name in ("gamma-2.2", "euroc"):
        table = curves()[name]
        assert bends(CameraResponse(np.stack([table / table[-1]] * 3, axis=1)), [(1, 254)] * 3) == [], name
    assert bend_text([]) == ""


@pytest.mark.slow
@pytest.mark.parametrize("curve, pipeline, flagged", [("flat-then-steep", "wb-jpeg92", True), ("kink-4x", "jpeg75", True),
                                                      ("gamma-2.2", "jpeg75", False), ("euroc", "wb-jpeg92", False),
                                                      ("s-curve", "jpeg75", False)])
def test_a_knee_rounded_by_jpeg_is_said_and_graded_doubtful(curve, pipeline, flagged, radiance):
    """The held-out prediction does not see a knee rounded by JPEG (flat-then-steep 2.2 % off was graded good): the
    fitted curve's bend is (fitted ratios: knees 2.2-4.9 in their sharpest channel, smooth curves <= 1.79 from level
    32 up; docs/calibration_pipelines.md), and the summary says so."""
    _, images, times, response = _fit(curve, pipeline, "2x", radiance)
    q = assess(images, times, response, method=None)
    assert bool(q["bends"]) is flagged, q["bends"]
    assert ("bends sharply" in q["summary"]) is flagged
    if flagged:
        assert q["grade"] != "good", q["summary"]


@pytest.mark.slow
def test_the_quality_of_real_stacks_is_stated_and_a_moved_one_is_broken():
    """taipei (a Nikon night scene; with refits 7.02 levels held-out, 2.83x its noise, docs/calibration_pipelines.md):
    doubtful (its 32 s exposure predicts at 13.4 levels); the same stack with every other exposure moved by 2 px, or
    with gamma 2.2 given, is worse."""
    from conftest import shared_path

    from radiometry.response.fit import load_brackets

    images, times, _ = load_brackets(shared_path("brackets", "taipei"), progress=False)
    response = fit_response(images, times)
    real = assess(images, times, response, method=None)
    assert real["grade"] in ("good", "doubtful") and 1.0 < real["holdout_over_noise"] < 4.0, real["summary"]
    moved = [np.roll(im, 2 * (k % 2), axis=1) for k, im in enumerate(images)]
    worse = assess(moved, times, fit_response(moved, times), method=None)
    assert worse["holdout_over_noise"] > real["holdout_over_noise"]
    wrong = assess(images, times, CameraResponse.gamma(2.2))
    assert wrong["grade"] == "broken", wrong["summary"]


# ------------------------------------------------------------------------------------------------ vignetting sweeps
@pytest.fixture(scope="module")
def euroc_vignette():
    from vignetting_sweeps import default_size, shared_available, vignette_field

    if not shared_available():
        pytest.skip("../shared/data (EuRoC vignette.png, lensfun) is absent")
    width, height = default_size("euroc")
    return vignette_field("euroc", width, height)


@pytest.mark.slow
def test_a_jpeg_sweep_through_the_response_from_a_jpeg_stack(euroc_vignette, radiance):
    """Measured: kink-4x, JPEG q92 with white balance: 0.21/0.25/0.71 levels (0.34/0.24/0.61 before the response
    fit left its outliers out: red's response improved, blue's moved from 0.97 to 1.10 % at the knee); with the true
    response a static JPEG q75 sweep is 0.24/0.31/0.44 (JPEG's rounding of a sheet that looks the same in every
    frame, not the response: docs)."""
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting
    from vignetting_sweeps import flat_rms_vs_truth

    table, _, _, response = _fit("kink-4x", "wb-jpeg92", "2x", radiance)
    frames = sweep(table, euroc_vignette, frames=64, **PIPELINES["wb-jpeg92"])
    model = fit_vignetting(collect_vignetting(frames, response, progress=False), model="lut")
    err = flat_rms_vs_truth(model.evaluate(), euroc_vignette, table)
    assert np.all(err <= 0.8), err


def test_a_sheet_clipped_below_255_is_refused_in_one_line(euroc_vignette):
    from radiometry.vignetting_calibration import collect_vignetting

    table = curves()["gamma-2.2"]
    # sensor overexposed at the sheet's centre, every gain below 1 after the clip: red piles up at level 240, green
    # at 248, blue at 246 (nothing reaches the usual 250 cut, so only the pile-up shows the clip)
    frames = sweep(table, euroc_vignette * 1.3, frames=24, top_level=254.0, gains=(0.88, 0.94, 0.92))
    with pytest.raises(CalibrationError, match=r"saturates in R at level 24\d") as err:
        collect_vignetting(frames, CameraResponse.from_table(table), progress=False)
    assert "\n" not in str(err.value) and "shorter exposure" in str(err.value)


@pytest.mark.slow
def test_auto_exposure_left_on_is_absorbed_or_refused(euroc_vignette, tmp_path):
    """A +-0.1-stop jitter (spread ~15 %) is absorbed by the drift correction (0.30-0.44 levels, measured); +-0.3
    stops (spread ~45 %) leaves 0.72 and the command refuses it without --allow-exposure-changes."""
    from click.testing import CliRunner

    from mapping.cli import cli as main
    from radiometry.images import write_image
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting
    from vignetting_sweeps import flat_rms_vs_truth

    table = curves()["kink-4x"]
    response = CameraResponse.from_table(table)
    small = sweep(table, euroc_vignette, frames=64, top_level=180.0, exposure_jitter=0.1)
    acc = collect_vignetting(small, response, progress=False)
    scales = acc.frame_scales()
    assert 0.05 < scales.max() / scales.min() - 1 < 0.25
    err = flat_rms_vs_truth(fit_vignetting(acc, model="lut").evaluate(), euroc_vignette, table)
    assert np.all(err <= 0.5), err
    big = sweep(table, euroc_vignette, frames=40, top_level=180.0, exposure_jitter=0.3, seed=4)
    folder = tmp_path / "sweep"
    folder.mkdir()
    for k, frame in enumerate(big):
        write_image(folder / f"{k:03d}.png", frame)
    response.save(tmp_path / "crf.npz")
    out = tmp_path / "v.npz"
    result = CliRunner().invoke(main, ["vignetting", str(folder), "-r", str(tmp_path / "crf.npz"), "-o", str(out),
                                       "--no-plots", "--no-progress"])
    assert result.exit_code == 1 and "auto" in result.output and "--allow-exposure-changes" in result.output
    assert not out.exists()
    result = CliRunner().invoke(main, ["vignetting", str(folder), "-r", str(tmp_path / "crf.npz"), "-o", str(out),
                                       "--no-plots", "--no-progress", "--allow-exposure-changes"])
    assert result.exit_code == 0, result.output
    assert "brightness varied" in result.output and "split-half uncertainty" in result.output


@pytest.mark.slow
def test_the_split_half_figure_is_the_size_of_the_error(euroc_vignette):
    """The even and odd frames' LUTs differ by about twice the full LUT's noise: the figure (half the difference)
    is within a factor 3 of the true error for the true response (measured 0.12-0.13 vs 0.15-0.18 levels)."""
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting
    from radiometry.vignetting_calibration.evaluate import split_half_levels
    from vignetting_sweeps import flat_rms_vs_truth

    table = curves()["euroc"] if "euroc" in curves() else curves()["gamma-2.2"]
    response = CameraResponse.from_table(table)
    acc = collect_vignetting(sweep(table, euroc_vignette, frames=64), response, progress=False)
    split = split_half_levels(acc, response, model="lut")
    err = flat_rms_vs_truth(fit_vignetting(acc, model="lut").evaluate(), euroc_vignette, table)
    assert split is not None and np.all(split > err / 3) and np.all(split < 3 * err), (split, err)


def test_jpeg_sweep_frames_are_recognised(euroc_vignette):
    """The accumulation records how blocky the sheet frames are (measured on 376x240 sweeps: PNG 0.99-1.01, JPEG q92
    1.60-1.68, q75 2.35-2.47), so that the summary can say what the split-half figure misses."""
    from radiometry.response.levels import BLOCKY
    from radiometry.vignetting_calibration import collect_vignetting

    table = curves()["kink-4x"]
    response = CameraResponse.from_table(table)
    png = collect_vignetting(sweep(table, euroc_vignette, frames=8), response, progress=False)
    jpeg = collect_vignetting(sweep(table, euroc_vignette, frames=8, quality=92), response, progress=False)
    assert png.blockiness < BLOCKY < jpeg.blockiness, (png.blockiness, jpeg.blockiness)


@pytest.mark.slow
def test_a_static_and_a_hand_held_jpeg_sweep_are_measured_and_said_to_be_jpeg(euroc_vignette):
    """JPEG q75 sweeps with the true response (kink curve): the static sweep (the same sheet image wherever it lies)
    0.24 / 0.31 / 0.44 levels, its split-half figure only 0.05 / 0.06 / 0.17 (JPEG's rounding is the same in every
    frame); a hand-held one (the light across the sheet +-5 % in a random direction each frame, paper texture 1 %)
    0.28 / 0.31 / 0.46 with a split-half of 0.31-0.32: the varying light dithers JPEG's rounding but adds its own
    error, so the target of 0.5 levels is met only narrowly, and the summary says the frames are JPEG."""
    from mapping.cli.vignetting import _truth_free_lines
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting
    from radiometry.vignetting_calibration.evaluate import split_half_levels
    from vignetting_sweeps import flat_rms_vs_truth

    table = curves()["kink-4x"]
    response = CameraResponse.from_table(table)
    for options, bound, split_low in (({}, 0.55, 0.0), ({"gradient": 0.05, "texture": 0.01}, 0.6, 0.2)):
        acc = collect_vignetting(sweep(table, euroc_vignette, frames=64, quality=75, **options), response,
                                 progress=False)
        err = flat_rms_vs_truth(fit_vignetting(acc, model="lut").evaluate(), euroc_vignette, table)
        split = split_half_levels(acc, response, model="lut")
        assert np.all(err <= bound) and np.all(split >= split_low), (options, err, split)
        facts: dict = {}
        lines = _truth_free_lines(acc, response, "lut", {}, facts, True)
        assert any("JPEG-compressed" in line for line in lines) and facts["quality"] == "doubtful", lines


def test_a_wrong_deblur_value_is_refused_naming_it():
    images = [np.full((8, 8, 3), v, np.uint8) for v in (60, 120)]
    with pytest.raises(ValueError, match=r"deblur must be True, False or 'auto'"):
        fit_response(images, [1.0, 2.0], deblur="yes")


def test_a_stack_too_small_to_tell_is_not_taken_for_jpeg():
    """Uncompressed noise's boundary/inside ratio strays past BLOCKY on small images (measured 20-42 % of random
    stacks at 64x48 and 16x16); too few boundary steps count as 'not JPEG' while a 160x120 JPEG stack is still seen."""
    import cv2

    from radiometry.response.levels import BLOCKY, blockiness

    rng = np.random.default_rng(3)
    for h, w in ((16, 16), (48, 64)):
        for _ in range(10):
            stack = rng.integers(90, 110, size=(3, h, w, 3)).astype(np.uint8)
            assert blockiness(stack) == 1.0
    ys, xs = np.mgrid[0:120, 0:160]
    smooth = (100 + 60 * np.sin(xs / 9.0) * np.cos(ys / 13.0))[..., None] + rng.normal(0, 2, (120, 160, 3))
    frames = []
    for gain in (0.6, 0.8, 1.0):
        img = np.clip(smooth * gain, 0, 255).astype(np.uint8)
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
        frames.append(cv2.imdecode(buf, cv2.IMREAD_COLOR))
    assert blockiness(np.stack(frames)) > BLOCKY
    assert blockiness(np.clip(np.stack([smooth * g for g in (0.6, 0.8, 1.0)]), 0, 255).astype(np.uint8)) < BLOCKY
