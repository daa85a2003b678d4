"""``radiomap correct`` and its inputs (audit C of 2026-11-28): ``--force`` over an earlier, longer video's frames
leaves none of them; a truncated video is said and its last, partly decoded frame is not written; an image's EXIF
orientation is carried over to the PNG; a resampled model is said for every image size that needs it; 16-bit input
keeps its precision in ``--irradiance``."""

from __future__ import annotations

import json
import logging
import struct

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting

W, H = 48, 36


def _models(folder, *, flat=False):
    yy, xx = np.mgrid[0:H, 0:W]
    r2 = ((xx - (W - 1) / 2) ** 2 + (yy - (H - 1) / 2) ** 2) / (0.25 * (W ** 2 + H ** 2))
    v = np.ones((H, W)) if flat else 1 - 0.35 * r2
    lut = LUTVignetting(np.repeat(v[:, :, None], 3, axis=2).astype(np.float32))
    return CameraResponse.gamma(2.2).save(folder / "crf.npz"), lut.save(folder / "v.npz")


def _correct(source, models, out, *extra):
    return CliRunner().invoke(cli, ["correct", str(source), "-r", str(models[0]), "--vignetting", str(models[1]),
                                    "-o", str(out), "--no-progress", *map(str, extra)])


def _video(path, frames, fourcc="MJPG"):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 10, (W, H))
    if not writer.isOpened():
        pytest.skip(f"OpenCV has no {fourcc} writer here")
    rng = np.random.default_rng(len(frames))
    for level in frames:
        img = np.clip(rng.normal(level, 30, (H, W, 3)), 0, 255).astype(np.uint8)  # texture: a JPEG of some size
        writer.write(img)
    writer.release()
    return path


def _listing(folder):
    return sorted(p.name for p in folder.iterdir() if not p.name.startswith("."))


