"""CameraResponse: evaluation on every dtype/shape, monotonicity, persistence and its failure modes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from radiometry import CameraResponse
from radiometry.errors import CalibrationFileError, ModelMismatchError
from radiometry.fileio import save_model_file
from radiometry.response import repair_monotone, validate_inverse_table


def s_curve_table(channels: int) -> np.ndarray:
    x = np.linspace(0, 1, 256)
    t = [x ** (1.2 + 0.3 * c) for c in range(channels)]
    cols = [tc * tc * (3 - 2 * tc) + 1e-3 * x for tc in t]  # smoothstep of a power: S-shaped, increasing
    return np.stack(cols, axis=1)


@pytest.mark.parametrize("channels", [1, 3])
def test_normalised_to_one_at_255_and_increasing(channels):
    r = CameraResponse.from_table(5.0 * s_curve_table(channels))
    assert r.channels == channels
    assert r.inverse_table.shape == (256, channels)
    np.testing.assert_allclose(r.inverse_table[-1], 1.0)
    assert np.all(np.diff(r.inverse_table, axis=0) > 0)


@pytest.mark.parametrize("shape", [(7,), (4, 5), (2, 3, 3), (6, 2, 4, 3)])
def test_inverse_forward_round_trip_uint8(shape):
    r = CameraResponse.from_table(s_curve_table(3))
    rng = np.random.default_rng(0)
    channels_last = shape[-1] == 3
    resp = r if channels_last else CameraResponse.from_table(s_curve_table(1))
    img = rng.integers(0, 256, size=shape).astype(np.uint8)
    e = resp.inverse(img)
    assert e.dtype == np.float32 and e.shape == img.shape
    back = resp.forward(e)
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, img, atol=2e-3)
    np.testing.assert_array_equal(resp.forward(e, dtype=np.uint8), img)


def test_float_inverse_interpolates_between_levels():
    r = CameraResponse.from_table(s_curve_table(3))
    x = np.array([[[10.5, 100.25, 254.75]]], dtype=np.float32)
    e = r.inverse(x)
    t = r.inverse_table
    expected = [0.5 * (t[10, 0] + t[11, 0]), 0.75 * t[100, 1] + 0.25 * t[101, 1], 0.25 * t[254, 2] + 0.75 * t[255, 2]]
    np.testing.assert_allclose(e[0, 0], expected, rtol=1e-5)
    # forward is the exact inverse of the interpolated inverse, not the nearest bin
    np.testing.assert_allclose(r.forward(e), x, atol=1e-3)


def test_forward_saturates_and_clips():
    r = CameraResponse.gamma(2.2)
    e = np.array([[-1.0, 0.0, 2.0]] * 1, dtype=np.float32).reshape(1, 1, 3)
    out = r.forward(e)
    np.testing.assert_allclose(out[0, 0], [0.0, 0.0, 255.0])
    nan = r.forward(np.full((1, 3), np.nan, dtype=np.float32))
    assert np.all(np.isfinite(nan))


def test_one_channel_response_serves_rgb_but_not_vice_versa():
    gray = CameraResponse.gamma(2.0, channels=1)
    img = np.full((2, 2, 3), 128, np.uint8)
    e = gray.inverse(img)
    np.testing.assert_allclose(e, (128 / 255) ** 2.0, rtol=1e-6)
    rgb = CameraResponse.gamma(2.0, channels=3)
    with pytest.raises(ModelMismatchError, match="channel"):
        rgb.inverse(np.zeros((4, 4), np.uint8))


def test_inverse_rejects_out_of_range_integers():
    r = CameraResponse.gamma()
    with pytest.raises(ValueError, match="0..255"):
        r.inverse(np.array([[[0, 300, 5]]], dtype=np.int32))
    with pytest.raises(TypeError, match="integer or float"):
        r.inverse(np.array([["a", "b", "c"]]))


@pytest.mark.parametrize("bad, match", [
    (np.full((256, 3), np.nan), "NaN"),
    (np.r_[np.linspace(0, 1, 128), np.linspace(0.5, 1, 128)][:, None], "strictly increasing"),
    (np.linspace(0, 1, 255)[:, None], "256 values"),
    (np.linspace(-1, 1, 256)[:, None], "negative"),
    (np.ones((256, 2)), "256 values"),
])
def test_validation_rejects_bad_tables(bad, match):
    with pytest.raises(CalibrationFileError, match=match):
        validate_inverse_table(bad)


def test_repair_makes_strictly_increasing():
    wiggly = np.linspace(0, 1, 256)
    wiggly[200:210] = wiggly[200]  # flat
    wiggly[250] = 0.5  # dip
    fixed = repair_monotone(wiggly)
    assert np.all(np.diff(fixed[:, 0]) > 0)
    r = CameraResponse.from_table(wiggly, repair=True)
    assert r.meta["repaired"] is True


@pytest.mark.parametrize("channels", [1, 3])
def test_save_load_round_trip(tmp_path, channels):
    r = CameraResponse.from_table(s_curve_table(channels), method="test", lam=3.0)
    path = r.save(tmp_path / "crf.npz")
    back = CameraResponse.load(path)
    np.testing.assert_array_equal(back.inverse_table, r.inverse_table)
    assert back.meta == {"method": "test", "lam": 3.0}
    # self-describing: the meta is plain JSON, readable without radiomap and without pickle
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
    assert meta["format"] == "radiomap" and meta["kind"] == "response" and meta["version"] == 1


def test_load_rejects_bad_files(tmp_path):
    missing = tmp_path / "nope.npz"
    with pytest.raises(CalibrationFileError, match="no such file"):
        CameraResponse.load(missing)
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"this is not a zip archive")
    with pytest.raises(CalibrationFileError, match="not a radiomap response file"):
        CameraResponse.load(garbage)
    truncated = tmp_path / "trunc.npz"
    good = CameraResponse.gamma().save(tmp_path / "good.npz").read_bytes()
    truncated.write_bytes(good[: len(good) // 2])
    with pytest.raises(CalibrationFileError):
        CameraResponse.load(truncated)
    nan = tmp_path / "nan.npz"
    save_model_file(nan, "response", {"inverse_table": np.full((256, 3), np.nan)})
    with pytest.raises(CalibrationFileError, match="NaN"):
        CameraResponse.load(nan)
    nonmono = tmp_path / "nonmono.npz"
    save_model_file(nonmono, "response", {"inverse_table": np.linspace(1, 0, 256)[:, None]})
    with pytest.raises(CalibrationFileError, match="strictly increasing"):
        CameraResponse.load(nonmono)
    wrong_kind = tmp_path / "vgn.npz"
    save_model_file(wrong_kind, "vignetting", {"lut": np.ones((4, 4, 3))})
    with pytest.raises(CalibrationFileError, match="'vignetting' model where a 'response'"):
        CameraResponse.load(wrong_kind)
    future = tmp_path / "future.npz"
    save_model_file(future, "response", {"inverse_table": np.linspace(0, 1, 256)[:, None]}, version=99)
    with pytest.raises(CalibrationFileError, match="version 99"):
        CameraResponse.load(future)
    missing_entry = tmp_path / "empty.npz"
    save_model_file(missing_entry, "response", {"something": np.zeros(3)})
    with pytest.raises(CalibrationFileError, match="inverse_table"):
        CameraResponse.load(missing_entry)


def test_gamma_rejects_bad_parameter():
    for g in (0.0, -1.0, np.nan, np.inf):
        with pytest.raises(ValueError, match="gamma"):
            CameraResponse.gamma(g)


def test_immutable():
    r = CameraResponse.gamma()
    with pytest.raises(ValueError):
        r.inverse_table[0, 0] = 5.0
