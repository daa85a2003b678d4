"""TSDF backend: float colour, ray-cast accuracy (and the two fixes of Open3D's kernels), colour pairs, export."""

from __future__ import annotations

import numpy as np
import pytest

from mapping.datasets.synthetic import box_room_sequence
from mapping.fusion.base import ColourPairs, ModelView
from mapping.fusion.tsdf import TSDFBackend

H, W = 60, 80
K = np.array([[64.0, 0, (W - 1) / 2], [0, 64.0, (H - 1) / 2], [0, 0, 1]])


def _plane(z=1.5, tilt=(0.0, 0.0)):
    """Depth of the plane z = z0 + a x + b y seen from the origin (float32 metres)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    return (z / (1 - tilt[0] * x - tilt[1] * y)).astype(np.float32)


def test_float_colour_survives_fusion():
    backend = TSDFBackend(voxel_size=0.01, depth_max=3.0)
    assert all(callable(getattr(backend, name)) for name in ("render", "integrate", "export", "stats"))
    depth = _plane()
    colour = np.empty((H, W, 3), np.float32)
    colour[...] = [3.5, 0.002, 250.0]          # irradiance above 1 and below 1/255, and intensity-like values
    pose = np.eye(4)
    assert backend.integrate(depth, colour, K, pose) is None      # nothing to compare against yet
    view = backend.render(pose, K, H, W)
    inner = view.depth[10:-10, 10:-10]
    assert np.all(inner > 0)
    np.testing.assert_allclose(view.colour[10:-10, 10:-10], np.broadcast_to(colour[10:-10, 10:-10], (40, 60, 3)),
                               rtol=1e-5)
    np.testing.assert_allclose(inner, 1.5, atol=0.0051)   # within half a voxel ("refine" is exact)
    # vertex = depth * K^-1 [u, v, 1]; normals face the camera
    v, u = 30, 40
    np.testing.assert_allclose(view.vertex[v, u], view.depth[v, u] * np.array([(u - K[0, 2]) / 64, (v - K[1, 2]) / 64,
                                                                             1.0]), rtol=1e-5)
    np.testing.assert_allclose(view.normal[v, u], [0, 0, -1], atol=0.02)
    # where nothing is seen: zeros
    empty = TSDFBackend().render(pose, K, H, W)
    assert not empty.valid.any() and not empty.colour.any() and not empty.normal.any()


@pytest.mark.parametrize("surface, max_bias_mm", [("open3d", None), ("debias", 1.5), ("refine", 1.0)])
def test_rendered_surface_bias(surface, max_bias_mm):
    """Open3D's ray cast reads floored voxels: rendered walls are ~half a voxel too far. The fixes remove it."""
    ds, _ = box_room_sequence(n_frames=1, width=160, height=120)
    f = ds[0]
    backend = TSDFBackend(voxel_size=0.02, depth_max=5.0, surface=surface)
    backend.integrate(f.depth, np.zeros(f.depth.shape + (3,), np.float32), f.K, f.pose)
    view = backend.render(f.pose, f.K, f.height, f.width)
    m = view.depth > 0
    bias_mm = 1000 * np.median(view.depth[m] - f.depth[m])
    if max_bias_mm is None:
        assert 6.0 < bias_mm < 14.0                     # about half of the 2 cm voxel
    else:
        assert abs(bias_mm) < max_bias_mm


def test_pixel_centre_fix_on_a_tilted_plane():
    depth = _plane(2.0, tilt=(0.6, 0.4))
    biases = {}
    for fix in (False, True):
        backend = TSDFBackend(voxel_size=0.005, depth_max=5.0, pixel_centre_fix=fix, surface="refine", block_count=8000)
        backend.integrate(depth, np.zeros((H, W, 3), np.float32), K, np.eye(4))
        view = backend.render(np.eye(4), K, H, W)
        m = view.depth[8:-8, 8:-8] > 0
        biases[fix] = 1000 * np.median((view.depth[8:-8, 8:-8] - depth[8:-8, 8:-8])[m])
    # Open3D integrates each voxel with pixel int(u): half a pixel off, 3-6 mm on this plane at 2 m
    assert abs(biases[False]) > 3.0 and abs(biases[True]) < 1.0


