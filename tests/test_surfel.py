"""The ElasticFusion-style surfel backend (mapping.fusion.surfel) on analytic scenes with known geometry and
colour, on the simulated room, and on the 7-Scenes sample."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from mapping.fusion.base import ColourPairs, ModelView
from mapping.fusion.surfel import SurfelBackend, SurfelMap, vertex_normal_maps, write_surfel_ply
from mapping.simulation.trajectory import look_at

W, H, F = 160, 120, 131.25  # a Kinect-like camera at a quarter of 640x480
C_STABLE = 10.0
EXP_CORNER = math.exp(-1.0 / 0.72)  # per-sample confidence at rho = 1 (image corner), sigma = 0.6
UP = (0.0, -1.0, 0.0)  # the analytic scenes' world up for look_at: -y (world axes as the first camera's)


# --------------------------------------------------------------------------------------------------
# analytic scenes
# --------------------------------------------------------------------------------------------------
def intrinsics(w: int = W, h: int = H, f: float = F) -> np.ndarray:
    return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])


def translation(x=0.0, y=0.0, z=0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = (x, y, z)
    return pose


def albedo(p: np.ndarray) -> np.ndarray:
    """A smooth colour field over world points (..., 3) -> (..., 3), levels in [40, 220]."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.stack([130 + 60 * np.sin(1.3 * x + 0.4) * np.cos(0.9 * y),
                     120 + 70 * np.sin(0.8 * y + 1.1 * z),
                     125 + 65 * np.cos(1.0 * z - 0.7 * x)], axis=-1)


def render(pose, K=None, w=W, h=H, *, room=((-3, -3, -1), (3, 3, 2)), boxes=()):
    """Depth along the optical axis and world points of the inside of an axis-aligned room, with solid
    axis-aligned boxes ``(lo, hi)`` in it (exact ray casting)."""
    K = intrinsics(w, h) if K is None else K
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], -1).reshape(-1, 3)
    d = rays @ pose[:3, :3].T
    o = pose[:3, 3]
    lo, hi = (np.asarray(a, float) for a in room)
    with np.errstate(divide="ignore", invalid="ignore"):
        tb = np.where(d > 0, (hi - o) / d, (lo - o) / d)
        t = np.min(np.where(np.isfinite(tb) & (tb > 0), tb, np.inf), axis=1)
        for blo, bhi in boxes:
            t1 = (np.asarray(blo, float) - o) / d
            t2 = (np.asarray(bhi, float) - o) / d
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tmax >= tmin) & (tmin > 0) & (tmin < t)
            t = np.where(hit, tmin, t)
    pts = (o + d * t[:, None]).reshape(h, w, 3)
    return t.reshape(h, w).astype(np.float32), pts


def uniform(colour, h=H, w=W) -> np.ndarray:
    return np.broadcast_to(np.asarray(colour, np.float32), (h, w, 3)).copy()


def fuse(backend, frames, K=None, start=0):
    K = intrinsics() if K is None else K
    pairs = []
    for i, (depth, colour, pose) in enumerate(frames):
        pairs.append(backend.integrate(depth, colour, K, pose, frame_index=start + i))
    return pairs


def project(points, pose, K):
    Tcw = np.linalg.inv(pose)
    pc = points @ Tcw[:3, :3].T + Tcw[:3, 3]
    return np.stack([K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2], K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]], 1), pc


def alpha_of(uv, K, w=W, h=H):
    rho2 = ((uv[:, 0] - K[0, 2]) ** 2 + (uv[:, 1] - K[1, 2]) ** 2) / (0.25 * (w * w + h * h))
    return np.exp(-rho2 / 0.72)


# --------------------------------------------------------------------------------------------------
# the measurement: colour pairs before averaging
# --------------------------------------------------------------------------------------------------
def test_colour_pairs_are_the_map_colour_before_averaging_and_the_new_sample():
    A, B, C = (100.0, 50.0, 200.0), (160.0, 80.0, 20.0), (10.0, 250.0, 90.0)
    depth, _ = render(np.eye(4))
    b = SurfelBackend()
    first = b.integrate(depth, uniform(A), intrinsics(), np.eye(4), frame_index=0)
    assert isinstance(first, ColourPairs) and len(first) == 0  # nothing to compare against yet
    n0 = len(b.map)
    assert n0 > 4000

    conf0 = b.map.confidence.copy()
    pairs = b.integrate(depth, uniform(B), intrinsics(), np.eye(4), frame_index=1)
    assert pairs.map_colour.dtype == np.float32 and pairs.sample_colour.dtype == np.float32
    assert pairs.map_colour.shape == pairs.sample_colour.shape == (len(pairs), 3)
    assert len(pairs) >= 0.97 * n0  # the second lattice finds (nearly) every surfel of the first
    np.testing.assert_array_equal(pairs.map_colour, np.tile(np.float32(A), (len(pairs), 1)))
    np.testing.assert_array_equal(pairs.sample_colour, np.tile(np.float32(B), (len(pairs), 1)))
    assert len(b.map) - n0 < 0.03 * n0  # no duplicates of the wall

    # the merge is the confidence-weighted mean (c0 * A + a * B) / (c0 + a), a = the sample's weight
    conf1 = b.map.confidence[:n0]
    col = b.map.colour[:n0]
    merged = conf1 > conf0
    assert merged.sum() == len(pairs)
    a = (conf1 - conf0)[merged, None]
    expect = (conf0[merged, None] * np.float32(A) + a * np.float32(B)) / conf1[merged, None]
    np.testing.assert_allclose(col[merged], expect, rtol=1e-5)
    np.testing.assert_allclose(col[merged], np.tile((np.add(A, B)) / 2, (merged.sum(), 1)), atol=3)

    # the next pairs compare against the averaged colour, not the first one
    before = {tuple(c) for c in col[merged]}
    third = b.integrate(depth, uniform(C), intrinsics(), np.eye(4), frame_index=2)
    assert len(third) >= 0.97 * n0
    assert {tuple(c) for c in third.map_colour} <= before | {tuple(np.float32(A))}
    np.testing.assert_array_equal(third.sample_colour, np.tile(np.float32(C), (len(third), 1)))


