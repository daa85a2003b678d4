"""Response files: radiomap .npz, radical .crf, DSO/TUM pcalib.txt - round trips, real files, malformed input."""

from __future__ import annotations

import functools

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
from conftest import shared_path
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from radiometry.errors import CalibrationFileError
from radiometry.formats import load_response, load_vignetting
from radiometry.formats.crf import MAGIC, read_radical_crf, write_radical_crf
from radiometry.formats.pcalib import read_pcalib, write_pcalib
from radiometry.response import CameraResponse

U = np.arange(256) / 255.0


def rgb_response() -> CameraResponse:
    """Distinct channels (gamma 1.8 / 2.2 / 2.6) so that an R/B swap cannot pass."""
    return CameraResponse(np.stack([U ** 1.8, U ** 2.2, U ** 2.6], axis=1) + 1e-4 * U[:, None], {"method": "test"})


def gray_response() -> CameraResponse:
    return CameraResponse((U ** 2.2)[:, None], {"method": "test"})


def crf_bytes(values: np.ndarray, *, cv_type: int = 21, dims: int = 2, rows: int = 256, cols: int = 1,
              magic: int = MAGIC, dtype: str = "<f4") -> bytes:
    return struct.pack("<5I", magic, cv_type, dims, rows, cols) + np.asarray(values, dtype=dtype).tobytes()


# --------------------------------------------------------------------------------------------------
# round trips
# --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("make", [rgb_response, gray_response])
def test_npz_round_trip(tmp_path, make):
    response = make()
    response.save(tmp_path / "crf.npz")
    back = load_response(tmp_path / "crf.npz")
    assert np.array_equal(back.inverse_table, response.inverse_table) and back.meta == response.meta


def test_crf_round_trip_keeps_channel_order(tmp_path):
    response = rgb_response()
    path = write_radical_crf(tmp_path / "camera.crf", response)
    data = path.read_bytes()
    magic, cv_type, dims, rows, cols = struct.unpack_from("<5I", data)
    assert (magic, cv_type, dims, rows, cols) == (0xC4A1FDD9, 21, 2, 256, 1)  # CV_32FC3, 256 x 1
    assert len(data) == 20 + 256 * 3 * 4
    level_128 = np.frombuffer(data, "<f4", count=3, offset=20 + 128 * 12)
    assert level_128 == pytest.approx(response.inverse_table[128, ::-1], rel=1e-6)  # BGR in the file
    back = load_response(path)
    assert back.channels == 3 and back.meta["method"] == "radical" and back.meta["repaired"] is False
    assert np.allclose(back.inverse_table, response.inverse_table, rtol=1e-6, atol=1e-7)


def test_crf_from_gray_response_has_three_equal_channels(tmp_path):
    back = read_radical_crf(write_radical_crf(tmp_path / "g.crf", gray_response()))
    assert back.channels == 3
    assert np.allclose(back.inverse_table, np.repeat(gray_response().inverse_table, 3, axis=1), atol=1e-7)


def test_crf_as_radical_writes_it(tmp_path):
    """radical's calibration clamps levels outside its valid range to 0 and 1 and sorts: plateaus."""
    table = np.stack([U ** 1.8, U ** 2.2, U ** 2.6], axis=1)
    table[:5] = 0.0
    table[251:] = 1.0
    table[120:122, 1] = table[120, 1]  # a flat step inside
    path = tmp_path / "asus.crf"
    path.write_bytes(crf_bytes(table[:, ::-1]))
    response = read_radical_crf(path)
    assert response.meta["repaired"] is True
    assert np.all(np.diff(response.inverse_table, axis=0) > 0)
    assert np.allclose(response.inverse_table, table, atol=1e-5)


def test_crf_float64_single_channel(tmp_path):
    path = tmp_path / "gray.crf"
    path.write_bytes(crf_bytes(U ** 2.0 + 1e-3, cv_type=6, rows=1, cols=256, dtype="<f8"))  # CV_64FC1, 1 x 256
    response = read_radical_crf(path)
    assert response.channels == 1 and response.inverse_table[128, 0] == pytest.approx(
        (U[128] ** 2 + 1e-3) / (1 + 1e-3))


