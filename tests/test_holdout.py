"""Held-out frames (mapping.holdout): known answers built independently of the code, withheld frames really not
fused, the CLI end to end, bad --holdout-every."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mapping.colour import IrradianceColour, RawIntensity
from mapping.datasets.base import RGBDFrame
from mapping.holdout import (HoldoutError, check_holdout_every, evaluate_holdout, is_held_out, valid_pixels)
from radiometry.response import CameraResponse

H, W = 48, 64
K = np.array([[50.0, 0, W / 2], [0, 50.0, H / 2], [0, 0, 1]])


def _frame(rgb, depth, index=7):
    return RGBDFrame(index=index, timestamp=float(index), rgb=np.ascontiguousarray(rgb, dtype=np.uint8),
                     depth=np.asarray(depth, dtype=np.float32), K=K)


def _levels(seed=0, lo=10, hi=120):
    return np.random.default_rng(seed).integers(lo, hi, size=(H, W, 3)).astype(np.float32)


def _flat_render(colour, depth=2.0):
    def render(pose, K_, height, width):
        assert (height, width) == colour.shape[:2]
        return colour, np.full((height, width), depth, np.float32)
    return render


def test_raw_exact_gain_gives_infinite_psnr():
    m = 4 * _levels(0, 3, 30)  # multiples of 4: every product below is an integer
    gain = np.array([2.0, 1.5, 1.25])
    rgb = m * gain
    assert np.all(rgb == np.round(rgb)) and rgb.max() < 250
    res = evaluate_holdout([_frame(rgb, np.full((H, W), 2.0))], [np.eye(4)], _flat_render(m), RawIntensity())
    (f,) = res.frames
    np.testing.assert_allclose(f.gain, gain, rtol=0, atol=1e-12)
    assert f.psnr == math.inf and f.l1 == 0.0 and f.pixels > 0.8 * H * W
    assert res.psnr == math.inf and res.l1 == 0.0


def test_raw_known_error_gives_the_expected_figures():
    m = _levels(1)
    rgb = 2 * m
    err = np.zeros((H, W), bool)
    err[::5, ::3] = True              # far fewer than half the pixels: the median ratio stays 2
    rgb[err, 0] += 3
    depth = np.full((H, W), 2.0)
    res = evaluate_holdout([_frame(rgb, depth)], [np.eye(4)], _flat_render(m), RawIntensity(), edge_dilation=-1)
    (f,) = res.frames
    n = H * W  # no edge test (-1), flat depth, every level within 5..249: every pixel valid
    assert f.pixels == n
    assert f.gain[0] == 2.0
    k = int(err.sum())
    assert f.l1 == pytest.approx(3 * k / n, abs=1e-12)
    assert f.psnr == pytest.approx(10 * math.log10(255 ** 2 / (9 * k / (3 * n))), abs=1e-9)


def test_irradiance_with_vignetting_recovers_exposure():
    """Levels chosen first, the map's irradiance built backwards through the true response and vignetting
    (``E = f^-1(I) / (k V)``): the prediction must give the levels back and the gain k."""
    response = CameraResponse.gamma(2.2)
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - W / 2) ** 2 + (yy - H / 2) ** 2) / ((W / 2) ** 2 + (H / 2) ** 2)
    V = np.stack([1 - 0.45 * r2, 1 - 0.4 * r2, 1 - 0.35 * r2 ** 1.5], axis=2).astype(np.float32)
    k = np.array([1.7, 1.2, 0.8])
    levels = _levels(2, 20, 240)
    E = (response.inverse(levels.astype(np.uint8)).astype(np.float64) / (k * V)).astype(np.float32)
    model = IrradianceColour(response, V)
    res = evaluate_holdout([_frame(levels, np.full((H, W), 2.0))], [np.eye(4)], _flat_render(E), model)
    (f,) = res.frames
    np.testing.assert_allclose(f.gain, k, rtol=1e-4)
    assert f.psnr > 70 and f.l1 < 0.01
    # the same frame judged without the vignetting: the model cannot explain the corners
    flat = evaluate_holdout([_frame(levels, np.full((H, W), 2.0))], [np.eye(4)], _flat_render(E),
                            IrradianceColour(response))
    assert flat.psnr < f.psnr - 30 and flat.l1 > 5


def test_valid_pixels_leaves_out_occlusion_clipping_and_edges():
    rgb = np.full((H, W, 3), 100, np.uint8)
    rgb[:5, :, 1] = 252          # saturated in one channel
    rgb[5:10, :, :] = 2          # dark
    depth = np.full((H, W), 2.0, np.float32)
    render = depth.copy()
    render[20:30, 20:30] = 1.5   # the map sees an occluder the frame does not: not the same surface
    render[40:, :] = 0           # no surface
    ok = valid_pixels(rgb, depth, render, edge_dilation=-1)
    assert not ok[:10].any() and not ok[20:30, 20:30].any() and not ok[40:].any()
    assert ok[15, 5] and ok[35, 40]
    # within tolerance (5 cm + 2 % of 2 m = 9 cm) counts, beyond it does not
    render2 = depth.copy()
    render2[:, : W // 2] += 0.085
    render2[:, W // 2:] += 0.095
    ok2 = valid_pixels(rgb, depth, render2, edge_dilation=-1)
    assert ok2[30, 5] and not ok2[30, W - 5]
    # the edge test removes pixels along the occluder's silhouette
    with_edges = valid_pixels(rgb, depth, render, edge_dilation=2)
    assert not with_edges[18, 25] and ok[18, 25]


def test_frames_without_pose_or_pixels_are_recorded_not_pooled():
    m = _levels(3)
    good = _frame(2 * m, np.full((H, W), 2.0), index=4)
    dark = _frame(np.zeros((H, W, 3)), np.full((H, W), 2.0), index=9)
    res = evaluate_holdout([good, dark, good], [np.eye(4), np.eye(4), None], _flat_render(m), RawIntensity())
    assert [f.index for f in res.frames] == [4, 9, 4]
    assert res.frames[1].reason.startswith("0 valid pixels") and res.frames[2].reason == "no pose"
    assert len(res.evaluated) == 1 and res.pixels == res.frames[0].pixels
    d = res.to_dict()
    assert d["frames_held_out"] == 3 and d["frames_evaluated"] == 1 and len(d["per_frame"]) == 3
    assert res.csv("none").splitlines()[0].startswith("method,index,psnr_db")


def test_pooled_figures_pool_pixels_not_frame_means():
    m = _levels(4)
    a = 2 * m
    b = 2 * m
    b[: H // 2, :, 2] += 4   # half the pixels wrong in one channel... but the median ratio must stay 2:
    b[: H // 2, : W // 2 + 2, 2] -= 4  # leave only a quarter (minus a little) wrong
    depth = np.full((H, W), 2.0)
    res = evaluate_holdout([_frame(a, depth), _frame(b, depth)], [np.eye(4)] * 2, _flat_render(m), RawIntensity(),
                           edge_dilation=-1)
    fa, fb = res.frames
    wrong = int(((b - a) != 0).any(axis=2).sum())
    assert fa.l1 == 0 and fb.l1 == pytest.approx(4 * wrong / (H * W))
    assert res.l1 == pytest.approx(4 * wrong / (2 * H * W))
    assert res.psnr == pytest.approx(10 * math.log10(255 ** 2 / (16 * wrong / (6 * H * W))))


@pytest.mark.parametrize("every", [0, -1, 1, 10, 11, 2.5, True, "3"])
def test_bad_every_is_refused(every):
    with pytest.raises(HoldoutError, match=r"--holdout-every must be a whole number in 2\.\.9 for 10 frames"):
        check_holdout_every(every, 10)


def test_every_held_out_positions():
    assert check_holdout_every(5, 50) == 5
    assert [i for i in range(12) if is_held_out(i, 5)] == [4, 9]
    assert not any(is_held_out(i, 0) for i in range(12))
    with pytest.raises(HoldoutError, match="at least 3"):
        check_holdout_every(2, 2)
