"""Held-out frames (mapping.holdout): known answers built independently of the code, withheld frames really not
fused, the CLI end to end, bad --holdout-every."""

from __future__ import annotations

import json
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
def test_every_held_out_positions():
    assert check_holdout_every(5, 50) == 5
    assert [i for i in range(12) if is_held_out(i, 5)] == [4, 9]
    assert not any(is_held_out(i, 0) for i in range(12))
    with pytest.raises(HoldoutError, match="at least 3"):
        check_holdout_every(2, 2)


# --------------------------------------------------------------------------------------------------
# through the pipeline: withheld frames are tracked, never fused
# --------------------------------------------------------------------------------------------------
def _box(n):
    from box_room import box_room_sequence

    ds, _ = box_room_sequence(n_frames=n, width=160, height=120)
    return ds


@pytest.mark.slow
def test_withheld_frames_are_not_fused_the_map_is_the_subsets():
    """A run withholding frames 2, 5, 8 fuses exactly what a run of the other frames alone fuses: the same
    histogram bin by bin and the same map size; the withheld frames are judged at their ground-truth poses."""
    from mapping.datasets.in_memory import ArrayDataset
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct

    ds = _box(10)
    full_backend = make_backend("tsdf", voxel_size=0.02, depth_max=5.0)
    run = reconstruct(ds, backend=full_backend, poses="gt", progress=False, holdout_every=3)
    sub_backend = make_backend("tsdf", voxel_size=0.02, depth_max=5.0)
    subset = reconstruct(ArrayDataset([f for i, f in enumerate(ds.frames) if i not in (2, 5, 8)]),
                         backend=sub_backend, poses="gt", progress=False)
    assert full_backend.frames_integrated == 7 == sub_backend.frames_integrated
    np.testing.assert_array_equal(run.histogram.counts, subset.histogram.counts)
    assert run.histogram.total == subset.histogram.total > 0
    full_stats, sub_stats = full_backend.stats(), sub_backend.stats()
    assert full_stats.pop("ray_casts") == sub_stats.pop("ray_casts") + 3   # the three renders that judge
    assert full_stats == sub_stats
    assert [r.reason for r in run.records if not r.fused] == ["held out for evaluation"] * 3
    assert sorted(run.held_out_poses) == [2, 5, 8]
    for i, pose in run.held_out_poses.items():
        np.testing.assert_array_equal(pose, ds.frames[i].pose)
    assert [f.index for f in run.holdout.frames] == [ds.frames[i].index for i in (2, 5, 8)]
    assert all(f.evaluated and f.pixels > 5000 for f in run.holdout.frames)
    # raw intensities of a box with constant light: the fitted gains are 1 and the prediction close
    np.testing.assert_allclose([f.gain for f in run.holdout.frames], 1.0, atol=0.01)
    assert run.holdout.psnr > 35
    assert run.metrics()["holdout"]["frames_evaluated"] == 3
    # withheld frames were asked for: neither fused nor skipped (frames = fused + skipped + held out)
    frames = run.metrics()["frames"]
    assert run.fused == 7 and run.held_out == 3 and run.skipped == 0 and run.skip_reasons() == {}
    assert frames["held_out"] == 3 and frames["skipped"] == 0 and frames["skipped_frames"] == []
    assert run.summary_row()["held out"] == 3 and run.summary_row()["skipped"] == 0


@pytest.mark.slow
def test_withheld_frames_are_tracked_with_icp():
    from mapping.factory import make_backend, make_tracker
    from mapping.pipeline import reconstruct

    ds = _box(9)
    backend = make_backend("tsdf", voxel_size=0.02, depth_max=5.0)
    run = reconstruct(ds, backend=backend, tracker=make_tracker(depth_max=5.0), poses="icp", progress=False,
                      holdout_every=4)
    assert backend.frames_integrated == 7 and sorted(run.held_out_poses) == [3, 7]
    for i, pose in run.held_out_poses.items():
        assert np.isfinite(run.records[i].fitness)                     # ICP ran on it
        np.testing.assert_allclose(pose[:3, 3], ds.frames[i].pose[:3, 3], atol=0.02)
    assert len(run.holdout.evaluated) == 2