def test_pcalib_round_trip(tmp_path):
    response = gray_response()
    path = write_pcalib(tmp_path / "pcalib.txt", response)
    first = path.read_text().splitlines()[0].split()
    assert len(first) == 256 and first[0] == "0.000000" and first[-1] == "255.000000"
    back = load_response(path)
    assert back.channels == 1 and back.meta["method"] == "pcalib"
    assert np.allclose(back.inverse_table, response.inverse_table, atol=2e-8)


def test_pcalib_from_rgb_needs_a_channel(tmp_path):
    response = rgb_response()
    with pytest.warns(UserWarning, match="writing the mean of the R, G and B"):
        write_pcalib(tmp_path / "mean.txt", response)
    mean = response.inverse_table.mean(axis=1)
    assert np.allclose(read_pcalib(tmp_path / "mean.txt").inverse_table[:, 0], (mean - mean[0]) / (1 - mean[0]),
                       atol=1e-8)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        write_pcalib(tmp_path / "g.txt", response, channel=1)
        write_pcalib(tmp_path / "m.txt", response, channel="mean")
    green = response.inverse_table[:, 1]
    assert np.allclose(read_pcalib(tmp_path / "g.txt").inverse_table[:, 0], (green - green[0]) / (1 - green[0]),
                       atol=1e-8)
    for bad in (3, -1, "red", True, 1.0):
        with pytest.raises(ValueError, match="channel must be"):
            write_pcalib(tmp_path / "x.txt", response, channel=bad)
    with pytest.raises(ValueError, match="1-channel response"):
        write_pcalib(tmp_path / "x.txt", gray_response(), channel=2)
    with pytest.raises(TypeError, match="CameraResponse"):
        write_pcalib(tmp_path / "x.txt", np.ones(256))


def test_pcalib_offset_at_level_zero_follows_dso(tmp_path):
    """DSO rescales to 255 (G - G[0]) / (G[255] - G[0]): a response with f^-1(0) > 0 loses the offset."""
    table = 0.05 + 0.95 * U ** 2.2
    back = read_pcalib(write_pcalib(tmp_path / "p.txt", CameraResponse(table[:, None])))
    assert back.inverse_table[0, 0] == 0.0
    assert np.allclose(back.inverse_table[:, 0], (table - 0.05) / 0.95, atol=1e-8)


def test_real_dso_pcalib():
    path = shared_path("vignetting", "euroc_mt9v034_752x480", "pcalib.txt")
    values = np.array(path.read_text().splitlines()[0].split(), dtype=float)
    response = load_response(path)
    assert response.channels == 1
    assert response.inverse_table[0, 0] == 0.0 and response.inverse_table[-1, 0] == 1.0
    assert np.allclose(response.inverse_table[:, 0], values / 255.0)  # this file already spans 0..255
    assert np.all(np.diff(response.inverse_table[:, 0]) > 0)


def test_writers_are_atomic(tmp_path, monkeypatch):
    """A failing write leaves the previous file untouched and no temporary file behind."""
    path = write_radical_crf(tmp_path / "c.crf", rgb_response())
    before = path.read_bytes()
    import radiometry.fileio as fileio

    def broken_fsync(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fileio.os, "fsync", broken_fsync)
    from radiometry.errors import OutputError

    with pytest.raises(OutputError, match="disk is full"):
        write_radical_crf(path, gray_response())
    with pytest.raises(OutputError, match="disk is full"):
        write_pcalib(tmp_path / "p.txt", gray_response())
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.crf"]


# --------------------------------------------------------------------------------------------------
# malformed files
# --------------------------------------------------------------------------------------------------
GOOD = np.stack([U ** 1.8, U ** 2.2, U ** 2.6], axis=1)[:, ::-1] + 1e-4


