"""Self-calibration that says what it cannot know (issue 29): known exposures, the tilt ambiguity, self-validation,
plausibility."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from radiometry.self_calibration import Observations, self_calibrate
from radiometry.self_calibration_checks import plausibility, tilt_visibility
from radiometry.self_calibration_validation import holdout_frames, parse_holdout, subset, validate

W, H = 160, 120
R = 0.5 * np.hypot(W, H)


def v_true(x, y, cx=86.0, cy=57.0):
    """A radial fall-off off the image centre times a left-right shading tilt (built here, not in the library)."""
    r2 = ((x - cx) ** 2 + (y - cy) ** 2) / R ** 2
    return (1 - 0.4 * r2) * (1 + 0.03 * (x - cx) / W)


def pan(seed=0, *, frames=24, points=1500, noise=0.004, shake=0.0):
    """Sightings of a camera that pans: every point moves by one shift per frame (plus ``shake`` px of random
    per-sighting motion, which parallax would give); exposures drift with the pan."""
    rng = np.random.default_rng(seed)
    shift = np.linspace(-60, 60, frames)
    x0 = rng.uniform(-60, W + 60, points)
    y0 = rng.uniform(0, H - 1, points)
    L = np.exp(rng.normal(0, 0.4, points))
    k = np.exp(0.004 * shift)            # auto exposure following the view
    pt, fr, xs, ys = [], [], [], []
    for j in range(frames):
        x = x0 - shift[j] + rng.normal(0, shake, points)
        inside = (x >= 0) & (x <= W - 1)
        pt.append(np.flatnonzero(inside))
        fr.append(np.full(inside.sum(), j))
        xs.append(x[inside])
        ys.append(y0[inside])
    pt, fr, xs, ys = map(np.concatenate, (pt, fr, xs, ys))
    seen = np.bincount(pt, minlength=points)
    keep = seen[pt] >= 2
    orig, fr, xs, ys = pt[keep], fr[keep], xs[keep], ys[keep]
    _, pt = np.unique(orig, return_inverse=True)
    e = k[fr] * v_true(xs, ys) * L[orig] * np.exp(rng.normal(0, noise, len(fr)))
    obs = Observations(pt, fr, xs, ys, np.repeat(e[:, None], 3, axis=1), (W, H), frames)
    return obs, np.repeat((k / k[0])[:, None], 3, axis=1)


# --------------------------------------------------------------------------------------------------
# the tilt ambiguity
# --------------------------------------------------------------------------------------------------
def test_a_pure_pan_leaves_the_tilt_open_and_random_positions_pin_it():
    obs, _ = pan()
    vis = tilt_visibility(obs.x, obs.y, np.ones(len(obs.x)), obs.point, obs.frame, obs.resolution, obs.n_points,
                          obs.n_frames)
    assert vis.open == (True, True) and max(vis.visibility) < 1e-6, vis
    rng = np.random.default_rng(1)
    spread = Observations(obs.point, obs.frame, rng.uniform(0, W - 1, len(obs.x)), rng.uniform(0, H - 1, len(obs.x)),
                          obs.irradiance, (W, H), obs.n_frames)
    vis = tilt_visibility(spread.x, spread.y, np.ones(len(obs.x)), obs.point, obs.frame, (W, H), obs.n_points,
                          obs.n_frames)
    assert vis.open == (False, False) and min(vis.visibility) > 0.3, vis


def test_a_weakly_seen_axis_gets_a_note_and_an_open_or_well_seen_one_does_not():
    from radiometry.self_calibration_checks import FREE_VISIBILITY, OPEN_VISIBILITY, TiltVisibility

    weak = (OPEN_VISIBILITY + FREE_VISIBILITY) / 2
    info = np.eye(2)
    note = TiltVisibility((0.75, weak), info, (False, False)).weak_text()
    assert note.startswith("note: V's up-down profile is seen weakly") and "tilt the camera up and down" in note
    assert f"up-down {100 * weak:.2f}%" in note and "left-right" not in note
    both = TiltVisibility((weak, weak), info, (False, False)).weak_text()
    assert "left-right and up-down profiles are seen weakly" in both and "they rest" in both
    assert "turn the camera back and forth and tilt the camera up and down to pin them" in both
    assert TiltVisibility((0.75, 0.5), info, (False, False)).weak_text() is None          # both pinned
    assert TiltVisibility((0.75, OPEN_VISIBILITY / 2), info, (False, True)).weak_text() is None   # open: ambiguity


@pytest.fixture(scope="module")
def pan_fits():
    obs, k = pan()
    centre = ((W - 1) / 2, (H - 1) / 2)
    return obs, k, self_calibrate(obs, centre=centre), self_calibrate(obs, centre=centre, exposures=k)


def _gauge_error(res, c=0, signed=False):
    v = res.vignetting.evaluate().astype(float)[:, :, c]
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    cx, cy = res.info["centre"][c]
    truth = v_true(xs, ys) / v_true(np.array(cx), np.array(cy))
    err = np.log(v) - np.log(truth)
    return (err if signed else np.abs(err)), res.vignetting.stderr[:, :, c]


@pytest.mark.slow
def test_on_a_pan_the_ambiguity_is_stated_and_the_stderr_covers_the_truth(pan_fits):
    obs, k, blind, _ = pan_fits
    assert blind.info["tilt_open"] == [True, True]
    assert "cannot pin a left-right or up-down tilt" in blind.info["ambiguity"]
    assert "--exposures" in blind.info["ambiguity"]
    err, se = _gauge_error(blind)
    assert np.mean(err <= 2 * se) >= 0.8, (np.mean(err <= 2 * se), np.median(err), np.median(se))


@pytest.mark.slow
def test_known_exposures_pin_the_tilt_on_the_same_pan(pan_fits):
    obs, k, blind, known = pan_fits
    # known exposures pin the left-right tilt; points of a pan never move up or down: that tilt stays open
    assert known.info["exposures_known"] == obs.n_frames and known.info["tilt_open"] == [False, True]
    assert "up-down" in known.info["ambiguity"] and "left-right or" not in known.info["ambiguity"]
    signed = {}
    for name, res in (("known", known), ("blind", blind)):
        err, se = _gauge_error(res, signed=True)
        signed[name] = np.mean(err[:, W // 2:]) - np.mean(err[:, :W // 2])     # the left-right tilt of the error
        if name == "known":
            assert np.mean(np.abs(err) <= 2 * se) >= 0.8
    assert abs(signed["known"]) < 0.002 and abs(signed["blind"]) > 4 * abs(signed["known"]), signed
    np.testing.assert_allclose(known.exposures, k, rtol=1e-9)     # given, not fitted (scaled to frame 0)


@pytest.mark.slow
def test_partly_known_exposures_fit_only_the_rest(pan_fits):
    obs, k, _, _ = pan_fits
    part = k.copy()
    part[5:9] = np.nan
    res = self_calibrate(obs, centre=((W - 1) / 2, (H - 1) / 2), exposures=part)
    np.testing.assert_allclose(res.exposures[:5], k[:5], rtol=1e-9)
    assert np.max(np.abs(res.exposures[5:9] / k[5:9] - 1)) < 0.01


# --------------------------------------------------------------------------------------------------
# self-validation
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("spec, held", [("every:5", [4, 9]), ("last:20%", [8, 9]), ("none", [])])
def test_holdout_frames(spec, held):
    assert np.flatnonzero(holdout_frames(10, spec)).tolist() == held


@pytest.mark.parametrize("spec", ["every:1", "every:x", "last:0%", "last:60%", "all", ""])
def test_bad_holdout_is_refused_naming_the_forms(spec):
    with pytest.raises(ValueError, match="every:N.*last:P%.*none"):
        parse_holdout(spec)


def _linear_tables():
    return np.repeat(np.linspace(0, 1, 256)[:, None], 3, axis=1)


@pytest.mark.slow
def test_validation_prefers_the_true_v_and_rejects_a_wrong_one():
    from dataclasses import replace

    from radiometry.vignetting import LUTVignetting

    obs, k = pan(shake=8.0)
    obs = Observations(obs.point, obs.frame, obs.x, obs.y, obs.irradiance * 0.5, obs.resolution, obs.n_frames)
    held = holdout_frames(obs.n_frames, "every:4")
    train, test = subset(obs, ~held[obs.frame]), subset(obs, held[obs.frame])
    res = self_calibrate(train, centre=((W - 1) / 2, (H - 1) / 2))
    good = validate(res, train, test, _linear_tables(), "every:4")
    assert good.helps and np.mean(good.l1_with) < 0.7 * np.mean(good.l1_without), good
    assert good.frames == held.sum() and np.all(np.isfinite(good.exposures[held]))
    # a V brighter at the corners (inverted): the withheld frames say so
    v = res.vignetting.evaluate()
    wrong = replace(res, vignetting=LUTVignetting((1.0 / v).astype(np.float32)))
    bad = validate(wrong, train, test, _linear_tables(), "every:4")
    assert not bad.helps and "does NOT help" in bad.text()


def _made_up(l1, psnr, l1_noise=0.1, psnr_noise=0.2):
    """A validation with the channels' figures ``l1 = (without, with)`` and ``psnr = (without, with)``."""
    from radiometry.self_calibration_validation import Validation

    return Validation(10, 5000, (l1[0],) * 3, (l1[1],) * 3, (psnr[0],) * 3, (psnr[1],) * 3, "every:5",
                      np.full((50, 3), np.nan), l1_noise, psnr_noise)


