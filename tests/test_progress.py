"""Progress bars (radiometry.progress): drawn on a terminal only, never into a pipe; ``--no-progress`` on every
command that loops; the bars count events (frames, images), not whatever a redraw happened to print.

A bar is tested by what it counted (``bar.n`` against ``bar.total``, every bar recorded by the ``bars`` fixture
with the arguments it was made with) and by the pipeline's per-frame DEBUG lines; the drawn text only where it
does not depend on timing (the first draw, and the final draw of a bar that stays on screen).
"""

from __future__ import annotations

import io
import logging
import os
import subprocess
import sys
import threading
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

import radiometry.progress as progress
from mapping.cli import cli
from radiometry.progress import progress_bar
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting

REPO = Path(__file__).resolve().parents[1]
BRACKETS = REPO / "data_samples" / "brackets"


class Terminal(io.StringIO):
    """A text stream that says it is a terminal (what a person watching stderr has)."""

    def isatty(self) -> bool:
        return True


class Bars(list):
    """The bars made during a test, as ``(bar, keyword arguments)``, and the terminal they draw on."""

    def __init__(self) -> None:
        super().__init__()
        self.screen = Terminal()


@pytest.fixture
def bars(monkeypatch) -> Bars:
    """Record every bar made through radiometry.progress.progress_bar; bars made for stderr draw on
    ``bars.screen`` instead, a terminal, so that those enabled draw and count."""
    made = Bars()
    real = progress.progress_bar

    def recording(*args, **kwargs):
        bar = real(*args, **{"file": made.screen, **kwargs})
        made.append((bar, kwargs))
        return bar

    monkeypatch.setattr(progress, "progress_bar", recording)
    return made


# ==================================================================================================
# the helper
# ==================================================================================================
@pytest.mark.slow
def test_bar_drawn_on_a_terminal():
    term = Terminal()
    assert list(progress_bar(range(5), desc="things", file=term)) == list(range(5))
    text = term.getvalue()
    # the first draw happens when the bar is made; a bar that stays (leave=True) draws its final state on close
    assert text.startswith("\rthings:   0%") and "0/5" in text and "5/5" in text and "frame/s" in text


@pytest.mark.slow
def test_no_bar_off_a_terminal_or_when_disabled():
    for stream, enabled in ((io.StringIO(), True), (Terminal(), False)):
        bar = progress_bar(total=5, desc="things", file=stream, enabled=enabled)
        bar.update(3)
        bar.set_postfix(skipped=1)
        bar.close()
        assert stream.getvalue() == "" and bar.disable
        assert list(progress_bar(range(5), desc="things", file=stream, enabled=enabled)) == list(range(5))
        assert stream.getvalue() == ""


@pytest.mark.slow
def test_default_stream_is_stderr_at_the_time_of_the_call(monkeypatch, capsys):
    bar = progress_bar(total=2, desc="piped")  # capsys: stderr is not a terminal
    bar.update(2)
    bar.close()
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(sys, "stderr", Terminal())
    bar = progress_bar(total=2, desc="watched")
    bar.update(2)
    bar.close()
    assert "watched" in sys.stderr.getvalue() and "2/2" in sys.stderr.getvalue()


@pytest.mark.slow
def test_a_bar_that_does_not_stay_clears_its_line():
    term = Terminal()
    list(progress_bar(range(3), desc="things", file=term, leave=False))
    text = term.getvalue()
    assert "things" in text and text.endswith("\r") and text.rsplit("\r", 2)[-2].strip() == ""


def test_every_bar_is_made_by_the_helper():
    """tqdm is imported in one place only: every other module takes its bar from radiometry.progress."""
    users = [str(p.relative_to(REPO)) for folder in ("mapping", "radiometry", "scripts") for p in
             sorted((REPO / folder).rglob("*.py")) if "tqdm" in p.read_text(encoding="utf-8")]
    assert users == ["radiometry/progress.py"]


