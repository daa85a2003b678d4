"""Smoke tests of ``radiomap simulate`` on tiny sizes."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.images import read_rgb
from radiometry.simulation import CameraSpec
from conftest import shared_path

TINY = ["--width", "64", "--height", "48", "--no-progress"]


def run(*args: str):
    return CliRunner().invoke(cli, ["simulate", *args], catch_exceptions=False)


@pytest.mark.slow
def test_room(tmp_path):
    out = tmp_path / "room"
    res = run("room", "-o", str(out), "--seed", "2", "--num-frames", "3", *TINY)
    assert res.exit_code == 0, res.output
    assert "room" in res.output and "64x48" in res.output
    manifest = json.loads((out / "radiomap_sequence.json").read_text())
    assert manifest["kind"] == "room" and manifest["n_frames"] == 3 and manifest["seed"] == 2
    assert manifest["exposure"] == "auto"
    assert len(list((out / "rgb").glob("*.png"))) == 3 and len(list((out / "depth").glob("*.png"))) == 3
    for name in ("response.npz", "vignetting.npy", "exposures.txt", "camera.json", "room.json", "room_mesh.ply"):
        assert (out / "truth" / name).is_file(), name
    assert read_rgb(next((out / "rgb").glob("*.png"))).shape == (48, 64, 3)


@pytest.mark.slow
def test_room_is_deterministic_and_refuses_to_overwrite(tmp_path):
    args = ["--seed", "5", "--num-frames", "2", "--fixed-exposure", "--light-change", "0.5", *TINY]
    assert run("room", "-o", str(tmp_path / "a"), *args).exit_code == 0
    assert run("room", "-o", str(tmp_path / "b"), *args).exit_code == 0
    a = sorted((tmp_path / "a" / "rgb").glob("*.png"))
    b = sorted((tmp_path / "b" / "rgb").glob("*.png"))
    assert [p.read_bytes() for p in a] == [p.read_bytes() for p in b]
    exposures = np.loadtxt(tmp_path / "a" / "truth" / "exposures.txt")
    assert exposures[0, 1] == exposures[1, 1]
    np.testing.assert_array_equal(np.loadtxt(tmp_path / "a" / "truth" / "light_scale.txt")[:, 1], [1.0, 0.5])
    res = run("room", "-o", str(tmp_path / "a"), *args)
    assert res.exit_code == 1
    assert "not empty; pass --force" in res.output
    assert "Traceback" not in res.output
    assert run("room", "-o", str(tmp_path / "a"), *args, "--num-frames", "1", "--force").exit_code == 0
    assert len(list((tmp_path / "a" / "rgb").glob("*.png"))) == 1


@pytest.mark.slow
def test_paper_with_real_response_and_lensfun_vignetting(tmp_path):
    pcalib = shared_path("vignetting", "euroc_mt9v034_752x480", "pcalib.txt")
    db = shared_path("lensfun", "db")
    out = tmp_path / "paper"
    res = run("paper", "-o", str(out), "--num-frames", "4", "--crf", str(pcalib), "--lensfun", "EF-S 10-22",
              "--lens-focal", "10", "--lens-aperture", "4", "--lensfun-db", str(db), "--flicker", "0.05", *TINY)
    assert res.exit_code == 0, res.output
    spec = CameraSpec.load(out / "truth" / "camera.json")
    assert spec.crf["family"] == "table" and "EF-S 10-22" in spec.vignetting.source
    assert spec.vignetting.coeffs[0] == (-0.6724, 0.0578, 0.0247)
    V = np.load(out / "truth" / "vignetting.npy")
    assert 0.35 < V[0, 0, 1] < 0.5
    assert len(list((out / "truth" / "masks").glob("*.png"))) == 4
    manifest = json.loads((out / "radiomap_sequence.json").read_text())
    assert manifest["kind"] == "paper" and manifest["flicker"] == 0.05


@pytest.mark.slow
def test_brackets(tmp_path):
    out = tmp_path / "br"
    res = run("brackets", "-o", str(out), "--num-frames", "4", "--camera", "mild", "--vignetting-preset", "none",
              "--crf", "gamma", "--jpeg-quality", "90", *TINY)
    assert res.exit_code == 0, res.output
    lines = (out / "times.txt").read_text().split()
    assert lines == ["exposure_00.png", "0.001", "exposure_01.png", "0.002", "exposure_02.png", "0.004",
                     "exposure_03.png", "0.008"]
    spec = CameraSpec.load(out / "truth" / "camera.json")
    assert spec.jpeg_quality == 90 and spec.crf == {"family": "gamma", "gamma": 2.2}
    np.testing.assert_array_equal(np.load(out / "truth" / "vignetting.npy"), 1.0)


@pytest.mark.parametrize("args, message", [
    (["paper", "--flicker", "0.1", "--light-change", "0.5"], "for 'room'"),
    (["room", "--flicker", "0.1"], "--flicker is for 'paper'"),
    (["room", "--vignetting-preset", "mild", "--lensfun", "x"], "at most one of"),
    (["room", "--crf", "no-such-curve"], "neither a response family"),
    (["room", "--lens-focal", "10"], "need --lensfun"),
    (["room", "--width", "8"], "8 is not in the range"),
    (["brackets", "--exposure-time", "0.01"], "--exposure-time is for room and paper"),
    (["cube"], "'cube' is not one of"),
])
def test_bad_options_are_usage_errors(tmp_path, args, message):
    res = run(args[0], "-o", str(tmp_path / "x"), *args[1:])
    assert res.exit_code == 2
    assert message in res.output
    assert not (tmp_path / "x").exists()


def test_help_lists_kinds_and_examples():
    res = run("--help")
    assert res.exit_code == 0
    assert "{brackets|paper|room}" in res.output and "Examples:" in res.output and "--seed" in res.output


@pytest.mark.slow
def test_no_progress_bar_when_stderr_is_not_a_terminal(tmp_path):
    """Without --no-progress but with a stderr that is not a terminal (click's runner, like a pipe or a log), no
    bar is drawn; stdout holds only the summary table. (The bar on a terminal: test_progress.py.)"""
    res = CliRunner().invoke(cli, ["simulate", "room", "-o", str(tmp_path / "seq"), "--num-frames", "2",
                                   "--width", "64", "--height", "48"], catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert "simulate room" not in res.stderr and "\r" not in res.stderr and "0/2" not in res.stderr
    assert "simulate room" not in res.stdout and "0/2" not in res.stdout
    assert "64x48" in res.stdout and "64x48" not in res.stderr
