"""``radiomap response`` on the embedded sample: outputs, summary, --force, one-line errors."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.formats import load_response
from radiometry.response import CameraResponse

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "data_samples" / "brackets"


def invoke(*args: str, quality: str = "fast"):
    """``radiomap response ARGS``, a calibration with ``--quality fast`` unless the test gives ``--quality`` or
    ``quality="full"``: the command's default figure refits the stack once per exposure and twice on half the pixels
    (~8x the fit's CPU). test_response_on_the_sample runs the default and checks the figure it prints."""
    args = [str(a) for a in args]
    calibrates = bool(args) and Path(args[0]).is_dir() and not {"--gamma", "--linear"} & set(args)
    if calibrates and quality != "full" and "--quality" not in args:
        args += ["--quality", quality]
    return CliRunner().invoke(cli, ["response", *args])


def one_line_error(result) -> str:
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    lines = [line for line in result.output.splitlines() if line.startswith("radiomap: error:")]
    assert len(lines) == 1, result.output
    return lines[0]


@pytest.fixture
def sample_copy(tmp_path):
    folder = tmp_path / "brackets"
    shutil.copytree(SAMPLE, folder)
    return folder


@pytest.mark.slow
def test_sample_is_up_to_date():
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "make_samples.py"), "--check"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr


@pytest.mark.slow
def test_response_on_the_sample(tmp_path):
    out = tmp_path / "out" / "crf.npz"
    result = invoke(SAMPLE, "-o", out, quality="full")   # the command's default quality figure
    assert result.exit_code == 0, result.output
    for word in ("method loglog (auto: the log-log fit; every exposure ratio is 4x", "channels", "images",
                 "samples", "fit RMS", "monotone", "time", "wrote"):
        assert word in result.output
    quality = CameraResponse.load(out).meta["quality"]   # the full figure: refits and split halves
    assert quality["holdout_refit"] and quality["split_half_percent"] is not None, quality
    if quality["grade"] == "good":
        assert quality["summary"] in result.output
    response = CameraResponse.load(out)
    truth = CameraResponse.load(SAMPLE / "ground_truth_response.npz")
    assert response.channels == 3 and response.meta["method"] == "loglog"
    # measured: 0.33% of the range (levels 5..250, normalised f^-1(255) = 1; Debevec 0.39 %)
    levels = np.arange(5, 251)
    assert np.abs(response.inverse_table[levels] - truth.inverse_table[levels]).max() < 0.01
    assert response.meta["prediction_rms_levels"] < 1.2  # measured 0.78 (the true response: 0.77, Debevec 0.94)
    png = out.with_suffix(".png").read_bytes()
    assert png.startswith(b"\x89PNG\r\n\x1a\n") and len(png) > 10_000
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["command"] == "response" and record["summary"]["method"] == "loglog"
    assert record["response"]["images_used"] == [f"exposure_{k}.png" for k in range(5)]


@pytest.mark.slow
def test_overwrite_needs_force(tmp_path):
    out = tmp_path / "crf.npz"
    assert invoke(SAMPLE, "-o", out, "--samples", "10").exit_code == 0
    first = out.read_bytes()
    assert CameraResponse.load(out).meta["samples_per_level"] == 10  # --samples: Debevec
    line = one_line_error(invoke(SAMPLE, "-o", out))
    assert line == f"radiomap: error: {out} exists; pass --force to overwrite it or choose another name"
    assert out.read_bytes() == first
    assert invoke(SAMPLE, "-o", out, "--force").exit_code == 0
    assert out.read_bytes() != first and CameraResponse.load(out).meta["method"] == "loglog"


@pytest.mark.slow
@pytest.mark.parametrize("suffix, method, extra, channels", [
    (".crf", "debevec", [], 3),
    (".txt", "debevec", ["--channel", "G"], 1),
    (".npz", "opencv-debevec", ["--samples", "100", "--lambda", "5"], 3),
    (".npz", "robertson", [], 3),
])
def test_formats_and_methods(tmp_path, suffix, method, extra, channels):
    out = tmp_path / f"response{suffix}"
    result = invoke(SAMPLE, "-o", out, "--method", method, *extra)
    assert result.exit_code == 0, result.output
    response = load_response(out)
    assert response.channels == channels and np.all(np.diff(response.inverse_table, axis=0) > 0)
    assert out.with_suffix(".png").is_file()


