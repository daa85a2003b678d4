"""Image textures: the user's pictures pasted on the room's walls (``make_room(pictures=...)``,
``radiomap simulate room --picture``)."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest
from click.testing import CliRunner

from mapping.cli import cli
from mapping.simulation import Renderer, load_room, look_at, make_room
from mapping.simulation import textures as tx
from radiometry.errors import DatasetError, ImageError
from radiometry.images import write_image
from radiometry.simulation import default_intrinsics

# 2 x 3 blocks of distinct sRGB colours, black and white included
BLOCKS = np.array([[[0, 0, 0], [255, 255, 255], [255, 0, 0]],
                   [[0, 128, 255], [30, 200, 90], [250, 180, 20]]], np.uint8)
BLOCK_PX = 100


def block_picture(path, *, portrait: bool = False, blocks: np.ndarray = BLOCKS):
    """A (200, 300) RGB picture of 100-pixel blocks (transposed to (300, 200) when ``portrait``)."""
    img = np.repeat(np.repeat(blocks, BLOCK_PX, axis=0), BLOCK_PX, axis=1)
    if portrait:
        img = np.ascontiguousarray(img.transpose(1, 0, 2))
    write_image(path, img)
    return path


def expected_albedo(srgb: np.ndarray) -> np.ndarray:
    """sRGB codes -> linear light (IEC 61966-2-1), written out independently of the module, then mapped
    onto the room's albedo range."""
    c = np.asarray(srgb, np.float64) / 255.0
    linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return tx.ALBEDO_MIN + (tx.ALBEDO_MAX - tx.ALBEDO_MIN) * linear


def face_named(room, name):
    return [f for f in room.faces if f.name == name][0]


def block_interiors(pl, n_rows: int, n_cols: int, margin: int = 2):
    """(row slice, col slice) of each block's interior in the wall texture, keyed by (i, j)."""
    out = {}
    for i in range(n_rows):
        for j in range(n_cols):
            r0, r1 = pl.top + i * pl.height / n_rows, pl.top + (i + 1) * pl.height / n_rows
            c0, c1 = pl.left + j * pl.width / n_cols, pl.left + (j + 1) * pl.width / n_cols
            out[i, j] = (slice(int(np.ceil(r0)) + margin, int(np.floor(r1)) - margin),
                         slice(int(np.ceil(c0)) + margin, int(np.floor(c1)) - margin))
    return out


def test_albedo_range_is_the_rooms():
    assert 0.02 <= tx.ALBEDO_MIN < 0.05 and 0.85 < tx.ALBEDO_MAX <= 0.92


# ------------------------------------------------------------------------------------ texture
def test_picture_is_in_the_wall_texture_as_linear_albedo(tmp_path):
    path = block_picture(tmp_path / "blocks.png")
    plain = make_room(3, texel=0.01)
    room = make_room(3, texel=0.01, pictures=(str(path),))
    assert len(room.pictures) == 1
    pl = room.pictures[0]
    assert pl.path == str(path.resolve()) and pl.face.startswith("wall_")
    # longer side 0.5-1.0 m, aspect ratio kept (to a texel)
    assert 0.5 - 0.01 <= pl.width * 0.01 <= 1.0 + 0.01
    assert abs(pl.height - pl.width * 2 / 3) <= 1.0
    wall = face_named(room, pl.face).texture
    assert pl.top >= 0 and pl.left >= 0 and pl.top + pl.height <= wall.shape[0] - 8    # above the skirting
    assert pl.left + pl.width <= wall.shape[1]
    for (i, j), (rows, cols) in block_interiors(pl, 2, 3).items():
        patch = wall[rows, cols]
        assert patch.shape[0] >= 5 and patch.shape[1] >= 5
        np.testing.assert_allclose(patch, np.broadcast_to(expected_albedo(BLOCKS[i, j]), patch.shape),
                                   atol=5e-5, err_msg=f"block {i, j}")
    assert wall.min() >= tx.ALBEDO_MIN and wall.max() <= tx.ALBEDO_MAX
    # nothing else in the room changed: same geometry, same textures outside the picture
    assert room.checksum(textures=False) == plain.checksum(textures=False)
    outside = np.ones(wall.shape[:2], bool)
    outside[pl.top:pl.top + pl.height, pl.left:pl.left + pl.width] = False
    np.testing.assert_array_equal(wall[outside], face_named(plain, pl.face).texture[outside])
    for a, b in zip(room.faces, plain.faces):
        if a.name != pl.face:
            np.testing.assert_array_equal(a.texture, b.texture)