def test_pairs_follow_the_radius_gate():
    """A sample from much farther away (radius >= 1.5x the surfel's) only raises the confidence: its colour
    is not averaged in, so no pair is recorded (ElasticFusion update.vert)."""
    b = SurfelBackend()
    room = ((-8, -8, -1), (8, 8, 2))
    near, _ = render(translation(z=1.2), room=room)  # wall 0.8 m away
    far, _ = render(np.eye(4), room=room)  # wall 2.0 m away: radius 2.5x larger
    b.integrate(near, uniform((50, 50, 50)), intrinsics(), translation(z=1.2), frame_index=0)
    conf0 = b.map.confidence.copy()
    pairs = b.integrate(far, uniform((200, 200, 200)), intrinsics(), np.eye(4), frame_index=1)
    s = b.surfels()
    old = s["created"] == 0
    assert len(pairs) == 0
    np.testing.assert_array_equal(s["colour"][old], np.full((old.sum(), 3), 50, np.float32))
    assert np.count_nonzero(b.map.confidence[: conf0.size] > conf0) > 0.2 * conf0.size  # confidence did rise


# --------------------------------------------------------------------------------------------------
# association: the normal gate and the index map's resolution
# --------------------------------------------------------------------------------------------------
def tilted_wall(theta_deg: float, K=None, w=W, h=H, z0=2.0, max_depth=3.5):
    """Depth of a plane through the line x = 0, z = z0 (identity pose), turned by ``theta_deg`` about the y
    axis: at 0 degrees the wall z = z0, else a plane crossing it along that line."""
    K = intrinsics(w, h) if K is None else K
    up = (np.arange(w) - K[0, 2]) / K[0, 0]
    z = z0 / (1.0 - math.tan(math.radians(theta_deg)) * up)
    z = np.where((z > 0) & (z < max_depth), z, 0.0)
    return np.ascontiguousarray(np.broadcast_to(z, (h, w)), dtype=np.float32)


@pytest.mark.parametrize("theta, merged", [(15.0, True), (45.0, False)])
def test_crossing_planes_merge_only_within_the_normal_gate(theta, merged):
    """A wall, then a plane crossing it along x = 0. Near the crossing line the second plane's samples lie
    within the depth gate of the wall's surfels; at 15 degrees (inside the 28.6 degree gate) they are merged
    into them, at 45 degrees (outside) they make new surfels and the wall keeps its colour."""
    K = intrinsics()
    A, B = (200.0, 0.0, 0.0), (0.0, 200.0, 0.0)
    b = SurfelBackend()
    b.integrate(tilted_wall(0.0), uniform(A), K, np.eye(4), frame_index=0)
    n0 = len(b.map)
    pairs = b.integrate(tilted_wall(theta), uniform(B), K, np.eye(4), frame_index=1)
    s = b.surfels()
    near = np.abs(s["position"][:, 0]) < 0.05   # within 5 cm of the crossing line
    wall = near & (s["created"] == 0)
    new = near & (s["created"] == 1)
    assert wall.sum() > 100
    if merged:
        assert len(pairs) > 100 and np.all(pairs.map_colour == np.float32(A))
        assert np.count_nonzero(s["colour"][wall, 1] > 0) > 0.9 * wall.sum()   # the wall took some green
        assert new.sum() < 0.1 * wall.sum()
    else:
        assert len(pairs) == 0
        np.testing.assert_array_equal(s["colour"][wall], np.tile(np.float32(A), (wall.sum(), 1)))
        assert new.sum() > 0.5 * wall.sum()   # the second plane's own surfels, crossing the wall's
        assert len(b.map) - n0 == b.last_frame["samples"]


