"""The mapping pipeline end to end: simulated room (ATE, colour accuracy against the true radiance), the real
7-Scenes sample (ATE, results folder), colour models, tracking failures, interruption, backends."""

from __future__ import annotations

import json

import numpy as np
import pytest
from box_room import box_room_sequence
from conftest import shared_path

from mapping.colour import FastForward, FrameColour, IrradianceColour, RawIntensity, make_colour_model
from mapping.datasets import open_dataset
from mapping.datasets.base import RGBDFrame
from mapping.datasets.in_memory import ArrayDataset
from mapping.export import RUNNING_MARKER, ResultsFolder, is_complete
from mapping.factory import make_backend, make_tracker
from mapping.pipeline import reconstruct
from radiometry.errors import OutputError
from radiometry.response import CameraResponse


@pytest.fixture(scope="module")
def room():
    from mapping.simulation import sample_sequence

    return open_dataset(sample_sequence("room"))


# --------------------------------------------------------------------------------------------------
# simulated room: tracking accuracy and colour accuracy against the truth
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_simulated_room_icp_ate(room):
    run = reconstruct(room, backend=make_backend("tsdf", voxel_size=0.02, depth_max=4.0),
                      tracker=make_tracker(depth_max=4.0), progress=False)
    assert run.fused == len(room) and run.skipped == 0
    assert run.ate is not None and run.ate.pairs == len(room)
    # spec: < 2 cm; measured 0.35 cm (0.09 cm at 1 cm voxels), Open3D's own loop 0.60 cm (0.26 cm)
    assert run.ate.rmse < 0.01
    gt = room.ground_truth()[1]
    assert np.linalg.norm(run.poses[-1, :3, 3] - gt[-1, :3, 3]) < 0.05   # no drift away (first pose = truth)


def _mesh_error(colours: np.ndarray, truth: np.ndarray, *, scale: str) -> float:
    """Mean absolute error of mesh colours against the true radiance, relative to the mean radiance, after a
    least-squares scale: ``scale="channel"`` fits one scale per channel (forgives white balance),
    ``scale="global"`` one scalar for all three channels, ``s = sum(t c) / sum(c^2)`` over every vertex and
    channel (what issue 5 asks for: any colour cast counts). Vertices farther than 3 cm from the true
    surface (NaN truth) or with a non-positive value are left out; they must be fewer than 10 %."""
    ok = np.all(np.isfinite(truth), 1) & np.all(truth > 0, 1) & np.all(colours > 0, 1)
    assert ok.mean() > 0.9 and ok.sum() > 5000           # measured: 99.2 % of 47 000 vertices
    c, t = colours[ok].astype(np.float64), truth[ok].astype(np.float64)
    if scale == "channel":
        s = (t * c).sum(0) / (c ** 2).sum(0)
    elif scale == "global":
        s = (t * c).sum() / (c ** 2).sum()
    else:
        raise ValueError(f"scale must be 'channel' or 'global', got {scale!r}")
    return float(np.abs(c * s - t).mean() / t.mean())


@pytest.fixture(scope="module")
def calibrated_lut(room, tmp_path_factory):
    """The vignetting LUT calibrated as a user would: a 50-frame white-paper sweep (fixed exposure) simulated
    with the room sample's own camera (``truth/camera.json``: same spec, resolution, response, vignetting
    and noise), accumulated with the camera's true response and fitted as a LUT (about 3 s)."""
    from mapping.simulation.sequences import simulate_paper
    from radiometry.simulation import CameraSpec
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting_lut, vignetting_error_levels

    spec = CameraSpec.load(room.truth_path("camera.json"))
    response = room.true_response()
    assert (spec.width, spec.height) == (room.width, room.height) == (320, 240)
    np.testing.assert_array_equal(spec.response().inverse_table, response.inverse_table)
    sweep = simulate_paper(tmp_path_factory.mktemp("sweep") / "paper", camera=spec, seed=1, n_frames=50,
                           force=True, progress=False, write_depth_images=False)
    acc = collect_vignetting(sweep / "rgb", response, progress=False)
    lut = fit_vignetting_lut(acc)
    # measured: 50 of 50 frames used; RMS error vs the true V 0.17 / 0.16 / 0.15 levels (flat field at 200)
    assert acc.frames_used >= 45
    assert np.all(vignetting_error_levels(lut, room.true_vignetting(), response) < 0.5)
    return lut


