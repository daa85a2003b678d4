"""Drive the INSTALLED ``radiomap`` command over a catalogue of bad inputs and faults, as a user would, and report
each case clean or unclean (issue 31).

Every case runs ``radiomap ...`` in a subprocess with a timeout. A case is clean when:

- the exit code is the expected one (1 or 2 for a refusal, 130 for Ctrl-C, 0 for input that must be accepted,
  -9 where the case kills the run itself), never a crash (another negative code: a signal) nor a timeout;
- stderr holds no traceback, a refusal ends with exactly one error line (``radiomap: error: ...`` or click's
  ``Error: ...``) and no line of stderr is longer than 2,100 characters;
- nothing is lost: every file the case protects (inputs, a previous result) is byte for byte as before, or,
  for an interrupted ``--force`` run, the previous result or a complete new one stands, never neither;
- anything else the case checks (no output written, a message fragment).

Fixtures are made with the installed command itself (``radiomap simulate``, ``response``, ``vignetting``,
``self-calibrate``) in a work folder; the 7-Scenes kitchen is read from ``../shared/data`` when present (its cases
are skipped otherwise). Interruptions wait for an event (a lock or staging folder appearing), not for a time.

    python scripts/robustness_catalogue.py [--radiomap PATH] [--work DIR] [--timeout 300] [--out results.json]
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
KITCHEN = REPO.parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"
LINE_MAX = 2100
RADIOMAP = ["radiomap"]          # the command under test (set by main)


@dataclass
class Case:
    name: str
    kind: str
    argv: list[str]
    expect: tuple[int, ...] = (1, 2)            # acceptable exit codes
    fragments: tuple[str, ...] = ()              # must appear in the last stderr line
    protect: tuple[Path, ...] = ()               # files/folders that must stay byte for byte
    absent: tuple[Path, ...] = ()                # must not exist afterwards
    setup: Callable[[], None] | None = None
    check: Callable[[subprocess.CompletedProcess], str | None] | None = None   # None = fine, else the problem
    interrupt: tuple[Callable[[], bool], int] | None = None    # (event, signal): send the signal once event()
    limits: dict = field(default_factory=dict)   # resource limits of the child: {"as": bytes, "nofile": n}
    needs: Path | None = None                    # skipped when this path is missing


# --------------------------------------------------------------------------------------------------
# running
# --------------------------------------------------------------------------------------------------
def snapshot(path: Path) -> dict[str, bytes]:
    if path.is_file():
        return {"": path.read_bytes()}
    if not path.exists():
        return {}
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*"))
            if p.is_file() and p.name != "LOCK" and ".tmp-radiomap" not in str(p.relative_to(path))}


def _preexec(limits: dict):
    def apply():
        signal.signal(signal.SIGINT, signal.SIG_DFL)       # as a terminal delivers it (DEVELOPERS.md)
        if "as" in limits:
            resource.setrlimit(resource.RLIMIT_AS, (limits["as"], limits["as"]))
        if "nofile" in limits:
            resource.setrlimit(resource.RLIMIT_NOFILE, (limits["nofile"], limits["nofile"]))
    return apply


def run_case(radiomap: str, case: Case, timeout: float, cwd: Path) -> dict:
    if case.needs is not None and not case.needs.exists():
        return {"name": case.name, "kind": case.kind, "status": "skipped", "why": f"{case.needs} missing"}
    if case.setup is not None:
        case.setup()
    before = {str(p): snapshot(p) for p in case.protect}
    start = time.perf_counter()
    proc = subprocess.Popen([radiomap, *map(str, case.argv)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=cwd, preexec_fn=_preexec(case.limits))
    timed_out = False
    try:
        if case.interrupt is not None:
            event, sig = case.interrupt
            deadline = time.monotonic() + timeout
            while proc.poll() is None and not event():
                if time.monotonic() > deadline:
                    break
                time.sleep(0.002)          # polls for the event (a file appearing); the signal follows it
            if proc.poll() is None:
                proc.send_signal(sig)
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        timed_out = True
    seconds = time.perf_counter() - start
    out, err = out.decode("utf-8", "replace"), err.decode("utf-8", "replace")
    res = subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    problems = []
    if timed_out:
        problems.append(f"timeout after {timeout:g} s")
    if res.returncode not in case.expect:
        problems.append(f"exit {res.returncode}, expected {case.expect}")
    if res.returncode < 0 and res.returncode != -signal.SIGKILL:
        problems.append(f"crash (signal {-res.returncode})")
    if "Traceback" in err or "Traceback" in out:
        problems.append("traceback")
    lines = [line for line in err.splitlines() if line.strip()]
    last = lines[-1] if lines else ""
    if any(len(line) > LINE_MAX for line in err.splitlines()):
        problems.append(f"an error line of {max(map(len, err.splitlines())):,} characters")
    if res.returncode in (1, 2):
        errors = [line for line in lines if line.startswith(("radiomap: error:", "Error:"))]
        if len(errors) != 1 or not last.startswith(("radiomap: error:", "Error:")):
            problems.append(f"{len(errors)} error lines, last line {last[:80]!r}")
    for fragment in case.fragments:
        if fragment not in last:
            problems.append(f"{fragment!r} not in the last line")
    for path, snap in before.items():
        if snapshot(Path(path)) != snap:
            problems.append(f"{path} changed (lost or half-overwritten)")
    for path in case.absent:
        if Path(path).exists():
            problems.append(f"{path} written")
    if case.check is not None:
        problem = case.check(res)
        if problem:
            problems.append(problem)
    return {"name": case.name, "kind": case.kind, "status": "clean" if not problems else "unclean",
            "exit": res.returncode, "seconds": round(seconds, 2), "line": last[:160], "problems": problems}


# --------------------------------------------------------------------------------------------------
# fixtures (made with the installed command)
# --------------------------------------------------------------------------------------------------
def make_fixtures(radiomap: str, work: Path) -> dict[str, Path]:
    def rm(*args):
        res = subprocess.run([radiomap, *map(str, args), "--no-progress"], capture_output=True, text=True,
                             cwd=work)
        if res.returncode != 0:
            raise SystemExit(f"fixture failed: radiomap {' '.join(map(str, args))}\n{res.stderr}")

    f = {"work": work}
    f["brackets"] = work / "brackets"
    rm("simulate", "brackets", "-o", f["brackets"], "-n", "5", "--width", "160", "--height", "120", "--seed", "1")
    f["paper"] = work / "paper"
    rm("simulate", "paper", "-o", f["paper"], "-n", "120", "--width", "160", "--height", "120", "--seed", "1")
    f["room"] = work / "room"
    rm("simulate", "room", "-o", f["room"], "-n", "14", "--width", "160", "--height", "120", "--seed", "3")
    f["crf"] = work / "crf.npz"
    rm("response", f["brackets"], "-o", f["crf"])
    f["sweep"] = f["paper"] / "rgb"
    f["vgn"] = work / "v.npz"
    rm("vignetting", f["sweep"], "-r", f["crf"], "-o", f["vgn"], "--no-plots")
    f["selfcal"] = work / "selfcal"
    rm("self-calibrate", f["room"], "-r", f["room"] / "truth" / "response.npz", "--poses", "gt", "-o", f["selfcal"],
       "--no-plots")
    f["run"] = work / "run"
    rm("reconstruct", f["room"], "--poses", "gt", "-o", f["run"])
    return f


def copy(src: Path, dest: Path) -> Callable[[], None]:
    def setup():
        if dest.exists():
            shutil.rmtree(dest) if dest.is_dir() else dest.unlink()
        (shutil.copytree if src.is_dir() else shutil.copy2)(src, dest)
    return setup


def appears(folder: Path, prefix: str) -> Callable[[], bool]:
    """True once an entry whose name starts with ``prefix`` exists in ``folder`` (a lock, a staging folder)."""
    def event() -> bool:
        try:
            return any(name.startswith(prefix) for name in os.listdir(folder))
        except OSError:
            return False
    return event


def previous_or_new(folder: Path, before: dict[str, bytes], primary: str) -> Callable:
    """After an interrupted --force run: the previous set byte for byte, or a complete new one (its primary file
    present and no RUNNING marker), never neither."""
    def check(_res) -> str | None:
        now = snapshot(folder)
        if now == before:
            return None
        if primary in now and "RUNNING" not in now:
            return None
        return f"{folder}: neither the previous result nor a new one ({sorted(now)[:6]})"
    return check


# --------------------------------------------------------------------------------------------------
# the catalogue
# --------------------------------------------------------------------------------------------------
FLOAT_OPTIONS = {
    "reconstruct": ["--voxel-size", "--depth-max", "--depth-scale", "--display-exposure"],
    "compare": ["--voxel-size", "--depth-max", "--depth-scale"],
    "self-calibrate": ["--depth-scale"],
    "response": ["--gamma", "--lambda"],
    "simulate": ["--flicker", "--exposure-time", "--light-change", "--lens-focal", "--lens-aperture"],
    "vignetting": ["--smooth-sigma"],
}


def catalogue(f: dict[str, Path]) -> list[Case]:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from robustness_force_cases import force_cases, staged

    w = f["work"]
    out = w / "out"
    first_frame = sorted(f["sweep"].iterdir())[0].name
    first_bracket = sorted(f["brackets"].glob("*.png"))[0].stem
    cases: list[Case] = []
    base = {"reconstruct": [f["room"], "-o", out / "rec"], "compare": [f["room"], "-r", f["crf"], "-o", out / "cmp"],
            "self-calibrate": [f["room"], "-o", out / "sc"], "response": ["-o", out / "r.npz"],
            "simulate": ["room", "-o", out / "sim"], "vignetting": [f["sweep"], "-r", f["crf"], "-o", out / "v.npz"]}
    for command, options in FLOAT_OPTIONS.items():
        for option in options:
            for value in ("inf", "nan", "-inf"):
                extra = ["--gamma", "2.2"] if command == "response" and option == "--lambda" else []
                extra += ["--lensfun", "x"] if option.startswith("--lens-") else []
                cases.append(Case(f"{command} {option} {value}", "option value",
                                  [command, *base[command], *extra, f"{option}={value}"], fragments=(option,),
                                  absent=(base[command][base[command].index("-o") + 1],),
                                  protect=(f["room"], f["sweep"])))
    cases += [
        Case("response --gamma 0.1", "option value", ["response", "--gamma", "0.1", "-o", out / "g.npz"],
             fragments=("0.2..5",), absent=(out / "g.npz",)),
        Case("reconstruct --voxel-size 0.5", "option value", ["reconstruct", f["room"], "-o", out / "r", "--voxel-size",
                                                              "0.5"], fragments=("0.001..0.2",), absent=(out / "r",)),
        Case("simulate --flicker 0.5", "option value", ["simulate", "paper", "-o", out / "p", "--flicker", "0.5"],
             absent=(out / "p",)),
        Case("batch reconstruct -- --depth-max nan", "option value",
             ["batch", "reconstruct", w / "list.txt", "-o", out / "b", "--", "--depth-max", "nan"],
             setup=lambda: (w / "list.txt").write_text(f"{f['room']}\n"), absent=(out / "b",)),
    ]
    # ---- the memory bound
    cases += [
        Case("kitchen --voxel-size 0.001 (ulimit -v 8 GB)", "memory",
             ["reconstruct", KITCHEN, "-o", out / "k1", "--voxel-size", "0.001", "--poses", "gt", "--no-progress"],
             fragments=("--voxel-size",), limits={"as": 8 * 2 ** 30}, needs=KITCHEN),
        Case("kitchen --voxel-size 0.001 --depth-max 20 (ulimit -v 8 GB)", "memory",
             ["reconstruct", KITCHEN, "-o", out / "k2", "--voxel-size", "0.001", "--depth-max", "20", "--poses", "gt",
              "--no-progress"], fragments=("--voxel-size",), limits={"as": 8 * 2 ** 30}, needs=KITCHEN),
        Case("room --voxel-size 0.001 (ulimit -v 3 GB)", "memory",
             ["reconstruct", f["room"], "-o", out / "k3", "--voxel-size", "0.001", "--poses", "gt", "--no-progress"],
             fragments=("--voxel-size",), limits={"as": 3 * 2 ** 30}),
        Case("room --voxel-size 0.002 --depth-max 20 (ulimit -v 3 GB)", "memory",
             ["reconstruct", f["room"], "-o", out / "k4", "--voxel-size", "0.002", "--depth-max", "20", "--poses",
              "gt", "--no-progress"], expect=(0, 1), limits={"as": 3 * 2 ** 30}),
    ]
    # ---- inputs never overwritten
    b2 = w / "b2"
    sweep2 = w / "sweep2"
    cases += [
        Case("response -o the bracket folder's times file --force", "own input",
             ["response", b2, "-o", b2 / "times.txt", "--force"], setup=copy(f["brackets"], b2), protect=(b2,),
             fragments=("is the input",)),
        Case("response -o a bracket image's name (.png companion) --force", "own input",
             ["response", b2, "-o", b2 / f"{first_bracket}.npz", "--force"], setup=copy(f["brackets"], b2), protect=(b2,),
             fragments=("is the input",)),
        Case("vignetting -o one of the sweep's frames --force", "own input",
             ["vignetting", sweep2, "-r", f["crf"], "-o", sweep2 / first_frame, "--force"],
             setup=copy(f["sweep"], sweep2), protect=(sweep2,), fragments=("is the input",)),
        Case("vignetting -o the response file --force", "own input",
             ["vignetting", f["sweep"], "-r", w / "crf2.npz", "-o", w / "crf2.npz", "--force"],
             setup=copy(f["crf"], w / "crf2.npz"), protect=(w / "crf2.npz",), fragments=("is the input",)),
        Case("correct -o its input folder --force", "own input",
             ["correct", sweep2, "-r", f["crf"], "--vignetting", f["vgn"], "-o", sweep2, "--force"],
             setup=copy(f["sweep"], sweep2), protect=(sweep2,), fragments=("never replaces an input",)),
        Case("reconstruct -o the sequence folder --force", "own input",
             ["reconstruct", w / "room2", "-o", w / "room2", "--force", "--poses", "gt"],
             setup=copy(f["room"], w / "room2"), protect=(w / "room2",), fragments=("is the input sequence",)),
        Case("self-calibrate -o the sequence folder --force", "own input",
             ["self-calibrate", w / "room2", "-o", w / "room2", "--force"], setup=copy(f["room"], w / "room2"),
             protect=(w / "room2",), fragments=("is the input sequence",)),
    ]
    # ---- pose convention
    cases += [
        Case("kitchen ground truth inverted (world-to-camera)", "pose convention",
             ["reconstruct", w / "kinv", "-o", out / "kinv", "--poses", "gt", "--no-progress"],
             setup=lambda: kitchen_copy(w / "kinv", invert=True), fragments=("camera-to-world expected",),
             absent=(out / "kinv",), needs=KITCHEN),
        Case("kitchen ground truth as given (no false alarm), 20 frames", "pose convention",
             ["reconstruct", KITCHEN, "-o", out / "kok", "--poses", "gt", "--frames", "0:20", "--no-progress"],
             expect=(0,), needs=KITCHEN),
        Case("simulated room ground truth inverted", "pose convention",
             ["reconstruct", w / "rinv", "-o", out / "rinv", "--poses", "gt", "--no-progress"],
             setup=lambda: room_inverted(f["room"], w / "rinv"), fragments=("look like world-to-camera",),
             absent=(out / "rinv",)),
        Case("self-calibrate on the inverted room", "pose convention",
             ["self-calibrate", w / "rinv", "-o", out / "scinv", "--poses", "gt", "--no-progress"],
             setup=lambda: room_inverted(f["room"], w / "rinv"), fragments=("camera-to-world expected",)),
    ]
    # ---- operating-system errors
    long = "a" * 300
    cases += [
        Case("response -o a name of 300 characters", "os error", ["response", "--gamma", "2.2", "-o", w / f"{long}.npz"],
             fragments=("too long",)),
        Case("simulate -o a folder name of 300 characters", "os error",
             ["simulate", "paper", "-n", "2", "--width", "32", "--height", "24", "-o", w / long], fragments=("too long",)),
        Case("reconstruct -o a folder name of 300 characters", "os error",
             ["reconstruct", f["room"], "-o", w / long, "--poses", "gt"], fragments=("too long",)),
        Case("reconstruct -o under a file", "os error", ["reconstruct", f["room"], "-o", f["crf"] / "x", "--poses", "gt"]),
        Case("response -o into /proc (not writable)", "os error", ["response", "--gamma", "2.2", "-o", "/proc/x.npz"]),
        Case("reconstruct with 12 open files at most (ulimit -n 12)", "os error",
             ["reconstruct", f["room"], "-o", out / "nofile", "--poses", "gt", "--no-progress"], expect=(0, 1),
             limits={"nofile": 12}),
        Case("vignetting with ulimit -n 10", "os error",
             ["vignetting", f["sweep"], "-r", f["crf"], "-o", out / "nofile.npz", "--no-progress"], expect=(0, 1),
             limits={"nofile": 10}),
    ]
    # ---- config files Python's JSON reader cannot parse
    def config(name: str, text: str) -> Callable[[], None]:
        return lambda: (w / name).write_text(text)

    cases += [
        Case("config.json nested 100,000 deep", "config json", ["reconstruct", "--config", w / "c1.json", "-o", out / "c"],
             setup=config("c1.json", "[" * 100_000 + "]" * 100_000), fragments=("c1.json",), absent=(out / "c",)),
        Case("config.json with a 5,000-digit number", "config json",
             ["reconstruct", "--config", w / "c2.json", "-o", out / "c"],
             setup=config("c2.json", '{"config_version": 1, "command": "reconstruct", "parameters": {"voxel_size": '
                          + "9" * 5000 + "}}"), fragments=("c2.json",), absent=(out / "c",)),
        Case("config.json with 1e999 (infinity)", "config json",
             ["reconstruct", "--config", w / "c3.json", "-o", out / "c"],
             setup=config("c3.json", json.dumps({"config_version": 1, "command": "reconstruct", "parameters": {
                 "sequence": str(f["room"])}}).replace("}}", ', "voxel_size": 1e999}}')),
             fragments=("voxel_size",), absent=(out / "c",)),
        Case("config.json with NaN", "config json", ["reconstruct", "--config", w / "c4.json", "-o", out / "c"],
             setup=config("c4.json", json.dumps({"config_version": 1, "command": "reconstruct", "parameters": {
                 "sequence": str(f["room"]), "depth_max": float("nan")}})), fragments=("depth_max",), absent=(out / "c",)),
        Case("config.json that is a list", "config json", ["reconstruct", "--config", w / "c5.json", "-o", out / "c"],
             setup=config("c5.json", "[1, 2]"), absent=(out / "c",)),
        Case("config.json truncated", "config json", ["reconstruct", "--config", w / "c6.json", "-o", out / "c"],
             setup=config("c6.json", '{"config_version": 1, "comm'), absent=(out / "c",)),
    ]
    # ---- locks
    cases += [
        Case("a stale lock of a dead process", "lock", ["reconstruct", f["room"], "-o", out / "stale", "--poses", "gt",
                                                         "--no-progress"], expect=(0,),
             setup=lambda: lock_of(out / "stale", dead_pid())),
        Case("a lock held by a zombie (killed, unreaped)", "lock",
             ["reconstruct", f["room"], "-o", out / "zombie", "--poses", "gt", "--no-progress"], expect=(0,),
             setup=lambda: lock_of(out / "zombie", ZOMBIES.make())),
        Case("a lock held by a live process", "lock",
             ["reconstruct", f["room"], "-o", out / "live", "--poses", "gt", "--no-progress"],
             setup=lambda: lock_of(out / "live", os.getpid()), fragments=("in use by another radiomap run",)),
    ]
    # ---- interruptions: previous result or new one, never neither; Ctrl-C one line
    sc = w / "sc_force"
    rsp = w / "rsp_force"
    vg = w / "vg_force"
    sc_before: dict = {}
    rsp_before: dict = {}
    vg_before: dict = {}

    def keep(src: Path, dest: Path, store: dict) -> Callable[[], None]:
        def setup():
            copy(src, dest)()
            store.clear()
            store.update(snapshot(dest))
        return setup

    def response_set(dest: Path) -> Callable[[], None]:
        def setup():
            if dest.exists():
                shutil.rmtree(dest)
            dest.mkdir()
            for suffix in (".npz", ".png", ".json"):
                shutil.copy2(f["crf"].with_suffix(suffix), dest / f"crf{suffix}")
            rsp_before.clear()
            rsp_before.update(snapshot(dest))
        return setup

    def vignetting_set(dest: Path) -> Callable[[], None]:
        def setup():
            if dest.exists():
                shutil.rmtree(dest)
            dest.mkdir()
            for p in f["work"].glob("v*"):
                if p.is_file() and p.name.startswith(("v.", "v_")):
                    shutil.copy2(p, dest / p.name)
            vg_before.clear()
            vg_before.update(snapshot(dest))
        return setup

    sc_args = ["self-calibrate", f["room"], "-r", f["room"] / "truth" / "response.npz", "--poses", "gt", "-o", sc,
               "--force", "--no-progress"]
    cases += [
        Case("self-calibrate --force, SIGKILL once it holds the lock", "interrupt", sc_args, expect=(-9, 0),
             setup=keep(f["selfcal"], sc, sc_before), interrupt=(appears(sc, "LOCK"), signal.SIGKILL),
             check=lambda r: previous_or_new(sc, sc_before, "self_calibration.json")(r)),
        Case("self-calibrate --force, SIGINT once it holds the lock", "interrupt", sc_args, expect=(130, 0),
             setup=keep(f["selfcal"], sc, sc_before), interrupt=(appears(sc, "LOCK"), signal.SIGINT),
             check=lambda r: previous_or_new(sc, sc_before, "self_calibration.json")(r)),
        Case("self-calibrate --force, SIGKILL once it stages files", "interrupt", sc_args, expect=(-9, 0),
             setup=keep(f["selfcal"], sc, sc_before), interrupt=(appears(sc, ".tmp-radiomap"), signal.SIGKILL),
             check=lambda r: previous_or_new(sc, sc_before, "self_calibration.json")(r)),
        Case("self-calibrate --force, SIGTERM once it stages files", "interrupt", sc_args, expect=(143, 0),
             setup=keep(f["selfcal"], sc, sc_before), interrupt=(appears(sc, ".tmp-radiomap"), signal.SIGTERM),
             check=lambda r: previous_or_new(sc, sc_before, "self_calibration.json")(r)),
        Case("response --force, SIGKILL once it stages files", "interrupt",
             ["response", f["brackets"], "-o", rsp / "crf.npz", "--force", "--no-progress"], expect=(-9, 0),
             setup=response_set(rsp), interrupt=(appears(rsp, ".tmp-radiomap"), signal.SIGKILL),
             check=lambda r: previous_or_new(rsp, rsp_before, "crf.npz")(r)),
        Case("response --force, SIGINT once it stages files", "interrupt",
             ["response", f["brackets"], "-o", rsp / "crf.npz", "--force", "--no-progress"], expect=(130, 0),
             setup=response_set(rsp), interrupt=(appears(rsp, ".tmp-radiomap"), signal.SIGINT),
             check=lambda r: previous_or_new(rsp, rsp_before, "crf.npz")(r)),
        Case("vignetting --force, SIGINT once it stages files", "interrupt",
             ["vignetting", f["sweep"], "-r", f["crf"], "-o", vg / "v.npz", "--force", "--no-progress"],
             expect=(130, 0), setup=vignetting_set(vg), interrupt=(appears(vg, ".tmp-radiomap"), signal.SIGINT),
             check=lambda r: previous_or_new(vg, vg_before, "v.npz")(r)),
        Case("vignetting --force, SIGKILL once it stages files", "interrupt",
             ["vignetting", f["sweep"], "-r", f["crf"], "-o", vg / "v.npz", "--force", "--no-progress"],
             expect=(-9, 0), setup=vignetting_set(vg), interrupt=(appears(vg, ".tmp-radiomap"), signal.SIGKILL),
             check=lambda r: previous_or_new(vg, vg_before, "v.npz")(r)),
        Case("reconstruct, SIGINT once RUNNING is written", "interrupt",
             ["reconstruct", f["room"], "-o", out / "int", "--poses", "gt", "--no-progress"], expect=(130, 0),
             interrupt=(appears(out / "int", "RUNNING"), signal.SIGINT),
             check=lambda r: None if r.returncode == 0 or r.stderr.strip().endswith("radiomap: interrupted")
             else "no 'radiomap: interrupted' line"),
        Case("reconstruct --force over a finished run, SIGKILL once its staging folder holds RUNNING", "interrupt",
             ["reconstruct", f["room"], "-o", w / "run2", "--poses", "gt", "--force", "--no-progress"],
             expect=(-9, 0), setup=copy(f["run"], w / "run2"), interrupt=(staged(w / "run2", "RUNNING"), signal.SIGKILL),
             check=lambda r: reconstruct_never_neither(w / "run2")),
        Case("reconstruct --force over a finished run, SIGINT once it stages files", "interrupt",
             ["reconstruct", f["room"], "-o", w / "run3", "--poses", "gt", "--force", "--no-progress"],
             expect=(130, 0), setup=copy(f["run"], w / "run3"),
             interrupt=(appears(w / "run3", ".tmp-radiomap"), signal.SIGINT),
             check=lambda r: reconstruct_never_neither(w / "run3")),
    ]
    cases += force_cases(f, sys.modules[__name__])
    # ---- error lines of a readable length; bad inputs of the earlier catalogue, rechecked
    b3 = w / "b3"

    def huge_token():
        copy(f["brackets"], b3)()
        lines = (b3 / "times.txt").read_text().splitlines()
        lines[-1] = lines[-1].split()[0] + " " + "9x" * 30_000_000        # a 60 MB token
        (b3 / "times.txt").write_text("\n".join(lines) + "\n")

    cases += [
        Case("times.txt with a 60 MB token", "long line", ["response", b3, "-o", out / "t.npz"], setup=huge_token,
             fragments=("characters",), absent=(out / "t.npz",)),
        Case("--frames with 100,000 characters", "long line",
             ["reconstruct", f["room"], "-o", out / "fr", "--frames", "1" * 100_000], absent=(out / "fr",)),
        Case("--intrinsics nan,nan,nan,nan", "option value",
             ["reconstruct", f["room"], "-o", out / "in", "--intrinsics", "nan,nan,nan,nan"], absent=(out / "in",)),
        Case("--mesh-exposure inf", "option value",
             ["reconstruct", f["room"], "-r", f["crf"], "-o", out / "me", "--mesh-exposure", "inf"],
             absent=(out / "me",)),
        Case("correct --scale nan", "option value",
             ["correct", f["sweep"], "-r", f["crf"], "--vignetting", f["vgn"], "-o", out / "sc", "--scale", "nan"],
             absent=(out / "sc",)),
        Case("a corrupt frame in a sweep", "bad input", ["vignetting", w / "sweep3", "-r", f["crf"], "-o", out / "v3.npz"],
             setup=lambda: (copy(f["sweep"], w / "sweep3")(), (w / "sweep3" / first_frame).write_bytes(b"\x89PNG junk")),
             absent=(out / "v3.npz",)),
        Case("a response file with NaN", "bad input",
             ["correct", f["sweep"], "-r", w / "nan.npz", "--vignetting", f["vgn"], "-o", out / "cn"],
             setup=lambda: nan_response(f["crf"], w / "nan.npz"), absent=(out / "cn",)),
        Case("an empty folder as a sequence", "bad input", ["reconstruct", w / "empty", "-o", out / "e"],
             setup=lambda: (w / "empty").mkdir(exist_ok=True), absent=(out / "e",)),
        Case("--depth-scale 1 on TUM depth", "bad input",
             ["reconstruct", f["room"], "-o", out / "ds", "--depth-scale", "1", "--poses", "gt"], absent=(out / "ds",)),
    ]
    return cases


def fresh_comparison(f: dict, dest: Path, methods: str = "none") -> None:
    if dest.exists():
        shutil.rmtree(dest)
    subprocess.run([RADIOMAP[0], "compare", str(f["room"]), "-r",
                    str(f["room"] / "truth" / "response.npz"), "--methods", methods, "-o", str(dest), "--no-progress",
                    "--views", "0"], capture_output=True, check=True)


def reconstruct_never_neither(folder: Path) -> str | None:
    """A results folder after a killed ``reconstruct --force``: the previous run's results or the new run's,
    complete (metrics.json "complete", no RUNNING marker), never neither."""
    try:
        status = json.loads((folder / "metrics.json").read_text()).get("status")
    except (OSError, ValueError):
        status = None
    if status == "complete" and not (folder / "RUNNING").exists() and (folder / "mesh.ply").is_file():
        return None
    return f"{folder}: neither the previous run nor a new one (status {status!r}, RUNNING marker)"


def kitchen_copy(dest: Path, *, invert: bool) -> None:
    import numpy as np

    if dest.exists():
        shutil.rmtree(dest)
    (dest / "frames").mkdir(parents=True)
    os.symlink(KITCHEN / "camera-intrinsics.txt", dest / "camera-intrinsics.txt")
    for pose_file in sorted((KITCHEN / "frames").glob("*.pose.txt")):
        stem = pose_file.name[: -len(".pose.txt")]
        for kind in ("color.jpg", "depth.png"):
            os.symlink(KITCHEN / "frames" / f"{stem}.{kind}", dest / "frames" / f"{stem}.{kind}")
        pose = np.loadtxt(pose_file)
        np.savetxt(dest / "frames" / pose_file.name, np.linalg.inv(pose) if invert else pose)


def room_inverted(room: Path, dest: Path) -> None:
    """A TUM copy of the simulated room whose groundtruth.txt holds the inverse poses (quaternion + position)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(room, dest)
    (dest / "radiomap_sequence.json").unlink(missing_ok=True)     # read as plain TUM
    rows = [line.split() for line in (room / "groundtruth.txt").read_text().splitlines() if line and line[0] != "#"]
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for row in rows:
        t, xyz, q = row[0], np.array(row[1:4], float), np.array(row[4:8], float)
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q).as_matrix()
        T[:3, 3] = xyz
        inv = np.linalg.inv(T)
        qi = Rotation.from_matrix(inv[:3, :3]).as_quat()
        lines.append(" ".join([t, *(f"{v:.9f}" for v in inv[:3, 3]), *(f"{v:.9f}" for v in qi)]))
    (dest / "groundtruth.txt").write_text("\n".join(lines) + "\n")