@pytest.mark.parametrize("tilt, gate, merged", [(20.0, None, True), (35.0, None, False), (35.0, 40.0, True)])
def test_surfels_whose_normals_differ_beyond_the_gate_are_not_associated(tilt, gate, merged):
    """The same wall seen twice, the first frame's surfel normals turned by ``tilt`` degrees in between (not
    grazing: |n_z| > 0.75): within the gate (default 28.6 degrees, or ``normal_gate_deg``) every sample
    finds its surfel, beyond it none does and every sample creates a surfel."""
    K = intrinsics()
    depth, _ = render(np.eye(4))
    b = SurfelBackend() if gate is None else SurfelBackend(normal_gate_deg=gate)
    b.integrate(depth, uniform((1, 1, 1)), K, np.eye(4), frame_index=0)
    n0 = len(b.map)
    t = math.radians(tilt)
    b.map.array("normal")[:n0] = np.float32([math.sin(t), 0.0, -math.cos(t)])
    pairs = b.integrate(depth, uniform((2, 2, 2)), K, np.eye(4), frame_index=1)
    if merged:
        assert len(pairs) >= 0.97 * n0 and len(b.map) - n0 < 0.03 * n0
    else:
        assert len(pairs) == 0 and b.last_frame["associated"] == 0
        assert len(b.map) - n0 == b.last_frame["samples"] > 0.97 * n0


@pytest.mark.parametrize("scale", [1, 4])
def test_a_finer_index_map_finds_surfels_that_share_a_pixel(scale):
    """Every pixel fused (``pixel_stride=1``) at 2 m, then the camera steps back 0.4 m: the wall's surfels
    are now denser than the pixels. An index map at image resolution keeps one surfel per pixel (the
    nearest) and the others are never refined; at 4x4 texels per pixel (Keller et al.) every one is."""
    K = intrinsics()
    near, far = np.eye(4), translation(z=-0.4)
    b = SurfelBackend(pixel_stride=1, index_scale=scale)
    b.integrate(render(near)[0], uniform((1, 1, 1)), K, near, frame_index=0)
    n0 = len(b.map)
    conf0 = b.map.confidence.copy()
    pairs = b.integrate(render(far)[0], uniform((2, 2, 2)), K, far, frame_index=1)
    refined = int(np.count_nonzero(b.map.confidence[:n0] > conf0))
    assert refined == b.last_frame["refined"] == len(pairs)
    if scale == 4:
        assert refined == n0
    else:
        assert refined < 0.8 * n0


# --------------------------------------------------------------------------------------------------
# confidence weighting
# --------------------------------------------------------------------------------------------------
def test_sample_confidence_falls_off_with_the_distance_from_the_principal_point():
    K = intrinsics()
    depth, _ = render(np.eye(4))
    b = SurfelBackend()
    b.integrate(depth, uniform((1, 2, 3)), K, np.eye(4))
    s = b.surfels()
    uv, _ = project(s["position"].astype(np.float64), np.eye(4), K)
    np.testing.assert_allclose(s["confidence"], alpha_of(uv, K), rtol=1e-4)
    assert s["confidence"].max() > 0.99
    corner = np.hypot(uv[:, 0] - K[0, 2], uv[:, 1] - K[1, 2]) > 0.95 * math.hypot(W / 2, H / 2)
    assert corner.any() and np.all(s["confidence"][corner] < 1.05 * math.exp(-0.95 ** 2 / 0.72))
    assert s["confidence"].min() > 0.98 * EXP_CORNER


def test_border_samples_move_the_colour_less_than_central_ones():
    """A surfel seen at the centre (weight ~1) and then at the border of a shifted view moves a quarter of
    the way to the new colour; one seen first at the border and then at the centre moves most of the way."""
    K = intrinsics()
    A, B = 40.0, 200.0
    shift = translation(x=0.9)  # 0.9 m sideways at 2 m: about 59 px of the 160 px image
    b = SurfelBackend()
    b.integrate(render(np.eye(4))[0], uniform((A, A, A)), K, np.eye(4), frame_index=0)
    s0 = b.surfels()
    b.integrate(render(shift)[0], uniform((B, B, B)), K, shift, frame_index=1)
    s1 = b.surfels()
    old = s1["created"] == 0
    moved = (s1["colour"][old, 0] - A) / (B - A)
    merged = moved > 0
    assert merged.sum() > 1000
    uv0, _ = project(s0["position"][merged].astype(float), np.eye(4), K)
    uv1, _ = project(s1["position"][old][merged].astype(float), shift, K)
    a0, a1 = alpha_of(uv0, K), alpha_of(uv1, K)
    np.testing.assert_allclose(moved[merged], a1 / (a0 + a1), atol=0.03)
    centre_first = a0 > 0.95
    border_first = a0 < 0.45
    assert centre_first.sum() > 50 and border_first.sum() > 50
    assert np.median(moved[merged][centre_first]) < 0.4  # now near the left border: little weight
    assert np.median(moved[merged][border_first]) > 0.65  # now near the centre: most of the weight


