"""``demo --force`` over a complete demo, interrupted at any moment (SIGKILL or SIGINT, early: its first step; late:
everything written), leaves the previous demo byte for byte; a completed run replaces it wholly (issue 31; the
mechanism and the compare/simulate cases: test_robustness_force.py).

The demo is made small here (:func:`shrink_demo`: 64x48 pixels, 6 room frames, and the simulator's true response
instead of the 6 s response fit): the folders it writes, and so its publication, are the demo's own.
"""

from __future__ import annotations

import contextlib
import shutil
import signal
from pathlib import Path

import pytest
from test_robustness_force import assert_previous_kept, cli_ok, no_leftovers, paused_run, tree

TINY = dict(width=64, height=48, room_frames=6, paper_frames=24, voxel_size=0.04, depth_max=3.5, render_width=64,
            speed=4.0)


def _true_response(calib, sim, *, seed, progress, timings, say):
    """Step 2 of the demo without the fit: the simulator's response, saved where the demo saves its estimate."""
    sim.response.save(calib / "response.npz")
    timings["response"] = 0.0
    say("response: the simulator's (test)")
    return sim.response, 0, [0.0, 0.0, 0.0]


def shrink_demo() -> dict:
    """Make ``radiomap demo --quick`` small (the module doc); returns what it replaced."""
    import mapping.demo as demo

    old = {"QUICK": demo.QUICK, "_calibrate_response": demo._calibrate_response}
    demo.QUICK = demo.DemoSize(**TINY)
    demo._calibrate_response = _true_response
    return old


@contextlib.contextmanager
def shrunk():
    import mapping.demo as demo

    old = shrink_demo()
    try:
        yield
    finally:
        for name, value in old.items():
            setattr(demo, name, value)


def _demo(out: Path, *extra) -> list:
    return ["demo", "-o", out, "--quick", "--no-progress", *extra]


@pytest.fixture(scope="module")
def previous(tmp_path_factory) -> Path:
    """A complete (small) demo with exposure compensation, with the user's notes beside it."""
    out = tmp_path_factory.mktemp("demo") / "demo"
    with shrunk():
        cli_ok(*_demo(out))
    (out / "notes.txt").write_text("mine\n")
    return out


@pytest.mark.slow
@pytest.mark.parametrize("moment", ["mapping.demo:_calibrate_response",    # its first step
                                    "mapping.demo:DemoFolder.complete"],   # everything written
                         ids=["early", "late"])
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT], ids=["SIGKILL", "SIGINT"])
def test_demo_force_interrupted_keeps_the_previous_demo(previous, tmp_path, moment, sig):
    out = tmp_path / "demo"
    shutil.copytree(previous, out)
    before = tree(out)
    res = paused_run(moment, _demo(out, "--force", "--seed", "1", "--no-exposure-compensation"), sig)
    assert_previous_kept(res, sig, out, before)


@pytest.mark.slow
def test_demo_force_replaces_the_previous_demo_wholly(previous, tmp_path):
    """Without exposure compensation (other method folders) and another seed: the published demo is exactly a
    fresh one's set of files (no old method folder, no old frame), the records name OUT, the user's notes stay."""
    import json

    out = tmp_path / "demo"
    shutil.copytree(previous, out)
    assert (out / "compare" / "lut+ec").is_dir()
    with shrunk():
        cli_ok(*_demo(out, "--force", "--seed", "1", "--no-exposure-compensation"))
        fresh = tmp_path / "fresh"
        cli_ok(*_demo(fresh, "--seed", "1", "--no-exposure-compensation"))
    no_leftovers(out)
    assert (out / "notes.txt").read_text() == "mine\n"
    assert set(tree(out)) - {"notes.txt"} == set(tree(fresh))
    assert not (out / "compare" / "lut+ec").exists() and (out / "compare" / "lut").is_dir()
    assert (out / "sequence" / "rgb").is_dir() and tree(out / "sequence") == tree(fresh / "sequence")  # same seed
    assert json.loads((out / "demo.json").read_text())["seed"] == 1
    assert f"report: {out / 'compare' / 'report.html'}" in (out / "demo.txt").read_text()
