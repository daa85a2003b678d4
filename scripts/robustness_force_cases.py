"""The catalogue's cases of ``--force`` over a complete result (issue 31), for ``scripts/robustness_catalogue.py``.

``compare``, ``simulate`` and ``demo`` with ``--force`` over a complete result, interrupted (SIGKILL, SIGINT) early
(once the staging folder appears in OUT) or late (once it holds a late output): the previous result byte for byte
or the complete new one; run to the end: the new result only, the user's file kept. ``cat`` is the catalogue
module (its ``Case``, ``snapshot``, ``appears``, ``copy``, ``previous_or_new``, ``fresh_comparison`` and the command
under test, ``RADIOMAP``).
"""

from __future__ import annotations

import os
import signal
import subprocess
from pathlib import Path
from typing import Callable


def staged(folder: Path, name: str) -> Callable[[], bool]:
    """True once a staging folder in ``folder`` (an interrupted --force run's new result) holds ``name``."""
    def event() -> bool:
        try:
            return any((folder / entry / name).exists() for entry in os.listdir(folder)
                       if entry.startswith(".tmp-radiomap"))
        except OSError:
            return False
    return event


def force_cases(f: dict, cat) -> list:
    """``compare``, ``simulate`` and ``demo`` with --force over a complete result: interrupted early (once the
    staging folder appears) or late (once it holds a late output), the previous result byte for byte or the complete
    new one; run to the end, the new result only (no file or folder of the previous one left)."""
    w = f["work"]
    before: dict[str, dict] = {}

    def keep(make: Callable[[Path], None], dest: Path) -> Callable[[], None]:
        def setup():
            make(dest)
            before[str(dest)] = cat.snapshot(dest)
        return setup

    def comparison(methods: str) -> Callable[[Path], None]:
        return lambda dest: cat.fresh_comparison(f, dest, methods)

    def sequence(dest: Path) -> None:
        cat.copy(f["room"], dest)()

    def demo(dest: Path) -> None:
        prev = w / "demo_prev"
        if not prev.exists():
            subprocess.run([cat.RADIOMAP[0], "demo", "-o", str(prev), "--quick", "--no-progress"], capture_output=True,
                           check=True, cwd=w)
        cat.copy(prev, dest)()

    def kept(folder: Path, primary: str) -> Callable:
        return lambda r: cat.previous_or_new(folder, before[str(folder)], primary)(r)

    cmp_args = lambda dest: ["compare", f["room"], "-r", f["room"] / "truth" / "response.npz", "--methods",  # noqa
                             "response", "-o", dest, "--force", "--no-progress", "--views", "0"]
    sim_args = lambda dest: ["simulate", "room", "-o", dest, "-n", "6", "--width", "160", "--height", "120",  # noqa
                             "--seed", "5", "--force", "--no-progress"]
    demo_args = lambda dest: ["demo", "-o", dest, "--quick", "--force", "--no-progress", "--seed", "1",  # noqa
                              "--no-exposure-compensation"]
    cases = []
    for kind, args, make, primary, late in (
            ("compare", cmp_args, comparison("none,response"), "compare.json", "compare.csv"),
            ("simulate", sim_args, sequence, "radiomap_sequence.json", "groundtruth.txt"),
            ("demo", demo_args, demo, "demo.json", "compare")):
        for moment, event in (("early", lambda d: cat.appears(d, ".tmp-radiomap")),
                              ("late", lambda d, n=late: staged(d, n))):
            for sig in (signal.SIGKILL, signal.SIGINT):
                dest = w / f"{kind}_{moment}_{sig.name}"
                cases.append(cat.Case(f"{kind} --force over a complete result, {sig.name} {moment}", "interrupt",
                                      args(dest), expect=(-9 if sig == signal.SIGKILL else 130, 0),
                                      setup=keep(make, dest), interrupt=(event(dest), sig),
                                      check=kept(dest, primary)))
    # run to the end: the new result wholly, the user's file kept
    cmp_done, sim_done = w / "compare_done", w / "simulate_done"

    def only_new(folder: Path, expected: set[str]) -> Callable:
        def check(_res) -> str | None:
            names = {p.name for p in folder.iterdir()}
            if names != expected:
                return f"{folder}: {sorted(names ^ expected)} differ from a fresh result"
            return None
        return check

    def with_notes(make: Callable[[Path], None]) -> Callable[[Path], None]:
        def setup(dest: Path) -> None:
            make(dest)
            (dest / "notes.txt").write_text("mine\n")
        return setup

    cases += [
        cat.Case("compare --force over a comparison of 2 methods, 1 method, to the end", "force", cmp_args(cmp_done),
                 expect=(0,), setup=keep(with_notes(comparison("none,response")), cmp_done),
                 check=only_new(cmp_done, {".radiomap-files.json", "colour_error.png", "compare.csv", "compare.json",
                                           "compare.txt", "config.json", "histograms.png", "notes.txt", "report.html",
                                           "response", "summary.txt", "trajectory.png"})),
        cat.Case("simulate --force over 14 frames, 6 frames, to the end", "force", sim_args(sim_done), expect=(0,),
                 setup=keep(with_notes(sequence), sim_done),
                 check=lambda r: only_new(sim_done, {"depth", "depth.txt", "groundtruth.txt", "intrinsics.txt",
                                                     "notes.txt", "radiomap_sequence.json", "rgb", "rgb.txt",
                                                     "truth"})(r) or
                 (None if len(list((sim_done / "rgb").iterdir())) == 6 else f"{sim_done}/rgb: old frames left")),
    ]
    return cases
