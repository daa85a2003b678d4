"""What the summaries say about where a run's inputs came from: a pose file named by its absolute path, a given
--depth-scale named as given, and compare on real data without true radiance (it may have ground-truth poses)."""

from __future__ import annotations

import json
import os

from test_robustness import room, run, tum_copy  # noqa: F401 (fixture)


def test_the_settings_line_names_the_pose_file_absolute_and_a_given_depth_scale(room, tmp_path, monkeypatch):
    seq = tum_copy(room, tmp_path / "seq", indices=range(3))
    monkeypatch.chdir(tmp_path)
    res = run("reconstruct", "seq", "-o", "out", "--poses", "seq/groundtruth.txt", "--depth-scale", "5000",
              "--depth-max", "5", "--no-progress")
    assert res.exit_code == 0, res.output
    settings = next(line for line in res.output.splitlines() if line.startswith("settings: "))
    absolute = os.path.abspath(seq / "groundtruth.txt")
    assert f"poses {absolute} (given)" in settings, settings
    assert json.loads((tmp_path / "out" / "config.json").read_text())["parameters"]["poses"] == absolute
    assert "depth scale 5000 per metre (given)" in settings, settings
    # not given: the TUM default is not named as given, but with the reason it was chosen (mapping/datasets/tum.py)
    res = run("reconstruct", "seq", "-o", "out2", "--poses", "gt", "--depth-max", "5", "--no-progress")
    settings = next(line for line in res.output.splitlines() if line.startswith("settings: "))
    assert res.exit_code == 0 and "depth scale 5000 per metre (TUM's" in settings, settings
    assert "per metre (given)" not in settings, settings


def test_compare_on_a_real_sequence_says_no_true_radiance_not_no_ground_truth(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq", indices=range(3))          # ground-truth poses, no true radiance
    res = run("compare", seq, "-r", room / "truth" / "response.npz", "--methods", "none,response", "--poses", "gt",
              "--voxel-size", "0.04", "--depth-max", "5", "--views", "0", "-o", tmp_path / "cmp", "--no-progress")
    assert res.exit_code == 0, res.output
    assert "(no true radiance: colour error not measured; only a simulated sequence knows it)" in res.output
    assert "no ground truth" not in res.output
