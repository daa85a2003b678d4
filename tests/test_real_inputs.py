"""Real recordings in, without surprises (issue 30): intrinsics files of every layout, ORB-SLAM2's
associations.txt, a recorder's millimetre depth, poses from files (TUM, Redwood .log, 7-Scenes pose folders)
matched to the frames, the ground truth written as a TUM file, a tracking loss that keeps the map, and a refused
self-calibration that writes nothing."""

from __future__ import annotations

import json
import logging
import shutil

import numpy as np
import pytest
from box_room import box_room_sequence
from click.testing import CliRunner
from conftest import shared_path

from mapping.cli import cli
from mapping.datasets import intrinsics_text, open_dataset
from mapping.datasets.base import RGBDFrame
from mapping.datasets.in_memory import ArrayDataset
from mapping.datasets.redwood import write_log_trajectory
from mapping.export import RUNNING_MARKER, ResultsFolder, is_complete
from mapping.factory import make_backend, make_tracker
from mapping.metrics import format_tum_trajectory, read_tum_trajectory
from mapping.pipeline import TrackingError, TrackingLostError, reconstruct
from mapping.pose_files import PoseFileError, match_pose_file, pose_file_kind
from radiometry.images import write_depth, write_image

W, H = 160, 120


def _redwood_folder(path, n=8, *, camera_file="camera_intrinsic.json", trajectory=True, depth_zero_from=None,
                    size=(W, H)):
    """The box room written as Open3D's recorder layout: color/, depth/ (mm), an intrinsics file, trajectory.log."""
    ds, _ = box_room_sequence(n_frames=n, width=size[0], height=size[1])
    (path / "color").mkdir(parents=True)
    (path / "depth").mkdir()
    for i, f in enumerate(ds.frames):
        write_image(path / "color" / f"{i:06d}.png", f.rgb)
        depth = f.depth if depth_zero_from is None or i < depth_zero_from else np.zeros_like(f.depth)
        write_depth(path / "depth" / f"{i:06d}.png", depth, 1000.0)
    K = ds.frames[0].K
    if camera_file == "camera_intrinsic.json":   # Open3D's PinholeCameraIntrinsic JSON, column-major
        (path / camera_file).write_text(json.dumps({"width": size[0], "height": size[1],
                                                    "intrinsic_matrix": K.T.ravel().tolist()}))
    elif camera_file is not None:                # tsdf-fusion / 3DMatch: a 3 x 3 text matrix
        (path / camera_file).write_text("\n".join(" ".join(f"{v:.10g}" for v in row) for row in K) + "\n")
    if trajectory:
        write_log_trajectory(path / "trajectory.log", [f.pose for f in ds.frames])
    return ds


# ------------------------------------------------------------------------------------------------------------
# 1. intrinsics from the folder, associations, the recorder's depth scale
# ------------------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("name", ["camera_intrinsic.json", "intrinsics.K.txt", "camera-intrinsics.txt"])
def test_the_intrinsics_file_of_the_layout_is_read_and_named(tmp_path, name):
    ds = _redwood_folder(tmp_path / "seq", 2, camera_file=name, trajectory=False)
    opened = open_dataset(tmp_path / "seq")
    np.testing.assert_allclose(opened.K, ds.frames[0].K, atol=1e-9)
    assert opened.intrinsics_source.endswith(name)
    assert name in intrinsics_text(opened) and f"{ds.frames[0].K[0, 0]:.6g}" in intrinsics_text(opened)
    given = open_dataset(tmp_path / "seq", intrinsics="300,300,80,60")   # an explicit option still wins
    assert given.K[0, 0] == 300 and "(given)" in intrinsics_text(given)


def test_a_camera_json_of_another_image_size_is_refused(tmp_path):
    """Open3D's camera JSON declares its image size: a file of another stream (848x480 beside 640x480 frames;
    the lampshade with such a file fused with 421,421,424,240, exit 0) is refused naming the file, both sizes and
    the fix; the explicit option still opens the folder."""
    _redwood_folder(tmp_path / "seq", 1, trajectory=False)
    camera = tmp_path / "seq" / "camera_intrinsic.json"
    camera.write_text(json.dumps({"width": 2 * W + 10, "height": H, "intrinsic_matrix": [100, 0, 0, 0, 100, 0,
                                                                                        W / 2 + 5, H / 2, 1]}))
    result = CliRunner().invoke(cli, ["reconstruct", str(tmp_path / "seq"), "-o", str(tmp_path / "out"),
                                      "--no-progress"])
    assert result.exit_code == 1 and "Traceback" not in result.output
    line = result.stderr.strip().splitlines()[-1]
    for fragment in (str(camera), f"{2 * W + 10}x{H}", f"{W}x{H}", "--intrinsics fx,fy,cx,cy"):
        assert fragment in line, line
    assert not (tmp_path / "out").exists()
    assert open_dataset(tmp_path / "seq", intrinsics="100,100,80,60").K[0, 2] == 80


