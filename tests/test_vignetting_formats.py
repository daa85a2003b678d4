"""radical .vgn (LUT and polynomial) and DSO vignette.png: round trips, real data, malformed files, fuzz."""

from __future__ import annotations

import logging
import struct

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import shared_path
from radiometry.errors import CalibrationFileError
from radiometry.formats import load_vignetting
from radiometry.formats.dso_vignette import read_dso_vignette, write_dso_vignette
from radiometry.formats.vgn import MAGIC, read_radical_vgn, write_radical_vgn
from radiometry.vignetting import LUTVignetting, PolynomialVignetting, half_diagonal

FUZZ = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def rgb_lut(h: int = 12, w: int = 16) -> np.ndarray:
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return np.stack([1 - 0.01 * xs, 1 - 0.02 * ys, 0.5 + 0.001 * xs * ys], axis=2).astype(np.float32)


def poly() -> PolynomialVignetting:
    return PolynomialVignetting([[-0.5, 0.1, -0.05], [-0.45, 0.05, 0.0], [-0.6, 0.12, -0.02]],
                                [[80.0, 61.0], [79.5, 59.5], [84.0, 64.0]], (160, 120))


# ---------------------------------------------------------------------------------------------- radical
def test_vgn_lut_layout_and_round_trip(tmp_path):
    lut = rgb_lut()
    path = write_radical_vgn(LUTVignetting(lut), tmp_path / "v.vgn")
    data = path.read_bytes()
    assert data.startswith(b"NonparametricVignettingModel\n")
    off = len(b"NonparametricVignettingModel\n")
    magic, cv_type, dims, rows, cols = struct.unpack_from("<5I", data, off)
    assert (magic, cv_type, dims, rows, cols) == (MAGIC, 21, 2, 12, 16)  # CV_32FC3, rows = height
    first = np.frombuffer(data, "<f4", 3, off + 20)
    np.testing.assert_array_equal(first, lut[0, 0, ::-1])  # radical is BGR
    assert len(data) == off + 20 + 12 * 16 * 12
    back = read_radical_vgn(path)
    assert isinstance(back, LUTVignetting)
    np.testing.assert_array_equal(back.lut, lut)
    assert back.info["source"] == "radical .vgn"


def test_vgn_polynomial_layout_matches_radicals_formula(tmp_path):
    """radical evaluates V = 1 + sum b_k d^(2k) with d in pixels and (cx, cy, b1, b2, b3) BGR triples."""
    model = poly()
    path = write_radical_vgn(model, tmp_path / "p.vgn")
    data = path.read_bytes()
    header = b"PolynomialVignettingModel 3 160 120\n"
    assert data.startswith(header)
    magic, cv_type, dims, rows, cols = struct.unpack_from("<5I", data, len(header))
    assert (magic, cv_type, dims, rows * cols) == (MAGIC, 22, 2, 5)
    coeff = np.frombuffer(data, "<f8", 15, len(header) + 20).reshape(5, 3)  # rows cx, cy, b1, b2, b3; BGR
    ys, xs = np.mgrid[0:120, 0:160].astype(np.float64)
    ours = model.evaluate()
    for bgr in range(3):
        cx, cy, b1, b2, b3 = coeff[:, bgr]
        d2 = (xs - cx) ** 2 + (ys - cy) ** 2
        radical = 1 + b1 * d2 + b2 * d2 ** 2 + b3 * d2 ** 3
        np.testing.assert_allclose(radical, ours[:, :, 2 - bgr], rtol=1e-6)
    back = read_radical_vgn(path)
    assert isinstance(back, PolynomialVignetting)
    np.testing.assert_allclose(back.coefficients, model.coefficients, rtol=1e-12)
    np.testing.assert_array_equal(back.centres, model.centres)
    assert back.resolution == (160, 120)


