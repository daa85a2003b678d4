"""The robustness catalogue (docs/robustness_catalogue.md): one test per row, each through the command line.

Every bad input gives exit code 1, exactly one ``radiomap: error: ...`` line on stderr that names the file
at fault and says how to fix it, and no traceback. Outputs are atomic and calibrations are never replaced
without ``--force``. Faults that root cannot provoke (unreadable files, unwritable folders, a full disk)
are simulated in-process with ``monkeypatch`` (``np.fromfile``, ``os.access``, ``os.replace``, writers
that fail half-way). Data: the embedded bracket sample and tiny simulated sequences, copied and damaged in
``tmp_path``.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.fileio import save_model_file
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting, PolynomialVignetting

REPO = Path(__file__).resolve().parents[1]
BRACKETS = REPO / "data_samples" / "brackets"
VW, VH = 96, 72  # the models' calibration resolution (4:3)
pytestmark = pytest.mark.slow   # every row runs the command end to end (the catalogue; the full suite runs it)


# ==================================================================================================
# helpers
# ==================================================================================================
def run(*args, **env) -> "object":
    """``radiomap ARGS`` in-process (click's CliRunner); exceptions other than SystemExit propagate."""
    result = CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False, env=env or None)
    assert "Traceback" not in result.output
    return result


def error_line(result, *fragments: str, code: int = 1) -> str:
    """The one-line error: exit ``code``, exactly one ``radiomap: error:`` line, last on stderr, containing
    every fragment (the file at fault and the fix); no traceback anywhere."""
    assert result.exit_code == code, (result.exit_code, result.output)
    assert "Traceback" not in result.output
    err = result.stderr
    assert err.count("radiomap: error: ") == 1, err
    line = err[err.index("radiomap: error: "):]
    assert line.endswith("\n") and "\n" not in line[:-1], f"not one line: {line!r}"
    for fragment in fragments:
        assert str(fragment) in line, f"{fragment!r} not in {line!r}"
    return line.strip()


