"""A recorded exposure list whose clock is off is caught by the images (mapping/exposure_alignment.py).

Before: ``reconstruct --exposures`` with a list shifted by a frame ran with every frame given its neighbour's
exposure, exit 0. The scene: the simulated self-calibration room (160x120), its frames rewritten with exposures
imposed on purpose (a random walk, through the true response), so that the true exposures are known exactly."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest

FRAMES = 14


@pytest.fixture(scope="module")
def lit_room(selfcal_room, tmp_path_factory):
    """``(folder, k (N, 3) the true exposures, timestamps)``: the room with a random walk of exposures imposed."""
    from mapping.datasets import open_dataset
    from radiometry.formats import load_response
    from radiometry.images import read_rgb, write_image

    out = tmp_path_factory.mktemp("align") / "room"
    shutil.copytree(selfcal_room, out)
    response = load_response(out / "truth" / "response.npz")
    truth = np.loadtxt(out / "truth" / "exposures.txt")
    base = truth[:, 1:2] * truth[:, 2:5]
    rng = np.random.default_rng(3)
    imposed = np.exp(np.clip(np.cumsum(rng.normal(0, 0.15, len(base))), -0.7, 0.7))
    dataset = open_dataset(out)
    for i, f in enumerate(dataset.frame_files):
        rgb = read_rgb(f.rgb)
        write_image(f.rgb, response.forward(response.inverse(rgb) * imposed[i], dtype=np.uint8))
    return out, base * imposed[:, None], dataset.timestamps


def _write(path, stamps, k, shift=0):
    """Rows ``(t_i, k_{i-shift})``: with shift > 0 each exposure is listed ``shift`` rows late."""
    path.write_text("".join(f"{stamps[i]:.6f} {k[i - shift, 0]:.9e} {k[i - shift, 1]:.9e} {k[i - shift, 2]:.9e}\n"
                            for i in range(len(k)) if 0 <= i - shift < len(k)))
    return path


def _check(room, path):
    from mapping.datasets import open_dataset
    from mapping.exposure_alignment import check_alignment
    from mapping.exposure_files import match_exposure_file
    from mapping.factory import as_vignetting
    from radiometry.formats import load_response

    folder = room[0]
    dataset = open_dataset(folder, frames=slice(0, FRAMES))
    response = load_response(folder / "truth" / "response.npz")
    return check_alignment(dataset, match_exposure_file(dataset, path), response,
                           as_vignetting(folder / "truth" / "vignetting.npz"))


def test_the_images_tell_the_right_alignment_from_shifted_ones(lit_room, tmp_path):
    _, k, stamps = lit_room
    good = _check(lit_room, _write(tmp_path / "k.txt", stamps, k))
    assert good.verdict == "ok" and good.pairs >= 6
    assert min(good.disagreement, key=good.disagreement.get) == 0
    for shift in (1, -1, 2):
        bad = _check(lit_room, _write(tmp_path / "k.txt", stamps, k, shift))
        assert bad.verdict == "refuse" and bad.shift == shift, (shift, bad)
        assert bad.seconds == pytest.approx(shift / 30, abs=1e-3)
        assert bad.disagreement[shift] < 0.5 * bad.disagreement[0]


def test_a_constant_list_is_not_checked_and_no_image_is_read(lit_room, tmp_path, monkeypatch):
    from mapping import exposure_alignment

    _, k, stamps = lit_room
    monkeypatch.setattr(exposure_alignment, "image_log_ratios", lambda *a, **kw: pytest.fail("images read"))
    check = _check(lit_room, _write(tmp_path / "k.txt", stamps, np.ones_like(k)))
    assert check.verdict == "constant" and "never change" in check.text()


def test_weaker_evidence_warns_in_one_line_and_clear_evidence_refuses(caplog):
    from mapping.exposure_alignment import enforce, verdict_of
    from mapping.exposure_files import ExposureFileError

    seconds = {s: s * 0.04 for s in range(-3, 4)} | {"signal": 0.08}
    weak = verdict_of({-1: 0.05, 0: 0.04, 1: 0.028, 2: 0.05}, seconds, 20)        # 0.7 of the alignment's
    assert weak.verdict == "warn" and weak.shift == 1
    with caplog.at_level(logging.WARNING):
        enforce(weak, "cam/k.txt")
    assert "cam/k.txt: the exposures are off by +1 frame(s) (+0.040 s" in caplog.text
    assert "\n" not in caplog.records[-1].getMessage()
    strong = verdict_of({-1: 0.05, 0: 0.04, 1: 0.01, 2: 0.05}, seconds, 20)
    with pytest.raises(ExposureFileError, match=r"cam/k\.txt: the exposures are off by \+1 frame.*correct the file's "
                                                r"clock offset"):
        enforce(strong, "cam/k.txt")
    # a shift that does not explain the images (disagreement above the file's own change) is not believed
    assert verdict_of({0: 0.2, 1: 0.09}, seconds | {"signal": 0.05}, 20).verdict == "ok"
    assert verdict_of({0: 0.2, 1: 0.01}, seconds, 3).verdict == "unchecked"


def _reconstruct(room, path, out, *extra):
    from click.testing import CliRunner

    from mapping.cli import cli

    folder = room[0]
    return CliRunner().invoke(cli, ["reconstruct", str(folder), "-o", str(out), "-r",
                                    str(folder / "truth" / "response.npz"), "--vignetting",
                                    str(folder / "truth" / "vignetting.npz"), "--poses", "gt", "--frames",
                                    f"3:{3 + FRAMES}", "--exposures", str(path), "--no-progress", *extra])


def test_reconstruct_refuses_a_list_one_frame_late_in_one_line_before_writing(lit_room, tmp_path):
    from cli_helpers import error_line

    _, k, stamps = lit_room
    path = _write(tmp_path / "k.txt", stamps, k, 1)
    res = _reconstruct(lit_room, path, tmp_path / "rec")
    assert res.exit_code == 1, res.output
    line = error_line(res)
    assert f"{path}: the exposures are off by +1 frame(s) (+0.033 s in the file's clock)" in line
    assert "correct the file's clock offset (or give one row per frame, in order)" in line
    assert not (tmp_path / "rec").exists()


@pytest.mark.slow
@pytest.mark.parametrize("constant", [False, True])
def test_reconstruct_takes_a_correct_or_constant_list_without_a_word(lit_room, tmp_path, constant):
    _, k, stamps = lit_room
    path = _write(tmp_path / "k.txt", stamps, np.ones_like(k) if constant else k)
    res = _reconstruct(lit_room, path, tmp_path / "rec")
    assert res.exit_code == 0, res.output
    assert "off by" not in res.output and "exposures never change" not in res.output
    doc = json.loads((tmp_path / "rec" / "exposures.json").read_text())
    check = doc["settings"]["alignment_check"]
    assert check["verdict"] == ("constant" if constant else "ok"), check
    if not constant:
        assert check["shift_rows"] == 0 and check["disagreement"]["0"] == min(check["disagreement"].values())


def test_the_longer_baseline_raises_the_verdict_one_step_and_never_more():
    from mapping.exposure_alignment import AlignmentCheck, combine

    def c(verdict, shift=0, baseline=1):
        return AlignmentCheck(verdict, 20, {0: 0.05, shift: 0.01}, shift, shift / 30, 0.1, baseline)

    assert combine({1: c("warn", 1), 4: c("refuse", 1, 4)}).verdict == "refuse"
    assert combine({1: c("warn", 1), 4: c("refuse", -2, 4)}).verdict == "warn"      # another shift: not raised
    raised = combine({1: c("ok"), 4: c("refuse", 2, 4)})
    assert raised.verdict == "warn" and raised.shift == 2 and raised.baseline == 4 and 1 in raised.others
    assert combine({1: c("ok"), 4: c("warn", 2, 4)}).verdict == "ok"
    assert combine({1: c("refuse", 1), 4: c("ok", 0, 4)}).verdict == "refuse"


def test_a_list_the_images_do_not_show_at_all_is_warned_about(selfcal_room, lit_room, tmp_path, caplog):
    """Exposures of another recording (or another frame rate) on the room as simulated (its own auto exposure
    changes by 2-5 % a frame): no shift helps, and the file's changes are far larger than the images'; a warning,
    not a refusal (the images cannot say what the right list is)."""
    from mapping.exposure_alignment import enforce

    _, k, stamps = lit_room
    other = np.exp(np.random.default_rng(7).normal(0, 0.2, len(k)))[:, None] * np.ones(3)
    check = _check((selfcal_room,), _write(tmp_path / "k.txt", stamps, other))
    assert check.verdict == "mismatch", check
    with caplog.at_level(logging.WARNING):
        enforce(check, tmp_path / "k.txt")
    assert "k.txt: the file's exposure changes do not match the images'" in caplog.text


def test_compare_refuses_a_list_one_frame_early_before_writing(lit_room, tmp_path):
    from click.testing import CliRunner
    from cli_helpers import error_line

    from mapping.cli import cli

    folder, k, stamps = lit_room
    path = _write(tmp_path / "k.txt", stamps, k, -1)
    res = CliRunner().invoke(cli, ["compare", str(folder), "-r", str(folder / "truth" / "response.npz"), "--methods",
                                   "response+ec", "--exposures", str(path), "--poses", "gt", "--frames",
                                   f"3:{3 + FRAMES}", "-o", str(tmp_path / "cmp"), "--no-progress"])
    line = error_line(res)
    assert f"{path}: the exposures are off by -1 frame(s) (-0.033 s in the file's clock)" in line
    assert not (tmp_path / "cmp").exists()
