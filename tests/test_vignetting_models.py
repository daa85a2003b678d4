"""Vignetting models: validation, evaluation at other resolutions, persistence."""

from __future__ import annotations

import numpy as np
import pytest

from radiometry.errors import CalibrationFileError, ModelMismatchError
from radiometry.fileio import save_model_file
from radiometry.vignetting import (LUTVignetting, PolynomialVignetting, VignettingModel, calibration_coordinates,
                                   half_diagonal, same_aspect_ratio)


def linear_lut(h: int = 48, w: int = 64, channels: int = 3) -> np.ndarray:
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    chans = [1.0 - 0.002 * (c + 1) * xs - 0.003 * ys for c in range(channels)]
    return np.stack(chans, axis=2).astype(np.float32)


def poly_model(channels: int = 3) -> PolynomialVignetting:
    coeffs = np.array([[-0.5, 0.1, -0.05], [-0.45, 0.05, 0.0], [-0.6, 0.12, -0.02]])[:channels]
    centres = np.array([[33.0, 22.0], [31.5, 23.5], [36.0, 26.0]])[:channels]
    return PolynomialVignetting(coeffs, centres, (64, 48))


# ---------------------------------------------------------------------------------------------- LUT
@pytest.mark.parametrize("channels", [1, 3])
def test_lut_evaluates_itself_at_calibration_resolution(channels):
    lut = linear_lut(channels=channels)
    model = LUTVignetting(lut)
    assert model.channels == channels and model.resolution == (64, 48)
    v = model.evaluate()
    assert v.dtype == np.float32 and v.shape == (48, 64, channels)
    np.testing.assert_array_equal(v, lut)
    v[0, 0, 0] = 5.0  # a copy: the model is immutable
    assert model.evaluate()[0, 0, 0] == lut[0, 0, 0]
    assert not model.lut.flags.writeable


def test_lut_2d_input_is_one_channel():
    model = LUTVignetting(linear_lut(channels=1)[:, :, 0])
    assert model.channels == 1 and model.evaluate(24, 32).shape == (24, 32, 1)


@pytest.mark.parametrize("size", [(96, 128), (24, 32), (25, 33), (240, 320)])
def test_lut_resampling_is_bilinear_with_pixel_centres_aligned(size):
    """A field linear in x and y is reproduced exactly by bilinear resampling at the mapped pixel centres
    (inside the image; outside, cv2.resize clamps to the border pixels)."""
    h, w = size
    model = LUTVignetting(linear_lut())
    v = model.evaluate(h, w)
    xs, ys = calibration_coordinates(h, w, (64, 48))
    xs, ys = np.clip(xs, 0, 63), np.clip(ys, 0, 47)
    for c in range(3):
        expected = 1.0 - 0.002 * (c + 1) * xs[None, :] - 0.003 * ys[:, None]
        np.testing.assert_allclose(v[:, :, c], expected, atol=2e-6)


def test_pixel_centre_mapping():
    xs, ys = calibration_coordinates(2, 2, (4, 4))
    np.testing.assert_allclose(xs, [0.5, 2.5])  # the centre of a 2x2 block of the 4x4 grid
    np.testing.assert_allclose(ys, [0.5, 2.5])


@pytest.mark.parametrize("size", [(36, 64), (48, 48), (100, 64)])
def test_other_aspect_ratio_is_a_clear_error(size):
    model = LUTVignetting(linear_lut())
    h, w = size
    with pytest.raises(ModelMismatchError, match=rf"calibrated at 64x48.*images are {w}x{h}.*calibrate vignetting"):
        model.evaluate(h, w)


def test_same_aspect_ratio_tolerates_one_pixel():
    assert same_aspect_ratio((640, 480), (321, 241))
    assert same_aspect_ratio((752, 480), (376, 240))
    assert not same_aspect_ratio((640, 480), (640, 360))
    assert not same_aspect_ratio((640, 480), (640, 478))


@pytest.mark.parametrize("bad, error, message", [
    (np.full((4, 4, 3), np.nan, np.float32), ValueError, "NaN or infinite"),
    (np.full((4, 4, 3), np.inf, np.float32), ValueError, "NaN or infinite"),
    (np.zeros((4, 4, 3), np.float32), ValueError, "strictly positive"),
    (-np.ones((4, 4, 3), np.float32), ValueError, "strictly positive"),
    (np.ones((4, 4, 4), np.float32), ValueError, r"shape \(H, W\)"),
    (np.ones(16, np.float32), ValueError, r"shape \(H, W\)"),
    (np.ones((0, 4, 3), np.float32), ValueError, r"shape \(H, W\)"),
    (np.full((4, 4, 3), "a"), TypeError, "real numeric"),
    (np.full((4, 4, 3), 5000.0, np.float32), ValueError, "not plausible"),
])
def test_lut_validation(bad, error, message):
    with pytest.raises(error, match=message):
        LUTVignetting(bad)


