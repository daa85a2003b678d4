"""OpenCV's fits (``--method opencv-debevec`` / ``robertson``) declare the levels the data constrain, as radiomap's own
fits do: they fit every level, saturated ones included, so the quality figures and a vignetting budget must not
judge a channel above where it saturates, and the command says which levels those are (audit leftover)."""

from __future__ import annotations

import numpy as np
import pytest

from camera_pipelines import PIPELINES, ceiling_level, render
from response_curves import TIMES, curves, scene


@pytest.mark.parametrize("method", ["opencv-debevec", "robertson"])
def test_opencv_fits_declare_the_levels_below_each_channel_s_saturation(method):
    from radiometry.response.fit import fit_response
    from radiometry.response.levels import declared

    table = curves(include_euroc=False)["gamma-2.2"]
    options = PIPELINES["wb-after-clip"]  # red saturates at 240, blue at 248
    images = render(table, scene(120, 160, seed=1), TIMES, seed=2, **options)
    response = fit_response(images, TIMES, method=method)
    ceilings = [ceiling_level(table, g) for g in options["gains"]]
    got = response.meta["declared_levels"]
    assert [hi for _, hi in declared(response, 3)] == [hi for _, hi in got]
    assert all(hi <= c for (_, hi), c in zip(got, ceilings)), (got, ceilings)
    assert got[0][1] < 245 and got[1][1] > 250, got  # red's saturation found; green's is not cut
    summary = response.meta["levels_summary"]
    assert summary.startswith("saturates R at") and "OpenCV fitted the others too" in summary, summary


def test_the_command_prints_the_opencv_fit_s_levels(tmp_path):
    import cv2
    from click.testing import CliRunner

    from mapping.cli import cli

    table = curves(include_euroc=False)["gamma-2.2"]
    images = render(table, scene(60, 80, seed=1), TIMES, seed=2, **PIPELINES["wb-after-clip"])
    folder = tmp_path / "stack"
    folder.mkdir()
    lines = []
    for i, (img, t) in enumerate(zip(images, TIMES)):
        cv2.imwrite(str(folder / f"e{i:02d}.png"), np.ascontiguousarray(img[..., ::-1]))
        lines.append(f"e{i:02d}.png {float(t)!r}")
    (folder / "times.txt").write_text("\n".join(lines) + "\n")
    result = CliRunner().invoke(cli, ["response", str(folder), "-o", str(tmp_path / "crf.npz"), "--method",
                                      "robertson", "--quality", "none", "--no-progress"])
    assert result.exit_code == 0, result.output
    assert "levels the data constrain R 1..2" in result.output and "OpenCV fitted the others" in result.output, \
        result.output