@pytest.mark.slow
def test_a_comparison_withholds_the_same_frames_when_the_map_starts_late(tmp_path):
    """The first frame has no depth, so with ICP the map starts at position 1, a withheld position: it must stay
    withheld (without a pose, it cannot found the map), as in the runs at the shared poses, which withhold by
    position; every method fuses the same frames and judges the same ones."""
    import dataclasses

    from mapping.compare import compare, make_methods
    from mapping.datasets.in_memory import ArrayDataset

    frames = list(_box(8).frames)
    frames[0] = dataclasses.replace(frames[0], depth=np.zeros_like(frames[0].depth))
    methods = make_methods(CameraResponse.gamma(), names=["none", "response"])
    res = compare(ArrayDataset(frames), methods, output=tmp_path / "cmp", poses="icp", views=0,
                  progress=False, holdout_every=2, depth_max=5.0, voxel_size=0.02, mesh_formats=("ply",))
    assert res.poses_identical
    for r in res.results:
        assert sorted(r.run.held_out_poses) == [1, 3, 5, 7] and r.run.held_out_poses[1] is None
        assert r.run.fused == 3 and r.run.skipped == 1 and r.run.skip_reasons() != {}
        assert [f.reason for f in r.run.holdout.frames] == ["no pose", "", "", ""]


def test_reconstruct_refuses_a_bad_every_before_anything_runs():
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct

    backend = make_backend("tsdf", voxel_size=0.02, depth_max=5.0)
    with pytest.raises(HoldoutError, match="2..3 for 4 frames"):
        reconstruct(_box(4), backend=backend, poses="gt", progress=False, holdout_every=4)
    assert backend.frames_integrated == 0


# --------------------------------------------------------------------------------------------------
# the commands
# --------------------------------------------------------------------------------------------------
def _cli(*args):
    from click.testing import CliRunner

    from mapping.cli import cli

    return CliRunner().invoke(cli, list(args), catch_exceptions=False)


@pytest.fixture(scope="module")
def room_seq():
    from mapping.simulation import sample_sequence

    return sample_sequence("room")


@pytest.mark.slow
def test_compare_holdout_end_to_end(room_seq, tmp_path):
    """Three methods, ICP tracked once: every method judges the same withheld frames at the same poses; the figures
    reach compare.csv/.json, holdout.csv, each method's metrics.json and the report."""
    import csv
    import json

    seq, out = room_seq, tmp_path / "cmp"
    res = _cli("compare", str(seq), "-r", str(seq / "truth" / "response.npz"), "--vignetting-lut",
               str(seq / "truth" / "vignetting.npy"), "--methods", "none,response+ec,lut+ec", "--poses", "icp",
               "--frames", "0:10", "--voxel-size", "0.02", "--depth-max", "4", "--holdout-every", "3", "--views", "0",
               "--no-glb", "--no-progress", "-o", str(out))
    assert res.exit_code == 0, res.output
    assert "holdout PSNR" in res.output and "1 frame in 3 withheld" in res.output
    rows = list(csv.DictReader((out / "holdout.csv").open()))
    assert [r["method"] for r in rows] == ["none"] * 3 + ["response+ec"] * 3 + ["lut+ec"] * 3
    assert [r["index"] for r in rows[:3]] == ["2", "5", "8"] and all(r["reason"] == "" for r in rows)
    table = {r["method"]: r for r in csv.DictReader((out / "compare.csv").open())}
    doc = json.loads((out / "compare.json").read_text())
    assert doc["parameters"]["holdout_every"] == 3 and "holdout PSNR" in doc["columns"]
    for name in ("none", "response+ec", "lut+ec"):
        metrics = json.loads((out / name / "metrics.json").read_text())
        assert metrics["frames"]["fused"] == 7 and metrics["holdout"]["frames_evaluated"] == 3
        assert float(table[name]["holdout PSNR"]) == pytest.approx(metrics["holdout"]["psnr"], abs=1e-3)
        assert 15 < metrics["holdout"]["psnr"] < 60 and metrics["holdout"]["l1"] > 0
        assert (out / name / "holdout.csv").is_file()
    # the same frames at the same pixels for every method (their maps' geometry is the same up to clipped pixels)
    pixels = {r["method"]: int(r["pixels"]) for r in rows if r["index"] == "5"}
    assert max(pixels.values()) - min(pixels.values()) < 0.02 * max(pixels.values())
    assert "Held-out frames" in (out / "report.html").read_text()
    # the simulated camera vignettes strongly and the LUT is its true V: the metric must see it (measured: L1 about
    # 4 % lower with V on these 10 frames, 9 % on 15; the bound leaves room for noise)
    l1 = {name: float(table[name]["holdout L1"]) for name in table}
    psnr = {name: float(table[name]["holdout PSNR"]) for name in table}
    assert l1["lut+ec"] < 0.98 * l1["response+ec"] and psnr["lut+ec"] > psnr["response+ec"], (l1, psnr)