@pytest.fixture(scope="module")
def room_colour_runs(room, calibrated_lut):
    """The room fused at the ground-truth poses with each colour model: ``{name: (mesh colours, true radiance
    at the vertices, histogram stats)}``; the raw-intensity run is also given linearised through the true
    response as ``none-linearised`` (undoes the camera's non-linearity, not its vignetting or exposure)."""
    from mapping.simulation import load_room

    truth = load_room(room.truth_path("room.json"))
    response, V = room.true_response(), room.true_vignetting()
    exposures = room.true_exposures()
    stamps = np.array(sorted(exposures))
    k = np.array([exposures[s][0] * exposures[s][1:] for s in stamps])

    def true_exposure(frame, irradiance, view, pose):
        return k[np.argmin(np.abs(stamps - frame.timestamp))]

    models = {"none": RawIntensity(),
              "lut": IrradianceColour(response, V),
              "lut-calibrated": IrradianceColour(response, calibrated_lut),
              "lut+exposure": IrradianceColour(response, V, exposure=true_exposure,
                                               reference_exposure=float(np.median(k[:, 0])))}
    runs = {}
    for name, model in models.items():
        backend = make_backend("tsdf", voxel_size=0.02, depth_max=4.0)
        run = reconstruct(room, colour_model=model, backend=backend, poses="gt", progress=False)
        mesh = backend.extract_mesh()
        radiance = truth.radiance_at(mesh.vertices, mesh.normals, max_distance=0.03)
        runs[name] = (mesh.colours, radiance, run.histogram.stats())
    colours, radiance, stats = runs["none"]
    runs["none-linearised"] = (response.inverse(np.clip(colours, 0, 255)), radiance, stats)
    return runs


@pytest.mark.slow
def test_simulated_room_corrected_colours_are_closer_to_the_truth(room_colour_runs):
    """One scale per channel (white balance forgiven): what vignetting correction alone buys."""
    errors = {name: _mesh_error(c, t, scale="channel") for name, (c, t, _) in room_colour_runs.items()}
    hists = {name: stats for name, (_, _, stats) in room_colour_runs.items()}
    # measured: none linearised 13.2 %, LUT 5.6 %, calibrated LUT 5.6 %, LUT + true exposure 3.8 % (mean error
    # relative to the mean radiance)
    assert errors["lut"] < 0.7 * errors["none-linearised"]
    assert errors["lut-calibrated"] < 0.7 * errors["none-linearised"]
    assert errors["lut+exposure"] < errors["lut"]
    assert hists["lut+exposure"]["mean"] < hists["none"]["mean"]


@pytest.mark.slow
def test_simulated_room_colours_after_one_global_scale(room_colour_runs):
    """Issue 5 as written: with ground-truth poses, the mesh colours with LUT correction are closer to the truth
    (mean error after ONE global least-squares scale, the same for R, G and B) than without correction, with
    the simulator's true V and with a LUT calibrated from a white-paper sweep of the same camera.

    The truth is the surfaces' true radiance (albedo times the room's fixed, uneven lighting), i.e. the albedo
    as the camera can see it: no colour correction can remove the shading, so a comparison with the bare
    albedo measures the lighting (about 28-35 % for every run) rather than the correction."""
    errors = {name: _mesh_error(c, t, scale="global") for name, (c, t, _) in room_colour_runs.items()}
    # measured (relative to the mean radiance): none (raw 8-bit) 18.9 %, none linearised through the true
    # response 14.3 %, LUT (true V) 9.0 %, calibrated LUT 9.0 %, LUT + true exposure 3.8 %. The single scale
    # also counts the auto white balance's cast, which only the exposure run removes (9.0 % -> 3.8 %; with
    # one scale per channel the LUT runs are at 5.6 %).
    for lut in ("lut", "lut-calibrated"):
        assert errors[lut] < 0.55 * errors["none"], lut                  # measured ratio 0.48
        assert errors[lut] < 0.75 * errors["none-linearised"], lut       # measured ratio 0.63
    # the calibrated LUT does as well as the true V (measured 8.97 % vs 8.99 %)
    assert errors["lut-calibrated"] < 1.05 * errors["lut"]
    assert errors["lut+exposure"] < 0.6 * errors["lut"]                  # measured ratio 0.42