# --------------------------------------------------------------------------------------------------
# convergence
# --------------------------------------------------------------------------------------------------
def _orbit(i: int) -> np.ndarray:
    return look_at([0.25 * math.sin(i / 5), 0.15 * math.cos(i / 7), -0.6 + 0.02 * i],
                   [0.4 * math.sin(i / 9), 0.1 * math.cos(i / 6), 2.0], up=UP)


def test_stable_colours_converge_to_the_true_colour_with_noisy_samples():
    K = intrinsics(320, 240, 262.5)
    room = ((-2, -1.5, -2), (2, 1.5, 2))
    rng = np.random.default_rng(3)
    sigma = 8.0
    b = SurfelBackend()
    for i in range(30):
        pose = _orbit(i)
        depth, pts = render(pose, K, 320, 240, room=room)
        depth = depth + rng.normal(0, 0.002, depth.shape).astype(np.float32)
        colour = (albedo(pts) + rng.normal(0, sigma, pts.shape)).astype(np.float32)
        b.integrate(depth, colour, K, pose, frame_index=i)
    s = b.surfels(stable_only=True)
    assert s["colour"].dtype == np.float32
    assert s["position"].shape[0] > 10000
    assert np.all(s["confidence"] >= C_STABLE)
    err = np.abs(s["colour"] - albedo(s["position"].astype(np.float64))).mean()
    per_sample = sigma * math.sqrt(2 / math.pi)  # mean |noise| of one sample
    assert err < 0.3 * per_sample, (err, per_sample)
    # geometry: stable surfels lie on the walls
    p = s["position"].astype(np.float64)
    wall = np.min(np.abs(np.concatenate([p - np.array(room[0]), np.array(room[1]) - p], 1)), 1)
    assert np.median(wall) < 0.002 and np.percentile(wall, 99) < 0.01


def test_simulated_room_stable_surfels_average_the_noise_away():
    """The simulated room (sensor depth: noise, quantisation, holes) with ground-truth poses, fused twice: with
    radiance samples carrying 6 % noise and without. Association never looks at colour, so both runs build
    the same surfels; their colour difference is what is left of the sample noise after averaging. The
    noise-free run shows the floor set by the texture (5 % change per pixel) blurred over a surfel's reach."""
    from mapping import simulation as sim
    from radiometry.simulation import default_intrinsics

    w, h = 320, 240
    K = default_intrinsics(w, h)
    room = sim.make_room(0)
    poses = sim.room_trajectory(room, 24, seed=0)
    renderer = sim.Renderer(room, K, w, h)
    sensor = sim.DepthSensor()
    rng = np.random.default_rng(0)
    views = []
    for pose in poses:
        r = renderer.render(pose)
        views.append((sensor.measure(r, rng=rng, pose=pose, scene=room), r.radiance, pose))
    noise = 0.06
    noisy, clean = SurfelBackend(depth_max=4.0), SurfelBackend(depth_max=4.0)
    per_sample = []
    for i, (depth, radiance, pose) in enumerate(views):
        colour = (radiance * (1 + rng.normal(0, noise, radiance.shape))).astype(np.float32)
        ok = depth > 0
        per_sample.append(np.abs(colour[ok] - radiance[ok]).mean() / radiance[ok].mean())
        noisy.integrate(depth, colour, K, pose, frame_index=i)
        clean.integrate(depth, radiance, K, pose, frame_index=i)
    a, b = noisy.surfels(stable_only=True), clean.surfels(stable_only=True)
    assert a["position"].shape[0] > 10000
    np.testing.assert_array_equal(a["position"], b["position"])  # same geometry, deterministic
    residual = np.abs(a["colour"] - b["colour"]).mean() / b["colour"].mean()
    assert residual < 0.3 * np.mean(per_sample), (residual, np.mean(per_sample))
    truth = room.radiance_at(b["position"].astype(np.float64), b["normal"].astype(np.float64), max_distance=0.05)
    good = np.all(np.isfinite(truth), axis=1)
    assert good.mean() > 0.97  # stable surfels lie on the room's surfaces
    floor = np.abs(b["colour"][good] - truth[good]).mean() / truth[good].mean()
    assert floor < 0.05, floor


