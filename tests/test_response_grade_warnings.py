"""A response graded broken or doubtful when it was calibrated is not used downstream without a word, and a sweep
whose sheet lies outside the response's declared levels is refused naming those levels, not the sweep's coverage."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.formats import load_response
from radiometry.response import CameraResponse

U = np.linspace(0.0, 1.0, 256)


def graded(tmp_path, grade: str, name: str = "crf.npz"):
    summary = (f"quality {'BROKEN' if grade == 'broken' else grade}: held-out prediction 97.34 levels RMS, 101.40x "
               "the images' noise (trusted up to 2x and 1.5 %); do not use this response: the camera moved")
    response = CameraResponse(np.stack([U ** 2.2] * 3, axis=1) + 1e-4 * U[:, None],
                              {"method": "loglog", "quality": {"grade": grade, "summary": summary}})
    return response.save(tmp_path / name)


def warnings_of(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING and "was graded" in r.getMessage()]


@pytest.mark.parametrize("grade, word", [("broken", "BROKEN"), ("doubtful", "doubtful")])
def test_loading_a_response_graded_broken_or_doubtful_warns_once_naming_the_file(tmp_path, caplog, grade, word):
    path = graded(tmp_path, grade)
    with caplog.at_level(logging.WARNING):
        load_response(path)
        load_response(path)       # a command that loads it twice still says it once
    lines = warnings_of(caplog)
    assert len(lines) == 1, lines
    assert str(path) in lines[0] and f"graded {word}" in lines[0] and "101.40x the images' noise" in lines[0]
    assert "do not use" not in lines[0] and "\n" not in lines[0]   # the sentence's start, one line


def test_a_good_response_loads_without_a_warning(tmp_path, caplog):
    path = graded(tmp_path, "good")
    with caplog.at_level(logging.WARNING):
        load_response(path)
    assert warnings_of(caplog) == []


def test_correct_through_a_broken_response_warns(tmp_path, caplog):
    path = graded(tmp_path, "broken", "st_rot.npz")
    cv2.imwrite(str(tmp_path / "in.png"), np.full((8, 10, 3), 120, np.uint8))
    np.save(tmp_path / "v.npy", np.ones((8, 10, 3), np.float32))
    with caplog.at_level(logging.WARNING):
        result = CliRunner().invoke(cli, ["correct", str(tmp_path / "in.png"), "-r", str(path), "--vignetting",
                                          str(tmp_path / "v.npy"), "-o", str(tmp_path / "out"), "--no-progress"])
    assert result.exit_code == 0, result.output
    lines = warnings_of(caplog)
    assert len(lines) == 1 and "st_rot.npz" in lines[0] and "graded BROKEN" in lines[0]


def test_vignetting_names_the_response_levels_that_exclude_the_sheet(tmp_path):
    """A response that declares levels up to 64 only (a BROKEN stack) leaves the sweep no samples: the refusal says
    so, not that the sheet was not swept over the image. The sweep's folder name holds a ';', which the refusal
    once cut the finding at (the finding and the advice are kept apart now: AdvisedCalibrationError)."""
    from mapping.simulation.sequences import simulate_paper

    out = simulate_paper(tmp_path / "paper", camera="xtion", seed=5, n_frames=12, width=48, height=36,
                         progress=False, write_depth_images=False)
    sweep = out / "sheet; take 2"
    (out / "rgb").rename(sweep)
    truth = CameraResponse.load(out / "truth" / "response.npz")
    low = CameraResponse(truth.inverse_table, {"method": "loglog", "declared_levels": [[4, 64]] * 3,
                                               "extrapolated_levels": [list(range(65, 256))] * 3})
    low.save(tmp_path / "low.npz")
    result = CliRunner().invoke(cli, ["vignetting", str(sweep), "-r", str(tmp_path / "low.npz"), "-o",
                                      str(tmp_path / "v.npz"), "--no-plots", "--no-progress"])
    assert result.exit_code == 1, result.output
    line = result.stderr.strip().splitlines()[-1]
    assert "low.npz declares levels 4..64, 4..64, 4..64 only" in line and "of the sheet's readings" in line, line
    assert f"{sweep.name}: the sheet was seen at only" in line and "of the image in" in line, line
    assert "(the rest would be guessed)" not in line, line   # the fit's own advice gave way to the cause
    assert not (tmp_path / "v.npz").exists()
    # the sweep through its own response is accepted: the levels were the cause
    assert CliRunner().invoke(cli, ["vignetting", str(sweep), "-r", str(out / "truth" / "response.npz"), "-o",
                                    str(tmp_path / "v.npz"), "--no-plots", "--no-progress",
                                    "--min-samples", "2"]).exit_code == 0
