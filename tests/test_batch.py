"""radiomap batch: many sequences, one task each, on local processes (always tested) and on Ray (tested when it
is installed): each results folder as the single command writes it, skipped when complete, a killed worker's
folder run again, one failing sequence reported without stopping the others, the summary across sequences."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mapping.batch import (COMMANDS, BatchError, read_sequence_list, run_batch, task_names, thread_environment)
from mapping.batch.worker import THREAD_VARIABLES, error_line, execute
from radiometry.fileio import TEMP_TAG

W, H = 64, 48
RADIOMAP = [sys.executable, "-c", "import sys; from mapping.cli import main; sys.exit(main())"]
requires_ray = pytest.mark.skipif(not __import__("mapping.batch").batch.ray_available(),
                                  reason="Ray is not installed (pip install 'radiomap[cluster]'): the Ray engine is "
                                         "not tested; the local-process engine is")


def _simulate(path: Path, seed: int, frames: int) -> Path:
    from mapping.simulation.sequences import simulate_room
    from radiometry.simulation import CameraSpec

    return simulate_room(path, camera=CameraSpec.preset("xtion", width=W, height=H), seed=seed, n_frames=frames,
                         progress=False)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Three short simulated rooms (the first longer: the one a test kills), their list and a response file."""
    from radiometry.response import CameraResponse

    root = tmp_path_factory.mktemp("batch")
    seqs = [_simulate(root / "seqs" / name, seed, frames) for name, seed, frames in
            (("alpha", 1, 24), ("beta", 2, 8), ("gamma", 3, 8))]
    listing = root / "seqs" / "list.txt"
    listing.write_text("# three rooms\nalpha\n\n" + "\n".join(str(s) for s in seqs[1:]) + "\n")
    crf = root / "crf.npz"
    CameraResponse.gamma().save(crf)
    return {"root": root, "seqs": seqs, "list": listing, "crf": crf}


def _options(data) -> list[str]:
    return ["--poses", "gt", "-r", str(data["crf"]), "--depth-max", "6"]


#: imported by every Python process of a batch started with :func:`_stopping_batch` (``sitecustomize``): the first
#: run to finish frame 3 writes its pid and stops itself (SIGSTOP), so the test kills a run that is certainly
#: mid-way, on any machine, without racing it
_STOP_HOOK = """
import logging, os, signal

class _StopAtFrame(logging.Handler):
    def emit(self, record):
        if not record.getMessage().startswith("frame 3 of "):
            return
        token = os.environ["RADIOMAP_TEST_STOP_TOKEN"]
        try:
            os.mkdir(token)          # the first run only
        except FileExistsError:
            return
        with open(os.path.join(token, "pid.tmp"), "w") as fh:
            fh.write(str(os.getpid()))
        os.replace(os.path.join(token, "pid.tmp"), os.path.join(token, "pid"))
        os.kill(os.getpid(), signal.SIGSTOP)

_log = logging.getLogger("mapping.pipeline")
_log.setLevel(logging.DEBUG)
_log.addHandler(_StopAtFrame())
"""


def _batch(data, out: Path, *extra: str, command: str = "reconstruct", options=None, background: bool = False,
           env=None):
    args = [*RADIOMAP, "batch", command, str(data["list"]), "-o", str(out), "--no-progress", *extra, "--",
            *(_options(data) if options is None else options)]
    if background:
        return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    return subprocess.run(args, capture_output=True, text=True, timeout=900)


def _stopping_batch(data, out: Path, tmp_path: Path, *extra: str):
    """A batch in the background whose first run to finish frame 3 stops itself (:data:`_STOP_HOOK`)."""
    hook = tmp_path / "stop_hook"
    hook.mkdir()
    (hook / "sitecustomize.py").write_text(_STOP_HOOK)
    path = os.pathsep.join(p for p in (str(hook), os.environ.get("PYTHONPATH", "")) if p)
    env = {**os.environ, "PYTHONPATH": path, "RADIOMAP_TEST_STOP_TOKEN": str(tmp_path / "stopped")}
    return _batch(data, out, *extra, background=True, env=env)