# --------------------------------------------------------------------------------------------------
# the real 7-Scenes sample: a complete run with its results folder
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_sevenscenes_run_writes_results(tmp_path):
    root = shared_path("rgbd", "redkitchen_7scenes_000-099")
    ds = open_dataset(root, frames=slice(0, 100, 3))
    out = ResultsFolder(tmp_path / "kitchen")
    colour = make_colour_model(CameraResponse.gamma(2.2))
    run = reconstruct(ds, colour_model=colour, backend=make_backend("tsdf", voxel_size=0.02), tracker=make_tracker(),
                      output=out, progress=False)
    # measured: ATE 1.19 cm over these 34 frames (all 100 frames at 1 cm: 1.09 cm; Open3D's loop: 1.26 cm)
    assert run.fused == len(ds) == 34 and run.ate.rmse < 0.05
    folder = out.path
    assert is_complete(folder) and not (folder / RUNNING_MARKER).exists()
    for name in ("mesh.ply", "trajectory.txt", "histogram.json", "histogram.npz",
                 "histogram.png", "metrics.json", "frames.csv", "summary.txt"):
        assert (folder / name).is_file(), name
    assert not (folder / "mesh.glb").exists() and not (folder / "mesh_colours.npz").exists()   # one mesh by default
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["status"] == "complete" and metrics["frames"]["fused"] == 34
    assert metrics["ate"]["rmse"] == pytest.approx(run.ate.rmse)
    assert metrics["histogram"]["count"] > 1_000_000 and 5 < metrics["histogram"]["median"] < 100
    assert metrics["memory"]["peak_rss_mb"] > 100 and metrics["map"]["blocks"] > 100
    assert metrics["colour_model"]["name"] == "response"
    from mapping.metrics import read_tum_trajectory

    stamps, poses = read_tum_trajectory(folder / "trajectory.txt")
    np.testing.assert_allclose(poses, run.poses, atol=1e-4)      # 7-Scenes rotations are orthonormal to 1e-4
    with pytest.raises(OutputError, match="--force"):
        ResultsFolder(folder)


# --------------------------------------------------------------------------------------------------
# colour models
# --------------------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("response", [CameraResponse.gamma(2.2), CameraResponse.linear(),
                                      CameraResponse.from_table(np.stack([np.exp(np.linspace(-9, 0, 256)),
                                                                          np.linspace(0.01, 1, 256) ** 3,
                                                                          np.linspace(0, 1, 256)], 1))])
def test_fast_forward_matches_the_response(response):
    rng = np.random.default_rng(0)
    E = (rng.random((20000, 3)) ** 3 * 1.3).astype(np.float32)
    E[:4] = [[0, -1, np.nan], [1, 1, 1], [2, 1e-9, np.inf], response.inverse_table[[0, 7, 254]].diagonal()]
    ff = FastForward(response)
    np.testing.assert_allclose(ff(E), response.forward(E), atol=2e-4)
    np.testing.assert_allclose(ff(E.reshape(100, 200, 3)), response.forward(E).reshape(100, 200, 3), atol=2e-4)
    np.testing.assert_allclose(ff.l1(E, E[::-1]), np.abs(response.forward(E) - response.forward(E[::-1])).sum(1),
                               atol=1e-3)
    half = FastForward(response, reference_exposure=0.5)
    np.testing.assert_allclose(half(E), response.forward(E * 0.5), atol=2e-4)


@pytest.mark.slow
def test_display_l1_does_not_depend_on_the_number_of_threads():
    """The histogram's L1 kernel runs rows in parallel; each row sums its channels in one order, so one thread and
    every thread give the same float32 bits (and the same as the serial forward look-ups summed in that order)."""
    from mapping import _native

    ff = FastForward(CameraResponse.gamma(2.2), reference_exposure=1.3)
    rng = np.random.default_rng(3)
    a = (rng.random((50_001, 3)) * 1.2).astype(np.float32)
    b = (a * rng.uniform(0.9, 1.1, a.shape)).astype(np.float32)
    a[::97, 0], b[::89, 1], b[::83, 2] = np.nan, 5.0, -1.0
    threads = _native.get_num_threads()
    try:
        _native.set_num_threads(1)
        one = ff.l1(a, b)
    finally:
        _native.set_num_threads(threads)
    every = ff.l1(a, b)
    assert one.dtype == np.float32 and np.array_equal(one, every)
    la, lb = ff(a).astype(np.float64), ff(b).astype(np.float64)
    serial = np.zeros(len(a), np.float32)
    for c in range(3):  # out[i] += |la - lb| channel by channel, in float32 as the kernel stores it
        serial = (serial.astype(np.float64) + np.abs(la[:, c] - lb[:, c])).astype(np.float32)
    np.testing.assert_allclose(every, serial, atol=1e-4)


