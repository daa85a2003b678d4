"""``compare --force`` and ``simulate --force`` over a complete result, interrupted at any moment, leave the previous
result byte for byte or the complete new one, never neither; a completed run replaces the previous one wholly
(issue 31: both removed the previous result when the run began; ``mapping.publication.StagedResultsFolder``).
The demo's cases are in test_robustness_force_demo.py.

The child run pauses at a named function (a stand-in writes to a pipe, then waits); the test waits for that event,
not for a time, and only then sends the signal. A SIGKILL during the commit's renames is provoked at each rename in
turn (the child kills itself from inside ``os.rename``): the next run in the folder rolls it back.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import run_paused
from click.testing import CliRunner

from mapping.cli import cli

REPO = Path(__file__).resolve().parents[1]
STAGE = ".tmp-radiomap-"

#: a child that runs radiomap with TARGET ("module:attribute.path") replaced by a pause announced on the pipe FD;
#: the demo's size and response fit are made small there (the publication is what is tested)
_PAUSE_AT = r"""
import importlib, os, signal, sys, time
signal.signal(signal.SIGINT, signal.default_int_handler)   # as a terminal delivers it (see DEVELOPERS.md)
ready, target = int(sys.argv[1]), sys.argv[2]

def pause(*args, **kwargs):
    os.write(ready, b"paused")
    os.close(ready)
    while True:
        time.sleep(0.05)

import test_robustness_force_demo as small
small.shrink_demo()
module, _, path = target.partition(":")
owner = importlib.import_module(module)
*parents, name = path.split(".")
for part in parents:
    owner = getattr(owner, part)
setattr(owner, name, pause)
from mapping.cli import main
sys.exit(main(sys.argv[3:]))
"""


def paused_run(target: str, args: list, sig: int) -> subprocess.CompletedProcess:
    """``radiomap ARGS`` in a child paused at ``target`` and sent ``sig`` there (the run cannot end first)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO / "tests"), os.environ.get("PYTHONPATH", "")])}
    return run_paused(_PAUSE_AT, [target, *args], sig, env=env)


def tree(folder: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and folder (None) under ``folder``, but the lock a killed run leaves (stale: the next
    run takes it over)."""
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in sorted(folder.rglob("*"))
            if p.name != "LOCK"}


def assert_previous_kept(res: subprocess.CompletedProcess, sig: int, out: Path, before: dict) -> None:
    """The interrupted run ended as the signal says and OUT holds the previous result byte for byte (after a
    SIGKILL, beside the killed run's staging folder, which the next run removes)."""
    if sig == signal.SIGINT:
        assert res.returncode == 130, res.stderr
        assert res.stderr.strip().splitlines()[-1] == "radiomap: interrupted", res.stderr
    else:
        assert res.returncode == -signal.SIGKILL, res.stderr
    assert "Traceback" not in res.stderr
    now = tree(out)
    staged = {k for k in now if k.split(os.sep)[0].startswith(STAGE)}
    assert len({k.split(os.sep)[0] for k in staged}) == (1 if sig == signal.SIGKILL else 0), sorted(staged)[:3]
    assert {k: v for k, v in now.items() if k not in staged} == before        # byte for byte, no folder added


def cli_ok(*args) -> None:
    res = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)
    assert res.exit_code == 0, res.output


def no_leftovers(out: Path) -> None:
    """No staging folder or lock, no RUNNING marker in OUT, and no published file names a staging folder."""
    names = [p.name for p in out.rglob("*")]
    assert not [n for n in names if STAGE in n or n == "LOCK"] and not (out / "RUNNING").exists(), names
    for p in out.rglob("*"):
        if p.is_file() and p.suffix in (".json", ".txt", ".csv", ".html"):
            assert STAGE not in p.read_text(errors="replace"), p


# ==================================================================================================
# simulate --force
# ==================================================================================================
def _simulate(out: Path, *extra) -> list:
    return ["simulate", "room", "-o", out, "--width", "64", "--height", "48", "--no-progress", *extra]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory) -> Path:
    """A complete simulated room of 6 frames, with the user's notes beside it."""
    out = tmp_path_factory.mktemp("sim") / "seq"
    cli_ok(*_simulate(out, "-n", "6", "--seed", "1"))
    (out / "notes.txt").write_text("mine\n")
    return out


