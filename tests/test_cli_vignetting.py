"""Smoke tests of ``radiomap vignetting`` and ``radiomap correct`` on a small simulated sweep."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from conftest import shared_path
from mapping.cli import cli
from radiometry.correction import Corrector
from radiometry.formats import load_vignetting
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting, PolynomialVignetting
from radiometry.vignetting_calibration import vignetting_error_levels

W, H = 96, 72


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    from mapping.simulation.sequences import simulate_paper

    out = simulate_paper(tmp_path_factory.mktemp("cli") / "paper", camera="xtion", seed=5, n_frames=120, width=W,
                         height=H, progress=False, write_depth_images=False)
    return {"rgb": out / "rgb", "response": out / "truth" / "response.npz",
            "truth": np.load(out / "truth" / "vignetting.npy")}


def invoke(*args: str):
    result = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    return result


def one_line_error(result) -> str:
    """The error is one line (the progress bar, which clears itself on a terminal, may precede it)."""
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    assert result.stderr.count("radiomap: error: ") == 1, result.stderr
    line = result.stderr[result.stderr.index("radiomap: error: "):]
    assert line.endswith("\n") and "\n" not in line[:-1], result.stderr
    return line.strip()


@pytest.mark.slow
def test_vignetting_lut_writes_model_coverage_plots_and_summary(sweep, tmp_path):
    out = tmp_path / "vig.npz"
    result = invoke("vignetting", sweep["rgb"], "--response", sweep["response"], "-o", out, "--min-samples", "10")
    assert result.exit_code == 0, result.output
    for suffix in ("_coverage.png", "_vignetting.png", "_profiles.png", "_residuals.png"):
        assert cv2.imread(str(tmp_path / f"vig{suffix}")) is not None, suffix
    import re

    used, skipped = (int(v) for v in re.search(r"frames used: (\d+), skipped: (\d+)", result.stdout).groups())
    assert used + skipped == 120 and used >= 110
    assert "coverage:" in result.stdout and "corner/centre" in result.stdout and "fit_rms_levels" in result.stdout
    assert (tmp_path / "vig_summary.txt").read_text().strip() == result.stdout.strip()
    import json

    summary = json.loads((tmp_path / "vig_summary.json").read_text())
    assert summary["frames_used"] == used and len(summary["channels"]) == 3
    assert all(0.3 < row["corner/centre"] < 0.7 for row in summary["channels"])
    assert all(row["fit_rms_levels"] < 1.0 for row in summary["channels"])
    model = load_vignetting(out)
    assert isinstance(model, LUTVignetting)
    response = CameraResponse.load(sweep["response"])
    assert np.all(vignetting_error_levels(model, sweep["truth"], response) < 1.0)
    # a calibration is never overwritten without --force
    line = one_line_error(invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", out))
    assert "exists; pass --force" in line
    assert invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", out, "--force", "--no-plots",
                  "--max-frames", "60").exit_code == 0


@pytest.mark.slow
@pytest.mark.parametrize("name, model, cls", [("xtion.vgn", "poly", PolynomialVignetting),
                                              ("vignette.png", "poly-fixed-center", LUTVignetting)])
def test_vignetting_foreign_formats(sweep, tmp_path, name, model, cls):
    out = tmp_path / name
    result = invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", out, "--model", model, "--no-plots")
    assert result.exit_code == 0, result.output
    assert (tmp_path / f"{out.stem}_coverage.png").is_file()
    assert not (tmp_path / f"{out.stem}_profiles.png").exists()
    loaded = load_vignetting(out)
    assert isinstance(loaded, cls) and loaded.resolution == (W, H)


def test_vignetting_errors(sweep, tmp_path):
    clipped = shared_path("vignetting", "flatfield_clipped_usbcam", "white_background_500us.jpg")
    line = one_line_error(invoke("vignetting", clipped, "-r", sweep["response"], "-o", tmp_path / "v.npz"))
    assert "saturated" in line and "lower the exposure" in line
    assert not (tmp_path / "v.npz").exists()
    line = one_line_error(invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", tmp_path / "v.txt"))
    assert "unknown model format '.txt'" in line
    line = one_line_error(invoke("vignetting", sweep["rgb"], "-r", tmp_path / "none.npz", "-o", tmp_path / "v.npz"))
    assert "none.npz: no such file" in line
    line = one_line_error(invoke("vignetting", tmp_path / "nothing", "-r", sweep["response"], "-o", tmp_path / "v.npz"))
    assert "no such folder, video or image" in line
    result = invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", tmp_path / "v.npz", "--model", "spline")
    assert result.exit_code == 2 and "'spline' is not one of 'lut', 'poly', 'poly-fixed-center'" in result.output


def test_a_forced_run_removes_the_figures_it_does_not_write_again(sweep, tmp_path):
    """--force --no-plots (or a model without a standard error) over an earlier run: the earlier run's figures,
    which describe another model, go with the set it replaces; the coverage map and summaries are written anew."""
    out = tmp_path / "v1.png"
    common = ("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", out, "--max-frames", "40")
    assert invoke(*common).exit_code == 0
    figures = [tmp_path / f"v1_{name}.png" for name in ("vignetting", "stderr", "profiles", "residuals")]
    assert all(p.is_file() for p in figures)
    mine = tmp_path / "v1_notes.txt"   # not a name radiomap writes: never removed
    mine.write_text("mine")
    result = invoke(*common, "--model", "poly", "--force", "--no-plots")
    assert result.exit_code == 0, result.output
    assert [p.name for p in figures if p.exists()] == []
    assert (tmp_path / "v1_coverage.png").is_file() and (tmp_path / "v1_summary.json").is_file()
    assert mine.read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["v1.png", "v1_coverage.png", "v1_notes.txt",
                                                          "v1_summary.json", "v1_summary.txt"]


@pytest.fixture(scope="module")
def model_file(sweep, tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "v.npz"
    assert invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", path, "--no-plots",
                  "--max-frames", "80").exit_code == 0
    return path


@pytest.mark.slow
def test_correct_folder_and_irradiance(sweep, model_file, tmp_path):
    frames = sorted(sweep["rgb"].iterdir())[:3]
    src = tmp_path / "in"
    src.mkdir()
    for f in frames:
        (src / f.name).write_bytes(f.read_bytes())
    result = invoke("correct", src, "-r", sweep["response"], "--vignetting", model_file, "-o", tmp_path / "out",
                    "--scale", "0.9")
    assert result.exit_code == 0, result.output
    assert "wrote 3 corrected images" in result.stdout and "scale 0.9" in result.stdout
    cor = Corrector(CameraResponse.load(sweep["response"]), load_vignetting(model_file))
    rgb = cv2.cvtColor(cv2.imread(str(frames[0])), cv2.COLOR_BGR2RGB)
    written = cv2.cvtColor(cv2.imread(str(tmp_path / "out" / frames[0].name)), cv2.COLOR_BGR2RGB)
    np.testing.assert_array_equal(written, cor.correct(rgb, scale=0.9))
    result = invoke("correct", src, "-r", sweep["response"], "--vignetting", model_file, "-o", tmp_path / "irr",
                    "--irradiance")
    assert result.exit_code == 0 and "wrote 3 irradiance maps" in result.stdout
    irr = np.load(tmp_path / "irr" / (frames[0].stem + ".npy"))
    assert irr.dtype == np.float32
    np.testing.assert_array_equal(irr, cor.irradiance(rgb))
    result = invoke("correct", frames[1], "-r", sweep["response"], "--vignetting", model_file, "-o", tmp_path / "tif",
                    "--irradiance", "--irradiance-format", "tiff")
    assert result.exit_code == 0, result.output
    tif = cv2.imread(str(tmp_path / "tif" / (frames[1].stem + ".tiff")), cv2.IMREAD_UNCHANGED)
    rgb1 = cv2.cvtColor(cv2.imread(str(frames[1])), cv2.COLOR_BGR2RGB)
    np.testing.assert_allclose(tif[:, :, ::-1], cor.irradiance(rgb1), rtol=1e-6)
    # outputs are not overwritten silently
    line = one_line_error(invoke("correct", src, "-r", sweep["response"], "--vignetting", model_file,
                                 "-o", tmp_path / "out"))
    assert "exists; pass --force" in line


@pytest.mark.slow
def test_correct_video_and_auto_scale(sweep, model_file, tmp_path):
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (W, H))
    if not writer.isOpened():
        pytest.skip("OpenCV has no MJPG writer here")
    for f in sorted(sweep["rgb"].iterdir())[:4]:
        writer.write(cv2.imread(str(f)))
    writer.release()
    result = invoke("correct", video, "-r", sweep["response"], "--vignetting", model_file, "-o", tmp_path / "v",
                    "--scale", "auto")
    assert result.exit_code == 0, result.output
    assert "--scale auto:" in result.stdout and "wrote 4 corrected images" in result.stdout
    assert sorted(p.name for p in (tmp_path / "v").iterdir()) == [".radiomap-correct.json"] + [f"frame_{i:06d}.png"
                                                                  for i in range(4)]
    result = invoke("correct", video, "-r", sweep["response"], "--vignetting", model_file, "-o", tmp_path / "w",
                    "--scale", "-2")
    assert result.exit_code == 1 and "--scale -2 is outside the sensible range 0.0001..10000" in result.output


@pytest.mark.slow
def test_correct_resolution_mismatch(sweep, model_file, tmp_path):
    img = tmp_path / "square.png"
    cv2.imwrite(str(img), np.full((64, 64, 3), 100, np.uint8))
    line = one_line_error(invoke("correct", img, "-r", sweep["response"], "--vignetting", model_file,
                                 "-o", tmp_path / "o"))
    assert "calibrated at 96x72" in line and "64x64" in line


# ==================================================================================================
# live camera, --stop-when-covered, --smooth-sigma
# ==================================================================================================
class FakeCapture:
    """A stand-in for ``cv2.VideoCapture``: ``read()`` returns the given BGR frames, then fails."""

    def __init__(self, frames, opened=True):
        self.frames, self.opened, self.reads, self.released = list(frames), opened, 0, False

    def isOpened(self):  # noqa: N802 - OpenCV's name
        return self.opened

    def read(self):
        self.reads += 1
        if not self.opened or self.reads > len(self.frames):
            return False, None
        return True, self.frames[self.reads - 1].copy()

    def release(self):
        self.released = True


def _summary(prefix):
    import json

    return json.loads(prefix.with_name(prefix.name + "_summary.json").read_text())


@pytest.mark.slow
def test_vignetting_from_a_camera_index(sweep, tmp_path, monkeypatch):
    """``radiomap vignetting 0``: the camera's BGR frames (after 10 warm-up frames, noise here) give the
    same model as the same frames read from the folder."""
    from radiometry.images import list_images

    rng = np.random.default_rng(0)
    warmup = [rng.integers(0, 256, (H, W, 3), dtype=np.uint8) for _ in range(10)]
    bgr = [cv2.imread(str(p)) for p in list_images(sweep["rgb"])[:40]]
    captures = []

    def capture(index):
        captures.append((index, FakeCapture(warmup + bgr)))
        return captures[-1][1]

    monkeypatch.setattr(cv2, "VideoCapture", capture)
    result = invoke("vignetting", "0", "-r", sweep["response"], "-o", tmp_path / "cam.npz", "--no-plots",
                    "--max-frames", "30")
    assert result.exit_code == 0, result.output
    assert [i for i, _ in captures] == [0] and captures[0][1].released and captures[0][1].reads == 40
    folder = invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", tmp_path / "dir.npz", "--no-plots",
                    "--max-frames", "30")
    assert folder.exit_code == 0, folder.output
    live, ref = _summary(tmp_path / "cam"), _summary(tmp_path / "dir")
    assert live["frames_used"] == ref["frames_used"] >= 28 and live["frames_skipped"] == ref["frames_skipped"]
    assert live["run"]["parameters"]["frames"] == "0"
    np.testing.assert_array_equal(load_vignetting(tmp_path / "cam.npz").evaluate(),
                                  load_vignetting(tmp_path / "dir.npz").evaluate())
    # a camera that does not open: one line naming the camera and the fix, nothing written
    monkeypatch.setattr(cv2, "VideoCapture", lambda index: FakeCapture([], opened=False))
    line = one_line_error(invoke("vignetting", "3", "-r", sweep["response"], "-o", tmp_path / "none.npz"))
    assert "cannot open camera 3; check that it is connected" in line and "record the sweep to a video" in line
    assert not (tmp_path / "none.npz").exists()


@pytest.mark.slow
def test_vignetting_stop_when_covered(sweep, tmp_path):
    out = tmp_path / "early.npz"
    result = invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", out, "--min-samples", "5",
                    "--stop-when-covered", "--no-plots")
    assert result.exit_code == 0, result.output
    summary = _summary(tmp_path / "early")
    seen = summary["frames_used"] + summary["frames_skipped"]
    assert 20 <= seen < 100  # stopped well before the 120 frames of the sweep
    assert summary["fraction_below_min_samples"] == 0.0  # ... because every pixel had 5 samples
    assert "coverage: 100.0% of pixels have >= 5 samples" in result.stdout
    assert summary["run"]["parameters"]["stop_when_covered"] is True
    model = load_vignetting(out)
    assert isinstance(model, LUTVignetting) and model.info["frames_used"] == summary["frames_used"]
    response = CameraResponse.load(sweep["response"])
    assert np.all(vignetting_error_levels(model, sweep["truth"], response) < 0.5)


@pytest.mark.slow
def test_vignetting_smooth_sigma(sweep, tmp_path):
    """On a short sweep (40 frames, ~9 samples per pixel) a wider smoothing is closer to the true V."""
    import inspect

    from mapping.cli.vignetting import DEFAULT_SMOOTH_SIGMA
    from radiometry.vignetting_calibration import fit_vignetting_lut

    assert inspect.signature(fit_vignetting_lut).parameters["smooth_sigma"].default == DEFAULT_SMOOTH_SIGMA
    response = CameraResponse.load(sweep["response"])
    errors = {}
    for sigma in ("0", "3"):
        out = tmp_path / f"s{sigma}.npz"
        result = invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", out, "--no-plots",
                        "--max-frames", "40", "--smooth-sigma", sigma)
        assert result.exit_code == 0, result.output
        model = load_vignetting(out)
        assert model.info["smooth_sigma"] == float(sigma)  # recorded in the model file
        assert _summary(tmp_path / f"s{sigma}")["run"]["parameters"]["smooth_sigma"] == float(sigma)
        errors[sigma] = vignetting_error_levels(model, sweep["truth"], response)
    assert np.all(errors["3"] < 0.7 * errors["0"]), errors
    assert invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", tmp_path / "d.npz", "--no-plots",
                  "--max-frames", "20").exit_code == 0
    assert load_vignetting(tmp_path / "d.npz").info["smooth_sigma"] == DEFAULT_SMOOTH_SIGMA


@pytest.mark.slow
@pytest.mark.parametrize("value", ["-1", "nan"])
def test_vignetting_smooth_sigma_out_of_range(sweep, tmp_path, value):
    result = invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", tmp_path / "v.npz", "--smooth-sigma",
                    value)
    if value == "nan":  # issue 31: not a number at all, said so
        assert one_line_error(result) == ("radiomap: error: --smooth-sigma nan is not a finite number; pass a value in "
                                          "the sensible range 0..50 px (0 disables the smoothing, 2-3 suits thin "
                                          "sweeps)")
    else:
        assert one_line_error(result) == (f"radiomap: error: --smooth-sigma {float(value):g} px is outside the "
                                          "sensible range 0..50 px (0 disables the smoothing, 2-3 suits thin sweeps); "
                                          "pass a value in that range")
    assert not (tmp_path / "v.npz").exists()


@pytest.mark.slow
def test_vignetting_smooth_sigma_is_for_the_lut(sweep, tmp_path):
    result = invoke("vignetting", sweep["rgb"], "-r", sweep["response"], "-o", tmp_path / "v.npz", "--model", "poly",
                    "--smooth-sigma", "2")
    assert result.exit_code == 2, result.output
    error = [line for line in result.output.splitlines() if line.startswith("Error: ")]
    assert len(error) == 1 and error[0].startswith("Error: Invalid value for --smooth-sigma: applies to --model lut "
                                                   "only, got --model poly; drop --smooth-sigma or use --model lut")
    assert not (tmp_path / "v.npz").exists()


@pytest.mark.slow
def test_vignetting_reports_its_error_budget_and_plots_the_stderr(sweep, tmp_path):
    out = tmp_path / "vig.npz"
    result = invoke("vignetting", sweep["rgb"], "--response", sweep["response"], "-o", out, "--min-samples", "10")
    assert result.exit_code == 0, result.output
    assert "expected error, levels of a flat field at 200 (R/G/B):" in result.stdout
    for part in ("noise (were there >= 10 samples everywhere):", "coverage (pixels with < 10 samples or none):",
                 "normalisation", "response (propagated",
                 "total:"):
        assert part in result.stdout, part
    assert cv2.imread(str(tmp_path / "vig_stderr.png")) is not None
    import json

    summary = json.loads((tmp_path / "vig_summary.json").read_text())
    budget = summary["error_budget"]
    assert budget["min_samples"] == 10 and len(budget["total"]) == 3
    model = load_vignetting(out)
    assert model.stderr is not None and model.info["error_budget"] == budget
    # the budget's total is the size of the error against the truth (simulated sweep; measured within 2x)
    measured = vignetting_error_levels(model, sweep["truth"], CameraResponse.load(sweep["response"]))
    assert np.all(np.array(budget["total"]) < 3.0 * measured + 0.05) and np.all(np.array(budget["total"]) > 0.02)


@pytest.mark.slow
def test_correct_writes_the_relative_stderr_on_request(sweep, model_file, tmp_path):
    frame = sorted(sweep["rgb"].iterdir())[0]
    target = tmp_path / "se" / "stderr.npy"
    result = invoke("correct", frame, "-r", sweep["response"], "--vignetting", model_file, "-o", tmp_path / "out",
                    "--stderr", target)
    assert result.exit_code == 0, result.output
    assert "relative standard error of the corrected irradiance" in result.stdout
    se = np.load(target)
    model = load_vignetting(model_file)
    assert se.dtype == np.float32 and se.shape == (H, W, 3)
    np.testing.assert_array_equal(se, model.stderr)
    # a model without one: a one-line error before anything is written
    plain = tmp_path / "plain.npz"
    LUTVignetting(model.lut).save(plain)
    result = invoke("correct", frame, "-r", sweep["response"], "--vignetting", plain, "-o", tmp_path / "out2",
                    "--stderr", tmp_path / "x.npy")
    assert result.exit_code == 2 and "carries no standard error" in result.output
    assert not (tmp_path / "out2").exists()
    result = invoke("correct", frame, "-r", sweep["response"], "--vignetting", model_file, "-o", tmp_path / "out3",
                    "--stderr", tmp_path / "x.png")
    assert result.exit_code == 2 and ".npy, .tiff or .exr" in result.output


@pytest.mark.slow
def test_the_grade_says_what_the_response_and_the_budget_say(sweep, tmp_path):
    """The summary's last line is the calibration's grade with every reason that lowered it, as the JSON records it:
    a response graded broken when it was calibrated makes the calibration broken, an assumed one (``response
    --gamma``) doubtful; a calibrated response with a budget within 0.5 levels leaves it good."""
    from radiometry.formats import load_response

    true = load_response(sweep["response"])
    broken = tmp_path / "broken.npz"
    CameraResponse(true.inverse_table, {**true.meta, "quality": {
        "grade": "broken", "summary": "quality broken: held-out prediction 40 levels RMS"}}).save(broken)
    assert invoke("response", "--gamma", "2.2", "-o", tmp_path / "g22.npz").exit_code == 0
    grades = {}
    for name, response in (("true", sweep["response"]), ("broken", broken), ("assumed", tmp_path / "g22.npz")):
        out = tmp_path / name / "vig.npz"
        result = invoke("vignetting", sweep["rgb"], "--response", response, "-o", out, "--no-plots")
        assert result.exit_code == 0, result.output
        last = result.stdout.strip().splitlines()[-1]
        facts = _summary(out.with_name("vig"))
        assert last.startswith(f"quality: {facts['quality']}"), (last, facts["quality"])
        grades[name] = (facts["quality"], last, facts["error_budget"]["total"])
        if name == "assumed":  # gamma 2.2 given, not measured: the budget cannot put a number on its error
            assert facts["error_budget"]["response_source"] == "assumed", facts["error_budget"]
            assert "response (assumed, not calibrated: its error is unknown" in result.stdout
    assert grades["broken"][0] == "broken" and "graded broken when it was calibrated" in grades["broken"][1]
    assert grades["assumed"][0] == "doubtful" and "assumed (gamma 2.2)" in grades["assumed"][1]
    total = max(grades["true"][2])
    assert (grades["true"][0] == "good") == (total <= 0.5 and "split-half" not in grades["true"][1]), grades["true"]


@pytest.mark.slow
def test_a_budget_above_half_a_level_is_not_graded_good(sweep):
    from mapping.cli.vignetting import _truth_free_lines
    from radiometry.formats import load_response
    from radiometry.vignetting_calibration import collect_vignetting

    response = load_response(sweep["response"])
    acc = collect_vignetting(str(sweep["rgb"]), response, progress=False)
    for total, grade in (([0.2, 0.3, 0.2], "good"), ([0.2, 0.8, 0.2], "doubtful")):
        facts = {"error_budget": {"total": total}}
        lines = _truth_free_lines(acc, response, "lut", {}, facts, True)
        assert facts["quality"] == grade and lines[-1].startswith(f"quality: {grade}"), lines
    assert "the error budget's total is 0.80 levels" in lines[-1]