def nan_response(src: Path, dest: Path) -> None:
    import numpy as np

    data = dict(np.load(src))
    table = data["inverse_table"].astype(float)
    table[10, 0] = np.nan
    data["inverse_table"] = table
    np.savez(dest, **data)


def lock_of(folder: Path, pid: int) -> None:
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    try:
        start = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[19]
    except (OSError, IndexError):
        start = None
    (folder / "LOCK").write_text(json.dumps({"pid": pid, "start": start, "host": socket.gethostname(),
                                             "what": "run", "started": "earlier"}))


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


class _Zombies:
    """Children that exited and are kept unreaped (zombies) until the end of the catalogue."""

    def __init__(self) -> None:
        self.procs: list[subprocess.Popen] = []

    def make(self) -> int:
        proc = subprocess.Popen([sys.executable, "-c", "pass"])
        self.procs.append(proc)
        while True:      # wait for the exit without reaping: the state in /proc turns to Z
            state = Path(f"/proc/{proc.pid}/status").read_text().split("State:")[1].split()[0]
            if state == "Z":
                return proc.pid
            time.sleep(0.01)

    def reap(self) -> None:
        for proc in self.procs:
            proc.wait()


ZOMBIES = _Zombies()


# --------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--radiomap", default=shutil.which("radiomap"), help="the installed command")
    parser.add_argument("--work", type=Path, default=None, help="work folder (default: a temporary one, removed)")
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds per case")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    parser.add_argument("--only", default=None, help="run the cases whose name contains this")
    args = parser.parse_args(argv)
    if not args.radiomap:
        parser.error("no radiomap command on PATH; pip install the project or pass --radiomap")
    RADIOMAP[0] = args.radiomap
    work = args.work or Path(tempfile.mkdtemp(prefix="radiomap-catalogue-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        t0 = time.perf_counter()
        fixtures = make_fixtures(args.radiomap, work)
        cases = [c for c in catalogue(fixtures) if args.only is None or args.only in c.name]
        results = []
        for case in cases:
            result = run_case(args.radiomap, case, args.timeout, work)
            results.append(result)
            mark = {"clean": "ok ", "unclean": "BAD", "skipped": "-- "}[result["status"]]
            print(f"{mark} [{result['kind']}] {result['name']}: exit {result.get('exit')} "
                  f"{result.get('seconds', 0):.1f} s  {'; '.join(result.get('problems', [])) or result.get('line', '')[:90]}",
                  flush=True)
    finally:
        ZOMBIES.reap()
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
    ran = [r for r in results if r["status"] != "skipped"]
    clean = sum(r["status"] == "clean" for r in ran)
    kinds = sorted({r["kind"] for r in ran})
    print(f"\n{clean} of {len(ran)} cases clean ({100 * clean / max(len(ran), 1):.0f} %), "
          f"{len(results) - len(ran)} skipped, {time.perf_counter() - t0:.0f} s in all")
    for kind in kinds:
        rows = [r for r in ran if r["kind"] == kind]
        print(f"  {kind}: {sum(r['status'] == 'clean' for r in rows)} of {len(rows)} clean")
    crashes = [r for r in ran if isinstance(r.get("exit"), int) and r["exit"] < 0 and r["exit"] != -9]
    print(f"  crashes (signals other than the catalogue's own SIGKILL): {len(crashes)}")
    if args.out:
        args.out.write_text(json.dumps({"radiomap": args.radiomap, "date": time.strftime("%Y-%m-%d %H:%M %Z"),
                                        "clean": clean, "cases": len(ran), "results": results}, indent=1))
    return 0 if clean == len(ran) else 1


if __name__ == "__main__":
    sys.exit(main())
