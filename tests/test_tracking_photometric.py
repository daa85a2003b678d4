"""Photometric trackers (hybrid RGB-D odometry, coloured ICP): known motions on analytic textured scenes built
here (planes with a random blob texture, rendered exactly), clean failures, the exposure estimate before
tracking, the frame's colour in map units, the --tracker option end to end."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.datasets.base import RGBDFrame
from mapping.factory import TRACKERS, make_tracker
from mapping.fusion.base import ModelView
from mapping.metrics import rotation_angle
from mapping.tracking_photometric import (ColouredICPTracker, HybridTracker, estimate_exposure, luminance,
                                          tracking_colour)
from radiometry.response import CameraResponse

W, H = 160, 120
K = np.array([[0.8 * W, 0, (W - 1) / 2], [0, 0.8 * W, (H - 1) / 2], [0, 0, 1.0]])


def _rotation(axis, deg):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(deg)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx


def _pose(R=np.eye(3), t=(0, 0, 0)):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, t
    return T


class Planes:
    """Planes ``n . x = d`` (camera looks along +z from the origin) with a smooth random blob texture in world
    coordinates: radiance in (0.1, 0.9), grey times a fixed per-channel tint."""

    def __init__(self, planes, *, textured=True, seed=0):
        self.planes = [(np.asarray(n, float) / np.linalg.norm(n), float(d)) for n, d in planes]
        rng = np.random.default_rng(seed)
        self.centres = rng.uniform(-2, 2, (250, 3))
        self.weights = rng.uniform(-1, 1, 250)
        self.textured = textured

    def radiance(self, p):
        if not self.textured:
            return np.full(p.shape[:-1] + (3,), 0.5)
        d2 = ((p[..., None, :] - self.centres) ** 2).sum(-1)
        g = 0.5 + 0.35 * np.tanh(2 * (np.exp(-d2 / 0.02) * self.weights).sum(-1))
        return g[..., None] * np.array([0.9, 1.0, 0.8])

    def render(self, pose):
        """depth, radiance, vertex (camera frame), normal (camera frame) at ``pose`` (camera-to-world)."""
        v, u = np.mgrid[0:H, 0:W].astype(float)
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
        dirs = rays @ pose[:3, :3].T
        o = pose[:3, 3]
        best = np.full((H, W), np.inf)
        normal = np.zeros((H, W, 3))
        for n, d in self.planes:
            denom = dirs @ n
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (d - o @ n) / denom
            hit = (t > 0.05) & (t < best)
            best[hit] = t[hit]
            normal[hit] = n
        ok = np.isfinite(best)
        depth = np.where(ok, best, 0.0)  # unit camera-z rays: t is the depth
        points = o + depth[..., None] * dirs
        L = np.where(ok[..., None], self.radiance(points), 0.0)
        vertex = np.where(ok[..., None], rays * depth[..., None], 0.0)
        n_cam = np.where(ok[..., None], normal @ pose[:3, :3], 0.0)
        return depth.astype(np.float32), L.astype(np.float32), vertex.astype(np.float32), n_cam.astype(np.float32)


CORNER = [((1, 0, 0), 1.2), ((0, 1, 0), 0.9), ((0, 0, -1), -3.0)]   # a side wall, the floor, the back wall
WALL = [((0, 0, -1), -2.0)]                                           # one wall: in-plane motion is unobservable


def _view(scene, pose, k=1.0):
    depth, L, vertex, normal = scene.render(pose)
    return ModelView(depth, (k * L).astype(np.float32), vertex, normal, pose=pose)


def _frame(scene, pose, *, k=1.0, response=None):
    depth, L, _, _ = scene.render(pose)
    response = response or CameraResponse.linear()
    rgb = response.forward((k * 200 / 255 * L).astype(np.float32), dtype=np.uint8)
    return RGBDFrame(index=1, timestamp=0.0, rgb=rgb, depth=depth, K=K, pose=pose, name="f")


def _raw_colour(frame):
    from mapping.colour import RawIntensity

    return tracking_colour(RawIntensity(), frame.rgb)


def _error(T_est, T_true):
    E = np.linalg.inv(T_true) @ T_est
    return float(np.linalg.norm(E[:3, 3])), float(np.degrees(rotation_angle(E[:3, :3])))


def _raw_view(scene, pose):
    """The map of raw levels as the frame at ``pose`` shows them (linear camera, 200/255 of radiance)."""
    return _view(scene, pose, k=200.0)


MOTION = _pose(_rotation((0.3, 1, 0.1), 1.0), (0.015, -0.01, 0.01))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["icp", "hybrid", "coloured-icp"])
def test_each_tracker_recovers_a_known_motion_in_a_textured_corner(name):
    scene = Planes(CORNER)
    view_pose = np.eye(4)
    true = view_pose @ MOTION
    frame = _frame(scene, true)
    tracker = make_tracker(name, depth_max=5.0)
    tracker.start(view_pose)
    result = tracker.track(frame.depth, K, _raw_view(scene, view_pose), view_pose, colour=_raw_colour(frame))
    assert result.ok, result.reason
    t_err, r_err = _error(result.pose, true)
    assert t_err < 0.004 and r_err < 0.2, (t_err, r_err)
    start_t, start_r = _error(view_pose, true)
    assert start_t > 10 * t_err      # it moved from the initial guess to the truth
    assert result.iterations > 0 and 0.5 < result.fitness <= 1.0


@pytest.mark.slow
@pytest.mark.parametrize("name", ["hybrid", "coloured-icp"])
def test_colour_recovers_what_geometry_cannot_see(name):
    """On one textured wall a sideways motion leaves the depth unchanged: point-to-plane ICP has a singular
    system (rejected), the photometric trackers find the motion from the texture."""
    scene = Planes(WALL)
    true = _pose(t=(0.02, 0.0, 0.0))
    frame = _frame(scene, true)
    view = _raw_view(scene, np.eye(4))
    results = {}
    for tracker_name in ("icp", name):
        tracker = make_tracker(tracker_name, depth_max=5.0, motion_model="previous")
        tracker.start(np.eye(4))
        results[tracker_name] = tracker.track(frame.depth, K, view, np.eye(4), colour=_raw_colour(frame))
    assert not results["icp"].ok and "Singular" in results["icp"].reason  # no information along the wall
    assert results[name].ok, results[name].reason
    assert _error(results[name].pose, true)[0] < 0.005


@pytest.mark.slow
@pytest.mark.parametrize("cls", [HybridTracker, ColouredICPTracker])
def test_empty_or_missing_views_fail_cleanly(cls):
    scene = Planes(CORNER)
    frame = _frame(scene, MOTION)
    colour = _raw_colour(frame)
    tracker = cls(depth_max=5.0)
    tracker.start(np.eye(4))
    empty = ModelView(np.zeros((H, W), np.float32), np.zeros((H, W, 3), np.float32),
                      np.zeros((H, W, 3), np.float32), np.zeros((H, W, 3), np.float32))
    for view, reason in ((None, "no model view"), (empty, "too little of the map in view (0 pixels)")):
        result = tracker.track(frame.depth, K, view, np.eye(4), colour=colour)
        assert not result.ok and reason in result.reason
        np.testing.assert_array_equal(result.pose, np.eye(4))   # the prediction, nothing fused from it
    no_depth = tracker.track(np.zeros((H, W), np.float32), K, _raw_view(scene, np.eye(4)), np.eye(4), colour=colour)
    assert not no_depth.ok and "valid depth pixels" in no_depth.reason
    with pytest.raises(ValueError, match="needs the frame's colour"):
        tracker.track(frame.depth, K, _raw_view(scene, np.eye(4)), np.eye(4))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["hybrid", "coloured-icp"])
def test_a_textureless_view_tracks_on_geometry_or_fails_by_the_rules(name):
    """No texture at all: the intensity term is flat (no gradient); the trackers still align on depth in the
    corner, and on a single blank wall, where nothing shows a sideways motion, they are rejected (singular
    system) with the prediction as the pose, as point-to-plane ICP is."""
    scene = Planes(CORNER, textured=False)
    frame = _frame(scene, MOTION)
    tracker = make_tracker(name, depth_max=5.0)
    tracker.start(np.eye(4))
    result = tracker.track(frame.depth, K, _raw_view(scene, np.eye(4)), np.eye(4), colour=_raw_colour(frame))
    assert np.all(np.isfinite(result.pose))
    assert result.ok and _error(result.pose, MOTION)[0] < 0.01
    wall = Planes(WALL, textured=False)
    true = _pose(t=(0.03, 0.0, 0.0))
    frame = _frame(wall, true)
    tracker = make_tracker(name, depth_max=5.0, motion_model="previous")
    tracker.start(np.eye(4))
    result = tracker.track(frame.depth, K, _raw_view(wall, np.eye(4)), np.eye(4), colour=_raw_colour(frame))
    assert not result.ok and "no correspondences" in result.reason
    np.testing.assert_array_equal(result.pose, np.eye(4))


@pytest.mark.slow
def test_exposure_is_estimated_before_tracking_against_the_map():
    """A frame 1.6x brighter (per channel gains) than the map: the estimate from the PREDICTED pose (2 cm, 1 deg
    off) is within 1 %, and the frame's intensity is then at the map's exposure."""
    scene = Planes(CORNER)
    response = CameraResponse.gamma()
    gains = np.array([1.6, 1.5, 1.7])
    true = MOTION
    depth, L, _, _ = scene.render(true)
    from mapping.colour import IrradianceColour

    model = IrradianceColour(response)
    rgb = response.forward((gains * 0.5 * L).astype(np.float32), dtype=np.uint8)
    colour = tracking_colour(model, rgb)
    view = _view(scene, np.eye(4), k=0.5)
    predicted = true @ _pose(_rotation((0, 1, 0), 1.0), (0.02, 0, 0))
    k = estimate_exposure(colour.colour, colour.usable, depth, K, view, predicted)
    np.testing.assert_allclose(k, gains, rtol=0.01)
    assert estimate_exposure(colour.colour, colour.usable, depth, K, view, _pose(t=(5, 0, 0))) is None


@pytest.mark.slow
def test_tracking_colour_is_in_the_units_the_map_holds():
    from mapping.colour import IrradianceColour, RawIntensity
    from mapping.exposure_compensation import CompensatedColour

    rgb = np.full((4, 5, 3), 255, np.uint8)
    rgb[0, 0] = 100
    raw = tracking_colour(RawIntensity(), rgb)
    assert raw.colour.dtype == np.float32 and not raw.estimate_exposure
    np.testing.assert_allclose(luminance(raw.colour, raw.scale)[1, 1], 1.0, rtol=1e-6)   # white at 1
    response = CameraResponse.gamma()
    irr = tracking_colour(IrradianceColour(response), rgb)
    np.testing.assert_allclose(irr.colour[0, 0], response.inverse(np.array([100, 100, 100], np.uint8)), rtol=1e-5)
    assert not irr.estimate_exposure and not irr.usable[1, 1] and irr.usable[0, 0]     # 255 is clipped
    np.testing.assert_allclose(luminance(irr.colour, irr.scale)[1, 1], 1.0, rtol=1e-5)
    assert tracking_colour(CompensatedColour(IrradianceColour(response)), rgb).estimate_exposure
    # an ablation without exposure estimation keeps the map's colours undivided: the tracker must not divide
    assert not tracking_colour(CompensatedColour(IrradianceColour(response), compensate=False), rgb).estimate_exposure


@pytest.mark.slow
def test_a_wrong_tracker_name_lists_the_valid_ones():
    assert tuple(TRACKERS) == ("auto", "icp", "hybrid", "coloured-icp")
    with pytest.raises(ValueError, match="tracker must be one of auto, icp, hybrid, coloured-icp, got 'orb'"):
        make_tracker("orb")


@pytest.fixture(scope="module")
def tiny_room(tmp_path_factory):
    from mapping.simulation.sequences import simulate_room

    return simulate_room(tmp_path_factory.mktemp("room") / "seq", seed=5, n_frames=6, width=160, height=120,
                         progress=False)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["hybrid", "coloured-icp"])
def test_reconstruct_tracker_option_end_to_end(tiny_room, tmp_path, name):
    """``radiomap reconstruct --tracker NAME`` on raw levels and on irradiance with exposure compensation:
    every frame tracked and fused, the tracker recorded in config.json, the trajectory close to the truth."""
    import json

    from click.testing import CliRunner
    from mapping.cli import cli

    for extra in ([], ["--response", str(tiny_room / "truth" / "response.npz")]):
        out = tmp_path / f"out{len(extra)}"
        res = CliRunner().invoke(cli, ["reconstruct", str(tiny_room), "-o", str(out), "--tracker", name,
                                       "--voxel-size", "0.02", "--no-progress", *extra])
        assert res.exit_code == 0, res.output
        config = json.loads((out / "config.json").read_text())
        assert config["pipeline"]["tracker"] == name
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["frames"]["fused"] == 6
        assert metrics["ate"]["rmse"] < 0.02, metrics["ate"]
        assert f"tracker {name}" in res.output


@pytest.mark.slow
def test_compare_tracker_option_end_to_end(tiny_room, tmp_path):
    import json

    from click.testing import CliRunner
    from mapping.cli import cli

    out = tmp_path / "cmp"
    res = CliRunner().invoke(cli, ["compare", str(tiny_room), "--response", str(tiny_room / "truth" / "response.npz"),
                                   "-o", str(out), "--poses", "icp", "--tracker", "hybrid", "--methods",
                                   "none,response", "--views", "0", "--no-glb", "--voxel-size", "0.02", "--no-progress"])
    assert res.exit_code == 0, res.output
    assert json.loads((out / "config.json").read_text())["parameters"]["tracker"] == "hybrid"
    assert "tracker hybrid (given)" in res.output
    none = json.loads((out / "none" / "config.json").read_text())
    assert none["tracker"]["class"] == "HybridTracker"
    assert json.loads((out / "compare.json").read_text())["pose_source"] == "hybrid tracking (tracked with 'none')"


@pytest.mark.slow
def test_a_wrong_tracker_option_lists_the_valid_ones(tiny_room, tmp_path):
    from click.testing import CliRunner
    from mapping.cli import cli

    for command in ("reconstruct", "compare"):
        res = CliRunner().invoke(cli, [command, str(tiny_room), "-o", str(tmp_path / command), "--tracker", "orb",
                                       *(["--response", str(tiny_room / "truth" / "response.npz")]
                                         if command == "compare" else [])])
        assert res.exit_code == 2
        assert "'orb' is not one of 'auto', 'icp', 'hybrid', 'coloured-icp'" in res.output
        assert not (tmp_path / command).exists()


@pytest.mark.parametrize("name", ["icp", "hybrid"])
def test_the_map_is_founded_again_when_the_first_frames_colour_is_rejected(name):
    """``_Loop._pose``: a black first frame (every pixel clipped: the clip mask fuses none of it) leaves the map
    empty, so the next frame founds it (tracking needs a map) and the others are tracked against it (was: a
    TypeError on the second frame)."""
    import dataclasses

    from box_room import box_room_sequence
    from mapping.datasets.in_memory import ArrayDataset
    from mapping.exposure_compensation import make_compensated_colour
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct

    ds, _ = box_room_sequence(n_frames=6, width=160, height=120)
    frames = list(ds.frames)
    frames[0] = dataclasses.replace(frames[0], rgb=np.zeros_like(frames[0].rgb))
    run = reconstruct(ArrayDataset(frames), colour_model=make_compensated_colour(CameraResponse.gamma(), compensate=False),
                      backend=make_backend("tsdf", voxel_size=0.02, depth_max=5.0),
                      tracker=make_tracker(name, depth_max=5.0), progress=False)
    assert [r.fused for r in run.records] == [False] + [True] * 5
    assert run.records[0].reason.startswith("colour rejected")
    np.testing.assert_array_equal(run.poses[0], frames[1].pose)        # founded at its ground truth
    assert run.ate is not None and run.ate.rmse < 0.01


@pytest.mark.parametrize("command", ["reconstruct", "compare"])
def test_a_tracker_without_tracking_is_a_one_line_error(tiny_room, tmp_path, command):
    """``--tracker hybrid`` with ground-truth poses (compare's default) would be silently ignored: refused in one
    line naming the option, nothing written."""
    from click.testing import CliRunner
    from mapping.cli import cli

    extra = ["--response", str(tiny_room / "truth" / "response.npz"), "--methods", "none,response"] \
        if command == "compare" else []
    res = CliRunner().invoke(cli, [command, str(tiny_room), "-o", str(tmp_path / "out"), "--tracker", "hybrid",
                                   "--poses", "gt", *extra])
    assert res.exit_code == 2
    assert "--tracker" in res.output and "applies with --poses icp only" in res.output
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------------------------
# the default tracker (issue 30): point-to-plane ICP, hybrid odometry where geometry does not fix the pose
# ------------------------------------------------------------------------------------------------------------
def _association(scene, pose):
    from mapping.tracking_photometric import point_to_plane_association

    depth, _, _, _ = scene.render(pose)
    view = _raw_view(scene, pose)
    q, n, r = point_to_plane_association(depth, K, view, view.depth <= 0, np.eye(4), depth_min=0.1, depth_max=5.0)
    return q, n


def test_the_condition_number_tells_a_corner_from_a_wall():
    """Three planes fix all six motions (a small, size-independent number); one wall leaves three free."""
    from mapping.tracking_auto import icp_condition

    corner = icp_condition(*_association(Planes(CORNER), np.eye(4)))
    wall = icp_condition(*_association(Planes(WALL), np.eye(4)))
    assert corner < 20 and wall > 1e6, (corner, wall)
    q, n = _association(Planes(CORNER), np.eye(4))
    assert icp_condition(q * 10, n) == pytest.approx(corner, rel=1e-6)   # metres or decimetres alike


def test_a_strided_association_is_the_sparse_image_s():
    """step=3 gives the points, normals and residuals (same bits, same order) of a full-size image holding only every
    3rd pixel of every 3rd row: what the auto tracker built before, at a tenth of the cost."""
    from mapping.tracking_photometric import point_to_plane_association

    scene = Planes(CORNER)
    depth, _, _, _ = scene.render(np.eye(4))
    view = _raw_view(scene, np.eye(4))
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.015]
    for step in (2, 3, 5):
        sparse = np.zeros_like(depth)
        sparse[::step, ::step] = depth[::step, ::step]
        want = point_to_plane_association(sparse, K, view, view.depth <= 0, T, depth_min=0.1, depth_max=5.0)
        got = point_to_plane_association(depth, K, view, view.depth <= 0, T, depth_min=0.1, depth_max=5.0, step=step)
        assert want[0].shape[1] > 100
        for a, b in zip(want, got):
            assert np.array_equal(a, b)


@pytest.mark.slow
def test_the_auto_tracker_uses_colour_where_icp_is_singular():
    """One textured wall, a sideways motion: ICP's system is singular, the auto tracker takes coloured ICP's pose
    (within 5 mm of the truth) and counts it; with hybrid odometry as the fallback, the same."""
    scene = Planes(WALL)
    true = _pose(t=(0.02, 0.0, 0.0))
    frame = _frame(scene, true)
    for fallback in ("coloured-icp", "hybrid"):
        tracker = make_tracker("auto", depth_max=5.0, motion_model="previous", fallback=fallback)
        tracker.start(np.eye(4))
        result = tracker.track(frame.depth, K, _raw_view(scene, np.eye(4)), np.eye(4), colour=_raw_colour(frame))
        assert result.ok, result.reason
        assert _error(result.pose, true)[0] < 0.005
        assert tracker.stats()["frames_by_method"] == {"icp": 0, fallback: 1, "failed": 0}
    assert make_tracker("auto").fallback == "coloured-icp"


@pytest.mark.slow
def test_the_auto_tracker_keeps_icp_where_geometry_fixes_the_pose():
    scene = Planes(CORNER)
    frame = _frame(scene, MOTION)
    auto, icp = make_tracker("auto", depth_max=5.0), make_tracker("icp", depth_max=5.0)
    results = []
    for tracker in (auto, icp):
        tracker.start(np.eye(4))
        results.append(tracker.track(frame.depth, K, _raw_view(scene, np.eye(4)), np.eye(4),
                                     colour=_raw_colour(frame)))
    assert results[0].ok and auto.stats()["frames_by_method"]["icp"] == 1
    np.testing.assert_allclose(results[0].pose, results[1].pose, atol=1e-6)   # ICP's own (threaded sums: ~1e-8)
    assert _error(results[0].pose, MOTION)[0] < 0.004


@pytest.mark.slow
def test_the_auto_tracker_fails_by_the_rules_on_a_blank_wall():
    """Nothing fixes a sideways motion on a blank wall: both fail, the frame is rejected with both reasons."""
    wall = Planes(WALL, textured=False)
    frame = _frame(wall, _pose(t=(0.03, 0.0, 0.0)))
    tracker = make_tracker("auto", depth_max=5.0, motion_model="previous")
    tracker.start(np.eye(4))
    result = tracker.track(frame.depth, K, _raw_view(wall, np.eye(4)), np.eye(4), colour=_raw_colour(frame))
    assert not result.ok and "coloured-icp" in result.reason
    np.testing.assert_array_equal(result.pose, np.eye(4))
    assert tracker.stats()["frames_by_method"]["failed"] == 1
    with pytest.raises(ValueError, match="fallback must be one of hybrid, coloured-icp"):
        make_tracker("auto", fallback="orb")