def test_vgn_reads_radicals_column_layout(tmp_path):
    """radical's Check accepts any 5-element matrix: a 5 x 1 column reads like the 1 x 5 row."""
    radius = half_diagonal((160, 120))
    coeff = np.array([[80.0] * 3, [60.0] * 3, [-0.4 / radius ** 2] * 3, [0.0] * 3, [0.0] * 3])
    data = (b"PolynomialVignettingModel 3 160 120\n" + struct.pack("<5I", MAGIC, 22, 2, 5, 1)
            + coeff.astype("<f8").tobytes())
    (tmp_path / "col.vgn").write_bytes(data)
    model = read_radical_vgn(tmp_path / "col.vgn")
    np.testing.assert_allclose(model.coefficients[:, 0], -0.4)


def test_vgn_one_channel_and_scaled_models(tmp_path, caplog):
    mono = LUTVignetting(rgb_lut()[:, :, :1])
    back = read_radical_vgn(write_radical_vgn(mono, tmp_path / "m.vgn"))
    assert back.channels == 3
    np.testing.assert_array_equal(back.lut[:, :, 2], mono.lut[:, :, 0])
    scaled = PolynomialVignetting([[-0.3, 0, 0]] * 3, [[79.5, 59.5]] * 3, (160, 120), scale=[0.9, 1.0, 1.1])
    with caplog.at_level(logging.WARNING, logger="radiometry.formats.vgn"):
        back = read_radical_vgn(write_radical_vgn(scaled, tmp_path / "s.vgn"))
    assert "no per-channel scale" in caplog.text
    np.testing.assert_array_equal(back.scale, [1.0, 1.0, 1.0])
    np.testing.assert_allclose(back.coefficients, scaled.coefficients)


def _valid_lut_file(tmp_path):
    return write_radical_vgn(LUTVignetting(rgb_lut(4, 5)), tmp_path / "ok.vgn").read_bytes()


def _valid_poly_file(tmp_path):
    return write_radical_vgn(poly(), tmp_path / "okp.vgn").read_bytes()


@pytest.mark.parametrize("mutate, message", [
    (lambda lut, pol: lut[:-7], "truncated"),
    (lambda lut, pol: lut + b"\0\0\0\0", "trailing bytes"),
    (lambda lut, pol: lut[:40], "truncated"),
    (lambda lut, pol: b"NonparametricVignettingModel\n", "truncated after the header line"),
    (lambda lut, pol: lut.replace(struct.pack("<I", MAGIC), b"\0\0\0\0", 1), "bad magic"),
    (lambda lut, pol: lut.replace(struct.pack("<2I", MAGIC, 21), struct.pack("<2I", MAGIC, 22), 1), "matrix type 22"),
    (lambda lut, pol: b"SplineVignettingModel\n" + lut.split(b"\n", 1)[1], "not a radical vignetting model"),
    (lambda lut, pol: lut.replace(b"\n", b" ", 1).replace(b"\n", b""), "no header line"),
    (lambda lut, pol: pol.replace(b" 3 160", b" 2 160", 1), "degree 2"),
    (lambda lut, pol: pol.replace(b" 160 120", b" 0 120", 1), "not positive"),
    (lambda lut, pol: pol.replace(b" 160 120", b" x 120", 1), "bad header"),
    (lambda lut, pol: b"\xff\xfe\n" + lut, "not a radical vignetting model"),
])
def test_vgn_malformed(tmp_path, mutate, message):
    path = tmp_path / "bad.vgn"
    path.write_bytes(mutate(_valid_lut_file(tmp_path), _valid_poly_file(tmp_path)))
    with pytest.raises(CalibrationFileError, match=rf"bad\.vgn.*{message}"):
        read_radical_vgn(path)


@pytest.mark.parametrize("value, message", [(np.nan, "NaN"), (-0.5, "strictly positive"), (0.0, "strictly positive")])
def test_vgn_bad_values(tmp_path, value, message):
    lut = rgb_lut(4, 5)
    data = write_radical_vgn(LUTVignetting(lut), tmp_path / "v.vgn").read_bytes()
    off = len(b"NonparametricVignettingModel\n") + 20 + 4 * 7
    data = data[:off] + np.float32(value).tobytes() + data[off + 4:]
    (tmp_path / "v.vgn").write_bytes(data)
    with pytest.raises(CalibrationFileError, match=rf"v\.vgn: invalid vignetting model.*{message}"):
        read_radical_vgn(tmp_path / "v.vgn")


