"""Smoke test of scripts/robustness_catalogue.py: the catalogue covers every kind of fault with at least 60 cases,
and a case is judged by the installed command's behaviour (a traceback, a crash or a changed input is unclean)."""

from __future__ import annotations

import importlib.util
import os
import stat
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "robustness_catalogue.py"


def load():
    spec = importlib.util.spec_from_file_location("radiomap_script_robustness_catalogue", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module          # dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_the_catalogue_covers_every_kind(tmp_path):
    script = load()
    (tmp_path / "sweep").mkdir()
    (tmp_path / "sweep" / "000.png").write_bytes(b"x")
    (tmp_path / "brackets").mkdir()
    (tmp_path / "brackets" / "exposure_00.png").write_bytes(b"x")
    fixtures = {k: tmp_path / k for k in ("brackets", "paper", "room", "crf", "vgn", "selfcal", "run")}
    fixtures.update(work=tmp_path, sweep=tmp_path / "sweep")
    cases = script.catalogue(fixtures)
    kinds = {c.kind for c in cases}
    assert len(cases) >= 60
    assert {"option value", "memory", "own input", "pose convention", "os error", "config json", "lock",
            "interrupt", "long line"} <= kinds
    assert len({c.name for c in cases}) == len(cases)


def _fake(tmp_path: Path, body: str) -> str:
    path = tmp_path / "fake-radiomap"
    path.write_text("#!/bin/sh\n" + body + "\n")
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    return str(path)


def test_a_case_is_judged_by_exit_code_lines_and_files(tmp_path):
    script = load()
    kept = tmp_path / "kept.txt"
    kept.write_text("input\n")
    case = script.Case("x", "option value", ["--x"], protect=(kept,), fragments=("--x",))
    clean = script.run_case(_fake(tmp_path, 'echo "radiomap: error: --x bad; fix it" >&2; exit 1'), case, 60, tmp_path)
    assert clean["status"] == "clean", clean
    trace = script.run_case(_fake(tmp_path, 'echo "Traceback (most recent call last):" >&2; exit 1'), case, 60,
                            tmp_path)
    assert trace["status"] == "unclean" and "traceback" in trace["problems"]
    crash = script.run_case(_fake(tmp_path, "kill -SEGV $$"), case, 60, tmp_path)
    assert crash["status"] == "unclean" and any("crash" in p for p in crash["problems"])
    lost = script.run_case(_fake(tmp_path, f'echo new > {kept}; echo "radiomap: error: --x" >&2; exit 1'), case, 60,
                           tmp_path)
    assert lost["status"] == "unclean" and any("changed" in p for p in lost["problems"])
    assert os.path.exists(kept)