# ---- 4. mixed sizes ------------------------------------------------------------------------------------------
def test_a_resampled_model_is_said_for_every_size_that_needs_it(tmp_path):
    models = _models(tmp_path)
    folder = tmp_path / "in"
    folder.mkdir()
    for name, (h, w) in {"a": (H, W), "b": (H, W), "c": (2 * H, 2 * W), "d": (2 * H, 2 * W), "e": (H // 2, W // 2)}\
            .items():
        cv2.imwrite(str(folder / f"{name}.png"), np.full((h, w, 3), 100, np.uint8))
    result = _correct(folder, models, tmp_path / "out")
    assert result.exit_code == 0, result.output
    notes = [line for line in result.output.splitlines() if "is resampled" in line]
    assert len(notes) == 2, notes
    assert f"{2 * W}x{2 * H}" in notes[0] and "c.png" in notes[0]
    assert f"{W // 2}x{H // 2}" in notes[1] and "e.png" in notes[1]


# ---- 2. a truncated video ------------------------------------------------------------------------------------
def test_a_truncated_video_is_said_and_its_partial_last_frame_not_written(tmp_path, caplog):
    models = _models(tmp_path)
    whole = _video(tmp_path / "whole.avi", [40 + 15 * i for i in range(10)])
    data = whole.read_bytes()
    half = tmp_path / "half.avi"
    half.write_bytes(data[:len(data) // 2])
    cap = cv2.VideoCapture(str(half))
    declared, decoded = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0
    while cap.read()[0]:
        decoded += 1
    cap.release()
    assert declared == 10 and 0 < decoded < 10, (declared, decoded)  # the case: OpenCV reads a part, no error
    assert _correct(whole, models, tmp_path / "whole").exit_code == 0
    with caplog.at_level(logging.WARNING):
        result = _correct(half, models, tmp_path / "half")
    assert result.exit_code == 0, result.output
    said = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert any(str(half) in m and "10" in m and str(decoded) in m for m in said), said
    written = _listing(tmp_path / "half")
    assert written == [f"frame_{i:06d}.png" for i in range(decoded - 1)]   # the last decoded one left out
    for name in written:   # the frames kept are those of the intact file, byte for byte
        assert (tmp_path / "half" / name).read_bytes() == (tmp_path / "whole" / name).read_bytes()
    assert f"wrote {decoded - 1} corrected images" in result.output


def test_an_intact_video_keeps_its_last_frame(tmp_path, caplog):
    models = _models(tmp_path)
    clip = _video(tmp_path / "clip.avi", [50, 100, 150])
    with caplog.at_level(logging.WARNING):
        result = _correct(clip, models, tmp_path / "out")
    assert result.exit_code == 0 and "wrote 3 corrected images" in result.output, result.output
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "declares" in r.getMessage()]


# ---- 1. --force over an earlier, longer video ----------------------------------------------------------------
def test_force_over_a_longer_video_leaves_only_this_runs_frames(tmp_path):
    models = _models(tmp_path)
    long = _video(tmp_path / "long.avi", [60 + 10 * i for i in range(6)])
    short = _video(tmp_path / "short.avi", [200, 190, 180])
    out = tmp_path / "out"
    assert _correct(long, models, out).exit_code == 0
    (out / "notes.txt").write_text("mine")
    (out / "frame_7.png").write_bytes(b"not correct's name pattern")
    result = _correct(short, models, out, "--force")
    assert result.exit_code == 0, result.output
    assert _listing(out) == ["frame_000000.png", "frame_000001.png", "frame_000002.png", "frame_7.png", "notes.txt"]
    assert (out / "notes.txt").read_text() == "mine"
    assert "frame_000003.png" in result.output and "frame_000005.png" in result.output  # the removal is said
    record = json.loads((out / ".radiomap-correct.json").read_text())
    assert sorted(record["files"]) == ["frame_000000.png", "frame_000001.png", "frame_000002.png"]


def test_force_over_a_folder_run_removes_its_recorded_outputs_only(tmp_path):
    models = _models(tmp_path)
    first, second = tmp_path / "first", tmp_path / "second"
    first.mkdir()
    second.mkdir()
    for name in ("a", "b", "c"):
        cv2.imwrite(str(first / f"{name}.png"), np.full((H, W, 3), 120, np.uint8))
    cv2.imwrite(str(second / "a.png"), np.full((H, W, 3), 90, np.uint8))
    out = tmp_path / "out"
    assert _correct(first, models, out).exit_code == 0
    cv2.imwrite(str(out / "d.png"), np.zeros((H, W, 3), np.uint8))  # the user's, written after the run
    assert _correct(first, models, out, "--irradiance").exit_code == 0   # no name collides: added, recorded too
    assert _listing(out) == ["a.npy", "a.png", "b.npy", "b.png", "c.npy", "c.png", "d.png"]
    result = _correct(second, models, out, "--force")
    assert result.exit_code == 0, result.output
    assert _listing(out) == ["a.png", "d.png"]
    assert int(cv2.imread(str(out / "a.png"))[H // 2, W // 2, 0]) == 90


def test_an_interrupted_forced_run_keeps_the_earlier_frames(tmp_path, monkeypatch):
    from radiometry import images

    models = _models(tmp_path)
    long = _video(tmp_path / "long.avi", [60 + 10 * i for i in range(5)])
    short = _video(tmp_path / "short.avi", [200, 190])
    out = tmp_path / "out"
    assert _correct(long, models, out).exit_code == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real, calls = images.write_image, []

    def interrupted(path, image, **kw):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(path, image, **kw)

    monkeypatch.setattr(images, "write_image", interrupted)
    result = _correct(short, models, out, "--force")
    assert result.exit_code != 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before

def test_force_over_frames_of_a_version_without_the_record_goes_by_their_name_pattern(tmp_path):
    """Outputs of a radiomap before the record (the audit's out_vid): a video run's ``frame_NNNNNN`` files."""
    models = _models(tmp_path)
    long = _video(tmp_path / "long.avi", [60 + 10 * i for i in range(5)])
    out = tmp_path / "out"
    assert _correct(long, models, out).exit_code == 0
    (out / ".radiomap-correct.json").unlink()
    (out / "frame_7.png").write_bytes(b"not correct's name pattern")
    (out / "shot.png").write_bytes(b"the user's")
    result = _correct(_video(tmp_path / "short.avi", [200, 190]), models, out, "--force")
    assert result.exit_code == 0, result.output
    assert _listing(out) == ["frame_000000.png", "frame_000001.png", "frame_7.png", "shot.png"]


# ---- 3. EXIF orientation -------------------------------------------------------------------------------------
def _jpeg_with_orientation(path, image_rgb, orientation):
    """A JPEG whose APP1 carries only the EXIF orientation tag (written by hand: no dependency)."""
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 98])
    assert ok
    tiff = b"II*\x00" + struct.pack("<I", 8) + struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, orientation,
                                                                                   0) + struct.pack("<I", 0)
    app1 = b"Exif\x00\x00" + tiff
    data = buf.tobytes()
    path.write_bytes(data[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + data[2:])
    return path


def test_exif_orientation_is_carried_to_the_png_and_said(tmp_path):
    from radiometry.images import exif_orientation

    models = _models(tmp_path)
    rng = np.random.default_rng(3)
    img = rng.integers(40, 200, (H, W, 3), dtype=np.uint8)
    src = _jpeg_with_orientation(tmp_path / "portrait.jpg", img, 6)
    assert exif_orientation(src) == 6
    result = _correct(src, models, tmp_path / "out")
    assert result.exit_code == 0, result.output
    png = tmp_path / "out" / "portrait.png"
    assert exif_orientation(png) == 6       # viewers turn it as they turn the original
    stored = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    assert stored.shape == (H, W, 3)        # corrected in the stored (sensor) pixel order
    assert "orientation 6" in result.output and "portrait.jpg" in result.output
    from PIL import Image   # an independent reader: Pillow (a dependency of matplotlib) sees the tag in the PNG
    with Image.open(png) as im:
        assert im.getexif().get(0x0112) == 6
    plain = _correct(_jpeg_with_orientation(tmp_path / "plain.jpg", img, 1), models, tmp_path / "out2")
    assert plain.exit_code == 0 and "EXIF orientation" not in plain.output
    assert exif_orientation(tmp_path / "out2" / "plain.png") == 1


def test_exif_orientation_of_irradiance_output_is_said(tmp_path):
    models = _models(tmp_path)
    img = np.full((H, W, 3), 100, np.uint8)
    src = _jpeg_with_orientation(tmp_path / "p.jpg", img, 8)
    result = _correct(src, models, tmp_path / "out", "--irradiance")
    assert result.exit_code == 0, result.output
    assert "orientation 8" in result.output and "p.jpg" in result.output and "rotate" in result.output
    assert np.load(tmp_path / "out" / "p.npy").shape == (H, W, 3)


def test_exif_orientation_of_files_that_declare_none_or_garbage_is_as_stored(tmp_path):
    from radiometry.images import exif_orientation

    img = np.full((H, W, 3), 100, np.uint8)
    for name, data in {"text.png": b"not an image", "short.jpg": b"\xff\xd8\xff\xe1\x00\x10Exif\x00\x00II*\x00",
                       "bad_order.jpg": None}.items():
        path = tmp_path / name
        if data is None:
            _jpeg_with_orientation(path, img, 6)
            path.write_bytes(path.read_bytes().replace(b"Exif\x00\x00II", b"Exif\x00\x00XX", 1))
        else:
            path.write_bytes(data)
        assert exif_orientation(path) == 1, name
    cv2.imwrite(str(tmp_path / "plain.png"), img)
    assert exif_orientation(tmp_path / "plain.png") == 1


# ---- 5. 16-bit input and --irradiance ------------------------------------------------------------------------
def test_sixteen_bit_input_keeps_its_precision_in_irradiance(tmp_path):
    models = _models(tmp_path, flat=True)
    values = np.linspace(3000, 60000, H * W).astype(np.uint16).reshape(H, W)
    img16 = np.repeat(values[:, :, None], 3, axis=2)
    src = tmp_path / "grad16.png"
    cv2.imwrite(str(src), img16)
    result = _correct(src, models, tmp_path / "out", "--irradiance")
    assert result.exit_code == 0, result.output
    irr = np.load(tmp_path / "out" / "grad16.npy")
    truth = CameraResponse.gamma(2.2).inverse(img16.astype(np.float32) / 257.0)  # f^-1 interpolated between levels
    np.testing.assert_allclose(irr, truth, rtol=1e-5)
    assert len(np.unique(irr[:, :, 0])) == len(np.unique(values))
    eight = _correct(src, models, tmp_path / "out8")
    assert eight.exit_code == 0 and "16-bit" in eight.output and "grad16.png" in eight.output, eight.output