def _nan_table():
    t = GOOD.copy()
    t[100, 1] = np.nan
    return t


def _decreasing_table():
    t = GOOD.copy()
    t[200, 0] = t[150, 0]
    return t


@pytest.mark.parametrize("data, match", [
    (b"", r"truncated header \(0 of 20 bytes\)"),
    (crf_bytes(GOOD)[:12], "truncated header"),
    (crf_bytes(GOOD, magic=0x12345678), "not a radical cv::Mat file"),
    (b"0.1 0.2 0.3 " * 300, "not a radical cv::Mat file"),
    (crf_bytes(GOOD.astype(np.uint8), cv_type=16, dtype="u1"), r"type 16 \(depth 0, 3 channels\)"),
    (crf_bytes(np.tile(GOOD, (1, 2))[:, :4], cv_type=29), "4 channels"),
    (crf_bytes(GOOD[:255], rows=255), "255 x 1 matrix"),
    (crf_bytes(GOOD, dims=3), "dims 3"),
    (crf_bytes(GOOD)[:-4], r"truncated: 3088 bytes, expected 3092"),
    (crf_bytes(GOOD) + b"\x00" * 8, "8 unexpected bytes"),
    (crf_bytes(_nan_table()), "NaN or infinite"),
    (crf_bytes(-GOOD), "negative"),
    (crf_bytes(_decreasing_table()), "decreases at level 200"),
    (crf_bytes(np.zeros((256, 3))), "zero at level 255"),
])
def test_malformed_crf(tmp_path, data, match):
    assert_refused(read_radical_crf, tmp_path / "bad.crf", data, match)


def assert_refused(reader, path, data: bytes | str, match: str) -> None:
    """``reader`` refuses ``data`` written to ``path`` with a CalibrationFileError that names the file."""
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    with pytest.raises(CalibrationFileError, match=match) as info:
        reader(path)
    assert str(path) in str(info.value)


def test_missing_files(tmp_path):
    for reader in (read_radical_crf, read_pcalib, load_response):
        with pytest.raises(CalibrationFileError, match="no such file"):
            reader(tmp_path / "nope.crf")
        with pytest.raises(CalibrationFileError, match="no such file"):
            reader(tmp_path)  # a folder


def _line(values) -> str:
    return " ".join(f"{v:.6f}" for v in values)


INCREASING = 255 * U ** 2.2


@pytest.mark.parametrize("text, match", [
    ("", "the first line is empty"),
    ("\n" + _line(INCREASING), "the first line is empty"),
    (_line(INCREASING[:255]), "found 255 numbers .* expected 256"),
    (_line(np.r_[INCREASING, 256.0]), "found 257 numbers"),
    ("# comment\n" + _line(INCREASING), "found 0 numbers"),
    (_line(INCREASING[:100]) + " nan " + _line(INCREASING[101:]), "value 101 is 'nan'"),
    (_line(INCREASING[:3]) + " inf " + _line(INCREASING[4:]), "value 4 is 'inf'"),
    (_line(INCREASING[:10]) + " 1e999 " + _line(INCREASING[11:]), "overflows"),
    (_line(INCREASING[::-1]), "not strictly increasing at level 1"),
    (_line(np.r_[INCREASING[:50], INCREASING[49], INCREASING[51:]]), "not strictly increasing at level 50"),
    (_line(INCREASING[:10]) + " abc " + _line(INCREASING[11:]), "found 10 numbers"),
    ("1_0 " + _line(INCREASING[1:]), "found 0 numbers"),
])
def test_malformed_pcalib(tmp_path, text, match):
    """strict: a dip is refused as DSO refuses it (the default repairs a small one: test_pcalib_repair.py)."""
    assert_refused(functools.partial(read_pcalib, strict=True), tmp_path / "pcalib.txt", text, match)


