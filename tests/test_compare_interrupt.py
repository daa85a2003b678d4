"""Ctrl-C during ``radiomap compare``: exit 130, one line, no traceback; the comparison stays marked unfinished."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from test_robustness import interrupt_once_started, tum_copy

REPO = Path(__file__).resolve().parents[1]
DISTINCT, REPEATS = 4, 300    # a TUM copy of 4 simulated frames, 300 times over: 1200 frames per method (~25 s)


def test_ctrl_c_during_compare_leaves_it_marked_unfinished(tmp_path):
    """SIGINT once the first method fuses frames: exit 130 and exactly 'radiomap: interrupted' on stderr; the
    comparison keeps its RUNNING marker and has no compare.json (nothing claims it finished); the interrupted
    method's folder keeps its own RUNNING marker and its metrics.json says 'interrupted' with the frames done."""
    from mapping.simulation import simulate_room

    room = simulate_room(tmp_path / "room", seed=3, n_frames=DISTINCT, width=160, height=120, progress=False)
    seq = tum_copy(room, tmp_path / "seq", list(range(DISTINCT)) * REPEATS, shared=True)
    out = tmp_path / "cmp"
    proc = subprocess.Popen([sys.executable, "-m", "mapping.cli", "compare", str(seq), "--response",
                             str(room / "truth" / "response.npz"), "--methods", "none,response", "--poses", "gt",
                             "--voxel-size", "0.04", "-o", str(out), "--no-progress"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    stdout, stderr = interrupt_once_started(proc, out / "none" / "RUNNING")  # the first method's fusion started
    assert proc.returncode == 130, stderr
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
    assert 0 < metrics["frames"]["total"] < DISTINCT * REPEATS
    poses = [line for line in (out / "none" / "trajectory.txt").read_text().splitlines() if not line.startswith("#")]
    assert len(poses) == metrics["frames"]["fused"]
    assert not (out / "none" / "mesh.ply").exists() and not (out / "response").exists()
    # a new comparison into the folder needs --force (it holds an unfinished one)
    from click.testing import CliRunner

    from mapping.cli import cli

    res = CliRunner().invoke(cli, ["compare", str(seq), "--response", str(room / "truth" / "response.npz"),
                                   "--methods", "none", "-o", str(out), "--no-progress"])
    assert res.exit_code == 1 and "already holds a comparison" in res.stderr and "--force" in res.stderr
