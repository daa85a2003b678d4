"""Overwrites: a results folder is locked while a run writes it, ``--force`` removes the previous run's files, a
killed run never claims to be complete, and ``correct`` never overwrites its inputs or one result with another.

Concurrency is driven by events, never by sleeps racing a process: the first run is a subprocess; the test waits
until its ``LOCK`` file exists, stops it (SIGSTOP) so that it cannot finish meanwhile, runs the second, and lets
the first go on (SIGCONT).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_robustness import REPO, error_line, reconstruct, room, run, snapshot, tum_copy  # noqa: F401 (fixture)

from mapping.export import LOCK_NAME, MANIFEST, FolderLock, ResultsFolder, _process_start, is_complete
from radiometry.errors import OutputError
from radiometry.images import write_image


def start_reconstruct(seq: Path, out: Path, *extra) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "mapping.cli", "reconstruct", str(seq), "-o", str(out), "--poses",
                             "gt", "--no-progress", *map(str, extra)], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def wait_for(condition, proc: subprocess.Popen, what: str, timeout: float = 120) -> None:
    """Wait for an event (a file appearing); fail if the process ends first."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert proc.poll() is None, f"the run ended before {what}: {proc.communicate()}"
        assert time.monotonic() < deadline, f"no {what} after {timeout} s"
        time.sleep(0.002)


def running_status(out: Path) -> bool:
    try:
        return json.loads((out / "metrics.json").read_text())["status"] == "running"
    except (OSError, ValueError, KeyError):
        return False


@pytest.fixture(scope="module")
def long_seq(room, tmp_path_factory):
    """80 frames (the room's 14 repeated): long enough that a run is still going when the test acts on it."""
    return tum_copy(room, tmp_path_factory.mktemp("long") / "seq", indices=[i % 14 for i in range(80)])


@pytest.fixture
def idle_process():
    """A live process that is not radiomap (its pid owns a lock in some tests)."""
    proc = subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"], stdin=subprocess.PIPE)
    yield proc
    proc.stdin.close()
    proc.wait(timeout=30)


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait(timeout=30)
    return proc.pid