def test_vgn_polynomial_with_negative_v(tmp_path):
    bad = PolynomialVignetting([[-0.9, 0, 0]] * 3, [[79.5, 59.5]] * 3, (160, 120))
    data = write_radical_vgn(bad, tmp_path / "n.vgn").read_bytes().replace(b" 160 120", b" 320 240")
    # the pixel-unit coefficients of a 160x120 image applied to 320x240 reach V < 0 in the corners
    (tmp_path / "n.vgn").write_bytes(data)
    with pytest.raises(CalibrationFileError, match=r"n\.vgn.*<= 0 inside the image"):
        read_radical_vgn(tmp_path / "n.vgn")


def test_vgn_missing(tmp_path):
    with pytest.raises(CalibrationFileError, match="missing.vgn: no such file"):
        read_radical_vgn(tmp_path / "missing.vgn")


@FUZZ
@given(data=st.binary(max_size=400))
def test_vgn_fuzz_random_bytes(tmp_path, data):
    path = tmp_path / "f.vgn"
    path.write_bytes(data)
    with pytest.raises(CalibrationFileError, match="f.vgn"):
        read_radical_vgn(path)


@FUZZ
@given(which=st.booleans(), cut=st.integers(0, 400), flips=st.lists(st.tuples(st.integers(0, 400), st.integers(0, 255)),
                                                                     max_size=6))
def test_vgn_fuzz_mutated_files(tmp_path, which, cut, flips):
    base = bytearray(_valid_poly_file(tmp_path) if which else _valid_lut_file(tmp_path))
    for pos, value in flips:
        base[pos % len(base)] = value
    data = bytes(base[: max(0, len(base) - cut % len(base))] if cut % 3 == 0 else base)
    path = tmp_path / "m.vgn"
    path.write_bytes(data)
    try:
        model = read_radical_vgn(path)
    except CalibrationFileError as exc:
        assert "m.vgn" in str(exc)
    else:  # a mutation that still makes a valid model: it must be usable
        v = model.evaluate()
        assert np.all(np.isfinite(v)) and np.all(v > 0)


# ---------------------------------------------------------------------------------------------- DSO
def test_dso_real_file_and_byte_exact_round_trip(tmp_path):
    path = shared_path("vignetting", "euroc_mt9v034_752x480", "vignette.png")
    model = read_dso_vignette(path)
    assert model.channels == 1 and model.resolution == (752, 480)
    v = model.evaluate()
    assert float(v.max()) == 1.0
    assert float(v.min()) == pytest.approx(52416 / 65535, abs=1e-6)
    y, x = np.unravel_index(int(np.argmax(v[:, :, 0])), (480, 752))
    assert abs(x - 375) < 5 and abs(y - 237) < 5
    out = write_dso_vignette(model, tmp_path / "vignette.png")
    original = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    written = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert written.dtype == np.uint16 and written.shape == (480, 752)
    np.testing.assert_array_equal(written, original)
    assert load_vignetting(out).evaluate(240, 376).shape == (240, 376, 1)


def test_dso_colour_models(tmp_path, caplog):
    lut = rgb_lut()
    model = LUTVignetting(lut)
    with caplog.at_level(logging.WARNING, logger="radiometry.formats.dso_vignette"):
        mean = read_dso_vignette(write_dso_vignette(model, tmp_path / "mean.png"))
    assert "mean of 3 channels" in caplog.text
    expected = lut.mean(axis=2)
    np.testing.assert_allclose(mean.lut[:, :, 0], expected / expected.max(), atol=1 / 65535)
    blue = read_dso_vignette(write_dso_vignette(model, tmp_path / "b.png", channel="B"))
    np.testing.assert_allclose(blue.lut[:, :, 0], lut[:, :, 2] / lut[:, :, 2].max(), atol=1 / 65535)
    with pytest.raises(ValueError, match="channel must be 'mean', one of R/G/B"):
        write_dso_vignette(model, tmp_path / "x.png", channel="alpha")
    with pytest.raises(TypeError, match="VignettingModel"):
        write_dso_vignette(lut, tmp_path / "x.png")