def test_a_camera_json_of_another_image_size_given_by_option_is_refused(tmp_path):
    """The same file given as ``--intrinsics FILE`` was used without a word (the size was checked only on files
    found beside the frames): now refused naming the option, the file, both sizes and the fix, nothing written; the
    file of the frames' size given the same way is read."""
    ds = _redwood_folder(tmp_path / "seq", 2, camera_file=None)
    other = tmp_path / "d455_848x480.json"
    other.write_text(json.dumps({"width": 2 * W + 10, "height": H, "intrinsic_matrix": [100, 0, 0, 0, 100, 0,
                                                                                       W / 2 + 5, H / 2, 1]}))
    result = CliRunner().invoke(cli, ["reconstruct", str(tmp_path / "seq"), "-o", str(tmp_path / "out"),
                                      "--no-progress", "--intrinsics", str(other)])
    assert result.exit_code == 1 and "Traceback" not in result.output
    line = result.stderr.strip().splitlines()[-1]
    for fragment in (f"--intrinsics {other}", f"{2 * W + 10}x{H}", f"{W}x{H}", "--intrinsics fx,fy,cx,cy"):
        assert fragment in line, line
    assert not (tmp_path / "out").exists()
    right = tmp_path / "right.json"
    K = ds.frames[0].K
    right.write_text(json.dumps({"width": W, "height": H, "intrinsic_matrix": K.T.ravel().tolist()}))
    opened = open_dataset(tmp_path / "seq", intrinsics=str(right))
    opened[0]
    np.testing.assert_allclose(opened.K, K)


@pytest.mark.slow
def test_a_default_intrinsics_is_said_with_a_warning(tmp_path, caplog):
    _redwood_folder(tmp_path / "seq", 1, camera_file=None, trajectory=False, size=(640, 480))
    with caplog.at_level(logging.WARNING):
        opened = open_dataset(tmp_path / "seq")
    assert opened.K[0, 0] == 525 and "assumed" in opened.intrinsics_source
    assert any("assuming the PrimeSense default" in r.getMessage() for r in caplog.records)
    assert "assumed" in intrinsics_text(opened)


def _tum_folder(path, n=6, *, stamps=None, associations=True, scale=5000.0, name_lists=True):
    ds, _ = box_room_sequence(n_frames=n, width=W, height=H)
    (path / "rgb").mkdir(parents=True)
    (path / "depth").mkdir()
    stamps = np.arange(n) / 30.0 if stamps is None else np.asarray(stamps)
    lines = []
    for i, f in enumerate(ds.frames):
        write_image(path / "rgb" / f"{i:05d}.png", f.rgb)
        write_depth(path / "depth" / f"{i:05d}.png", f.depth, scale)
        lines.append(f"{stamps[i]:.6f} rgb/{i:05d}.png {stamps[i]:.6f} depth/{i:05d}.png")
    if name_lists:
        (path / "rgb.txt").write_text("".join(f"{s:.6f} rgb/{i:05d}.png\n" for i, s in enumerate(stamps)))
        (path / "depth.txt").write_text("".join(f"{s:.6f} depth/{i:05d}.png\n" for i, s in enumerate(stamps)))
    if associations:
        (path / "associations.txt").write_text("\n".join(lines) + "\n")
    return ds