def subprocess_run(*args, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mapping.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` with its bytes (to prove that nothing was touched)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def no_temporaries(folder: Path) -> None:
    leftovers = [p.name for p in folder.rglob(".*") if ".tmp" in p.name]
    assert not leftovers, f"temporary files left behind: {leftovers}"


def enospc(*_args, **_kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


# ==================================================================================================
# data
# ==================================================================================================
@pytest.fixture
def brackets(tmp_path) -> Path:
    """A writable copy of the embedded bracket sample (5 exposures, 160 x 120, times.txt)."""
    folder = tmp_path / "brackets"
    folder.mkdir()
    for name in [f"exposure_{i}.png" for i in range(5)] + ["times.txt"]:
        shutil.copy(BRACKETS / name, folder / name)
    return folder


def _vignetting_lut(width: int = VW, height: int = VH, channels: int = 3) -> LUTVignetting:
    yy, xx = np.mgrid[0:height, 0:width]
    r2 = ((xx - (width - 1) / 2) ** 2 + (yy - (height - 1) / 2) ** 2) / (0.25 * (width ** 2 + height ** 2))
    return LUTVignetting(np.repeat((1 - 0.35 * r2)[:, :, None], channels, axis=2).astype(np.float32))


@pytest.fixture(scope="module")
def models(tmp_path_factory) -> dict[str, Path]:
    """Good models in every format, at 96 x 72: the reference the damaged copies are made from."""
    from radiometry.formats.crf import write_radical_crf
    from radiometry.formats.dso_vignette import write_dso_vignette
    from radiometry.formats.pcalib import write_pcalib
    from radiometry.formats.vgn import write_radical_vgn

    d = tmp_path_factory.mktemp("models")
    response = CameraResponse.gamma(2.2)
    lut = _vignetting_lut()
    poly = PolynomialVignetting([[-0.3, 0.05, -0.01]] * 3, [[(VW - 1) / 2, (VH - 1) / 2]] * 3, (VW, VH))
    paths = {"response.npz": response.save(d / "response.npz"), "vignetting.npz": lut.save(d / "vignetting.npz"),
             "poly.npz": poly.save(d / "poly.npz"), "response.crf": write_radical_crf(d / "response.crf", response),
             "pcalib.txt": write_pcalib(d / "pcalib.txt", response, channel=1),
             "lut.vgn": write_radical_vgn(lut, d / "lut.vgn"), "poly.vgn": write_radical_vgn(poly, d / "poly.vgn"),
             "vignette.png": write_dso_vignette(lut, d / "vignette.png")}
    return paths


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    """Three 96 x 72 colour frames (the models' resolution) for 'radiomap correct'."""
    d = tmp_path_factory.mktemp("frames")
    rng = np.random.default_rng(0)
    for i in range(3):
        cv2.imwrite(str(d / f"frame_{i}.png"), rng.integers(20, 230, (VH, VW, 3), dtype=np.uint8))
    return d


@pytest.fixture(scope="module")
def paper(tmp_path_factory) -> dict[str, Path]:
    """A small simulated white-paper sweep (64 x 48, 30 frames) and its true response."""
    from mapping.simulation.sequences import simulate_paper

    out = simulate_paper(tmp_path_factory.mktemp("paper") / "paper", camera="xtion", seed=2, n_frames=30, width=64,
                         height=48, progress=False, write_depth_images=False)
    return {"rgb": out / "rgb", "response": out / "truth" / "response.npz"}


ROOM_W, ROOM_H, ROOM_FRAMES = 160, 120, 14


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> Path:
    """A simulated RGB-D room (160 x 120, 14 frames, TUM layout with ground truth): ICP tracks it."""
    from mapping.simulation.sequences import simulate_room

    return simulate_room(tmp_path_factory.mktemp("room") / "room", seed=3, n_frames=ROOM_FRAMES, width=ROOM_W,
                         height=ROOM_H, progress=False)


def tum_copy(room: Path, dest: Path, indices=range(4), *, shared: bool = False) -> Path:
    """A plain TUM sequence (no simulator manifest) of the room's frames ``indices`` (repeats allowed: the
    copy gets fresh timestamps 1/30 s apart), with its ground truth and intrinsics. Every listed frame has its
    own image files (a test may overwrite one), unless ``shared``: then repeats list one copy per source frame
    (long sequences at little cost)."""
    from mapping.metrics import read_tum_trajectory, write_tum_trajectory

    rgb = [line.split() for line in (room / "rgb.txt").read_text().splitlines() if line and line[0] != "#"]
    depth = [line.split() for line in (room / "depth.txt").read_text().splitlines() if line and line[0] != "#"]
    stamps, poses = read_tum_trajectory(room / "groundtruth.txt")
    (dest / "rgb").mkdir(parents=True)
    (dest / "depth").mkdir()
    rgb_lines, depth_lines, new_stamps, new_poses = [], [], [], []
    for k, i in enumerate(indices):
        t = 1000.0 + k / 30.0
        name = f"{i if shared else k:05d}.png"
        for kind, rows, lines in (("rgb", rgb, rgb_lines), ("depth", depth, depth_lines)):
            target = dest / kind / name
            if not target.exists():
                shutil.copy(room / rows[i][1], target)
            lines.append(f"{t:.6f} {kind}/{name}")
        new_stamps.append(t)
        new_poses.append(poses[i])
    (dest / "rgb.txt").write_text("# timestamp filename\n" + "\n".join(rgb_lines) + "\n")
    (dest / "depth.txt").write_text("# timestamp filename\n" + "\n".join(depth_lines) + "\n")
    write_tum_trajectory(dest / "groundtruth.txt", np.array(new_stamps), np.array(new_poses))
    shutil.copy(room / "intrinsics.txt", dest / "intrinsics.txt")
    return dest


# Run by interrupt_at_frame in a child process: the real command (mapping.cli.main) with a logging filter on the
# pipeline's per-frame DEBUG line ("frame K of N: ..."). At frame K the filter reports on a pipe and never returns:
# the run is paused for good in the middle of its loop, so SIGINT lands while it runs, whatever the machine's speed.
# (The pause polls rather than blocking in one system call: a signal delivered to another thread, e.g. one of
# Open3D's, is then still seen by the main thread within 50 ms.) Other records pass as without -v.
_PAUSE_AT_FRAME = """
import logging, os, signal, sys, time
ready, frame = int(sys.argv[1]), sys.argv[2]
# Ctrl-C as a terminal delivers it, also where the test runner inherited SIGINT ignored (a shell's background job
# starts with SIGINT ignored, and Python then keeps it ignored: the run would never see the test's signal)
signal.signal(signal.SIGINT, signal.default_int_handler)

def pause(record):
    if record.getMessage().startswith(f"frame {frame} of "):
        os.write(ready, b"paused")
        os.close(ready)
        while True:
            time.sleep(0.05)
    return record.levelno >= logging.WARNING

logger = logging.getLogger("mapping.pipeline")
logger.setLevel(logging.DEBUG)
logger.addFilter(pause)
from mapping.cli import main
sys.exit(main(sys.argv[3:]))
"""


def interrupt_at_frame(frame: int, *args) -> tuple[int, str, str]:
    """``radiomap ARGS`` in a child process, paused once the reconstruction loop has finished frame ``frame``
    (1-based; the first method's loop for compare) and interrupted there with SIGINT: ``(returncode, stdout,
    stderr)``. The run cannot finish before the signal: the test waits for the pause, not for a time. A run
    that ends without reaching the frame fails the test; the child is killed if anything goes wrong."""
    import select

    read_end, write_end = os.pipe()
    proc = subprocess.Popen([sys.executable, "-c", _PAUSE_AT_FRAME, str(write_end), str(frame), *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
                            pass_fds=(write_end,))
    os.close(write_end)  # the child holds the only write end: end-of-file means it exited without pausing
    try:
        # (the limit only ends a hung test: the pause is reached after a few frames of a tiny sequence)
        ready, _, _ = select.select([read_end], [], [], 600)
        paused = os.read(read_end, 16) if ready else b""
        assert paused == b"paused", (f"the run ended or hung before frame {frame}", proc.poll(), paused)
        assert proc.poll() is None
        proc.send_signal(signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=600)
        return proc.returncode, stdout, stderr
    finally:
        os.close(read_end)
        if proc.poll() is None:
            proc.kill()
            proc.communicate()


def reconstruct(seq: Path, out: Path, *extra):
    return run("reconstruct", seq, "-o", out, "--poses", "gt", "--no-progress", *extra)


# ==================================================================================================
# 1. images: missing, unreadable, corrupt, truncated, empty, of different sizes
# ==================================================================================================
def test_bracket_image_missing(brackets, tmp_path):
    (brackets / "exposure_3.png").unlink()
    line = error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), brackets / "times.txt",
                      "exposure_3.png", "fix the names or remove those lines")
    assert "has no such image" in line
    assert not (tmp_path / "crf.npz").exists()


def test_bracket_image_missing_through_the_entry_point(brackets, tmp_path):
    """The same row through ``python -m mapping.cli``: the real process, its stderr and exit status."""
    (brackets / "exposure_3.png").unlink()
    out = subprocess_run("response", brackets, "-o", tmp_path / "crf.npz")
    assert out.returncode == 1 and "Traceback" not in out.stderr
    assert out.stderr.strip().splitlines() == [out.stderr.strip()]
    assert out.stderr.startswith(f"radiomap: error: {brackets / 'times.txt'}: lists exposure_3.png")


def test_bracket_image_unreadable(brackets, tmp_path, monkeypatch):
    """Permission denied (root reads everything, so np.fromfile fails for that one file in-process)."""
    target = brackets / "exposure_2.png"
    fromfile = np.fromfile

    def denied(file, *args, **kwargs):
        if Path(file) == target:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(file))
        return fromfile(file, *args, **kwargs)

    monkeypatch.setattr(np, "fromfile", denied)
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), target, "Permission denied",
               "check the path and its permissions")


def test_bracket_image_corrupt(brackets, tmp_path):
    target = brackets / "exposure_2.png"
    target.write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(64))
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), target, "corrupt", "replace it")


def test_bracket_image_truncated(brackets, tmp_path):
    target = brackets / "exposure_1.png"
    target.write_bytes(target.read_bytes()[:400])
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), target, "truncated", "replace it")


def test_bracket_image_empty(brackets, tmp_path):
    target = brackets / "exposure_4.png"
    target.write_bytes(b"")
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), target, "empty file", "replace it")


def test_bracket_images_of_different_sizes(brackets, tmp_path):
    target = brackets / "exposure_2.png"
    cv2.imwrite(str(target), cv2.resize(cv2.imread(str(target)), (80, 60)))
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), target, "differs from",
               "all brackets must have the same size")


def test_sweep_frame_corrupt(paper, models, tmp_path):
    sweep = tmp_path / "sweep"
    shutil.copytree(paper["rgb"], sweep)
    target = sorted(sweep.iterdir())[7]
    target.write_bytes(target.read_bytes()[:100])
    error_line(run("vignetting", sweep, "-r", paper["response"], "-o", tmp_path / "v.npz"), target, "replace it")
    assert not (tmp_path / "v.npz").exists()


def test_sequence_image_corrupt(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    target = seq / "rgb" / "00002.png"
    target.write_bytes(b"not an image at all")
    line = error_line(reconstruct(seq, tmp_path / "run"), target, "replace it")
    assert "frame 2" in line
    assert (tmp_path / "run" / "RUNNING").is_file()  # the folder of the failed run is marked incomplete
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["status"] == "failed"


def test_sequence_image_missing(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    target = seq / "depth" / "00001.png"
    target.unlink()
    error_line(reconstruct(seq, tmp_path / "run"), target, "no such depth image", "check the path")


def test_sequence_colour_and_depth_of_different_sizes(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    target = seq / "depth" / "00000.png"
    depth = cv2.imread(str(target), cv2.IMREAD_UNCHANGED)
    cv2.imwrite(str(target), cv2.resize(depth, (ROOM_W // 2, ROOM_H // 2), interpolation=cv2.INTER_NEAREST))
    error_line(reconstruct(seq, tmp_path / "run"), seq / "rgb" / "00000.png", target, "80x60",
               "resize or register them first")
    assert not (tmp_path / "run").exists()  # refused before the results folder is made


def _suggested_scale(line: str) -> float:
    return float(line.split("e.g. --depth-scale ")[1].split(")")[0])


def _median_raw_depth(seq: Path) -> float:
    raw = cv2.imread(str(seq / "depth" / "00000.png"), cv2.IMREAD_UNCHANGED)
    return float(np.median(raw[raw > 0]))


def test_sequence_depth_in_the_wrong_unit(room, tmp_path):
    """Depth read with scale 1 (raw units taken as metres): the median is implausible; the suggested
    --depth-scale gives the scene a typical indoor depth (the simulator writes 5000 units per metre)."""
    seq = tum_copy(room, tmp_path / "seq")
    line = error_line(reconstruct(seq, tmp_path / "run", "--depth-scale", "1"), seq / "depth" / "00000.png",
                      "median depth", "with depth scale 1 is implausible", "pass the right --depth-scale")
    assert 0.5 < _median_raw_depth(seq) / _suggested_scale(line) < 5.0
    assert not (tmp_path / "run").exists()


def test_sequence_depth_in_an_unusual_unit(room, tmp_path):
    """Depth written at 50 units per metre but read as TUM (5000): the median (3 cm) is implausible; the
    suggestion puts it at a plausible indoor depth."""
    seq = tum_copy(room, tmp_path / "seq", indices=range(2))
    for path in (seq / "depth").iterdir():
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
        cv2.imwrite(str(path), np.rint(raw / 100).astype(np.uint16))  # 5000 -> 50 units per metre
    line = error_line(reconstruct(seq, tmp_path / "run"), seq / "depth" / "00000.png", "with depth scale 5000",
                      "is implausible", "pass the right --depth-scale")
    assert 0.5 < _median_raw_depth(seq) / _suggested_scale(line) < 5.0


# ==================================================================================================
# 2. empty sequences and selections
# ==================================================================================================
def test_sequence_empty(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    (seq / "rgb.txt").write_text("# timestamp filename\n")
    error_line(reconstruct(seq, tmp_path / "run"), seq / "rgb.txt", "lists no frames", "the sequence is empty",
               "; list one 'timestamp filename' line per colour image, or pass a complete sequence folder")


def test_sequence_frame_selection_empty(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    error_line(reconstruct(seq, tmp_path / "run", "--frames", "50:60"), seq, "leaves no frames", "widen --frames")


def test_sequence_folder_of_unknown_layout(tmp_path):
    (tmp_path / "seq").mkdir()
    (tmp_path / "seq" / "notes.txt").write_text("nothing here\n")
    error_line(reconstruct(tmp_path / "seq", tmp_path / "run"), tmp_path / "seq", "unknown RGB-D layout",
               "pass --format")


def test_sweep_folder_empty(paper, tmp_path):
    (tmp_path / "empty").mkdir()
    error_line(run("vignetting", tmp_path / "empty", "-r", paper["response"], "-o", tmp_path / "v.npz"),
               tmp_path / "empty", "no images", "check the folder")


def test_correct_folder_empty(models, tmp_path):
    (tmp_path / "empty").mkdir()
    error_line(run("correct", tmp_path / "empty", "-r", models["response.npz"],
                   "--vignetting", models["vignetting.npz"],
                   "-o", tmp_path / "out"), tmp_path / "empty", "no images", "check the folder")


# ==================================================================================================
# 3. exposure-time lists that do not match the images
# ==================================================================================================
@pytest.mark.parametrize("change, fragments", [
    (lambda t: t + "exposure_5.png 1.024\n", ["exposure_5.png", "has no such image", "remove those lines"]),
    (lambda t: t.replace("exposure_4.png 0.256\n", ""), ["does not list exposure_4.png", "add a line"]),
    (lambda t: t.replace("0.016", "fast"), [":4:", "'fast' is not a number of seconds", "write e.g."]),
    (lambda t: t.replace("0.016", "-0.016"), [":4:", "must be positive seconds, got '-0.016'",
                                               "; write exposure_2.png's exposure time in seconds, e.g. "
                                               "'exposure_2.png 0.004' or 'exposure_2.png 1/250'"]),
    (lambda t: t.replace("0.016", "1/0"), [":4:", "not a number of seconds"]),
    (lambda t: t + "exposure_1.png 0.004\n", ["listed twice", "keep one line per image"]),
    (lambda t: t.replace("exposure_2.png 0.016", "exposure_2.png"), [":4:", "expected 'image_name seconds'"]),
    (lambda t: "# nothing\n", ["no 'image_name seconds' lines", "list every bracket image"]),
], ids=["extra-line", "image-not-listed", "not-a-number", "negative", "division-by-zero", "duplicate",
        "missing-column", "no-lines"])
def test_times_file_does_not_match(brackets, tmp_path, change, fragments):
    times = brackets / "times.txt"
    times.write_text(change(times.read_text()))
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), times, *fragments)


def test_times_file_absent(brackets, tmp_path):
    (brackets / "times.txt").unlink()
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), brackets, "no times.txt or image_list.txt",
               "pass --times FILE")


def test_times_all_equal(brackets, tmp_path):
    times = brackets / "times.txt"
    times.write_text("\n".join(f"exposure_{i}.png 0.016" for i in range(5)) + "\n")
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), brackets, "times.txt",
               "at least two different exposure times",
               "; give each image its own exposure time, and capture the bracket at two or more different exposures")


# ==================================================================================================
# 4. broken calibration files: NaN, inf, non-monotone, wrong shape, wrong kind, corrupt; every format
# ==================================================================================================
def _table(kind: str) -> np.ndarray:
    table = np.repeat(((np.arange(256) / 255.0) ** 2.2)[:, None], 3, axis=1)
    if kind == "nan":
        table[100, 1] = np.nan
    elif kind == "inf":
        table[200, 0] = np.inf
    elif kind == "non-monotone":
        table[120:130] = table[120:130][::-1]
    return table


def _crf_bytes(table: np.ndarray, rows: int = 256) -> bytes:
    from radiometry.formats.crf import MAGIC

    return struct.pack("<5I", MAGIC, 21, 2, rows, 1) + table[:rows, ::-1].astype("<f4").tobytes()


def _vgn_lut_bytes(lut: np.ndarray) -> bytes:
    return b"NonparametricVignettingModel\n" + struct.pack("<5I", 0xC4A1FDD9, 21, 2, *lut.shape[:2]) \
        + lut[:, :, ::-1].astype("<f4").tobytes()


def make_bad_response(kind: str, d: Path, models: dict[str, Path]) -> Path:
    fmt, defect = kind.split(":")
    if fmt == "npz":
        path = d / "response.npz"
        if defect in ("nan", "inf", "non-monotone"):
            save_model_file(path, "response", {"inverse_table": _table(defect)})
        elif defect == "wrong-shape":
            save_model_file(path, "response", {"inverse_table": _table("ok")[:255]})
        elif defect == "wrong-kind":
            shutil.copy(models["vignetting.npz"], path)
        elif defect == "truncated":
            path.write_bytes(models["response.npz"].read_bytes()[:300])
    elif fmt == "crf":
        path = d / "response.crf"
        if defect == "truncated":
            path.write_bytes(models["response.crf"].read_bytes()[:1000])
        elif defect == "wrong-shape":
            path.write_bytes(_crf_bytes(_table("ok"), rows=128))
        else:
            path.write_bytes(_crf_bytes(_table(defect)))
    else:
        path = d / "pcalib.txt"
        values = models["pcalib.txt"].read_text().split()
        if defect == "nan":
            values[50] = "nan"
        elif defect == "non-monotone":  # a dip too deep to repair (small ones are: test_pcalib_repair.py)
            values[61] = values[20]
        elif defect == "wrong-shape":
            values = values[:255]
        path.write_text(" ".join(values) + "\n")
        if defect == "binary":
            path.write_bytes(os.urandom(300) + b"\xff\xfe")
    return path


RESPONSE_DEFECTS = {
    "npz:nan": ["contains NaN or infinite values", "re-create the response"],
    "npz:inf": ["contains NaN or infinite values", "re-create the response"],
    "npz:non-monotone": ["not strictly increasing", "re-calibrate or repair it"],
    "npz:wrong-shape": ["got shape (255, 3)", "re-create the response"],
    "npz:wrong-kind": ["holds a 'vignetting' model where a 'response' model is needed", "pass the right file"],
    "npz:truncated": ["not a radiomap response file or corrupt", "re-create it"],
    "crf:nan": ["contains NaN or infinite values", "re-create it"],
    "crf:inf": ["contains NaN or infinite values", "re-create it"],
    "crf:non-monotone": ["decreases at level", "re-create it"],
    "crf:wrong-shape": ["128 x 1 matrix", "a response has 256 levels"],
    "crf:truncated": ["truncated", "re-create it"],
    "pcalib:nan": ["'nan', not a finite number", "256 strictly increasing"],
    "pcalib:non-monotone": ["not strictly increasing at level 61", "256 strictly increasing"],
    "pcalib:wrong-shape": ["found 255 numbers", "expected 256"],
    "pcalib:binary": ["not a text file", "256 strictly increasing"],
}


@pytest.mark.parametrize("kind", sorted(RESPONSE_DEFECTS))
def test_bad_response_file(kind, models, frames, tmp_path):
    path = make_bad_response(kind, tmp_path, models)
    error_line(run("correct", frames, "-r", path, "--vignetting", models["vignetting.npz"], "-o", tmp_path / "out"),
               path, *RESPONSE_DEFECTS[kind])
    assert not (tmp_path / "out").exists()  # models are checked before any output is made


def make_bad_vignetting(kind: str, d: Path, models: dict[str, Path]) -> Path:
    fmt, defect = kind.split(":")
    lut = _vignetting_lut().lut.copy()
    meta = {"model": "lut", "resolution": [VW, VH]}
    if fmt == "npz":
        path = d / "vignetting.npz"
        if defect == "poly-nan":
            save_model_file(path, "vignetting", {"coefficients": np.array([[np.nan, 0, 0]] * 3),
                                                 "centres": np.array([[47.5, 35.5]] * 3)},
                            {"model": "polynomial", "resolution": [VW, VH]})
            return path
        if defect == "wrong-shape":
            meta["resolution"] = [VW, VH + 8]
        elif defect == "truncated":
            path.write_bytes(models["vignetting.npz"].read_bytes()[:500])
            return path
        else:
            lut[10, 20, 1] = {"nan": np.nan, "inf": np.inf, "zero": 0.0, "negative": -0.5}[defect]
        save_model_file(path, "vignetting", {"lut": lut}, meta)
    elif fmt == "vgn":
        path = d / "vignetting.vgn"
        if defect == "truncated":
            path.write_bytes(models["lut.vgn"].read_bytes()[:2000])
        elif defect == "poly-degree":
            data = models["poly.vgn"].read_bytes()
            path.write_bytes(data.replace(b"PolynomialVignettingModel 3", b"PolynomialVignettingModel 2", 1))
        else:
            lut[5, 5, 2] = {"nan": np.nan, "zero": 0.0}[defect]
            path.write_bytes(_vgn_lut_bytes(lut))
    else:
        path = d / "vignette.png"
        if defect == "zero":
            img = cv2.imread(str(models["vignette.png"]), cv2.IMREAD_UNCHANGED)
            img[0, :5] = 0
            cv2.imwrite(str(path), img)
        elif defect == "colour":
            cv2.imwrite(str(path), np.full((VH, VW, 3), 60000, np.uint16))
        elif defect == "truncated":
            path.write_bytes(models["vignette.png"].read_bytes()[:200])
        else:
            path.write_bytes(b"\x89PNG\r\n\x1a\n" + os.urandom(200))
    return path


VIGNETTING_DEFECTS = {
    "npz:nan": ["contains NaN or infinite values", "re-create the file"],
    "npz:inf": ["contains NaN or infinite values", "re-create the file"],
    "npz:zero": ["strictly positive", "re-create the file"],
    "npz:negative": ["strictly positive", "re-create the file"],
    "npz:wrong-shape": ["disagrees with the resolution", "re-create the file"],
    "npz:poly-nan": ["coefficients contains NaN", "re-create the file"],
    "npz:truncated": ["not a radiomap vignetting file or corrupt", "re-create it"],
    "vgn:nan": ["contains NaN or infinite values", "re-calibrate or re-export it"],
    "vgn:zero": ["strictly positive", "re-calibrate or re-export it"],
    "vgn:truncated": ["truncated", "re-export the model"],
    "vgn:poly-degree": ["polynomial of degree 2", "use degree 3",
                        "; re-export a degree-3 model from radical or re-calibrate with 'radiomap vignetting --model "
                        "poly'"],
    "png:zero": ["5 pixels are 0", "re-export the vignette with V > 0 everywhere"],
    "png:colour": ["has 3 channels", "single-channel (grayscale) 16-bit PNG"],
    "png:truncated": ["corrupt or truncated", "re-export the DSO vignette"],
    "png:corrupt": ["corrupt", "re-export the DSO vignette"],
}


@pytest.mark.parametrize("kind", sorted(VIGNETTING_DEFECTS))
def test_bad_vignetting_file(kind, models, frames, tmp_path):
    path = make_bad_vignetting(kind, tmp_path, models)
    error_line(run("correct", frames, "-r", models["response.npz"], "--vignetting", path, "-o", tmp_path / "out"),
               path, *VIGNETTING_DEFECTS[kind])
    assert not (tmp_path / "out").exists()


def test_bad_response_file_for_vignetting_calibration(paper, models, tmp_path):
    """'radiomap vignetting' checks its response before it reads a single frame."""
    path = make_bad_response("crf:nan", tmp_path, models)
    error_line(run("vignetting", paper["rgb"], "-r", path, "-o", tmp_path / "v.npz"), path,
               "contains NaN or infinite values")


def test_bad_response_file_for_reconstruction(room, models, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    path = make_bad_response("pcalib:non-monotone", tmp_path, models)
    error_line(reconstruct(seq, tmp_path / "run", "-r", path), path, "not strictly increasing")
    assert not (tmp_path / "run").exists()


def test_bad_vignetting_array_for_reconstruction(room, models, tmp_path):
    """--vignetting also takes a V array (.npy, a simulator's truth): NaN in it is a one-line error."""
    seq = tum_copy(room, tmp_path / "seq")
    V = np.ones((ROOM_H, ROOM_W, 3), np.float32)
    V[3, 4] = np.nan
    path = tmp_path / "vignetting.npy"
    np.save(path, V)
    error_line(reconstruct(seq, tmp_path / "run", "-r", models["response.npz"], "--vignetting", path), path, "NaN")
    assert not (tmp_path / "run").exists()


# ==================================================================================================
# 5. a model that does not fit the images (resolution, aspect ratio, channels)
# ==================================================================================================
def test_model_of_another_aspect_ratio(models, tmp_path):
    (tmp_path / "square").mkdir()
    image = tmp_path / "square" / "a.png"
    cv2.imwrite(str(image), np.full((64, 64, 3), 100, np.uint8))
    error_line(run("correct", tmp_path / "square", "-r", models["response.npz"],
                   "--vignetting", models["vignetting.npz"],
                   "-o", tmp_path / "out"), image, models["vignetting.npz"], "calibrated at 96x72", "64x64",
               "calibrate vignetting at this resolution")


def test_model_of_another_resolution_same_aspect_is_fine(models, tmp_path):
    """Not an error: a 96 x 72 model serves 48 x 36 images (resampled), exit 0."""
    (tmp_path / "half").mkdir()
    cv2.imwrite(str(tmp_path / "half" / "a.png"), np.full((36, 48, 3), 100, np.uint8))
    result = run("correct", tmp_path / "half", "-r", models["response.npz"], "--vignetting", models["vignetting.npz"],
                 "-o", tmp_path / "out")
    assert result.exit_code == 0, result.output
    corrected = cv2.imread(str(tmp_path / "out" / "a.png"))
    assert corrected[0, 0, 0] > corrected[18, 24, 0]  # the corners are brightened


def test_colour_model_on_grayscale_images(models, tmp_path):
    (tmp_path / "grey").mkdir()
    image = tmp_path / "grey" / "a.png"
    cv2.imwrite(str(image), np.full((VH, VW), 100, np.uint8))
    error_line(run("correct", tmp_path / "grey", "-r", models["response.npz"], "--vignetting", models["vignetting.npz"],
                   "-o", tmp_path / "out"), image, models["response.npz"], "channels", "grayscale")


def test_model_of_another_aspect_ratio_for_reconstruction(room, models, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    square = _vignetting_lut(64, 64).save(tmp_path / "square.npz")
    line = error_line(reconstruct(seq, tmp_path / "run", "-r", models["response.npz"], "--vignetting", square), square,
                      "aspect", "calibrate vignetting at this resolution")
    assert "160x120" in line
    assert not (tmp_path / "run").exists()  # refused before the results folder is made



# ==================================================================================================
# 6. calibration data that cannot calibrate: saturated, no sheet
# ==================================================================================================
def test_sweep_all_saturated(tmp_path, paper):
    from mapping.simulation.sequences import simulate_paper

    out = simulate_paper(tmp_path / "bright", camera="xtion", seed=2, n_frames=4, width=64, height=48,
                         exposure_time=1.0, progress=False, write_depth_images=False)
    error_line(run("vignetting", out / "rgb", "-r", paper["response"], "-o", tmp_path / "v.npz"), out / "rgb",
               "saturated", "lower the exposure time")
    assert not (tmp_path / "v.npz").exists()


def test_sweep_without_a_sheet(tmp_path, paper):
    """A dark recording (lens cap, lights off): nothing bright enough to be the sheet in any frame."""
    folder = tmp_path / "dark"
    folder.mkdir()
    rng = np.random.default_rng(1)
    for i in range(4):
        cv2.imwrite(str(folder / f"{i}.png"), rng.integers(0, 12, (48, 64, 3), dtype=np.uint8))
    error_line(run("vignetting", folder, "-r", paper["response"], "-o", tmp_path / "v.npz"), folder,
               "no white sheet found", "point the camera at an evenly lit white sheet")


def test_brackets_all_saturated(brackets, tmp_path):
    for i in range(5):
        cv2.imwrite(str(brackets / f"exposure_{i}.png"), np.full((120, 160, 3), 255, np.uint8))
    error_line(run("response", brackets, "-o", tmp_path / "crf.npz"), brackets, "saturated")
    assert not (tmp_path / "crf.npz").exists()