def test_picture_textures_handle_grey_portrait_and_enlargement():
    grey = np.array([[0, 255], [128, 64]], np.uint8)
    big = tx.picture(grey, 20, 20)                     # enlarged, bilinear
    assert big.shape == (20, 20, 3) and big.dtype == np.float32
    np.testing.assert_array_equal(big[..., 0], big[..., 2])
    np.testing.assert_allclose(big[0, 0], expected_albedo(0), atol=5e-5)
    np.testing.assert_allclose(big[0, -1], expected_albedo(255), atol=5e-5)
    # shrinking is an average in linear light, not of the sRGB codes
    halves = np.zeros((2, 4, 3), np.uint8)
    halves[:, ::2] = 255
    mean = tx.picture(halves, 1, 2)
    np.testing.assert_allclose(mean, (expected_albedo(0) + expected_albedo(255)) / 2, atol=5e-5)
    assert abs(float(mean[0, 0, 0]) - float(expected_albedo(128))) > 0.2
    with pytest.raises(ValueError, match="rgb must be uint8"):
        tx.picture(np.zeros((4, 4, 3), np.float32), 2, 2)
    with pytest.raises(ValueError, match="at least 1 texel"):
        tx.picture(grey, 0, 2)


def test_portrait_picture_keeps_its_orientation(tmp_path):
    path = block_picture(tmp_path / "portrait.png", portrait=True)
    room = make_room(1, size=(3.2, 3.2, 2.2), texel=0.01, n_boxes=0, pictures=[path])
    pl = room.pictures[0]
    assert pl.height > pl.width and abs(pl.width - pl.height * 2 / 3) <= 1.0
    wall = face_named(room, pl.face).texture
    blocks_t = BLOCKS.transpose(1, 0, 2)
    for (i, j), (rows, cols) in block_interiors(pl, 3, 2).items():
        np.testing.assert_allclose(wall[rows, cols].reshape(-1, 3).mean(0), expected_albedo(blocks_t[i, j]),
                                   atol=5e-5)


# ------------------------------------------------------------------------------------ rendering
def test_rendered_frame_shows_the_picture(tmp_path):
    path = block_picture(tmp_path / "blocks.png")
    room = make_room(5, size=(4.0, 4.0, 2.5), texel=0.01, n_boxes=0, pictures=[path])
    pl = room.pictures[0]
    face_id = [k for k, f in enumerate(room.faces) if f.name == pl.face][0]
    face = room.faces[face_id]
    th, tw = face.texture.shape[:2]

    def world(row: float, col: float) -> np.ndarray:
        """Centre of texel (row, col): row 0 is the top of the face (highest t)."""
        s = (col + 0.5) * face.size[0] / tw
        t = face.size[1] - (row + 0.5) * face.size[1] / th
        return face.origin + s * face.axis_s + t * face.axis_t

    centre = world(pl.top + pl.height / 2 - 0.5, pl.left + pl.width / 2 - 0.5)
    eye = centre + 1.5 * face.normal
    assert np.all(eye > 0.2) and np.all(eye < np.array(room.size) - 0.2)
    W, H = 160, 120
    K = default_intrinsics(W, H)
    renderer = Renderer(room, K, W, H)
    pose = look_at(eye, centre)
    r = renderer.render(pose)
    shading = []
    for (i, j), (rows, cols) in block_interiors(pl, 2, 3).items():
        p = world((rows.start + rows.stop - 1) / 2, (cols.start + cols.stop - 1) / 2)
        (u, v), = renderer.project(p[None], pose)[0]
        x, y = int(round(u)), int(round(v))
        assert 0 <= x < W and 0 <= y < H
        assert r.face[y, x] == face_id
        want = expected_albedo(BLOCKS[i, j])
        np.testing.assert_allclose(r.albedo[y, x], want, atol=2e-4, err_msg=f"block {i, j}")
        shading.append(r.radiance[y, x] / want)
    shading = np.array(shading)
    # the radiance carries the picture: divided by its albedo, what is left is the smooth light
    assert shading.max() / shading.min() < 1.3


