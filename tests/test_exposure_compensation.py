"""Exposure and white-balance compensation (mapping.exposure_compensation): masks and helpers on arrays, the
estimator on an analytic textured plane with known exposures, the full pipeline on simulated auto-exposure /
auto-white-balance sequences (accuracy against the simulator's truth, histogram, injected over- and
under-exposed frames), the real 7-Scenes kitchen, and the CLI."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mapping.datasets.base import RGBDFrame
from mapping.exposure_compensation import (CompensatedColour, ExposureEstimator, clipped_pixels, depth_edges,
                                           exposure_errors, local_mean, local_sums, make_compensated_colour,
                                           read_exposures, resolve_reference)
from mapping.fusion.base import ModelView
from radiometry.errors import CalibrationFileError
from radiometry.response import CameraResponse

GAMMA = CameraResponse.gamma(2.2)


# --------------------------------------------------------------------------------------------------
# an analytic scene: a textured plane z = 2 m (world), seen by a pinhole camera from any pose
# --------------------------------------------------------------------------------------------------
PW, PH, PF = 96, 72, 80.0
PK = np.array([[PF, 0, (PW - 1) / 2], [0, PF, (PH - 1) / 2], [0, 0, 1.0]])
ALBEDO = np.array([0.9, 1.0, 0.7])


def pose_at(x=0.0, y=0.0, yaw=0.0) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    T = np.eye(4)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    T[:3, 3] = (x, y, 0.0)
    return T


def plane_radiance(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(depth (H, W) float32, radiance (H, W, 3) float32) of the plane z = 2 seen from ``pose``."""
    u, v = np.meshgrid(np.arange(PW), np.arange(PH))
    rays = np.stack([(u - PK[0, 2]) / PF, (v - PK[1, 2]) / PF, np.ones((PH, PW))], -1)
    d = rays @ pose[:3, :3].T
    s = (2.0 - pose[2, 3]) / d[..., 2]
    p = pose[:3, 3] + s[..., None] * d
    X, Y = p[..., 0], p[..., 1]
    tex = 0.32 + 0.12 * np.sin(7 * X) * np.cos(5 * Y) + 0.06 * np.sin(23 * X + 11 * Y) + 0.1 * (X > 0.15)
    return s.astype(np.float32), (tex[..., None] * ALBEDO).astype(np.float32)


def plane_frame(index: int, pose: np.ndarray, k, *, response=GAMMA, seed=None, scale=1.0) -> RGBDFrame:
    """A frame of the plane with exposure ``k`` (3,) (and optional Gaussian noise of 1 % irradiance)."""
    depth, L = plane_radiance(pose)
    E = L * np.asarray(k, np.float32) * np.float32(scale)
    if seed is not None:
        E = E * (1 + 0.01 * np.random.default_rng(seed).standard_normal(E.shape)).astype(np.float32)
    rgb = np.clip(np.rint(response.forward(E)), 0, 255).astype(np.uint8)
    return RGBDFrame(index, float(index) / 30, rgb, depth, PK.copy(), pose)


def plane_view(pose: np.ndarray, k_map) -> ModelView:
    """The ideal map of the plane at ``pose``: colours in the units of an exposure ``k_map``."""
    depth, L = plane_radiance(pose)
    return ModelView(depth=depth, colour=(L * np.asarray(k_map, np.float32)).astype(np.float32))


# --------------------------------------------------------------------------------------------------
# masks and helpers
# --------------------------------------------------------------------------------------------------
def test_depth_edges_marks_a_step_and_hole_borders_only():
    depth = np.full((40, 50), 2.0, np.float32)
    depth[:, 25:] = 3.0                 # a 1 m step between columns 24 and 25
    depth[30:, 5:10] = 0.0              # a hole
    edges = depth_edges(depth, dilation=0)
    assert edges[:, 24].all() and edges[:, 25].all()
    assert not edges[:20, :23].any() and not edges[:20, 27:].any()
    assert edges[29, 5:10].all() and edges[30:, 4].all() and edges[30:, 10].all()
    assert not edges[depth == 0].any()
    grown = depth_edges(depth, dilation=2)
    assert grown[10, 22:28].all() and not grown[10, 21] and not grown[10, 28]
    # a tilted plane (smooth depth) has no edges
    ramp = np.tile(np.linspace(1.0, 3.0, 50, dtype=np.float32), (40, 1))
    assert not depth_edges(ramp).any()


@pytest.mark.parametrize("kwargs, match", [({"relative": -1}, "relative"), ({"dilation": -1}, "dilation")])
def test_depth_edges_rejects_bad_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        depth_edges(np.ones((4, 4), np.float32), **kwargs)
    with pytest.raises(ValueError, match="depth must be"):
        depth_edges(np.ones((4, 4, 1), np.float32))


