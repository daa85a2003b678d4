"""Self-calibration of vignetting, exposure and white balance (radiometry.self_calibration, mapping.self_calibration,
radiomap self-calibrate)."""

from __future__ import annotations

import numpy as np
import pytest

from radiometry.self_calibration import Observations, SelfCalibrationError, check_constrained, self_calibrate

W, H = 160, 120
R = 0.5 * np.hypot(W, H)


def true_v(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-channel truth built here, not from the library: shifted centres and a non-radial factor."""
    out = []
    for cx, cy, b1 in ((72.0, 55.0, -0.4), (80.0, 60.0, -0.45), (92.0, 66.0, -0.5)):
        r2 = ((x - cx) ** 2 + (y - cy) ** 2) / R ** 2
        out.append((1 + b1 * r2 + 0.05 * r2 ** 2) * (1 + 0.05 * np.sin(2 * np.pi * x / W) * np.cos(np.pi * y / H)))
    return np.stack(out, axis=-1)


def synthetic(seed: int = 0, *, frames: int = 30, points: int = 1500, per_point: int = 8, outliers: float = 0.05,
              spread: bool = True, noise: float = 0.005, noise_seed: int | None = None):
    """Sightings of a scene with known V, k and L; ``noise_seed`` redraws only the noise and outliers (the same
    scene, exposures and geometry as ``seed``)."""
    rng = np.random.default_rng(seed)
    k = np.exp(rng.normal(0, 0.3, (frames, 3)))
    k[0] = 1.0
    L = np.exp(rng.normal(0, 0.5, (points, 3)))
    point = np.repeat(np.arange(points), per_point)
    frame = np.concatenate([rng.choice(frames, per_point, replace=False) for _ in range(points)])
    if spread:
        x, y = rng.uniform(0, W - 1, point.size), rng.uniform(0, H - 1, point.size)
    else:   # every point at one image position: V is not constrained
        x, y = np.repeat(rng.uniform(0, W - 1, points), per_point), np.repeat(rng.uniform(0, H - 1, points), per_point)
    if noise_seed is not None:
        rng = np.random.default_rng(noise_seed)
    e = k[frame] * true_v(x, y) * L[point] * np.exp(rng.normal(0, noise, (point.size, 3)))
    bad = rng.random(point.size) < outliers
    e[bad] *= np.exp(rng.choice([-1, 1], (bad.sum(), 1)) * rng.uniform(0.3, 0.8, (bad.sum(), 3)))
    return Observations(point, frame, x, y, e, (W, H), frames), k, L


@pytest.fixture(scope="module")
def solved():
    obs, k, L = synthetic()
    return obs, k, L, self_calibrate(obs, smoothness=0.01, centre=((W - 1) / 2, (H - 1) / 2), centre_sigma=1.0)


@pytest.mark.slow
def test_recovers_v_k_and_l_despite_outliers(solved):
    obs, k, L, res = solved
    ys, xs = np.mgrid[0:H, 0:W]
    v_true = true_v(xs.astype(float), ys.astype(float))
    v = res.vignetting.evaluate().astype(float)
    # V up to its gauge (V = 1 at the fitted centre): compare shapes after removing the global scale
    ratio = np.log(v_true / v)
    assert np.all(np.std(ratio.reshape(-1, 3), axis=0) < 0.006)
    assert np.median(np.abs(res.exposures / k - 1)) < 0.003
    assert np.max(np.abs(res.exposures / k - 1)) < 0.02
    # radiances up to the one common factor of the gauge per channel
    scale = np.median(res.radiance / L, axis=0)
    assert np.median(np.abs(res.radiance / (L * scale) - 1)) < 0.005
    # the shifted blue centre is found (to a few pixels)
    cx, cy = res.info["centre"][2]
    assert abs(cx - 92) < 8 and abs(cy - 66) < 8


@pytest.mark.slow
def test_gauge(solved):
    obs, _, _, res = solved
    assert np.allclose(res.exposures[0], 1.0)
    v = res.vignetting.evaluate()
    for c, (cx, cy) in enumerate(res.info["centre"]):
        assert v[int(round(cy)), int(round(cx)), c] == pytest.approx(1.0, abs=0.01)
    assert res.vignetting.stderr is not None and res.vignetting.stderr.shape == v.shape
    assert np.all(np.isfinite(res.vignetting.stderr))


def _gauge_error(res) -> np.ndarray:
    """log(V_est / V_true) with the truth in the estimate's gauge (V = 1 at the fitted centre), ``(H, W, 3)``."""
    ys, xs = np.mgrid[0:H, 0:W]
    truth = true_v(xs.astype(float), ys.astype(float))
    out = np.empty_like(truth)
    for c, (cx, cy) in enumerate(res.info["centre"]):
        out[:, :, c] = np.log(res.vignetting.evaluate()[:, :, c] / (truth[:, :, c] /
                                                                     truth[int(round(cy)), int(round(cx)), c]))
    return out


@pytest.mark.slow
def test_stderr_matches_the_spread_of_v_across_noise_seeds():
    """The same scene and camera, four noise draws: the stated standard error of V describes how far V lands from
    the truth. Measured (this scene, 2 % noise): 95-99 % of pixels within 2 standard errors, RMS error / RMS
    stderr 0.78-1.08. Without the single sightings' part taken off the two clusterings (counted twice) the
    stderr was 1.4x too large (97-99.8 % within, ratio 0.66-0.89); with exposures and radiances held fixed, as
    before, it was several times too small."""
    within, ratios = [], []
    for noise_seed in range(4):
        obs, _, _ = synthetic(5, frames=20, points=800, noise=0.02, noise_seed=100 + noise_seed)
        res = self_calibrate(obs, smoothness=0.01, centre=((W - 1) / 2, (H - 1) / 2))
        d, se = _gauge_error(res), res.vignetting.stderr.astype(float)
        away = se > 0.2 * np.median(se)      # not at the gauge point, where both are ~0
        within.append(np.mean(np.abs(d[away]) < 2 * se[away]))
        ratios.append(np.sqrt(np.mean(d[away] ** 2) / np.mean(se[away] ** 2)))
    assert 0.85 < np.mean(within) < 0.995, within
    assert 0.8 < np.mean(ratios) < 1.3, ratios      # counted twice (ratio 0.73) fails


@pytest.mark.slow
def test_thinly_covered_regions_get_a_larger_stderr():
    """Nine in ten sightings in the top-left ninth of the image dropped: V's standard error there grows against
    the opposite corner, which kept all of its sightings, and against the same corner with all of them (measured
    1.79x and 1.76x)."""
    full, _, _ = synthetic(6, frames=20, points=800, noise=0.02)
    thin = (full.x < W / 3) & (full.y < H / 3) & (np.random.default_rng(0).random(full.x.size) < 0.9)
    keep = ~thin
    obs = Observations(full.point[keep], full.frame[keep], full.x[keep], full.y[keep], full.irradiance[keep],
                       (W, H), full.n_frames)
    se_full = self_calibrate(full, smoothness=0.01).vignetting.stderr
    se_thin = self_calibrate(obs, smoothness=0.01).vignetting.stderr
    tl, br = (slice(0, H // 4), slice(0, W // 4)), (slice(-H // 4, None), slice(-W // 4, None))
    assert np.median(se_thin[tl]) > 1.5 * np.median(se_thin[br])
    assert np.median(se_thin[tl]) > 1.5 * np.median(se_full[tl])


@pytest.mark.slow
def test_huber_resists_outliers_that_plain_least_squares_does_not():
    obs, k, _ = synthetic(1, outliers=0.15)
    robust = self_calibrate(obs, smoothness=0.01, centre_sigma=1.0)
    plain = self_calibrate(obs, smoothness=0.01, centre_sigma=1.0, huber=1e6)
    err = [np.median(np.abs(r.exposures / k - 1)) for r in (robust, plain)]
    assert err[0] < 0.004 and err[0] < 0.5 * err[1]


@pytest.mark.slow
def test_cannot_constrain_v_without_motion():
    obs, _, _ = synthetic(2, spread=False)
    with pytest.raises(SelfCalibrationError, match="cannot constrain vignetting.*pans and turns"):
        self_calibrate(obs)


@pytest.mark.slow
def test_too_few_frames():
    obs, _, _ = synthetic(3, frames=2, per_point=2)
    with pytest.raises(SelfCalibrationError, match="only 2 frame.*--frames"):
        check_constrained(obs)


@pytest.mark.slow
def test_observations_are_checked():
    with pytest.raises(ValueError, match="irradiance must be finite and > 0"):
        Observations(np.zeros(2, int), np.zeros(2, int), np.zeros(2), np.zeros(2), np.array([[1.0], [0.0]]),
                     (W, H), 1)
    with pytest.raises(ValueError, match="one length"):
        Observations(np.zeros(2, int), np.zeros(3, int), np.zeros(2), np.zeros(2), np.ones((2, 1)), (W, H), 1)


@pytest.fixture(scope="module")
def room(selfcal_room):
    return selfcal_room


@pytest.mark.slow
def test_cli_on_a_small_simulated_room(room, tmp_path):
    from click.testing import CliRunner

    from mapping.cli import cli
    from mapping.exposure_compensation.records import exposure_errors, read_exposures
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting, VignettingModel
    from radiometry.vignetting_calibration.evaluate import vignetting_error_levels

    out = tmp_path / "sc"
    args = ["self-calibrate", str(room), "-r", str(room / "truth" / "response.npz"), "--poses", "gt", "-o", str(out),
            "--no-progress"]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 0, res.output
    for name in ("vignetting.npz", "exposures.txt", "summary.txt", "self_calibration.json", "vignetting.png",
                 "coverage.png", "exposures.png", "residuals.png", "trajectory.txt"):
        assert (out / name).is_file(), name
    assert "coverage:" in res.output and "resid_after_%" in res.output
    model = VignettingModel.load(out / "vignetting.npz")
    assert isinstance(model, LUTVignetting) and model.stderr is not None
    truth = np.load(room / "truth" / "vignetting.npy")
    err = vignetting_error_levels(model, truth, CameraResponse.load(room / "truth" / "response.npz"))
    # measured 0.43 / 0.37 / 0.95 levels at 160x120, 30 frames, with the 3 px window (5 px: 1.26-1.41)
    assert np.all(err < 1.5), err
    ex = read_exposures(out / "exposures.txt")
    rows = np.loadtxt(room / "truth" / "exposures.txt")
    errs = exposure_errors(ex["k"], rows[ex["index"], 1:2] * rows[ex["index"], 2:5])
    # measured 2.0 % (fitted on 24 frames, every 5th withheld and predicted; 1.75 % with --holdout none; 1.4 %
    # before issue 29 freed the tilt where the data pin it, which took the 640x480 scan of tests/selfcal_camera.py
    # from 0.49 % to 0.10-0.14 %)
    assert errs["median"] < 0.025, errs["median"]
    # a second run into the same folder is refused without --force
    again = CliRunner().invoke(cli, args)
    assert again.exit_code == 1 and "already holds a self-calibration" in again.output


@pytest.mark.slow
def test_icp_poses_on_a_frame_range_that_does_not_start_at_zero(room):
    """ICP poses are placed by the frame's place in the selection, not its number in the sequence (a range
    starting at frame 6 raised IndexError): one pose per selected frame, the first the anchor's ground truth."""
    from mapping.datasets import open_dataset
    from mapping.self_calibration import _poses

    dataset = open_dataset(room, frames=slice(6, 18))
    frames = [dataset[i] for i in range(len(dataset))]
    poses, have = _poses(dataset, frames, "icp", depth_max=4.0, progress=False)
    assert len(poses) == len(have) == 12 and have.sum() >= 6
    np.testing.assert_allclose(poses[0], frames[0].pose, atol=1e-9)   # frame 6 founds the map at its own pose