def lock_file(folder: Path, pid: int, start: str | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    import socket

    (folder / LOCK_NAME).write_text(json.dumps({"pid": pid, "start": start, "host": socket.gethostname(),
                                                "what": "run", "started": "2026-01-01T00:00:00+0000"}))


# ==================================================================================================
# two runs into one folder
# ==================================================================================================
@pytest.mark.slow
def test_a_second_run_into_a_folder_being_written_is_refused(long_seq, tmp_path):
    out = tmp_path / "run"
    first = start_reconstruct(long_seq, out, "--voxel-size", "0.03", "--depth-max", "5")
    try:
        wait_for(lambda: (out / LOCK_NAME).is_file(), first, "its LOCK file")
        first.send_signal(signal.SIGSTOP)            # it cannot finish (or write anything) while the second runs
        assert (out / LOCK_NAME).is_file()
        owner = json.loads((out / LOCK_NAME).read_text())
        assert owner["pid"] == first.pid
        before = snapshot(out)
        line = error_line(reconstruct(long_seq, out, "--force", "--voxel-size", "0.05"), str(out),
                          f"pid {first.pid}", "wait for it to finish or choose another output folder")
        assert "in use by another radiomap run" in line
        assert snapshot(out) == before               # the second run wrote nothing
    finally:
        first.send_signal(signal.SIGCONT)
    stdout, stderr = first.communicate(timeout=600)
    assert first.returncode == 0, stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "complete" and is_complete(out) and not (out / LOCK_NAME).exists()
    config = json.loads((out / "config.json").read_text())
    assert "0.03" in json.dumps(config) and "0.05" not in json.dumps(config)   # the first run's, whole
    assert (out / "mesh.ply").is_file() and metrics["frames"]["fused"] == 80


@pytest.mark.slow
def test_a_folder_locked_by_a_live_process_refuses_compare_and_demo(idle_process, long_seq, tmp_path):
    """The same lock guards a comparison's folder and the demo's (the owner here is any live process)."""
    from mapping.demo import run_demo

    lock_file(tmp_path / "cmp", idle_process.pid, _process_start(idle_process.pid))
    error_line(run("compare", long_seq, "-r", REPO / "data_samples" / "brackets" / "ground_truth_response.npz",
                   "--methods", "none,response", "-o", tmp_path / "cmp", "--force", "--no-progress"),
               tmp_path / "cmp", f"pid {idle_process.pid}", "in use by another radiomap run")
    lock_file(tmp_path / "demo", idle_process.pid, _process_start(idle_process.pid))
    with pytest.raises(OutputError, match=f"in use by another radiomap run \\(pid {idle_process.pid}"):
        run_demo(tmp_path / "demo", quick=True, force=True, progress=False)
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == [LOCK_NAME]   # nothing else was touched


@pytest.mark.slow
def test_a_stale_lock_is_taken_over_with_a_message(room, tmp_path, caplog):
    seq = tum_copy(room, tmp_path / "seq", indices=range(3))
    out = tmp_path / "run"
    pid = dead_pid()
    lock_file(out, pid)
    result = reconstruct(seq, out)
    assert result.exit_code == 0, result.output
    assert f"taking over the lock of radiomap pid {pid}" in caplog.text + result.stderr
    assert not (out / LOCK_NAME).exists() and is_complete(out)
    # a lock whose pid was reused by another process (its start time differs) is stale too
    lock_file(out, os.getpid(), start="1")
    assert reconstruct(seq, out, "--force").exit_code == 0 and not (out / LOCK_NAME).exists()


@pytest.mark.slow
def test_the_lock_in_process(tmp_path):
    """One process may lock a folder again (a second run in one session); release removes the file."""
    first = FolderLock(tmp_path / "f")
    assert json.loads((tmp_path / "f" / LOCK_NAME).read_text())["pid"] == os.getpid()
    second = FolderLock(tmp_path / "f")
    first.release()                                   # the older object no longer owns it: the file stays
    assert (tmp_path / "f" / LOCK_NAME).is_file()
    second.release()
    assert not (tmp_path / "f" / LOCK_NAME).exists()
    with FolderLock(tmp_path / "f"):
        assert (tmp_path / "f" / LOCK_NAME).is_file()
    assert not (tmp_path / "f" / LOCK_NAME).exists()


# ==================================================================================================
# --force removes the previous run's files (and only those)
# ==================================================================================================
@pytest.mark.slow
def test_force_removes_the_previous_runs_files_and_keeps_the_users(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq", indices=range(4))
    out = tmp_path / "run"
    assert reconstruct(seq, out, "--depth-max", "5").exit_code == 0
    assert (out / "mesh.ply").is_file()
    written = json.loads((out / MANIFEST).read_text())["files"]
    assert {"mesh.ply", "metrics.json", "config.json", "trajectory.txt"} <= set(written)
    (out / "notes.txt").write_text("mine")
    manifest = json.loads((out / MANIFEST).read_text())
    (out / "extra_result.bin").write_bytes(b"x")       # a result a future version wrote, listed in the manifest
    (out / MANIFEST).write_text(json.dumps({"files": manifest["files"] + ["extra_result.bin"]}))
    result = reconstruct(seq, out, "--force", "--backend", "surfel", "--depth-max", "5")
    assert result.exit_code == 0, result.output
    names = {p.name for p in out.iterdir()}
    assert "surfels.ply" in names and "notes.txt" in names
    assert not names & {"mesh.ply", "mesh.glb", "mesh_colours.npz", "extra_result.bin"}, names
    assert (out / "notes.txt").read_text() == "mine"
    assert "notes.txt" not in json.loads((out / MANIFEST).read_text())["files"]


@pytest.mark.slow
def test_compare_force_removes_the_previous_comparisons_method_folders(room, tmp_path):
    """compare --methods none,response,lut then --methods none --force: response/ (its metrics.json "complete") and
    the stale colour_error.png stayed beside the new compare.json, one folder holding two runs; config.json and
    summary.txt were written after the lock was released and belonged to no run's file list."""
    out = tmp_path / "cmp"
    common = ["-r", room / "truth" / "response.npz", "--frames", "0:3", "--voxel-size", "0.04", "--depth-max", "5",
              "--views", "0", "-o", out, "--no-progress"]
    first = run("compare", room, "--methods", "none,response,lut", "--vignetting-lut",
                room / "truth" / "vignetting.npy", *common)
    assert first.exit_code == 0, first.output
    assert is_complete(out / "response") and (out / "colour_error.png").is_file()
    (out / "notes.txt").write_text("mine")                      # the user's files: kept
    (out / "lut" / "notes.txt").write_text("mine too")
    (out / "plots").mkdir()
    (out / "plots" / "metrics.json").write_text("{}")          # a folder no comparison wrote
    second = run("compare", room, "--methods", "none", *common, "--force")
    assert second.exit_code == 0, second.output
    assert not (out / "response").exists() and not (out / "colour_error.png").exists()
    assert sorted(p.name for p in (out / "lut").iterdir()) == ["notes.txt"]   # its results gone, the user's file kept
    assert (out / "notes.txt").read_text() == "mine" and (out / "plots" / "metrics.json").read_text() == "{}"
    assert [m["name"] for m in json.loads((out / "compare.json").read_text())["methods"]] == ["none"]
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["folders"] == ["none"]
    assert {"compare.json", "report.html", "config.json", "summary.txt"} <= set(manifest["files"])
    assert "notes.txt" not in manifest["files"] and not (out / LOCK_NAME).exists() and not (out / "RUNNING").exists()
    assert json.loads((out / "config.json").read_text())["methods_run"] == ["none"]
    assert "ranking by L1 mean (best first): none" in (out / "summary.txt").read_text()
    # a reconstruction into the comparison's folder without --force would remove the files the manifest lists
    before = snapshot(out)
    error_line(reconstruct(room, out), out, "already holds the results of a run", "pass --force")
    assert snapshot(out) == before


@pytest.mark.slow
def test_results_subfolders_are_listed_and_removed_by_the_next_force_run(tmp_path, idle_process):
    """The rule behind compare --force: a results folder made with subfolder() is listed in the MANIFEST and the
    next force run cleans it like its parent (results out, the user's files and unlisted folders stay), never while
    a live process holds its lock."""
    from mapping.compare import ComparisonFolder

    top = tmp_path / "top"
    with ResultsFolder(top) as folder:
        for name in ("custom", "kept"):
            with folder.subfolder(name) as part:
                part.write_text("summary.txt", "x")
                part.complete()
        folder.complete()
    assert json.loads((top / MANIFEST).read_text())["folders"] == ["custom", "kept"]
    with pytest.raises(OutputError, match="already holds a comparison or the results of a run; pass --force"):
        ComparisonFolder(top)                     # a comparison into a run's folder: only with force
    (top / "kept" / "mine.txt").write_text("mine")
    (top / "user").mkdir()
    (top / "user" / "summary.txt").write_text("the user's")
    lock_file(top / "custom", idle_process.pid, _process_start(idle_process.pid))
    with pytest.raises(OutputError, match=f"{top / 'custom'} is in use by another radiomap run"):
        ResultsFolder(top, force=True)
    assert (top / "custom" / "summary.txt").is_file() and not (top / LOCK_NAME).exists()
    (top / "custom" / LOCK_NAME).unlink()
    ResultsFolder(top, force=True).release()
    assert not (top / "custom").exists()
    assert sorted(p.name for p in (top / "kept").iterdir()) == ["mine.txt"]
    assert (top / "user" / "summary.txt").read_text() == "the user's"


@pytest.mark.slow
def test_a_killed_run_never_says_complete(long_seq, room, tmp_path):
    """SIGKILL of a --force run over a finished one (issue 31): the previous run stands byte for byte (the new run
    writes into a staging folder inside OUT, published only when complete); a killed run on an empty folder never
    says complete (RUNNING stays); the next run takes the stale lock over and removes the killed run's staging."""
    seq = tum_copy(room, tmp_path / "seq", indices=range(3))
    out = tmp_path / "run"
    assert reconstruct(seq, out).exit_code == 0 and is_complete(out)
    before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
    victim = start_reconstruct(long_seq, out, "--force", "--depth-max", "5")
    wait_for(lambda: any(running_status(d) for d in out.glob(".tmp-radiomap-*")), victim,
             "a staged metrics.json saying 'running'")
    victim.kill()
    victim.communicate(timeout=60)
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file() and p.name != LOCK_NAME} == before
    assert is_complete(out) and (out / LOCK_NAME).is_file()             # the lock left by the killed process
    error_line(reconstruct(seq, out), out, "already holds the results of a run", "pass --force")
    result = reconstruct(seq, out, "--force")
    assert result.exit_code == 0 and is_complete(out) and not (out / LOCK_NAME).exists()
    assert not list(out.glob(".tmp-radiomap-*"))
    # a first run killed mid-way: marked incomplete, never complete
    fresh = tmp_path / "fresh"
    victim = start_reconstruct(long_seq, fresh, "--depth-max", "5")
    wait_for(lambda: running_status(fresh), victim, "metrics.json saying 'running'")
    victim.kill()
    victim.communicate(timeout=60)
    assert (fresh / "RUNNING").is_file() and not is_complete(fresh)


def test_results_folder_refusals_release_the_lock(tmp_path):
    with ResultsFolder(tmp_path / "r") as folder:
        folder.complete()
    with pytest.raises(OutputError, match="already holds the results of a run"):
        ResultsFolder(tmp_path / "r")
    assert not (tmp_path / "r" / LOCK_NAME).exists()


def test_a_failed_run_counts_its_frames_and_the_next_run_is_told_it_is_unfinished(room, tmp_path):
    """A frame that cannot be read stops the run at frame 4 of 6: metrics.json says 6 frames in all, 4 processed
    (it said total 4, as if the run had 4 frames); the next run without --force hears that the folder holds an
    unfinished run (it was told the folder already holds the results of a run: it holds none)."""
    seq = tum_copy(room, tmp_path / "seq", indices=range(6))
    data = (seq / "rgb" / "00004.png").read_bytes()
    (seq / "rgb" / "00004.png").write_bytes(data[:len(data) // 2])      # truncated
    out = tmp_path / "run"
    error_line(reconstruct(seq, out, "--depth-max", "5"), "00004.png")
    frames = json.loads((out / "metrics.json").read_text())["frames"]
    assert frames["total"] == 6 and frames["processed"] == 4 and frames["fused"] + frames["skipped"] == 4, frames
    assert (out / "RUNNING").is_file() and not is_complete(out)
    line = error_line(reconstruct(seq, out), out, "holds an unfinished run (interrupted or failed", "--force",
                      "another output folder")
    assert "already holds the results" not in line
    with pytest.raises(OutputError, match="holds an unfinished run .* pass --force to replace it"):
        ResultsFolder(out)


def test_a_folder_of_the_users_files_named_like_results_is_refused_without_force(room, tmp_path):
    """No run of radiomap marked it (no metrics.json, RUNNING or MANIFEST): its mesh.ply and trajectory.txt are the
    user's; without --force nothing is deleted or replaced, and the error names a file and the fix."""
    out = tmp_path / "userdir"
    out.mkdir()
    (out / "mesh.ply").write_text("x")
    (out / "trajectory.txt").write_text("y")
    with pytest.raises(OutputError, match=r"holds mesh\.ply, which no run of radiomap wrote.*--force"):
        ResultsFolder(out)
    assert not (out / LOCK_NAME).exists()
    seq = tum_copy(room, tmp_path / "seq", indices=range(3))
    error_line(reconstruct(seq, out), "userdir holds mesh.ply", "--force", "another output folder")
    assert (out / "mesh.ply").read_text() == "x" and (out / "trajectory.txt").read_text() == "y"
    assert sorted(p.name for p in out.iterdir()) == ["mesh.ply", "trajectory.txt"]
    # the user's other files are no obstacle; --force writes over the result-named ones
    (out / "mesh.ply").unlink()
    (out / "trajectory.txt").rename(out / "notes.txt")
    with ResultsFolder(out) as folder:
        folder.complete()
    assert (out / "notes.txt").read_text() == "y"


def test_force_writes_over_the_users_files_named_like_results(tmp_path):
    out = tmp_path / "userdir"
    out.mkdir()
    (out / "mesh.ply").write_text("x")
    with ResultsFolder(out, force=True) as folder:
        folder.complete()
    assert not (out / "mesh.ply").exists()


# ==================================================================================================
# correct: never an input, never two inputs into one output
# ==================================================================================================
@pytest.fixture
def models(tmp_path):
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting

    CameraResponse.gamma(2.2).save(tmp_path / "crf.npz")
    LUTVignetting(np.full((6, 8, 3), 0.8, np.float32)).save(tmp_path / "v.npz")
    return ["-r", tmp_path / "crf.npz", "--vignetting", tmp_path / "v.npz"]


def images(folder: Path, *names: str) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        write_image(folder / name, np.full((6, 8, 3), 40 + 10 * i, np.uint8))
    return folder


def test_correct_refuses_to_overwrite_its_inputs(models, tmp_path):
    frames = images(tmp_path / "frames", "a.png", "b.png")
    before = snapshot(frames)
    for extra in ((), ("--force",)):
        error_line(run("correct", frames, *models, "-o", frames, *extra), frames / "a.png",
                   "is the input", "would overwrite the original", "choose another output folder")
        assert snapshot(frames) == before
    single = frames / "b.png"
    error_line(run("correct", single, *models, "-o", frames, "--force"), single, "is the input")
    assert snapshot(frames) == before
    # the same folder under another name (a symbolic link) is the same folder
    (tmp_path / "alias").symlink_to(frames)
    error_line(run("correct", frames, *models, "-o", tmp_path / "alias", "--force"), "is the input")
    assert snapshot(frames) == before
    # into the input folder without a collision (c.jpg -> c.png) is fine
    only_jpg = images(tmp_path / "jpg", "c.jpg")
    assert run("correct", only_jpg, *models, "-o", only_jpg).exit_code == 0
    assert sorted(p.name for p in only_jpg.iterdir()) == [".radiomap-correct.json", "c.jpg", "c.png"]


def test_correct_refuses_two_inputs_into_one_output(models, tmp_path):
    frames = images(tmp_path / "frames", "a.png", "a.jpg", "a.bmp", "b.png")
    line = error_line(run("correct", frames, *models, "-o", tmp_path / "out"), "would both be written to",
                      tmp_path / "out" / "a.png", "separate output folders")
    assert str(frames / "a.bmp") in line and str(frames / "a.jpg") in line     # the first collision, by name
    assert not (tmp_path / "out").exists()                                     # nothing written, not even the folder


@pytest.mark.slow
def test_a_simulation_folder_with_force_removes_only_an_earlier_simulation(tmp_path, caplog):
    """simulate's policy on the one results-folder mechanism (SequenceFolder): a non-empty folder is refused without
    --force; with it an earlier simulation's files (frames, lists, truth, brackets) go and the user's stay; a folder
    that holds no simulation is written into as it is, with a warning."""
    import logging

    from mapping.simulation.sequences import MANIFEST as SEQUENCE_MANIFEST, SequenceFolder

    seq = tmp_path / "seq"
    for rel in ("rgb/1.png", "truth/camera.json", "rgb.txt", "exposure_00.png", SEQUENCE_MANIFEST, "notes.txt"):
        (seq / rel).parent.mkdir(parents=True, exist_ok=True)
        (seq / rel).write_text("x")
    with pytest.raises(OutputError, match=f"^{seq} is not empty; pass --force to overwrite it or choose an empty "
                                          "folder$"):
        SequenceFolder(seq)
    assert sorted(p.name for p in seq.iterdir()) == ["exposure_00.png", "notes.txt", SEQUENCE_MANIFEST, "rgb",
                                                     "rgb.txt", "truth"]
    with SequenceFolder(seq, force=True) as folder:   # the complete earlier simulation stands until this one is out
        assert folder.path.parent == seq and folder.path.name.startswith(".tmp-radiomap-")
        assert sorted(p.name for p in seq.iterdir() if p != folder.path) == [
            LOCK_NAME, "exposure_00.png", "notes.txt", SEQUENCE_MANIFEST, "rgb", "rgb.txt", "truth"]
        assert sorted(p.name for p in folder.path.iterdir()) == ["RUNNING"]
        folder.complete()
    assert sorted(p.name for p in seq.iterdir()) == ["notes.txt"]        # no MANIFEST: the layout is fixed
    (seq / "rgb").mkdir()
    (seq / "rgb" / "mine.png").write_text("mine")
    with caplog.at_level(logging.WARNING, logger="mapping.export"):
        SequenceFolder(seq, force=True).release()
    assert "holds no earlier simulation; writing into it anyway (--force)" in caplog.text
    assert (seq / "rgb" / "mine.png").read_text() == "mine" and (seq / "RUNNING").is_file()