# --------------------------------------------------------------------------------------------------
# clean-up
# --------------------------------------------------------------------------------------------------
def test_unstable_surfels_are_removed_after_the_window_and_stable_ones_kept():
    K = intrinsics()
    depth, _ = render(np.eye(4))
    b = SurfelBackend(unstable_window=20)
    fuse(b, [(depth, uniform((9, 9, 9)), np.eye(4))] * 12)
    conf = b.map.confidence
    n_stable = int(np.count_nonzero(conf >= C_STABLE))
    n_unstable = int(np.count_nonzero(conf < C_STABLE))
    assert n_stable > 1000 and n_unstable > 1000  # the border never reaches 10 in 12 frames (weight < 0.8)
    empty = (np.zeros_like(depth), uniform((0, 0, 0)), np.eye(4))
    fuse(b, [empty] * 20, start=12)  # last update at frame 11; 31 - 11 = 20: not yet beyond the window
    assert b.stats()["surfels"] == n_stable + n_unstable
    fuse(b, [empty], start=32)
    assert b.stats()["surfels"] == n_stable
    assert np.all(b.surfels()["confidence"] >= C_STABLE)
    view = b.render(np.eye(4), K, H, W)  # render applies the rule too: only stable surfels remain to draw
    assert (view.depth[6:-6, 6:-6] > 0).mean() < 0.9


def test_free_space_violations_are_removed():
    """A plate 1.5 m in front of the wall is fused until stable, then taken away: once the wall behind it is
    stable, the plate's surfels lie in front of surfaces the sensor sees through them and are removed."""
    plate = ((-0.3, -0.3, 1.5), (0.3, 0.3, 1.52))
    frames_with = []
    frames_without = []
    for i in range(40):
        pose = translation(0.03 * math.sin(i / 3), 0.02 * math.cos(i / 4), 0.0)
        frames_with.append((render(pose, boxes=[plate])[0], uniform((200, 0, 0)), pose))
        frames_without.append((render(pose)[0], uniform((0, 200, 0)), pose))
    b = SurfelBackend()
    fuse(b, frames_with[:15])
    s = b.surfels()
    on_plate = np.abs(s["position"][:, 2] - 1.5) < 0.05
    assert np.count_nonzero(on_plate & (s["confidence"] >= C_STABLE)) > 300
    fuse(b, frames_without[15:40], start=15)
    s = b.surfels()
    assert np.count_nonzero(np.abs(s["position"][:, 2] - 1.5) < 0.05) == 0
    behind = (np.abs(s["position"][:, 2] - 2.0) < 0.02) & (np.abs(s["position"][:, 0]) < 0.25) \
        & (np.abs(s["position"][:, 1]) < 0.25) & (s["confidence"] >= C_STABLE)
    assert behind.sum() > 200  # the wall that was hidden is now in the map (about 270 surfels there)


def test_newer_duplicate_layer_in_front_of_a_stable_surface_is_removed():
    depth, _ = render(np.eye(4))
    b = SurfelBackend()
    fuse(b, [(depth, uniform((5, 5, 5)), np.eye(4))] * 14)
    s = b.surfels(stable_only=True)
    centre = np.hypot(s["position"][:, 0], s["position"][:, 1]) < 0.5
    m = int(centre.sum())
    dup = s["position"][centre] + np.float32([0.0015, 0.0015, -0.005])  # 5 mm in front, off-grid
    b.map.append(dup, s["normal"][centre], s["radius"][centre], np.full(m, 0.5, np.float32), s["colour"][centre],
                 b._tick - 1)
    fuse(b, [(depth, uniform((5, 5, 5)), np.eye(4))], start=14)
    s2 = b.surfels()
    left = np.count_nonzero(np.abs(s2["position"][:, 2] - (2.0 - 0.005)) < 0.002)
    assert left < 0.1 * m, (left, m)


# --------------------------------------------------------------------------------------------------
# render
# --------------------------------------------------------------------------------------------------
def test_render_of_an_empty_map_is_all_zero():
    view = SurfelBackend().render(np.eye(4), intrinsics(), H, W)
    assert isinstance(view, ModelView)
    for a, shape in ((view.depth, (H, W)), (view.colour, (H, W, 3)), (view.vertex, (H, W, 3)),
                     (view.normal, (H, W, 3))):
        assert a.shape == shape and a.dtype == np.float32 and not a.any()


def test_render_depth_of_a_fused_plane_at_another_pose():
    K = intrinsics()
    room = ((-4, -4, -1), (4, 4, 2.5))
    b = SurfelBackend()
    for i in range(14):
        pose = look_at([0.02 * i, 0.0, 0.0], [0.9, 0.1, 2.5], up=UP)  # wall z = 2.5 seen at ~20 degrees
        depth, pts = render(pose, room=room)
        b.integrate(depth, albedo(pts).astype(np.float32), K, pose, frame_index=i)
    other = look_at([0.2, -0.1, 0.3], [0.5, 0.0, 2.5], up=UP)
    truth, pts = render(other, room=room)
    view = b.render(other, K, H, W)
    ok = view.depth > 0
    assert ok.mean() > 0.8
    err = np.abs(view.depth[ok] - truth[ok])
    assert np.median(err) < 0.002 and np.percentile(err, 99) < 0.006
    # vertex = depth * ray; normals are the wall's, facing the camera
    np.testing.assert_allclose(view.vertex[..., 2][ok], view.depth[ok], rtol=1e-6)
    n_cam = np.linalg.inv(other)[:3, :3] @ np.array([0.0, 0.0, -1.0])
    assert np.percentile(view.normal[ok] @ n_cam, 1) > 0.99
    col_err = np.abs(view.colour[ok] - albedo(pts[ok])).mean()
    assert col_err < 1.5