@pytest.mark.slow
def test_associations_pair_the_frames_in_their_order_when_the_timestamps_are_broken(tmp_path, caplog):
    """The recorder wrote intervals instead of times (not increasing): associations.txt keeps the file's order
    (sorting by the broken stamps would scramble the frames) and the frames are dated N / 30 s, with a warning."""
    broken = [0.0058, 0.0070, 0.0154, 0.0148, 0.0163, 0.0120]
    ds = _tum_folder(tmp_path / "rec", stamps=broken, scale=1000.0)
    with caplog.at_level(logging.WARNING):
        opened = open_dataset(tmp_path / "rec", intrinsics="128,128,79.5,59.5")
    assert [f.rgb.name for f in opened.frame_files] == [f"{i:05d}.png" for i in range(6)]
    np.testing.assert_allclose(opened.timestamps, np.arange(6) / 30.0)
    assert any("do not increase" in r.getMessage() for r in caplog.records)
    # the depth was written in millimetres (as RealSense recorders do): detected, said, and read right
    assert opened.depth_scale == 1000.0 and "detected" in intrinsics_text(opened)
    np.testing.assert_allclose(opened[3].depth, ds.frames[3].depth, atol=6e-4)


@pytest.mark.slow
def test_tum_depth_at_5000_per_metre_is_kept_and_the_folder_name_gives_the_kinect(tmp_path):
    """TUM's own depth (the Kinect's millimetres times 5: multiples of 5) stays at 5000 per metre; 'fr2' in the
    folder name picks freiburg 2's intrinsics."""
    ds, _ = box_room_sequence(n_frames=2, width=640, height=480)
    folder = tmp_path / "rgbd_fr2_desk"
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    for i, f in enumerate(ds.frames):
        write_image(folder / "rgb" / f"{i}.png", f.rgb)
        write_depth(folder / "depth" / f"{i}.png", np.round(f.depth * 1000) / 1000, 5000.0)   # mm x 5
    (folder / "associations.txt").write_text("0.0 rgb/0.png 0.0 depth/0.png\n0.033 rgb/1.png 0.033 depth/1.png\n")
    opened = open_dataset(folder)
    assert opened.depth_scale == 5000.0 and opened.intrinsics_source.startswith("TUM freiburg2")
    assert opened.K[0, 0] == pytest.approx(520.9)


def test_millimetre_depth_is_detected_without_associations_and_simulated_tum_depth_is_kept(tmp_path, caplog):
    """rgb.txt / depth.txt without associations.txt: the multiples-of-5 detector used to run only with
    associations.txt, so millimetres were read at 5000 per metre (the office in this layout: depth 5x too small,
    L1 50.3 against 24). Now detected, warned and said; depth simulated at 5000 per metre (not multiples of 5,
    but a room's median) stays at 5000, and the settings line says so."""
    ds = _tum_folder(tmp_path / "mm", associations=False, scale=1000.0)
    with caplog.at_level(logging.WARNING):
        opened = open_dataset(tmp_path / "mm", intrinsics="128,128,79.5,59.5")
    assert opened.depth_scale == 1000.0
    assert any("read as millimetres" in r.getMessage() for r in caplog.records)
    assert "depth scale 1000 per metre (detected: depth in millimetres)" in intrinsics_text(opened)
    np.testing.assert_allclose(opened[2].depth, ds.frames[2].depth, atol=6e-4)
    _tum_folder(tmp_path / "sim", associations=False, scale=5000.0)
    kept = open_dataset(tmp_path / "sim", intrinsics="128,128,79.5,59.5")
    assert kept.depth_scale == 5000.0 and "depth scale 5000 per metre (TUM's" in intrinsics_text(kept)


def test_a_malformed_associations_line_names_the_file_and_line(tmp_path):
    _tum_folder(tmp_path / "rec", 2)
    (tmp_path / "rec" / "associations.txt").write_text("0.0 rgb/00000.png depth/00000.png\n")
    from radiometry.errors import DatasetError

    with pytest.raises(DatasetError, match=r"associations.txt:1: expected 'rgb_timestamp rgb_file"):
        open_dataset(tmp_path / "rec")


@pytest.mark.slow
def test_the_shared_recordings_are_read_as_their_layouts_say():
    office = open_dataset(shared_path("rgbd", "realsense_office_d435"), intrinsics="615,615,320,240")
    assert len(office) == 100 and office.frame_files[0].rgb.name == "rgb00002.png"
    assert office.frame_files[99].rgb.name == "rgb00101.png" and office.depth_scale == 1000.0
    assert 0.5 < float(np.median(office[50].depth[office[50].depth > 0])) < 3.0   # a desk, not 0.16 m
    lamp = open_dataset(shared_path("rgbd", "realsense_lampshade"))
    assert lamp.intrinsics_source.endswith("camera_intrinsic.json")
    np.testing.assert_allclose(lamp.K[[0, 1, 0, 1], [0, 1, 2, 2]], [610.4436, 609.7561, 311.9945, 246.0650],
                               atol=1e-3)


