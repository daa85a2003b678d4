"""``radiomap correct`` publishes its outputs all together or not at all (audit 2026-11-28: a folder whose third image
did not fit the models left the first two corrected images behind, exit 1, and SIGTERM after 20 of 150 frames left
20 images with no marker; a rerun then said "f000.png exists; pass --force"); and the same audit's small ones: a
float format OpenCV cannot write refused before the folder is made, a resampled model said, no OpenCV warnings
before the one-line error of a missing camera."""

from __future__ import annotations

import subprocess
import sys

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
    assert sorted(before) == [".radiomap-correct.json", "f0.png", "f1.png", "f2.png"]  # the record: audit C
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
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [".radiomap-correct.json", "f0.png", "f1.png"]
    se = np.load(tmp_path / "se" / "se.npy")
    assert se.shape == (H, W, 3) and np.allclose(se, 0.01, atol=1e-3)
    assert not [p for p in (tmp_path / "se").iterdir() if p.name != "se.npy"]


def test_a_float_format_opencv_cannot_write_is_refused_before_anything_is_made(tmp_path, monkeypatch):
    from radiometry import images

    def no_exr(path, img):
        from radiometry.errors import OutputError

        raise OutputError(f"{path}: OpenCV cannot write 32-bit float EXR (no encoder); use --irradiance-format npy")

    monkeypatch.setattr(images, "_encode_float", no_exr)
    models = _models(tmp_path)
    frames = _frames(tmp_path / "in", [(H, W)])
    result = _correct(frames, models, tmp_path / "out", "--irradiance", "--irradiance-format", "exr")
    assert result.exit_code == 2 and "--irradiance-format" in result.output and "EXR" in result.output, result.output
    assert not (tmp_path / "out").exists()


def test_a_model_resampled_to_the_images_is_said(tmp_path):
    models = _models(tmp_path)
    frames = _frames(tmp_path / "in", [(2 * H, 2 * W)])
    result = _correct(frames, models, tmp_path / "out")
    assert result.exit_code == 0, result.output
    assert f"the vignetting model ({W}x{H}) is resampled to the images' {2 * W}x{2 * H}" in result.output
    assert "cropped sensor" in result.output
    same = _correct(_frames(tmp_path / "same", [(H, W)]), models, tmp_path / "out2")
    assert same.exit_code == 0 and "is resampled to" not in same.output, same.output


def test_a_missing_camera_is_one_line_without_opencv_warnings(tmp_path):
    """``radiomap vignetting 9`` (a camera index with no camera): OpenCV printed two ``[ WARN:0 ...]`` lines to the
    process's stderr before radiomap's error; only the error is left."""
    response = CameraResponse.gamma(2.2).save(tmp_path / "crf.npz")
    done = subprocess.run([sys.executable, "-m", "mapping.cli", "vignetting", "9", "-r", str(response), "-o",
                           str(tmp_path / "v.npz")], capture_output=True, text=True, timeout=600)
    lines = [line for line in (done.stdout + done.stderr).splitlines() if line.strip()]
    assert done.returncode == 1 and len(lines) == 1 and "cannot open camera 9" in lines[0], lines