# ------------------------------------------------------------------------------------ persistence
def test_room_json_records_pictures_and_rebuilds_the_room(tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)
    block_picture(tmp_path / "blocks.png")
    room = make_room(2, size=(3.2, 3.2, 2.2), texel=0.01, pictures=("blocks.png",))
    saved = room.save(tmp_path / "room.json")
    data = json.loads(saved.read_text())
    assert data["params"]["pictures"] == [str(tmp_path / "blocks.png")]
    assert data["pictures"][0]["face"] == room.pictures[0].face and len(data["pictures"][0]["sha1"]) == 40
    monkeypatch.chdir("/")                                   # the absolute path still finds it
    with caplog.at_level(logging.WARNING, logger="mapping.simulation.room"):
        again = load_room(saved)
    assert not caplog.records
    assert again.checksum() == room.checksum() and again.pictures == room.pictures
    # the picture changed since: the texture checksum warning names it
    block_picture(tmp_path / "blocks.png", blocks=BLOCKS[:, ::-1])
    with caplog.at_level(logging.WARNING, logger="mapping.simulation.room"):
        changed = load_room(saved)
    assert changed.checksum(textures=False) == room.checksum(textures=False)
    assert changed.checksum() != room.checksum()
    assert "textures differ" in caplog.text and str(tmp_path / "blocks.png") in caplog.text
    # the picture is gone: one line naming room.json and the picture
    (tmp_path / "blocks.png").unlink()
    with pytest.raises(DatasetError) as err:
        load_room(saved)
    msg = str(err.value)
    assert "\n" not in msg and str(saved) in msg and str(tmp_path / "blocks.png") in msg
    assert "no such picture" in msg


def test_missing_and_corrupt_pictures_are_one_line_errors(tmp_path):
    missing = tmp_path / "nope.png"
    with pytest.raises(ImageError, match="no such picture") as err:
        make_room(0, texel=0.02, pictures=[missing])
    assert str(missing) in str(err.value) and "\n" not in str(err.value) and "--picture" in str(err.value)
    garbage = tmp_path / "garbage.png"
    garbage.write_bytes(b"this is not an image at all" * 10)
    truncated = block_picture(tmp_path / "truncated.png")
    truncated.write_bytes(truncated.read_bytes()[:200])
    for bad in (garbage, truncated):
        with pytest.raises(ImageError) as err:
            make_room(0, texel=0.02, pictures=[bad])
        msg = str(err.value)
        assert str(bad) in msg and "room picture" in msg and "\n" not in msg
        assert "replace it" in msg
    with pytest.raises(ValueError, match="single path"):
        make_room(0, pictures=str(missing))
    with pytest.raises(ValueError, match="sequence of image paths"):
        make_room(0, pictures=[3])


# ------------------------------------------------------------------------------------ CLI
def run(*args: str):
    return CliRunner().invoke(cli, ["simulate", *args], catch_exceptions=False)


@pytest.mark.slow
def test_cli_picture_end_to_end(tmp_path):
    pic = block_picture(tmp_path / "blocks.png")
    out = tmp_path / "seq"
    res = run("room", "-o", str(out), "--seed", "2", "--num-frames", "2", "--width", "64", "--height", "48",
              "--no-progress", "--picture", str(pic), "--picture", str(pic))
    assert res.exit_code == 0, res.output
    data = json.loads((out / "truth" / "room.json").read_text())
    assert data["params"]["pictures"] == [str(pic)] * 2
    room = load_room(out / "truth" / "room.json")
    assert len(room.pictures) == 2
    for pl in room.pictures:
        wall = face_named(room, pl.face).texture
        (rows, cols) = block_interiors(pl, 2, 3)[0, 1]
        np.testing.assert_allclose(wall[rows, cols].reshape(-1, 3).mean(0), expected_albedo(BLOCKS[0, 1]),
                                   atol=5e-5)
    assert len(list((out / "rgb").glob("*.png"))) == 2
    # errors: a missing picture is one line, exit 1, and leaves no output folder
    res = run("room", "-o", str(tmp_path / "bad"), "--num-frames", "1", "--width", "64", "--height", "48",
              "--no-progress", "--picture", str(tmp_path / "missing.png"))
    assert res.exit_code == 1
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and "no such picture" in lines[0] and str(tmp_path / "missing.png") in lines[0]
    assert not (tmp_path / "bad").exists()
    res = run("paper", "-o", str(tmp_path / "p"), "--picture", str(pic))
    assert res.exit_code == 2 and "--picture are for 'room'" in res.output
    assert "--picture" in run("--help").output