# ==================================================================================================
# the library's loops count what they process
# ==================================================================================================
@pytest.mark.slow
def test_reconstruct_counts_every_frame_and_logs_each(bars, caplog):
    """5 frames, the third without a pose: the bar counts 5 of 5 with 1 skipped, and the pipeline logs one DEBUG
    line per frame, in order, saying what became of it."""
    from mapping.datasets.in_memory import ArrayDataset
    from box_room import box_room_sequence
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct

    ds, _ = box_room_sequence(n_frames=5, width=80, height=60)
    frames = [ds[i] if i != 2 else replace(ds[i], pose=None) for i in range(5)]
    with caplog.at_level(logging.DEBUG, logger="mapping.pipeline"):
        run = reconstruct(ArrayDataset(frames, name="box"), backend=make_backend("tsdf", voxel_size=0.05),
                          poses="gt", progress=True)
    assert [r.fused for r in run.records] == [True, True, False, True, True]
    [(bar, kwargs)] = bars
    assert kwargs["desc"] == "reconstruct box" and bar.total == 5 and bar.n == 5
    assert bar.postfix == "skipped=1" and "reconstruct box" in bars.screen.getvalue()
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("frame ")]
    assert lines == ["frame 1 of 5: fused", "frame 2 of 5: fused", "frame 3 of 5: skipped (no ground-truth pose)",
                     "frame 4 of 5: fused", "frame 5 of 5: fused"]


@pytest.mark.slow
def test_reconstruct_without_progress_draws_nothing(bars):
    from box_room import box_room_sequence
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct

    ds, _ = box_room_sequence(n_frames=2, width=80, height=60)
    reconstruct(ds, backend=make_backend("tsdf", voxel_size=0.05), poses="gt", progress=False)
    [(bar, kwargs)] = bars
    assert kwargs["enabled"] is False and bars.screen.getvalue() == ""


@pytest.mark.slow
def test_compare_has_one_bar_over_every_method(bars, tmp_path):
    """3 frames x 2 methods: one bar, 6 frames counted, the fusions inside draw none of their own."""
    from mapping.compare import compare, make_methods
    from box_room import box_room_sequence

    ds, _ = box_room_sequence(n_frames=3, width=80, height=60)
    compare(ds, make_methods(CameraResponse.gamma(2.2), names=["none", "response"]), output=tmp_path / "cmp",
            voxel_size=0.05, views=0, progress=True)
    drawn = [(bar, kwargs) for bar, kwargs in bars if kwargs["enabled"]]
    assert [kwargs["desc"] for _, kwargs in drawn] == ["compare"]
    assert drawn[0][0].total == 6 and drawn[0][0].n == 6
    assert [kwargs["desc"] for _, kwargs in bars[1:]] == ["reconstruct box-room"] * 2
    assert "compare" in bars.screen.getvalue() and "6/6" in bars.screen.getvalue()  # it stays: its final state


@pytest.mark.slow
def test_simulation_and_calibration_loops_count(bars, tmp_path):
    from mapping.simulation import simulate_room
    from radiometry.response.fit import load_brackets

    simulate_room(tmp_path / "room", seed=1, n_frames=2, width=64, height=48, progress=True)
    images, _, _ = load_brackets(BRACKETS, progress=True)
    load_brackets(BRACKETS, progress=False)
    counted = [(kwargs["desc"], kwargs.get("unit", "frame"), bar.n, bar.total, kwargs["enabled"])
               for bar, kwargs in bars]
    assert counted == [("simulate room", "frame", 2, 2, True), ("reading brackets", "image", 5, 5, True),
                       ("reading brackets", "image", 0, 5, False)]
    assert len(images) == 5


# ==================================================================================================
# the commands: --no-progress everywhere a command loops; nothing drawn into a pipe
# ==================================================================================================
@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, Path]:
    """Tiny inputs for every looping command: a 4-frame room with its true response, a 30-frame paper sweep,
    and three frames with models of their size."""
    from mapping.simulation import simulate_paper, simulate_room

    d = tmp_path_factory.mktemp("inputs")
    room = simulate_room(d / "room", seed=3, n_frames=4, width=160, height=120, progress=False)
    paper = simulate_paper(d / "paper", camera="xtion", seed=2, n_frames=30, width=64, height=48, progress=False,
                           write_depth_images=False)
    frames = d / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(frames / f"frame_{i}.png"), rng.integers(20, 230, (48, 64, 3), dtype=np.uint8))
    CameraResponse.gamma(2.2).save(d / "gamma.npz")
    LUTVignetting(np.full((48, 64, 3), 0.9, np.float32)).save(d / "flat.npz")
    return {"room": room, "room_response": room / "truth" / "response.npz", "paper": paper / "rgb",
            "paper_response": paper / "truth" / "response.npz", "frames": frames, "gamma": d / "gamma.npz",
            "flat": d / "flat.npz"}


