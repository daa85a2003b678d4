"""Small refusals (audit, cosmetic): options silently ignored or errors that named the wrong cause."""

from __future__ import annotations

import shutil
from pathlib import Path

import click
import cv2
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from mapping.cli._common import FrameRange
from mapping.datasets._common import parse_intrinsics

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "brackets"


def test_a_standard_response_refuses_channel(tmp_path):
    result = CliRunner().invoke(cli, ["response", "--gamma", "2.2", "--channel", "r", "-o", str(tmp_path / "g.npz")])
    assert result.exit_code == 2 and "--channel" in result.output, result.output
    assert not (tmp_path / "g.npz").exists()


def test_a_grayscale_image_in_a_colour_stack_is_a_channel_mismatch(tmp_path):
    folder = tmp_path / "brackets"
    shutil.copytree(SAMPLE, folder)
    grey = cv2.imread(str(folder / "exposure_2.png"), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(folder / "exposure_2.png"), grey)
    result = CliRunner().invoke(cli, ["response", str(folder), "-o", str(tmp_path / "crf.npz"), "--quality", "none"])
    assert result.exit_code == 1, result.output
    assert f"{folder / 'exposure_2.png'}: grayscale (1 channel) but exposure_0.png is colour" in result.output
    assert "channel mismatch" in result.output and "same size" not in result.output


@pytest.mark.parametrize("text, count", [("500,500", 2), ("500 500 320", 3), ("1,2,3,4,5", 5)])
def test_intrinsics_with_the_wrong_count_of_numbers_says_four(tmp_path, monkeypatch, text, count):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(ValueError, match=rf"{count} numbers; give 4 numbers fx,fy,cx,cy .* or the path of an "):
        parse_intrinsics(text)
    assert parse_intrinsics("525,525,319.5,239.5")[0, 0] == 525


@pytest.mark.parametrize("text", ["-5:10", "-1::2", "-3"])
def test_frames_refuse_a_negative_start(text):
    with pytest.raises(click.BadParameter, match=r">= 0"):
        FrameRange().convert(text, None, None)
    assert FrameRange().convert("5:10", None, None) == slice(5, 10, None)
    assert FrameRange().convert("0:-1", None, None) == slice(0, -1, None)   # a negative end: all but the last