def _single(data, sequence: Path, out: Path) -> None:
    res = subprocess.run([*RADIOMAP, "reconstruct", str(sequence), "-o", str(out), "--no-progress",
                          *_options(data)], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr


def _same_results(a: Path, b: Path) -> None:
    """Two reconstruct folders of one sequence with the same options hold the same results."""
    ma, mb = (json.loads((d / "metrics.json").read_text()) for d in (a, b))
    assert ma["status"] == mb["status"] == "complete"
    assert ma["histogram"] == mb["histogram"] and ma["frames"] == mb["frames"] and ma["ate"] == mb["ate"]
    assert (a / "trajectory.txt").read_bytes() == (b / "trajectory.txt").read_bytes()
    ca, cb = (json.loads((d / "config.json").read_text()) for d in (a, b))
    for doc in (ca, cb):
        doc.pop("started")
        doc["parameters"].pop("output")
        doc["pipeline"].pop("output")
        doc.pop("argv")
    assert ca == cb
    assert sorted(p.name for p in a.iterdir()) == sorted(p.name for p in b.iterdir())


def _nothing_half_written(out: Path) -> None:
    for path in out.rglob("*"):
        assert TEMP_TAG not in path.name, path
        assert path.name not in ("RUNNING", "LOCK"), path
        if path.suffix == ".json":
            json.loads(path.read_text())


def _kill_stopped_worker(out: Path, tmp_path: Path, proc: subprocess.Popen, timeout: float = 600) -> str:
    """SIGKILL the run that stopped itself at frame 3 (:func:`_stopping_batch`): wait for its pid (the event), find
    the results folder whose LOCK it holds, check the folder is marked RUNNING, kill. Returns the folder's name."""
    pid_file = tmp_path / "stopped" / "pid"
    deadline = time.monotonic() + timeout   # only ends a hung test: the stop comes after 3 frames of a tiny run
    while not pid_file.exists():
        assert proc.poll() is None, f"the batch ended before any run reached frame 3: {proc.communicate()}"
        assert time.monotonic() < deadline, f"no run reached frame 3 in {timeout} s"
        time.sleep(0.02)
    pid = int(pid_file.read_text())
    folders = [lock.parent for lock in out.glob("*/LOCK") if json.loads(lock.read_text())["pid"] == pid]
    assert len(folders) == 1 and (folders[0] / "RUNNING").exists(), folders
    os.kill(pid, signal.SIGKILL)
    return folders[0].name


# ------------------------------------------------------------------ the sequence list and names
@pytest.mark.slow
def test_sequence_list_comments_relative_paths_and_errors(data, tmp_path):
    assert read_sequence_list(data["list"]) == data["seqs"]
    bad = tmp_path / "bad.txt"
    bad.write_text(f"{data['seqs'][0]}\nnowhere\n")
    with pytest.raises(BatchError, match=r"line 2: .*nowhere is not a folder"):
        read_sequence_list(bad)
    bad.write_text(f"{data['seqs'][0]}\n{data['seqs'][0]}/\n")
    with pytest.raises(BatchError, match="line 2: .* listed twice \\(first on line 1\\)"):
        read_sequence_list(bad)
    bad.write_text("# nothing\n\n")
    with pytest.raises(BatchError, match="lists no sequence folder"):
        read_sequence_list(bad)


def test_task_names_are_unique_folder_names():
    names = task_names([Path("/d/redkitchen/seq-01"), Path("/d/chess/seq-01"), Path("/d/chess/seq-02"),
                        Path("/d/x/logs"), Path("/a/b/c"), Path("/e/b/c")])
    assert names == ["redkitchen_seq-01", "chess_seq-01", "seq-02", "x_logs", "a_b_c", "e_b_c"]


def test_thread_environment_and_one_line_errors(monkeypatch, tmp_path):
    from radiometry.errors import DatasetError

    assert thread_environment(3) == {v: "3" for v in THREAD_VARIABLES}
    with pytest.raises(ValueError, match="threads must be a whole number >= 1, got 0"):
        thread_environment(0)
    assert error_line(DatasetError("x: no frames\nmore")) == "x: no frames"
    assert error_line(KeyError("k")) == "KeyError: 'k'"
    # a task in this process: the thread limits set (Open3D's TBB included), the failure one line, its log kept
    from mapping._open3d import o3d

    for name in THREAD_VARIABLES:
        monkeypatch.setenv(name, os.environ.get(name, "2"))
    log = tmp_path / "task.log"
    try:
        result = execute("reconstruct", {"sequence": tmp_path, "output": tmp_path / "out", "manifest": {},
                                         "settings": ""}, threads=1, log=str(log))
        assert o3d.utility.get_max_threads() == 1 and os.environ["OMP_NUM_THREADS"] == "1"
    finally:
        o3d.utility.set_max_threads(0)
    assert result["status"] == "failed" and "\n" not in result["error"] and str(tmp_path) in result["error"]
    assert "Traceback" in log.read_text()


# ------------------------------------------------------------------ the local-process engine
@pytest.mark.slow
def test_batch_reconstruct_writes_what_the_single_command_writes_then_skips(data, tmp_path):
    out = tmp_path / "out"
    res = _batch(data, out, "--engine", "processes", "--workers", "2")
    assert res.returncode == 0, res.stderr
    assert [line.split(":")[0] for line in res.stdout.splitlines() if ": complete in" in line] != []
    names = ["alpha", "beta", "gamma"]
    for name in names:
        assert COMMANDS["reconstruct"].complete(out / name)
    _single(data, data["seqs"][1], tmp_path / "alone_beta")
    _same_results(out / "beta", tmp_path / "alone_beta")
    config = json.loads((out / "beta" / "config.json").read_text())
    assert config["argv"][:5] == ["radiomap", "reconstruct", str(data["seqs"][1]), "-o", str(out / "beta")]
    # the summary across sequences
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["sequence"] for r in rows] == names and {r["status"] for r in rows} == {"complete"}
    metrics = json.loads((out / "beta" / "metrics.json").read_text())
    beta = rows[1]
    assert int(beta["frames"]) == 8 and float(beta["L1 mean"]) == pytest.approx(metrics["histogram"]["mean"], abs=1e-4)
    assert float(beta["L1 p90"]) == metrics["histogram"]["p90"] and beta["ATE cm"] == ""    # gt poses: no ATE
    index = (out / "index.html").read_text()
    assert all(f'href="{n}/summary.txt"' in index for n in names)
    assert (out / "logs" / "alpha.log").is_file()
    _nothing_half_written(out)
    # again: everything is complete, so everything is skipped and nothing is rewritten
    stamp = (out / "alpha" / "metrics.json").stat().st_mtime_ns
    res = _batch(data, out, "--engine", "processes")
    assert res.returncode == 0, res.stderr
    assert res.stdout.count("skipped, complete in") == 3
    assert (out / "alpha" / "metrics.json").stat().st_mtime_ns == stamp


