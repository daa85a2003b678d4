"""Depth holes at depth edges (``DepthSensor.edge_px``, ``edge_drop``) on a rendered depth step.

Scene: a wall 3 m ahead and a box front 1.5 m ahead, both facing the camera (fronto-parallel: no grazing
holes), sensor noise, dropout and the projector shadow off, so that every hole comes from the edge model.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from mapping.simulation import DepthSensor, Face, Lighting, Renderer, TexturedScene, look_at
from radiometry.simulation import default_intrinsics

W, H = 320, 240


def render_step(box_distance: float):
    wall = Face("wall", [-3, 3, -3], [1, 0, 0], [0, 0, 1], (6.0, 6.0), np.full((4, 4, 3), 0.5, np.float32))
    box = Face("box", [-0.3, box_distance, -0.25], [1, 0, 0], [0, 0, 1], (0.6, 0.5),
               np.full((2, 2, 3), 0.7, np.float32))
    scene = TexturedScene([wall, box], Lighting())
    r = Renderer(scene, default_intrinsics(W, H), W, H).render(look_at([0, 0, 0], [0, 1, 0]))
    near = r.face == 1
    # Chebyshev distance (pixels) of every pixel to the box (0 on it)
    dist = cv2.distanceTransform((~near).astype(np.uint8), cv2.DIST_C, 3)
    return r, near, dist


@pytest.fixture(scope="module")
def step():
    r, near, dist = render_step(1.5)
    assert r.valid.all() and 3000 < near.sum() < 30000
    np.testing.assert_allclose(r.depth[near], 1.5, rtol=1e-5)
    np.testing.assert_allclose(r.depth[dist > 3], 3.0, rtol=1e-5)
    return r, near, dist


def sensor(**kwargs) -> DepthSensor:
    return DepthSensor(projector_shadow=False, dropout=0.0, sigma0=0.0, sigma2=0.0, **kwargs)


@pytest.mark.parametrize("edge_px, edge_drop", [(1, 0.7), (3, 0.4)])
def test_holes_fill_a_band_of_edge_px_on_the_far_side_at_the_edge_drop_rate(step, edge_px, edge_drop):
    r, near, dist = step
    depth = sensor(edge_px=edge_px, edge_drop=edge_drop).measure(r, rng=np.random.default_rng(0))
    holes = depth == 0
    band = ~near & (dist <= edge_px)  # the wall within edge_px pixels of the box
    assert not holes[near].any()  # the near side keeps its depth
    assert not holes[~band].any()  # nothing far from the edge
    n = int(band.sum())
    assert n > 300 * edge_px
    rate = float(holes[band].mean())
    assert abs(rate - edge_drop) < 4 * np.sqrt(edge_drop * (1 - edge_drop) / n) + 0.01, (rate, n)
    for ring in range(1, edge_px + 1):  # the band really is edge_px wide: its outer ring has holes too
        on_ring = ~near & (dist == ring)
        assert holes[on_ring].mean() > 0.8 * edge_drop, ring
    # where there is no hole the depth is the true one (up to the disparity quantisation)
    np.testing.assert_allclose(depth[near], 1.5, atol=1.5 * sensor().step(1.5))
    np.testing.assert_allclose(depth[~holes & ~near], 3.0, atol=1.5 * sensor().step(3.0))


def test_the_holes_are_random_per_seed(step):
    r, near, dist = step
    s = sensor(edge_px=2, edge_drop=0.5)
    a, b = (s.measure(r, rng=np.random.default_rng(seed)) == 0 for seed in (1, 2))
    band = ~near & (dist <= 2)
    assert 0.4 < a[band].mean() < 0.6 and 0.4 < b[band].mean() < 0.6
    assert (a != b)[band].mean() > 0.3  # independent draws: about half of the band differs
    np.testing.assert_array_equal(a, s.measure(r, rng=np.random.default_rng(1)) == 0)  # reproducible


@pytest.mark.parametrize("kwargs", [{"edge_px": 0, "edge_drop": 0.9}, {"edge_px": 2, "edge_drop": 0.0}])
def test_no_edge_holes_when_switched_off(step, kwargs):
    r, _, _ = step
    assert np.all(sensor(**kwargs).measure(r, rng=np.random.default_rng(0)) > 0)


def test_a_step_below_the_edge_threshold_is_no_edge():
    r, near, dist = render_step(2.95)  # 3.0 / 2.95 = 1.017 < 1 + edge_threshold (0.04)
    assert near.sum() > 1000
    assert np.all(sensor(edge_px=2, edge_drop=1.0).measure(r, rng=np.random.default_rng(0)) > 0)
    # and with a threshold below the step the same edge drops its far side
    depth = sensor(edge_px=2, edge_drop=1.0, edge_threshold=0.01).measure(r, rng=np.random.default_rng(0))
    holes, band = depth == 0, ~near & (dist <= 2)
    assert not holes[~band].any() and holes[band].mean() > 0.98  # (the band's outermost corner pixels are spared)
