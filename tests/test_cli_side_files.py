"""Side files (plot, record, summaries) are never replaced without --force (audit: `response --gamma 2.2 -o crf.npz`
then `response --linear -o crf.txt` silently replaced crf.json and crf.png of the first run)."""

from __future__ import annotations

from pathlib import Path

import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry import fileio
from radiometry.errors import OutputError
from cli_helpers import error_line

REPO_SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "brackets"


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def test_a_standard_response_with_another_suffix_keeps_the_first_run_s_side_files(tmp_path):
    assert invoke("response", "--gamma", "2.2", "-o", tmp_path / "crf.npz").exit_code == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert set(before) == {"crf.npz", "crf.png", "crf.json"}
    line = error_line(invoke("response", "--linear", "-o", tmp_path / "crf.txt"))
    assert f"{tmp_path / 'crf.png'} exists" in line and "--force" in line, line
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before   # nothing replaced, no crf.txt
    assert invoke("response", "--linear", "-o", tmp_path / "crf.txt", "--force").exit_code == 0
    assert (tmp_path / "crf.txt").is_file() and (tmp_path / "crf.json").read_bytes() != before["crf.json"]


def test_a_calibration_refuses_an_existing_record_beside_its_output(tmp_path):
    (tmp_path / "crf.json").write_text("{}")    # e.g. left by `response ... -o crf.crf`
    line = error_line(invoke("response", REPO_SAMPLE, "-o", tmp_path / "crf.npz", "--quality", "none"))
    assert f"{tmp_path / 'crf.json'} exists" in line and "--force" in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["crf.json"]


def test_check_overwrite_refuses_companions_unless_forced(tmp_path):
    """The helper both response and vignetting use: the model and any companion (vignetting's names here)."""
    out = tmp_path / "vgn.png"
    sides = [tmp_path / f"vgn_{n}" for n in ("coverage.png", "summary.txt", "summary.json")]
    fileio.check_overwrite(out, *sides, force=False)
    sides[1].write_text("from the .npz run")
    with pytest.raises(OutputError, match=r"vgn_summary.txt exists .*--force"):
        fileio.check_overwrite(out, *sides, force=False)
    fileio.check_overwrite(out, *sides, force=True)


def test_vignetting_with_another_suffix_keeps_the_first_run_s_side_files(tmp_path):
    frames = tmp_path / "frames"
    frames.mkdir()
    (tmp_path / "vgn_summary.json").write_text("{}")     # left by `vignetting ... -o vgn.npz`
    line = error_line(invoke("vignetting", frames, "--response", tmp_path / "crf.npz", "-o", tmp_path / "vgn.png"))
    assert f"{tmp_path / 'vgn_summary.json'} exists" in line and "--force" in line, line