def test_clipped_pixels():
    rgb = np.full((2, 4, 3), 128, np.uint8)
    rgb[0, 0, 1] = 254          # one saturated channel is enough
    rgb[0, 1] = 3               # all channels black
    rgb[0, 2] = (3, 3, 40)      # one channel above black: usable
    rgb[0, 3, 2] = 253
    assert clipped_pixels(rgb).tolist() == [[True, True, False, False], [False] * 4]
    with pytest.raises(ValueError, match="uint8"):
        clipped_pixels(rgb.astype(np.float32))
    with pytest.raises(ValueError, match="dark"):
        clipped_pixels(rgb, high=10, dark=20)


@pytest.mark.parametrize("radius", [0, 1, 3])
def test_local_sums_and_means_match_brute_force(radius):
    rng = np.random.default_rng(radius)
    vals = rng.uniform(0, 1, (13, 17, 3)).astype(np.float32)
    mask = rng.uniform(size=(13, 17)) < 0.6
    sums, count = local_sums(vals, mask, radius)
    mean, _ = local_mean(vals, mask, radius)
    for y, x in [(0, 0), (6, 8), (12, 16), (3, 15)]:
        ys, xs = slice(max(y - radius, 0), y + radius + 1), slice(max(x - radius, 0), x + radius + 1)
        m = mask[ys, xs]
        assert count[y, x] == m.sum()
        np.testing.assert_allclose(sums[y, x], vals[ys, xs][m].sum(axis=0), rtol=1e-5, atol=1e-6)
        if m.any():
            np.testing.assert_allclose(mean[y, x], vals[ys, xs][m].mean(axis=0), rtol=1e-5)
    assert sums.dtype == np.float32 and count.dtype == np.float32
    with pytest.raises(ValueError, match="radius"):
        local_sums(vals, mask, -1)
    with pytest.raises(ValueError, match="mask"):
        local_sums(vals, mask[:, :5], 1)


def test_resolve_reference():
    est = np.array([[1.0, 1.0, 1.0], [2.0, 0.5, 1.5], [3.0, 0.4, 1.2]])
    np.testing.assert_allclose(resolve_reference("median", est), [2.0, 0.5, 1.2])
    np.testing.assert_allclose(resolve_reference("first", est), [1, 1, 1])
    np.testing.assert_allclose(resolve_reference("median"), [1, 1, 1])
    np.testing.assert_allclose(resolve_reference(0.5), [0.5] * 3)
    np.testing.assert_allclose(resolve_reference([1, 2, 3]), [1, 2, 3])
    for bad in ("mean", 0.0, -1, [1, 2], float("nan"), [1, float("inf"), 1]):
        with pytest.raises(ValueError, match="reference"):
            resolve_reference(bad)


def test_exposure_errors_on_known_values():
    truth = np.array([[2.0, 1.0, 1.0, 1.0], [1.0, 1.0, 2.0, 1.0], [1.0, 2.0, 1.0, 1.0], [2.0, 1.0, 1.0, 1.0]])
    true_k = truth[:, :1] * truth[:, 1:]
    est = true_k / true_k[0] * 3.0                                 # scale-free: only ratios matter
    est[2] *= [1.01, 1.0, 0.98]
    out = exposure_errors(est, truth)
    np.testing.assert_allclose(out["errors"][2], [0.01, 0.0, -0.02], atol=1e-12)
    assert out["max"] == pytest.approx(0.02) and out["frames"] == 4
    out = exposure_errors(est, true_k, use=np.array([True, True, False, True]), skip_first=1)
    assert out["max"] == pytest.approx(0.0, abs=1e-12) and out["frames"] == 2
    with pytest.raises(ValueError, match="must both be"):
        exposure_errors(est[:, :2], truth)
    with pytest.raises(ValueError, match="positive finite"):
        exposure_errors(-est, truth)
    with pytest.raises(ValueError, match="no frame left"):
        exposure_errors(est, truth, skip_first=4)


# --------------------------------------------------------------------------------------------------
# the estimator on the analytic plane (ideal map: any error is the estimator's)
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("downsample", [1, 2])
def test_against_the_map_recovers_per_channel_exposure(downsample):
    k0 = np.array([0.9, 0.9, 0.9])
    k1 = np.array([0.63, 0.72, 1.08])          # exposure and white balance both changed
    est = ExposureEstimator(GAMMA, frame_to_frame=False, downsample=downsample)
    first = est(plane_frame(0, pose_at(), k0), None, None)
    np.testing.assert_array_equal(first, [1, 1, 1])
    pose = pose_at(0.05, 0.02, 0.03)
    k = est(plane_frame(1, pose, k1, seed=1), None, plane_view(pose, k0))
    np.testing.assert_allclose(k, k1 / k0, rtol=0.004)      # measured: < 0.1 %
    rec = est.last
    assert rec.source == "map" and rec.correspondences > 2000 / downsample ** 2 and rec.map_coverage > 0.9
    assert est.fallbacks == 0 and rec.fuse_colour


