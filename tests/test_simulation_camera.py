"""The simulated camera: CRFs, vignetting fields, exposure control, noise, round trips, determinism."""

from __future__ import annotations

import json

import numpy as np
import pytest

from radiometry.errors import CalibrationFileError
from radiometry.response import CameraResponse
from radiometry.simulation import (CRF_PRESETS, AutoExposure, AutoWhiteBalance, CameraSpec, SimulatedCamera,
                                   VignettingSpec, crf_from_pcalib, crf_gamma, crf_linear, crf_s_curve,
                                   crf_spec_from_file, find_lensfun_vignetting, jpeg_roundtrip, make_crf,
                                   nonradial_field, polynomial_for_corner, polynomial_vignetting,
                                   vignetting_preset)
from conftest import shared_path

W, H = 160, 120


def smooth_field(seed: int, shape=(H, W), lo: float = 5.0, hi: float = 60.0) -> np.ndarray:
    """A textured radiance image (float32 (H, W, 3)) with structure at several scales."""
    import cv2

    rng = np.random.default_rng(seed)
    out = np.zeros(shape + (3,), np.float32)
    for cells in (4, 16, 60):
        small = rng.uniform(0, 1, (cells * shape[0] // shape[1] + 2, cells + 2, 3)).astype(np.float32)
        out += cv2.resize(small, shape[::-1], interpolation=cv2.INTER_CUBIC)
    out -= out.min()
    out /= out.max()
    return (lo + (hi - lo) * out).astype(np.float32)


def luma(image: np.ndarray) -> float:
    return float(image.reshape(-1, 3).astype(np.float64).mean(0) @ [0.299, 0.587, 0.114])


# ------------------------------------------------------------------------------------------ CRFs
@pytest.mark.parametrize("family", ["linear", "gamma", "s_curve"])
def test_parametric_crfs_are_valid_responses(family):
    resp = make_crf(**CRF_PRESETS[family])
    table = resp.inverse_table
    assert table.shape == (256, 3)
    assert np.all(np.diff(table, axis=0) > 0)
    np.testing.assert_allclose(table[-1], 1.0)
    np.testing.assert_allclose(table[0], 0.0, atol=1e-12)
    # forward(inverse(I)) == I for every level
    levels = np.repeat(np.arange(256, dtype=np.uint8)[:, None], 3, axis=1)
    np.testing.assert_array_equal(resp.forward(resp.inverse(levels), dtype=np.uint8), levels)


def test_gamma_and_s_curve_shapes():
    x = np.arange(256) / 255.0
    np.testing.assert_allclose(crf_gamma(2.2).inverse_table[:, 1], x ** 2.2, rtol=1e-12)
    per_channel = crf_gamma([1.8, 2.0, 2.4]).inverse_table
    np.testing.assert_allclose(per_channel[128], (128 / 255) ** np.array([1.8, 2.0, 2.4]), rtol=1e-12)
    # a pure logistic tone curve (gamma 1): f^-1 is a logit, concave in the shadows, convex in the highlights
    s = crf_s_curve(contrast=6.0, midpoint=0.5, gamma=1.0).inverse_table[:, 0]
    d2 = np.diff(s, 2)
    assert np.all(d2[:100] < 0) and np.all(d2[-100:] > 0)
    # symmetric around the midpoint: f^-1(255 - I) = 1 - f^-1(I)
    np.testing.assert_allclose(s[::-1], 1 - s, atol=1e-12)
    # larger contrast: a steeper mid-tone (more levels per unit irradiance) than a weaker curve
    steep = crf_s_curve(contrast=9.0, gamma=1.0).inverse_table[:, 0]
    assert steep[140] - steep[115] < s[140] - s[115]


def test_pcalib_crf_matches_the_real_file():
    path = shared_path("vignetting", "euroc_mt9v034_752x480", "pcalib.txt")
    first = np.array(path.read_text().splitlines()[0].split(), dtype=float)
    values = (first - first[0]) / (first[-1] - first[0])
    resp = crf_from_pcalib(path)
    for c in range(3):
        np.testing.assert_allclose(resp.inverse_table[:, c], values, rtol=1e-12)
    spec = crf_spec_from_file(path)
    assert spec["family"] == "table" and len(spec["table"]) == 256
    np.testing.assert_allclose(make_crf(**spec).inverse_table, resp.inverse_table)


@pytest.mark.parametrize("content", ["1 2 3\n", "0 1 x 3\n", " ".join(str(255 - i) for i in range(256)) + "\n", ""])
def test_malformed_pcalib_is_rejected(tmp_path, content):
    path = tmp_path / "pcalib.txt"
    path.write_text(content)
    with pytest.raises(CalibrationFileError, match="pcalib.txt"):
        crf_from_pcalib(path)


def test_crf_argument_errors():
    with pytest.raises(ValueError, match="must be one of linear, gamma, s_curve, table, pcalib, got 'sigmoid'"):
        make_crf("sigmoid")
    with pytest.raises(ValueError, match="crf family must be one of linear, gamma, s_curve, table, pcalib"):
        CameraSpec(crf={"family": "sigmoid"})
    with pytest.raises(ValueError, match="crf family 'linear' takes no parameters"):
        make_crf("linear", gamma=2.0)
    with pytest.raises(ValueError, match=r"crf family 'table' needs \['table'\]"):
        make_crf("table")
    with pytest.raises(ValueError, match="does not take"):
        make_crf("gamma", contrast=2)
    with pytest.raises(ValueError, match="gamma must be finite and > 0"):
        crf_gamma(-1.0)
    with pytest.raises(ValueError, match="gamma must be finite"):
        crf_gamma(np.nan)
    with pytest.raises(ValueError, match="one per channel"):
        crf_gamma([1.0, 2.0])
    with pytest.raises(ValueError, match="midpoint must be in"):
        crf_s_curve(midpoint=1.2)


# ------------------------------------------------------------------------------------ vignetting
def test_polynomial_vignetting_corner_ratio_is_as_configured():
    for corner in (0.5, 0.7, 0.9):
        V = VignettingSpec.polynomial(corner).render(640, 480)
        assert V.dtype == np.float32 and V.shape == (480, 640, 3)
        r = np.hypot(319.5, 239.5) / 400.0       # the corner pixel centre, radius normalised by the half-diagonal
        b1, b2, b3 = polynomial_for_corner(corner)
        expected = 1 + b1 * r**2 + b2 * r**4 + b3 * r**6
        for y, x in ((0, 0), (0, 639), (479, 0), (479, 639)):
            np.testing.assert_allclose(V[y, x], expected, rtol=5e-6)      # float32
        assert abs(expected - corner) < 0.005
        np.testing.assert_allclose(V.reshape(-1, 3).max(0), 1.0)
        # monotone fall-off along the diagonal
        diag = V[np.arange(240), np.arange(240) * 4 // 3, 1]
        assert np.all(np.diff(diag[::-1]) <= 1e-7)


def test_xtion_preset_is_strong_with_a_shifted_blue_centre():
    spec = vignetting_preset("xtion")
    V = spec.render(640, 480)
    corners = V[[0, 0, -1, -1], [0, -1, 0, -1]]
    assert np.all(corners > 0.38) and np.all(corners < 0.62), corners
    assert abs(float(corners[:, 1].mean()) - 0.5) < 0.05
    # without the non-radial field, each channel peaks at its configured centre
    radial = VignettingSpec("polynomial", spec.coeffs, spec.centres).render(640, 480)
    for c, (cx, cy) in enumerate(spec.centres):
        y, x = np.unravel_index(np.argmax(radial[:, :, c]), (480, 640))
        assert abs(x - (cx * 640 - 0.5)) <= 0.5 and abs(y - (cy * 480 - 0.5)) <= 0.5
    blue_shift = np.subtract(spec.centres[2], spec.centres[1]) * [640, 480]
    assert np.hypot(*blue_shift) > 6.0      # "several pixels", as the paper saw


def test_non_radial_component_cannot_be_fitted_by_a_polynomial():
    spec = vignetting_preset("xtion")
    radial_only = VignettingSpec("polynomial", spec.coeffs, spec.centres)

    def residual(V: np.ndarray) -> float:
        # best even polynomial about the (known) centre of the green channel, by linear least squares
        cx, cy = spec.centres[1][0] * 320 - 0.5, spec.centres[1][1] * 240 - 0.5
        yy, xx = np.mgrid[0:240, 0:320]
        r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / (0.5 * np.hypot(320, 240)) ** 2
        A = np.stack([np.ones_like(r2), r2, r2**2, r2**3], axis=-1).reshape(-1, 4)
        coef, *_ = np.linalg.lstsq(A, V[:, :, 1].reshape(-1).astype(np.float64), rcond=None)
        return float(np.sqrt(np.mean((A @ coef - V[:, :, 1].reshape(-1)) ** 2)))

    assert residual(radial_only.render(320, 240)) < 1e-6
    assert residual(spec.render(320, 240)) > 0.004
    field = nonradial_field(320, 240, spec.nonradial)
    assert 0.02 < field.max() - field.min() < 0.12      # a few percent


def test_dso_vignette_png_is_resampled_without_stretching():
    import cv2

    path = shared_path("vignetting", "euroc_mt9v034_752x480", "vignette.png")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.float64)
    native = VignettingSpec.dso(path).render(752, 480)
    np.testing.assert_allclose(native[:, :, 0], raw / raw.max(), rtol=1e-6)
    np.testing.assert_array_equal(native[:, :, 0], native[:, :, 2])
    small = VignettingSpec.dso(path).render(320, 240)        # 4:3 from 752x480: centre crop of 640 columns
    crop = raw[:, 56:696]
    expected = cv2.resize(crop, (320, 240), interpolation=cv2.INTER_AREA)
    np.testing.assert_allclose(small[:, :, 1], expected / expected.max(), atol=1e-5)


def test_lensfun_entries_and_their_fall_off():
    db = shared_path("lensfun", "db")
    entry = find_lensfun_vignetting("EF-S 10-22", focal=10, aperture=4, db=db)
    assert (entry.k1, entry.k2, entry.k3) == (-0.6724, 0.0578, 0.0247)
    assert entry.focal == 10 and entry.aperture == 4
    V = VignettingSpec.lensfun(entry).render(400, 300)
    r = np.hypot(199.5, 149.5) / 250.0
    expected = 1 + entry.k1 * r**2 + entry.k2 * r**4 + entry.k3 * r**6
    np.testing.assert_allclose(V[0, 0], expected, rtol=1e-5)
    widest = find_lensfun_vignetting("EF-S 10-22", db=db)   # no focal/aperture: shortest focal, widest aperture
    assert widest.focal == 10 and widest.aperture == 3.5
    with pytest.raises(ValueError, match="no lensfun lens .* matches"):
        find_lensfun_vignetting("no such lens 123", db=db)
    with pytest.raises(CalibrationFileError, match="no such lensfun database"):
        find_lensfun_vignetting("EF", db=db / "missing")


def test_vignetting_argument_errors():
    with pytest.raises(ValueError, match="kind must be one of"):
        VignettingSpec("radial")
    with pytest.raises(ValueError, match="corner must be within"):
        polynomial_for_corner(0.0)
    with pytest.raises(ValueError, match=r"V = .* <= 0.01"):
        VignettingSpec("polynomial", ((-1.5, 0.0, 0.0),)).render(64, 48)
    with pytest.raises(ValueError, match="needs path"):
        VignettingSpec("dso")
    with pytest.raises(ValueError, match="valid names: xtion, asymmetric, mild, none"):
        vignetting_preset("strongest")
    with pytest.raises(ValueError, match="centres must have shape"):
        polynomial_vignetting(8, 8, [[0, 0, 0]] * 3, [[0.5, 0.5]])


# --------------------------------------------------------------------------- image formation
@pytest.fixture(scope="module")
def camera() -> SimulatedCamera:
    return SimulatedCamera(CameraSpec.preset("xtion", width=W, height=H))


def test_float_path_round_trips_to_float_precision(camera):
    """inverse CRF and V applied to the pre-quantisation intensity recover k * g * L (noise off)."""
    assert_float_round_trip(camera, smooth_field(1, lo=0.5, hi=60.0), 0.012)


def assert_float_round_trip(camera, L, k):
    """Capture radiance ``L`` at exposure ``k`` (gains 0.85 / 1 / 1.3, noise off): f^-1 and V recover
    ``k g L`` wherever the sensor is not saturated (at least 90 % of the pixels)."""
    g = np.array([0.85, 1.0, 1.3])
    cap = camera.capture(L, exposure_time=k, gains=g, noise=False, jpeg=False)
    truth = k * g * L
    unsaturated = cap.irradiance < 0.999
    assert unsaturated.mean() > 0.9
    recovered = camera.response.inverse(cap.intensity) / camera.vignetting
    assert recovered.dtype == np.float32
    np.testing.assert_allclose(recovered[unsaturated], truth[unsaturated], rtol=2e-6, atol=1e-9)
    np.testing.assert_allclose(cap.irradiance, truth * camera.vignetting, rtol=1e-6)


def test_float_path_round_trips_a_rendered_room_frame(camera):
    """The same round trip on the radiance of a real rendered room frame (sharp texture edges, dark
    skirting boards and bright walls, light fall-off) instead of a smooth synthetic field."""
    from mapping.simulation import Renderer, make_room, room_trajectory
    from radiometry.simulation import default_intrinsics

    room = make_room(3, texel=0.01)
    pose = room_trajectory(room, 100, seed=5)[40]
    r = Renderer(room, default_intrinsics(W, H), W, H).render(pose)
    L = r.radiance
    assert r.valid.all() and L.dtype == np.float32 and L.min() > 0
    assert np.percentile(L, 99) / np.percentile(L, 1) > 10          # a real, contrasty frame
    assert_float_round_trip(camera, L, 0.6 / float(np.percentile(L, 99)))


def test_uint8_path_round_trips_within_half_a_level(camera):
    """With 8-bit rounding, |f^-1(I) - E| is at most half of the larger table step next to level I."""
    L = smooth_field(2, lo=0.5, hi=60.0)
    k = 0.01
    cap = camera.capture(L, exposure_time=k, noise=False, jpeg=False)
    img = cap.image
    assert img.dtype == np.uint8
    table = camera.response.inverse_table
    inner = (img > 0) & (img < 255)
    E_hat = camera.response.inverse(img).astype(np.float64)
    c = np.broadcast_to(np.arange(3), img.shape)
    lo = table[np.maximum(img.astype(int) - 1, 0), c]
    hi = table[np.minimum(img.astype(int) + 1, 255), c]
    mid = table[img, c]
    bound = 0.5 * np.maximum(mid - lo, hi - mid) + 1e-6
    err = np.abs(E_hat - cap.irradiance)
    assert np.all(err[inner] <= bound[inner])
    # and in k * L units after dividing by V, relative to the signal: well under 2 % in the mid-tones
    rel = err / cap.irradiance
    mid_tones = inner & (img > 40) & (img < 220)
    assert np.median(rel[mid_tones]) < 0.01


def test_noise_is_signal_dependent_like_shot_plus_read_noise():
    spec = CameraSpec.preset("ideal", width=200, height=200, full_well=5000.0, read_noise=0.002)
    cam = SimulatedCamera(spec)
    for E in (0.02, 0.2, 0.6):
        cap = cam.capture(np.full((200, 200, 3), E / 0.01, np.float32), exposure_time=0.01,
                          rng=np.random.default_rng(3))
        d = (cap.signal - cap.irradiance).astype(np.float64)
        expected = np.sqrt(E / 5000 + 0.002**2)
        assert abs(d.std() / expected - 1) < 0.03
        assert abs(d.mean()) < 4 * expected / np.sqrt(d.size)


def test_capture_is_deterministic_for_a_seed(camera):
    L = smooth_field(4)
    a = camera.capture(L, exposure_time=0.01, rng=np.random.default_rng(11)).image
    b = camera.capture(L, exposure_time=0.01, rng=np.random.default_rng(11)).image
    c = camera.capture(L, exposure_time=0.01, rng=np.random.default_rng(12)).image
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()
    assert np.abs(a.astype(int) - c.astype(int)).mean() < 3      # only the noise differs


def test_jpeg_is_optional_and_close(camera):
    L = smooth_field(5)
    lossless = camera.capture(L, exposure_time=0.01, noise=False).image
    errors = {}
    for q in (50, 95):
        jpeg_cam = SimulatedCamera(camera.spec.replace(jpeg_quality=q))
        lossy = jpeg_cam.capture(L, exposure_time=0.01, noise=False).image
        assert lossy.dtype == np.uint8 and lossy.tobytes() != lossless.tobytes()
        errors[q] = np.abs(lossy.astype(int) - lossless.astype(int)).mean()
        assert abs(luma(lossy) - luma(lossless)) < 1.0          # compression keeps the brightness
    assert errors[95] < errors[50] < 12
    np.testing.assert_array_equal(jpeg_cam.capture(L, exposure_time=0.01, noise=False, jpeg=False).image, lossless)
    with pytest.raises(ValueError, match="quality must be"):
        jpeg_roundtrip(lossless, 0)


def test_capture_argument_errors(camera):
    L = smooth_field(6)
    with pytest.raises(ValueError, match=r"shape \(120, 160, 3\)"):
        camera.capture(L[:10], exposure_time=0.01, noise=False)
    with pytest.raises(TypeError, match="float"):
        camera.capture(L.astype(np.uint8), exposure_time=0.01, noise=False)
    for bad in (np.nan, -1.0, np.inf):
        L2 = L.copy()
        L2[0, 0, 0] = bad
        with pytest.raises(ValueError, match="finite and >= 0"):
            camera.capture(L2, exposure_time=0.01, noise=False)
    with pytest.raises(ValueError, match="needs rng"):
        camera.capture(L, exposure_time=0.01)
    with pytest.raises(ValueError, match="exposure_time must be a positive"):
        camera.capture(L, exposure_time=0.0, noise=False)
    with pytest.raises(ValueError, match="gains must be"):
        camera.capture(L, exposure_time=0.01, gains=(1, -1, 1), noise=False)
    zero = camera.capture(np.zeros_like(L), exposure_time=0.01, noise=False)
    assert zero.image.max() == 0


# ------------------------------------------------------------------------------ exposure control
def test_auto_exposure_holds_the_brightness_band_when_the_light_dims(camera):
    """Light halves at frame 60: brightness drops, then AE (lag, limited step) brings it back to the
    band within 20 frames and the exposure ends about twice as long."""
    L = smooth_field(7, lo=3.0, hi=45.0)
    ae = AutoExposure(target=0.45, smoothing=0.3, max_step_ev=0.4, deadband_ev=0.08)
    ctrl = camera.controller(auto_exposure=ae, auto_white_balance=False, exposure_time=0.002)
    target, band = 0.45 * 255, 12.0
    means, ks = [], []
    for i in range(120):
        light = 1.0 if i < 60 else 0.5
        k, g = ctrl.settings()
        cap = camera.capture(L * light, exposure_time=k, gains=g, rng=np.random.default_rng(i))
        ctrl.observe(cap.image)
        means.append(luma(cap.image))
        ks.append(k)
    means, ks = np.array(means), np.array(ks)
    assert means[0] < target - band                       # starts badly exposed
    assert np.all(np.abs(means[35:60] - target) < band)    # converged
    assert means[60] < target - band and means[61] < target - band   # the dimming shows, with a lag
    back = 60 + int(np.argmax(np.abs(means[60:] - target) < band))
    assert back <= 80
    assert np.all(np.abs(means[back:] - target) < band)
    assert ks[60] == ks[59]                               # exposure reacts one frame later
    assert abs(ks[-1] / ks[59] - 2.0) < 0.2
    steps = np.abs(np.diff(np.log2(ks)))
    assert steps.max() <= 0.4 + 1e-9                      # limited step per frame


def test_auto_exposure_is_clamped_and_latency_delays_it(camera):
    L = smooth_field(8, lo=0.01, hi=0.05)                  # far too dark
    ae = AutoExposure(max_time=1 / 30)
    ctrl = camera.controller(auto_exposure=ae, auto_white_balance=False, exposure_time=0.01)
    for i in range(60):
        ctrl.observe(camera.capture(L, exposure_time=ctrl.exposure_time, noise=False).image)
    assert ctrl.exposure_time == pytest.approx(1 / 30)
    slow = camera.controller(auto_exposure=AutoExposure(latency=3), exposure_time=0.01, auto_white_balance=False)
    seen = []
    for i in range(5):
        seen.append(slow.exposure_time)
        slow.observe(camera.capture(L, exposure_time=slow.exposure_time, noise=False).image)
    assert seen[0] == seen[1] == seen[2] == 0.01 and seen[3] > 0.01


def test_auto_white_balance_drifts_to_grey_world(camera):
    L = smooth_field(9, lo=5, hi=40) * np.array([1.4, 1.0, 0.65], np.float32)   # a warm light
    awb = AutoWhiteBalance(smoothing=0.15, max_step=0.05)
    ctrl = camera.controller(auto_exposure=False, auto_white_balance=awb, exposure_time=0.01)
    gains = []
    for i in range(150):
        k, g = ctrl.settings()
        gains.append(g)
        cap = camera.capture(L, exposure_time=k, gains=g, noise=False)
        ctrl.observe(cap.image)
    gains = np.array(gains)
    assert np.all(np.abs(np.diff(np.log(gains), axis=0)) <= 0.05 + 1e-12)   # lag: limited step
    assert gains[0].tolist() == [1.0, 1.0, 1.0] and np.all(gains[:, 1] == 1.0)
    irr = camera.response.inverse(cap.image)
    ok = np.all((cap.image > 8) & (cap.image < 247), axis=2)
    means = irr[ok].mean(0)
    np.testing.assert_allclose(means / means[1], 1.0, atol=0.02)
    assert gains[-1, 0] < 0.8 and gains[-1, 2] > 1.3


def test_exposure_parameter_errors():
    with pytest.raises(ValueError, match="target must be"):
        AutoExposure(target=1.5)
    with pytest.raises(ValueError, match="min_time < max_time"):
        AutoExposure(min_time=0.1, max_time=0.01)
    with pytest.raises(ValueError, match="latency"):
        AutoExposure(latency=0)
    with pytest.raises(ValueError, match="min_gain <= 1 <= max_gain"):
        AutoWhiteBalance(min_gain=1.5)


# ------------------------------------------------------------------------------- serialisation
@pytest.mark.parametrize("preset", ["xtion", "mild", "ideal"])
def test_camera_spec_json_round_trip(tmp_path, preset):
    spec = CameraSpec.preset(preset, width=W, height=H, jpeg_quality=90)
    assert CameraSpec.from_json(spec.to_json()) == spec
    path = spec.save(tmp_path / "camera.json")
    again = CameraSpec.load(path)
    assert again == spec
    L = smooth_field(10)
    a = SimulatedCamera(spec).capture(L, exposure_time=0.01, rng=np.random.default_rng(5))
    b = SimulatedCamera(again).capture(L, exposure_time=0.01, rng=np.random.default_rng(5))
    assert a.image.tobytes() == b.image.tobytes()


def test_camera_spec_with_tabulated_and_file_parts_round_trips(tmp_path):
    pcalib = shared_path("vignetting", "euroc_mt9v034_752x480", "pcalib.txt")
    png = shared_path("vignetting", "euroc_mt9v034_752x480", "vignette.png")
    spec = CameraSpec.preset("xtion", width=W, height=H).replace(crf=crf_spec_from_file(pcalib),
                                                                 vignetting=VignettingSpec.dso(png))
    again = CameraSpec.load(spec.save(tmp_path / "camera.json"))
    cam1, cam2 = SimulatedCamera(spec), SimulatedCamera(again)
    np.testing.assert_array_equal(cam1.vignetting, cam2.vignetting)
    np.testing.assert_array_equal(cam1.response.inverse_table, cam2.response.inverse_table)


def test_bad_camera_files_are_rejected(tmp_path):
    bad = tmp_path / "camera.json"
    bad.write_text("{not json")
    with pytest.raises(CalibrationFileError, match="not a valid radiomap camera description"):
        CameraSpec.load(bad)
    data = CameraSpec.preset("ideal").to_dict()
    data["format"] = "something-else"
    bad.write_text(json.dumps(data))
    with pytest.raises(CalibrationFileError, match="format 'something-else'"):
        CameraSpec.load(bad)
    data = CameraSpec.preset("ideal").to_dict()
    data["shutter"] = 1
    bad.write_text(json.dumps(data))
    with pytest.raises(CalibrationFileError, match="unknown camera fields"):
        CameraSpec.load(bad)
    with pytest.raises(CalibrationFileError, match="no such camera description"):
        CameraSpec.load(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="jpeg_quality"):
        CameraSpec(jpeg_quality=101)
    with pytest.raises(ValueError, match="valid names: xtion, asymmetric, mild, ideal"):
        CameraSpec.preset("kinect2")


def test_truth_response_is_a_camera_response(tmp_path, camera):
    path = camera.response.save(tmp_path / "response.npz")
    loaded = CameraResponse.load(path)
    np.testing.assert_array_equal(loaded.inverse_table, camera.response.inverse_table)
    assert crf_linear().meta["family"] == "linear"