def test_verdict_is_mixed_when_psnr_gets_worse_beyond_its_noise_while_l1_improves():
    # the kitchen's figures (audit): L1 2.57 -> 2.43, PSNR 31.89 -> 31.06 dB was printed as "V helps"
    found = _made_up((2.57, 2.43), (31.89, 31.06))
    assert found.verdict == "mixed" and not found.helps
    assert "mixed: L1 better, PSNR worse by 0.83 dB" in found.text() and "V helps" not in found.text()
    assert found.as_dict()["verdict"] == "mixed" and found.as_dict()["v_helps"] is False
    # the other way round
    other = _made_up((2.43, 2.57), (31.06, 31.89), l1_noise=0.05)
    assert other.verdict == "mixed" and "mixed: PSNR better, L1 worse by 0.14 levels" in other.text()


@pytest.mark.parametrize("l1, psnr, verdict", [
    ((2.57, 2.43), (31.89, 31.80), "helps"),           # PSNR worse, but within its noise (0.2 dB)
    ((2.57, 2.43), (31.06, 31.89), "helps"),           # both better
    ((2.43, 2.47), (31.06, 31.89), "helps"),           # L1 worse within its noise (0.1 levels)
    ((2.43, 2.57), (31.89, 31.06), "does not help"),   # both worse
    ((2.50, 2.50), (31.00, 31.00), "does not help"),   # no change
])
def test_verdict_helps_only_when_neither_figure_gets_worse_beyond_its_noise(l1, psnr, verdict):
    found = _made_up(l1, psnr)
    assert found.verdict == verdict and found.helps == (verdict == "helps")
    assert ("V helps" in found.text()) == (verdict == "helps")