def test_dso_reads_8_bit(tmp_path):
    img = np.full((6, 8), 200, np.uint8)
    img[2:4, 3:5] = 250
    cv2.imwrite(str(tmp_path / "v8.png"), img)
    v = read_dso_vignette(tmp_path / "v8.png").evaluate()
    assert v.max() == 1.0 and v.min() == pytest.approx(0.8)


@pytest.mark.parametrize("make, message", [
    (lambda p: cv2.imwrite(str(p), np.full((6, 8, 3), 60000, np.uint16)), "3 channels"),
    (lambda p: cv2.imwrite(str(p), np.zeros((6, 8), np.uint16)), "all pixels are 0"),
    (lambda p: cv2.imwrite(str(p), np.pad(np.full((4, 6), 60000, np.uint16), 1)), "24 pixels are 0"),
    (lambda p: p.write_bytes(b""), "cannot decode"),
    (lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 30), "cannot decode"),
])
def test_dso_malformed(tmp_path, make, message):
    path = tmp_path / "vignette.png"
    make(path)
    with pytest.raises(CalibrationFileError, match=rf"vignette\.png.*{message}"):
        read_dso_vignette(path)


def test_dso_truncated_and_float(tmp_path):
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.full((40, 50), 50000, np.uint16))
    (tmp_path / "cut.png").write_bytes(good.read_bytes()[:60])
    with pytest.raises(CalibrationFileError, match="cut.png: cannot decode"):
        read_dso_vignette(tmp_path / "cut.png")
    if cv2.imwrite(str(tmp_path / "f.tiff"), np.ones((4, 4), np.float32)):
        with pytest.raises(CalibrationFileError, match="f.tiff: pixel type float32"):
            read_dso_vignette(tmp_path / "f.tiff")
    with pytest.raises(CalibrationFileError, match="nope.png: no such file"):
        read_dso_vignette(tmp_path / "nope.png")


def test_dso_rejects_an_implausible_header_before_decoding(tmp_path):
    ok, buf = cv2.imencode(".png", np.full((8, 8), 40000, np.uint16))
    data = bytearray(buf.tobytes())
    data[16:24] = (60000).to_bytes(4, "big") + (50000).to_bytes(4, "big")  # IHDR width, height
    (tmp_path / "huge.png").write_bytes(bytes(data))
    with pytest.raises(CalibrationFileError, match=r"huge\.png: the PNG header claims 60000x50000 pixels"):
        read_dso_vignette(tmp_path / "huge.png")


@FUZZ
@given(data=st.binary(max_size=300))
def test_dso_fuzz_random_bytes(tmp_path, data):
    path = tmp_path / "fz.png"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + data if data[:1] == b"\0" else data)
    with pytest.raises(CalibrationFileError, match="fz.png"):
        read_dso_vignette(path)


@FUZZ
@given(flips=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=8),
       cut=st.integers(0, 200))
def test_dso_fuzz_mutated_png(tmp_path, flips, cut):
    ok, buf = cv2.imencode(".png", (np.arange(64, dtype=np.uint16).reshape(8, 8) + 30000))
    data = bytearray(buf.tobytes())
    for pos, value in flips:
        data[pos % len(data)] = value
    path = tmp_path / "mut.png"
    path.write_bytes(bytes(data[: len(data) - cut % len(data)]))
    try:
        model = read_dso_vignette(path)
    except CalibrationFileError as exc:
        assert "mut.png" in str(exc)
    else:
        v = model.evaluate()
        assert np.all(np.isfinite(v)) and v.max() == 1.0 and v.min() > 0


# ---------------------------------------------------------------------------------------------- dispatch
def test_load_vignetting_dispatches_on_suffix(tmp_path):
    lut = LUTVignetting(rgb_lut())
    assert isinstance(load_vignetting(write_radical_vgn(poly(), tmp_path / "a.vgn")), PolynomialVignetting)
    assert isinstance(load_vignetting(write_dso_vignette(lut, tmp_path / "b.png")), LUTVignetting)
    assert isinstance(load_vignetting(lut.save(tmp_path / "c.npz")), LUTVignetting)
    with pytest.raises(CalibrationFileError, match="d.vgn: no such file"):
        load_vignetting(tmp_path / "d.vgn")