def test_pcalib_binary_and_trailing_text(tmp_path):
    path = tmp_path / "pcalib.txt"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(CalibrationFileError, match="not a text file"):
        read_pcalib(path)
    path.write_text(_line(INCREASING) + " trailing words 1 2 3\nvis_exponent: 1.000000\nanything else\n")
    assert read_pcalib(path).inverse_table[128, 0] == pytest.approx(U[128] ** 2.2, abs=1e-6)


# --------------------------------------------------------------------------------------------------
# fuzz: the readers raise CalibrationFileError or return a valid response, never anything else
# --------------------------------------------------------------------------------------------------
def _read_or_reject(reader, path: Path) -> None:
    try:
        response = reader(path)
    except CalibrationFileError:
        return
    table = response.inverse_table
    assert table.shape[0] == 256 and np.all(np.isfinite(table)) and np.all(np.diff(table, axis=0) > 0)


FUZZ = settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _mutated_crf(level: int, channel: int, value: float, cut: int) -> bytes:
    table = GOOD.astype(np.float32)
    table[level, channel] = value
    data = crf_bytes(table)
    return data[:cut] if cut < len(data) else data


@FUZZ
@given(st.one_of(
    st.binary(max_size=400),
    st.builds(lambda head, body: struct.pack("<I", MAGIC) + head + body,
              st.binary(min_size=16, max_size=16), st.binary(max_size=400)),
    st.builds(_mutated_crf, st.integers(0, 255), st.integers(0, 2), st.floats(width=32),
              st.integers(0, 3200)),
))
def test_fuzz_crf_reader(tmp_path_factory, data):
    path = tmp_path_factory.getbasetemp() / "fuzz.crf"
    path.write_bytes(data)
    _read_or_reject(read_radical_crf, path)


TOKENS = _line(INCREASING).split()


def _mutated_pcalib(index: int, token: str, drop: bool, tail: str) -> str:
    tokens = list(TOKENS)
    if drop:
        del tokens[index]
    else:
        tokens[index] = token
    return " ".join(tokens) + tail


@FUZZ
@given(st.one_of(
    st.text(max_size=300),
    st.binary(max_size=300),
    st.builds(_mutated_pcalib, st.integers(0, 255),
              st.sampled_from(["0", "-1", "1e3", "1e999", "nan", "-inf", "x", "255", "1e-7", ".", "+.5", "",
                               "1,5"]),
              st.booleans(), st.text(max_size=20)),
))
def test_fuzz_pcalib_reader(tmp_path_factory, content):
    path = tmp_path_factory.getbasetemp() / "fuzz_pcalib.txt"
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8", errors="surrogatepass")
    _read_or_reject(read_pcalib, path)


@pytest.mark.parametrize("name, writer", [("x.crf", "write_radical_crf"), ("x.txt", "write_pcalib"),
                                          ("x", "name the file .npz")])
def test_a_response_saves_as_npz_only_and_names_the_writer_of_another_format(tmp_path, name, writer):
    """CameraResponse.save once wrote a zip under any name (x.crf, pcalib.txt) that no reader could read back."""
    with pytest.raises(ValueError, match=writer) as info:
        rgb_response().save(tmp_path / name)
    assert name in str(info.value) and "\n" not in str(info.value)
    assert not (tmp_path / name).exists()
    assert load_response(rgb_response().save(tmp_path / "x.NPZ")).channels == 3


@pytest.mark.parametrize("name, kind", [("v.png", "DSO"), ("v.vgn", "radical")])
def test_a_vignetting_model_saves_as_npz_only_and_names_the_writer_of_another_format(tmp_path, name, kind):
    from radiometry.formats import save_vignetting
    from radiometry.vignetting import LUTVignetting

    model = LUTVignetting(np.ones((6, 8, 1), np.float32))
    with pytest.raises(ValueError, match=f"save_vignetting.*{kind}"):
        model.save(tmp_path / name)
    assert not (tmp_path / name).exists()
    save_vignetting(model, tmp_path / name)   # the writer it names reads back
    assert load_vignetting(tmp_path / name).resolution == (8, 6)