def test_evaluate_arguments():
    model = LUTVignetting(linear_lut())
    with pytest.raises(ValueError, match="both height and width"):
        model.evaluate(48)
    with pytest.raises(ValueError, match="positive"):
        model.evaluate(0, 0)
    with pytest.raises(TypeError, match="integers"):
        model.evaluate(24.0, 32.0)


# ------------------------------------------------------------------------------------------ polynomial
def test_polynomial_matches_its_formula():
    model = poly_model()
    v = model.evaluate()
    ys, xs = np.mgrid[0:48, 0:64].astype(np.float64)
    radius = half_diagonal((64, 48))
    assert radius == pytest.approx(40.0)
    for c in range(3):
        b1, b2, b3 = model.coefficients[c]
        cx, cy = model.centres[c]
        r2 = ((xs - cx) ** 2 + (ys - cy) ** 2) / radius ** 2
        np.testing.assert_allclose(v[:, :, c], 1 + b1 * r2 + b2 * r2 ** 2 + b3 * r2 ** 3, rtol=1e-6)
        assert v[int(cy), int(cx), c] == pytest.approx(1.0, abs=1e-3)


def test_polynomial_is_resolution_independent():
    """At twice the resolution, V at a pixel equals V at its pixel centre in calibration coordinates,
    so the centres scale with the image and r stays normalised."""
    model = poly_model()
    big = model.evaluate(96, 128)
    xs, ys = calibration_coordinates(96, 128, (64, 48))
    radius = half_diagonal((64, 48))
    for c in range(3):
        b1, b2, b3 = model.coefficients[c]
        cx, cy = model.centres[c]
        r2 = ((xs[None, :] - cx) ** 2 + (ys[:, None] - cy) ** 2) / radius ** 2
        np.testing.assert_allclose(big[:, :, c], 1 + b1 * r2 + b2 * r2 ** 2 + b3 * r2 ** 3, rtol=1e-6)
    # the corner values agree between resolutions to within the pixel-size difference
    assert abs(float(big[0, 0, 1]) - float(model.evaluate()[0, 0, 1])) < 0.01


def test_polynomial_scale_and_profile():
    model = PolynomialVignetting([[-0.4, 0.0, 0.0]], [[31.5, 23.5]], (64, 48), scale=[0.8])
    assert model.radial_profile(np.array([0.0, 1.0]))[0] == pytest.approx(0.8)
    assert model.radial_profile(np.array([1.0]))[0] == pytest.approx(0.8 * 0.6)
    assert model.normalised().scale[0] == 1.0
    with pytest.raises(ValueError, match="channel must be"):
        model.radial_profile(np.array([0.5]), channel=2)