@pytest.mark.parametrize("bad", [np.nan, np.inf, -1.0, 0.0])
def test_invalid_depth_and_map_values_are_ignored(bad):
    k0, k1 = np.array([1.0, 1.0, 1.0]), np.array([0.6, 0.7, 0.8])
    est = ExposureEstimator(GAMMA)
    est(plane_frame(0, pose_at(), k0), None, None)
    p = pose_at(0.04, 0.01)
    f = plane_frame(1, p, k1, seed=4)
    depth = f.depth.copy()
    depth[:10] = bad                             # a band of invalid depth in the frame ...
    view = plane_view(p, k0)
    view.depth[:, :8] = bad                      # ... and in the rendered map
    view.colour[-6:] = bad                       # and invalid map colours (where the map still has depth)
    k = est(RGBDFrame(1, f.timestamp, f.rgb, depth, PK, p), None, view)
    np.testing.assert_allclose(k, k1, rtol=0.005)
    assert np.all(np.isfinite(est.last.frame_k)) and est.last.source == "map"


@pytest.mark.parametrize("downsample", [1, 2])
def test_frame_to_frame_starts_the_sequence_and_cross_checks(downsample):
    k0, k1, k2 = np.array([1.0, 1.0, 1.0]), np.array([0.8, 0.85, 0.9]), np.array([0.7, 0.8, 0.95])
    est = ExposureEstimator(GAMMA, downsample=downsample)
    est(plane_frame(0, pose_at(), k0), None, None)
    # no map yet: frame to frame through depth and the relative pose
    p1 = pose_at(0.08, -0.03, 0.05)
    k = est(plane_frame(1, p1, k1, seed=2), None, None)
    np.testing.assert_allclose(k, k1 / k0, rtol=0.005)
    assert est.last.source == "frame" and np.isnan(est.last.disagreement)
    # with a map both are measured; the map is the anchor; their disagreement is recorded
    p2 = pose_at(0.12, 0.0, -0.04)
    k = est(plane_frame(2, p2, k2, seed=3), None, plane_view(p2, k0))
    rec = est.last
    assert rec.source == "map"
    np.testing.assert_allclose(k, k2 / k0, rtol=0.005)
    np.testing.assert_allclose(rec.frame_k, k2 / k0, rtol=0.01)
    assert 0 <= rec.disagreement < 0.01
    # view.pose (the pose the backend rendered it at) wins over frame.pose (here the ground truth is withheld)
    est2 = ExposureEstimator(GAMMA)
    est2(plane_frame(0, pose_at(), k0), None, None)
    frame = plane_frame(1, p1, k1)
    view = ModelView(depth=np.zeros((PH, PW), np.float32), colour=np.zeros((PH, PW, 3), np.float32))
    view.pose = p1
    blind = RGBDFrame(frame.index, frame.timestamp, frame.rgb, frame.depth, frame.K, None)
    np.testing.assert_allclose(est2(blind, None, view), k1 / k0, rtol=0.005)


def test_too_few_correspondences_falls_back_and_is_counted():
    est = ExposureEstimator(GAMMA)
    est(plane_frame(0, pose_at(), [1, 1, 1]), None, None)
    # no map, no pose: nothing to compare with
    frame = plane_frame(1, pose_at(0.1), [0.8, 0.8, 0.8])
    blind = RGBDFrame(1, frame.timestamp, frame.rgb, frame.depth, frame.K, None)
    k = est(blind, None, None)
    np.testing.assert_array_equal(k, [1, 1, 1])
    assert est.fallbacks == 1 and est.last.source == "fallback" and not est.last.fuse_colour
    assert est.last.reason.startswith("too few correspondences")
    # a saturated frame has no usable pixel either
    white = plane_frame(2, pose_at(0.05), [20, 20, 20])
    assert (white.rgb == 255).mean() > 0.99
    est(white, None, plane_view(pose_at(0.05), [1, 1, 1]))
    assert est.fallbacks == 2 and est.summary()["fallback_reasons"] == {"too few correspondences": 2}
    assert est.summary()["fallback_frames"] == [1, 2]


def test_implausible_jumps_fall_back_but_a_lasting_change_is_accepted():
    est = ExposureEstimator(GAMMA, confirm_frames=3)
    est(plane_frame(0, pose_at(), [0.5, 0.5, 0.5]), None, None)
    p = pose_at(0.03)
    view = plane_view(p, [0.5, 0.5, 0.5])
    for i, scale in enumerate([4.0, 1.0, 0.25, 1.0], start=1):     # isolated glitches: rejected
        k = est(plane_frame(i, p, [0.5, 0.5, 0.5], scale=scale), None, view)
        np.testing.assert_allclose(k, [1, 1, 1], rtol=0.003)
    assert [r.source for r in est.records] == ["reference", "fallback", "map", "fallback", "map"]
    assert est.records[1].reason.startswith("implausible jump (x4")
    assert est.records[3].reason.startswith("implausible jump (x0.25")
    # a real change of 2.5x: rejected twice, accepted on the third consistent frame
    for i in range(5, 9):
        est(plane_frame(i, p, [0.5, 0.5, 0.5], scale=2.5, seed=i), None, view)
    assert [r.source for r in est.records[5:]] == ["fallback", "fallback", "map", "map"]
    assert "accepted after 3 consistent frames" in est.records[7].reason
    np.testing.assert_allclose(est.records[8].k, [2.5] * 3, rtol=0.005)
    assert est.fallbacks == 4