def test_validation_noise_is_the_standard_error_over_withheld_frames():
    from radiometry.self_calibration_validation import _clustered_stderr

    # one value per frame, 40 sightings each: the standard error of the mean of the frames' values
    per_frame = np.array([0.3, -0.1, 0.5, 0.2, 0.0])
    frame = np.repeat(np.arange(5), 40)
    got = _clustered_stderr(per_frame[frame], frame)
    assert got == pytest.approx(np.std(per_frame, ddof=1) / np.sqrt(5))
    assert _clustered_stderr(np.ones(30), np.zeros(30, int)) == 0.0       # one frame: no spread to measure


# --------------------------------------------------------------------------------------------------
# plausibility
# --------------------------------------------------------------------------------------------------
def _lut(f):
    ys, xs = np.mgrid[0:H, 0:W].astype(float)
    return np.repeat(f(xs, ys)[:, :, None], 3, axis=2)


def test_a_lens_like_v_is_plausible():
    assert plausibility(_lut(v_true), None, [(86, 57)] * 3) == []
    # a decentred, elliptical fall-off with a tilt (no blob): plausible too, whatever centre it is judged from
    odd = _lut(lambda x, y: (1 - 0.5 * (((x - 110) / W) ** 2 + 2.5 * ((y - 40) / H) ** 2)) * (1 + 0.05 * x / W))
    assert plausibility(odd, None, [(79.5, 59.5)] * 3) == []


