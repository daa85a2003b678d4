"""A measured DSO ``pcalib.txt`` that dips loads through the documented repair (isotonic regression), with a
warning that says how much changed; ``strict=True`` keeps DSO's refusal; a file that would need a large change
is refused."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from conftest import shared_path
from radiometry.errors import CalibrationFileError
from radiometry.formats import load_response
from radiometry.formats.pcalib import MAX_REPAIR, isotonic_repair, read_pcalib


def _write(path, values) -> str:
    path.write_text(" ".join(f"{v:.6f}" for v in values) + " \nvis_exponent: 1.0\n")
    return path


def _dipping() -> np.ndarray:
    """A smooth curve in 0..255 with two dips: a wiggle near saturation (levels 240..243 fall by 0.6) and a
    swapped pair in the middle."""
    values = 255.0 * (np.arange(256) / 255.0) ** 1.8
    values[241:244] = values[240] - np.array([0.2, 0.4, 0.6])
    values[100], values[101] = values[101], values[100]
    return values


def test_isotonic_repair_is_the_pool_adjacent_violators_fit():
    y = np.array([0.0, 1.0, 3.0, 2.0, 4.0, 3.5, 3.0, 6.0])
    out = isotonic_repair(y, min_step=0.0)
    np.testing.assert_allclose(out, [0.0, 1.0, 2.5, 2.5, 3.5, 3.5, 3.5, 6.0])
    strict = isotonic_repair(y)
    assert np.all(np.diff(strict) > 0)
    np.testing.assert_allclose(strict, out, atol=1e-5 * 6)
    # an increasing sequence is left alone (up to the separation, which is zero here)
    np.testing.assert_array_equal(isotonic_repair(np.arange(5.0), min_step=0.0), np.arange(5.0))


def test_a_dipping_pcalib_loads_with_a_warning_that_says_how_much_changed(tmp_path, caplog):
    path = _write(tmp_path / "pcalib.txt", _dipping())
    with caplog.at_level(logging.WARNING, logger="radiometry.formats.pcalib"):
        response = read_pcalib(path)
    table = response.inverse_table[:, 0]
    assert np.all(np.diff(table) > 0)
    (record,) = [r for r in caplog.records if "not strictly increasing" in r.getMessage()]
    message = record.getMessage()
    assert "first at level 101" in message and "isotonic regression" in message and "strict=True" in message
    repaired = response.meta["repaired"]
    assert repaired["levels"] == [100, 101, 240, 241, 242, 243]
    assert f"{len(repaired['levels'])} levels changed (100..243)" in message
    # the largest change: the swapped pair pooled to its mean (half their step), or 240..243 pooled (0.3)
    values = _dipping()
    change = max(abs(values[100] - values[101]) / 2, values[240] - values[240:244].mean()) / (values[-1] - values[0])
    assert repaired["max_change_fraction"] == pytest.approx(change, rel=1e-3)
    import re

    stated = float(re.search(r"at most by ([0-9.]+) of 0\.\.255", message).group(1))
    assert stated == pytest.approx(255 * change, abs=1e-3)
    # unchanged levels keep DSO's normalisation of the file's values exactly
    np.testing.assert_allclose(table[:100], values[:100] / 255.0, atol=1e-8)  # the file holds 6 decimals
    # the same through the --response dispatcher
    np.testing.assert_array_equal(load_response(path).inverse_table, response.inverse_table)


def test_strict_refuses_a_dip(tmp_path):
    path = _write(tmp_path / "pcalib.txt", _dipping())
    with pytest.raises(CalibrationFileError, match="not strictly increasing at level 101 \\(DSO rejects"):
        read_pcalib(path, strict=True)


def test_a_large_dip_is_no_response(tmp_path):
    values = 255.0 * np.arange(256) / 255.0
    values[150] = values[20]  # a drop of half the range
    path = _write(tmp_path / "pcalib.txt", values)
    with pytest.raises(CalibrationFileError, match=f"more than {100 * MAX_REPAIR:g}%\\): not a response"):
        read_pcalib(path)


def test_the_real_euroc_pcalib_needs_no_repair(caplog):
    path = shared_path("vignetting", "euroc_mt9v034_752x480", "pcalib.txt")
    if not path.is_file():
        pytest.skip(f"shared data absent: {path}")
    with caplog.at_level(logging.WARNING):
        response = read_pcalib(path)
    assert "repaired" not in response.meta and not caplog.records


def test_a_repeated_value_is_separated(tmp_path):
    values = 255.0 * (np.arange(256) / 255.0) ** 2
    values[50] = values[49]
    response = read_pcalib(_write(tmp_path / "pcalib.txt", values))
    assert np.all(np.diff(response.inverse_table[:, 0]) > 0)
    assert response.meta["repaired"]["levels"] == [49, 50]
    assert response.meta["repaired"]["max_change_fraction"] < 1e-5
