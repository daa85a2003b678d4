"""Ctrl-C during ``radiomap compare``: exit 130, one line, no traceback; the comparison stays marked unfinished."""

from __future__ import annotations

import json

import pytest

from test_robustness import interrupt_at_frame

FRAMES, STOP = 6, 3    # a 6-frame simulated room; the first method is interrupted after its frame 3


@pytest.mark.slow
def test_ctrl_c_during_compare_leaves_it_marked_unfinished(tmp_path):
    """SIGINT while the first method fuses frames (paused after its frame 3): exit 130 and exactly 'radiomap:
    interrupted' on stderr; the comparison keeps its RUNNING marker and has no compare.json (nothing claims it
    finished); the interrupted method's folder keeps its own RUNNING marker and its metrics.json says 'interrupted'
    with the 3 frames done."""
    from mapping.simulation import simulate_room

    room = simulate_room(tmp_path / "room", seed=3, n_frames=FRAMES, width=160, height=120, progress=False)
    out = tmp_path / "cmp"
    code, stdout, stderr = interrupt_at_frame(STOP, "compare", room, "--response", room / "truth" / "response.npz",
                                              "--methods", "none,response", "--poses", "gt", "--voxel-size", "0.04",
                                              "-o", out, "--no-progress")
    assert code == 130, stderr
    assert "Traceback" not in stderr and stderr.strip() == "radiomap: interrupted"
    assert "ranking" not in stdout and "report:" not in stdout
    # the comparison: still marked as running, no table, no report, no config
    assert (out / "RUNNING").is_file() and "comparison started" in (out / "RUNNING").read_text()
    for name in ("compare.json", "compare.csv", "report.html", "renders.jpg", "config.json"):
        assert not (out / name).exists(), name
    # the interrupted method: its own marker, partial metrics and trajectory, no mesh; the next never started
    assert (out / "none" / "RUNNING").is_file()
    metrics = json.loads((out / "none" / "metrics.json").read_text())
    assert metrics["status"] == "interrupted"
    assert metrics["frames"]["processed"] == STOP and metrics["frames"]["fused"] == STOP
    poses = [line for line in (out / "none" / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(poses) == STOP
    assert not (out / "none" / "mesh.ply").exists() and not (out / "response").exists()
    # a new comparison into the folder needs --force (it holds an unfinished one)
    from click.testing import CliRunner

    from mapping.cli import cli

    res = CliRunner().invoke(cli, ["compare", str(room), "--response", str(room / "truth" / "response.npz"),
                                   "--methods", "none", "-o", str(out), "--no-progress"])
    assert res.exit_code == 1 and "holds an unfinished comparison" in res.stderr and "--force" in res.stderr