def test_brighter_corners_and_dark_blobs_are_flagged_with_the_causes():
    inverted = _lut(lambda x, y: 1 / v_true(x, y))
    notes = plausibility(inverted, None, [(86, 57)] * 3)
    assert any("brighter away from its centre" in n for n in notes)
    assert "lens-shading correction" in notes[-1] and "depth not registered" in notes[-1]
    blob = _lut(lambda x, y: v_true(x, y) * (1 - 0.1 * np.exp(-((x - 50) ** 2 + (y - 70) ** 2) / 50.0)))
    notes = plausibility(blob, None, [(86, 57)] * 3)
    assert any("dark blob" in n and "x=50" in n for n in notes), notes


# --------------------------------------------------------------------------------------------------
# known exposures from files
# --------------------------------------------------------------------------------------------------
def _dataset(n=10, start=0.0):
    from mapping.datasets.base import RGBDFrame
    from mapping.datasets.in_memory import ArrayDataset

    K = np.array([[50.0, 0, 8], [0, 50.0, 6], [0, 0, 1]])
    return ArrayDataset([RGBDFrame(index=i, timestamp=start + i / 30, rgb=np.zeros((12, 16, 3), np.uint8),
                                   depth=np.ones((12, 16), np.float32), K=K) for i in range(n)])


@pytest.mark.parametrize("text, per_channel, kind", [
    ("# t k\n" + "".join(f"{i / 30:.6f} {1 + i / 10}\n" for i in range(10)), False, "plain"),
    ("".join(f"{i / 30:.6f} {1 + i / 10} {2 + i / 10} {3 + i / 10}\n" for i in range(10)), True, "plain"),
    ("".join(f"{i} {i / 30:.6f} {(1 + i / 10) * 10}\n" for i in range(10)), False, "tum-monovo"),
    ("# radiomap\n" + "".join(f"{i} {i / 30:.6f} {1 + i / 10} {2 + i / 10} {3 + i / 10} 100 map\n"
                              for i in range(10)), True, "radiomap"),
])
def test_exposure_files_of_every_layout(tmp_path, text, per_channel, kind):
    from mapping.exposure_files import match_exposure_file

    path = tmp_path / "exp.txt"
    path.write_text(text)
    table = match_exposure_file(_dataset(), path)
    assert table.kind == kind and table.per_channel == per_channel and table.matched == 10
    ratio = table.values / table.values[0]
    assert np.allclose(ratio[:, 0], (1 + np.arange(10) / 10) / 1.0)