@pytest.mark.slow
def test_colour_models():
    response = CameraResponse.gamma(2.2)
    rgb = np.random.default_rng(1).integers(0, 256, (6, 8, 3)).astype(np.uint8)
    frame = RGBDFrame(0, 0.0, rgb, np.ones((6, 8), np.float32), np.eye(3))
    raw = RawIntensity()
    np.testing.assert_array_equal(raw.to_map(frame).colour, rgb.astype(np.float32))
    np.testing.assert_array_equal(raw.to_display(np.array([[-3, 100.5, 300]], np.float32)), [[0, 100.5, 255]])
    V = np.full((6, 8, 3), 0.5, np.float32)
    model = IrradianceColour(response, V)
    out = model.to_map(frame)
    assert isinstance(out, FrameColour) and out.valid is None and out.reason == ""
    E = out.colour
    assert E.dtype == np.float32
    np.testing.assert_allclose(E, response.inverse(rgb) / 0.5, rtol=1e-6)
    np.testing.assert_allclose(model.to_display(E * 0.5), rgb, atol=1e-3)     # display = f(E * k_ref)
    # the exposure hook divides by k per channel
    seen = []
    hooked = IrradianceColour(response, V, exposure=lambda f, e, view, pose: seen.append(pose) or np.array([2.0, 1.0, 0.5]))
    np.testing.assert_allclose(hooked.to_map(frame, None, np.eye(4)).colour, E / [2.0, 1.0, 0.5], rtol=1e-6)
    np.testing.assert_array_equal(seen[0], np.eye(4))                     # the hook receives the pose
    bad = IrradianceColour(response, exposure=lambda f, e, view, pose: -1.0)
    with pytest.raises(ValueError, match="exposure estimate"):
        bad.to_map(frame)
    a, b = E.reshape(-1, 3)[:10], E.reshape(-1, 3)[10:20]
    np.testing.assert_allclose(model.display_l1(a, b), np.abs(model.to_display(a) - model.to_display(b)).sum(1),
                               atol=1e-3)
    assert isinstance(make_colour_model(), RawIntensity)
    with pytest.raises(ValueError, match="needs the camera response"):
        make_colour_model(None, V)
    with pytest.raises(TypeError, match="CameraResponse"):
        IrradianceColour("gamma")
    assert model.describe()["name"] == "response+vignetting"


# --------------------------------------------------------------------------------------------------
# failures, interruption, backends
# --------------------------------------------------------------------------------------------------
def _box(n=8):
    ds, _ = box_room_sequence(n_frames=n, width=160, height=120)
    return ds


@pytest.mark.slow
def test_a_frame_without_depth_is_skipped_and_not_fused():
    ds = _box()
    frames = list(ds.frames)
    f = frames[4]
    frames[4] = RGBDFrame(f.index, f.timestamp, f.rgb, np.zeros_like(f.depth), f.K, f.pose, f.name)
    backend = make_backend("tsdf", voxel_size=0.02, depth_max=5.0)
    run = reconstruct(ArrayDataset(frames), backend=backend, tracker=make_tracker(depth_max=5.0), progress=False)
    assert run.skipped == 1 and run.fused == 7 and backend.frames_integrated == 7
    record = run.records[4]
    assert not record.fused and "valid depth pixels" in record.reason
    assert run.skip_reasons() == {"too few valid depth pixels": 1}
    assert 4 / 30 not in run.stamps.tolist()
    # the frame after the gap is tracked across it
    assert run.records[5].fused and run.ate.rmse < 0.01


