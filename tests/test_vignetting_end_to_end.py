"""Vignetting calibrated END TO END on a camera radiomap did not make (issue 15): the response calibrated from
brackets by our default method, then the LUT from a white-paper sweep with that response, against the truth.

The EuRoC MT9V034's measured ``vignette.png`` (blue channel shifted) and its measured ``pcalib.txt``, or a kinked
curve (4x steeper above level 180); brackets by ``tests/response_curves.py`` (12 exposures 2x apart, noise, 8-bit)
and sweeps by ``tests/vignetting_sweeps.py`` (random sheet placements, noise, 8-bit), neither using radiomap's
camera code. Measure: RMS in levels of a flat field imaged at 200 where ``V = 1``, through the calibrated ``V`` vs
the true one (a uniform error of the normalisation counts). Needs ``../shared/data``.
"""

from __future__ import annotations

import numpy as np
import pytest

from radiometry.response import CameraResponse
from radiometry.response.fit import fit_response
from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting
from response_curves import TIMES, curves, render_brackets, scene
from vignetting_sweeps import (default_size, flat_rms_vs_truth, render_sweep, shared_available, sheet_masks,
                               vignette_field)

pytestmark = pytest.mark.skipif(not shared_available(),
                                reason="../shared/data (EuRoC vignette.png and pcalib.txt, lensfun) is absent")


@pytest.fixture(scope="module")
def euroc_vignette():
    width, height = default_size("euroc")
    return vignette_field("euroc", width, height)


@pytest.fixture(scope="module", params=["euroc", "kink-4x"])
def calibrated(request, euroc_vignette):
    table = curves()[request.param]
    images = render_brackets(table, scene(240, 320), TIMES)
    response = fit_response(images, TIMES)  # the default method
    sweep = render_sweep(table, euroc_vignette, frames=64)
    luts = {label: fit_vignetting(collect_vignetting(sweep, r, progress=False), model="lut")
            for label, r in (("truth", CameraResponse.from_table(table)), ("calibrated", response))}
    return {"curve": request.param, "table": table, "luts": luts}


@pytest.mark.slow
def test_the_lut_from_the_calibrated_response_is_within_half_a_level(calibrated, euroc_vignette):
    """Measured (R/G/B) with the default (loglog): EuRoC curve 0.17/0.20/0.35, kink-4x 0.10/0.09/0.11; with Debevec
    0.22/0.26/0.32 and 0.06/0.09/0.08 (issue 15 measured 1.85-2.0 before)."""
    lut = calibrated["luts"]["calibrated"].evaluate()
    error = flat_rms_vs_truth(lut, euroc_vignette, calibrated["table"])
    assert np.all(error <= 0.45), (calibrated["curve"], error)


@pytest.mark.slow
def test_with_the_true_response_the_lut_is_within_a_quarter_level_and_unbiased(calibrated, euroc_vignette):
    """Measured: EuRoC curve 0.14/0.15/0.18, kink-4x 0.05/0.05/0.06; the normalisation's uniform part < 0.1 %."""
    lut = calibrated["luts"]["truth"].evaluate()
    strict = flat_rms_vs_truth(lut, euroc_vignette, calibrated["table"])
    assert np.all(strict <= 0.25), strict
    bias = np.median(euroc_vignette / lut, axis=(0, 1)) - 1.0
    assert np.all(np.abs(bias) < 0.001), bias


@pytest.mark.slow
def test_the_budget_of_the_true_response_lut_is_its_error(calibrated, euroc_vignette):
    model = calibrated["luts"]["truth"]
    measured = flat_rms_vs_truth(model.evaluate(), euroc_vignette, calibrated["table"])
    total = np.array(model.info["error_budget"]["total"])
    assert np.all(total > 0.6 * measured) and np.all(total < 1.5 * measured), (total, measured)
    z = (model.evaluate() / euroc_vignette - 1.0) / model.stderr
    assert np.all(np.sqrt(np.mean(z ** 2, axis=(0, 1))) < 1.5)


@pytest.mark.slow
def test_the_centre_fit_removes_the_bias_of_a_noisy_sweep(euroc_vignette, monkeypatch):
    """24 frames, 1500 e- full well: the former normaliser (maximum of the coarsely smoothed LUT) put V 0.1-0.2 %
    low everywhere (strict RMS 0.52-0.63 levels); the centre fit's bias is within 0.1 % (0.47-0.54 levels)."""
    import radiometry.vignetting_calibration.fit as fit_module

    table = curves()["euroc"]
    height, width = euroc_vignette.shape[:2]
    sweep = render_sweep(table, euroc_vignette, frames=24, full_well=1500.0,
                         masks=sheet_masks(height, width, 24, seed=0))
    acc = collect_vignetting(sweep, CameraResponse.from_table(table), progress=False)
    new = fit_vignetting(acc, model="lut").evaluate()

    def maximum(smooth, flat, weights):
        observed = weights > 0
        return np.array([float(np.max(smooth[:, :, c][observed[:, :, c]])) for c in range(smooth.shape[2])]), {
            "stderr": [float("nan")] * smooth.shape[2]}

    monkeypatch.setattr(fit_module, "centre_normalisers", maximum)
    old = fit_vignetting(acc, model="lut").evaluate()
    bias_new = np.median(euroc_vignette / new, axis=(0, 1)) - 1.0
    bias_old = np.median(euroc_vignette / old, axis=(0, 1)) - 1.0
    assert np.all(np.abs(bias_new) < 0.001), bias_new
    assert np.mean(bias_old) > 0.001 and np.mean(bias_old) > 2 * np.mean(np.abs(bias_new)), (bias_old, bias_new)
    assert np.all(flat_rms_vs_truth(new, euroc_vignette, table) <= flat_rms_vs_truth(old, euroc_vignette, table) + 0.01)