def test_vignetting_is_divided_out_before_the_ratio():
    from radiometry.vignetting import LUTVignetting

    yy, xx = np.mgrid[0:PH, 0:PW]
    r2 = ((xx - PW / 2) ** 2 + (yy - PH / 2) ** 2) / (PW / 2) ** 2
    V = np.repeat((1 - 0.35 * r2)[..., None], 3, axis=2).astype(np.float32)
    V /= V.max()

    def vignetted(index, pose, k):
        depth, L = plane_radiance(pose)
        rgb = np.clip(np.rint(GAMMA.forward(L * V * np.asarray(k, np.float32))), 0, 255).astype(np.uint8)
        return RGBDFrame(index, index / 30, rgb, depth, PK, pose)

    p = pose_at(0.06, 0.0, 0.02)
    good = ExposureEstimator(GAMMA, LUTVignetting(V), frame_to_frame=False)
    good(vignetted(0, pose_at(), [1, 1, 1]), None, None)
    np.testing.assert_allclose(good(vignetted(1, p, [0.7, 0.7, 0.7]), None, plane_view(p, [1, 1, 1])), [0.7] * 3,
                               rtol=0.003)
    ignorant = ExposureEstimator(GAMMA, None, frame_to_frame=False)
    ignorant(vignetted(0, pose_at(), [1, 1, 1]), None, None)
    k = ignorant(vignetted(1, p, [0.7, 0.7, 0.7]), None, plane_view(p, [1, 1, 1]))
    assert np.all(k < 0.7 * 0.97)          # vignetting not removed: the median pixel looks darker


def bar_scene(k, *, bleed=2, period=16, bar_width=8, seed=None):
    """Bright bars 1 m in front of a dark wall, seen head-on: ``(depth, radiance of the surface at each pixel's
    depth, rgb at exposure k)``. Colour and depth are misregistered as on real sensors: in the colour image the
    bars are ``bleed`` pixels wider on each side than in the depth image, so next to every depth step the wall's
    depth carries the bar's (3.2x brighter) colour, always in the same direction."""
    u, v = np.meshgrid(np.arange(PW), np.arange(PH))
    phase = (u + 4) % period
    colour_bar = phase < bar_width
    depth_bar = (phase >= bleed) & (phase < bar_width - bleed)
    depth = np.where(depth_bar, 1.5, 2.5).astype(np.float32)
    tex = 0.32 + 0.12 * np.sin(0.4 * u) * np.cos(0.3 * v) + 0.05 * np.sin(1.3 * u + 0.7 * v)
    L_surface = (tex * np.where(depth_bar, 1.6, 0.5))[..., None] * ALBEDO
    L_image = (tex * np.where(colour_bar, 1.6, 0.5))[..., None] * ALBEDO
    E = L_image * np.asarray(k, np.float64)
    if seed is not None:
        E = E * (1 + 0.01 * np.random.default_rng(seed).standard_normal(E.shape))
    rgb = np.clip(np.rint(GAMMA.forward(E.astype(np.float32))), 0, 255).astype(np.uint8)
    return depth, L_surface.astype(np.float32), rgb


def test_depth_edges_are_excluded_from_the_estimate():
    """With misregistered colour at depth steps (a quarter of the pixels lie within 2 px of one), including
    the edge pixels biases the exposure by ~40 %; the default exclusion (steps grown by 2 px) removes it."""
    k0, k1 = np.array([0.9, 0.9, 0.9]), np.array([0.63, 0.72, 1.08])
    depth, L, rgb1 = bar_scene(k1, seed=1)
    assert np.mean(depth_edges(depth)) > 0.3 and not depth_edges(depth, dilation=0)[:, 8:10].any()

    def estimate(**edge_options):
        est = ExposureEstimator(GAMMA, frame_to_frame=False, downsample=1, **edge_options)
        _, _, rgb0 = bar_scene(k0)
        est(RGBDFrame(0, 0.0, rgb0, depth, PK, np.eye(4)), None, None)
        view = ModelView(depth=depth.copy(), colour=(L * k0).astype(np.float32))   # the ideal map, k0 units
        k = est(RGBDFrame(1, 1 / 30, rgb1, depth, PK, np.eye(4)), None, view)
        assert est.last.source == "map"
        return k / (k1 / k0) - 1, est.last.correspondences

    err, n_default = estimate()
    assert np.abs(err).max() < 0.003, err                              # measured 0.02 %
    err, n_all = estimate(edge_dilation=0, edge_absolute=1e3, edge_relative=0.0)   # no edge is ever found
    assert err.min() > 0.2 and n_all > 2 * n_default, err              # measured +41 %, brighter: the bars' colour
    err, _ = estimate(edge_dilation=0)                                 # the steps alone, not grown
    assert err.min() > 0.2, err                                        # measured +43 %: the 2 px bleed remains


