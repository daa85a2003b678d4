"""A calibration and its companions are published together or not at all (radiometry.fileio.publish_set).

``radiomap response --force`` over an existing set (crf.npz, crf.png, crf.json) is killed with SIGKILL at random
moments and at every file-system call of its publication, fails with a full disk and is interrupted with Ctrl-C at
every such call: afterwards the folder holds either the old set byte for byte or the complete new one, never a
mix, and the next run leaves no temporary behind. The same for ``radiomap vignetting`` (model, figures, summaries).

The kills run in children forked by one helper process (a "zygote" that imported radiomap once), so that 20 kills
cost seconds, not a minute of start-ups; every child runs ``radiomap response`` exactly as the command line does.
"""

from __future__ import annotations

import errno
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from test_robustness import BRACKETS, REPO, error_line, no_temporaries, run

from radiometry import fileio

SET = ("crf.npz", "crf.png", "crf.json")
OTHER = {"debevec": "robertson", "robertson": "debevec"}

# a helper process: imports radiomap once, then forks one child per request that runs the command line; a request
# may ask the child to kill itself (SIGKILL) at its k-th os.replace / os.link / os.fsync call
ZYGOTE = r"""
import json, os, signal, sys
from mapping.cli import main
import mapping.cli.response, radiometry.response.fit, radiometry.plots, scipy.sparse.linalg  # noqa: F401
import matplotlib.pyplot  # noqa: F401
print("ready", flush=True)
for line in sys.stdin:
    request = json.loads(line)
    pid = os.fork()
    if pid == 0:
        log = os.open(request["log"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
        os.dup2(log, 1)
        os.dup2(log, 2)
        if request.get("plots"):              # the plot from a file: a run takes 0.1 s instead of 1 s
            import mapping.cli.response as response_cli
            from radiometry.fileio import atomic_write_bytes
            plots = request["plots"]
            def cached_plot(path, response, title):
                atomic_write_bytes(path, open(plots[title.split(":")[0]], "rb").read())
            response_cli._plot = cached_plot
        k = request.get("kill_at")
        if k:
            calls = [0]
            def dying(real):
                def call(*args, **kwargs):
                    calls[0] += 1
                    if calls[0] == k:
                        os.kill(os.getpid(), signal.SIGKILL)
                    return real(*args, **kwargs)
                return call
            for name in ("replace", "link", "fsync"):
                setattr(os, name, dying(getattr(os, name)))
        os._exit(main(request["argv"]))
    print(json.dumps({"pid": pid}), flush=True)
    sys.stdin.readline()                      # the test has sent its kill (or not): reap the child now
    _, status = os.waitpid(pid, 0)
    print(json.dumps({"killed": os.WIFSIGNALED(status), "code": os.WEXITSTATUS(status) if os.WIFEXITED(status)
                      else None}), flush=True)
"""


class Zygote:
    def __init__(self) -> None:
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MPLBACKEND="Agg")
        self.proc = subprocess.Popen([sys.executable, "-c", ZYGOTE], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, cwd=REPO, env=env)
        assert self.proc.stdout.readline().strip() == "ready"

    def start(self, argv: list[str], log: Path, kill_at: int | None = None, plots: dict | None = None) -> int:
        self.proc.stdin.write(json.dumps({"argv": argv, "log": str(log), "kill_at": kill_at, "plots": plots}) + "\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())["pid"]

    def reap(self) -> dict:
        self.proc.stdin.write("\n")
        self.proc.stdin.flush()
        return json.loads(self.proc.stdout.readline())

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


@pytest.fixture(scope="module")
def zygote():
    z = Zygote()
    yield z
    z.close()


def running(pid: int) -> bool:
    """The child runs (it is not yet a zombie waiting for the helper to reap it)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def wait_for_staging(out: Path, pid: int, strays: set[str]) -> float:
    """Wait until the child's publication begins (a new staging folder appears) or the child ends; the time."""
    while running(pid) and not any(p.name.startswith(".tmp-radiomap-") and p.name not in strays
                                   for p in out.iterdir()):
        time.sleep(0.0005)
    return time.monotonic()


def argv(out: Path, method: str) -> list[str]:
    # --quality fast: what is tested is the publication of the set; the full figure (a refit per exposure and two half
    # fits) would multiply each run's CPU by ~8 (tests/test_cli_response.py::test_response_on_the_sample runs it)
    return ["response", str(BRACKETS), "-o", str(out / "crf.npz"), "--method", method, "--force", "--quality", "fast"]


def snapshot(out: Path) -> dict[str, bytes]:
    return {name: (out / name).read_bytes() for name in SET if (out / name).exists()}


def method_of(out: Path) -> str:
    return json.loads((out / "crf.json").read_text())["summary"]["method"]


@pytest.fixture(scope="module")
def references(tmp_path_factory):
    """The complete set of each method (the plot is byte-identical between runs; the model's table too)."""
    refs = {}
    for method in ("debevec", "robertson"):
        out = tmp_path_factory.mktemp(method)
        assert run(*argv(out, method)).exit_code == 0
        refs[method] = {"png": (out / "crf.png").read_bytes(), "png_path": out / "crf.png",
                        "table": np.load(out / "crf.npz")["inverse_table"], "files": snapshot(out)}
    return refs


def is_complete_set(out: Path, method: str, references) -> bool:
    if sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) != sorted(SET):
        return False
    ref = references[method]
    record = json.loads((out / "crf.json").read_text())
    return ((out / "crf.png").read_bytes() == ref["png"]
            and np.array_equal(np.load(out / "crf.npz")["inverse_table"], ref["table"])
            and record["summary"]["method"] == method and record["outputs"]["response"] == str(out / "crf.npz"))