def test_render_fills_holes_with_unstable_surfels_only_when_asked():
    depth, _ = render(np.eye(4))
    for fill in (True, False):
        b = SurfelBackend(fill_unstable=fill)
        b.integrate(depth, uniform((1, 1, 1)), intrinsics(), np.eye(4))
        cover = (b.render(np.eye(4), intrinsics(), H, W).depth[6:-6, 6:-6] > 0).mean()
        assert (cover > 0.99) if fill else (cover == 0)


# --------------------------------------------------------------------------------------------------
# export and stats
# --------------------------------------------------------------------------------------------------
def _read_ply(path):
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii")
    n = int(re.search(r"element vertex (\d+)", header).group(1))
    types = {"float": "<f4", "uchar": "u1"}
    props = re.findall(r"property (\w+) (\w+)", header)
    return header, np.frombuffer(data[end:], dtype=np.dtype([(name, types[t]) for t, name in props]), count=n)


def test_export_writes_only_stable_surfels_with_radius_and_confidence(tmp_path):
    depth, _ = render(np.eye(4))
    b = SurfelBackend()
    fuse(b, [(depth, uniform((100, 40.4, 300)), np.eye(4))] * 12)
    stable = b.surfels(stable_only=True)
    assert 0 < stable["position"].shape[0] < len(b.map)
    out = b.export(tmp_path / "run", lambda c: c * 0.5)
    assert set(out) == {"surfels"} and out["surfels"] == tmp_path / "run" / "surfels.ply"
    header, rec = _read_ply(out["surfels"])
    assert header.startswith("ply\nformat binary_little_endian 1.0\n")
    assert rec.shape[0] == stable["position"].shape[0]
    assert rec.dtype.names == ("x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "radius", "confidence")
    assert np.all(rec["confidence"] >= C_STABLE)
    np.testing.assert_array_equal(rec["radius"], stable["radius"])
    assert np.all(rec["radius"] > 0.002) and np.all(rec["radius"] < 0.06)
    assert set(np.unique(rec["red"])) == {50} and set(np.unique(rec["green"])) == {20}
    assert set(np.unique(rec["blue"])) == {150}
    # interoperability: Open3D reads positions, normals, colours and the custom properties
    from mapping._open3d import o3d

    pcd = o3d.t.io.read_point_cloud(str(out["surfels"]))
    np.testing.assert_allclose(pcd.point.positions.numpy(), stable["position"], atol=1e-6)
    np.testing.assert_allclose(pcd.point.radius.numpy().ravel(), stable["radius"], rtol=1e-6)
    np.testing.assert_allclose(pcd.point.normals.numpy(), stable["normal"], atol=1e-6)
    assert not list(tmp_path.joinpath("run").glob(".*tmp*"))  # atomic: no temporary left behind


def test_export_poisson_mesh_behind_a_flag(tmp_path):
    from mapping._open3d import o3d

    b = SurfelBackend(mesh=True, poisson_depth=7)
    frames = []
    for i in range(12):
        pose = look_at([0.02 * i, 0, 0], [0.3, 0.2, 2.0], up=UP)
        depth, pts = render(pose)
        frames.append((depth, albedo(pts).astype(np.float32), pose))
    fuse(b, frames)
    out = b.export(tmp_path, lambda c: c)
    assert set(out) == {"surfels", "mesh"}
    mesh = o3d.io.read_triangle_mesh(str(out["mesh"]))
    assert len(mesh.triangles) > 500
    v = np.asarray(mesh.vertices)
    assert np.median(np.abs(v[:, 2] - 2.0)) < 0.01  # the wall


def test_export_of_an_empty_map_and_bad_display_function(tmp_path):
    b = SurfelBackend()
    out = b.export(tmp_path, lambda c: c)
    _, rec = _read_ply(out["surfels"])
    assert rec.shape[0] == 0
    fuse(b, [(render(np.eye(4))[0], uniform((1, 1, 1)), np.eye(4))] * 12)
    with pytest.raises(ValueError, match="to_display must map"):
        b.export(tmp_path, lambda c: c[:, :1])


def test_times_are_the_frame_indices_passed_in():
    depth, _ = render(np.eye(4))
    b = SurfelBackend()
    b.integrate(depth, uniform((1, 1, 1)), intrinsics(), np.eye(4), frame_index=100)
    b.integrate(depth, uniform((1, 1, 1)), intrinsics(), np.eye(4), frame_index=107)
    s = b.surfels()
    assert s["created"].dtype == np.int64 and set(np.unique(s["created"])) <= {100, 107}
    assert np.count_nonzero(s["created"] == 100) > 4000
    assert np.count_nonzero(s["updated"] == 107) >= 0.97 * np.count_nonzero(s["created"] == 100)


def test_stats_count_surfels_and_memory():
    b = SurfelBackend(initial_capacity=1000)
    st = b.stats()
    assert st["surfels"] == 0 and st["stable_surfels"] == 0 and st["memory_bytes"] >= st["map_bytes"] > 0
    fuse(b, [(render(np.eye(4))[0], uniform((1, 1, 1)), np.eye(4))] * 12)
    st = b.stats()
    assert st["surfels"] == len(b.map) and 0 < st["stable_surfels"] < st["surfels"]
    assert st["capacity"] >= st["surfels"] and st["frames_integrated"] == 12
    assert st["map_bytes"] == 52 * st["capacity"]  # 13 float32/int32 fields per surfel


# --------------------------------------------------------------------------------------------------
# pieces
# --------------------------------------------------------------------------------------------------
def test_surfel_map_grows_by_doubling_and_compacts_in_order():
    m = SurfelMap(capacity=4)
    rows = m.append(np.arange(15, dtype=np.float32).reshape(5, 3), np.tile([0, 0, 1], (5, 1)), np.ones(5),
                    np.arange(5), np.zeros((5, 3)), 7)
    assert m.capacity == 8 and len(m) == 5 and rows.tolist() == [0, 1, 2, 3, 4]
    m.append(np.zeros((4, 3)), np.tile([0, 0, 1], (4, 1)), np.ones(4), np.ones(4), np.zeros((4, 3)), 8)
    assert m.capacity == 16 and len(m) == 9
    assert m.kill(np.array([1, 3, 3])) == 2 and len(m) == 7 and m.size == 9
    m.compact()
    assert m.size == 7 and m.dead == 0
    np.testing.assert_array_equal(m.position[:3, 0], [0, 6, 12])
    np.testing.assert_array_equal(m.created, [7, 7, 7, 8, 8, 8, 8])
    with pytest.raises(ValueError, match="radius must have one row per surfel"):
        m.append(np.zeros((2, 3)), np.zeros((2, 3)), np.ones(3), np.ones(2), np.zeros((2, 3)), 0)
    with pytest.raises(ValueError, match="confidence must be >= 0"):
        m.append(np.zeros((1, 3)), np.zeros((1, 3)), np.ones(1), -np.ones(1), np.zeros((1, 3)), 0)


def test_vertex_normal_maps_face_the_camera_and_match_the_fusion_samples():
    pose = look_at([0, 0, 0], [0.8, 0.3, 2.0], up=UP)
    depth, _ = render(pose)
    K = intrinsics()
    vert, nrm = vertex_normal_maps(depth, K)
    assert vert.dtype == nrm.dtype == np.float32
    inner = (slice(2, -2), slice(2, -2))
    assert np.all(np.einsum("ijk,ijk->ij", nrm[inner], vert[inner]) < 0)
    wall = np.linalg.inv(pose)[:3, :3] @ np.array([0.0, 0.0, -1.0])  # the far wall's normal, camera frame
    far = np.abs(depth - depth.max()) < 1e-3  # pixels on the far wall are at different depths; use truth
    pts_wall = np.abs(render(pose)[1][..., 2] - 2.0) < 1e-6
    sel = pts_wall[inner] & (nrm[inner][..., 2] != 0)
    assert np.percentile(nrm[inner][sel] @ wall, 1) > 0.999
    assert far.any()
    # the fusion kernel computes the same normals (no filter, +-1 pixel differences)
    b = SurfelBackend(bilateral=False, normal_baseline=1, pixel_stride=1)
    smp = b._samples(depth, uniform((1, 1, 1)), K, 0)
    np.testing.assert_allclose(smp.normal, nrm[smp.v, smp.u], atol=1e-5)
    np.testing.assert_allclose(smp.vertex, vert[smp.v, smp.u], rtol=1e-6)


@pytest.mark.parametrize("kwargs, match", [
    ({"confidence_threshold": 0}, "confidence_threshold must be > 0"),
    ({"pixel_stride": 5}, "pixel_stride must be between 1 and 4"),
    ({"index_scale": 1.5}, "index_scale must be an integer"),
    ({"normal_gate_deg": 200}, "normal_gate_deg must be below 180"),
    ({"depth_max": float("nan")}, "depth_max must be > 0 and finite"),
    ({"poisson_trim": 1.0}, "poisson_trim must be a fraction"),
])
def test_bad_parameters_are_named(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        SurfelBackend(**kwargs)


def test_bad_frames_are_named():
    b = SurfelBackend()
    depth = np.ones((H, W), np.float32)
    col = uniform((1, 1, 1))
    K = intrinsics()
    with pytest.raises(ValueError, match=r"colour must have shape \(120, 160, 3\)"):
        b.integrate(depth, col[:, :, :2], K, np.eye(4))
    with pytest.raises(ValueError, match="depth must be a \\(H, W\\) array"):
        b.integrate(depth[..., None], col, K, np.eye(4))
    with pytest.raises(TypeError, match="depth must be float metres"):
        b.integrate(depth.astype(np.uint16), col, K, np.eye(4))
    with pytest.raises(ValueError, match="pose must be finite"):
        b.integrate(depth, col, K, np.full((4, 4), np.nan))
    bad = np.eye(4)
    bad[0, 0] = 2
    with pytest.raises(ValueError, match="pose must hold a rotation"):
        b.render(bad, K, H, W)
    with pytest.raises(ValueError, match="K must be finite with positive focal lengths"):
        b.render(np.eye(4), np.zeros((3, 3)), H, W)
    with pytest.raises(ValueError, match="colours must be uint8"):
        write_surfel_ply("unused.ply", np.zeros((1, 3)), np.zeros((1, 3)), np.zeros((1, 3)), [1], [1])


def test_nan_depth_and_colour_are_ignored():
    depth, _ = render(np.eye(4))
    depth[:, :40] = np.nan
    col = uniform((3, 3, 3))
    col[:, 80:] = np.inf
    b = SurfelBackend()
    b.integrate(depth, col, intrinsics(), np.eye(4))
    s = b.surfels()
    assert len(b.map) > 500 and np.all(np.isfinite(s["colour"])) and np.all(np.isfinite(s["position"]))
    uv, _ = project(s["position"].astype(float), np.eye(4), intrinsics())
    assert uv[:, 0].min() > 40 and uv[:, 0].max() < 80


# --------------------------------------------------------------------------------------------------
# the pass over the map
# --------------------------------------------------------------------------------------------------
def test_cull_skips_blocks_out_of_view_without_changing_the_result():
    """The per-frame pass skips blocks of the map (1024 rows) whose bounding box lies outside the view and
    that hold no surfel due for the unstable rule. A second map whose block boxes are widened to cover
    everything (nothing skipped) fuses the same frames into the same surfels, pairs and counts, with a far
    block of unstable surfels that the unstable rule removes in both."""
    frames = []
    for i in range(30):
        pose = look_at([0.2 * math.sin(0.2 * i), 0.0, 0.1 * i - 1.0], [2.0 * math.sin(0.3 * i), 0.5, 2.5], up=UP)
        depth, pts = render(pose)
        frames.append((depth, albedo(pts).astype(np.float32), pose))
    runs = []
    for widen in (False, True):
        b = SurfelBackend()
        far = np.random.default_rng(0).uniform(50, 60, (3000, 3)).astype(np.float32)  # behind no camera here
        b.map.append(far, np.tile([0, 0, 1], (3000, 1)), np.full(3000, 0.01), np.r_[np.full(2000, 20.0),
                     np.full(1000, 1.0)], np.zeros((3000, 3)), 0)
        pairs, counts = [], []
        for i, (depth, colour, pose) in enumerate(frames):
            if widen:
                b.map.block_lo[:] = -1e6
                b.map.block_hi[:] = 1e6
            pairs.append(b.integrate(depth, colour, intrinsics(), pose, frame_index=i))
            counts.append(dict(b.last_frame))
        runs.append((b.surfels(), pairs, counts, b.stats()))
    (s0, p0, c0, st0), (s1, p1, c1, st1) = runs
    assert c0 == c1 and st0 == st1
    assert sum(c["removed_unstable"] for c in c0) >= 1000  # the far unstable block expired
    for a, b in zip(p0, p1):
        np.testing.assert_array_equal(a.map_colour, b.map_colour)
        np.testing.assert_array_equal(a.sample_colour, b.sample_colour)
    for k in s0:
        np.testing.assert_array_equal(s0[k], s1[k])


def test_surfel_map_block_summaries_bound_their_rows():
    m = SurfelMap(capacity=4, stable_confidence=10.0)
    pos = np.random.default_rng(1).normal(size=(3000, 3)).astype(np.float32)
    conf = np.where(np.arange(3000) % 3 == 0, 20.0, 1.0)
    m.append(pos, np.tile([0, 0, 1], (3000, 1)), np.ones(3000), conf, np.zeros((3000, 3)), 5)
    m.kill(np.arange(0, 3000, 7))
    m.compact()
    for b in range((m.size + m.BLOCK - 1) // m.BLOCK):
        rows = slice(b * m.BLOCK, min(m.size, (b + 1) * m.BLOCK))
        np.testing.assert_array_equal(m.block_lo[b], m.position[rows].min(axis=0))
        np.testing.assert_array_equal(m.block_hi[b], m.position[rows].max(axis=0))
        assert m.block_oldest[b] == 5  # every block holds unstable surfels made at time 5
    first = m.claim(2)
    m.array("position")[first:first + 2] = 100.0
    m.array("confidence")[first:first + 2] = 20.0
    m.note_rows(first, first + 2)
    assert np.all(m.block_hi[first // m.BLOCK] == 100.0)