def test_a_short_exposure_list_for_a_command_that_fits_none_is_one_error_without_a_fitted_warning(tmp_path, caplog):
    """reconstruct with 10 of 20 frames listed: it said WARNING "... theirs are fitted", then the error that it needs
    one per frame. Now the error alone; self-calibrate (which fits them) still warns and goes on."""
    from mapping.exposure_files import ExposureFileError, match_exposure_file
    from mapping.factory import _given_exposures

    path = tmp_path / "exp.txt"
    path.write_text("".join(f"{i / 30:.6f} {1 + i / 10}\n" for i in range(10)))
    with caplog.at_level(logging.WARNING), pytest.raises(
            ExposureFileError, match=r"exp\.txt: 10 of 20 frames have no exposure \(by timestamp.*; reconstruct needs one "
                                     r"per frame \(radiomap self-calibrate fits the missing ones"):
        _given_exposures(path, _dataset(20), None, None, 0.02)
    assert "fitted" not in caplog.text
    with pytest.raises(ExposureFileError, match="; compare needs one per frame"):
        match_exposure_file(_dataset(20), path, every_frame="compare")
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert match_exposure_file(_dataset(20), path).matched == 10
    assert "10 of 20 frames have no exposure in the file; theirs are fitted" in caplog.text


def test_exposures_by_order_when_the_clock_differs(tmp_path, caplog):
    from mapping.exposure_files import match_exposure_file

    class Seq:       # a file sequence's attributes: timestamps from another clock, 10 frames in all
        total_frames = 10

        def __init__(self):
            self.frames = [_dataset(10, start=1e9)[i] for i in range(10)]

        def __len__(self):
            return 10

        def __getitem__(self, i):
            return self.frames[i]

    path = tmp_path / "times.txt"
    path.write_text("".join(f"{i} {i * 0.05:.3f} {5 + i}\n" for i in range(10)))
    with caplog.at_level(logging.WARNING):
        table = match_exposure_file(Seq(), path)
    assert table.matched == 10 and "in order" in table.how and "taken in order" in caplog.text
    assert table.values[3, 0] == 8