class _RecordingColour(RawIntensity):
    """Raw intensities that reject every pixel of frame 2 and the left half of the others, recording what the
    pipeline hands over."""

    def __init__(self):
        self.calls = []

    def to_map(self, frame, view=None, pose=None):
        self.calls.append((frame.index, view, None if pose is None else pose.copy()))
        valid = np.ones(frame.depth.shape, bool)
        valid[:, : frame.width // 2] = False
        if frame.index == 2:
            valid[:] = False
        return FrameColour(frame.rgb.astype(np.float32), valid, "colour rejected: the test says so")


@pytest.mark.slow
def test_the_frame_contract_pose_view_and_valid_pixels():
    """The colour model gets the view rendered for the frame and the pose it is fused at; its valid mask reaches
    the backend; a frame with nothing valid is skipped with the model's reason."""
    ds = _box(4)
    colour = _RecordingColour()
    backend = make_backend("tsdf", voxel_size=0.02, depth_max=5.0)
    fused = []
    integrate = backend.integrate
    backend.integrate = lambda *a, **kw: fused.append(kw["valid"]) or integrate(*a, **kw)
    run = reconstruct(ds, colour_model=colour, backend=backend, poses="gt", progress=False)
    assert [c[0] for c in colour.calls] == [0, 1, 2, 3]
    for index, view, pose in colour.calls:
        np.testing.assert_array_equal(pose, ds[index].pose)
        np.testing.assert_array_equal(view.pose, pose)            # the backend's view of this frame, at its pose
    assert run.fused == 3 and run.records[2].reason == "colour rejected: the test says so"
    assert len(fused) == 3 and all(not v[:, :80].any() and v[:, 80:].all() for v in fused)


@pytest.mark.slow
def test_tracking_lost_for_good_raises(tmp_path):
    ds = _box(5)
    frames = [ds.frames[0]] + [RGBDFrame(f.index, f.timestamp, f.rgb, np.zeros_like(f.depth), f.K, f.pose)
                               for f in ds.frames[1:]]
    from mapping.pipeline import TrackingError

    out = ResultsFolder(tmp_path / "lost")
    with pytest.raises(TrackingError, match="4 consecutive frames"):
        reconstruct(ArrayDataset(frames), backend=make_backend("tsdf", voxel_size=0.02, depth_max=5.0),
                    tracker=make_tracker(depth_max=5.0), output=out, max_consecutive_failures=4, progress=False)
    assert (out.path / RUNNING_MARKER).exists()
    assert json.loads((out.path / "metrics.json").read_text())["status"] == "failed"


class _Interrupting(ArrayDataset):
    def __getitem__(self, index):
        if index == 3:
            raise KeyboardInterrupt
        return super().__getitem__(index)


@pytest.mark.slow
def test_interrupted_run_stays_marked_incomplete(tmp_path):
    ds = _Interrupting(_box(6).frames)
    out = ResultsFolder(tmp_path / "run")
    with pytest.raises(KeyboardInterrupt):
        reconstruct(ds, backend=make_backend("tsdf", voxel_size=0.02, depth_max=5.0), poses="gt", output=out,
                    progress=False)
    assert (out.path / RUNNING_MARKER).exists() and not is_complete(out.path)
    metrics = json.loads((out.path / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and metrics["frames"]["fused"] == 3
    assert (out.path / "trajectory.txt").read_text().count("\n") == 4         # header + 3 poses
    ResultsFolder(out.path, force=True)                                       # --force reuses the folder


@pytest.mark.slow
def test_a_frame_cut_short_by_ctrl_c_is_not_counted_as_skipped(tmp_path):
    """Ctrl-C while frame 3 is being fused: frames 0-2 fused, frame 3 neither fused nor counted as skipped (it
    once appeared as a skip with an empty reason)."""
    backend = make_backend("tsdf", voxel_size=0.02, depth_max=5.0)
    original = backend.integrate

    def integrate(*args, frame_index=0, **kwargs):
        if frame_index == 3:
            raise KeyboardInterrupt
        return original(*args, frame_index=frame_index, **kwargs)

    backend.integrate = integrate
    out = ResultsFolder(tmp_path / "run")
    with pytest.raises(KeyboardInterrupt):
        reconstruct(_box(6), backend=backend, poses="gt", output=out, progress=False)
    metrics = json.loads((out.path / "metrics.json").read_text())
    assert metrics["status"] == "interrupted"
    assert metrics["frames"] | {"skip_reasons": None, "skipped_frames": None} == {
        "total": 6, "processed": 3, "fused": 3, "skipped": 0, "skip_reasons": None, "skipped_frames": None}
    assert metrics["frames"]["skip_reasons"] == {} and metrics["frames"]["skipped_frames"] == []


@pytest.mark.slow
def test_backends_by_name():
    with pytest.raises(ValueError, match="backend must be one of tsdf, surfel, got 'octomap'"):
        make_backend("octomap")
    assert type(make_backend("surfel", voxel_size=0.02, block_resolution=8)).__name__ == "SurfelBackend"
    with pytest.raises(ValueError, match="surfel_mesh applies to the surfel backend only"):
        make_backend("tsdf", surfel_mesh=True)
    with pytest.raises(ValueError, match="poses must be one of"):
        reconstruct(_box(2), backend=make_backend("tsdf"), poses="slam")
    with pytest.raises(ValueError, match="needs a tracker"):
        reconstruct(_box(2), backend=make_backend("tsdf"), poses="icp")


@pytest.mark.slow
def test_surfel_backend_through_the_pipeline():
    pytest.importorskip("mapping.fusion.surfel")
    ds = _box(6)
    backend = make_backend("surfel", depth_max=5.0)
    assert backend.name == "surfel"
    run = reconstruct(ds, backend=backend, tracker=make_tracker(depth_max=5.0), progress=False)
    assert run.fused == 6 and run.histogram.total > 1000
    assert run.ate.rmse < 0.02
