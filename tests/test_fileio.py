"""The file boundary: RGB order, depth units, atomic writes that never leave half files."""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from radiometry import arrays, fileio, images
from radiometry.errors import ImageError, OutputError


def test_read_rgb_converts_from_bgr(tmp_path):
    img = np.zeros((4, 6, 3), np.uint8)
    img[..., 0] = 200  # red in RGB
    images.write_image(tmp_path / "a.png", img)
    on_disk = cv2.imread(str(tmp_path / "a.png"))
    assert on_disk[0, 0, 2] == 200 and on_disk[0, 0, 0] == 0  # OpenCV sees it as BGR
    back = images.read_rgb(tmp_path / "a.png")
    np.testing.assert_array_equal(back, img)


def test_read_rgb_errors_name_the_file(tmp_path):
    with pytest.raises(ImageError, match="missing.png: no such image"):
        images.read_rgb(tmp_path / "missing.png")
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    with pytest.raises(ImageError, match="empty.png: empty file"):
        images.read_rgb(empty)
    bad = tmp_path / "bad.jpg"
    bad.write_bytes(b"\xff\xd8 not really a jpeg")
    with pytest.raises(ImageError, match="bad.jpg: cannot decode"):
        images.read_rgb(bad)
    good = tmp_path / "good.png"
    images.write_image(good, np.full((64, 64, 3), 7, np.uint8))
    trunc = tmp_path / "trunc.png"
    trunc.write_bytes(good.read_bytes()[:40])
    with pytest.raises(ImageError, match="trunc.png"):
        images.read_rgb(trunc)


def test_depth_round_trip_metres(tmp_path):
    depth = np.array([[0.0, 0.5, 1.2345], [3.0, 10.0, 0.0]], np.float32)
    images.write_depth(tmp_path / "d.png", depth, 5000)
    back = images.read_depth(tmp_path / "d.png", 5000)
    assert back.dtype == np.float32
    np.testing.assert_allclose(back, depth, atol=1 / 5000)
    with pytest.raises(ValueError, match="depth scale"):
        images.read_depth(tmp_path / "d.png", 0)
    images.write_image(tmp_path / "rgb.png", np.zeros((2, 3, 3), np.uint8))
    with pytest.raises(ImageError, match="channels"):
        images.read_depth(tmp_path / "rgb.png", 1000)


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
    assert [p.name for p in images.list_images(tmp_path)] == ["a.jpg", "b.png"]
    with pytest.raises(ImageError, match="no such folder"):
        images.list_images(tmp_path / "nope")


def test_atomic_files_follow_umask(tmp_path):
    path = fileio.atomic_write_text(tmp_path / "x.txt", "x")
    assert path.stat().st_mode & 0o777 == 0o666 & ~fileio._UMASK


# --------------------------------------------------------------------------------------------------
# model arrays must hold real numbers (bool, integer, float): one check for every loader
# --------------------------------------------------------------------------------------------------
BAD_DTYPES = {
    "complex": (lambda a: a.astype(np.complex128) + 1e-3j, "complex values (complex128)"),
    "object": (lambda a: a.astype(object), "pickled Python-object values (object)"),
    "string": (lambda a: a.astype(str), "text values (<U"),
    "structured": (lambda a: np.array([(v,) for v in a.ravel()], dtype=[("v", "f8")]).reshape(a.shape),
                   "structured values ([('v', '<f8')])"),
}


def _models(tmp_path):
    """One valid file per model type: (path, the array to spoil, loader)."""
    from radiometry.formats import load_response, load_vignetting
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting, PolynomialVignetting

    CameraResponse.gamma(2.2).save(tmp_path / "response.npz")
    LUTVignetting(np.full((6, 8, 3), 0.9, np.float32)).save(tmp_path / "lut.npz")
    PolynomialVignetting(np.array([[-0.3, 0.0, 0.0]] * 3), np.array([[3.5, 2.5]] * 3), (8, 6)).save(tmp_path / "poly.npz")
    return {"response": (tmp_path / "response.npz", "inverse_table", load_response),
            "lut": (tmp_path / "lut.npz", "lut", load_vignetting),
            "poly-coefficients": (tmp_path / "poly.npz", "coefficients", load_vignetting),
            "poly-centres": (tmp_path / "poly.npz", "centres", load_vignetting)}


