"""Edge cases of a run's frames and options that used to end with exit 0 and no word: a one-frame map (L1 nan,
ATE "-"), a --frames range past the sequence's end, a vignetting model no compared method uses."""

from __future__ import annotations

import json

import numpy as np
from test_robustness import error_line, reconstruct, room, run, tum_copy  # noqa: F401 (fixture)


def test_a_one_frame_map_says_why_it_has_no_l1_and_no_ate(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq", indices=range(3))          # with ground truth: ATE is asked for
    out = tmp_path / "one"
    res = run("reconstruct", seq, "-o", out, "--frames", "2:3", "--poses", "icp", "--depth-max", "5",
              "--no-progress")
    assert res.exit_code == 0, res.output
    summary = (out / "summary.txt").read_text()
    for text in (res.output, summary):
        assert "note: no L1: 1 frame fused (L1 compares each frame with the map the frames before it made" in text
        assert "note: no ATE: 1 pose(s) in the trajectory; the alignment to the ground truth needs 3" in text
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"]["fused"] == 1 and metrics["ate"] is None
    # two frames: L1 is measured, the ATE still not (and says so)
    res = run("reconstruct", seq, "-o", tmp_path / "two", "--frames", "0:2", "--poses", "icp", "--depth-max", "5",
              "--no-progress")
    assert res.exit_code == 0 and "note: no L1" not in res.output and "note: no ATE: 2 pose(s)" in res.output


def test_a_frame_range_past_the_end_is_cut_with_a_warning(room, tmp_path, caplog):
    seq = tum_copy(room, tmp_path / "seq", indices=range(3))
    out = tmp_path / "run"
    res = reconstruct(seq, out, "--frames", "0:5000", "--depth-max", "5")
    assert res.exit_code == 0, res.output
    assert "--frames 0:5000 reaches past the sequence's 3 frames; cut to 0:3" in caplog.text
    assert json.loads((out / "metrics.json").read_text())["frames"]["total"] == 3
    caplog.clear()
    res = reconstruct(seq, tmp_path / "inside", "--frames", "0:3", "--depth-max", "5")
    assert res.exit_code == 0 and "reaches past" not in caplog.text


def test_compare_refuses_a_vignetting_model_no_listed_method_uses(room, tmp_path):
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting

    CameraResponse.gamma(2.2).save(tmp_path / "crf.npz")
    LUTVignetting(np.full((6, 8, 3), 0.8, np.float32)).save(tmp_path / "v.npz")
    out = tmp_path / "cmp"
    res = run("compare", room, "-r", tmp_path / "crf.npz", "--vignetting-self", tmp_path / "v.npz", "--methods", "none",
              "-o", out, "--no-progress")
    assert res.exit_code == 2 and "--vignetting-self" in res.output, res.output
    assert "applies to the self methods (self, self+ec) only and the methods compared (none) include neither; drop " \
           "--vignetting-self or add self to --methods" in " ".join(res.output.split())
    assert not out.exists()
