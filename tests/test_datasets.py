"""Dataset loaders: Redwood/Open3D, TUM, 7-Scenes and simulated layouts; pairing, errors, laziness."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_path

from mapping.datasets import FORMATS, detect_format, open_dataset
from mapping.datasets._common import parse_intrinsics
from mapping.datasets.base import RGBDDataset, RGBDFrame
from mapping.datasets.redwood import read_log_trajectory, write_log_trajectory
from mapping.datasets.in_memory import ArrayDataset
from mapping.metrics import associate_timestamps, write_tum_trajectory
from radiometry.errors import DatasetError
from radiometry.images import write_depth, write_image

OPEN3D = ("rgbd", "open3d_testdata")
KITCHEN = ("rgbd", "redkitchen_7scenes_000-099")


# --------------------------------------------------------------------------------------------------
# association by nearest timestamp
# --------------------------------------------------------------------------------------------------
def test_associate_pairs_nearest_within_max_difference():
    rgb = np.arange(10) / 30.0
    jitter = np.array([0.004, -0.007, 0.008, 0.0, 0.006, 0.0, 0.001, 0.003, 0.0, -0.002])
    keep = np.array([0, 1, 2, 3, 4, 6, 7, 9])          # no depth near colour frames 5 and 8 (>= 25 ms)
    depth = (rgb + jitter)[keep]
    ia, ib = associate_timestamps(rgb, depth, max_difference=0.02)
    assert ia.tolist() == keep.tolist()
    assert ib.tolist() == list(range(len(keep)))
    assert np.all(np.abs(rgb[ia] - depth[ib]) <= 0.02)
    # a tighter maximum difference drops the frames whose depth is 7-8 ms away
    ia, _ = associate_timestamps(rgb, depth, max_difference=0.005)
    assert ia.tolist() == [0, 3, 6, 7, 9]


def test_associate_is_one_to_one_and_order_free():
    rgb = np.array([1.00, 1.01, 2.0])
    depth = np.array([2.004, 1.006])          # unsorted; both 1.00 and 1.01 want 1.006
    ia, ib = associate_timestamps(rgb, depth, max_difference=0.02)
    assert ia.tolist() == [1, 2]               # 1.01 is closer to 1.006 than 1.00 is
    assert ib.tolist() == [1, 0]
    assert associate_timestamps([], depth)[0].size == 0
    with pytest.raises(ValueError, match="max_difference"):
        associate_timestamps(rgb, depth, max_difference=-1)


# --------------------------------------------------------------------------------------------------
# Redwood / Open3D layout
# --------------------------------------------------------------------------------------------------
def test_redwood_open3d_testdata():
    root = shared_path(*OPEN3D)
    assert detect_format(root) == "redwood"
    ds = open_dataset(root)
    assert isinstance(ds, RGBDDataset)
    assert len(ds) == 5 and (ds.width, ds.height) == (640, 480)
    np.testing.assert_allclose(ds.K, [[525, 0, 319.5], [0, 525, 239.5], [0, 0, 1]])  # camera_primesense.json
    f = ds[2]
    assert isinstance(f, RGBDFrame)
    assert f.rgb.dtype == np.uint8 and f.rgb.shape == (480, 640, 3)
    assert f.depth.dtype == np.float32 and f.depth.shape == (480, 640)
    valid = f.depth[f.depth > 0]
    assert 0.5 < np.median(valid) < 4.0                       # millimetres / 1000 -> metres
    assert f.index == 2 and f.timestamp == pytest.approx(2 / 30)
    # trajectory.log: the 4 x 4 after the first 'id id n' line is frame 0's pose
    lines = (root / "trajectory.log").read_text().splitlines()
    np.testing.assert_allclose(ds[0].pose, np.loadtxt(lines[1:5]))
    assert ds[0].pose[0, 3] == pytest.approx(-0.31058, abs=1e-5)
    stamps, poses = ds.ground_truth()
    assert poses.shape == (5, 4, 4) and stamps.tolist() == pytest.approx([i / 30 for i in range(5)])
    strided = open_dataset(root, frames=slice(1, None, 2))
    assert [strided[i].index for i in range(len(strided))] == [1, 3]


def test_redwood_log_round_trip_and_malformed(tmp_path):
    poses = [np.eye(4), np.array([[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1.0]])]
    path = write_log_trajectory(tmp_path / "t.log", poses)
    back = read_log_trajectory(path)
    assert sorted(back) == [0, 1]
    np.testing.assert_allclose(back[1], poses[1])
    bad = tmp_path / "bad.log"
    bad.write_text("0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 x\n0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"bad\.log:4: not numbers"):
        read_log_trajectory(bad)
    bad.write_text("0 0 1\n1 0 0 0\n0 1 0 0\n")
    with pytest.raises(DatasetError, match=r"bad\.log:1: incomplete block"):
        read_log_trajectory(bad)
    bad.write_text("0 0 1\n2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DatasetError, match="not a rigid"):
        read_log_trajectory(bad)


# --------------------------------------------------------------------------------------------------
# TUM layout: the real fr1 frame of other_formats/ in a tiny TUM folder
# --------------------------------------------------------------------------------------------------
def _tum_folder(tmp_path: Path, *, stamps_rgb, stamps_depth, gt: str | None = None) -> Path:
    src = shared_path(*OPEN3D, "other_formats")
    root = tmp_path / "rgbd_dataset_freiburg1_test"
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    rgb_lines, depth_lines = ["# colour images"], ["# depth maps"]
    for t in stamps_rgb:
        shutil.copy(src / "TUM_color.png", root / "rgb" / f"{t:.6f}.png")
        rgb_lines.append(f"{t:.6f} rgb/{t:.6f}.png")
    for t in stamps_depth:
        shutil.copy(src / "TUM_depth.png", root / "depth" / f"{t:.6f}.png")
        depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt is not None:
        (root / "groundtruth.txt").write_text(gt)
    return root


def test_tum_single_real_frame(tmp_path):
    root = _tum_folder(tmp_path, stamps_rgb=[100.0], stamps_depth=[100.012],
                       gt="# timestamp tx ty tz qx qy qz qw\n99.99 1 2 3 0 0 0 1\n100.01 1.2 2 3 0 0 0 1\n")
    assert detect_format(root) == "tum"
    ds = open_dataset(root)
    assert len(ds) == 1 and ds.depth_scale == 5000
    np.testing.assert_allclose(ds.K[[0, 1, 0, 1], [0, 1, 2, 2]], [517.3, 516.5, 318.6, 255.3])  # freiburg1
    f = ds[0]
    assert f.rgb.shape == (480, 640, 3) and f.depth.dtype == np.float32
    assert 0.5 < np.median(f.depth[f.depth > 0]) < 5.0
    # ground truth interpolated at t = 100.0, halfway between the two samples
    np.testing.assert_allclose(f.pose[:3, 3], [1.1, 2, 3], atol=1e-9)
    # wrong depth scale: the median depth becomes implausible and the error names the option
    with pytest.raises(DatasetError, match=r"--depth-scale.*5000"):
        open_dataset(root, depth_scale=50)


def test_tum_pairing_drops_unmatched_frames(tmp_path):
    root = _tum_folder(tmp_path, stamps_rgb=[1.0, 1.0333, 1.0667], stamps_depth=[1.005, 1.0700])
    ds = open_dataset(root)
    assert len(ds) == 2 and ds.timestamps.tolist() == [1.0, 1.0667]
    assert ds.pairing["paired"] == 2 and ds.pairing["colour_frames"] == 3
    assert ds.ground_truth() is None
    with pytest.raises(DatasetError, match="no colour frame has a depth frame"):
        open_dataset(_tum_folder(tmp_path / "far", stamps_rgb=[1.0], stamps_depth=[1.5]))


@pytest.mark.parametrize("name, text, match", [
    ("rgb.txt", "# header\n1.0 rgb/1.000000.png\n1.1 rgb/x.png extra\n", r"rgb\.txt:3: expected 'timestamp filename'"),
    ("rgb.txt", "abc rgb/1.000000.png\n", r"rgb\.txt:1: timestamp 'abc' is not a number"),
    ("groundtruth.txt", "1.0 0 0 0 0 0 1\n", r"groundtruth\.txt:1: TUM trajectory files must have 8 entries"),
    ("groundtruth.txt", "1.0 0 0 0 0 0 0 5\n", r"groundtruth\.txt:1: quaternion"),
])
def test_tum_malformed_lists_name_file_and_line(tmp_path, name, text, match):
    root = _tum_folder(tmp_path, stamps_rgb=[1.0], stamps_depth=[1.0])
    (root / name).write_text(text)
    with pytest.raises(DatasetError, match=match):
        open_dataset(root)


def test_empty_sequence_and_unknown_layout(tmp_path):
    root = _tum_folder(tmp_path, stamps_rgb=[1.0], stamps_depth=[1.0])
    (root / "rgb.txt").write_text("# nothing here\n")
    with pytest.raises(DatasetError, match="lists no frames"):
        open_dataset(root)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(DatasetError, match=r"unknown RGB-D layout.*--format"):
        open_dataset(empty)
    with pytest.raises(DatasetError, match="no such sequence folder"):
        open_dataset(tmp_path / "missing")
    with pytest.raises(ValueError, match="format must be one of"):
        open_dataset(root, format="kinectfusion")
    with pytest.raises(DatasetError, match="leaves no frames"):
        open_dataset(_tum_folder(tmp_path / "one", stamps_rgb=[1.0], stamps_depth=[1.0]), frames=slice(5, None))


def test_colour_and_depth_of_different_sizes(tmp_path):
    root = tmp_path / "seq"
    write_image(root / "color" / "000.png", np.zeros((480, 640, 3), np.uint8))
    write_depth(root / "depth" / "000.png", np.ones((240, 320), np.float32), 1000)
    with pytest.raises(DatasetError, match=r"640x480.*320x240.*registered"):
        open_dataset(root)


def test_frames_are_loaded_lazily(monkeypatch):
    root = shared_path(*KITCHEN)
    import mapping.datasets._common as common

    calls = []
    real = common.read_rgb
    monkeypatch.setattr(common, "read_rgb", lambda p: calls.append(Path(p).name) or real(p))
    ds = open_dataset(root)
    assert len(ds) == 100 and len(calls) == 1       # opening reads the first frame only (to check it)
    ds[57]
    assert calls[-1] == "frame-000057.color.jpg" and len(calls) == 2


# --------------------------------------------------------------------------------------------------
# 7-Scenes
# --------------------------------------------------------------------------------------------------
def test_sevenscenes_sample():
    root = shared_path(*KITCHEN)
    assert detect_format(root) == "7scenes"
    ds = open_dataset(root, frames=slice(0, 10, 2))
    assert len(ds) == 5 and [ds[i].index for i in range(5)] == [0, 2, 4, 6, 8]
    np.testing.assert_allclose(ds.K, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    f = ds[1]
    assert f.name == "frame-000002" and f.timestamp == pytest.approx(2 / 30)
    expected = np.loadtxt(root / "frames" / "frame-000002.pose.txt")
    np.testing.assert_allclose(f.pose, expected)
    assert f.depth.max() < 10 and 0.5 < np.median(f.depth[f.depth > 0]) < 4
    stamps, poses = ds.ground_truth()
    assert poses.shape == (5, 4, 4)


def test_sevenscenes_malformed_pose(tmp_path):
    src = shared_path(*KITCHEN, "frames")
    root = tmp_path / "seq"
    root.mkdir()
    for suffix in ("color.jpg", "depth.png"):
        shutil.copy(src / f"frame-000000.{suffix}", root / f"frame-000000.{suffix}")
    (root / "frame-000000.pose.txt").write_text("1 0 0 0\n0 1 0\n0 0 1 0\n0 0 0 1\n")
    with pytest.raises(DatasetError, match=r"frame-000000\.pose\.txt:2: 3 values"):
        open_dataset(root)  # the first frame is read (and checked) on opening
    (root / "frame-000000.pose.txt").write_text("inf 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    ds = open_dataset(root)
    assert ds[0].pose is None and ds.ground_truth() is None   # lost KinectFusion frames carry inf


def test_sevenscenes_reads_its_intrinsics_file(tmp_path):
    """camera-intrinsics.txt beside frames/ is really read (not the 7-Scenes default 585, 585, 320, 240)."""
    shared = shared_path(*KITCHEN)
    root = tmp_path / "seq"
    (root / "frames").mkdir(parents=True)
    for i in range(2):
        for suffix in ("color.jpg", "depth.png", "pose.txt"):
            shutil.copy(shared / "frames" / f"frame-{i:06d}.{suffix}", root / "frames" / f"frame-{i:06d}.{suffix}")
    original = np.loadtxt(shared / "camera-intrinsics.txt")
    np.testing.assert_allclose(original, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])   # the shipped file
    modified = original.copy()
    modified[0, 0], modified[1, 1], modified[0, 2], modified[1, 2] = 532.5, 531.0, 318.25, 241.5
    np.savetxt(root / "camera-intrinsics.txt", modified)
    ds = open_dataset(root)
    assert detect_format(root) == "7scenes" and len(ds) == 2
    np.testing.assert_allclose(ds.K, modified)
    np.testing.assert_allclose(ds[1].K, modified)                    # the frames carry it too
    assert ds.intrinsics_source == str(root / "camera-intrinsics.txt")
    # without the file: the documented default, and the source says so
    (root / "camera-intrinsics.txt").unlink()
    ds = open_dataset(root)
    np.testing.assert_allclose(ds.K, original)
    assert "default" in ds.intrinsics_source and "camera-intrinsics" not in ds.intrinsics_source
    # an explicit --intrinsics wins over the file
    np.savetxt(root / "camera-intrinsics.txt", modified)
    ds = open_dataset(root, intrinsics="500,501,319,239")
    np.testing.assert_allclose(ds.K, [[500, 0, 319], [0, 501, 239], [0, 0, 1]])
    assert ds.intrinsics_source == "option"


# --------------------------------------------------------------------------------------------------
# simulator output
# --------------------------------------------------------------------------------------------------
def test_simulated_room_sample():
    from mapping.simulation import sample_sequence

    root = sample_sequence("room")
    assert detect_format(root) == "simulated"
    ds = open_dataset(root)
    manifest = json.loads((root / "radiomap_sequence.json").read_text())
    assert len(ds) == manifest["n_frames"] and (ds.width, ds.height) == (manifest["width"], manifest["height"])
    np.testing.assert_allclose(ds.K, manifest["K"])
    assert ds.intrinsics_source == "manifest" and ds.depth_scale == manifest["depth_scale"]
    stamps, poses = ds.ground_truth()
    assert len(stamps) == len(ds)
    np.testing.assert_allclose(ds[3].pose, poses[3])
    V = ds.true_vignetting()
    assert V.shape == (ds.height, ds.width, 3) and V.dtype == np.float32 and V.max() <= 1.0 + 1e-6
    assert len(ds.true_exposures()) == len(ds)
    assert ds.true_response().channels in (1, 3)
    # the manifest's frame count is checked against the lists
    (tmp := root.parent / "broken_copy")
    if tmp.exists():
        shutil.rmtree(tmp)
    shutil.copytree(root, tmp)
    manifest["n_frames"] = 99
    (tmp / "radiomap_sequence.json").write_text(json.dumps(manifest))
    try:
        with pytest.raises(DatasetError, match="incomplete"):
            open_dataset(tmp)
        assert FORMATS["tum"](tmp) is not None          # still readable as plain TUM
    finally:
        shutil.rmtree(tmp)


# --------------------------------------------------------------------------------------------------
# intrinsics and in-memory data
# --------------------------------------------------------------------------------------------------
def test_intrinsics_option_forms(tmp_path):
    K = parse_intrinsics("500,510,320,240")
    np.testing.assert_allclose(K, [[500, 0, 320], [0, 510, 240], [0, 0, 1]])
    (tmp_path / "k.txt").write_text("500 0 320\n0 510 240\n0 0 1\n")
    np.testing.assert_allclose(parse_intrinsics(tmp_path / "k.txt"), K)
    (tmp_path / "cam.json").write_text(json.dumps({"intrinsic_matrix": [500, 0, 0, 0, 510, 0, 320, 240, 1]}))
    np.testing.assert_allclose(parse_intrinsics(str(tmp_path / "cam.json")), K)
    np.testing.assert_allclose(parse_intrinsics((500, 510, 320, 240)), K)
    (tmp_path / "bad.txt").write_text("500 0 320\n0 x 240\n")
    with pytest.raises(DatasetError, match=r"bad\.txt:2: not numbers"):
        parse_intrinsics(tmp_path / "bad.txt")
    with pytest.raises(ValueError, match="positive focal"):
        parse_intrinsics("0,510,320,240")
    root = shared_path(*OPEN3D)
    with pytest.raises(DatasetError, match="principal point"):
        open_dataset(root, intrinsics="525,525,1000,239.5")


def test_array_dataset_and_trajectory_file(tmp_path):
    frames = [RGBDFrame(i, i / 30, np.zeros((4, 5, 3), np.uint8), np.ones((4, 5), np.float32), np.eye(3),
                        pose=np.eye(4)) for i in range(3)]
    ds = ArrayDataset(frames)
    assert len(ds) == 3 and ds.ground_truth()[1].shape == (3, 4, 4)
    with pytest.raises(DatasetError, match="no frames"):
        ArrayDataset([])
    write_tum_trajectory(tmp_path / "gt.txt", np.arange(3.0), np.repeat(np.eye(4)[None], 3, 0))
    assert (tmp_path / "gt.txt").read_text().count("\n") == 4


# --------------------------------------------------------------------------------------------------
# lists written by other tools (radiometry/textlists.py, tidy_stamped) and poses of the wrong kind
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("data", [
    b"\xef\xbb\xbf1.0 rgb/a.png\r\n2.0 rgb/b.png\r\n",                 # UTF-8 byte-order mark, CRLF
    "1.0 rgb/a.png\r\n2.0 rgb/b.png\r\n".encode("utf-16"),            # UTF-16 with its mark (Windows tools)
    b"1.0 rgb/a.png\r2.0 rgb/b.png",                                  # old Mac line ends, no final newline
])
def test_stamped_list_encodings_and_line_ends(tmp_path, data):
    from mapping.datasets._common import read_stamped_list

    (tmp_path / "rgb.txt").write_bytes(data)
    assert read_stamped_list(tmp_path / "rgb.txt") == [(1.0, "rgb/a.png", 1), (2.0, "rgb/b.png", 2)]


def test_non_utf8_names_open_the_same_file(tmp_path, caplog):
    from mapping.datasets._common import read_stamped_list

    name = b"caf\xe9.png".decode("utf-8", "surrogateescape")   # a Latin-1 name, as the file system gives it
    (tmp_path / name).write_bytes(b"x")
    (tmp_path / "rgb.txt").write_bytes(b"1.0 caf\xe9.png\n")
    rows = read_stamped_list(tmp_path / "rgb.txt")
    assert (tmp_path / rows[0][1]).read_bytes() == b"x"
    assert "1 line(s) are not UTF-8" in caplog.text


def test_binary_list_is_not_text(tmp_path):
    from mapping.datasets._common import read_stamped_list

    (tmp_path / "rgb.txt").write_bytes(b"1.0 a.png\n\x00\x01\x02")
    with pytest.raises(DatasetError, match=r"rgb\.txt: not a text file"):
        read_stamped_list(tmp_path / "rgb.txt")


def test_stamped_list_sorted_and_repeats_dropped_with_counts(tmp_path, caplog):
    from mapping.datasets._common import read_stamped_list

    (tmp_path / "rgb.txt").write_text("3.0 c.png\n1.0 a.png\n2.0 b.png\n2.0 b2.png\n4.0 a.png\n")
    rows = read_stamped_list(tmp_path / "rgb.txt")
    assert [(t, n) for t, n, _ in rows] == [(1.0, "a.png"), (2.0, "b.png"), (3.0, "c.png")]
    assert ("1 line(s) out of time order (sorted by timestamp); 1 line(s) repeating a timestamp (dropped; the first "
            "line kept); 1 line(s) listing a file again at another time (dropped; the first kept); 3 of 5 frames "
            "kept") in caplog.text


def test_tum_pairing_drops_are_warned(tmp_path, caplog):
    root = _tum_folder(tmp_path, stamps_rgb=[1.0, 1.0333, 1.0667], stamps_depth=[1.005, 1.0700])
    assert len(open_dataset(root)) == 2
    assert "1 of 3 colour frames have no depth frame within 0.02 s and are dropped; 2 frames kept" in caplog.text


def test_redwood_log_with_bom_and_crlf(tmp_path):
    poses = [np.eye(4), np.diag([1.0, -1.0, -1.0, 1.0])]
    text = write_log_trajectory(tmp_path / "t.log", poses).read_text()
    (tmp_path / "t.log").write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    read = read_log_trajectory(tmp_path / "t.log")
    np.testing.assert_allclose(read[1], poses[1])


def test_reflection_is_not_a_pose(tmp_path):
    """A rotation with determinant -1 (another handedness) would fuse the scene mirrored."""
    from mapping.datasets._common import check_pose

    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])
    with pytest.raises(DatasetError, match=r"reflection \(determinant -1\)"):
        check_pose(mirror, "t.log:2")
    write_log_trajectory(tmp_path / "t.log", [np.eye(4), mirror])
    with pytest.raises(DatasetError, match=r"t\.log:7: the rotation is a reflection"):
        read_log_trajectory(tmp_path / "t.log")


def test_a_list_that_is_a_folder_is_refused(tmp_path):
    root = _tum_folder(tmp_path, stamps_rgb=[1.0], stamps_depth=[1.0])
    (root / "groundtruth.txt").mkdir()
    with pytest.raises(DatasetError, match=r"groundtruth\.txt: the ground truth is a folder"):
        open_dataset(root)
    (root / "groundtruth.txt").rmdir()
    (root / "rgb.txt").unlink()
    (root / "rgb.txt").mkdir()  # not taken for another layout (a Redwood folder has rgb/ and depth/ too)
    with pytest.raises(DatasetError, match=r"rgb\.txt: the colour list is a folder"):
        open_dataset(root)


def test_grey_frames_in_a_colour_sequence_are_refused(tmp_path):
    root = _tum_folder(tmp_path, stamps_rgb=[1.0, 2.0], stamps_depth=[1.0, 2.0])
    grey = root / "rgb" / "2.000000.png"
    write_image(grey, np.full((480, 640), 128, np.uint8))
    ds = open_dataset(root)
    with pytest.raises(DatasetError, match=r"2\.000000\.png: a grey \(single-channel\) image in a sequence of colour"):
        ds[1]
    write_image(root / "rgb" / "1.000000.png", np.full((480, 640), 90, np.uint8))
    ds = open_dataset(root)  # all grey: fused as R = G = B
    assert ds[1].rgb.shape == (480, 640, 3) and np.all(ds[1].rgb == 128)