@pytest.mark.parametrize("kwargs, match", [
    ({"low": 200, "high": 100}, "low"), ({"min_correspondences": 0}, "min_correspondences"),
    ({"max_jump": 1.0}, "max_jump"), ({"confirm_frames": 1}, "confirm_frames"),
    ({"min_map_coverage": 1.5}, "min_map_coverage"), ({"smoothing_radius": -1}, "smoothing_radius"),
    ({"min_fill": 0}, "min_fill"), ({"depth_abs_tol": 0}, "depth_abs_tol"), ({"max_samples": 10}, "max_samples"),
    ({"edge_dilation": -2}, "edge_dilation"), ({"downsample": 0}, "downsample")])
def test_estimator_rejects_bad_settings(kwargs, match):
    with pytest.raises(ValueError, match=match):
        ExposureEstimator(GAMMA, **kwargs)


def test_estimator_rejects_bad_inputs():
    with pytest.raises(TypeError, match="CameraResponse"):
        ExposureEstimator("gamma")
    est = ExposureEstimator(GAMMA)
    frame = plane_frame(0, pose_at(), [1, 1, 1])
    bad = RGBDFrame(0, 0.0, frame.rgb.astype(np.float32), frame.depth, PK, None)
    with pytest.raises(ValueError, match="uint8"):
        est(bad, None, None)
    est(frame, None, None)
    with pytest.raises(ValueError, match="view.depth"):
        est(plane_frame(1, pose_at(), [1, 1, 1]), None, ModelView(np.ones((3, 3), np.float32),
                                                                  np.ones((3, 3, 3), np.float32)))


def test_estimates_round_trip_through_files(tmp_path):
    est = ExposureEstimator(GAMMA)
    est(plane_frame(0, pose_at(), [1, 1, 1]), None, None)
    p = pose_at(0.04)
    est(plane_frame(1, p, [0.8, 0.9, 1.1]), None, plane_view(p, [1, 1, 1]))
    est(plane_frame(2, p, [4, 4, 4]), None, plane_view(p, [1, 1, 1]))
    files = est.save(tmp_path, export_reference=est.reference("median"), histogram_reference="first frame x 1")
    txt, js = read_exposures(files["exposures_txt"]), read_exposures(files["exposures_json"])
    for got in (txt, js):
        assert got["index"].tolist() == [0, 1, 2]
        assert list(got["source"]) == ["reference", "map", "fallback"]
        np.testing.assert_allclose(got["k"], est.estimates(), rtol=1e-5)
        assert got["correspondences"][1] == est.records[1].correspondences > 0
    doc = json.loads(files["exposures_json"].read_text())
    assert doc["kind"] == "exposure-estimates" and doc["summary"]["fallbacks"] == 1
    assert doc["frames"][2]["reason"].startswith("implausible jump")
    np.testing.assert_allclose(doc["export_reference"], np.median(est.estimates()[:2], axis=0))
    lines = files["exposures_txt"].read_text().splitlines()
    assert lines[1] == "# index timestamp k_r k_g k_b correspondences source" and len(lines) == 5
    bad = tmp_path / "bad.txt"
    bad.write_text("0 0.0 1 1 1 12 map\n1 0.1 1 1 x 12 map\n")
    with pytest.raises(CalibrationFileError, match="bad.txt:2"):
        read_exposures(bad)
    bad.write_text("0 0.0 1 1 1 12 sometimes\n")
    with pytest.raises(CalibrationFileError, match="bad.txt:1"):
        read_exposures(bad)
    with pytest.raises(CalibrationFileError, match="no such"):
        read_exposures(tmp_path / "missing.json")
    (tmp_path / "other.json").write_text('{"kind": "histogram"}')
    with pytest.raises(CalibrationFileError, match="not a radiomap exposure"):
        read_exposures(tmp_path / "other.json")