@pytest.mark.slow
@pytest.mark.parametrize("moment", ["mapping.simulation.sequences:write_image",            # the first frame
                                    "mapping.simulation.sequences:SequenceFolder.complete"],  # all written
                         ids=["early", "late"])
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_simulate_force_interrupted_keeps_the_previous_sequence(sequence, tmp_path, moment, sig):
    out = tmp_path / "seq"
    shutil.copytree(sequence, out)
    before = tree(out)
    res = paused_run(moment, _simulate(out, "-n", "4", "--seed", "2", "--force"), sig)
    assert_previous_kept(res, sig, out, before)


@pytest.mark.slow
def test_simulate_force_replaces_the_previous_sequence_wholly(sequence, tmp_path):
    """Fewer frames than before: none of the old frames is left; the user's notes stay; a killed run's staging
    folder is removed by the next run."""
    out = tmp_path / "seq"
    shutil.copytree(sequence, out)
    res = paused_run("mapping.simulation.sequences:SequenceFolder.complete",
                     _simulate(out, "-n", "3", "--seed", "2", "--force"), signal.SIGKILL)
    assert res.returncode == -signal.SIGKILL
    cli_ok(*_simulate(out, "-n", "4", "--seed", "2", "--force"))
    fresh = tmp_path / "fresh"
    cli_ok(*_simulate(fresh, "-n", "4", "--seed", "2"))
    no_leftovers(out)
    assert (out / "notes.txt").read_text() == "mine\n"
    assert {k: v for k, v in tree(out).items() if k != "notes.txt"} == tree(fresh)   # the new sequence, only it


# ==================================================================================================
# compare --force
# ==================================================================================================
@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("room") / "room"
    cli_ok(*_simulate(out, "-n", "5", "--seed", "3"))
    return out


def _compare(room: Path, out: Path, methods: str, *extra) -> list:
    return ["compare", room, "-r", room / "truth" / "response.npz", "--methods", methods, "-o", out, "--views", "0",
            "--voxel-size", "0.04", "--no-progress", *extra]


@pytest.fixture(scope="module")
def comparison(room, tmp_path_factory) -> Path:
    """A complete comparison of two methods, with the user's notes beside it and in a method folder."""
    out = tmp_path_factory.mktemp("cmp") / "cmp"
    cli_ok(*_compare(room, out, "none,response"))
    (out / "notes.txt").write_text("mine\n")
    (out / "none" / "mine.txt").write_text("mine too\n")
    return out


@pytest.mark.slow
@pytest.mark.parametrize("moment", ["mapping.pipeline:reconstruct",                       # the first method's run
                                    "mapping.compare.results:ComparisonFolder.complete"],  # all written
                         ids=["early", "late"])
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_compare_force_interrupted_keeps_the_previous_comparison(room, comparison, tmp_path, moment, sig):
    out = tmp_path / "cmp"
    shutil.copytree(comparison, out)
    before = tree(out)
    res = paused_run(moment, _compare(room, out, "response", "--force"), sig)
    assert_previous_kept(res, sig, out, before)


@pytest.mark.slow
def test_compare_force_replaces_the_previous_comparison_wholly(room, comparison, tmp_path):
    """One method instead of two: the old method folder goes but for the user's file in it, the new comparison's
    files are exactly a fresh comparison's (but its run-dependent bytes); the user's notes stay."""
    import json

    out = tmp_path / "cmp"
    shutil.copytree(comparison, out)
    res = CliRunner().invoke(cli, [str(a) for a in _compare(room, out, "response", "--force")],
                             catch_exceptions=False)
    assert res.exit_code == 0, res.output
    assert f"report: {out / 'report.html'}" in res.output
    fresh = tmp_path / "fresh"
    cli_ok(*_compare(room, fresh, "response"))
    no_leftovers(out)
    names = {k for k, v in tree(out).items()}
    assert names - {"notes.txt", "none", os.path.join("none", "mine.txt")} == set(tree(fresh))
    assert sorted(p.name for p in (out / "none").iterdir()) == ["mine.txt"]      # the user's file, kept
    assert json.loads((out / "compare.json").read_text())["ranking_l1_mean"] == ["response"]
    listed = json.loads((out / ".radiomap-files.json").read_text())
    assert listed["folders"] == ["response"] and "compare.json" in listed["files"]