@pytest.mark.slow
def test_reconstruct_holdout_end_to_end(room_seq, tmp_path):
    import json

    out = tmp_path / "run"
    res = _cli("reconstruct", str(room_seq), "--poses", "gt", "--frames", "0:8", "--voxel-size", "0.02",
               "--depth-max", "4", "--holdout-every", "4", "--no-progress", "-o", str(out))
    assert res.exit_code == 0, res.output
    assert "warning: skipped" not in res.output    # the withheld frames were asked for
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["frames"]["fused"] == 6 and metrics["holdout"]["frames_evaluated"] == 2
    assert (out / "holdout.csv").read_text().splitlines()[0].startswith("index,psnr_db")
    assert json.loads((out / "config.json").read_text())["pipeline"]["holdout_every"] == 4


@pytest.mark.parametrize("every", ["0", "-2", "1", "8", "20"])
@pytest.mark.parametrize("command", ["reconstruct", "compare"])
def test_bad_holdout_every_is_one_line(room_seq, tmp_path, command, every):
    out = tmp_path / "x"
    extra = ["-r", str(room_seq / "truth" / "response.npz"), "--methods", "none"] if command == "compare" else []
    res = _cli(command, str(room_seq), *extra, "--frames", "0:8", "--holdout-every", every, "--no-progress",
               "-o", str(out))
    assert res.exit_code == 1, res.output
    lines = [line for line in res.output.splitlines() if line.strip()]
    assert len(lines) == 1 and "--holdout-every must be a whole number in 2..7 for 8 frames" in lines[0], res.output
    assert not out.exists()


@pytest.mark.slow
def test_batch_summary_rows_carry_the_holdout_figures(tmp_path):
    """A batch's summary.csv shows each sequence's held-out PSNR and L1 when its run withheld frames, and no such
    columns for a run that did not."""
    from mapping.batch.commands import reconstruct_rows
    from mapping.batch.report import columns_of

    metrics = {"frames": {"total": 10, "fused": 8}, "timing": {"seconds": 2.0},
               "histogram": {"mean": 12.5, "median": 10.0, "p90": 30.0}, "ate": None}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    plain = reconstruct_rows(tmp_path)
    assert "holdout PSNR" not in columns_of(plain)
    metrics["holdout"] = {"psnr": 24.25, "l1": 30.5, "pixels": 1000}
    (tmp_path / "metrics.json").write_text(json.dumps(metrics))
    (row,) = reconstruct_rows(tmp_path)
    assert row["holdout PSNR"] == 24.25 and row["holdout L1"] == 30.5 and row["L1 mean"] == 12.5
    assert columns_of([row]).index("holdout PSNR") < columns_of([row]).index("error")