# ------------------------------------------------------------------------------------------------------------
# 2. poses from a file
# ------------------------------------------------------------------------------------------------------------
def test_a_pose_file_of_a_list_without_a_clock_is_matched_by_its_copied_stamps_or_refused(tmp_path):
    """associations.txt's stamps do not increase (intervals): the frames are dated N / 30 s, so a trajectory that
    copies the listed stamps (ORB-SLAM2's CameraTrajectory.txt) was matched by the nearest time to other frames'
    poses (the office: frame 0 took frame 13's, exit 0). It is matched by the copied stamps; radiomap's own
    trajectory (N / 30 s) likewise; anything else is refused, whatever --poses-max-difference says."""
    broken = [0.0058, 0.0070, 0.0154, 0.0148, 0.0163, 0.0120]
    ds = _tum_folder(tmp_path / "rec", stamps=broken, scale=1000.0)
    opened = open_dataset(tmp_path / "rec", intrinsics="128,128,79.5,59.5")
    truth = np.stack([f.pose for f in ds.frames])
    for stamps in (np.array(broken), np.arange(6) / 30.0):
        tum = tmp_path / "traj.txt"
        tum.write_text(format_tum_trajectory(stamps, truth))
        table = match_pose_file(opened, tum)
        np.testing.assert_allclose(np.stack(table.poses), truth, atol=1e-6)
    # ORB-SLAM2 leaves out lost frames: the others keep their own poses
    tum.write_text(format_tum_trajectory(np.array(broken)[[0, 1, 3, 4, 5]], truth[[0, 1, 3, 4, 5]]))
    table = match_pose_file(opened, tum)
    assert table[2] is None and table.matched == 5
    np.testing.assert_allclose(table[3], truth[3], atol=1e-6)
    tum.write_text(format_tum_trajectory(np.array(broken) + 0.002, truth))
    with pytest.raises(PoseFileError, match=r"traj.txt: cannot be matched.*do not increase.*Redwood .log"):
        match_pose_file(opened, tum, max_difference=10.0)
    # listed stamps that repeat (the office's frames 22 and 23: 2.4e-7 s apart): a row per frame is matched row by
    # row; with a frame left out the rows are ambiguous and refused
    repeated = [0.0058, 0.0070, 0.0154, 0.0148, 0.0058, 0.0120]
    _tum_folder(tmp_path / "rep", stamps=repeated, scale=1000.0)
    opened = open_dataset(tmp_path / "rep", intrinsics="128,128,79.5,59.5")
    tum.write_text(format_tum_trajectory(np.array(repeated), truth))
    np.testing.assert_allclose(np.stack(match_pose_file(opened, tum).poses), truth, atol=1e-6)
    tum.write_text(format_tum_trajectory(np.array(repeated)[[0, 1, 2, 3, 5]], truth[[0, 1, 2, 3, 5]]))
    with pytest.raises(PoseFileError, match="cannot be matched"):
        match_pose_file(opened, tum)


@pytest.mark.slow
def test_each_kind_of_pose_file_is_matched_to_the_frames(tmp_path):
    ds = _redwood_folder(tmp_path / "seq", 6)
    opened = open_dataset(tmp_path / "seq")
    truth = [f.pose for f in ds.frames]
    # Redwood .log by frame number
    table = match_pose_file(opened, tmp_path / "seq" / "trajectory.log")
    assert table.kind == "redwood-log" and table.matched == 6
    np.testing.assert_allclose(np.stack(table.poses), np.stack(truth), atol=1e-9)
    # a folder of 7-Scenes pose files, frame 2 lost (inf, as 7-Scenes marks it): skipped
    poses_dir = tmp_path / "poses"
    poses_dir.mkdir()
    for i, p in enumerate(truth):
        np.savetxt(poses_dir / f"frame-{i:06d}.pose.txt", p if i != 2 else np.full((4, 4), np.inf))
    table = match_pose_file(opened, poses_dir)
    assert table.kind == "7scenes" and table.matched == 5 and table[2] is None
    np.testing.assert_allclose(table[4], truth[4], atol=1e-6)
    # a TUM file, 3 ms off the frames' times: matched within the default 20 ms, refused within 1 ms
    tum = tmp_path / "traj.txt"
    tum.write_text(format_tum_trajectory(opened.timestamps + 0.003, np.stack(truth)))
    assert pose_file_kind(tum) == "tum"
    table = match_pose_file(opened, tum)
    np.testing.assert_allclose(np.stack(table.poses), np.stack(truth), atol=1e-6)
    with pytest.raises(PoseFileError, match=r"6 of 6 frames have no pose within 0.001 s.*--poses-max-difference"):
        match_pose_file(opened, tum, max_difference=0.001)