COMMANDS = {
    "response": lambda i, out: ["response", BRACKETS, "-o", out / "crf.npz", "--quality", "fast"],
    "vignetting": lambda i, out: ["vignetting", i["paper"], "-r", i["paper_response"], "-o", out / "v.npz",
                                  "--min-samples", "5", "--no-plots"],
    "correct": lambda i, out: ["correct", i["frames"], "-r", i["gamma"], "--vignetting", i["flat"], "-o", out],
    "simulate": lambda i, out: ["simulate", "room", "-o", out / "seq", "--num-frames", "2", "--width", "64",
                                "--height", "48"],
    "reconstruct": lambda i, out: ["reconstruct", i["room"], "-o", out / "run", "--poses", "gt", "--voxel-size",
                                   "0.04"],
    "compare": lambda i, out: ["compare", i["room"], "--response", i["room_response"], "--methods", "response",
                               "--poses", "gt", "--voxel-size", "0.04", "--views", "0", "-o", out / "cmp"],
}


@pytest.mark.slow
@pytest.mark.parametrize("name", list(COMMANDS))
def test_no_progress_on_every_looping_command(name, inputs, bars, tmp_path):
    """Each command that loops accepts --no-progress and then makes every bar disabled; without it, its bar is
    enabled (drawn when stderr is a terminal)."""
    for flag, out in ((["--no-progress"], tmp_path / "quiet"), ([], tmp_path / "default")):
        bars.clear()
        res = CliRunner().invoke(cli, [str(a) for a in COMMANDS[name](inputs, out)] + flag, catch_exceptions=False)
        assert res.exit_code == 0, res.output
        assert bars, f"{name} made no progress bar"
        enabled = [kwargs["enabled"] for _, kwargs in bars]  # (compare's fusions never draw their own)
        assert (not any(enabled)) if flag else any(enabled), [kwargs for _, kwargs in bars]


@pytest.mark.slow
def test_no_progress_on_the_demo(monkeypatch, tmp_path):
    """The demo passes --no-progress to its run (whose loops are the ones above: test_demo.py runs it whole)."""
    import mapping.cli.demo as demo
    from radiometry.errors import RadiomapError

    seen = []

    def run_demo(*args, **kwargs):
        seen.append(kwargs["progress"])
        raise RadiomapError("stopped by the test")

    monkeypatch.setattr(demo, "run_demo", run_demo)
    for flag in (["--no-progress"], []):
        res = CliRunner().invoke(cli, ["demo", "--quick", "-o", str(tmp_path / f"demo{len(flag)}"), *flag])
        assert res.exit_code == 1 and "stopped by the test" in res.stderr
    assert seen == [False, True]


@pytest.mark.slow
def test_piped_100_frame_reconstruction_writes_no_progress(inputs, tmp_path):
    """The real command in a child process whose stderr is a pipe (a log, CI): 100 frames, the default options
    (no --no-progress), and not one redraw reaches the pipe."""
    from test_robustness import tum_copy

    seq = tum_copy(inputs["room"], tmp_path / "seq", list(range(4)) * 25, shared=True)  # 100 frames
    out = subprocess.run([sys.executable, "-m", "mapping.cli", "reconstruct", str(seq), "-o", str(tmp_path / "run"),
                          "--poses", "gt", "--voxel-size", "0.04"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                         text=True, cwd=REPO)
    assert out.returncode == 0, out.stderr
    assert "\r" not in out.stderr and "frame/s" not in out.stderr and "reconstruct" not in out.stderr, out.stderr
    assert "\r" not in out.stdout and "L1 mean" in out.stdout


@pytest.mark.slow
def test_the_same_run_on_a_terminal_draws_a_bar(inputs, tmp_path):
    """The control: with a (pseudo-)terminal as stderr the same command draws its bar (so the test above can fail;
    4 frames are enough to show it)."""
    import fcntl
    import pty
    import struct
    import termios
    import tty

    master, slave = pty.openpty()
    tty.setraw(slave)  # no newline translation: every "\r" read comes from the program
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    chunks: list[bytes] = []

    def drain():  # read while it runs: a full terminal buffer would block the child
        while True:
            try:
                data = os.read(master, 4096)
            except OSError:  # EIO: every writer closed
                return
            if not data:
                return
            chunks.append(data)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    try:
        out = subprocess.run([sys.executable, "-m", "mapping.cli", "reconstruct", str(inputs["room"]), "-o",
                              str(tmp_path / "run"), "--poses", "gt", "--voxel-size", "0.04"],
                             stdout=subprocess.PIPE, stderr=slave, text=True, cwd=REPO)
    finally:
        os.close(slave)
    reader.join(timeout=60)
    os.close(master)
    drawn = b"".join(chunks).decode("utf-8", "replace")
    assert out.returncode == 0, drawn
    assert "\r" in drawn and "reconstruct room" in drawn and "0/4" in drawn and "frame" in drawn
