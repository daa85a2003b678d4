"""Image names in a bracket times file (audit 2026-11-28): names with spaces could not be written in any form (the
error blamed the number), and a name typed in Unicode's decomposed form (NFD, as macOS spells it) did not match the
same name composed (NFC) on disk, with both printing the same."""

from __future__ import annotations

import unicodedata

import cv2
import numpy as np
import pytest

from radiometry.errors import DatasetError
from radiometry.response.fit import load_brackets, read_times_file

TIMES = [0.001, 0.004, 0.016]


def _stack(folder, names):
    folder.mkdir()
    rng = np.random.default_rng(0)
    radiance = rng.uniform(0.02, 1.0, (24, 32, 3))
    for name, t in zip(names, TIMES):
        img = np.clip(255 * np.clip(radiance * t / 0.016, 0, 1) ** (1 / 2.2), 0, 255).astype(np.uint8)
        assert cv2.imwrite(str(folder / name), img)
    return folder


@pytest.mark.parametrize("line", ['"exp 0.png" 0.001', "'exp 0.png' 1/1000", "exp 0.png\t0.001", "exp 0.png\t0.001\t1000"])
def test_a_name_with_spaces_is_read_quoted_or_tab_separated(tmp_path, line):
    times = tmp_path / "times.txt"
    times.write_text(f"# name seconds\n{line}\nb.png 0.004\n", encoding="utf-8")
    assert read_times_file(times) == [("exp 0.png", 0.001), ("b.png", 0.004)]


def test_an_unquoted_name_with_spaces_is_told_to_quote_it(tmp_path):
    times = tmp_path / "times.txt"
    times.write_text("exp 0.png 0.001\n", encoding="utf-8")
    with pytest.raises(DatasetError, match=r"times.txt:1: exposure time '0.png' is not a number of seconds; a file "
                                           r"name with spaces must be quoted"):
        read_times_file(times)
    times.write_text("exp.png fast\n", encoding="utf-8")  # no number further on: no such hint
    with pytest.raises(DatasetError) as err:
        read_times_file(times)
    assert "spaces" not in str(err.value)


def test_brackets_with_spaces_in_their_names_load(tmp_path):
    names = ["exp 0.png", "exp 1.png", "exp 2.png"]
    folder = _stack(tmp_path / "b", names)
    (folder / "times.txt").write_text("".join(f'"{n}" {t}\n' for n, t in zip(names, TIMES)), encoding="utf-8")
    images, times, got = load_brackets(folder, progress=False)
    assert got == names and np.allclose(times, TIMES) and len(images) == 3


@pytest.mark.parametrize("disk, listed", [("NFC", "NFD"), ("NFD", "NFC")])
def test_composed_and_decomposed_names_match(tmp_path, disk, listed):
    base = ["\u00e9xp_0.png", "\u00e9xp_1.png", "\u00e9xp_2.png"]
    folder = _stack(tmp_path / "b", [unicodedata.normalize(disk, n) for n in base])
    (folder / "times.txt").write_text("".join(f"{unicodedata.normalize(listed, n)} {t}\n"
                                              for n, t in zip(base, TIMES)), encoding="utf-8")
    images, times, got = load_brackets(folder, progress=False)
    assert len(images) == 3 and np.allclose(times, TIMES)
    assert got == [unicodedata.normalize("NFC", n) for n in base]
