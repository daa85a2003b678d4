"""Repeat ``radiomap reconstruct`` (TSDF backend) many times, half of the runs beside a CPU-burning process.

Proves the TSDF backend does not crash (issue 13 item 1: Open3D's ray cast segfaulted under load). Every run
is a fresh process (``python -m mapping.cli reconstruct ... --poses gt``) over one of a set of varied cases:

- ``../shared/data/repro/tsdf_segfault_room`` (a deep room, walls 1.5-4.5 m) cut by ``--depth-max`` 3 (the
  default), 2, 4 and 5;
- the 7-Scenes sample ``../shared/data/rgbd/redkitchen_7scenes_000-099`` (8-frame subsets, voxels 1 and 2 cm);
- rooms simulated once into the work folder (``radiomap simulate room``) at 640x480, 320x240, 212x160 (not a
  multiple of 8), 160x120 and 800x600, one of them also with its focal length scaled (``--intrinsics``).

Runs alternate idle / under load (a ``python -c "while True: pass"`` process started before the run and
stopped after it, by this script). A run crashed when its return code is negative (killed by a signal, e.g.
-11 = SIGSEGV; a shell would show 139); any other non-zero exit is a failure. Prints one line per run, a table
per case and a final line with the totals; exits 1 when any run crashed or failed. Usage::

    python scripts/stress_tsdf.py                      # 200 runs
    python scripts/stress_tsdf.py --runs 40 --json stress.json
    python scripts/stress_tsdf.py --pythonpath /tmp/old_tree   # the radiomap code of another checkout

Ctrl-C (or SIGTERM) stops after the current run and reports the finished runs.

``--pythonpath`` puts a source tree (folders ``mapping`` and ``radiometry``, e.g. ``git archive OLD mapping
radiometry | tar -x -C /tmp/old_tree``) first on the runs' import path, to measure older code the same way.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
REPRO = SHARED / "repro" / "tsdf_segfault_room"
KITCHEN = SHARED / "rgbd" / "redkitchen_7scenes_000-099"
# (name, width, height, seed, frames) of the simulated rooms
SIMULATED = (("sim640", 640, 480, 11, 6), ("sim320", 320, 240, 12, 8), ("sim212", 212, 160, 13, 8),
             ("sim160", 160, 120, 14, 8), ("sim800", 800, 600, 15, 5))


@dataclass
class Case:
    name: str
    sequence: Path
    args: list[str] = field(default_factory=list)


def _cli(pythonpath: str | None) -> tuple[list[str], dict]:
    """The command and environment of a run (run it outside the checkout: ``python -m`` puts the working
    folder first on the import path, before ``--pythonpath``)."""
    env = dict(os.environ)
    if pythonpath:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (pythonpath, env.get("PYTHONPATH")) if p)
    return [sys.executable, "-m", "mapping.cli"], env


def simulate_rooms(folder: Path, pythonpath: str | None) -> dict[str, Path]:
    """Render the simulated rooms (once per work folder; an existing complete one is reused)."""
    cli, env = _cli(pythonpath)
    folder.mkdir(parents=True, exist_ok=True)
    rooms = {}
    for name, width, height, seed, frames in SIMULATED:
        out = folder / name
        if not (out / "radiomap_sequence.json").exists():
            cmd = cli + ["simulate", "room", "-o", str(out), "--seed", str(seed), "--width", str(width),
                         "--height", str(height), "--num-frames", str(frames), "--no-progress", "--force"]
            done = subprocess.run(cmd, env=env, cwd=folder, capture_output=True, text=True)
            if done.returncode != 0:
                raise SystemExit(f"simulating {name} failed (exit {done.returncode}): {done.stderr.strip()[-500:]}")
        rooms[name] = out
    return rooms


def _scaled_intrinsics(sequence: Path, factor: float) -> str:
    """fx,fy,cx,cy of a simulated room with the focal length scaled (a wider or narrower camera)."""
    K = json.loads((sequence / "radiomap_sequence.json").read_text())["K"]
    fx, fy, cx, cy = K[0][0], K[1][1], K[0][2], K[1][2]
    return f"{fx * factor:g},{fy * factor:g},{cx:g},{cy:g}"


def build_cases(rooms: dict[str, Path]) -> list[Case]:
    cases = []
    if REPRO.is_dir():
        cases += [Case("repro_room dmax 3", REPRO), Case("repro_room dmax 2", REPRO, ["--depth-max", "2"]),
                  Case("repro_room dmax 4", REPRO, ["--depth-max", "4"]),
                  Case("repro_room dmax 5", REPRO, ["--depth-max", "5"])]
    if KITCHEN.is_dir():
        cases += [Case("7scenes 0:8", KITCHEN, ["--frames", "0:8:1"]),
                  Case("7scenes 45:53", KITCHEN, ["--frames", "45:53:1"]),
                  Case("7scenes 0:100:12 vox2cm", KITCHEN, ["--frames", "0:100:12", "--voxel-size", "0.02"])]
    for name, *_ in SIMULATED:
        cases.append(Case(name, rooms[name]))
    cases.append(Case("sim320 fx*0.6", rooms["sim320"], ["--intrinsics", _scaled_intrinsics(rooms["sim320"], 0.6)]))
    cases.append(Case("sim640 fx*1.5 dmax 5", rooms["sim640"],
                      ["--intrinsics", _scaled_intrinsics(rooms["sim640"], 1.5), "--depth-max", "5"]))
    return cases


def start_burner() -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", "while True: pass"], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)


def stop_burner(burner: subprocess.Popen) -> None:
    burner.terminate()
    try:
        burner.wait(timeout=10)
    except subprocess.TimeoutExpired:
        burner.kill()
        burner.wait()


def run_once(case: Case, out: Path, loaded: bool, timeout: float, pythonpath: str | None) -> dict:
    cli, env = _cli(pythonpath)
    cmd = cli + ["reconstruct", str(case.sequence), "--poses", "gt", "-o", str(out), "--force", "--no-progress",
                 *case.args]
    burner = start_burner() if loaded else None
    start = time.perf_counter()
    try:
        done = subprocess.run(cmd, env=env, cwd=out.parent, capture_output=True, text=True, timeout=timeout)
        code, tail = done.returncode, done.stderr.strip()[-300:]
    except subprocess.TimeoutExpired:
        code, tail = None, f"timed out after {timeout:g} s"
    finally:
        if burner is not None:
            stop_burner(burner)
    seconds = time.perf_counter() - start
    shutil.rmtree(out, ignore_errors=True)
    if code is None:
        outcome = "timeout"
    elif code < 0:
        outcome = "crash"
    else:
        outcome = "ok" if code == 0 else "error"
    return {"case": case.name, "loaded": loaded, "returncode": code, "outcome": outcome,
            "signal": signal.Signals(-code).name if code is not None and code < 0 else None,
            "seconds": round(seconds, 2), "stderr_tail": tail if outcome != "ok" else ""}


def table(records: list[dict], cases: list[Case]) -> str:
    header = ("case", "runs", "idle ok", "load ok", "crashes", "errors", "mean s")
    rows = []
    for case in cases:
        mine = [r for r in records if r["case"] == case.name]
        if not mine:
            continue
        signals = sorted({r["signal"] for r in mine if r["signal"]})
        crashes = sum(r["outcome"] == "crash" for r in mine)
        rows.append((case.name, str(len(mine)),
                     f"{sum(r['outcome'] == 'ok' and not r['loaded'] for r in mine)}/{sum(not r['loaded'] for r in mine)}",
                     f"{sum(r['outcome'] == 'ok' and r['loaded'] for r in mine)}/{sum(r['loaded'] for r in mine)}",
                     f"{crashes}" + (f" ({', '.join(signals)})" if signals else ""),
                     str(sum(r["outcome"] in ("error", "timeout") for r in mine)),
                     f"{sum(r['seconds'] for r in mine) / len(mine):.1f}"))
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(header, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths)) for row in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=200, help="number of runs (default 200; half under load)")
    parser.add_argument("--json", type=Path, help="write every run and the totals to this JSON file")
    parser.add_argument("--workdir", type=Path, help="folder for the simulated rooms and run outputs "
                        "(default: a temporary folder, removed at the end)")
    parser.add_argument("--timeout", type=float, default=600.0, help="seconds before a run counts as hung")
    parser.add_argument("--pythonpath", help="import radiomap from this source tree (to measure other code)")
    parser.add_argument("--offset", type=int, default=0, help="start at this case (to split the runs over "
                        "several processes)")
    args = parser.parse_args(argv)
    if args.runs < 1:
        parser.error("--runs must be at least 1")
    if args.pythonpath and not (Path(args.pythonpath) / "mapping").is_dir():
        parser.error(f"--pythonpath {args.pythonpath}: no 'mapping' package there")

    temporary = args.workdir is None
    work = Path(tempfile.mkdtemp(prefix="stress_tsdf_")) if temporary else args.workdir
    work.mkdir(parents=True, exist_ok=True)
    try:
        rooms = simulate_rooms(work / "sequences", args.pythonpath)
        cases = build_cases(rooms)
        records = []
        started = time.perf_counter()
        signal.signal(signal.SIGTERM, signal.default_int_handler)   # SIGTERM too: stop and report
        interrupted = False
        for i in range(args.runs):
            case, loaded = cases[(i // 2 + args.offset) % len(cases)], i % 2 == 1
            try:
                record = run_once(case, work / "out", loaded, args.timeout, args.pythonpath)
            except KeyboardInterrupt:
                interrupted = True
                print(f"interrupted: reporting the {len(records)} finished runs", file=sys.stderr)
                break
            records.append(record)
            note = f" {record['signal'] or record['returncode']}: {record['stderr_tail'][-120:]}" \
                if record["outcome"] != "ok" else ""
            print(f"[{i + 1}/{args.runs}] {case.name:<24} {'load' if loaded else 'idle'}  {record['outcome']:<7} "
                  f"{record['seconds']:6.1f} s{note}", file=sys.stderr, flush=True)
    finally:
        if temporary:
            shutil.rmtree(work, ignore_errors=True)

    crashes = sum(r["outcome"] == "crash" for r in records)
    failures = sum(r["outcome"] in ("error", "timeout") for r in records)
    loaded_runs = sum(r["loaded"] for r in records)
    summary = {"runs": len(records), "under_load": loaded_runs, "ok": sum(r["outcome"] == "ok" for r in records),
               "crashes": crashes, "crashes_under_load": sum(r["outcome"] == "crash" and r["loaded"] for r in records),
               "failures": failures, "cases": len({r["case"] for r in records}),
               "minutes": round((time.perf_counter() - started) / 60, 1), "pythonpath": args.pythonpath,
               "interrupted": interrupted}
    print(table(records, cases))
    print(f"TOTAL runs {summary['runs']} ({loaded_runs} under load) over {summary['cases']} cases: "
          f"{summary['ok']} ok, {crashes} crashes ({summary['crashes_under_load']} under load), {failures} other "
          f"failures, {summary['minutes']} min" + (" (interrupted)" if interrupted else ""))
    if args.json:
        from radiometry.fileio import atomic_write_json

        atomic_write_json(args.json, {"summary": summary, "runs": records})
    return 1 if crashes or failures else 0


if __name__ == "__main__":
    sys.exit(main())