def check_outcome(out: Path, before: dict[str, bytes], method: str, references) -> str:
    """After a kill: the old set byte for byte, or the complete new one; a kill during the renames leaves a
    journal that the next run rolls back (checked here through the same function the next run calls)."""
    outcome = ""
    if any((p / ".radiomap-journal.json").is_file() for p in out.iterdir() if p.is_dir()):
        fileio.remove_strays(out)
        outcome = "rolled back "
    if snapshot(out) == before and sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == sorted(SET):
        return outcome + "old"
    assert is_complete_set(out, method, references), (f"a mix of two sets after the kill: "
                                                      f"{sorted(p.name for p in out.iterdir())}")
    return outcome + "new"


def cached_plots(monkeypatch, references) -> None:
    """The response plot from the reference runs' files instead of matplotlib (1 s of the 1.1 s of a run): the
    loops below run the command 20-40 times; what they test, the publication of crf.png, is unchanged."""
    import mapping.cli.response as response_cli

    monkeypatch.setattr(response_cli, "_plot", lambda path, response, title: fileio.atomic_write_bytes(
        path, references[title.split(":")[0]]["png"]))


def seed_folder(out: Path, references, method: str = "robertson") -> None:
    out.mkdir(exist_ok=True)
    for name, data in references[method]["files"].items():
        (out / name).write_bytes(data)


# ==================================================================================================
# SIGKILL
# ==================================================================================================
@pytest.mark.slow
def test_sigkill_at_random_moments_leaves_the_old_or_the_new_set(zygote, references, tmp_path):
    """20 kills of ``radiomap response --force`` over an existing set: 10 at a random moment of the whole run,
    10 at a random moment of its publication (after its staging folder appeared). Every outcome is checked;
    a final run leaves no temporary of the killed ones behind. (The plot comes from a file, see cached_plots.)"""
    out = tmp_path / "calib"
    seed_folder(out, references)
    plots = {m: str(r["png_path"]) for m, r in references.items()}
    t0 = time.monotonic()
    pid = zygote.start(argv(out, "debevec"), tmp_path / "log", plots=plots)
    published = wait_for_staging(out, pid, set())
    while running(pid):
        time.sleep(0.001)
    end = time.monotonic()
    assert zygote.reap() == {"killed": False, "code": 0}
    whole, publication = end - t0, end - published   # how long a run takes, and its publication
    rng = random.Random(13)
    outcomes = []
    for i in range(20):
        method = OTHER[method_of(out)]
        before = snapshot(out)
        strays = {p.name for p in out.iterdir() if p.name.startswith(".")}
        pid = zygote.start(argv(out, method), tmp_path / "log", plots=plots)
        if i % 2 == 0:
            time.sleep(rng.uniform(0, 1.1 * whole))
        else:  # wait for the event "publication began", then a random part of the publication's duration
            wait_for_staging(out, pid, strays)
            time.sleep(rng.uniform(0, 1.1 * publication))
        os.kill(pid, signal.SIGKILL)
        status = zygote.reap()
        outcomes.append(check_outcome(out, before, method, references) + ("" if status["killed"] else " (finished)"))
    print("outcomes:", {o: outcomes.count(o) for o in sorted(set(outcomes))})
    # the next run cleans up the strays of the killed ones (their processes are gone)
    method = OTHER[method_of(out)]
    assert zygote.start(argv(out, method), tmp_path / "log", plots=plots)
    assert zygote.reap() == {"killed": False, "code": 0}
    assert sorted(p.name for p in out.iterdir()) == sorted(SET)
    assert is_complete_set(out, method, references)