# --------------------------------------------------------------------------------------------------
# the colour model
# --------------------------------------------------------------------------------------------------
def test_compensated_colour_divides_masks_and_displays():
    model = make_compensated_colour(GAMMA)
    assert isinstance(model, CompensatedColour) and model.name == "response+exposure"
    f0 = plane_frame(0, pose_at(), [1, 1, 1])
    rgb = f0.rgb.copy()
    rgb[:3, :3] = 255            # saturated corner
    f0 = RGBDFrame(0, 0.0, rgb, f0.depth, PK, f0.pose)
    c0 = model.to_map(f0, None)
    assert c0.colour.dtype == np.float32
    assert c0.valid is not None and c0.valid.sum() == PW * PH - 9
    assert not c0.valid[:3, :3].any() and c0.reason == "colour rejected: every pixel clipped or black"
    p = pose_at(0.03)
    c1 = model.to_map(plane_frame(1, p, [0.5, 0.6, 0.7]), plane_view(p, [1, 1, 1]), p)
    assert c1.valid is None                                  # nothing clipped
    E1 = c1.colour
    np.testing.assert_allclose(model.estimator.last.k, [0.5, 0.6, 0.7], rtol=0.004)
    # compensated irradiance is in first-frame units: it matches the ideal map
    _, L = plane_radiance(p)
    assert np.median(np.abs(E1 / L - 1)) < 0.01
    # an over-exposed glitch: fallback, nothing of it is fused
    c2 = model.to_map(plane_frame(2, p, [3, 3, 3]), plane_view(p, [1, 1, 1]), p)
    assert model.estimator.last.source == "fallback" and not c2.valid.any()
    assert c2.reason == "colour rejected: the exposure estimate fell back"
    # display: the histogram's reference is fixed (first frame), the export's is the median of the estimates
    np.testing.assert_allclose(model.to_display(np.full((1, 3), 0.5, np.float32)), GAMMA.forward(np.full((1, 3), 0.5)),
                               atol=1e-3)
    k_ref = model.export_reference_k()
    np.testing.assert_allclose(k_ref, np.median([[1, 1, 1], [0.5, 0.6, 0.7]], axis=0), rtol=0.004)
    shown = model.display_for_export()(np.full((1, 3), 0.5, np.float32))
    np.testing.assert_allclose(shown, GAMMA.forward((0.5 * k_ref)[None].astype(np.float32)), atol=1e-3)
    doc = model.describe()
    assert doc["exposure_compensation"] is True and doc["exposure"]["summary"]["fallbacks"] == 1
    assert doc["export_reference"]["kind"] == "median"


def test_compensated_colour_options_and_errors():
    from mapping.colour import IrradianceColour, RawIntensity

    with pytest.raises(TypeError, match="IrradianceColour"):
        CompensatedColour(RawIntensity())
    base = IrradianceColour(GAMMA)
    with pytest.raises(ValueError, match="either an estimator or its options"):
        CompensatedColour(base, ExposureEstimator(GAMMA), max_jump=3.0)
    with pytest.raises(ValueError, match="reference"):
        CompensatedColour(IrradianceColour(GAMMA), export_reference="mean")
    masked_only = CompensatedColour(IrradianceColour(GAMMA), compensate=False, export_reference="first")
    assert masked_only.estimator is None and masked_only.name == "response+clip-mask"
    assert masked_only.save_results("unused") == {}
    f = plane_frame(0, pose_at(), [30, 30, 30])              # saturated: masked, not compensated
    c = masked_only.to_map(f, None)
    np.testing.assert_allclose(c.colour, masked_only.base.irradiance(f.rgb))
    assert c.valid.mean() < 0.01
    np.testing.assert_allclose(masked_only.export_reference_k(), [1, 1, 1])
    fixed = CompensatedColour(IrradianceColour(GAMMA), export_reference=[0.5, 1, 2], max_jump=3.0)
    assert fixed.estimator.max_jump == 3.0
    np.testing.assert_allclose(fixed.export_reference_k(), [0.5, 1, 2])


def test_the_pipeline_does_not_fuse_clipped_pixels():
    """Four views of the plane at the same exposure; in the last a patch is saturated (a specular highlight).
    With the clip mask the map keeps the first views' colour there; without it the highlight is averaged in."""
    from mapping.colour import IrradianceColour
    from mapping.datasets.in_memory import ArrayDataset
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct

    frames = [plane_frame(i, pose_at(0.01 * i), [0.8] * 3, seed=i) for i in range(4)]
    last = frames[-1]
    rgb = last.rgb.copy()
    rgb[20:50, 30:60] = 255
    frames[-1] = RGBDFrame(3, last.timestamp, rgb, last.depth, PK, last.pose)
    shown = {}
    for mask in (True, False):
        model = CompensatedColour(IrradianceColour(GAMMA), mask_clipped=mask)
        backend = make_backend("tsdf", voxel_size=0.02, depth_max=4.0)
        run = reconstruct(ArrayDataset(frames), colour_model=model, backend=backend, poses="gt", progress=False)
        assert run.fused == 4 and model.estimator.fallbacks == 0
        view = backend.render_for_frame(last.depth, PK, last.pose)
        assert np.all(view.depth[25:45, 35:55] > 0)
        shown[mask] = model.to_display(view.colour[25:45, 35:55].reshape(-1, 3))
    expected = last.rgb[25:45, 35:55].reshape(-1, 3).astype(np.float32)   # the true colour at that exposure
    err_masked = np.median(np.abs(shown[True] - expected))
    err_fused = np.median(np.abs(shown[False] - expected))
    assert err_masked < 3.0 and err_fused > 20.0, (err_masked, err_fused)  # measured 0.7 and 45


# --------------------------------------------------------------------------------------------------
# the pipeline on simulated auto-exposure + auto-white-balance sequences
# --------------------------------------------------------------------------------------------------
SIM_W, SIM_H, SIM_N = 160, 120, 50
INJECTED = {12: 4.0, 18: 0.25, 25: 4.0, 33: 0.25}      # frame -> factor on its exposure (glitches)