@pytest.mark.parametrize("text, message", [
    ("1.0 2.0 3.0 4.0 5.0\n", "expected 'timestamp k'"),
    ("0.0 1.0\n0.1 1.0 1.0 1.0\n", "one layout per file"),
    ("0.0 -1.0\n", "finite and > 0"),
    ("0.0 abc\n", "not numbers"),
    ("# nothing\n", "no exposure rows"),
])
def test_bad_exposure_files_are_refused_in_one_line(tmp_path, text, message):
    from mapping.exposure_files import ExposureFileError, match_exposure_file

    path = tmp_path / "exp.txt"
    path.write_text(text)
    with pytest.raises(ExposureFileError, match=message) as info:
        match_exposure_file(_dataset(), path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_an_exposure_file_of_another_sequence_is_refused(tmp_path):
    from mapping.exposure_files import ExposureFileError, match_exposure_file

    path = tmp_path / "exp.txt"
    path.write_text("".join(f"{100 + i:.3f} 1.0\n" for i in range(3)))
    with pytest.raises(ExposureFileError, match="10 of 10 frames have no exposure"):
        match_exposure_file(_dataset(), path)


# --------------------------------------------------------------------------------------------------
# the command
# --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def room(selfcal_room):
    return selfcal_room


@pytest.mark.slow
def test_cli_with_known_exposures_validation_and_checks(room, tmp_path):
    import json

    from click.testing import CliRunner

    from mapping.cli import cli
    from mapping.datasets import open_dataset

    rows = np.loadtxt(room / "truth" / "exposures.txt")
    k = rows[:, 1:2] * rows[:, 2:5]
    stamps = open_dataset(room).timestamps
    exp_file = tmp_path / "exposures_known.txt"
    exp_file.write_text("# timestamp kR kG kB\n" + "".join(f"{t:.6f} {a:.9e} {b:.9e} {c:.9e}\n"
                                                           for t, (a, b, c) in zip(stamps, k)))
    out = tmp_path / "sc"
    res = CliRunner().invoke(cli, ["self-calibrate", str(room), "-r", str(room / "truth" / "response.npz"),
                                   "--poses", "gt", "-o", str(out), "--no-progress", "--no-plots",
                                   "--exposures", str(exp_file), "--holdout", "every:4"])
    assert res.exit_code == 0, res.output
    doc = json.loads((out / "self_calibration.json").read_text())
    assert doc["validation"]["withheld_frames"] == 7 and doc["validation"]["v_helps"] is True
    assert "validation on 7 withheld frames (every:4" in res.output and "V helps" in res.output
    assert doc["exposures_given"].startswith(str(exp_file)) and doc["solver"]["exposures_known"] == 30
    from mapping.exposure_compensation.records import read_exposures

    got = read_exposures(out / "exposures.txt")
    # the given exposures come back (scaled to the first frame), withheld frames included
    assert len(got["index"]) == 30
    np.testing.assert_allclose(got["k"], k[got["index"]] / k[0], rtol=1e-5)


@pytest.mark.slow
def test_strict_refuses_a_v_that_does_not_help_and_writes_nothing(room, tmp_path, monkeypatch):
    from click.testing import CliRunner

    from mapping.cli import cli
    from radiometry import self_calibration_validation as scv

    monkeypatch.setattr(scv.Validation, "helps", property(lambda self: False))
    out = tmp_path / "sc"
    args = ["self-calibrate", str(room), "-r", str(room / "truth" / "response.npz"), "--poses", "gt", "-o", str(out),
            "--no-progress", "--no-plots", "--frames", "0:20"]
    res = CliRunner().invoke(cli, [*args, "--strict"])
    assert res.exit_code == 1 and "--strict: V does not predict withheld frames better than no V" in res.output
    assert not out.exists()          # no trace: the next run into it is not refused
    res = CliRunner().invoke(cli, args)            # without --strict: written, with the warning
    assert res.exit_code == 0 and "do not use this vignetting.npz" in res.output
    assert (out / "vignetting.npz").is_file()


@pytest.mark.slow
@pytest.mark.parametrize("option, message", [
    (["--holdout", "every:1"], "--holdout"),
    (["--exposures", "missing.txt"], "no such exposure file"),
])
def test_cli_bad_options_fail_in_one_line_before_writing(room, tmp_path, option, message):
    from click.testing import CliRunner

    from mapping.cli import cli

    out = tmp_path / "sc"
    res = CliRunner().invoke(cli, ["self-calibrate", str(room), "--poses", "gt", "-o", str(out), "--no-progress",
                                   *option])
    assert res.exit_code != 0 and message in res.output, res.output
    assert not out.exists()


def _known_file(room, path, rows=None):
    from mapping.datasets import open_dataset

    truth = np.loadtxt(room / "truth" / "exposures.txt")
    k = truth[:, 1:2] * truth[:, 2:5]
    stamps = open_dataset(room).timestamps
    keep = range(len(k)) if rows is None else rows
    path.write_text("".join(f"{stamps[i]:.6f} {k[i, 0]:.9e} {k[i, 1]:.9e} {k[i, 2]:.9e}\n" for i in keep))
    return k


@pytest.mark.slow
def test_reconstruct_uses_given_exposures_instead_of_estimates(room, tmp_path):
    from click.testing import CliRunner

    from mapping.cli import cli
    from mapping.exposure_compensation.records import read_exposures

    k = _known_file(room, tmp_path / "k.txt")
    out = tmp_path / "rec"
    res = CliRunner().invoke(cli, ["reconstruct", str(room), "-o", str(out), "-r", str(room / "truth" / "response.npz"),
                                   "--poses", "gt", "--frames", "0:8", "--exposures", str(tmp_path / "k.txt"),
                                   "--no-progress"])
    assert res.exit_code == 0, res.output
    got = read_exposures(out / "exposures.txt")
    assert list(got["source"]) == ["reference"] + ["given"] * 7
    np.testing.assert_allclose(got["k"], k[:8] / k[0], rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("extra, message", [
    ([], "--exposures"),                                     # no response: nothing to compensate
    (["-r", "RESPONSE", "--frames", "0:12"], "2 of 12 frames have no exposure"),
])
def test_reconstruct_refuses_given_exposures_it_cannot_use(room, tmp_path, extra, message):
    from click.testing import CliRunner

    from mapping.cli import cli

    _known_file(room, tmp_path / "k.txt", rows=range(10))
    extra = [str(room / "truth" / "response.npz") if e == "RESPONSE" else e for e in extra]
    out = tmp_path / "rec"
    res = CliRunner().invoke(cli, ["reconstruct", str(room), "-o", str(out), "--poses", "gt", "--exposures",
                                   str(tmp_path / "k.txt"), "--no-progress", *extra])
    assert res.exit_code != 0 and message in res.output, res.output
    assert not (out / "mesh.ply").exists()


@pytest.mark.slow
def test_compare_ec_methods_take_given_exposures(room, tmp_path):
    from click.testing import CliRunner

    from mapping.cli import cli
    from mapping.exposure_compensation.records import read_exposures

    k = _known_file(room, tmp_path / "k.txt")
    out = tmp_path / "cmp"
    base = ["compare", str(room), "-o", str(out), "-r", str(room / "truth" / "response.npz"), "--poses", "gt",
            "--frames", "0:6", "--no-progress", "--views", "0", "--exposures", str(tmp_path / "k.txt")]
    res = CliRunner().invoke(cli, [*base, "--methods", "response+ec"])
    assert res.exit_code == 0, res.output
    got = read_exposures(next(out.rglob("exposures.txt")))
    assert list(got["source"]) == ["reference"] + ["given"] * 5
    np.testing.assert_allclose(got["k"], k[:6] / k[0], rtol=1e-5)
    res = CliRunner().invoke(cli, [*base[:3], str(tmp_path / "cmp2"), *base[4:], "--methods", "response"])
    assert res.exit_code == 2 and "applies to the +ec methods only" in res.output


def test_given_exposures_are_looked_up_relative_to_the_first_frame():
    from types import SimpleNamespace

    from mapping.exposure_compensation.given import GivenExposures
    from radiometry.response import CameraResponse

    est = GivenExposures(CameraResponse.gamma(2.2), known={5: [2.0, 2.0, 4.0], 6: 3.0}, source="k.txt")
    first = est.estimate(SimpleNamespace(index=5, timestamp=0.0))
    second = est(SimpleNamespace(index=6, timestamp=0.1))
    assert first.source == "reference" and np.allclose(first.k, 1.0)
    np.testing.assert_allclose(second, [1.5, 1.5, 0.75])
    assert est.records[-1].source == "given" and est.settings() == {"given": "k.txt", "frames": 2}
    with pytest.raises(KeyError, match="frame 7 has no given exposure"):
        est.estimate(SimpleNamespace(index=7, timestamp=0.2))
    with pytest.raises(ValueError, match="finite and > 0"):
        GivenExposures(CameraResponse.gamma(2.2), known={1: [1.0, -1.0, 1.0]})


@pytest.mark.slow
def test_a_run_refused_after_the_folder_was_made_leaves_no_trace(room, tmp_path, monkeypatch):
    """A refusal raised while the run works (data that cannot constrain V, found only after reading the frames)
    removes the RUNNING marker and the folder this run made: the next run into it needs no --force
    (docs/real_inputs.md, "A refused run writes nothing")."""
    from click.testing import CliRunner

    from mapping import self_calibration as msc
    from mapping.cli import cli
    from radiometry.self_calibration import SelfCalibrationError

    def refuse(*args, **kwargs):
        raise SelfCalibrationError("the sequence cannot constrain vignetting: too few surface points")

    out = tmp_path / "sc"
    args = ["self-calibrate", str(room), "-r", str(room / "truth" / "response.npz"), "--poses", "gt", "-o", str(out),
            "--no-progress", "--no-plots", "--frames", "0:20"]
    with monkeypatch.context() as m:
        m.setattr(msc, "_solve_and_check", refuse)
        res = CliRunner().invoke(cli, args)
    assert res.exit_code == 1 and "cannot constrain vignetting" in res.output
    assert not out.exists()
    res = CliRunner().invoke(cli, args)            # not refused for an earlier run: there was none
    assert res.exit_code == 0, res.output
    assert (out / "vignetting.npz").is_file()