@pytest.mark.slow
def test_pcalib_of_colour_images_warns(tmp_path):
    result = invoke(SAMPLE, "-o", tmp_path / "pcalib.txt")
    assert result.exit_code == 0 and "writing the mean of R, G and B" in result.output


@pytest.mark.parametrize("times_text, match", [
    ("exposure_0.png 0.001\nexposure_1.png fast\n", r"times.txt:2: exposure time 'fast' is not a number"),
    ("exposure_0.png 0.001\nexposure_9.png 0.004\n", r"lists exposure_9.png but .* has no such image"),
    ("exposure_0.png 1000\nexposure_1.png 250\nexposure_2.png 62.5\nexposure_3.png 15.625\n"
     "exposure_4.png 3.90625\n", r"times are inverted"),
])
def test_bad_times_file_is_one_line(sample_copy, tmp_path, times_text, match):
    (sample_copy / "times.txt").write_text(times_text)
    line = one_line_error(invoke(sample_copy, "-o", tmp_path / "crf.npz"))
    assert re.search(match, line), line
    assert not (tmp_path / "crf.npz").exists()


def test_other_known_errors(tmp_path, sample_copy):
    line = one_line_error(invoke(SAMPLE, "-o", tmp_path / "crf.json"))
    assert "unknown response format '.json'" in line
    line = one_line_error(invoke(tmp_path / "missing", "-o", tmp_path / "crf.npz"))
    assert "no such folder" in line
    (sample_copy / "times.txt").unlink()
    line = one_line_error(invoke(sample_copy, "-o", tmp_path / "crf.npz"))
    assert "no times.txt or image_list.txt" in line
    (sample_copy / "exposure_2.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    line = one_line_error(invoke(sample_copy, "--times", SAMPLE / "times.txt", "-o", tmp_path / "crf.npz"))
    assert "exposure_2.png: cannot decode the image" in line


@pytest.mark.parametrize("args, message", [
    (["--method", "robertson", "--lambda", "3"], "apply to debevec, loglog (--lambda only) and opencv-debevec, not "
                                                 "robertson"),
    (["--lambda", "3"], "--lambda N with --method auto is ambiguous: give --method loglog"),
    (["--method", "opencv-debevec", "--mask-blue"], "--mask-blue needs --method debevec"),
    (["--channel", "R"], "--channel applies to a .txt"),
    (["--method", "svd"], "'svd' is not one of 'auto', 'debevec', 'engel', 'loglog', 'opencv-debevec', 'robertson'"),
    (["--method", "engel", "--lambda", "3"], "and opencv-debevec, not engel"),
    (["--method", "engel", "--samples", "30"], "and opencv-debevec, not engel"),
    (["--method", "opencv-debevec", "--lambda", "auto"], "--lambda auto (cross-validation) needs --method debevec"),
    (["--method", "loglog", "--lambda", "auto"], "--lambda auto (cross-validation) needs --method debevec"),
    (["--method", "loglog", "--samples", "30"], "--samples applies to debevec and opencv-debevec; loglog uses all"),
    (["--lambda", "abc"], "'abc' is not a valid float"),
    (["--samples", "0"], "0 is not in the range x>=1"),
])
def test_usage_errors(tmp_path, args, message):
    result = invoke(SAMPLE, "-o", tmp_path / "crf.npz", *args)
    assert result.exit_code == 2 and message in result.output


@pytest.mark.slow
def test_loglog_takes_its_prior_weight_from_lambda(tmp_path):
    out = tmp_path / "crf.npz"
    result = invoke(SAMPLE, "-o", out, "--method", "loglog", "--lambda", "0.5", "--mask-blue")
    assert result.exit_code == 0, result.output
    meta = CameraResponse.load(out).meta
    assert meta["method"] == "loglog" and meta["lambda"] == 0.5 and meta["masked"] is True
    assert "chosen_by" not in meta and np.asarray(meta["inverse_stderr"]).shape == (256, 3)
    default = tmp_path / "default.npz"
    assert invoke(SAMPLE, "-o", default, "--method", "loglog").exit_code == 0
    other = CameraResponse.load(default)
    assert other.meta["lambda"] == 0.1  # the weight reached the fit: the curves differ
    assert np.abs(other.inverse_table - CameraResponse.load(out).inverse_table).max() > 1e-4


@pytest.mark.slow
def test_mask_blue_is_reported(tmp_path):
    result = invoke(SAMPLE, "-o", tmp_path / "crf.npz", "--mask-blue")
    assert result.exit_code == 0 and "masked 0.0% of the pixels" in result.output


@pytest.mark.slow
def test_console_entry_point(tmp_path):
    out = subprocess.run([sys.executable, "-m", "mapping.cli", "response", str(SAMPLE), "-o",
                          str(tmp_path / "crf.crf")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert "method loglog" in out.stdout and (tmp_path / "crf.crf").is_file()


@pytest.mark.slow
def test_plot_response_is_axis_first(tmp_path):
    from matplotlib.colors import to_hex

    from radiometry.plots import CHANNEL_COLOURS, new_figure, plot_response, response_figure, save_figure

    fig, ax = new_figure()
    rgb = CameraResponse.load(SAMPLE / "ground_truth_response.npz")
    lines = plot_response(ax, rgb, label="truth", linestyle="--")
    assert [to_hex(line.get_color()) for line in lines] == list(CHANNEL_COLOURS[3])
    assert [line.get_label() for line in lines] == ["truth R", "truth G", "truth B"]
    assert np.array_equal(lines[2].get_ydata(), rgb.inverse_table[:, 2]) and lines[0].get_linestyle() == "--"
    gray = CameraResponse.linear(channels=1)  # f^-1(0) = 0: hidden, not -inf, on a log axis
    (line,) = plot_response(ax, gray, log=True)
    assert ax.get_yscale() == "log" and np.isnan(line.get_ydata()[0]) and line.get_ydata()[255] == 1.0
    path = save_figure(response_figure(rgb, title="sample"), tmp_path / "curves.png")
    assert path.read_bytes().startswith(b"\x89PNG")


@pytest.mark.slow
@pytest.mark.parametrize("args, name, expected", [
    (["--gamma", "2.2"], "gamma.npz", (np.arange(256) / 255.0) ** 2.2),
    (["--linear"], "linear.crf", np.arange(256) / 255.0),
    (["--gamma", "1.8"], "pcalib.txt", (np.arange(256) / 255.0) ** 1.8),
])
def test_standard_responses_are_written(tmp_path, args, name, expected):
    """`radiomap response --gamma 2.2 -o gamma.npz` (or --linear) writes the documented default response for a
    camera whose response is unknown, in any response format, with its plot and record; --force as ever."""
    out = tmp_path / name
    result = invoke(*args, "-o", out)
    assert result.exit_code == 0, result.output
    assert result.output.startswith(f"wrote {out} (")
    response = load_response(out)
    assert response.channels == (1 if name.endswith(".txt") else 3)
    np.testing.assert_allclose(response.inverse_table, np.repeat(expected[:, None], response.channels, axis=1),
                               atol=1e-6)
    assert out.with_suffix(".png").read_bytes().startswith(b"\x89PNG")
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["command"] == "response" and record["summary"]["method"] in ("gamma", "linear")
    first = out.read_bytes()
    line = one_line_error(invoke(*args, "-o", out))
    assert line == f"radiomap: error: {out} exists; pass --force to overwrite it or choose another name"
    assert out.read_bytes() == first and invoke(*args, "-o", out, "--force").exit_code == 0


@pytest.mark.parametrize("args, message", [
    ([], "give the FOLDER of bracketed images to calibrate, or --gamma G / --linear"),
    ([str(SAMPLE), "--gamma", "2.2"], "they take no FOLDER"),
    (["--gamma", "2.2", "--samples", "10"], "they take no FOLDER, --times, --lambda, --samples"),
    (["--gamma", "2.2", "--linear"], "give --gamma or --linear, not both"),
    (["--gamma", "0"], "--gamma 0 is outside the sensible range 0.2..5"),    # mapping.validation: exit 1
])
def test_standard_response_usage_errors(tmp_path, args, message):
    result = invoke(*args, "-o", tmp_path / "r.npz")
    assert result.exit_code == (1 if "sensible range" in message else 2) and message in result.output, result.output
    assert not (tmp_path / "r.npz").exists()


@pytest.mark.slow
def test_method_choices_are_the_registry():
    from mapping.cli.response import RESPONSE_METHODS
    from radiometry.response.fit import FITTERS, METHODS

    assert RESPONSE_METHODS == METHODS == FITTERS.names()


@pytest.mark.slow
def test_lambda_auto_on_the_sample(tmp_path):
    out = tmp_path / "crf.npz"
    result = invoke(SAMPLE, "-o", out, "--lambda", "AUTO")
    assert result.exit_code == 0, result.output
    response = CameraResponse.load(out)
    meta = response.meta
    assert meta["lambda_selection"] == "cross-validation" and meta["lambda"] in (0.3, 1, 3, 10, 30, 100)
    assert f"lambda {meta['lambda']:g}, chosen by cross-validation on held-out pixels" in result.output
    truth = CameraResponse.load(SAMPLE / "ground_truth_response.npz")
    levels = np.arange(5, 251)
    # measured: lambda 3, 1.06 % of the range (lambda 10: 0.39 %)
    assert np.abs(response.inverse_table[levels] - truth.inverse_table[levels]).max() < 0.02
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["parameters"]["lambda"] == "auto" and record["response"]["lambda_scores"]


@pytest.fixture
def varied_folder(tmp_path):
    """A bracket folder rendered through the kinked test curve, exposure ratios that differ (tests/response_curves)."""
    from response_curves import TIMES, kink_curve, render_brackets, scene

    from radiometry.images import write_image

    times = TIMES * 2.0 ** np.random.default_rng(5).uniform(-0.35, 0.35, TIMES.size)
    folder = tmp_path / "kink"
    folder.mkdir()
    lines = []
    for k, (t, image) in enumerate(zip(times, render_brackets(kink_curve(), scene(120, 160), times))):
        write_image(folder / f"b{k:02d}.png", image)
        lines.append(f"b{k:02d}.png {float(t)!r}")
    (folder / "times.txt").write_text("\n".join(lines) + "\n")
    return folder, kink_curve()


@pytest.mark.slow
def test_engel_method(tmp_path, varied_folder):
    folder, truth = varied_folder
    out = tmp_path / "engel.npz"
    result = invoke(folder, "-o", out, "--method", "engel", "--no-progress")
    assert result.exit_code == 0, result.output
    assert "engel" in result.output and "px" in result.output
    assert "levels constrained by data: 1..254, 1..254, 1..254 (per channel); the others are extrapolated" in \
        result.output
    response = CameraResponse.load(out)
    assert response.meta["method"] == "engel" and response.meta["extrapolated_levels"][0] == [0, 255]
    err = np.abs(response.inverse_table[5:251] - truth[5:251, None]).max()
    assert err < 0.015  # measured 0.87 % (160x120)
    assert out.with_suffix(".png").is_file()
    record = json.loads(out.with_suffix(".json").read_text())
    assert record["summary"]["method"] == "engel" and record["response"]["observed_range"] == [[1, 254]] * 3


@pytest.mark.slow
def test_engel_on_equal_ratios_warns(tmp_path):
    out = tmp_path / "engel.npz"
    result = invoke(SAMPLE, "-o", out, "--method", "engel", "--mask-blue")
    assert result.exit_code == 0, result.output
    assert CameraResponse.load(out).meta["equal_ratios"] == pytest.approx(4.0)
