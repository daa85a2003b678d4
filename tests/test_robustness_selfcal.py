"""``self-calibrate --force`` interrupted at any stage leaves the previous self-calibration or the new one, never
neither (issue 31: SIGINT or SIGKILL early in the run used to leave neither: ``--force`` removed the previous files
when the run began).

The child run pauses at a named stage (a stand-in for that stage's function writes to a pipe, then waits); the
test waits for that event, not for a time, and only then sends the signal.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import run_paused
from test_robustness import REPO, snapshot

#: a child that runs radiomap with the function at STAGE replaced by a pause (announced on the pipe FD)
_PAUSE_AT = r"""
import os, signal, sys, time
signal.signal(signal.SIGINT, signal.default_int_handler)   # as a terminal delivers it (see DEVELOPERS.md)
ready, stage = int(sys.argv[1]), sys.argv[2]
import mapping.self_calibration as sc

def pause(*args, **kwargs):
    os.write(ready, b"paused")
    os.close(ready)
    while True:
        time.sleep(0.05)

if stage == "commit":
    sc.SelfCalibrationFolder.complete = pause
elif stage == "self_calibrate":          # the solver (imported by the run from radiometry)
    import radiometry.self_calibration as rs
    rs.self_calibrate = pause
else:
    setattr(sc, stage, pause)
from mapping.cli import main
sys.exit(main(sys.argv[3:]))
"""


def paused_run(stage: str, args: list[str], sig: int) -> subprocess.CompletedProcess:
    return run_paused(_PAUSE_AT, [stage, *args], sig)


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from mapping.simulation.sequences import simulate_room
    from mapping.simulation.trajectory import HandheldMotion
    from radiometry.simulation.camera import CameraSpec

    out = tmp_path_factory.mktemp("selfcal") / "room"
    simulate_room(out, camera=CameraSpec.preset("asymmetric", width=160, height=120), seed=1, n_frames=20,
                  width=160, height=120, motion=HandheldMotion(speed=3.0), progress=False)
    return out


def _args(room: Path, out: Path, *extra) -> list[str]:
    return ["self-calibrate", str(room), "-r", str(room / "truth" / "response.npz"), "--poses", "gt", "-o", str(out),
            "--no-progress", *extra]


def _results(folder: Path) -> dict[str, bytes]:
    """The folder's files but the lock a killed run leaves (stale: the next run takes it over)."""
    return {k: v for k, v in snapshot(folder).items() if k != "LOCK"}


@pytest.fixture(scope="module")
def previous(room, tmp_path_factory) -> tuple[Path, dict[str, bytes]]:
    """A complete self-calibration (with --no-plots, so that a new run with figures differs in its file set)."""
    from click.testing import CliRunner

    from mapping.cli import cli

    out = tmp_path_factory.mktemp("previous") / "sc"
    res = CliRunner().invoke(cli, _args(room, out, "--no-plots"), catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return out, _results(out)


@pytest.mark.slow
@pytest.mark.parametrize("stage", ["collect_observations", "self_calibrate", "commit"])
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_force_interrupted_at_any_stage_keeps_the_previous_result(room, previous, tmp_path, stage, sig):
    import shutil

    from mapping.self_calibration import self_calibration_complete

    src, files = previous
    out = tmp_path / "sc"
    shutil.copytree(src, out)
    res = paused_run(stage, _args(room, out, "--force"), sig)
    if sig == signal.SIGINT:
        assert res.returncode == 130 and res.stderr.strip().splitlines()[-1] == "radiomap: interrupted", res.stderr
        assert "Traceback" not in res.stderr
    else:
        assert res.returncode == -signal.SIGKILL
    left = _results(out)
    staged = [k for k in left if k.startswith(".tmp-radiomap")]
    assert {k: v for k, v in left.items() if k not in staged} == files       # the previous set, byte for byte
    assert self_calibration_complete(out)
    if (stage, sig) != ("commit", signal.SIGKILL):
        return
    # the next --force run cleans the killed run's staging folder and publishes the new set
    from click.testing import CliRunner

    from mapping.cli import cli

    res = CliRunner().invoke(cli, _args(room, out, "--force"), catch_exceptions=False)
    assert res.exit_code == 0, res.output
    names = sorted(_results(out))
    assert not [n for n in names if n.startswith(".tmp")], names
    assert "vignetting.png" in names and "RUNNING" not in names and self_calibration_complete(out)
    assert (out / "vignetting.npz").read_bytes() != b""


@pytest.mark.slow
def test_a_failed_force_run_keeps_the_previous_result(room, previous, tmp_path):
    """A run that fails (too few frames with a pose) after --force keeps the previous set too."""
    import shutil

    from click.testing import CliRunner

    from mapping.cli import cli

    src, files = previous
    out = tmp_path / "sc"
    shutil.copytree(src, out)
    res = CliRunner().invoke(cli, _args(room, out, "--force", "--frames", "0:2"), catch_exceptions=False)
    assert res.exit_code == 1 and "radiomap: error:" in res.output
    assert _results(out) == files


@pytest.mark.slow
def test_a_new_run_replaces_only_the_previous_runs_files(room, previous, tmp_path):
    """With --no-plots after a run with figures, the old figures go once the new set is in place; the user's
    notes stay."""
    import shutil

    from click.testing import CliRunner

    from mapping.cli import cli

    src, _files = previous
    out = tmp_path / "sc"
    shutil.copytree(src, out)
    (out / "notes.txt").write_text("mine\n")
    assert CliRunner().invoke(cli, _args(room, out, "--force")).exit_code == 0
    assert (out / "vignetting.png").is_file()
    assert CliRunner().invoke(cli, _args(room, out, "--force", "--no-plots")).exit_code == 0
    names = set(_results(out))
    assert "vignetting.png" not in names and "notes.txt" in names and "vignetting.npz" in names
