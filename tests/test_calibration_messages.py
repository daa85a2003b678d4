"""One-line errors of the calibration commands that the audit of 2026-11-28 found vague: each names the file and
says what it is and what to pass (files built here, in tmp_path)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.errors import CalibrationFileError
from radiometry.formats import load_response, load_vignetting
from radiometry.images import write_image
from radiometry.response import CameraResponse
from cli_helpers import error_line

U = np.linspace(0.0, 1.0, 256)


def test_a_grey_sweep_through_an_rgb_response_names_both(tmp_path):
    frames = tmp_path / "grey"
    frames.mkdir()
    for k in range(3):
        cv2.imwrite(str(frames / f"{k}.png"), np.full((24, 32), 150, np.uint8))
    rgb = CameraResponse(np.stack([U ** 2.2] * 3, axis=1) + 1e-4 * U[:, None], {"method": "test"}).save(
        tmp_path / "crf.npz")
    line = error_line(CliRunner().invoke(cli, ["vignetting", str(frames), "-r", str(rgb), "-o", str(tmp_path / "v.npz"),
                                               "--no-progress"]))
    assert f"{frames} through {rgb}" in line and "3 channels but the image has 1" in line


def test_a_run_record_or_a_vignetting_file_given_as_a_response_says_what_it_is(tmp_path):
    record = tmp_path / "crf.json"
    record.write_text(json.dumps({"command": "response", "radiomap_version": "0"}))
    with pytest.raises(CalibrationFileError, match="crf.json: a JSON file .*record of a run.*not a response"):
        load_response(record)
    for name, load, message in (("x.vgn", load_response, r"x.vgn: a vignetting file \(.vgn\), not a response"),
                                ("x.dat", load_response, "x.dat: unknown response file extension '.dat'"),
                                ("r.crf", load_vignetting, r"r.crf: a response file \(.crf\), not a vignetting model")):
        (tmp_path / name).write_bytes(b"\x00" * 64)
        with pytest.raises(CalibrationFileError, match=message):
            load(tmp_path / name)


def test_a_response_saved_under_another_suffix_still_loads(tmp_path):
    """Any other suffix is still read as radiomap's .npz when it is one (a file renamed by hand)."""
    path = CameraResponse.gamma(2.2).save(tmp_path / "r.npz").rename(tmp_path / "r.resp")
    assert load_response(path).channels == 3


def test_a_reversed_pcalib_is_said_to_decrease(tmp_path):
    path = tmp_path / "pcalib.txt"
    path.write_text(" ".join(f"{v:.6f}" for v in 255 * (1 - U) ** 0.8) + "\n")
    with pytest.raises(CalibrationFileError, match=r"the values decrease \(255 at level 0 to 0 at 255\): a reversed "
                                                   "file, or the forward response instead of its inverse"):
        load_response(path)


def test_a_three_channel_dso_vignette_names_the_conversion(tmp_path):
    path = tmp_path / "vignette.png"
    cv2.imwrite(str(path), np.full((12, 16, 3), 60000, np.uint16))
    with pytest.raises(CalibrationFileError, match="has 3 channels.*convert it to grey keeping 16 bits"):
        load_vignetting(path)


def test_channel_on_a_grey_stack_is_refused(tmp_path):
    folder = tmp_path / "grey"
    folder.mkdir()
    rng = np.random.default_rng(0)
    radiance = np.exp(rng.uniform(-4, 0, (24, 32)))
    times = [1 / 16, 1 / 4, 1.0]
    for k, t in enumerate(times):
        write_image(folder / f"e{k}.png", np.clip(255 * np.clip(radiance * t, 0, 1) ** (1 / 2.2), 0, 255)
                    .astype(np.uint8))
    (folder / "times.txt").write_text("".join(f"e{k}.png {t}\n" for k, t in enumerate(times)))
    result = CliRunner().invoke(cli, ["response", str(folder), "-o", str(tmp_path / "g.txt"), "--channel", "r",
                                      "--quality", "fast", "--no-progress"])
    assert result.exit_code == 2 and "--channel" in result.output and "are grey" in result.output, result.output
    assert not (tmp_path / "g.txt").exists()