@pytest.mark.slow
def test_a_failing_sequence_does_not_stop_the_others(data, tmp_path):
    broken = data["root"] / "seqs" / "broken"
    broken.mkdir(exist_ok=True)
    listing = tmp_path / "list.txt"
    listing.write_text(f"{broken}\n{data['seqs'][1]}\n")
    out = tmp_path / "out"
    res = subprocess.run([*RADIOMAP, "batch", "reconstruct", str(listing), "-o", str(out), "--engine", "processes",
                          "--workers", "1", "--no-progress", "--", *_options(data)],
                         capture_output=True, text=True, timeout=900)
    assert res.returncode == 1
    failed = [line for line in res.stderr.splitlines() if line.startswith("broken: failed: ")]
    assert len(failed) == 1 and "broken" in failed[0]
    assert "1 of 2 sequences failed (broken)" in res.stderr and "Traceback" not in res.stderr
    assert COMMANDS["reconstruct"].complete(out / "beta")
    rows = {r["sequence"]: r for r in csv.DictReader((out / "summary.csv").open())}
    assert rows["broken"]["status"] == "failed" and rows["broken"]["error"] and rows["beta"]["status"] == "complete"
    assert 'href="logs/broken.log"' in (out / "index.html").read_text()


@pytest.mark.slow
def test_a_killed_worker_leaves_running_and_the_rerun_completes_it(data, tmp_path):
    out = tmp_path / "out"
    proc = _stopping_batch(data, out, tmp_path, "--engine", "processes", "--workers", "1")
    assert _kill_stopped_worker(out, tmp_path, proc) == "alpha"                  # one worker: the first listed
    stdout, stderr = proc.communicate(timeout=900)
    assert proc.returncode == 1
    assert "alpha: failed: the worker" in stderr and "killed by SIGKILL" in stderr
    assert (out / "alpha" / "RUNNING").exists()                                    # marked: not complete
    assert json.loads((out / "alpha" / "metrics.json").read_text())["status"] == "running"
    assert COMMANDS["reconstruct"].complete(out / "beta") and COMMANDS["reconstruct"].complete(out / "gamma")
    # the rerun takes over the dead worker's lock, runs alpha again and skips the others
    res = _batch(data, out, "--engine", "processes", "--workers", "2")
    assert res.returncode == 0, res.stderr
    assert "alpha: complete in" in res.stdout and res.stdout.count("skipped, complete in") == 2
    _nothing_half_written(out)
    _single(data, data["seqs"][0], tmp_path / "alone_alpha")
    _same_results(out / "alpha", tmp_path / "alone_alpha")