def test_colour_pairs_compare_the_map_before_fusion():
    backend = TSDFBackend(voxel_size=0.01, depth_max=3.0)
    depth = _plane()
    first = np.full((H, W, 3), 10.0, np.float32)
    second = np.full((H, W, 3), 20.0, np.float32)
    pose = np.eye(4)
    view0 = backend.render_for_frame(depth, K, pose)
    assert not view0.valid.any() and backend.ray_casts == 0        # an empty map is not ray cast
    backend.integrate(depth, first, K, pose, view=view0)
    view1 = backend.render_for_frame(depth, K, pose)
    pairs = backend.integrate(depth, second, K, pose, view=view1)
    assert backend.ray_casts == 1                                   # render_for_frame's cast was reused
    assert isinstance(pairs, ColourPairs)
    assert len(pairs) > 0.8 * H * W
    np.testing.assert_allclose(pairs.map_colour, 10.0, rtol=1e-5)    # the map before the second frame
    np.testing.assert_allclose(pairs.sample_colour, 20.0)
    again = backend.render(pose, K, H, W)
    np.testing.assert_allclose(again.colour[20:40, 20:60], 15.0, rtol=1e-4)   # the running average
    # a surface 30 cm in front of the map is not the same surface: no pairs, yet it is fused
    pairs = backend.integrate(depth - 0.3, second, K, pose)
    assert len(pairs) == 0 and backend.frames_integrated == 3


def test_export_and_stats(tmp_path):
    import trimesh

    ds, _ = box_room_sequence(n_frames=3, width=80, height=60)
    backend = TSDFBackend(voxel_size=0.04, depth_max=5.0)
    for f in ds:
        backend.integrate(f.depth, f.rgb.astype(np.float32), f.K, f.pose)
    files = backend.export(tmp_path, lambda c: np.clip(c * 0.5, 0, 255))
    assert set(files) == {"mesh_ply", "mesh_glb", "mesh_colours"}
    mesh = trimesh.load(files["mesh_ply"], process=False)
    data = np.load(files["mesh_colours"])
    assert len(mesh.vertices) == len(data["vertices"]) > 1000 and len(mesh.faces) == len(data["triangles"])
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, :3], data["display"])
    np.testing.assert_array_equal(data["display"], np.clip(np.rint(data["colours"] * 0.5), 0, 255).astype(np.uint8))
    glb = trimesh.load(files["mesh_glb"], force="mesh", process=False)
    assert len(glb.faces) == len(mesh.faces)
    stats = backend.stats()
    assert stats["frames_integrated"] == 3 and stats["blocks"] > 0
    assert stats["used_mb"] <= stats["allocated_mb"] and stats["truncation_m"] == pytest.approx(0.32)
    # an empty map writes only the colour archive
    assert set(TSDFBackend().export(tmp_path / "empty", lambda c: c)) == {"mesh_colours"}


def test_arguments():
    with pytest.raises(ValueError, match="voxel_size"):
        TSDFBackend(voxel_size=0)
    with pytest.raises(ValueError, match="depth_min"):
        TSDFBackend(depth_min=5, depth_max=3)
    with pytest.raises(ValueError, match="surface must be one of"):
        TSDFBackend(surface="marching")
    backend = TSDFBackend()
    with pytest.raises(ValueError, match="float32"):
        backend.integrate(np.ones((4, 4)), np.zeros((4, 4, 3), np.float32), K, np.eye(4))
    with pytest.raises(ValueError, match="colour must be"):
        backend.integrate(np.ones((4, 4), np.float32), np.zeros((4, 5, 3), np.float32), K, np.eye(4))
    view = ModelView(depth=np.zeros((2, 2), np.float32), colour=np.zeros((2, 2, 3), np.float32))
    assert not view.valid.any()


def test_range_map_buffer_is_reserved_on_the_empty_grid():
    """The one-off ray cast that sizes Open3D's range-map buffer runs before the first integration, when no
    ray can read a voxel (on a filled grid that cast, which no weight stops, crashed Open3D 0.20 now and
    then); once per camera, and later casts see the whole view."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    backend = TSDFBackend(voxel_size=0.02, depth_max=4.0)
    blocks_at_reservation = []                  # map size whenever a camera's buffer was actually reserved
    original = backend._reserve_range_fragments

    def reserve(*args):
        size, before = int(backend.grid.hashmap().size()), len(backend._range_reserved)
        original(*args)
        if len(backend._range_reserved) > before:
            blocks_at_reservation.append(size)

    backend._reserve_range_fragments = reserve
    depth = np.full((480, 640), 2.0, np.float32)
    for z in (0.0, 0.05):
        pose = np.eye(4)
        pose[2, 3] = z
        view = backend.render_for_frame(depth, K, pose)
        backend.integrate(depth, np.ones((480, 640, 3), np.float32), K, pose, view=view)
    assert blocks_at_reservation == [0]
    assert (backend.render(np.eye(4), K, 480, 640).depth > 0).mean() > 0.9      # measured 0.944
