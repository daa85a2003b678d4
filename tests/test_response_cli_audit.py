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


def test_tied_levels_under_the_default_method_name_the_times_not_the_default_method(tmp_path):
    """Two exposures listed at one time: the default method (auto -> loglog) ties levels; the advice must not be to
    fit with the default method, which was used, but to check the exposure times."""
    from response_curves import gamma_curve, render_brackets, scene

    true_times = np.array([1 / 1000, 1 / 250, 1 / 62.5, 1 / 15.6, 1 / 3.9])   # the auditor's times, 4x apart
    listed = [1 / 1000, 1 / 1000, 1 / 62.5, 1 / 15.6, 1 / 3.9]                # the second one listed at the first's
    folder = bracket(tmp_path / "eq", render_brackets(gamma_curve(), scene(60, 80), true_times), listed)
    result = response(folder, "-o", tmp_path / "crf.npz")
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "crf.json").read_text())["response"]["quality"]["summary"]
    assert "the fit tied" in summary, summary
    assert "fit with the default method" not in summary and "check the exposure times" in summary
    assert summary.count("do not use this response") <= 1


def test_tied_levels_under_another_method_suggest_the_default_one(tmp_path):
    from radiometry.response import CameraResponse
    from radiometry.response.quality import assess

    images = gamma_stack(TIMES, shape=(48, 64), seed=5)
    u = np.linspace(0.0, 1.0, 256)
    for method, advice in (("engel", True), ("loglog", False)):
        curve = CameraResponse(np.stack([u ** 2.2] * 3, axis=1),
                               {"method": method, "pooled_levels": [[list(range(100, 140))]] * 3})  # 16 % tied
        summary = assess(images, TIMES, curve)["summary"]
        assert "the fit tied 16 %" in summary, summary
        assert ("fit with the default method" in summary) is advice
        assert ("check the exposure times" in summary) is not advice


def test_a_response_written_into_its_bracket_folder_does_not_break_the_next_run(tmp_path):
    """crf.png (the plot of radiomap response -o folder/crf.npz) was taken for an unlisted exposure: 'times.txt does
    not list crf.png'. The run record crf.json lists it as an output: it is not an exposure."""
    folder = bracket(tmp_path / "stack", gamma_stack(TIMES, shape=(48, 64), seed=6))
    first = response(folder, "-o", folder / "crf.npz")
    assert first.exit_code == 0, first.output
    again = response(folder, "-o", folder / "crf.npz", "--force")
    assert again.exit_code == 0, again.output
    assert json.loads((folder / "crf.json").read_text())["response"]["images_used"] == [f"e{k}.png" for k in range(4)]
    # an image no radiomap record lists is still refused as unlisted
    write_image(folder / "stray.png", np.zeros((48, 64, 3), np.uint8))
    refused = response(folder, "-o", tmp_path / "other.npz")
    assert refused.exit_code == 1 and "does not list stray.png" in refused.output