@pytest.mark.slow
def test_batch_compare_and_usage_errors(data, tmp_path):
    out = tmp_path / "cmp"
    res = _batch(data, out, "--engine", "processes", command="compare",
                 options=["-r", str(data["crf"]), "--methods", "none,response", "--views", "0", "--frames", "0:4"])
    assert res.returncode == 0, res.stderr
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [(r["sequence"], r["method"]) for r in rows] == [(s, m) for s in ("alpha", "beta", "gamma")
                                                            for m in ("none", "response")]
    assert all(int(r["frames"]) == 4 for r in rows)
    assert 'href="alpha/report.html"' in (out / "index.html").read_text()
    assert json.loads((out / "beta" / "config.json").read_text())["methods_run"] == ["none", "response"]
    # the command's own usage errors, once, before anything runs
    res = _batch(data, tmp_path / "x", command="compare", options=["-r", str(data["crf"]), "--methods", "lut"])
    assert res.returncode == 2 and "--vignetting-lut" in res.stderr and not (tmp_path / "x").exists()
    res = _batch(data, tmp_path / "x", options=["-o", "elsewhere"])
    assert res.returncode == 2 and "-o OUT of batch" in res.stderr
    res = _batch(data, tmp_path / "x", options=["--force"])
    assert res.returncode == 2 and "--force of batch" in res.stderr


