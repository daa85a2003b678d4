"""Smoke tests of ``radiomap reconstruct`` on small data, and its one-line errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from click.testing import CliRunner
from conftest import shared_path

from mapping.cli import cli


def run(*args: str):
    return CliRunner().invoke(cli, ["reconstruct", *args], catch_exceptions=False)


@pytest.mark.slow
def test_redwood_ground_truth_raw(tmp_path):
    seq = shared_path("rgbd", "open3d_testdata")
    out = tmp_path / "raw"
    res = run(str(seq), "-o", str(out), "--poses", "gt", "--voxel-size", "0.02", "--no-progress")
    assert res.exit_code == 0, res.output
    assert "L1 mean" in res.output and "results in" in res.output
    for name in ("mesh.ply", "trajectory.txt", "histogram.json", "histogram.png", "metrics.json",
                 "config.json", "summary.txt", "frames.csv"):
        assert (out / name).is_file(), name
    assert not (out / "RUNNING").exists()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"]["fused"] == 5 and metrics["colour_model"]["name"] == "none"
    assert metrics["ate"] is None                         # poses taken from the ground truth
    config = json.loads((out / "config.json").read_text())
    assert config["command"] == "reconstruct" and config["parameters"]["poses"] == "gt"
    assert config["dataset"]["class"] == "RedwoodDataset" and config["dataset"]["frames"] == 5
    assert (out / "summary.txt").read_text().splitlines()[0].split()[:3] == ["frames", "fused", "skipped"]
    # the same folder again: refused without --force, accepted with it
    res = run(str(seq), "-o", str(out), "--poses", "gt", "--voxel-size", "0.02", "--no-progress")
    assert res.exit_code == 1 and "--force" in res.output and "Traceback" not in res.output
    res = run(str(seq), "-o", str(out), "--poses", "gt", "--voxel-size", "0.02", "--frames", "0:5:2", "--force",
              "--no-progress")
    assert res.exit_code == 0, res.output
    assert json.loads((out / "metrics.json").read_text())["frames"]["total"] == 3


@pytest.mark.slow
def test_timing_and_no_progress_bar_off_a_terminal(tmp_path):
    """metrics.json reports a positive, finite frame rate. Click's runner gives the command a stderr that is not a
    terminal, so no progress bar is drawn at all (the convention of radiometry.progress; the bar on a terminal,
    the bar's counting and a piped run are tested in test_progress.py): no redraw on stderr, only the summary on
    stdout."""
    seq = shared_path("rgbd", "open3d_testdata")
    res = run(str(seq), "-o", str(tmp_path / "bar"), "--poses", "gt", "--voxel-size", "0.03")
    assert res.exit_code == 0, res.output
    assert "\r" not in res.stderr and "frame/s" not in res.stderr and "reconstruct" not in res.stderr, res.stderr
    assert "L1 mean" in res.stdout and "\r" not in res.stdout
    timing = json.loads((tmp_path / "bar" / "metrics.json").read_text())["timing"]
    fps = timing["frames_per_second"]
    assert isinstance(fps, float) and math.isfinite(fps) and fps > 0
    assert fps == pytest.approx(5 / timing["seconds"], rel=1e-9)    # the 5 frames over the run's time


@pytest.mark.slow
def test_simulated_room_corrected_with_icp(tmp_path):
    from mapping.simulation import sample_sequence

    seq = sample_sequence("room")
    out = tmp_path / "corrected"
    res = run(str(seq), "-o", str(out), "--response", str(seq / "truth" / "response.npz"),
              "--vignetting", str(seq / "truth" / "vignetting.npy"), "--frames", "0:12", "--voxel-size", "0.02",
              "--depth-max", "4", "--formats", "ply,npz", "--no-progress")
    assert res.exit_code == 0, res.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"]["fused"] == 12 and metrics["ate"]["rmse"] < 0.02
    # (exposure compensation, on by default with --response, may add "+exposure")
    assert metrics["colour_model"]["name"].startswith("response+vignetting")
    data = np.load(out / "mesh_colours.npz")
    assert data["colours"].dtype == np.float32 and data["colours"].max() < 5.0     # irradiance, not levels


def test_errors_are_one_line(tmp_path):
    seq = shared_path("rgbd", "redkitchen_7scenes_000-099")
    res = run(str(seq), "-o", str(tmp_path / "a"), "--depth-scale", "10", "--no-progress")
    assert res.exit_code == 1 and "radiomap: error:" in res.output and "--depth-scale 1000" in res.output
    assert "Traceback" not in res.output and not (tmp_path / "a").exists()      # nothing written
    empty = tmp_path / "empty"
    empty.mkdir()
    res = run(str(empty), "-o", str(tmp_path / "b"), "--no-progress")
    assert res.exit_code == 1 and "unknown RGB-D layout" in res.output
    res = run(str(seq), "-o", str(tmp_path / "c"), "--vignetting", str(seq / "camera-intrinsics.txt"))
    assert res.exit_code == 2 and "--vignetting needs --response" in res.output
    res = run(str(seq), "-o", str(tmp_path / "d"), "--voxel-size", "-1")
    assert res.exit_code == 1 and "--voxel-size -1 m is outside the sensible range" in res.output
    res = run(str(seq), "-o", str(tmp_path / "e"), "--intrinsics", "585,585,900,240", "--no-progress")
    assert res.exit_code == 1 and "principal point" in res.output


def test_help_lists_examples():
    res = CliRunner().invoke(cli, ["reconstruct", "--help"])
    assert res.exit_code == 0
    for text in ("Examples:", "--poses", "--backend", "--frames", "--depth-scale", "histogram.json"):
        assert text in res.output
