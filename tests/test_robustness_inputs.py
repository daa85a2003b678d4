"""The robustness catalogue, continued: option values that are plausible to type but physically absurd, runs
that go wrong but used to report success, inputs of the wrong kind, and lists written by other tools.

Each test reproduces a case of issue 13 through the command line (items 4-6) and asserts the one-line error
(exit 1, no traceback, nothing written), or for lists that are merely untidy, the warning and a correct run.
The rules live in ``mapping/validation.py`` (ranges, memory), ``radiometry/quorum.py`` (too little used) and
``radiometry/textlists.py`` (the tolerant list reader).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import shared_path
from test_robustness import error_line, frames, models, paper, room, run, tum_copy  # noqa: F401 (fixtures)

from mapping.validation import (DEPTH_MAX_M, FOV_DEG, VOXEL_SIZE_M, ImplausibleValueError, check_intrinsics,
                                estimate_memory, too_little_fused)
from radiometry.response import CameraResponse


def reconstruct(seq: Path, out: Path, *extra, **env):
    return run("reconstruct", seq, "-o", out, "--poses", "gt", "--no-progress", *extra, **env)


# ==================================================================================================
# item 4: option values that used to crash, hang or eat all memory
# ==================================================================================================
@pytest.mark.parametrize("option, value, fragments", [
    ("--intrinsics", "0,0,0,0", ["--intrinsics", "positive focal lengths", "fx=0"]),          # was a traceback
    ("--intrinsics", "26.25,26.25,79.5,59.5", ["--intrinsics", "143.7 deg", "10..140 deg"]),  # 15.8 GB, segfault
    ("--intrinsics", "1,1,79.5,59.5", ["--intrinsics", "178.6 deg", "fx should be in"]),      # hung
    ("--intrinsics", "131.25,131.25,500,59.5", ["--intrinsics", "principal point"]),
    ("--intrinsics", "131.25,40,79.5,59.5", ["--intrinsics", "fx / fy"]),
    ("--voxel-size", "0.5", ["--voxel-size 0.5 m", "0.001..0.2 m"]),                          # segfault
    ("--voxel-size", "0.6", ["--voxel-size 0.6 m", "0.001..0.2 m"]),                          # hung
    ("--voxel-size", "1", ["--voxel-size 1 m", "0.001..0.2 m"]),                              # traceback
    ("--voxel-size", "1e-5", ["--voxel-size 1e-05 m", "0.001..0.2 m"]),                       # memory without bound
    ("--depth-max", "0.1", ["--depth-max 0.1 m", "0.2..20 m"]),                               # traceback
    ("--depth-max", "1e6", ["--depth-max 1e+06 m", "0.2..20 m"]),                             # memory without bound
    ("--depth-scale", "1e-9", ["--depth-scale 1e-09", "1..100000"]),
])
def test_implausible_option_is_one_line(room, tmp_path, option, value, fragments):
    out = tmp_path / "out"
    error_line(reconstruct(room, out, option, value), *fragments)
    assert not out.exists()  # refused before anything is written


@pytest.mark.slow
def test_truncation_band_wider_than_the_depth_range(room, tmp_path):
    """--voxel-size 0.2 with --depth-max 0.5: the TSDF band (8 voxels, 1.6 m) covers the whole range."""
    out = tmp_path / "out"
    error_line(reconstruct(room, out, "--voxel-size", "0.2", "--depth-max", "0.5"), "truncation band of 1.6 m",
               "--voxel-size below")
    assert not out.exists()


@pytest.mark.slow
def test_compare_validates_the_same_options(room, tmp_path):
    out = tmp_path / "cmp"
    error_line(run("compare", room, "-r", room / "truth" / "response.npz", "--methods", "none", "-o", out,
                   "--voxel-size", "0.6", "--no-progress"), "--voxel-size 0.6 m", "0.001..0.2 m")
    assert not out.exists() or not any(out.iterdir())  # nothing written (the folder lock may have made it)


@pytest.mark.slow
@pytest.mark.parametrize("args, fragments", [
    (["simulate", "paper", "--lensfun", "iphone", "--lens-focal", "-5"], ["--lens-focal -5 mm", "1..2000 mm"]),
    (["simulate", "paper", "--lensfun", "iphone", "--lens-aperture", "0"], ["--lens-aperture 0", "0.7..64"]),
    (["simulate", "paper", "--exposure-time", "1e9"], ["--exposure-time 1e+09 s", "1e-06..60 s"]),
    (["simulate", "room", "--light-change", "1e9"], ["--light-change 1e+09 x", "0.01..100 x"]),
])
def test_simulate_options_out_of_range(tmp_path, args, fragments):
    out = tmp_path / "sim"
    error_line(run(*args, "-o", out, "--frames", "2", "--width", "32", "--height", "24", "--no-progress"), *fragments)
    assert not out.exists()


@pytest.mark.slow
def test_correct_scale_out_of_range(models, frames, tmp_path):
    """--scale 1e30 used to write images that were 100 % clipped."""
    out = tmp_path / "out"
    error_line(run("correct", frames, "-r", models["response.npz"], "--vignetting", models["vignetting.npz"], "-o", out,
                   "--scale", "1e30"), "--scale 1e+30", "0.0001..10000")
    assert not out.exists()


@pytest.mark.slow
def test_vignetting_smooth_sigma_out_of_range(paper, tmp_path):
    """--smooth-sigma 1e9 used to end in an OpenCV traceback (a Gaussian kernel too large)."""
    out = tmp_path / "v.npz"
    error_line(run("vignetting", paper["rgb"], "-r", paper["response"], "-o", out, "--smooth-sigma", "1e9",
                   "--no-progress"), "--smooth-sigma 1e+09 px", "0..50 px")
    assert not out.exists()
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting_lut

    acc = collect_vignetting(paper["rgb"], CameraResponse.load(paper["response"]), progress=False)
    with pytest.raises(ValueError, match="smooth_sigma must be at most 50 pixels, got 1000000000.0"):
        fit_vignetting_lut(acc, smooth_sigma=1e9)


@pytest.mark.slow
def test_library_entry_points_validate_too(room):
    """ReconstructConfig/build_run and make_backend use the same rules: a ValueError for library callers."""
    from mapping.factory import ReconstructConfig, build_run, make_backend

    with pytest.raises(ValueError, match=r"--voxel-size 1 m is outside"):
        make_backend("tsdf", voxel_size=1.0)
    with pytest.raises(ImplausibleValueError, match=r"--depth-max 100 m is outside"):
        build_run(ReconstructConfig(sequence=room, depth_max=100.0, progress=False))
    with pytest.raises(ValueError, match="horizontal field of view of 178.6 deg"):
        check_intrinsics(np.array([[1.0, 0, 79.5], [0, 1.0, 59.5], [0, 0, 1]]), 160, 120)
    lo, hi = FOV_DEG
    assert (lo, hi) == (10.0, 140.0) and VOXEL_SIZE_M == (0.001, 0.2) and DEPTH_MAX_M == (0.2, 20.0)


def test_run_that_cannot_fit_in_memory_is_refused(room, tmp_path):
    """A 1 mm voxel grid of the room (about 12 GiB) on a machine with 2 GiB available: one line, nothing written.
    (RADIOMAP_MEMORY_LIMIT stands for /proc/meminfo's MemAvailable.)"""
    out = tmp_path / "out"
    line = error_line(reconstruct(room, out, "--voxel-size", "0.001", RADIOMAP_MEMORY_LIMIT=str(2 * 2 ** 30)),
                      "GiB", "2.0 GiB are available", "--voxel-size")
    needed = float(line.split("about ")[1].split(" GiB")[0].replace(",", ""))
    assert 5 < needed < 40, line
    assert not out.exists()


@pytest.mark.slow
def test_memory_estimate_against_a_real_run(room, tmp_path):
    """The TSDF estimate is an upper bound of the right order: 1-3x the blocks the run allocates."""
    from mapping.datasets import open_dataset
    from mapping.validation import scene_depth

    out = tmp_path / "out"
    result = reconstruct(room, out, "--voxel-size", "0.005")
    assert result.exit_code == 0, result.output
    used = json.loads((out / "metrics.json").read_text())["map"]["blocks"]
    ds = open_dataset(room)
    est = estimate_memory(backend="tsdf", K=ds.K, width=ds.width, height=ds.height, frames=len(ds), voxel_size=0.005,
                          scene_depth=scene_depth(ds))
    blocks = float(est.detail.split(" voxel blocks")[0].replace(",", ""))
    assert used <= blocks <= 3 * used, (used, est.detail)


# ==================================================================================================
# item 5: runs that went wrong but reported success; inputs of the wrong kind
# ==================================================================================================
@pytest.mark.slow
def test_poses_gt_without_ground_truth(room, tmp_path):
    """Used to fuse 0 of N frames and exit 0 with "status": "complete"."""
    seq = tum_copy(room, tmp_path / "seq")
    (seq / "groundtruth.txt").unlink()
    out = tmp_path / "out"
    error_line(reconstruct(seq, out), "has no ground-truth poses", "--poses icp")
    assert not out.exists()


@pytest.mark.slow
def test_ground_truth_that_is_a_folder(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    (seq / "groundtruth.txt").unlink()
    (seq / "groundtruth.txt").mkdir()
    out = tmp_path / "out"
    error_line(reconstruct(seq, out), "groundtruth.txt: the ground truth is a folder")
    assert not out.exists()


@pytest.mark.slow
def test_run_that_fuses_too_little_fails(room, tmp_path):
    """Ground truth for 1 of 12 frames: 1 fused is below the rule (2 frames and 10 %); exit 1, the results say
    "failed" and keep their RUNNING marker."""
    from mapping.metrics import read_tum_trajectory, write_tum_trajectory

    seq = tum_copy(room, tmp_path / "seq", indices=range(12), shared=True)
    stamps, poses = read_tum_trajectory(seq / "groundtruth.txt")
    write_tum_trajectory(seq / "groundtruth.txt", stamps[:1], poses[:1])
    out = tmp_path / "out"
    error_line(reconstruct(seq, out), "fused 1 of 12 frames", "no ground-truth pose: 11", "at least 2 frames and 10%")
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "failed" and metrics["frames"]["fused"] == 1
    assert (out / "RUNNING").exists() and not (out / "mesh.ply").exists()
    assert too_little_fused(0, 20) and too_little_fused(1, 20) and too_little_fused(9, 100)
    assert not too_little_fused(2, 20) and not too_little_fused(1, 1) and not too_little_fused(10, 100)


def test_reflection_pose_is_refused(tmp_path):
    """A pose with determinant -1 used to be fused mirrored."""
    seq = tmp_path / "seq"
    shutil.copytree(shared_path("rgbd", "open3d_testdata"), seq)
    lines = (seq / "trajectory.log").read_text().splitlines()
    for i in range(1, 4):  # negate the first column of frame 0's rotation
        values = lines[i].split()
        lines[i] = " ".join([str(-float(values[0]))] + values[1:])
    (seq / "trajectory.log").write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    error_line(reconstruct(seq, out, "--depth-max", "4"), "trajectory.log:2", "reflection (determinant -1)")
    assert not out.exists()


@pytest.mark.slow
def test_grey_frame_in_a_colour_sequence(room, tmp_path):
    seq = tum_copy(room, tmp_path / "seq")
    grey = seq / "rgb" / "00002.png"
    cv2.imwrite(str(grey), cv2.cvtColor(cv2.imread(str(grey)), cv2.COLOR_BGR2GRAY))
    out = tmp_path / "out"
    error_line(reconstruct(seq, out), "00002.png", "grey (single-channel) image in a sequence of colour images")
    assert json.loads((out / "metrics.json").read_text())["status"] == "failed" and (out / "RUNNING").exists()


@pytest.mark.slow
def test_lut_given_as_the_polynomial(room, models, tmp_path):
    """compare --vignetting-poly LUT.npz used the LUT under the polynomial's name; then it was a usage error (exit 2,
    three lines) naming the model's internal "source" instead of the file."""
    out = tmp_path / "cmp"
    result = run("compare", room, "-r", models["response.npz"], "--vignetting-poly", models["vignetting.npz"],
                 "--vignetting-lut", models["vignetting.npz"], "-o", out, "--no-progress", "--views", "0")
    error_line(result, f"{models['vignetting.npz']}: --vignetting-poly holds a look-up table (LUT) vignetting model",
               "pass it as --vignetting-lut")
    assert not out.exists()


# ==================================================================================================
# a bare .npy array where a model file is expected; a V array .npy where a vignetting model is
# ==================================================================================================
@pytest.fixture(scope="module")
def v_npy(room) -> Path:
    """The simulator's true V as an array (room/truth/vignetting.npy)."""
    return room / "truth" / "vignetting.npy"


@pytest.mark.slow
@pytest.mark.parametrize("command", ["correct", "reconstruct", "vignetting", "compare"])
def test_bare_npy_given_as_the_response(command, room, paper, v_npy, tmp_path):
    """-r V.npy ended in "TypeError: 'numpy.ndarray' object does not support the context manager protocol"."""
    out = tmp_path / ("v.npz" if command == "vignetting" else "out")
    args = {"correct": ["correct", room / "rgb", "-r", v_npy, "--vignetting", v_npy, "-o", out],
            "reconstruct": ["reconstruct", room, "-r", v_npy, "--poses", "gt", "-o", out, "--no-progress"],
            "vignetting": ["vignetting", paper["rgb"], "-r", v_npy, "-o", out, "--no-progress"],
            "compare": ["compare", room, "-r", v_npy, "--methods", "none,response", "-o", out, "--no-progress"]}
    error_line(run(*args[command]), f"{v_npy}: a bare .npy array, not a radiomap response model file",
               "pass the response .npz that radiomap wrote")
    assert not out.exists()


@pytest.mark.slow
def test_bare_npy_under_a_model_name_given_as_the_vignetting(room, frames, models, tmp_path):
    """A V array saved as v.npz is read as a model file (by its suffix) and refused by name with the way out."""
    disguised = tmp_path / "v.npz"
    with open(disguised, "wb") as fh:
        np.save(fh, np.ones((72, 96, 3), np.float32))
    out = tmp_path / "out"
    error_line(run("correct", frames, "-r", models["response.npz"], "--vignetting", disguised, "-o", out),
               f"{disguised}: a bare .npy array, not a radiomap vignetting model file",
               "a V array is read from a .npy file by reconstruct/correct --vignetting")
    assert not out.exists()


@pytest.mark.slow
def test_correct_takes_a_v_array_npy_as_reconstruct_does(frames, models, tmp_path):
    """correct --vignetting V.npy: the same images as the LUT model holding that V (reconstruct already read it)."""
    from radiometry.vignetting import VignettingModel

    lut = VignettingModel.load(models["vignetting.npz"])
    np.save(tmp_path / "v.npy", lut.evaluate(72, 96))
    for vignetting, out in ((models["vignetting.npz"], tmp_path / "model"), (tmp_path / "v.npy", tmp_path / "array")):
        result = run("correct", frames, "-r", models["response.npz"], "--vignetting", vignetting, "-o", out,
                     "--no-progress")
        assert result.exit_code == 0, result.output
    names = sorted(p.name for p in (tmp_path / "model").glob("*.png"))
    assert names == sorted(p.name for p in (tmp_path / "array").glob("*.png")) and len(names) == 3
    for name in names:
        np.testing.assert_array_equal(cv2.imread(str(tmp_path / "array" / name)),
                                      cv2.imread(str(tmp_path / "model" / name)))
    # the array is V itself: the correction brightened the corners (it did something)
    corrected, raw = cv2.imread(str(tmp_path / "array" / names[0])), cv2.imread(str(frames / names[0]))
    assert corrected[:8, :8].astype(float).mean() > raw[:8, :8].astype(float).mean() + 5


@pytest.mark.slow
def test_sweep_whose_first_frame_has_another_size(paper, models, tmp_path):
    """The accumulator took the first frame's size: 29 good frames were skipped and the model rested on one."""
    sweep = tmp_path / "sweep"
    shutil.copytree(paper["rgb"], sweep)
    first = sorted(sweep.iterdir())[0]
    cv2.imwrite(str(first), cv2.resize(cv2.imread(str(first)), (48, 36)))
    out = tmp_path / "v.npz"
    error_line(run("vignetting", sweep, "-r", paper["response"], "-o", out, "--no-progress"),
               "different sizes (29 at 64x48, 1 at 48x36)", "the first frame's size (48x36) is the rarer")
    assert not out.exists()


@pytest.mark.slow
def test_sweep_with_one_odd_frame_later_is_used_with_a_warning(paper, tmp_path, caplog):
    sweep = tmp_path / "sweep"
    shutil.copytree(paper["rgb"], sweep)
    last = sorted(sweep.iterdir())[-1]
    cv2.imwrite(str(last), cv2.resize(cv2.imread(str(last)), (48, 36)))
    out = tmp_path / "v.npz"
    result = run("vignetting", sweep, "-r", paper["response"], "-o", out, "--no-progress")
    assert result.exit_code == 0, result.output
    assert "skipped 1 frames of another size than the first (29 at 64x48, 1 at 48x36)" in caplog.text
    assert out.exists()


@pytest.mark.slow
def test_vignetting_on_room_frames(room, tmp_path):
    """Ordinary room frames (no sheet) used to give a model: now each plain region is too little brighter than
    its surroundings or too textured, and the sweep is refused."""
    out = tmp_path / "v.npz"
    error_line(run("vignetting", room / "rgb", "-r", room / "truth" / "response.npz", "-o", out, "--no-progress"),
               "the sheet was seen at only", "of the image", "point the camera at an evenly lit white sheet")
    assert not out.exists()


# ==================================================================================================
# item 6: lists written by other tools
# ==================================================================================================
def _stamped_lines(path: Path) -> list[str]:
    return [line for line in path.read_text().splitlines() if line and not line.startswith("#")]


def test_tum_lists_with_bom_crlf_latin1_names_disorder_and_duplicates(room, tmp_path, caplog):
    """rgb.txt with a UTF-8 byte-order mark, CRLF line ends, a Latin-1 file name, lines in reverse time order and
    one line repeated: read, sorted by time, the repeat dropped, a warning with the counts; the run fuses every
    frame in time order. (Before: 'rgb.txt:1: expected 'timestamp filename', got 3 entries ('\\ufeff# ...')'.)"""
    seq = tum_copy(room, tmp_path / "seq", indices=range(6))
    rows = _stamped_lines(seq / "rgb.txt")
    stamp0, name0 = rows[0].split()
    latin = b"rgb/caf\xe9.png"
    (seq / "rgb" / "00000.png").rename(seq.joinpath(latin.decode("utf-8", "surrogateescape")))
    body = [f"{stamp0} ".encode() + latin] + [r.encode() for r in rows[1:]]
    body = body[::-1] + [body[3]]
    (seq / "rgb.txt").write_bytes(b"\xef\xbb\xbf# timestamp filename\r\n" + b"\r\n".join(body) + b"\r\n")
    (seq / "depth.txt").write_bytes(b"\xef\xbb\xbf" + (seq / "depth.txt").read_bytes().replace(b"\n", b"\r\n"))
    out = tmp_path / "out"
    result = reconstruct(seq, out)
    assert result.exit_code == 0, result.output
    assert "1 line(s) are not UTF-8" in caplog.text
    assert "5 line(s) out of time order (sorted by timestamp); 1 line(s) repeating a timestamp (dropped; the " \
           "first line kept); 6 of 7 frames kept" in caplog.text
    frames = (out / "frames.csv").read_text().splitlines()[1:]
    stamps = [float(line.split(",")[1]) for line in frames]
    assert len(stamps) == 6 and stamps == sorted(stamps) and all(line.split(",")[2] == "1" for line in frames)


@pytest.mark.slow
def test_times_file_with_bom_crlf_and_latin1_name(tmp_path, caplog):
    """A bracket image_list.txt saved by a Windows tool: UTF-16 with a byte-order mark, CRLF, and an image whose
    name is not UTF-8; the response is fitted from all five brackets."""
    from test_robustness import BRACKETS

    folder = tmp_path / "b"
    folder.mkdir()
    lines = []
    for i, (name, seconds) in enumerate(line.split()[:2] for line in (BRACKETS / "times.txt").read_text().splitlines()
                                        if line.strip() and not line.startswith("#")):
        target = f"caf\udce9_{i}.png" if i == 2 else name
        shutil.copy(BRACKETS / name, folder / target)
        lines.append(f"{target} {seconds}")
    text = "# name seconds\r\n" + "\r\n".join(lines) + "\r\n"
    (folder / "times.txt").write_bytes(text.encode("utf-8", "surrogateescape"))
    out = tmp_path / "crf.npz"
    result = run("response", folder, "-o", out)
    assert result.exit_code == 0, result.output
    assert out.exists() and "1 line(s) are not UTF-8" in caplog.text
    (folder / "times.txt").write_bytes(b"\xff\xfe" + ("\r\n".join(lines[:2] + lines[3:]) + "\r\n").encode("utf-16-le"))
    (folder / f"caf\udce9_2.png").unlink()
    result = run("response", folder, "-o", tmp_path / "crf16.npz")
    assert result.exit_code == 0, result.output