# ==================================================================================================
# a SIGKILL during the commit's renames: rolled back by the next run
# ==================================================================================================
_KILL_AT_RENAME = r"""
import os, signal, sys
from pathlib import Path
from mapping.compare import ComparisonFolder
out, kill_at = Path(sys.argv[1]), int(sys.argv[2])
with ComparisonFolder(out, force=True) as top:
    (top.path / "compare.csv").write_text("new\n")
    (top.path / "compare.json").write_text('{"new": true}')
    with top.subfolder("response") as method:
        (method.path / "metrics.json").write_text('{"status": "complete", "new": true}')
    calls = [0]
    rename, replace = os.rename, os.replace

    def counting(move):
        def call(*args, **kwargs):
            calls[0] += 1
            if calls[0] == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
            return move(*args, **kwargs)
        return call
    os.rename, os.replace = counting(rename), counting(replace)
    top.complete()
    os.rename, os.replace = rename, replace
print(calls[0])
"""


def _fake_comparison(out: Path) -> None:
    """A complete comparison made by the folder classes (no fusion): files, two method folders, the user's notes."""
    from mapping.compare import ComparisonFolder

    with ComparisonFolder(out) as top:
        for name in ("compare.csv", "report.html", "compare.json"):
            (top.path / name).write_text(f"old {name}\n")
        for method in ("none", "lut"):
            with top.subfolder(method) as sub:
                (sub.path / "metrics.json").write_text('{"status": "complete"}')
                (sub.path / "mesh.ply").write_text("old mesh\n")
        top.complete()
    (out / "notes.txt").write_text("mine\n")
    (out / "lut" / "mine.txt").write_text("mine too\n")


@pytest.mark.slow
def test_a_sigkill_at_any_rename_of_the_commit_is_rolled_back(tmp_path):
    """The commit moves the old method folders away, the new one in and the files over, compare.json last; a
    SIGKILL at each of those renames in turn leaves a journal that the next run in OUT rolls back: the previous
    comparison byte for byte. Without a kill the new comparison stands alone (the user's files kept)."""
    from mapping.compare import ComparisonFolder

    env = {**os.environ, "PYTHONPATH": str(REPO)}
    probe = tmp_path / "probe"
    _fake_comparison(probe)
    done = subprocess.run([sys.executable, "-c", _KILL_AT_RENAME, str(probe), "0"], capture_output=True, text=True,
                          cwd=REPO, env=env)
    assert done.returncode == 0, done.stderr
    renames = int(done.stdout.split()[-1])
    assert renames >= 6, renames        # journal-free renames (atomic writes) and the commit's
    assert sorted(p.name for p in probe.iterdir()) == [".radiomap-files.json", "compare.csv", "compare.json", "lut",
                                                       "notes.txt", "response"], sorted(probe.iterdir())
    assert sorted(p.name for p in (probe / "lut").iterdir()) == ["mine.txt"]
    assert (probe / "compare.json").read_text() == '{"new": true}' and not (probe / "report.html").exists()
    killed_in_commit = 0
    for k in range(1, renames + 1):
        out = tmp_path / f"k{k}"
        _fake_comparison(out)
        before = tree(out)
        res = subprocess.run([sys.executable, "-c", _KILL_AT_RENAME, str(out), str(k)], capture_output=True,
                             text=True, cwd=REPO, env=env)
        assert res.returncode == -signal.SIGKILL, (k, res.stderr)
        journal = list(out.glob(f"{STAGE}*/.radiomap-journal.json"))
        killed_in_commit += bool(journal)
        ComparisonFolder(out, force=True).release()     # the next run: rolls back, removes the staging folder
        assert tree(out) == before, k
    assert killed_in_commit >= 5, killed_in_commit     # 2 folders moved out, 1 in, a file retired, 2 replaced