@pytest.mark.parametrize("kwargs, message", [
    ({"coefficients": [[np.nan, 0, 0]] * 3}, "coefficients contains NaN"),
    ({"centres": [[np.inf, 1]] * 3}, "centres contains NaN"),
    ({"centres": [[31.5, 23.5]] * 2}, r"centres must have shape \(3, 2\)"),
    ({"coefficients": [[-0.5, 0]] * 3}, r"coefficients must have shape \(C, 3\)"),
    ({"centres": [[200.0, 20.0]] * 3}, "outside the 64x48 image"),
    ({"coefficients": [[-1.5, 0, 0]] * 3}, "<= 0 inside the image"),
    ({"scale": [1.0, 0.0, 1.0]}, "scale must be positive"),
    ({"scale": [1.0, 1.0]}, r"scale must have shape \(3,\)"),
    ({"resolution": (0, 48)}, "resolution must be positive"),
    ({"resolution": "big"}, "resolution must be"),
    ({"coefficients": [[1e12, 0, 0]] * 3}, "not plausible"),
])
def test_polynomial_validation(kwargs, message):
    args = {"coefficients": [[-0.5, 0.1, 0.0]] * 3, "centres": [[31.5, 23.5]] * 3, "resolution": (64, 48)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        PolynomialVignetting(args["coefficients"], args["centres"], args["resolution"], args.get("scale"))


def test_polynomial_aspect_mismatch():
    with pytest.raises(ModelMismatchError, match="64x48.*64x64"):
        poly_model().evaluate(64, 64)


# ------------------------------------------------------------------------------------------ persistence
@pytest.mark.parametrize("channels", [1, 3])
def test_round_trip_lut(tmp_path, channels):
    model = LUTVignetting(linear_lut(channels=channels), info={"method": "lut", "frames_used": 12})
    path = model.save(tmp_path / "v.npz")
    back = VignettingModel.load(path)
    assert isinstance(back, LUTVignetting)
    np.testing.assert_array_equal(back.lut, model.lut)
    assert back.info == {"method": "lut", "frames_used": 12}
    assert isinstance(LUTVignetting.load(path), LUTVignetting)


@pytest.mark.parametrize("channels", [1, 3])
def test_round_trip_polynomial(tmp_path, channels):
    model = poly_model(channels)
    back = VignettingModel.load(model.save(tmp_path / "p.npz"))
    assert isinstance(back, PolynomialVignetting)
    np.testing.assert_array_equal(back.coefficients, model.coefficients)
    np.testing.assert_array_equal(back.centres, model.centres)
    assert back.resolution == (64, 48)
    np.testing.assert_array_equal(back.evaluate(24, 32), model.evaluate(24, 32))


def test_load_rejects_the_wrong_subclass(tmp_path):
    path = poly_model().save(tmp_path / "p.npz")
    with pytest.raises(CalibrationFileError, match="holds a 'polynomial' vignetting model, not a 'lut'"):
        LUTVignetting.load(path)


@pytest.mark.parametrize("arrays, meta, message", [
    ({"lut": np.full((4, 4, 3), np.nan, np.float32)}, {"model": "lut", "resolution": [4, 4]}, "NaN"),
    ({"lut": -np.ones((4, 4, 3), np.float32)}, {"model": "lut", "resolution": [4, 4]}, "strictly positive"),
    ({"lut": np.ones((4, 4, 3), np.float32)}, {"model": "lut", "resolution": [8, 4]}, "disagrees with the resolution"),
    ({"other": np.ones(3)}, {"model": "lut", "resolution": [4, 4]}, "no 'lut' entry"),
    ({"lut": np.ones((4, 4, 3), np.float32)}, {"model": "spline", "resolution": [4, 4]}, "unknown vignetting model"),
    ({"lut": np.ones((4, 4, 3), np.float32)}, {"model": "lut"}, "resolution must be"),
    ({"coefficients": np.ones((3, 2)), "centres": np.ones((3, 2))}, {"model": "polynomial", "resolution": [4, 4]},
     "coefficients must have shape"),
    ({"coefficients": np.full((3, 3), -2.0), "centres": np.ones((3, 2))},
     {"model": "polynomial", "resolution": [4, 4]}, "<= 0 inside the image"),
])
def test_load_rejects_bad_content(tmp_path, arrays, meta, message):
    path = save_model_file(tmp_path / "bad.npz", "vignetting", arrays, meta)
    with pytest.raises(CalibrationFileError, match=rf"bad\.npz.*{message}"):
        VignettingModel.load(path)


def test_load_rejects_other_files(tmp_path):
    response = save_model_file(tmp_path / "crf.npz", "response", {"inverse_table": np.ones((256, 1))})
    with pytest.raises(CalibrationFileError, match="'response' model where a 'vignetting' model is needed"):
        VignettingModel.load(response)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(CalibrationFileError, match="junk.npz: not a radiomap vignetting file"):
        VignettingModel.load(tmp_path / "junk.npz")
    with pytest.raises(CalibrationFileError, match="no such file"):
        VignettingModel.load(tmp_path / "missing.npz")


def test_to_lut():
    model = poly_model()
    lut = model.to_lut()
    np.testing.assert_array_equal(lut.evaluate(), model.evaluate())
    assert lut.info["converted_from"] == "polynomial"


# ------------------------------------------------------------------------------------------ fuzz
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 100_000), st.integers(0, 255)), min_size=1, max_size=6),
       cut=st.integers(0, 3000), which=st.booleans())
def test_load_fuzz_mutated_model_files(tmp_path, flips, cut, which):
    """Mutated radiomap model files either load as a valid model or raise CalibrationFileError."""
    model = LUTVignetting(linear_lut(6, 8)) if which else poly_model()
    data = bytearray(model.save(tmp_path / "orig.npz").read_bytes())
    for pos, value in flips:
        data[pos % len(data)] = value
    path = tmp_path / "fz.npz"
    path.write_bytes(bytes(data[: len(data) - cut % len(data)]))
    try:
        back = VignettingModel.load(path)
    except CalibrationFileError as exc:
        assert "fz.npz" in str(exc)
    else:
        v = back.evaluate()
        assert np.all(np.isfinite(v)) and np.all(v > 0)
