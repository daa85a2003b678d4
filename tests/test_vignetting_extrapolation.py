"""The standard error of a LUT where no sheet went (audit 2026-11-28): a sweep that never covered the right 40 % of
the image (the vignette's centre in the top-left corner) was filled from the radial fit 15.7 % off (median) while
its stated error said 2.4 %, and the budget's coverage part said 3.0 levels against 14.8 measured. Built here
without radiometry's simulator: a static sheet on the left of each frame, a quadratic vignette, gamma 2.2."""

from __future__ import annotations

import numpy as np

from radiometry.response import CameraResponse

W, H = 188, 120


def _truth() -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    return 1.0 - 0.45 * ((xx - 40) ** 2 + (yy - 30) ** 2) / (W ** 2 + H ** 2)


def _frames(cover: float, n: int = 30) -> list[np.ndarray]:
    rng = np.random.default_rng(3)
    truth = _truth()
    frames = []
    for _ in range(n):
        radiance = np.where(np.arange(W)[None, :] < cover * W, 0.6, 0.08) * truth
        radiance = radiance * (1 + rng.normal(0, 0.003, radiance.shape))
        level = 255.0 * np.clip(radiance, 0, 1) ** (1 / 2.2)
        frames.append(np.repeat(np.clip(np.rint(level), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2))
    return frames


def test_the_filled_pixels_error_is_stated_where_the_sheet_never_went():
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting

    acc = collect_vignetting(_frames(0.62), CameraResponse.gamma(2.2), progress=False)
    model = fit_vignetting(acc, model="lut")
    uncovered = acc.count[:, :, 0] == 0
    assert 0.3 < uncovered.mean() < 0.5
    err = np.abs(np.log(model.evaluate()[:, :, 0] / _truth()))[uncovered]
    se = model.stderr[:, :, 0][uncovered]
    ratio = float(np.sqrt(np.mean((err / se) ** 2)))
    assert np.median(err) > 0.05  # the fill is far off there: the test is about saying so
    assert 0.5 < ratio < 2.0, (ratio, np.median(err), np.median(se))  # 5.6 before
    slope = model.info["extrapolation_per_pixel"][0]
    assert slope is not None and slope > 0
    # the budget's coverage part (levels of a flat field at 200) is the size of the true error there
    truth_levels = 200.0 * np.exp(err) ** (1 / 2.2) - 200.0
    true_rms = float(np.sqrt(np.sum(truth_levels ** 2) / uncovered.size))
    coverage = model.info["error_budget"]["coverage"][0]
    assert 0.5 * true_rms < coverage < 2.5 * true_rms, (coverage, true_rms)


def test_a_fully_covered_sweep_has_nothing_to_extrapolate():
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting

    frames = _frames(1.01, n=12)
    model = fit_vignetting(collect_vignetting(frames, CameraResponse.gamma(2.2), progress=False), model="lut")
    assert model.info["extrapolation_per_pixel"] == [0.0, 0.0, 0.0]
    assert model.info["error_budget"]["coverage"][0] < 0.1


def test_a_sheet_just_below_the_clip_is_said_not_blamed_on_the_sweep(caplog):
    """Audit 2026-11-28: a full-frame sheet at levels 233-249 (not clipped) lost its brightest part to the cut at
    250 - 6 and the refusal that followed said the sheet was seen at only 22 % of the image, 'sweep it across the
    whole image'; the help said 'below 250'. The sweep is now warned about with the level to stay under."""
    import logging

    from radiometry.vignetting_calibration import collect_vignetting

    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    v = 1.0 - 0.08 * ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / (W ** 2 + H ** 2) * 4
    bright = [np.repeat(np.clip(np.rint(249.0 * v), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)] * 6
    with caplog.at_level(logging.WARNING):
        collect_vignetting(bright, CameraResponse.gamma(2.2), progress=False)
    line = next((r.getMessage() for r in caplog.records if "left out" in r.getMessage()), "")
    assert "within 6 levels of 250" in line and "stays below 244" in line, caplog.text
    caplog.clear()
    dim = [np.repeat(np.clip(np.rint(225.0 * v), 0, 255).astype(np.uint8)[:, :, None], 3, axis=2)] * 6
    with caplog.at_level(logging.WARNING):
        collect_vignetting(dim, CameraResponse.gamma(2.2), progress=False)
    assert not any("left out" in r.getMessage() for r in caplog.records), caplog.text
