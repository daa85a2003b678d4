"""GLB colours follow glTF 2.0: COLOR_0 is linear, so the display (sRGB) colours of the PLY are stored decoded.

The GLB is parsed here without a glTF library (header, JSON chunk, BIN chunk, accessors), so the test checks
the bytes a viewer reads, not what a loader makes of them."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from mapping.export import write_mesh


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear light in [0, 1] -> sRGB-encoded [0, 1] (IEC 61966-2-1), written out here independently."""
    v = np.asarray(linear, dtype=np.float64)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(np.maximum(v, 0.0), 1 / 2.4) - 0.055)


def read_glb(path) -> tuple[dict, dict[str, np.ndarray]]:
    """(the glTF JSON, {attribute name or 'indices': array}) of a single-primitive GLB."""
    data = path.read_bytes()
    magic, version, length = struct.unpack_from("<III", data, 0)
    assert (magic, version, length) == (0x46546C67, 2, len(data))
    json_len, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0
    doc = json.loads(data[20:20 + json_len])
    bin_len, bin_type = struct.unpack_from("<II", data, 20 + json_len)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0
    blob = data[28 + json_len:28 + json_len + bin_len]
    assert doc["buffers"][0]["byteLength"] <= bin_len
    dtypes = {5126: "<f4", 5125: "<u4", 5123: "<u2", 5121: "u1"}
    widths = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}

    def accessor(index: int) -> np.ndarray:
        acc = doc["accessors"][index]
        view = doc["bufferViews"][acc["bufferView"]]
        start = view.get("byteOffset", 0) + acc.get("byteOffset", 0)
        assert start % 4 == 0 and "byteStride" not in view
        arr = np.frombuffer(blob, dtype=dtypes[acc["componentType"]], count=acc["count"] * widths[acc["type"]],
                            offset=start)
        return arr.reshape(acc["count"], widths[acc["type"]]) if widths[acc["type"]] > 1 else arr

    (primitive,) = doc["meshes"][0]["primitives"]
    arrays = {name: accessor(i) for name, i in primitive["attributes"].items()}
    arrays["indices"] = accessor(primitive["indices"])
    return doc, arrays


@pytest.fixture
def mesh(tmp_path):
    """A strip of triangles whose vertex colours cover every display level in every channel."""
    rng = np.random.default_rng(3)
    n = 256
    vertices = np.stack([np.arange(n) * 0.01, (np.arange(n) % 2) * 0.01, np.zeros(n)], axis=1).astype(np.float32)
    triangles = np.stack([np.arange(n - 2), np.arange(1, n - 1), np.arange(2, n)], axis=1)
    levels = np.stack([np.arange(n), rng.permutation(n), n - 1 - np.arange(n)], axis=1)
    colours = (levels / 255.0).astype(np.float32)  # map units; to_display below turns them into 0..255
    normals = np.tile([0.0, 0.0, 2.0], (n, 1))  # not unit length: the GLB must normalise them
    files = write_mesh(tmp_path, vertices, triangles, colours, lambda c: c * 255.0, normals=normals,
                       formats=("ply", "glb"))
    return {"files": files, "vertices": vertices, "triangles": triangles, "levels": levels}


def test_glb_colours_are_the_ply_colours_linearised(mesh):
    import trimesh

    ply = trimesh.load(mesh["files"]["mesh_ply"], process=False)
    ply_rgb = np.asarray(ply.visual.vertex_colors)[:, :3].astype(np.float64)
    np.testing.assert_array_equal(ply_rgb, mesh["levels"])  # the PLY holds the display bytes
    doc, arrays = read_glb(mesh["files"]["mesh_glb"])
    colour = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["COLOR_0"]]
    assert colour["componentType"] == 5126 and colour["type"] == "VEC3"  # float linear values
    linear = arrays["COLOR_0"].astype(np.float64)
    assert linear.min() >= 0.0 and linear.max() <= 1.0
    back = 255.0 * srgb_encode(linear)  # through the sRGB transfer function, as a viewer shows them
    assert np.abs(back - ply_rgb).max() <= 1.0
    assert np.abs(back - ply_rgb).max() < 1e-3  # float32 keeps them exact, in fact
    # linear, not the display bytes: mid grey 128 is stored as 0.216, not 0.502
    assert linear[128, 0] == pytest.approx(0.2158605, abs=1e-6)


def test_glb_geometry_and_material(mesh):
    doc, arrays = read_glb(mesh["files"]["mesh_glb"])
    np.testing.assert_array_equal(arrays["POSITION"], mesh["vertices"])
    np.testing.assert_array_equal(arrays["indices"].reshape(-1, 3), mesh["triangles"])
    np.testing.assert_allclose(arrays["NORMAL"], np.tile([0.0, 0.0, 1.0], (256, 1)))
    position = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    np.testing.assert_allclose(position["min"], mesh["vertices"].min(axis=0))
    np.testing.assert_allclose(position["max"], mesh["vertices"].max(axis=0))
    (material,) = doc["materials"]
    assert material["pbrMetallicRoughness"]["metallicFactor"] == 0.0
    assert "KHR_materials_unlit" in material["extensions"] and "extensionsRequired" not in doc


def test_glb_loads_in_trimesh(mesh):
    """A glTF reader takes it: same faces and vertices (trimesh keeps COLOR_0's linear values)."""
    import trimesh

    glb = trimesh.load(mesh["files"]["mesh_glb"], force="mesh", process=False)
    assert len(glb.faces) == len(mesh["triangles"]) and len(glb.vertices) == len(mesh["vertices"])
