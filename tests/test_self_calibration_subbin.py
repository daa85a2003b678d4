"""The solver's position bins must not hide how points drift across the image (radiometry.self_calibration._SubBin).

A camera that turns on the spot moves points along hyperbolas: a point above the horizon rises as it nears the
image's left or right edge (perspective). With the exposures known, that slow vertical drift is all that pins V's
vertical profile. The data here are exact and of the model's own form (no noise, an even polynomial about a
centre off the image centre), built here with a pinhole camera, not with radiomap's simulator."""

from __future__ import annotations

import numpy as np
import pytest

import radiometry.self_calibration as sc
from radiometry.self_calibration import Observations, self_calibrate

W, H, F = 640, 480, 525.0
CX, CY = 331.5, 232.5          # V's centre: 12 px right of and 7 px above the image centre
RADIUS = 0.5 * np.hypot(W, H)


def v_true(x, y):
    r2 = ((x - CX) ** 2 + (y - CY) ** 2) / RADIUS ** 2
    return 1 - 0.25 * r2 - 0.1 * r2 ** 2


def turning_camera(frames=30, points=2500, seed=0):
    """Sightings of a camera that turns about its vertical axis (-35 .. 35 degrees), points at infinity."""
    rng = np.random.default_rng(seed)
    az = rng.uniform(np.radians(-70), np.radians(70), points)
    el = rng.uniform(np.radians(-23), np.radians(23), points)
    L = np.exp(rng.normal(0, 0.4, points))
    yaw = np.radians(np.linspace(-35, 35, frames))
    k = np.exp(0.3 * np.sin(np.linspace(0, 3, frames)))      # exposures: given, not fitted
    pt, fr, xs, ys = [], [], [], []
    for j, t in enumerate(yaw):
        a = az - t
        x = F * np.tan(a) + (W - 1) / 2
        y = F * np.tan(el) / np.cos(a) + (H - 1) / 2
        inside = (np.cos(a) > 0.3) & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
        pt.append(np.flatnonzero(inside))
        fr.append(np.full(inside.sum(), j))
        xs.append(x[inside])
        ys.append(y[inside])
    pt, fr, xs, ys = map(np.concatenate, (pt, fr, xs, ys))
    keep = np.bincount(pt, minlength=points)[pt] >= 2
    orig, fr, xs, ys = pt[keep], fr[keep], xs[keep], ys[keep]
    _, pt = np.unique(orig, return_inverse=True)
    e = k[fr] * v_true(xs, ys) * L[orig]
    obs = Observations(pt, fr, xs, ys, e[:, None], (W, H), frames)
    return obs, (k / k[0])[:, None]


def _log_error(res):
    v = res.vignetting.evaluate().astype(float)[:, :, 0]
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    err = np.log(v) - np.log(v_true(xs, ys))
    return err - np.median(err)


@pytest.fixture(scope="module")
def turning():
    return turning_camera()


def test_a_turning_camera_with_known_exposures_recovers_the_vertical_profile(turning, monkeypatch):
    obs, k = turning
    res = self_calibrate(obs, exposures=k, centre=((W - 1) / 2, (H - 1) / 2), iterations=8)
    err = _log_error(res)
    rows = err.mean(axis=1)
    assert np.sqrt(np.mean(err ** 2)) < 0.0015, np.sqrt(np.mean(err ** 2))
    assert np.ptp(rows) < 0.005, rows[::40]
    assert abs(res.info["centre"][0][1] - CY) < 2.0, res.info["centre"]
    # the same fit with each sighting taken at its bin's centre (the solver before the correction): the
    # vertical profile comes out bent, which is what the correction removes
    monkeypatch.setattr(sc._SubBin, "correction", lambda self, p: np.zeros(len(self.dx)))
    binned = _log_error(self_calibrate(obs, exposures=k, centre=((W - 1) / 2, (H - 1) / 2), iterations=8))
    assert np.sqrt(np.mean(binned ** 2)) > 3 * np.sqrt(np.mean(err ** 2)), (np.sqrt(np.mean(binned ** 2)),
                                                                          np.sqrt(np.mean(err ** 2)))