def frames_dataset(frames, K, rgb_override=None):
    """The simulator's in-memory frames as an RGBDDataset (ground-truth poses), optionally with replaced images."""
    from mapping.datasets.in_memory import ArrayDataset

    rgb_override = rgb_override or {}
    return ArrayDataset([RGBDFrame(f.index, f.timestamp, rgb_override.get(f.index, f.rgb),
                                   f.depth.astype(np.float32), K, f.pose) for f in frames], name="simulated-ae-awb")


def test_a_frame_without_usable_pixels_does_not_become_the_anchor():
    """A black (lens cap) or blown-out first frame anchors nothing: it falls back, its colour is not fused, and the
    first frame with enough usable pixels becomes the anchor; the frames after it are estimated against it."""
    est = ExposureEstimator(GAMMA)
    first = plane_frame(0, pose_at(), [1, 1, 1])
    black = RGBDFrame(0, first.timestamp, np.zeros_like(first.rgb), first.depth, first.K, first.pose)
    white = plane_frame(1, pose_at(0.02), [20, 20, 20])
    for frame in (black, white):
        np.testing.assert_array_equal(est(frame, None, None), [1, 1, 1])
        assert est.last.source == "fallback" and not est.last.fuse_colour
        assert est.last.reason.startswith("no anchor yet: 0 usable pixels (need 200)")
    est(plane_frame(2, pose_at(0.04), [1, 1, 1]), None, None)
    assert est.last.source == "reference" and est.last.fuse_colour and "first frame with enough" in est.last.reason
    k = est(plane_frame(3, pose_at(0.06), [0.8, 0.7, 0.9]), None, None)   # frame to frame against the anchor
    assert est.last.source == "frame"
    np.testing.assert_allclose(k, [0.8, 0.7, 0.9], rtol=0.02)


def test_a_black_first_frame_does_not_stop_a_compensated_run(ae_awb_sequence):
    from mapping.colour import IrradianceColour

    seq = ae_awb_sequence
    frames = list(seq["frames"][:8])
    f0 = frames[0]
    frames[0] = type(f0)(**{**f0.__dict__, "rgb": np.zeros_like(f0.rgb)})
    model = CompensatedColour(IrradianceColour(seq["camera"].response, seq["camera"].vignetting))
    run, _ = _run(frames_dataset(frames, seq["K"]), model)
    assert run.fused == 7 and [r.fused for r in run.records] == [False] + [True] * 7
    records = model.estimator.records
    assert records[0].source == "fallback" and records[1].source == "reference"
    assert [r.source for r in records[2:]] == ["map"] * 6


@pytest.fixture(scope="module")
def ae_awb_sequence():
    """50 frames of the simulated room (Xtion-like camera: S-shaped CRF differing per channel, strong vignetting,
    shot and read noise, depth-sensor noise and holes) with auto exposure and auto white balance running from a
    2.5x too long start exposure: the exposure falls to 0.34x (red), 0.50x (green), 0.63x (blue) of the first
    frame, the white balance moves by 1.8x between red and blue."""
    from mapping.simulation import iter_room_frames, make_room, resolve_camera, room_trajectory
    from radiometry.simulation import default_intrinsics

    room = make_room(3)
    cam = resolve_camera("xtion", SIM_W, SIM_H)
    K = default_intrinsics(SIM_W, SIM_H)
    poses = room_trajectory(room, SIM_N, seed=5)
    frames = list(iter_room_frames(room, cam, poses, K=K, seed=5, auto_exposure=True, auto_white_balance=True,
                                   exposure_time=0.025))
    truth = np.array([f.exposure_time * f.gains for f in frames])
    return {"frames": frames, "K": K, "camera": cam, "truth": truth}


def _run(dataset, model, voxel_size=0.03):
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct

    backend = make_backend("tsdf", voxel_size=voxel_size, depth_max=4.0)
    run = reconstruct(dataset, colour_model=model, backend=backend, poses="gt", progress=False)
    return run, backend


@pytest.mark.slow
def test_simulated_auto_exposure_and_white_balance_are_recovered(ae_awb_sequence):
    from mapping.colour import IrradianceColour

    seq = ae_awb_sequence
    cam, truth = seq["camera"], seq["truth"]
    rel = truth / truth[0]
    assert rel[-1].max() < 0.7 and rel[-1, 2] / rel[-1, 0] > 1.7        # the sequence really changes a lot
    ds = frames_dataset(seq["frames"], seq["K"])
    base_run, _ = _run(ds, IrradianceColour(cam.response, cam.vignetting))
    model = CompensatedColour(IrradianceColour(cam.response, cam.vignetting))
    run, _ = _run(ds, model)
    est = model.estimator
    assert est.fallbacks == 0 and len(est.records) == SIM_N
    assert est.summary()["sources"]["map"] == SIM_N - 1
    err = exposure_errors(est.estimates(), truth, skip_first=3)
    # measured: median 0.18 %, worst 0.38 %, drift (last - first quarter of the frames) -0.08 % at most; the
    # issue asks for 2 % / 5 %; the bounds guard the measured accuracy with a margin of ~2.5x
    assert err["median"] < 0.005
    assert err["max"] < 0.01
    assert np.max(np.abs(err["drift"])) < 0.003
    assert np.max(np.abs(err["errors"][1:3])) < 0.02              # the start-up frames are fine too
    # the map-vs-frame-to-frame cross-check agrees to a fraction of a percent (measured median 0.05 %)
    assert est.summary()["disagreement_median"] < 0.005
    # the colour disagreement halves: measured mean 43.0 -> 21.9, p90 85 -> 45 (L1 over R, G, B, 8-bit levels)
    before, after = base_run.histogram.stats(), run.histogram.stats()
    assert after["mean"] < 0.6 * before["mean"], (before, after)
    assert after["p90"] < 0.65 * before["p90"], (before, after)


