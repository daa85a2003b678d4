"""Exposure times out of order (audit: two times swapped in a 4-image stack were blamed on saturation, 'usable
4..-1', with the advice to add exposures)."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.errors import CalibrationError
from radiometry.response import levels as levels_module
from radiometry.response.fit import fit_response
from radiometry.response.inputs import _check_brightness_order
from response_curves import gamma_stack


def test_two_swapped_times_are_found_and_named():
    images = gamma_stack([8.0, 4.0, 2.0, 1.0])
    with pytest.raises(ValueError, match=r"times look out of order.*given 4 s is darker than the image given 2 s"
                                              r".*1 of 6 pairs disagree.*times file") as info:
        fit_response(images, [8.0, 2.0, 4.0, 1.0])
    assert not info.value.inverted and info.value.pairs == [(1, 2)]
    assert "c.png (4 s) is darker than b.png (2 s)" in info.value.message(["a.png", "b.png", "c.png", "d.png"])
    _check_brightness_order(np.stack(images), np.array([8.0, 4.0, 2.0, 1.0]))   # the right times pass
    with pytest.raises(ValueError, match="times are inverted"):            # a 1/t column
        _check_brightness_order(np.stack(images), np.array([1 / 8, 1 / 4, 1 / 2, 1.0]))


def test_an_empty_usable_range_is_not_printed_as_a_range(monkeypatch):
    """channel_levels leaving nothing (low 4 > high -1) is said as no usable levels, with the times as a suspect."""
    monkeypatch.setattr(levels_module, "channel_levels",
                        lambda values, times, limits: levels_module.ChannelLevels(4, -1, 64, 1, None))
    images = np.stack(gamma_stack([1.0, 2.0]))
    with pytest.raises(CalibrationError) as info:
        levels_module.detect_levels(images, np.array([1.0, 2.0]))
    message = str(info.value)
    assert "4..-1" not in message and "no usable levels" in message and "times file" in message, message


def test_the_audit_s_swapped_taipei_times_name_the_times_file(tmp_path):
    import cv2
    from conftest import shared_path

    src = shared_path("brackets", "taipei")
    names = ["DSC_0060.png", "DSC_0061.png", "DSC_0062.png", "DSC_0063.png"]
    for n in names:   # a quarter of the size keeps the test fast; the order check does not need more
        image = cv2.imread(str(src / n))
        cv2.imwrite(str(tmp_path / n), cv2.resize(image, None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA))
    (tmp_path / "times.txt").write_text("".join(f"{n} {t}\n" for n, t in zip(names, [8, 2, 4, 1])))
    result = CliRunner().invoke(cli, ["response", str(tmp_path), "-o", str(tmp_path / "out" / "crf.npz"),
                                      "--quality", "none", "--no-progress"])
    assert result.exit_code == 1, result.output
    line = [ln for ln in result.output.splitlines() if ln.startswith("radiomap: error:")][0]
    assert f"{tmp_path / 'times.txt'}: the times look out of order" in line, line
    assert "DSC_0062.png (4 s) is darker than DSC_0061.png (2 s)" in line and "-1" not in line, line