@pytest.mark.slow
def test_sigkill_at_every_call_of_the_publication(zygote, references, tmp_path):
    """The child kills itself at its k-th os.replace / os.link / os.fsync, for every k until a run completes:
    every step of writing the temporaries, backing up, journaling and renaming is interrupted once."""
    out = tmp_path / "calib"
    seed_folder(out, references)
    outcomes = []
    for k in range(1, 60):
        method = OTHER[method_of(out)]
        before = snapshot(out)
        zygote.start(argv(out, method), tmp_path / "log", kill_at=k,
                     plots={m: str(r["png_path"]) for m, r in references.items()})
        status = zygote.reap()
        outcomes.append(check_outcome(out, before, method, references))
        if not status["killed"]:
            assert status["code"] == 0 and outcomes[-1] == "new"
            break
    else:
        pytest.fail("the run never completed")
    print(f"{k - 1} kills:", outcomes)
    assert k > 10  # the publication makes at least this many of those calls (3 files, backups, journal, renames)
    assert outcomes[:-1].count("rolled back old") >= 4, outcomes   # the kills during the renames were undone
    assert sorted(p.name for p in out.iterdir()) == sorted(SET)   # the completing run removed every stray


@pytest.mark.slow
def test_strays_of_a_live_process_are_left_alone(tmp_path):
    live = tmp_path / f".crf.npz.tmp-radiomap-{os.getppid()}-abc.npz"
    dead_pid = 2 ** 22 + 12345                                     # above pid_max: no such process
    dead = tmp_path / f".crf.npz.tmp-radiomap-{dead_pid}-abc.npz"
    stage = tmp_path / f".tmp-radiomap-{dead_pid}-xyz"
    user = tmp_path / ".hidden-but-mine"
    for p in (live, dead, user):
        p.write_text("x")
    stage.mkdir()
    (stage / "crf.npz").write_text("half")
    assert sorted(fileio.remove_strays(tmp_path)) == sorted([dead.name, stage.name])
    assert live.exists() and user.exists() and not dead.exists() and not stage.exists()


# ==================================================================================================
# disk full and Ctrl-C during the publication, in-process, at every call
# ==================================================================================================
def _fault_at(monkeypatch, k: int, exc: BaseException) -> list[int]:
    calls = [0]

    def failing(real):
        def call(*args, **kwargs):
            calls[0] += 1
            if calls[0] == k:
                raise exc
            return real(*args, **kwargs)
        return call

    for name in ("replace", "link", "fsync"):
        monkeypatch.setattr(os, name, failing(getattr(os, name)))
    return calls


@pytest.mark.slow
@pytest.mark.parametrize("fault", ["disk full", "ctrl-c"])
def test_response_fault_at_every_call_keeps_the_old_set(references, tmp_path, fault, monkeypatch):
    cached_plots(monkeypatch, references)
    out = tmp_path / "calib"
    seed_folder(out, references)
    before = snapshot(out)
    for k in range(1, 60):
        exc = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)) if fault == "disk full" else KeyboardInterrupt()
        with pytest.MonkeyPatch.context() as mp:
            calls = _fault_at(mp, k, exc)
            result = run(*argv(out, "debevec"))
        if calls[0] < k:                       # no call left to fail: the run completed
            assert result.exit_code == 0 and is_complete_set(out, "debevec", references)
            break
        if fault == "disk full":
            error_line(result, "the disk is full", "free some space", str(out))
        else:
            assert result.exit_code == 130 and "radiomap: interrupted" in result.stderr
        assert snapshot(out) == before, f"the old set changed at call {k}"
        assert sorted(p.name for p in out.iterdir()) == sorted(SET), f"left behind at call {k}"
        no_temporaries(out)
    else:
        pytest.fail("the run never completed")
    assert k > 10


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    from mapping.simulation.sequences import simulate_paper

    return simulate_paper(tmp_path_factory.mktemp("sweep") / "paper", camera="xtion", seed=3, n_frames=40,
                          width=64, height=48, progress=False, write_depth_images=False)


@pytest.mark.slow
def test_vignetting_disk_full_at_every_call_keeps_the_old_set(sweep, tmp_path, monkeypatch):
    """Model, coverage map and both summaries: a full disk at any call of their publication leaves the
    previous calibration's files byte for byte."""
    out = tmp_path / "calib"
    args = ["vignetting", sweep / "rgb", "-r", sweep / "truth" / "response.npz", "-o", out / "v.npz",
            "--no-progress", "--no-drift-correction", "--no-plots"]
    assert run(*args, "--model", "poly").exit_code == 0
    coverage = (out / "v_coverage.png").read_bytes()       # the figure from a file from now on (see cached_plots)
    monkeypatch.setattr("radiometry.plots_vignetting.save_coverage_png",
                        lambda path, count, min_samples: fileio.atomic_write_bytes(path, coverage))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    assert len(before) == 4   # v.npz, v_coverage.png, v_summary.txt, v_summary.json
    for k in range(1, 80):
        with pytest.MonkeyPatch.context() as mp:
            calls = _fault_at(mp, k, OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
            result = run(*args, "--force")
        if calls[0] < k:
            assert result.exit_code == 0 and json.loads((out / "v_summary.json").read_text())["model"] == "lut"
            break
        error_line(result, "the disk is full", str(out))
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before, f"the old set changed at call {k}"
    else:
        pytest.fail("the run never completed")
    assert sorted(p.name for p in out.iterdir()) == sorted(before)
