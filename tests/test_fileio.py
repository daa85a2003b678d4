"""The file boundary: RGB order, depth units, atomic writes that never leave half files."""

from __future__ import annotations

import errno
import os

import cv2
import numpy as np
import pytest

from radiometry import fileio
from radiometry.errors import ImageError, OutputError


def test_read_rgb_converts_from_bgr(tmp_path):
    img = np.zeros((4, 6, 3), np.uint8)
    img[..., 0] = 200  # red in RGB
    fileio.write_image(tmp_path / "a.png", img)
    on_disk = cv2.imread(str(tmp_path / "a.png"))
    assert on_disk[0, 0, 2] == 200 and on_disk[0, 0, 0] == 0  # OpenCV sees it as BGR
    back = fileio.read_rgb(tmp_path / "a.png")
    np.testing.assert_array_equal(back, img)


def test_read_rgb_errors_name_the_file(tmp_path):
    with pytest.raises(ImageError, match="missing.png: no such image"):
        fileio.read_rgb(tmp_path / "missing.png")
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(ImageError, match="empty.png: empty file"):
        fileio.read_rgb(empty)
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8 not really a jpeg")
    with pytest.raises(ImageError, match="bad.jpg: cannot decode"):
        fileio.read_rgb(bad)
    good = tmp_path / "good.png"
    fileio.write_image(good, np.full((64, 64, 3), 7, np.uint8))
    trunc = tmp_path / "trunc.png"
    trunc.write_bytes(good.read_bytes()[:40])
    with pytest.raises(ImageError, match="trunc.png"):
        fileio.read_rgb(trunc)


def test_depth_round_trip_metres(tmp_path):
    depth = np.array([[0.0, 0.5, 1.2345], [3.0, 10.0, 0.0]], np.float32)
    fileio.write_depth(tmp_path / "d.png", depth, 5000)
    back = fileio.read_depth(tmp_path / "d.png", 5000)
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, depth, atol=1 / 5000)
    with pytest.raises(ValueError, match="depth scale"):
        fileio.read_depth(tmp_path / "d.png", 0)
    fileio.write_image(tmp_path / "rgb.png", np.zeros((2, 3, 3), np.uint8))
    with pytest.raises(ImageError, match="channels"):
        fileio.read_depth(tmp_path / "rgb.png", 1000)


def test_atomic_write_keeps_old_file_on_failure(tmp_path):
    target = tmp_path / "model.txt"
    target.write_text("good")
    with pytest.raises(RuntimeError):
        with fileio.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash in the middle")
    assert target.read_text() == "good"
    assert [p.name for p in tmp_path.iterdir()] == ["model.txt"]  # no temporary left behind


def test_atomic_write_disk_full_is_one_clear_error(tmp_path, monkeypatch):
    target = tmp_path / "m.json"
    target.write_text("{}")

    def full(*_a, **_k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "replace", full)
    with pytest.raises(OutputError, match="disk is full"):
        fileio.atomic_write_json(target, {"a": 1})
    assert target.read_text() == "{}"


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere; permission errors cannot be provoked")
def test_unwritable_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    with pytest.raises(OutputError, match="permission denied"):
        fileio.atomic_write_text(ro / "x.txt", "x")


def test_output_folder_that_is_a_file(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputError, match="is an existing file"):
        fileio.ensure_dir(f)
    with pytest.raises(OutputError):
        fileio.atomic_write_text(f / "inner.txt", "x")


def test_check_overwrite(tmp_path):
    p = tmp_path / "crf.npz"
    fileio.check_overwrite(p, force=False)
    p.write_bytes(b"x")
    with pytest.raises(OutputError, match="--force"):
        fileio.check_overwrite(p, force=False)
    fileio.check_overwrite(p, force=True)


def test_list_images_sorted(tmp_path):
    for name in ("b.png", "a.jpg", "c.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in fileio.list_images(tmp_path)] == ["a.jpg", "b.png"]
    with pytest.raises(ImageError, match="no such folder"):
        fileio.list_images(tmp_path / "nope")


def test_atomic_files_follow_umask(tmp_path):
    path = fileio.atomic_write_text(tmp_path / "x.txt", "x")
    assert path.stat().st_mode & 0o777 == 0o666 & ~fileio._UMASK