@pytest.mark.slow
def test_periphery_and_lowpass_psnr_see_a_smooth_field_that_texture_hides():
    """A prediction wrong by a smooth field that darkens the corners (a vignette left uncorrected) plus
    zero-mean pixel noise: the low-pass PSNR sees only the field, the periphery PSNR the corners, both computed
    here independently of the module."""
    from mapping.holdout import LOWPASS_WINDOW, PERIPHERY, HoldoutFrame, HoldoutResult, _evaluate_frame

    h, w = 120, 160
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    r = np.hypot(x - (w - 1) / 2, y - (h - 1) / 2) / (0.5 * np.hypot(w, h))
    observed = np.full((h, w, 3), 120, np.uint8)
    smooth = (-20.0 * r ** 2)[..., None] * np.ones(3)           # the field: 0 at the centre, -20 in the corners
    noise = np.where(rng.random((h, w, 1)) < 0.5, -6.0, 6.0) * np.ones(3)   # +-6 levels, zero mean per window
    predicted = observed + smooth + noise

    class Model:
        def predict_observed(self, colour, rgb, valid):
            return predicted, np.ones(3)

    class Frame:
        index, rgb, K = 0, observed, np.eye(3)
        depth = np.ones((h, w), np.float32)

    def render(pose, K, hh, ww):
        return np.ones((hh, ww, 3), np.float32), np.ones((hh, ww), np.float32)

    record = _evaluate_frame(Frame(), np.eye(4), render, Model(), 200, dict(
        depth_tolerance=0.05, depth_relative=0.02, dark=5, saturated=250, edge_dilation=2))
    err = smooth + noise
    full = 10 * np.log10(255 ** 2 / np.mean(err ** 2))
    outer = r > PERIPHERY
    periphery = 10 * np.log10(255 ** 2 / np.mean(err[outer] ** 2))
    assert record.psnr == pytest.approx(full, abs=1e-6)
    assert record.psnr_periphery == pytest.approx(periphery, abs=1e-6) and record.psnr_periphery < record.psnr
    # local means by an integral image (windows cut by the image border count only their inside; a pixel is kept
    # when at least half its window is inside): exactly the module's figure
    half = LOWPASS_WINDOW // 2
    integral = np.zeros((h + 1, w + 1, 3))
    integral[1:, 1:] = err.cumsum(0).cumsum(1)
    y0, y1 = np.clip(np.arange(h) - half, 0, h), np.clip(np.arange(h) + half + 1, 0, h)
    x0, x1 = np.clip(np.arange(w) - half, 0, w), np.clip(np.arange(w) + half + 1, 0, w)
    sums = (integral[y1][:, x1] - integral[y0][:, x1] - integral[y1][:, x0] + integral[y0][:, x0])
    count = (y1 - y0)[:, None] * (x1 - x0)[None, :]
    keep = count >= 0.5 * LOWPASS_WINDOW ** 2
    local = sums[keep] / count[keep][:, None]
    assert record.psnr_lowpass == pytest.approx(10 * np.log10(255 ** 2 / np.mean(local ** 2)), abs=1e-6)
    # and it is the smooth field's: the noise averages out (within 0.5 dB of the field's own local means)
    field_sums = (np.pad(smooth, ((1, 0), (1, 0), (0, 0))).cumsum(0).cumsum(1))
    fs = field_sums[y1][:, x1] - field_sums[y0][:, x1] - field_sums[y1][:, x0] + field_sums[y0][:, x0]
    field_local = fs[keep] / count[keep][:, None]
    assert abs(record.psnr_lowpass - 10 * np.log10(255 ** 2 / np.mean(field_local ** 2))) < 0.5
    assert record.psnr_lowpass > record.psnr + 2
    pooled = HoldoutResult([record, HoldoutFrame(1, reason="no pose")])
    assert pooled.psnr_periphery == pytest.approx(record.psnr_periphery)
    assert pooled.psnr_lowpass == pytest.approx(record.psnr_lowpass)
    assert "psnr_periphery_db" in pooled.csv() and pooled.to_dict()["psnr_lowpass"] == pooled.psnr_lowpass
