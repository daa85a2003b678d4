"""16-bit images are reduced to 8 bits (their top 8 bits): data that uses fewer than 16 bits (12-bit sensors stored in
16-bit PNGs) is said on load, and a fit that then finds too few levels names the 16-bit input and the fix instead of
advising more exposures (audit: 'only 15 usable levels ... add exposures')."""

from __future__ import annotations

import logging

import cv2
import numpy as np
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.images import read_rgb

TIMES = [0.25, 0.5, 1.0, 2.0, 4.0]


def _write_stack(folder, scale):
    """A gamma-2.2 stack of a random scene as 16-bit PNGs: 8-bit levels times ``scale`` (16: 12-bit data)."""
    folder.mkdir()
    rng = np.random.default_rng(0)
    radiance = np.exp(rng.uniform(-4.0, 0.0, (48, 64, 3)))
    for k, t in enumerate(TIMES):
        img = np.round(255 * np.clip(radiance * t, 0, 1) ** (1 / 2.2)).astype(np.uint16) * scale
        cv2.imwrite(str(folder / f"{k}.png"), img)
    (folder / "times.txt").write_text("".join(f"{k}.png {t}\n" for k, t in enumerate(TIMES)))
    return folder


def test_twelve_bit_data_in_sixteen_bit_files_is_said_on_load(tmp_path, caplog):
    folder = _write_stack(tmp_path / "b12", 16)
    with caplog.at_level(logging.WARNING, logger="radiometry.images"):
        img = read_rgb(folder / "0.png")
    assert img.dtype == np.uint8 and img.max() <= 15
    text = caplog.text
    assert "0.png: 16-bit image whose values use 12 of the 16 bits" in text, text
    assert "save 8-bit images, or scale the data to the full 16-bit range (x16 for 12-bit data)" in text


def test_full_range_sixteen_bit_data_loads_without_a_warning(tmp_path, caplog):
    folder = _write_stack(tmp_path / "b16", 257)
    with caplog.at_level(logging.WARNING, logger="radiometry.images"):
        img = read_rgb(folder / "4.png")
    assert img.max() > 200 and "16-bit" not in caplog.text


def test_too_few_levels_in_sixteen_bit_input_names_it_and_the_fix(tmp_path):
    folder = _write_stack(tmp_path / "b12", 16)
    result = CliRunner().invoke(cli, ["response", str(folder), "-o", str(tmp_path / "crf.npz"), "--quality", "none",
                                      "--no-progress"])
    assert result.exit_code == 1, result.output
    line = [ln for ln in result.output.splitlines() if ln.startswith("radiomap: error:")][0]
    assert "usable levels" in line and "add exposures" not in line, line
    assert "is a 16-bit image whose values use 12 of the 16 bits" in line and "scale the data" in line, line


def test_the_sixteen_bit_note_replaces_only_the_advice_of_a_too_few_levels_error(tmp_path):
    """The note is placed by the error's parts, not by splitting its words: a too-few-levels error keeps its finding
    and loses its advice to add exposures; any other error keeps all of its text, the note after it."""
    from radiometry.errors import CalibrationError, TooFewLevelsError
    from radiometry.images import with_sixteen_bit_note

    folder = _write_stack(tmp_path / "b12", 16)
    paths = sorted(folder.glob("*.png"))
    few = TooFewLevelsError("channel R shows only 9 usable levels (usable 3..11)", "add more exposures, reworded")
    assert str(few) == "channel R shows only 9 usable levels (usable 3..11); add more exposures, reworded"
    line = with_sixteen_bit_note(few, paths)
    assert line.startswith("channel R shows only 9 usable levels (usable 3..11); the input ") and "reworded" not in line
    assert "scale the data" in line, line
    other = CalibrationError("the fit did not converge")
    assert with_sixteen_bit_note(other, paths).startswith("the fit did not converge; the input ")
    assert with_sixteen_bit_note(few, [tmp_path / "none.png"]) == str(few)  # no 16-bit input: as it was
