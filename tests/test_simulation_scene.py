"""Scenes, rendering, depth sensor, trajectories and sequence files of the simulator."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mapping.simulation import (DEPTH_SCALE, MANIFEST, DepthSensor, Face, HandheldMotion, Lighting, PointLight,
                                Renderer, TexturedScene, iter_paper_frames, iter_room_frames, light_step,
                                load_room, look_at, make_paper_scene, make_room, motion_per_frame,
                                paper_trajectory, pose_to_tum, quaternion_to_rotation, room_trajectory,
                                sample_sequence,
                                simulate_brackets, simulate_paper, simulate_room, tum_to_pose)
from mapping.simulation.sequences import resolve_camera
from radiometry.errors import DatasetError, OutputError
from radiometry.images import read_depth, read_rgb
from radiometry.response import CameraResponse
from radiometry.simulation import CameraSpec, default_intrinsics


@pytest.fixture(scope="module")
def room():
    return make_room(3, texel=0.01)


def plane_scene(albedo: float = 0.5) -> TexturedScene:
    """A 20 m x 20 m floor at z = 0 with a 2-texel checker, lit by ambient light only."""
    tex = np.full((4, 4, 3), albedo, np.float32)
    tex[::2, ::2] *= 0.5
    tex[1::2, 1::2] *= 0.5
    face = Face("floor", [-10, -10, 0], [1, 0, 0], [0, 1, 0], (20.0, 20.0), tex)
    return TexturedScene([face], Lighting((np.pi, np.pi, np.pi)))


# ------------------------------------------------------------------------------------ geometry
def test_depth_of_a_known_plane_matches_the_analytic_value():
    scene = plane_scene()
    W, H = 160, 120
    K = default_intrinsics(W, H)
    eye = np.array([0.3, -0.2, 1.7])
    pose = look_at(eye, [1.0, 0.8, 0.0], roll=0.2)
    r = Renderer(scene, K, W, H).render(pose)
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d_world = d_cam @ pose[:3, :3].T
    z_expected = -eye[2] / d_world[..., 2]      # ray parameter to z = 0 == depth (unit camera-frame z)
    assert r.valid.all()
    np.testing.assert_allclose(r.depth, z_expected, rtol=2e-6, atol=2e-6)
    np.testing.assert_allclose(r.points[..., 2], 0.0, atol=2e-5)
    np.testing.assert_allclose(r.normal, np.broadcast_to([0, 0, 1], r.normal.shape))
    cos = np.abs(d_world[..., 2]) / np.linalg.norm(d_world, axis=-1)
    np.testing.assert_allclose(r.cos_incidence, cos, rtol=2e-5)
    # a fronto-parallel view: constant depth, grazing-free
    top = Renderer(scene, K, W, H).render(look_at([0, 0, 2.5], [0, 0, 0], up=[0, 1, 0]))
    np.testing.assert_allclose(top.depth, 2.5, rtol=1e-6)
    np.testing.assert_allclose(top.cos_incidence, 1 / np.linalg.norm(d_cam, axis=-1), rtol=1e-5)


def test_box_corners_project_where_K_and_the_pose_say(room):
    W, H = 320, 240
    K = default_intrinsics(W, H)
    renderer = Renderer(room, K, W, H)
    lo, hi = room.camera_bounds
    eye = (lo + hi) / 2
    checked = 0
    for box in room.boxes:
        if box.base != 0.0 or box.size[2] > eye[2] - 0.3:     # its top must be seen from above
            continue
        top = box.corners()[4:]
        corner = top[np.argmin(np.linalg.norm(top - eye, axis=1))]
        pose = look_at(eye, corner + np.array([0.25, -0.2, -0.15]))
        # independent projection: world -> camera -> pixels
        R, t = pose[:3, :3], pose[:3, 3]
        X = R.T @ (corner - t)
        u, v = K[0, 0] * X[0] / X[2] + K[0, 2], K[1, 1] * X[1] / X[2] + K[1, 2]
        (pu, pv), = renderer.project(corner[None], pose)[0]
        assert abs(pu - u) < 1e-9 and abs(pv - v) < 1e-9
        if not (3 <= u <= W - 4 and 3 <= v <= H - 4):
            continue
        # is the corner itself visible (nothing in front of it)?
        ray = np.concatenate([eye, corner - eye])[None]
        if room.occluded(ray, tnear=0.0, tfar=0.999):
            continue
        r = renderer.render(pose)
        iu, iv = int(round(u)), int(round(v))
        window = (slice(iv - 2, iv + 3), slice(iu - 2, iu + 3))
        # the rendered surface points around that pixel include the corner (to a pixel footprint)
        pts = r.points[window].reshape(-1, 3)
        footprint = X[2] / K[0, 0]
        assert np.min(np.linalg.norm(pts - corner, axis=1)) < 2.5 * footprint
        # and its top face and at least one side face meet there
        faces = {room.faces[f].name for f in np.unique(r.face[window]) if f >= 0}
        index = [i for i, b in enumerate(room.boxes) if b is box][0]
        assert any(n.startswith(f"box{index}_top") for n in faces), faces
        assert any(n.startswith(f"box{index}_side") for n in faces), faces
        # the rendered depth next to the corner agrees with the projected depth
        assert np.min(np.abs(r.depth[window] - X[2])) < 0.03
        checked += 1
    assert checked >= 2


def test_rendered_radiance_is_the_view_independent_truth(room):
    W, H = 96, 72
    K = default_intrinsics(W, H)
    renderer = Renderer(room, K, W, H)
    poses = room_trajectory(room, 200, seed=5)[::99]
    rng = np.random.default_rng(0)
    for pose in poses:
        r = renderer.render(pose)
        ys, xs = rng.integers(0, H, 200), rng.integers(0, W, 200)
        pts, nrm = r.points[ys, xs], r.normal[ys, xs]
        truth = room.radiance_at(pts, nrm)
        np.testing.assert_allclose(r.radiance[ys, xs], truth, rtol=2e-4, atol=1e-5)
        np.testing.assert_allclose(r.albedo[ys, xs], room.albedo_at(pts, nrm), rtol=2e-4, atol=1e-6)
    # a point hovering 1 cm in front of a wall gets that wall's radiance; far points can be masked
    wall = room.faces[2]
    p = wall.origin + 1.3 * wall.axis_s + 1.1 * wall.axis_t
    on = room.radiance_at(p[None])
    off = room.radiance_at((p + 0.01 * wall.normal)[None], wall.normal[None])
    np.testing.assert_allclose(on, off, rtol=1e-3)
    assert np.isnan(room.radiance_at((p + 0.5 * wall.normal)[None], max_distance=0.1)).all()


def test_texture_lookup_hits_texel_centres_exactly(room):
    face_id = 0
    f = room.faces[face_id]
    h, w = f.texture.shape[:2]
    ts, tt = f.size[0] / w, f.size[1] / h
    i, j = np.array([0, 5, h // 2, h - 1]), np.array([0, 7, w // 3, w - 1])
    coords = np.stack([(j + 0.5) * ts, f.size[1] - (i + 0.5) * tt], 1)
    np.testing.assert_allclose(room.albedo_on_faces(np.full(4, face_id), coords), f.texture[i, j], rtol=1e-5)


def test_lighting_is_lambertian_with_softened_point_lights():
    light = PointLight((0.0, 0.0, 2.0), (10.0, 20.0, 30.0), 0.5)
    lit = Lighting((1.0, 1.0, 1.0), 0.25, (light,))
    p = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 3.0]])
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    E = lit.irradiance(p, n)
    np.testing.assert_allclose(E[0], 1.25 + np.array([10, 20, 30]) / (4 + 0.25), rtol=1e-6)
    cos = 2 / np.sqrt(8)
    np.testing.assert_allclose(E[1], 1.25 + np.array([10, 20, 30]) * cos / (8 + 0.25), rtol=1e-6)
    np.testing.assert_allclose(E[2], 1.25, rtol=1e-6)      # the light is behind this surface


def test_shading_from_face_coordinates_equals_the_3d_formula(room):
    rng = np.random.default_rng(1)
    faces = rng.integers(0, len(room.faces), 5000)
    coords = rng.uniform(0, 1, (5000, 2)) * room.face_sizes[faces]
    fast = room.irradiance_on_faces(faces, coords)
    points = room.face_points(faces, coords)
    slow = room.lighting.irradiance(points, room.face_normals[faces])
    np.testing.assert_allclose(fast, slow, rtol=1e-4)
    assert fast.min() > 0 and fast.max() / np.median(fast) < 20     # smoothly varying, no hot spots


# ---------------------------------------------------------------------------------- depth sensor
def test_depth_noise_grows_with_distance_and_is_quantised():
    scene = plane_scene()
    W, H = 120, 90
    K = default_intrinsics(W, H)
    fine = DepthSensor(projector_shadow=False, dropout=0.0, edge_px=0, subpixel=1e5)   # ~no quantisation
    kinect = DepthSensor(projector_shadow=False, dropout=0.0, edge_px=0)
    stds = []
    for z in (1.0, 2.0, 3.5):
        r = Renderer(scene, K, W, H).render(look_at([0, 0, z], [0, 0, 0], up=[0, 1, 0]))
        d = fine.measure(r, rng=np.random.default_rng(1))
        assert (d > 0).mean() > 0.99
        err = d[d > 0] - z
        sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
        assert abs(err.std() / sigma - 1) < 0.05, (z, err.std(), sigma)
        assert abs(err.mean()) < 4 * sigma / np.sqrt(err.size)
        stds.append(err.std())
        q = kinect.measure(r, rng=np.random.default_rng(1))
        values = np.unique(q[q > 0])
        disparities = kinect.focal * kinect.baseline * kinect.subpixel / values
        np.testing.assert_allclose(disparities, np.round(disparities), atol=1e-3)
        assert len(values) >= 2
        steps = np.diff(values)
        np.testing.assert_allclose(steps.min(), kinect.step(z), rtol=0.1)   # ~z^2 / (f b subpixel)
    assert stds[0] < stds[1] < stds[2]


def test_depth_range_limits_and_grazing_holes():
    scene = plane_scene()
    W, H = 120, 90
    K = default_intrinsics(W, H)
    sensor = DepthSensor(projector_shadow=False, dropout=0.0, edge_px=0)
    for z in (0.3, 7.0):
        r = Renderer(scene, K, W, H).render(look_at([0, 0, z], [0, 0, 0], up=[0, 1, 0]))
        assert np.all(sensor.measure(r, rng=np.random.default_rng(0)) == 0)
    # a floor seen from 0.5 m height, looking almost horizontally: holes grow towards the horizon
    sensor = DepthSensor(projector_shadow=False, dropout=0.0, edge_px=0, z_max=50.0)
    r = Renderer(scene, K, W, H).render(look_at([-9.0, 0, 0.5], [0, 0, 0.1]))
    d = sensor.measure(r, rng=np.random.default_rng(0))
    angle = np.degrees(np.arccos(np.clip(r.cos_incidence, 0, 1)))
    steep = r.valid & (angle < 65)
    grazing = r.valid & (angle > 85)
    assert steep.sum() > 100 and grazing.sum() > 100
    assert (d[steep] > 0).mean() > 0.98
    assert (d[grazing] > 0).mean() < 0.02


def test_projector_shadow_falls_left_of_foreground_objects():
    # a wall 3 m ahead and a panel 1 m ahead, both facing the camera (normal -y)
    wall = Face("wall", [-3, 3, -3], [1, 0, 0], [0, 0, 1], (6.0, 6.0), np.full((4, 4, 3), 0.5, np.float32))
    panel = Face("panel", [-0.2, 1.0, -0.3], [1, 0, 0], [0, 0, 1], (0.4, 0.6), np.full((2, 2, 3), 0.7, np.float32))
    scene = TexturedScene([wall, panel], Lighting())
    W, H = 320, 240
    K = default_intrinsics(W, H)
    pose = look_at([0, 0, 0], [0, 1, 0])
    r = Renderer(scene, K, W, H).render(pose)
    sensor = DepthSensor(dropout=0.0, edge_px=0)
    d = sensor.measure(r, rng=np.random.default_rng(0), pose=pose, scene=scene)
    holes = (d == 0) & r.valid
    row = H // 2
    cols = np.flatnonzero(holes[row])
    panel_cols = np.flatnonzero(r.face[row] == 1)
    assert panel_cols.size > 50
    assert cols.size > 0 and cols.max() < panel_cols.min()       # the shadow is left of the panel
    assert cols.max() == panel_cols.min() - 1                     # and touches it
    expected = K[0, 0] * sensor.baseline * (1 / 1.0 - 1 / 3.0)  # disparity difference in image pixels
    assert abs(cols.size - expected) <= 1.5
    assert not holes[:, panel_cols.max() + 1:].any()             # nothing on the right


# ------------------------------------------------------------------------------------ trajectory
@pytest.mark.slow
def test_handheld_trajectory_is_smooth_inside_the_room(room):
    poses = room_trajectory(room, 300, seed=2)
    lo, hi = room.camera_bounds
    assert np.all(poses[:, :3, 3] >= lo - 1e-9) and np.all(poses[:, :3, 3] <= hi + 1e-9)
    R = poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    assert np.allclose(np.linalg.det(R), 1.0)
    trans, rot = motion_per_frame(poses)
    assert 0.008 < trans.mean() < 0.05 and trans.max() < 0.08        # ~1-5 cm per frame at 30 Hz
    assert 0.5 < rot.mean() < 3.0 and rot.max() < 5.0                 # ~1-2 degrees per frame
    accel = np.linalg.norm(np.diff(poses[:, :3, 3], 2, axis=0), axis=1)
    assert accel.max() < 0.01                                          # no jumps
    # the camera looks slightly down (y axis of the camera has a downward component) and sees the room
    assert np.all(poses[:, 2, 2] < 0.2)
    faster = room_trajectory(room, 300, seed=2, motion=HandheldMotion(speed=2.0))
    assert motion_per_frame(faster)[0].mean() > 1.6 * trans.mean()
    again = room_trajectory(room, 100, seed=2)
    np.testing.assert_array_equal(again, poses[:100])                  # prefix-stable and deterministic


def test_tum_pose_round_trip():
    rng = np.random.default_rng(0)
    poses = [look_at(rng.normal(size=3), rng.normal(size=3) + [0, 0, 5], roll=rng.uniform(-3, 3)) for _ in range(20)]
    for angle in (np.pi, np.pi - 1e-9):          # half turns: the numerically delicate case
        for axis in np.eye(3):
            T = np.eye(4)
            T[:3, :3] = quaternion_to_rotation(np.append(axis * np.sin(angle / 2), np.cos(angle / 2)))
            poses.append(T)
    for pose in poses:
        t, q = pose_to_tum(pose)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1) < 1e-12
        np.testing.assert_allclose(tum_to_pose(t, q), pose, atol=1e-12)
    # the TUM convention: qx qy qz qw of a 90 degree turn about z
    T = np.eye(4)
    T[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    np.testing.assert_allclose(pose_to_tum(T)[1], [0, 0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)


def test_paper_sweep_covers_every_pixel_many_times():
    scene = make_paper_scene(1)
    W, H = 80, 60
    K = default_intrinsics(W, H)
    poses = paper_trajectory(150, K, W, H, seed=1)
    heights = poses[:, 2, 3] - 0.0
    assert heights.min() > 0.29 and heights.max() < 0.51
    cam = resolve_camera(CameraSpec.preset("xtion", width=W, height=H))
    cover = np.zeros((H, W), int)
    prev_centre, tracked = None, []
    for fr in iter_paper_frames(scene, cam, poses, K=K, seed=1):
        mask = fr.render.face == scene.sheet_face
        assert mask.mean() > 0.05                               # the sheet never leaves the view
        cover += mask
        sheet, desk = fr.rgb[mask], fr.rgb[(fr.render.face == 0)]
        if sheet.size and desk.size:
            assert sheet.mean() > desk.mean() + 60
        assert fr.rgb.max() < 255                               # fixed exposure with headroom: no clipping
        ys, xs = np.nonzero(mask)
        if prev_centre is not None:                             # a flood fill seeded at the last centre works
            tracked.append(bool(mask[int(round(prev_centre[1])), int(round(prev_centre[0]))]))
        prev_centre = (xs.mean(), ys.mean())
    assert np.mean(tracked) > 0.95
    assert cover.min() >= 12 and np.median(cover) > 30
    assert cover[0, 0] >= 12 and cover[-1, -1] >= 12 and cover[0, -1] >= 12 and cover[-1, 0] >= 12


# ----------------------------------------------------------------------------- room persistence
def test_room_is_regenerated_exactly_from_room_json(tmp_path, room):
    path = room.save(tmp_path / "room.json")
    again = load_room(path)
    assert again.checksum() == room.checksum()
    np.testing.assert_array_equal(again.vertices, room.vertices)
    other = make_room(4, texel=0.01)
    assert other.checksum(textures=False) != room.checksum(textures=False)
    data = json.loads(path.read_text())
    data["seed"] = 4
    path.write_text(json.dumps(data))
    with pytest.raises(DatasetError, match="geometry differs"):
        load_room(path)
    path.write_text(json.dumps({"format": "nope"}))
    with pytest.raises(DatasetError, match="not a radiomap room"):
        load_room(path)
    with pytest.raises(DatasetError, match="no such room"):
        load_room(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="unknown room parameters"):
        make_room(0, windows=3)
    with pytest.raises(ValueError, match="size must be"):
        make_room(0, size=(1.0, 5.0, 2.5))


def test_room_contents(room):
    names = [f.name for f in room.faces]
    assert names[:6] == ["floor", "ceiling", "wall_south", "wall_east", "wall_north", "wall_west"]
    assert len(room.boxes) >= 5
    centre = np.array(room.size) / 2
    for f in room.faces[:6]:      # walls, floor and ceiling face the inside of the room
        mid = f.origin + f.axis_s * f.size[0] / 2 + f.axis_t * f.size[1] / 2
        assert np.dot(centre - mid, f.normal) > 0
    lo, hi = room.camera_bounds
    for b in room.boxes:          # furniture stays out of the camera region and faces outwards
        x0, x1, y0, y1 = b.footprint_aabb()
        assert x1 < lo[0] or x0 > hi[0] or y1 < lo[1] or y0 > hi[1]
    for f in room.faces[6:]:
        box_faces = [g for g in room.faces if g.name.split("_")[0] == f.name.split("_")[0]]
        c = np.mean([g.origin + g.axis_s * g.size[0] / 2 + g.axis_t * g.size[1] / 2 for g in box_faces], 0)
        mid = f.origin + f.axis_s * f.size[0] / 2 + f.axis_t * f.size[1] / 2
        assert np.dot(mid - c, f.normal) > 0
    # textures have edges and fine detail: strong gradients exist on most faces
    detailed = sum(np.abs(np.diff(f.texture, axis=1)).max() > 0.15 for f in room.faces)
    assert detailed >= len(room.faces) // 2


# ------------------------------------------------------------------------------------ sequences
@pytest.mark.slow
def test_room_sequence_files_and_truth(tmp_path, room):
    W, H, n = 96, 72, 6
    out = simulate_room(tmp_path / "seq", seed=4, n_frames=n, width=W, height=H, room=room, progress=False,
                        mesh_spacing=0.25)
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["format"] == "radiomap-sim" and manifest["version"] == 1 and manifest["kind"] == "room"
    assert (manifest["width"], manifest["height"], manifest["n_frames"], manifest["depth_scale"]) == (W, H, n, 5000)
    K = np.array(manifest["K"])
    np.testing.assert_allclose(np.loadtxt(out / "intrinsics.txt"), K)
    rgb_list = [ln.split() for ln in (out / "rgb.txt").read_text().splitlines() if not ln.startswith("#")]
    depth_list = [ln.split() for ln in (out / "depth.txt").read_text().splitlines() if not ln.startswith("#")]
    assert (out / "rgb.txt").read_text().startswith("# ")
    assert len(rgb_list) == len(depth_list) == n
    ts = np.array([float(t) for t, _ in rgb_list])
    np.testing.assert_allclose(np.diff(ts), 1 / 30, atol=2e-6)
    assert rgb_list[0][1] == f"rgb/{rgb_list[0][0]}.png"
    gt = np.loadtxt(out / "groundtruth.txt")
    assert gt.shape == (n, 8)
    poses = room_trajectory(room, n, seed=4)
    for row, pose in zip(gt, poses):
        np.testing.assert_allclose(tum_to_pose(row[1:4], row[4:8]), pose, atol=1e-7)
    # the frames on disk are the in-memory frames
    cam = resolve_camera(CameraSpec.load(out / "truth" / "camera.json"))
    frames = list(iter_room_frames(room, cam, poses, K=K, seed=4))
    for (t, rgb_name), (_, depth_name), fr in zip(rgb_list, depth_list, frames):
        np.testing.assert_array_equal(read_rgb(out / rgb_name), fr.rgb)
        np.testing.assert_allclose(read_depth(out / depth_name, DEPTH_SCALE), fr.depth, atol=0.5 / DEPTH_SCALE + 1e-6)
        assert (fr.depth > 0).mean() > 0.7
    exposures = np.loadtxt(out / "truth" / "exposures.txt")
    assert exposures.shape == (n, 5)
    np.testing.assert_allclose(exposures[:, 1], [f.exposure_time for f in frames], rtol=1e-8)
    np.testing.assert_allclose(exposures[:, 2:], [f.gains for f in frames], rtol=1e-8)
    V = np.load(out / "truth" / "vignetting.npy")
    assert V.dtype == np.float32 and V.shape == (H, W, 3)
    np.testing.assert_array_equal(V, cam.vignetting)
    np.testing.assert_array_equal(CameraResponse.load(out / "truth" / "response.npz").inverse_table,
                                  cam.response.inverse_table)
    assert load_room(out / "truth" / "room.json").checksum() == room.checksum()
    assert (out / "truth" / "room_mesh.ply").stat().st_size > 1000
    light = np.loadtxt(out / "truth" / "light_scale.txt")
    np.testing.assert_array_equal(light[:, 1], 1.0)


@pytest.mark.slow
def test_sequences_are_deterministic_for_a_seed(tmp_path, room):
    def pngs(path):
        return [p.read_bytes() for p in sorted(path.glob("*/*.png"))]

    kw = dict(n_frames=3, width=64, height=48, room=room, progress=False, mesh_spacing=0.5)
    a = simulate_room(tmp_path / "a", seed=9, **kw)
    b = simulate_room(tmp_path / "b", seed=9, **kw)
    c = simulate_room(tmp_path / "c", seed=10, **kw)
    assert pngs(a) == pngs(b)
    assert pngs(a) != pngs(c)
    assert (a / "groundtruth.txt").read_bytes() == (b / "groundtruth.txt").read_bytes()
    # a room generated from a seed is the same room every time
    assert make_room(21, texel=0.02).checksum() == make_room(21, texel=0.02).checksum()
    with pytest.raises(OutputError, match="not empty"):
        simulate_room(a, seed=9, **kw)
    simulate_room(a, seed=9, force=True, **{**kw, "n_frames": 2})
    assert len(list((a / "rgb").glob("*.png"))) == 2       # stale frames of the earlier run are gone


def test_auto_exposure_follows_a_dimming_light_in_the_room(room):
    W, H, n = 64, 48, 70
    K = default_intrinsics(W, H)
    cam = resolve_camera(CameraSpec.preset("xtion", width=W, height=H))
    poses = np.repeat(room_trajectory(room, 1, seed=3), n, axis=0)      # a still camera
    frames = list(iter_room_frames(room, cam, poses, K=K, seed=3, light_scale=light_step(n, 0.5),
                                   depth_sensor=None))
    ks = np.array([f.exposure_time for f in frames])
    means = np.array([f.rgb.reshape(-1, 3).mean(0) @ [0.299, 0.587, 0.114] for f in frames])
    target = 0.45 * 255
    assert np.all(np.abs(means[:35] - target) < 12)                    # settled before recording
    assert means[35] < target - 12                                      # the light goes down...
    assert np.all(np.abs(means[55:] - target) < 12)                     # ...and AE brings it back
    assert abs(ks[-1] / ks[30] - 2.0) < 0.25
    fixed = list(iter_room_frames(room, cam, poses[:40], K=K, seed=3, auto_exposure=False,
                                  light_scale=light_step(40, 0.5), depth_sensor=None))
    assert len({f.exposure_time for f in fixed}) == 1 and len({tuple(f.gains) for f in fixed}) == 1
    assert fixed[-1].rgb.mean() < fixed[0].rgb.mean() - 20


@pytest.mark.slow
def test_paper_sequence_files(tmp_path):
    out = simulate_paper(tmp_path / "paper", seed=2, n_frames=8, width=64, height=48, flicker=0.1, progress=False)
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["kind"] == "paper" and manifest["exposure"] == "fixed"
    assert len(list((out / "rgb").glob("*.png"))) == 8 and len(list((out / "truth" / "masks").glob("*.png"))) == 8
    exposures = np.loadtxt(out / "truth" / "exposures.txt")
    assert np.all(exposures[:, 1] == exposures[0, 1])
    light = np.loadtxt(out / "truth" / "light_scale.txt")[:, 1]
    assert light.std() > 0.005 and np.all(np.abs(light - 1) <= 0.1 + 1e-12)
    paper = json.loads((out / "truth" / "paper.json").read_text())
    assert paper["sheet_albedo"] == 0.85 and len(paper["sheet_corners"]) == 4
    mask = read_rgb(sorted((out / "truth" / "masks").glob("*.png"))[0])
    assert set(np.unique(mask)) <= {0, 255}


@pytest.mark.slow
def test_bracket_sequence_files(tmp_path):
    out = simulate_brackets(tmp_path / "br", seed=1, width=96, height=72, progress=False)
    lines = (out / "times.txt").read_text().splitlines()
    assert len(lines) == 9
    names, times = zip(*(ln.split() for ln in lines))
    np.testing.assert_allclose([float(t) for t in times], 0.001 * 2.0 ** np.arange(9))
    means = [read_rgb(out / n).mean() for n in names]
    assert np.all(np.diff(means) > 0)
    imgs = np.stack([read_rgb(out / n) for n in names])
    # every level is populated somewhere in the stack and each pixel is well exposed in some image
    assert len(np.unique(imgs)) > 250
    well = ((imgs > 20) & (imgs < 235)).any(axis=0)
    assert well.mean() > 0.95
    radiance = np.load(out / "truth" / "radiance.npy")
    assert radiance.shape == (72, 96, 3) and radiance.max() / radiance.min() > 1000


@pytest.mark.slow
def test_sample_sequence_is_generated_once(tmp_path):
    path = sample_sequence("brackets", root=tmp_path)
    assert (path / "times.txt").is_file() and (path / "sample.json").is_file()
    stamp = (path / "exposure_00.png").stat().st_mtime_ns
    assert sample_sequence("brackets", root=tmp_path) == path
    assert (path / "exposure_00.png").stat().st_mtime_ns == stamp
    with pytest.raises(ValueError, match="valid names: room, paper, brackets"):
        sample_sequence("kitchen", root=tmp_path)


@pytest.mark.slow
def test_sequence_argument_errors(tmp_path):
    with pytest.raises(ValueError, match="n_frames must be a whole number >= 1"):
        simulate_room(tmp_path / "a", n_frames=0)
    with pytest.raises(ValueError, match="flicker amplitude"):
        simulate_paper(tmp_path / "b", n_frames=2, width=32, height=24, flicker=0.7, progress=False)
    with pytest.raises(ValueError, match="positive exposure times"):
        simulate_brackets(tmp_path / "c", times=[0.01, -1.0], width=32, height=24)
    with pytest.raises(ValueError, match="unknown bracket scene"):
        simulate_brackets(tmp_path / "d", scene="sky", width=32, height=24, progress=False)
    assert not (tmp_path / "b").exists() and not (tmp_path / "d").exists()     # nothing half-made
    with pytest.raises(TypeError, match="camera must be a preset name"):
        simulate_brackets(tmp_path / "e", camera=42)
    with pytest.raises(ValueError, match="valid names: xtion, asymmetric, mild, ideal"):
        simulate_brackets(tmp_path / "f", camera="webcam")
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match="is an existing file"):
        simulate_brackets(tmp_path / "file", width=32, height=24)
    with pytest.raises(ValueError, match="light_scale must have one value per frame"):
        list(iter_room_frames(make_room(0, texel=0.05, n_boxes=0), resolve_camera("ideal", 32, 24),
                              np.repeat(np.eye(4)[None], 3, 0), K=default_intrinsics(32, 24), seed=0,
                              light_scale=[1.0, 2.0]))