@pytest.mark.slow
def test_batch_self_calibrate_is_the_single_command_per_sequence(data, tmp_path):
    """A room that constrains V (160x120, 30 frames) and one that cannot (beta: 8 frames at 64x48): the first's
    folder holds what 'radiomap self-calibrate' writes alone (same V, stderr and exposures), the second fails in
    one line without stopping it, and a rerun skips the complete one."""
    import numpy as np

    from mapping.simulation.sequences import simulate_room
    from mapping.simulation.trajectory import HandheldMotion
    from radiometry.simulation import CameraSpec

    room = simulate_room(tmp_path / "seqs" / "room", camera=CameraSpec.preset("asymmetric", width=160, height=120),
                         seed=1, n_frames=30, motion=HandheldMotion(speed=3.0), progress=False)
    listing = tmp_path / "list.txt"
    listing.write_text(f"{room}\n{data['seqs'][1]}\n")
    out = tmp_path / "out"
    options = ["-r", str(room / "truth" / "response.npz"), "--poses", "gt", "--no-plots"]
    args = [*RADIOMAP, "batch", "self-calibrate", str(listing), "-o", str(out), "--engine", "processes",
            "--workers", "1", "--no-progress", "--", *options]
    res = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert res.returncode == 1 and "1 of 2 sequences failed (beta)" in res.stderr, res.stderr
    assert any(line.startswith("beta: failed: ") and "cannot constrain vignetting" in line
               for line in res.stderr.splitlines())
    assert COMMANDS["self-calibrate"].complete(out / "room") and not COMMANDS["self-calibrate"].complete(out / "beta")
    alone = tmp_path / "alone"
    single = subprocess.run([*RADIOMAP, "self-calibrate", str(room), "-o", str(alone), *options],
                            capture_output=True, text=True, timeout=600)
    assert single.returncode == 0, single.stderr
    a, b = (np.load(d / "vignetting.npz") for d in (out / "room", alone))
    assert np.array_equal(a["lut"], b["lut"]) and np.array_equal(a["stderr"], b["stderr"])
    assert (out / "room" / "exposures.txt").read_text() == (alone / "exposures.txt").read_text()
    rows = {r["sequence"]: r for r in csv.DictReader((out / "summary.csv").open())}
    doc = json.loads((out / "room" / "self_calibration.json").read_text())
    assert rows["room"]["status"] == "complete" and int(rows["room"]["frames"]) == 30
    assert int(rows["room"]["sightings"]) == doc["sampling"]["sightings"] and rows["beta"]["status"] == "failed"
    assert 'href="room/summary.txt"' in (out / "index.html").read_text()
    res = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert "room: skipped, complete in" in res.stdout


def test_a_command_batch_does_not_run_is_named_in_one_line(data, tmp_path):
    names = ", ".join(COMMANDS)
    for wrong in ("demo", "reconstuct"):   # a command batch does not run; a typo
        res = _batch(data, tmp_path / "x", command=wrong, options=[])
        assert res.returncode == 1 and not (tmp_path / "x").exists()
        assert res.stderr.strip() == f"radiomap: error: radiomap batch runs {names}, not {wrong!r}"


def test_run_batch_checks_its_arguments(tmp_path):
    with pytest.raises(ValueError, match="engine must be one of auto, ray, processes"):
        run_batch([], tmp_path, engine="spark")
    with pytest.raises(ValueError, match="workers must be a whole number >= 1"):
        run_batch([], tmp_path, workers=0, engine="processes")
    with pytest.raises(BatchError, match="--address joins a Ray cluster"):
        run_batch([], tmp_path, engine="processes", address="auto")


# ------------------------------------------------------------------ Ray
@requires_ray
def test_ray_engine_same_results_and_a_killed_worker_rerun(data, tmp_path):
    out = tmp_path / "ray"
    proc = _stopping_batch(data, out, tmp_path, "--engine", "ray", "--workers", "1")
    assert _kill_stopped_worker(out, tmp_path, proc) == "alpha"
    stdout, stderr = proc.communicate(timeout=900)
    assert proc.returncode == 1 and "alpha: failed: the Ray worker died" in stderr
    assert (out / "alpha" / "RUNNING").exists()
    res = _batch(data, out, "--engine", "ray", "--workers", "2")
    assert res.returncode == 0, res.stderr
    assert "alpha: complete in" in res.stdout and res.stdout.count("skipped, complete in") == 2
    _nothing_half_written(out)
    for name, sequence in zip(("alpha", "beta"), data["seqs"]):
        _single(data, sequence, tmp_path / f"alone_{name}")
        _same_results(out / name, tmp_path / f"alone_{name}")