@pytest.mark.parametrize("bad", sorted(BAD_DTYPES))
@pytest.mark.parametrize("model", ["response", "lut", "poly-coefficients", "poly-centres"])
def test_model_files_refuse_arrays_that_are_not_real_numbers(tmp_path, model, bad):
    """A response, LUT or polynomial .npz whose array is complex, object, text or structured is one clear
    error naming the file and the array; no numpy warning (complex used to load, imaginary part dropped)."""
    import warnings

    from radiometry.errors import CalibrationFileError

    good, key, loader = _models(tmp_path)[model]
    loader(good)  # the valid file loads
    with np.load(good, allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    spoil, message = BAD_DTYPES[bad]
    arrays[key] = spoil(arrays[key])
    path = tmp_path / f"bad_{bad}.npz"
    np.savez(path, **arrays)  # object arrays are pickled into the archive
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a ComplexWarning would fail here
        with pytest.raises(CalibrationFileError) as info:
            loader(path)
    text = str(info.value)
    assert text.startswith(f"{path}: array '{key}' holds {message}") and "\n" not in text
    assert text.endswith("are needed; re-create the " + ("response" if model == "response" else "vignetting")
                         + " file with radiomap")


@pytest.mark.parametrize("bad", sorted(BAD_DTYPES))
def test_vignetting_array_npy_refuses_arrays_that_are_not_real_numbers(tmp_path, bad):
    from radiometry.api import read_vignetting
    from radiometry.errors import CalibrationFileError

    good = np.full((6, 8, 3), 0.9)
    np.save(tmp_path / "good.npy", good)
    assert read_vignetting(tmp_path / "good.npy").resolution == (8, 6)
    spoil, message = BAD_DTYPES[bad]
    path = tmp_path / f"{bad}.npy"
    np.save(path, spoil(good), allow_pickle=True)
    with pytest.raises(CalibrationFileError) as info:
        read_vignetting(path)
    assert str(info.value).startswith(f"{path}: holds {message}")
    assert str(info.value).endswith("pass a float (H, W[, C]) .npy with finite V > 0")


def test_real_dtypes_of_every_kind_are_accepted(tmp_path):
    """bool, signed/unsigned integers and floats of any width are numbers: a uint16 or float16 V loads."""
    from radiometry.api import read_vignetting

    for dtype in (np.uint8, np.int32, np.uint16, np.float16, np.float64):
        np.save(tmp_path / "v.npy", np.ones((6, 8), dtype))
        assert read_vignetting(tmp_path / "v.npy").channels == 1
    arrays.check_real_arrays("x.npz", {"a": np.dtype(bool), "b": np.dtype(">i8"), "c": np.dtype("<f4")}, "fix")


def test_array_file_errors_name_the_file(tmp_path):
    from radiometry.errors import CalibrationFileError

    with pytest.raises(CalibrationFileError, match=r"missing.npy: no such file; FIX$"):
        arrays.load_array_file(tmp_path / "missing.npy", fix="FIX")
    np.savez(tmp_path / "two.npy", a=np.ones(3), b=np.ones(3))  # numpy writes two.npy.npz; rename it
    os.replace(tmp_path / "two.npy.npz", tmp_path / "two.npy")
    with pytest.raises(CalibrationFileError, match=r"two.npy: an .npz archive of several arrays, not one .npy"):
        arrays.load_array_file(tmp_path / "two.npy", fix="FIX")
    (tmp_path / "text.npy").write_text("not numpy")
    with pytest.raises(CalibrationFileError, match=r"text.npy: not a NumPy .npy array or corrupt \(ValueError\); FIX"):
        arrays.load_array_file(tmp_path / "text.npy", fix="FIX")


def test_complex_response_through_the_cli_is_one_line(tmp_path):
    """`radiomap correct -r` with a complex response: exit 1, one line, no output folder."""
    from click.testing import CliRunner

    from mapping.cli import cli
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting

    CameraResponse.gamma(2.2).save(tmp_path / "r.npz")
    with np.load(tmp_path / "r.npz", allow_pickle=False) as data:
        arrays = {name: data[name] for name in data.files}
    arrays["inverse_table"] = arrays["inverse_table"] + 0j
    np.savez(tmp_path / "complex.npz", **arrays)
    (tmp_path / "in").mkdir()
    images.write_image(tmp_path / "in" / "a.png", np.full((6, 8, 3), 100, np.uint8))
    LUTVignetting(np.full((6, 8, 3), 0.9, np.float32)).save(tmp_path / "v.npz")
    result = CliRunner().invoke(cli, ["correct", str(tmp_path / "in"), "--response", str(tmp_path / "complex.npz"),
                                      "--vignetting", str(tmp_path / "v.npz"), "-o", str(tmp_path / "out")])
    assert result.exit_code == 1, result.output
    assert result.output.strip().splitlines() == [
        f"radiomap: error: {tmp_path / 'complex.npz'}: array 'inverse_table' holds complex values (complex128) where "
        "real numbers (bool, integer or float) are needed; re-create the response file with radiomap"]
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------------------------------
# publication of a set (a calibration and its companions) and output collisions
# --------------------------------------------------------------------------------------------------
def _set(folder, tag):
    with fileio.publish_set(folder / "m.npz") as fs:
        for name in ("a.json", "m.npz", "b.png"):
            fileio.atomic_write_text(fs.path(folder / name), f"{tag} {name}")
    return fs


def test_publish_set_renames_the_model_last(tmp_path, monkeypatch):
    _set(tmp_path, "old")
    order, replace = [], os.replace
    monkeypatch.setattr(os, "replace", lambda a, b: (order.append(Path(b)), replace(a, b))[1])
    _set(tmp_path, "new")
    published = [p.name for p in order if p.parent == tmp_path]        # not the writes into the staging folder
    assert published[-1] == "m.npz" and sorted(published) == ["a.json", "b.png", "m.npz"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.png", "m.npz"]
    assert (tmp_path / "a.json").read_text() == "new a.json"


def test_a_journal_left_by_a_killed_publication_is_rolled_back(tmp_path):
    """A process killed half-way through the renames: its staging folder holds the journal and the backups; the
    next run in the folder puts the old set back and removes the staging folder."""
    _set(tmp_path, "old")
    dead = 2 ** 22 + 777                                                   # above pid_max: not running
    stage = tmp_path / f"{fileio.TEMP_TAG}{dead}-abc"
    (stage / ".radiomap-old").mkdir(parents=True)
    for name in ("a.json", "m.npz"):
        os.link(tmp_path / name, stage / ".radiomap-old" / name)
    (stage / "m.npz").write_text("new m.npz")                             # not renamed yet
    (tmp_path / "a.json").unlink()
    (tmp_path / "a.json").write_text("new a.json")                        # renamed already
    (tmp_path / "c.txt").write_text("new c.txt")                          # a file the new set added
    (stage / ".radiomap-journal.json").write_text(json.dumps(
        {"pid": dead, "files": [["c.txt", False], ["a.json", True], ["m.npz", True]]}))
    assert fileio.remove_strays(tmp_path) == [stage.name]
    assert {p.name: p.read_text() for p in tmp_path.iterdir()} == {"a.json": "old a.json", "b.png": "old b.png",
                                                                   "m.npz": "old m.npz"}


def test_check_outputs_names_the_first_collision(tmp_path):
    for name in ("a.png", "a.jpg"):
        (tmp_path / name).write_text("x")
    fix = {"fix_input": "FIX-IN", "fix_shared": "FIX-SHARED"}
    with pytest.raises(OutputError, match=r"a\.png is the input .*a\.png: writing it would overwrite the original; "
                                          "FIX-IN$"):
        fileio.check_outputs([(tmp_path / "a.png", tmp_path / "a.png")], **fix)
    with pytest.raises(OutputError, match=r"a\.jpg and .*b/a\.jpg would both be written to .*out/a\.png .*FIX-SHARED$"):
        fileio.check_outputs([(tmp_path / "a.jpg", tmp_path / "out" / "a.png"),
                              (tmp_path / "b" / "a.jpg", tmp_path / "out" / "a.png")], **fix)
    fileio.check_outputs([(tmp_path / "a.jpg", tmp_path / "a2.png"), (tmp_path / "a.png", tmp_path / "o.png")], **fix)


@pytest.mark.parametrize("name", ["v.npy", "v.npz"])  # a bare array, also under a model's name
def test_a_bare_npy_array_where_a_model_file_is_needed(tmp_path, name):
    """np.load returns the array itself for a .npy: it used to end in "TypeError: 'numpy.ndarray' object does not
    support the context manager protocol" in load_model_file (responses, vignetting models, histograms)."""
    from mapping.histogram import DisagreementHistogram
    from radiometry.errors import CalibrationFileError
    from radiometry.response import CameraResponse
    from radiometry.vignetting import VignettingModel

    path = tmp_path / name
    with open(path, "wb") as fh:
        np.save(fh, np.full((6, 8, 3), 0.9, np.float32))
    texts = {}
    loaders = [(CameraResponse.load, "response"), (VignettingModel.load, "vignetting")]
    if name.endswith(".npz"):  # a histogram is read by its suffix: .npz as a model file, else as JSON
        loaders.append((DisagreementHistogram.load, "disagreement-histogram"))
    for load, kind in loaders:
        with pytest.raises(CalibrationFileError) as info:
            load(path)
        texts[kind] = str(info.value)
        assert texts[kind].startswith(f"{path}: a bare .npy array, not a radiomap {kind} model file; pass the {kind} "
                                      ".npz that radiomap wrote") and "\n" not in texts[kind]
    hint = "a V array is read from a .npy file by reconstruct/correct --vignetting and compare --vignetting-lut"
    assert hint in texts["vignetting"] and hint not in texts["response"]


def test_load_model_file_refuses_whatever_np_load_returns_that_is_not_an_archive(tmp_path, monkeypatch):
    """The magic-bytes check aside, anything np.load returns that is not an NpzFile is refused by name."""
    from radiometry.errors import CalibrationFileError
    from radiometry.response import CameraResponse

    path = CameraResponse.gamma(2.2).save(tmp_path / "crf.npz")
    monkeypatch.setattr(np, "load", lambda *a, **k: np.zeros(3))
    with pytest.raises(CalibrationFileError, match="crf.npz: a bare .npy array, not a radiomap response model file"):
        fileio.load_model_file(path, "response")
