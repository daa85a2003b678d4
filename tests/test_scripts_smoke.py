"""Smoke tests of the scripts in ``scripts/`` on tiny inputs: they run and write finite results."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def load_script(name: str):
    spec = importlib.util.spec_from_file_location(f"radiomap_script_{name}", SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_repeatability_script(tmp_path, capsys):
    script = load_script("repeatability")
    out = tmp_path / "rep"
    assert script.main(["-o", str(out), "--sessions", "2", "--num-frames", "20", "--width", "64", "--height", "48"]) == 0
    figure = cv2.imread(str(out / "repeatability.png"))
    assert figure is not None and figure.shape[0] > 100 and figure.shape[1] > 100
    data = json.loads((out / "repeatability.json").read_text())
    assert data["parameters"]["sessions"] == 2 and data["parameters"]["num_frames"] == 20
    rows = data["rows"]
    assert [(r["model"], r["channel"]) for r in rows] == [(m, c) for m in script.MODELS for c in script.CHANNELS]
    for r in rows:
        values = [r[k] for k in ("median", "mean", "p90", "max", "vs_truth_median")]
        assert r["pairs"] == 2 and np.all(np.isfinite(values)), r
        assert 0 < r["median"] <= r["max"] < 10 and 0 < r["vs_truth_median"] < 5, r  # 8-bit levels
    for m in script.MODELS:
        errors = np.array(data["errors"][m], dtype=float)
        truth = np.array(data["truth_errors"][m], dtype=float)
        assert errors.shape == (2, 3) and truth.shape == (2, 3)
        assert np.all(np.isfinite(errors)) and np.all(errors > 0) and np.all(np.isfinite(truth))
    table = (out / "repeatability.txt").read_text()
    assert "2 simulated sessions" in table and table.count("\n") == len(rows) + 4
    assert table.strip() in capsys.readouterr().out
    assert not (out / "sessions").exists()  # the sweeps were temporary (no --keep)


@pytest.mark.slow
def test_repeatability_script_needs_two_sessions(tmp_path, capsys):
    script = load_script("repeatability")
    with pytest.raises(SystemExit) as info:
        script.main(["-o", str(tmp_path / "rep"), "--sessions", "1"])
    assert info.value.code == 2 and "--sessions must be at least 2" in capsys.readouterr().err
    assert not (tmp_path / "rep").exists()


@pytest.mark.slow
def test_response_stderr_study_script(capsys):
    """The coverage study of the response's stated standard error runs and reports shares in 0..1 per channel."""
    script = load_script("study_response_stderr")
    rows = script.study("gamma-2.2", "clean", width=96, height=72, sensitivity=True)
    assert [r["channel"] for r in rows] == ["R", "G", "B"]
    for r in rows:
        assert 0.0 <= r["within_2se"] <= r["within_2se_with_sensitivity"] <= 1.0 and r["max_error_percent"] > 0.0
    assert script.main(["--curves", "gamma-2.2", "--pipelines", "clean", "--size", "96x72"]) == 0
    assert "gamma-2.2" in capsys.readouterr().out