def _render_display(backend, model, frames, K, w, h):
    """The map seen from the frames' poses (ray cast within the blocks each frame's depth touches), in display
    levels at the first frame's exposure: [(depth, colour)]."""
    out = []
    for f in frames:
        view = backend.render_for_frame(f.depth.astype(np.float32), K, f.pose)
        out.append((view.depth, model.to_display(view.colour.reshape(-1, 3)).reshape(h, w, 3)))
    return out


@pytest.mark.slow
def test_over_and_under_exposed_frames_do_not_corrupt_the_map(ae_awb_sequence):
    from mapping.colour import IrradianceColour

    seq = ae_awb_sequence
    cam, frames, K = seq["camera"], seq["frames"], seq["K"]
    glitched = {}
    for i, factor in INJECTED.items():      # the same scene at 4x / 0.25x the exposure (noise included)
        signal = frames[i].capture.signal * np.float32(factor)
        glitched[i] = np.clip(np.rint(cam.response.forward(signal)), 0, 255).astype(np.uint8)
    assert np.mean(glitched[12] >= 254) > 0.3                                # 42 % of the values clipped
    assert glitched[18].mean() < 0.6 * frames[18].rgb.mean()
    with_glitches = frames_dataset(frames, K, glitched)
    without = frames_dataset([f for f in frames if f.index not in INJECTED], K)

    model_a = CompensatedColour(IrradianceColour(cam.response, cam.vignetting))
    run_a, backend_a = _run(with_glitches, model_a)
    model_b = CompensatedColour(IrradianceColour(cam.response, cam.vignetting))
    run_b, backend_b = _run(without, model_b)
    # every glitch is caught and counted; no other frame falls back
    assert model_a.estimator.fallbacks == len(INJECTED)
    assert model_a.estimator.summary()["fallback_frames"] == sorted(INJECTED)
    assert model_a.estimator.summary()["fallback_reasons"] == {"implausible jump": len(INJECTED)}
    assert model_b.estimator.fallbacks == 0
    assert run_a.skip_reasons() == {"colour rejected: the exposure estimate fell back": len(INJECTED)}
    # the estimates of the other frames are unchanged by the glitches
    keep = np.array([f.index not in INJECTED for f in frames])
    np.testing.assert_allclose(model_a.estimator.estimates()[keep], model_b.estimator.estimates(), rtol=0.003)
    # the maps look the same: rendered at every 4th pose, display levels (first frame's exposure)
    views_a = _render_display(backend_a, model_a, frames[::4], K, SIM_W, SIM_H)
    views_b = _render_display(backend_b, model_b, frames[::4], K, SIM_W, SIM_H)
    diffs = []
    for (da, ca), (db, cb) in zip(views_a, views_b):
        both = (da > 0) & (db > 0) & (np.abs(da - db) < 0.03)
        diffs.append(np.abs(ca[both] - cb[both]).sum(axis=1))
    d = np.concatenate(diffs)
    assert d.size > 50000
    # measured: mean, median, p90 and p99 all 0.0 levels (L1 over R, G, B): the glitched frames fused nothing
    assert d.mean() < 0.5 and np.percentile(d, 90) < 3.0, (d.mean(), np.percentile(d, 90))
    # for scale: without compensation the same glitches shift the map (measured mean 18.1, p90 27.2 levels)
    plain_a, pb_a = _run(with_glitches, IrradianceColour(cam.response, cam.vignetting))
    plain_b, pb_b = _run(without, IrradianceColour(cam.response, cam.vignetting))
    model_p = IrradianceColour(cam.response, cam.vignetting)
    pa = _render_display(pb_a, model_p, frames[::4], K, SIM_W, SIM_H)
    pb = _render_display(pb_b, model_p, frames[::4], K, SIM_W, SIM_H)
    dp = np.concatenate([np.abs(ca[(da > 0) & (db > 0) & (np.abs(da - db) < 0.03)]
                                - cb[(da > 0) & (db > 0) & (np.abs(da - db) < 0.03)]).sum(axis=1)
                         for (da, ca), (db, cb) in zip(pa, pb)])
    assert np.percentile(dp, 90) > 3 * np.percentile(d, 90) + 5