def test_frames_without_a_pose_are_skipped_with_a_count_and_too_many_refused(tmp_path, caplog):
    """radiometry.quorum's rule: fewer than 2 frames or 10 % of them with a pose is refused before the run."""
    frames = [RGBDFrame(i, i / 30.0, np.zeros((H, W, 3), np.uint8), np.ones((H, W), np.float32),
                        np.array([[100.0, 0, 80], [0, 100, 60], [0, 0, 1]])) for i in range(30)]
    ds = ArrayDataset(frames)
    tum = tmp_path / "part.txt"
    tum.write_text(format_tum_trajectory(np.arange(20) / 30.0, np.repeat(np.eye(4)[None], 20, axis=0)))
    with caplog.at_level(logging.WARNING):
        table = match_pose_file(ds, tum)
    assert table.matched == 20 and all(table[i] is None for i in range(20, 30))
    assert any("10 of 30 frames have no pose" in r.getMessage() for r in caplog.records)
    few = tmp_path / "few.txt"
    few.write_text(format_tum_trajectory(np.arange(2) / 30.0, np.repeat(np.eye(4)[None], 2, axis=0)))
    with pytest.raises(PoseFileError, match="28 of 30 frames have no pose.*at least 2 frames and 10%"):
        match_pose_file(ds, few)


