"""Correction I' = f(scale f^-1(I) / V) (uint8 fast path and exact float), irradiance, exposure ratio."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import shared_path
from radiometry.correction import Corrector, correct_reference_numpy
from radiometry.errors import ModelMismatchError
from radiometry.exposure import exposure_ratio
from radiometry.formats.dso_vignette import read_dso_vignette
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting, PolynomialVignetting

H, W = 60, 80


def s_curve(channels: int = 3) -> CameraResponse:
    x = np.linspace(0, 1, 256)
    cols = [x ** g * (1 + 0.2 * np.sin(np.pi * x)) for g in (2.0, 2.2, 1.8)[:channels]]
    return CameraResponse.from_table(np.stack(cols, axis=1) + 1e-4 * x[:, None])


def vignetting(channels: int = 3) -> PolynomialVignetting:
    coeffs = [[-0.55, 0.1, -0.05], [-0.5, 0.08, -0.02], [-0.65, 0.12, -0.03]][:channels]
    centres = [[40.0, 29.0], [39.5, 29.5], [43.0, 31.0]][:channels]
    return PolynomialVignetting(coeffs, centres, (W, H))


def image(shape, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, shape, dtype=np.uint8)


def exact(img: np.ndarray, response: CameraResponse, v: np.ndarray, scale: float = 1.0) -> np.ndarray:
    """Reference in float64: f(scale * f^-1(I) / V), unrounded."""
    arr = img if img.ndim == 3 else img[:, :, None]
    tables = response.channel_tables(arr.shape[2]).astype(np.float64)
    out = np.empty(arr.shape)
    for c in range(arr.shape[2]):
        e = tables[:, c][arr[:, :, c]] * scale / v[:, :, min(c, v.shape[2] - 1)].astype(np.float64)
        out[:, :, c] = np.interp(e, tables[:, c], np.arange(256.0))
    return out if img.ndim == 3 else out[:, :, 0]


CASES = [  # image shape, response channels, vignetting channels
    ((H, W, 3), 3, 3),
    ((H, W, 3), 1, 3),
    ((H, W, 3), 3, 1),
    ((H, W, 3), 1, 1),
    ((H, W), 1, 1),
    ((H, W, 1), 1, 1),
]


@pytest.mark.parametrize("shape, rc, vc", CASES)
@pytest.mark.parametrize("scale", [1.0, 0.7])
def test_uint8_fast_path_matches_exact_formula(shape, rc, vc, scale):
    response, model = s_curve(rc), vignetting(vc)
    img = image(shape)
    out = Corrector(response, model).correct(img, scale=scale)
    assert out.dtype == np.uint8 and out.shape == img.shape
    ref = exact(img, response, model.evaluate(H, W), scale)
    # unrounded: within half a level plus the gain quantisation's share (a few hundredths of a level)
    assert np.abs(out - ref).max() <= 0.55
    rounded = np.clip(np.rint(ref), 0, 255)
    diff = np.abs(out.astype(np.int64) - rounded.astype(np.int64))
    assert diff.max() <= 1  # the stated bound: at most 1 level from the exactly rounded formula
    assert np.mean(diff > 0) < 0.02  # and only for values within a hair of a .5 boundary


@pytest.mark.parametrize("shape, rc, vc", CASES)
def test_irradiance_is_exact(shape, rc, vc):
    response, model = s_curve(rc), vignetting(vc)
    img = image(shape, seed=1)
    irr = Corrector(response, model).irradiance(img)
    assert irr.dtype == np.float32 and irr.shape == img.shape
    arr = img if img.ndim == 3 else img[:, :, None]
    v = model.evaluate(H, W).astype(np.float64)
    tables = response.channel_tables(arr.shape[2]).astype(np.float64)
    ref = np.stack([tables[:, c][arr[:, :, c]] / v[:, :, min(c, vc - 1)] for c in range(arr.shape[2])], axis=2)
    np.testing.assert_allclose(irr.reshape(ref.shape), ref, rtol=2e-7, atol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.uint16])
def test_float_and_uint16_inputs_use_the_exact_formula(dtype):
    response, model = s_curve(), vignetting()
    img8 = image((H, W, 3), seed=2)
    img = img8.astype(dtype) * (257 if dtype == np.uint16 else 1)
    cor = Corrector(response, model)
    out = cor.correct(img, scale=0.8)
    assert out.dtype == np.float32
    np.testing.assert_allclose(out, exact(img8, response, model.evaluate(H, W), 0.8), atol=2e-3)
    np.testing.assert_allclose(cor.irradiance(img), cor.irradiance(img8), rtol=1e-5, atol=1e-7)


def test_no_vignetting_and_scale_one_is_the_identity():
    img = image((H, W, 3), seed=3)
    np.testing.assert_array_equal(Corrector(s_curve()).correct(img), img)


def test_flat_field_becomes_flat():
    """An image of a uniform white wall through the camera comes out uniform."""
    response, model = s_curve(), vignetting()
    level = 180
    e = response.inverse_table[level] * model.evaluate(H, W)
    observed = response.forward(e, dtype=np.uint8)
    out = Corrector(response, model).correct(observed)
    assert np.all(np.abs(out.astype(int) - level) <= 2)  # the input's own rounding, amplified in the corners
    assert np.abs(out.astype(float) - level).mean() < 0.6


def test_other_resolution_and_cache():
    cor = Corrector(s_curve(), vignetting())
    small = image((H // 2, W // 2, 3))
    out = cor.correct(small)
    ref = exact(small, cor.response, vignetting().evaluate(H // 2, W // 2))
    assert np.abs(out - ref).max() <= 0.55
    assert cor.gain_map(H // 2, W // 2) is cor.gain_map(H // 2, W // 2)
    with pytest.raises(ModelMismatchError, match="80x60.*images are 80x80"):
        cor.correct(image((80, 80, 3)))


def test_channel_mismatches_are_clear():
    with pytest.raises(ModelMismatchError, match="vignetting model has 3 channels but the image has 1"):
        Corrector(s_curve(1), vignetting(3)).correct(image((H, W)))
    with pytest.raises(ModelMismatchError, match="response has 3 channels but the image has 1"):
        Corrector(s_curve(3), vignetting(1)).irradiance(image((H, W)))
    with pytest.raises(ValueError, match=r"image must have shape \(H, W\)"):
        Corrector(s_curve()).correct(image((H, W, 4)))
    with pytest.raises(TypeError, match="uint8, uint16 or float"):
        Corrector(s_curve()).correct(np.zeros((H, W, 3), dtype=bool))


@pytest.mark.parametrize("scale, error", [(0.0, ValueError), (-1.0, ValueError), (np.nan, ValueError),
                                          (np.inf, ValueError), ("a", TypeError)])
def test_bad_scale(scale, error):
    with pytest.raises(error, match="scale must be"):
        Corrector(s_curve(), vignetting()).correct(image((H, W, 3)), scale=scale)


def test_constructor_arguments():
    with pytest.raises(TypeError, match="response must be a CameraResponse"):
        Corrector(np.ones((256, 3)))
    with pytest.raises(TypeError, match="vignetting must be a VignettingModel"):
        Corrector(s_curve(), np.ones((H, W, 3)))
    with pytest.raises(ValueError, match="gain_levels must be"):
        Corrector(s_curve(), gain_levels=1)


def test_suggest_scale():
    response, model = s_curve(), vignetting()
    cor = Corrector(response, model)
    worst = cor.suggest_scale(percentile=100.0)
    assert worst == pytest.approx(float(model.evaluate().min()), rel=1e-6)
    # a bright scene: what is bright in the corners would exceed saturation once V is divided out
    scene = image((H, W, 3), seed=4)
    s = cor.suggest_scale(scene, percentile=99.0)
    corrected = cor.irradiance(scene) * s  # what correct(..., scale=s) maps through f; > 1 clips at 255
    assert np.mean(corrected > 1.0) <= 0.01
    assert np.mean(cor.irradiance(scene) > 1.0) > 0.1  # without the scale 10% of the values would clip
    assert np.mean(cor.correct(scene, scale=s) == 255) < np.mean(cor.correct(scene) == 255) / 5
    white = np.full((H, W, 3), 250, np.uint8)
    assert cor.suggest_scale([white, white]) == pytest.approx(cor.suggest_scale(white))
    with pytest.raises(ValueError, match="percentile must be"):
        cor.suggest_scale(percentile=0)


def test_real_dso_vignette_corrects_a_flat_field():
    model = read_dso_vignette(shared_path("vignetting", "euroc_mt9v034_752x480", "vignette.png"))
    response = CameraResponse.gamma(2.2, channels=1)
    v = model.evaluate(240, 376)  # half resolution
    flat = response.forward(response.inverse_table[200, 0] * v, dtype=np.uint8)
    out = Corrector(response, model).correct(flat)
    assert out.shape == flat.shape
    assert np.abs(out.astype(int) - 200).max() <= 1
    assert np.ptp(flat) > 15  # it was not flat before


def test_reference_numpy_implementation_agrees():
    response, model = s_curve(), vignetting()
    img = image((H, W, 3), seed=5)
    ref = correct_reference_numpy(img, response, model.evaluate(H, W), scale=0.9)
    fast = Corrector(response, model).correct(img, scale=0.9)
    assert np.abs(ref.astype(int) - fast.astype(int)).max() <= 1


# ---------------------------------------------------------------------------------------------- exposure
def _observations(n: int = 2000, ratio=(1.6, 1.5, 1.4), seed: int = 0, noise: float = 0.0):
    """Point i seen near the corners in observation 1 (V 0.45..0.7) and near the centre in 2 (V 0.85..1),
    with ``noise`` relative irradiance noise in both."""
    rng = np.random.default_rng(seed)
    response = s_curve()
    radiance = rng.uniform(0.02, 0.5, (n, 3))
    v1, v2 = rng.uniform(0.45, 0.7, (n, 3)), rng.uniform(0.85, 1.0, (n, 3))
    noise1 = 1 + noise * rng.standard_normal((n, 3))
    noise2 = 1 + noise * rng.standard_normal((n, 3))
    i1 = response.forward(np.asarray(ratio) * v1 * radiance * noise1)
    i2 = response.forward(1.0 * v2 * radiance * noise2)
    return response, i1, i2, v1, v2


def test_exposure_ratio_recovers_the_ratio_per_channel():
    response, i1, i2, v1, v2 = _observations()
    ratio, n = exposure_ratio(i1, i2, v1, v2, response)
    np.testing.assert_allclose(ratio, [1.6, 1.5, 1.4], rtol=1e-4)
    assert n.dtype == np.int64 and np.all(n > 1000)
    # uint8 observations: quantisation only
    ratio8, _ = exposure_ratio(np.rint(i1).astype(np.uint8), np.rint(i2).astype(np.uint8), v1, v2, response)
    np.testing.assert_allclose(ratio8, [1.6, 1.5, 1.4], rtol=0.01)
    # ignoring vignetting biases it: that is what V is for
    biased, _ = exposure_ratio(i1, i2, None, None, response)
    assert np.all(np.abs(biased / [1.6, 1.5, 1.4] - 1) > 0.2)


def test_exposure_ratio_excludes_saturated_and_dark_pixels():
    response, i1, i2, v1, v2 = _observations(noise=0.02)
    i1 = i1.copy()
    i1[:600] = 255.0  # clipped in observation 1: would pull the median down
    i2 = i2.copy()
    i2[600:900] = 3.0  # dark in observation 2
    ratio, n = exposure_ratio(i1, i2, v1, v2, response)
    np.testing.assert_allclose(ratio, [1.6, 1.5, 1.4], rtol=0.005)  # the noise's median over ~1100 pixels
    assert np.all(n <= 1100)
    lenient, _ = exposure_ratio(i1, i2, v1, v2, response, low=0, high=256)
    assert np.all(np.abs(lenient / [1.6, 1.5, 1.4] - 1) > 0.01)


def test_exposure_ratio_without_usable_pixels_is_nan_not_an_error():
    response, i1, i2, v1, v2 = _observations(50)
    ratio, n = exposure_ratio(np.full_like(i1, 255.0), i2, v1, v2, response)
    assert np.all(np.isnan(ratio)) and np.all(n == 0)
    ratio, n = exposure_ratio(np.empty((0, 3)), np.empty((0, 3)), None, None, response)
    assert np.all(np.isnan(ratio)) and np.all(n == 0)
    ratio, n = exposure_ratio(i1, i2, v1, v2, response, mask=np.zeros(50, bool))
    assert np.all(np.isnan(ratio)) and np.all(n == 0)
    ratio, n = exposure_ratio(i1, i2, v1, v2, response, min_count=1000)
    assert np.all(np.isnan(ratio)) and np.all(n > 0)


def test_exposure_ratio_grayscale_and_scalar_vignetting():
    response = CameraResponse.gamma(2.2, channels=1)
    radiance = np.linspace(0.05, 0.4, 100)
    i1 = response.forward(2.0 * 0.8 * radiance)
    i2 = response.forward(radiance)
    ratio, n = exposure_ratio(i1, i2, 0.8, 1.0, response)
    assert ratio.shape == (1,) and ratio[0] == pytest.approx(2.0, rel=1e-4) and n[0] > 50


@pytest.mark.parametrize("kwargs, message", [
    ({"intensity2": np.zeros((5, 3))}, "same shape"),
    ({"vignetting1": np.ones((7, 3))}, r"vignetting1 must have shape \(10,\)"),
    ({"mask": np.ones(3, bool)}, r"mask must have shape \(10,\)"),
    ({"low": 200, "high": 100}, "low < high"),
    ({"min_count": 0}, "min_count must be"),
    ({"intensity1": np.zeros((10, 3, 2)), "intensity2": np.zeros((10, 3, 2))}, r"shape \(N, C\)"),
])
def test_exposure_ratio_argument_errors(kwargs, message):
    args = {"intensity1": np.full((10, 3), 100.0), "intensity2": np.full((10, 3), 100.0), "vignetting1": None,
            "vignetting2": None}
    extra = {k: kwargs.pop(k) for k in list(kwargs) if k not in args}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message):
        exposure_ratio(args["intensity1"], args["intensity2"], args["vignetting1"], args["vignetting2"], s_curve(),
                       **extra)


def test_lut_and_polynomial_models_correct_alike():
    model = vignetting()
    lut = LUTVignetting(model.evaluate())
    img = image((H, W, 3), seed=7)
    a = Corrector(s_curve(), model).correct(img)
    b = Corrector(s_curve(), lut).correct(img)
    assert np.abs(a.astype(int) - b.astype(int)).max() <= 1


@pytest.mark.parametrize("gain_levels", [1000, 65535])
def test_fast_path_bound_holds_for_fewer_and_more_gain_levels(gain_levels):
    """Fewer levels (a coarser grid) and many more (a uint32 gain map) alike."""
    response, model = s_curve(), vignetting()
    img = image((H, W, 3), seed=8)
    out = Corrector(response, model, gain_levels=gain_levels).correct(img, scale=0.7)
    ref = exact(img, response, model.evaluate(H, W), 0.7)
    assert np.abs(out - ref).max() <= 0.55


def test_fast_path_table_stays_small_for_a_huge_dynamic_range():
    """A response with a huge dynamic range (level 1 at 1e-12) keeps the table small (the grid step grows with
    the range of exposures), and the darkest levels still come out right."""
    x = np.linspace(0, 1, 256)
    table = np.concatenate([[0.0, 1e-12, 1e-9], x[3:] ** 2.2])
    response = CameraResponse.from_table(np.repeat(table[:, None], 3, axis=1))
    model = vignetting()
    cor = Corrector(response, model)
    img = image((H, W, 3), seed=9)
    out = cor.correct(img, scale=0.9)
    q, k, lut = cor._fast_tables(H, W, 3, 0.9)
    assert lut.size < 3 * 80_000 and q.dtype == np.uint16
    ref = exact(img, response, model.evaluate(H, W), 0.9)
    assert np.abs(out - ref).max() <= 0.55
    np.testing.assert_array_equal(out[img <= 2], np.rint(ref[img <= 2]))
