"""``radiomap correct`` publishes its outputs all together or not at all (audit 2026-11-28: a folder whose third image
did not fit the models left the first two corrected images behind, exit 1, and SIGTERM after 20 of 150 frames left
20 images with no marker; a rerun then said "f000.png exists; pass --force")."""

from __future__ import annotations

import cv2
import numpy as np
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting

W, H = 48, 36


def _models(folder):
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - (W - 1) / 2) ** 2 + (yy - (H - 1) / 2) ** 2) / (0.25 * (W ** 2 + H ** 2))
    lut = LUTVignetting(np.repeat((1 - 0.35 * r2)[:, :, None], 3, axis=2).astype(np.float32))
    return CameraResponse.gamma(2.2).save(folder / "crf.npz"), lut.save(folder / "v.npz")


def _frames(folder, shapes):
    folder.mkdir()
    rng = np.random.default_rng(0)
    for i, (h, w) in enumerate(shapes):
        cv2.imwrite(str(folder / f"f{i}.png"), rng.integers(20, 230, (h, w, 3), dtype=np.uint8))
    return folder


def _correct(frames, models, out, *extra):
    return CliRunner().invoke(cli, ["correct", str(frames), "-r", str(models[0]), "--vignetting", str(models[1]),
                                    "-o", str(out), "--no-progress", *map(str, extra)])


def test_an_image_that_does_not_fit_leaves_no_partial_output(tmp_path):
    models = _models(tmp_path)
    frames = _frames(tmp_path / "in", [(H, W), (H, W), (W, H)])  # the third one turned 90 degrees
    result = _correct(frames, models, tmp_path / "out")
    assert result.exit_code == 1 and "f2.png" in result.output, result.output
    out = tmp_path / "out"
    assert not out.exists() or not list(out.iterdir()), list(out.iterdir())  # no image, no staging folder


def test_a_failed_forced_run_keeps_the_earlier_outputs_byte_for_byte(tmp_path):
    models = _models(tmp_path)
    good = _frames(tmp_path / "good", [(H, W)] * 3)
    assert _correct(good, models, tmp_path / "out").exit_code == 0
    before = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    assert sorted(before) == ["f0.png", "f1.png", "f2.png"]
    bad = _frames(tmp_path / "bad", [(H, W), (H, W), (W, H)])
    cv2.imwrite(str(bad / "f0.png"), np.zeros((H, W, 3), np.uint8))  # would replace f0.png with other content
    result = _correct(bad, models, tmp_path / "out", "--force")
    assert result.exit_code == 1, result.output
    after = {p.name: p.read_bytes() for p in (tmp_path / "out").iterdir()}
    assert after == before  # nothing replaced, nothing staged left behind


def test_a_complete_run_writes_every_image_and_the_stderr_file(tmp_path):
    models = _models(tmp_path)
    frames = _frames(tmp_path / "in", [(H, W)] * 2)
    lut = LUTVignetting.load(models[1])
    stderr = LUTVignetting(lut.lut, stderr=np.full_like(lut.lut, 0.01)).save(tmp_path / "vs.npz")
    result = CliRunner().invoke(cli, ["correct", str(frames), "-r", str(models[0]), "--vignetting", str(stderr),
                                      "-o", str(tmp_path / "out"), "--stderr", str(tmp_path / "se" / "se.npy"),
                                      "--no-progress"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["f0.png", "f1.png"]
    se = np.load(tmp_path / "se" / "se.npy")
    assert se.shape == (H, W, 3) and np.allclose(se, 0.01, atol=1e-3)
    assert not [p for p in (tmp_path / "se").iterdir() if p.name != "se.npy"]