@pytest.mark.slow
def test_a_trajectory_written_by_radiomap_reproduces_its_poses(tmp_path):
    """reconstruct tracks (the default tracker), writes trajectory.txt; given back as --poses FILE the run fuses every
    frame at the same poses (< 0.1 mm, < 1e-4 degrees); the ground truth is written beside it as a TUM file."""
    _redwood_folder(tmp_path / "seq", 8)
    run1, run2 = tmp_path / "run1", tmp_path / "run2"
    res = CliRunner().invoke(cli, ["reconstruct", str(tmp_path / "seq"), "-o", str(run1), "--depth-max", "5",
                                   "--voxel-size", "0.02", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert "intrinsics" in res.output and "camera_intrinsic.json" in res.output   # the settings line says which
    res = CliRunner().invoke(cli, ["reconstruct", str(tmp_path / "seq"), "-o", str(run2), "--depth-max", "5",
                                   "--voxel-size", "0.02", "--no-progress", "--poses", str(run1 / "trajectory.txt")])
    assert res.exit_code == 0, res.output
    t1, p1 = read_tum_trajectory(run1 / "trajectory.txt")
    t2, p2 = read_tum_trajectory(run2 / "trajectory.txt")
    assert len(t1) == len(t2) == 8
    np.testing.assert_array_equal(t1, t2)
    assert np.abs(p1[:, :3, 3] - p2[:, :3, 3]).max() < 1e-4
    from mapping.metrics import rotation_angle

    assert max(np.degrees(rotation_angle(a[:3, :3].T @ b[:3, :3])) for a, b in zip(p1, p2)) < 1e-4
    # the ground truth (trajectory.log) beside the estimate, for evo; equal to the sequence's
    gt_t, gt_p = read_tum_trajectory(run1 / "groundtruth_tum.txt")
    truth = open_dataset(tmp_path / "seq").ground_truth()
    np.testing.assert_allclose(gt_t, truth[0], atol=1e-6)
    np.testing.assert_allclose(gt_p, truth[1], atol=1e-6)
    config = json.loads((run2 / "config.json").read_text())
    assert config["parameters"]["poses"] == str((run1 / "trajectory.txt").resolve())
    metrics = json.loads((run1 / "metrics.json").read_text())
    assert metrics["tracking"]["tracker"] == "auto"


@pytest.mark.slow
def test_no_ground_truth_no_groundtruth_file(tmp_path):
    _redwood_folder(tmp_path / "seq", 4, trajectory=False)
    run = tmp_path / "run"
    res = CliRunner().invoke(cli, ["reconstruct", str(tmp_path / "seq"), "-o", str(run), "--depth-max", "5",
                                   "--voxel-size", "0.02", "--no-progress", "--tracker", "icp"])
    assert res.exit_code == 0, res.output
    assert (run / "trajectory.txt").is_file() and not (run / "groundtruth_tum.txt").exists()


def test_poses_option_errors_are_one_line(tmp_path):
    _redwood_folder(tmp_path / "seq", 3)
    for args, text in ((["--poses", str(tmp_path / "nope.txt")], "neither icp, gt nor an existing trajectory"),
                       (["--poses-max-difference", "0.1"], "applies with --poses FILE only"),
                       (["--poses", str(tmp_path / "seq" / "trajectory.log"), "--poses-max-difference", "-1"],
                        "outside the sensible range 0..10 s")):
        res = CliRunner().invoke(cli, ["reconstruct", str(tmp_path / "seq"), "-o", str(tmp_path / "out"), *args])
        assert res.exit_code != 0 and text in res.output, res.output
        assert not (tmp_path / "out").exists()


@pytest.mark.slow
def test_compare_and_self_calibrate_take_a_pose_file(tmp_path):
    """--poses FILE on compare (every method at the file's poses) and self-calibrate (--tracker too)."""
    ds = _redwood_folder(tmp_path / "seq", 6)
    from radiometry.response import CameraResponse

    CameraResponse.linear().save(tmp_path / "crf.npz")
    log = str(tmp_path / "seq" / "trajectory.log")
    res = CliRunner().invoke(cli, ["compare", str(tmp_path / "seq"), "-r", str(tmp_path / "crf.npz"), "-o",
                                   str(tmp_path / "cmp"), "--poses", log, "--methods", "none,response", "--views", "0",
                                   "--depth-max", "5", "--voxel-size", "0.02", "--no-progress", "--no-glb"])
    assert res.exit_code == 0, res.output
    for method in ("none", "response"):
        _, poses = read_tum_trajectory(tmp_path / "cmp" / method / "trajectory.txt")
        np.testing.assert_allclose(poses, np.stack([f.pose for f in ds.frames]), atol=1e-6)
    res = CliRunner().invoke(cli, ["self-calibrate", str(tmp_path / "seq"), "-o", str(tmp_path / "sc"), "--poses",
                                   log, "--no-plots", "--no-progress"])
    assert res.exit_code == 0, res.output
    _, poses = read_tum_trajectory(tmp_path / "sc" / "trajectory.txt")
    np.testing.assert_allclose(poses, np.stack([f.pose for f in ds.frames]), atol=1e-6)
    assert (tmp_path / "sc" / "groundtruth_tum.txt").is_file()
    assert "intrinsics" in res.output and "camera_intrinsic.json" in res.output   # which, and from where
    res = CliRunner().invoke(cli, ["self-calibrate", str(tmp_path / "seq"), "-o", str(tmp_path / "sc2"), "--poses",
                                   "gt", "--tracker", "hybrid"])
    assert res.exit_code == 2 and "applies with --poses icp only" in res.output


# ------------------------------------------------------------------------------------------------------------
# 4. a tracking loss keeps the map; 5. a refused run writes nothing
# ------------------------------------------------------------------------------------------------------------
def _losing(n_good=6, n=12):
    """A box room whose depth vanishes after ``n_good`` frames: tracking is lost for good."""
    ds, _ = box_room_sequence(n_frames=n, width=W, height=H)
    return ArrayDataset([f if i < n_good else RGBDFrame(f.index, f.timestamp, f.rgb, np.zeros_like(f.depth), f.K,
                                                         f.pose) for i, f in enumerate(ds.frames)])


@pytest.mark.slow
def test_a_tracking_loss_keeps_the_map_marks_it_partial_and_fails(tmp_path):
    out = ResultsFolder(tmp_path / "lost")
    with pytest.raises(TrackingLostError, match="kept the 6 of 12 frames fused before the loss") as info:
        reconstruct(_losing(), backend=make_backend("tsdf", voxel_size=0.02, depth_max=5.0),
                    tracker=make_tracker("icp", depth_max=5.0), output=out, max_consecutive_failures=3,
                    progress=False)
    assert info.value.run.fused == 6 and info.value.run.status == "partial"
    metrics = json.loads((out.path / "metrics.json").read_text())
    assert metrics["status"] == "partial" and "3 consecutive frames" in metrics["partial_reason"]
    assert metrics["frames"]["fused"] == 6 and metrics["frames"]["processed"] == 9   # stopped at the loss
    assert metrics["frames"]["total"] == 12
    assert (out.path / "mesh.ply").stat().st_size > 1000 and not (out.path / RUNNING_MARKER).exists()
    assert len(read_tum_trajectory(out.path / "trajectory.txt")[0]) == 6
    assert not is_complete(out.path)   # a batch runs it again


@pytest.mark.slow
def test_a_loss_before_a_map_exists_still_fails_unfinished(tmp_path):
    out = ResultsFolder(tmp_path / "lost")
    with pytest.raises(TrackingError) as info:
        reconstruct(_losing(n_good=1, n=30), backend=make_backend("tsdf", voxel_size=0.02, depth_max=5.0),
                    tracker=make_tracker("icp", depth_max=5.0), output=out, max_consecutive_failures=3,
                    progress=False)
    assert not isinstance(info.value, TrackingLostError)
    assert (out.path / RUNNING_MARKER).exists()


@pytest.mark.slow
def test_the_cli_writes_the_partial_map_and_exits_non_zero(tmp_path):
    _redwood_folder(tmp_path / "seq", 40, depth_zero_from=8)
    res = CliRunner().invoke(cli, ["reconstruct", str(tmp_path / "seq"), "-o", str(tmp_path / "run"), "--depth-max",
                                   "5", "--voxel-size", "0.02", "--no-progress", "--tracker", "icp"])
    assert res.exit_code == 1 and "kept the 8 of 40 frames fused before the loss" in res.output
    assert "PARTIAL" in (tmp_path / "run" / "summary.txt").read_text()
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["status"] == "partial"


def test_a_self_calibration_refused_at_validation_writes_nothing(tmp_path):
    """--poses gt on a sequence without ground truth: refused before any work, no folder, no RUNNING marker; the
    next run needs no --force."""
    _redwood_folder(tmp_path / "seq", 4, trajectory=False)
    out = tmp_path / "sc"
    for _ in range(2):
        res = CliRunner().invoke(cli, ["self-calibrate", str(tmp_path / "seq"), "-o", str(out), "--poses", "gt"])
        assert res.exit_code == 1 and "has no ground-truth poses" in res.output, res.output
        assert "--force" not in res.output and not out.exists()
    out.mkdir()   # an existing empty folder stays empty
    res = CliRunner().invoke(cli, ["self-calibrate", str(tmp_path / "seq"), "-o", str(out), "--poses", "gt"])
    assert res.exit_code == 1 and list(out.iterdir()) == []
    shutil.rmtree(out)


@pytest.mark.slow
def test_a_batch_gives_each_sequence_its_own_pose_file(tmp_path):
    """``radiomap batch reconstruct LIST -- --poses groundtruth.txt``: a relative path not found from the working
    folder is each sequence's own file; the poses fused are that sequence's."""
    from mapping.simulation.sequences import simulate_room

    seqs = [simulate_room(tmp_path / name, seed=seed, n_frames=5, width=64, height=48, progress=False)
            for name, seed in (("a", 1), ("b", 2))]
    (tmp_path / "list.txt").write_text("\n".join(str(s) for s in seqs) + "\n")
    res = CliRunner().invoke(cli, ["batch", "reconstruct", str(tmp_path / "list.txt"), "-o", str(tmp_path / "runs"),
                                   "--no-progress", "--", "--poses", "groundtruth.txt", "--depth-max", "6",
                                   "--voxel-size", "0.04"])
    assert res.exit_code == 0, res.output
    for seq in seqs:
        truth = open_dataset(seq).ground_truth()
        _, poses = read_tum_trajectory(tmp_path / "runs" / seq.name / "trajectory.txt")
        np.testing.assert_allclose(poses, truth[1], atol=1e-6)
        config = json.loads((tmp_path / "runs" / seq.name / "config.json").read_text())
        assert config["parameters"]["poses"] == str((seq / "groundtruth.txt").resolve())
