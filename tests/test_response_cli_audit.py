"""``radiomap response`` on small stacks built here: what the audit of 2026-11-28 found it said wrongly or not at all
(a registration's blue fill, tied levels' advice, its own outputs in the bracket folder, --channel on grey)."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner
from response_curves import gamma_stack

from mapping.cli import cli
from radiometry.images import write_image

TIMES = [1 / 64, 1 / 16, 1 / 4, 1.0]


def bracket(folder, images, times=TIMES):
    folder.mkdir()
    for k, image in enumerate(images):
        write_image(folder / f"e{k}.png", image)
    (folder / "times.txt").write_text("".join(f"e{k}.png {t!r}\n" for k, t in enumerate(times)))
    return folder


def response(*args):
    return CliRunner().invoke(cli, ["response", *map(str, args), "--quality", "fast", "--no-progress"])


def test_a_pure_blue_fill_without_mask_blue_is_warned_and_not_graded_good(tmp_path):
    images = gamma_stack(TIMES, shape=(48, 64), seed=3)
    for image in images:   # a registration's fill, as memorial's: the same pure blue in every exposure
        image[:5] = (0, 0, 255)
    folder = bracket(tmp_path / "stack", images)
    result = response(folder, "-o", tmp_path / "crf.npz")
    assert result.exit_code == 0, result.output
    warned = [line for line in result.stderr.splitlines() if "pure blue" in line]
    # 5 rows and the 2 blue_fill_mask grows the fill by, of 48
    assert len(warned) == 1 and "fit with --mask-blue" in warned[0] and "14.6%" in warned[0], result.stderr
    assert json.loads((tmp_path / "crf.json").read_text())["response"]["quality"]["grade"] != "good"
    masked = response(folder, "-o", tmp_path / "masked.npz", "--mask-blue")
    assert masked.exit_code == 0 and "pure blue in some exposure" not in masked.stderr
    clean = response(bracket(tmp_path / "clean", gamma_stack(TIMES, shape=(48, 64), seed=3)), "-o", tmp_path / "c.npz")
    assert clean.exit_code == 0 and "pure blue" not in clean.stderr
