"""TSDF backend: float and 16-bit colour, ray-cast accuracy (and the two fixes of Open3D's kernels), colour pairs,
export."""

from __future__ import annotations

import contextlib
import re

import numpy as np
import pytest

from box_room import box_room_sequence
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
    backend = TSDFBackend(voxel_size=0.01, depth_max=3.0, colour_storage="float32")
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


@pytest.mark.parametrize("storage", ["float32", "uint16"])
def test_rendered_colour_is_the_trilinear_interpolation_of_the_observed_voxels(storage):
    """The view's colour at a surface point is the trilinear interpolation of the eight voxels around it, over
    those observed (voxel i at i * voxel_size, where integration puts it): checked against a float64 reference
    read from the grid through Open3D's own hash map, on a room whose texture varies from pixel to pixel."""
    from mapping._open3d import o3d

    ds, _ = box_room_sequence(n_frames=2, width=160, height=120)
    backend = TSDFBackend(voxel_size=0.02, depth_max=5.0, surface="open3d", colour_storage=storage)
    rng = np.random.default_rng(3)
    for f in ds:
        backend.integrate(f.depth, rng.uniform(0.01, 300.0, f.depth.shape + (3,)).astype(np.float32), f.K, f.pose)
    f = ds[1]
    view = backend.render(f.pose, f.K, f.height, f.width)
    colour = backend.grid.attribute("color").numpy()
    weight = backend.grid.attribute("weight").numpy()[..., 0]
    assert colour.dtype == weight.dtype == np.dtype(storage)
    colour = colour.astype(np.float64)
    res, vs = backend.block_resolution, backend.voxel_size
    vv, uu = np.nonzero(view.depth > 0)
    pick = rng.choice(len(vv), 300, replace=False)
    checked = 0
    for v, u in zip(vv[pick], uu[pick]):
        ray = f.pose[:3, :3] @ [(u - f.K[0, 2]) / f.K[0, 0], (v - f.K[1, 2]) / f.K[1, 1], 1.0]
        g = (f.pose[:3, 3] + float(view.depth[v, u]) * ray) / vs
        base, frac = np.floor(g).astype(int), g - np.floor(g)
        acc, total = np.zeros(3), 0.0
        for k in range(8):
            d = np.array([k & 1, (k >> 1) & 1, (k >> 2) & 1])
            corner = base + d
            slot, found = backend.grid.hashmap().find(o3d.core.Tensor((corner // res).reshape(1, 3).astype(np.int32)))
            x, y, z = corner % res
            if not found.numpy()[0] or weight[int(slot.numpy()[0]), z, y, x] <= 0:
                continue
            r = np.prod(np.where(d == 1, frac, 1 - frac))
            acc += r * colour[int(slot.numpy()[0]), z, y, x]
            total += r
        if total > 0:   # stored x colour_scale (Open3D stores float colours x 255)
            np.testing.assert_allclose(view.colour[v, u], acc / total / backend.colour_scale, rtol=1e-4, atol=1e-3)
            checked += 1
    assert checked > 250


def _by_key(backend, name):
    """A grid attribute (blocks, voxels, channels) in the order of the block coordinates (the hash map's slot order
    depends on its threads)."""
    hashmap = backend.grid.hashmap()
    slots = hashmap.active_buf_indices().numpy()
    keys = hashmap.key_tensor().numpy()[slots]
    order = np.lexsort(keys.T)
    value = backend.grid.attribute(name).numpy()
    return keys[order], value[slots[order]].reshape(len(slots), -1, value.shape[-1])


def test_uint16_colour_round_trip_at_the_extremes(caplog):
    """The 16-bit grid stores round(colour x colour_scale): zero, one step, half a step (rounded up, where Open3D's
    kernel truncates) and the top of the range come back exactly; colour above the range or negative is clamped,
    counted and reported once; NaN stores 0; the running average of the top value stays at the top; weights stop
    at 65535 instead of wrapping."""
    scale = 64.0
    top = 65535 / scale
    backend = TSDFBackend(voxel_size=0.01, depth_max=3.0, colour_scale=scale)
    depth = _plane()
    colour = np.empty((H, W, 3), np.float32)
    colour[:, : W // 2] = [0.0, 1 / scale, 2.5 / scale]
    colour[:, W // 2:] = [top, 2 * top, -1.0]
    colour[: H // 2, W // 2:, 1] = np.nan
    with caplog.at_level("WARNING", logger="mapping.fusion.tsdf"):
        for _ in range(3):
            backend.integrate(depth, colour, K, np.eye(4))
    view = backend.render(np.eye(4), K, H, W)
    np.testing.assert_allclose(view.colour[20:40, 10:30], np.broadcast_to([0.0, 1 / scale, 3 / scale], (20, 20, 3)),
                               rtol=1e-6)
    np.testing.assert_allclose(view.colour[H // 2 + 5:-10, 50:70], np.broadcast_to([top, top, 0.0], (15, 20, 3)),
                               rtol=1e-6)
    np.testing.assert_allclose(view.colour[10:H // 2 - 5, 50:70, 1], 0.0)
    _, stored = _by_key(backend, "color")
    assert stored.dtype == np.uint16 and stored.max() == 65535
    assert backend.colour_clipped > 0 and backend.stats()["colour_clipped"] == backend.colour_clipped
    assert len([r for r in caplog.records if "clamped" in r.message]) == 1
    assert "colour_storage='float32'" in caplog.records[0].message
    weight = backend.grid.attribute("weight").numpy()
    weight[weight > 0] = 65534
    for _ in range(2):
        backend.integrate(depth, colour, K, np.eye(4))
    assert weight.max() == 65535 and set(np.unique(weight)) <= {0, 65535}


def test_first_colour_scale():
    from mapping.fusion.tsdf import first_colour_scale

    assert first_colour_scale(np.array([0.2, 1.5], np.float32)) == 8192.0     # holds 8.0 >= 4 x 1.5
    assert first_colour_scale(np.array([255.0])) == 64.0                        # intensities: up to 1024
    for nothing in (np.zeros(3), np.array([np.nan, -np.inf, 0.0]), np.zeros(0)):
        assert first_colour_scale(nothing) == 8192.0                            # as if the largest were 1
    assert first_colour_scale(np.array([np.inf, 3.0])) == 4096.0                # inf is not a colour


def test_uint16_grid_agrees_with_the_float_grid():
    """On a fused room with a pixel-to-pixel texture, the 16-bit grid (our integration kernel) and the float grid
    (Open3D's) hold the same blocks, bit-identical TSDF values and weights (the same voxels fused with the same
    arithmetic), and colours within the rounding bound: each update rounds to the nearest step (1 / colour_scale)
    around the exact running average, so after w updates the error is at most (w + 1) / 4 steps (and unbiased).
    Renders and meshes follow."""
    ds, _ = box_room_sequence(n_frames=8, width=160, height=120)
    backends = {k: TSDFBackend(voxel_size=0.02, depth_max=5.0, colour_storage=k) for k in ("float32", "uint16")}
    rng = np.random.default_rng(5)
    for f in ds:
        colour = rng.uniform(0.0, 1.5, f.depth.shape + (3,)).astype(np.float32)
        for backend in backends.values():
            backend.integrate(f.depth, colour, f.K, f.pose, view=backend.render_for_frame(f.depth, f.K, f.pose))
    b32, b16 = backends["float32"], backends["uint16"]
    step = 1.0 / b16.colour_scale
    assert b16.colour_scale == 8192.0 and b16.colour_clipped == 0
    (k32, t32), (k16, t16) = _by_key(b32, "tsdf"), _by_key(b16, "tsdf")
    (_, w32), (_, w16) = _by_key(b32, "weight"), _by_key(b16, "weight")
    assert np.array_equal(k32, k16) and len(k32) > 50
    np.testing.assert_array_equal(w32, w16.astype(np.float32))
    np.testing.assert_array_equal(t32[w32 > 0], t16[w16 > 0])
    (_, c32), (_, c16) = _by_key(b32, "color"), _by_key(b16, "color")
    seen = w32[..., 0] > 0
    error = c16[seen] * step - c32[seen] / 255.0                       # map units
    bound = ((w32[seen] + 1) / 4 + 1e-3) * step
    assert np.all(np.abs(error) <= bound) and seen.sum() > 100_000
    assert abs(error.mean()) < 0.01 * step and np.abs(error).max() > 0.5 * step   # unbiased; and not float32
    f = ds[4]
    v32, v16 = (b.render(f.pose, f.K, f.height, f.width) for b in (b32, b16))
    np.testing.assert_array_equal(v32.depth, v16.depth)
    assert np.abs(v16.colour - v32.colour).max() <= (len(ds) + 1) / 4 * step
    m32, m16 = b32.extract_mesh(), b16.extract_mesh()
    o32, o16 = np.lexsort(m32.vertices.T), np.lexsort(m16.vertices.T)
    np.testing.assert_array_equal(m32.vertices[o32], m16.vertices[o16])
    assert np.abs(m16.colours[o16] - m32.colours[o32]).max() <= (len(ds) + 1) / 4 * step * 1.001
    assert b16.stats()["used_mb"] == pytest.approx(b32.stats()["used_mb"] * 12 / 20)


@pytest.mark.parametrize("storage", ["uint16", "float32"])
def test_block_list_follows_the_hash_map(storage):
    """The block list behind the colour kernel's table (coordinates and buffer slots) is kept up to date frame by
    frame as blocks are added, is dropped when the hash map grows (which moves every block), and always equals
    the hash map's own: on a room swept fast enough to add blocks every frame, from a 4-block hash map."""
    from mapping._open3d import o3d

    ds, _ = box_room_sequence(n_frames=10, width=160, height=120, step=0.1, turn_deg=8)
    backend = TSDFBackend(voxel_size=0.01, depth_max=5.0, block_count=4, colour_storage=storage)
    kept = dropped = 0
    for f in ds:
        hashmap = backend.grid.hashmap()
        size, capacity = hashmap.size(), hashmap.capacity()
        backend.integrate(f.depth, np.ones(f.depth.shape + (3,), np.float32), f.K, f.pose,
                          view=backend.render_for_frame(f.depth, f.K, f.pose))
        hashmap = backend.grid.hashmap()
        assert hashmap.size() > size                                   # blocks added every frame
        if hashmap.capacity() != capacity:
            assert backend._blocks_known is None
            dropped += 1
        elif backend.frames_integrated > 1:
            assert len(backend._blocks_known[1]) == hashmap.size()      # complete without reading the hash map
            assert backend._blocks_known[2] == hashmap.capacity()
            kept += 1
        keys, slots = backend._known_blocks()
        truth = hashmap.active_buf_indices().numpy()
        assert dict(zip(map(tuple, keys), slots)) == dict(zip(map(tuple, hashmap.key_tensor().numpy()[truth]), truth))
    assert kept >= 3 and dropped >= 2
    # Open3D's hash map also grows (moving every block) when asked to activate blocks it holds, if their count
    # plus its size exceeds its capacity, as Open3D's integrate does after ours (float storage): same size, new
    # slots. The list must follow.
    hashmap = backend.grid.hashmap()
    old = dict(zip(map(tuple, backend._known_blocks()[0]), backend._known_blocks()[1]))
    capacity = hashmap.capacity()
    present = hashmap.key_tensor().numpy()[hashmap.active_buf_indices().numpy()]
    hashmap.activate(o3d.core.Tensor(np.tile(present, (capacity // len(present) + 1, 1))))
    assert hashmap.capacity() > capacity and hashmap.size() == len(present)
    keys, slots = backend._known_blocks()
    truth = hashmap.active_buf_indices().numpy()
    truth = dict(zip(map(tuple, hashmap.key_tensor().numpy()[truth]), truth))
    assert len(truth) == len(old) and truth != old                       # same blocks, moved
    assert dict(zip(map(tuple, keys), slots)) == truth


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


def test_frame_contract_view_carries_the_block_list_and_masked_pixels_are_not_fused(monkeypatch):
    """render_for_frame hands its block search over in the view (ModelView.prepared, with the pose); integrate
    reuses it for that frame, searches again when pixels are masked (valid) or the view is of another pose, and
    fuses nothing where valid is False."""
    backend = TSDFBackend(voxel_size=0.01, depth_max=3.0)
    searches = []
    prepare = backend._prepare
    monkeypatch.setattr(backend, "_prepare", lambda *a: searches.append(1) or prepare(*a))
    depth, colour, pose = _plane(), np.full((H, W, 3), 10.0, np.float32), np.eye(4)
    view = backend.render_for_frame(depth, K, pose)
    assert view.prepared is not None and np.array_equal(view.pose, pose) and len(searches) == 1
    valid = np.ones((H, W), bool)
    valid[:, : W // 2] = False
    backend.integrate(depth, colour, K, pose, view=view, valid=valid)
    assert len(searches) == 2                                        # masked: the blocks are searched again
    seen = backend.render(pose, K, H, W)
    assert not seen.valid[:, : W // 2 - 15].any()                   # nothing fused where colour was invalid
    assert seen.valid[10:-10, W // 2 + 15:-10].all()
    view = backend.render_for_frame(depth, K, pose)
    backend.integrate(depth, colour, K, pose, view=view)
    assert len(searches) == 3                                        # reused: one search for the frame
    moved = pose.copy()
    moved[0, 3] = 0.05
    backend.integrate(depth, colour, K, moved, view=backend.render_for_frame(depth, K, pose))
    assert len(searches) == 5                                        # a view of another pose is not reused
    other = depth - 0.2                                              # nor a view rendered for other depth
    backend.integrate(other, colour, K, pose, view=backend.render_for_frame(depth, K, pose))
    assert len(searches) == 7


def test_export_and_stats(tmp_path):
    import trimesh

    ds, _ = box_room_sequence(n_frames=3, width=80, height=60)
    backend = TSDFBackend(voxel_size=0.04, depth_max=5.0)
    for f in ds:
        backend.integrate(f.depth, f.rgb.astype(np.float32), f.K, f.pose)
    assert set(backend.export(tmp_path / "default", lambda c: c)) == {"mesh_ply"}      # one mesh by default
    files = backend.export(tmp_path, lambda c: np.clip(c * 0.5, 0, 255), formats=("ply", "glb", "npz"))
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
    # an empty map writes only the colour archive, when asked for
    assert set(TSDFBackend().export(tmp_path / "empty", lambda c: c, formats=("ply", "npz"))) == {"mesh_colours"}
    assert TSDFBackend().export(tmp_path / "empty2", lambda c: c) == {}


def test_arguments():
    with pytest.raises(ValueError, match="voxel_size"):
        TSDFBackend(voxel_size=0)
    with pytest.raises(ValueError, match="depth_min"):
        TSDFBackend(depth_min=5, depth_max=3)
    with pytest.raises(ValueError, match="surface must be one of"):
        TSDFBackend(surface="marching")
    with pytest.raises(ValueError, match="colour_storage must be one of uint16, float32, got 'half'"):
        TSDFBackend(colour_storage="half")
    for bad in (0, -1.0, float("nan"), "8"):
        with pytest.raises(ValueError, match="colour_scale must be a positive number"):
            TSDFBackend(colour_scale=bad)
    backend = TSDFBackend()
    with pytest.raises(ValueError, match="float32"):
        backend.integrate(np.ones((4, 4)), np.zeros((4, 4, 3), np.float32), K, np.eye(4))
    with pytest.raises(ValueError, match="colour must be"):
        backend.integrate(np.ones((4, 4), np.float32), np.zeros((4, 5, 3), np.float32), K, np.eye(4))
    view = ModelView(depth=np.zeros((2, 2), np.float32), colour=np.zeros((2, 2, 3), np.float32))
    assert not view.valid.any()


def _open3d_range_log(text: str) -> list[tuple[bool, int]]:
    """(overflowed, fragments needed) of every ray cast in Open3D's debug output, in order."""
    found = re.findall(r"(Could not generate full range map; allocated|EstimateRange Allocated) \d+ fragments "
                       r"(?:but|and) needed (\d+)", text)
    return [(kind.startswith("Could"), int(n)) for kind, n in found]


class _RecordingGrid:
    """Forwards to Open3D's grid and records the arguments of every ray cast."""

    def __init__(self, grid):
        self._grid, self.casts = grid, []

    def __getattr__(self, name):
        return getattr(self._grid, name)

    def ray_cast(self, blocks, K, extrinsic, width, height, attrs, *args):
        self.casts.append((blocks.numpy().copy(), K.numpy(), extrinsic.numpy(), height, width, list(attrs)))
        return self._grid.ray_cast(blocks, K, extrinsic, width, height, attrs, *args)


def test_no_ray_cast_reads_an_unwritten_range_fragment(monkeypatch, capfd):
    """Open3D's ray cast crashed (issue 13) when its fragment buffer overflowed: the block straddling the end of
    the buffer writes none of its fragments, yet the slots below the end are read back as pixel coordinates.
    Every cast the backend makes must fit the buffer, except the casts that grow it, whose blocks take one
    fragment each (nothing unwritten is read). Checked on Open3D's own report of each cast (debug log): the
    first frames, a far wall, then a smaller view with another camera on the same grid. The former one-off
    reservation cast (blocks of up to 6 fragments, 3256 needed, 1800 allocated) fails here."""
    from mapping._open3d import o3d
    from mapping.fusion import tsdf

    monkeypatch.setattr(tsdf, "_quiet", contextlib.nullcontext)     # keep Open3D's debug report
    K640 = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    backend = TSDFBackend(voxel_size=0.01, depth_max=3.0, ray_caster="open3d")   # the guard of Open3D's cast
    grid = backend.grid = _RecordingGrid(backend.grid)
    u = np.arange(640, dtype=np.float32)[None, :].repeat(480, axis=0)
    frames = [(1.5 + 1.3 * u / 640).astype(np.float32)] * 3 + [np.full((480, 640), 2.9, np.float32)]
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Debug):
        capfd.readouterr()
        for i, depth in enumerate(frames):
            pose = np.eye(4)
            pose[0, 3] = 0.03 * i
            backend.integrate(depth, np.ones((480, 640, 3), np.float32), K640, pose,
                              view=backend.render_for_frame(depth, K640, pose))
        first = backend.render_for_frame(frames[0], K640, np.eye(4))
        small = backend.render_for_frame(frames[0][::2, ::2], K640 / 2 + np.diag([0, 0, 0.5]), np.eye(4))
        log = _open3d_range_log(capfd.readouterr().out)
    assert len(log) == len(grid.casts) >= 6
    assert (first.depth > 0).mean() > 0.95 and (small.depth > 0).mean() > 0.95        # complete views
    for (overflowed, needed), (blocks, K, extrinsic, height, width, attrs) in zip(log, grid.casts):
        per_block = tsdf.range_map_fragments(blocks, K, extrinsic, height, width, block_resolution=16,
                                             voxel_size=0.01, depth_min=backend.depth_min, depth_max=3.0)
        assert per_block.sum() == needed                                   # the count matches Open3D's
        if "color" in attrs:
            assert not overflowed                                          # renders are complete
        if overflowed:
            assert per_block.max() == 1                                    # no fragment slot left unwritten


def test_range_map_fragments_match_open3d(capfd):
    """The backend's count of a cast's range-map fragments is Open3D's, for frustum walls near and far, at
    another pose, and at a view size that is not a multiple of 16 range-map pixels."""
    from mapping._open3d import o3d
    from mapping.fusion.tsdf import range_map_fragments

    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    backend = TSDFBackend(voxel_size=0.02, depth_max=4.0)
    cases = []
    for depth, shift, (h, w) in ((0.3, 0.0, (480, 640)), (3.5, 0.0, (480, 640)), (1.2, 0.7, (480, 640)),
                                 (2.0, -0.4, (232, 312))):
        pose = np.eye(4)
        pose[:3, 3] = [shift, 0.5 * shift, 0.0]
        pose[:3, :3] = np.array([[np.cos(shift), 0, np.sin(shift)], [0, 1, 0], [-np.sin(shift), 0, np.cos(shift)]])
        extrinsic = np.linalg.inv(pose)
        Kc = K * np.array([[w / 640], [h / 480], [1]])
        wall = o3d.t.geometry.Image(o3d.core.Tensor(np.full((h, w), depth, np.float32)))
        blocks = backend.grid.compute_unique_block_coordinates(wall, o3d.core.Tensor(Kc),
                                                               o3d.core.Tensor(extrinsic), 1.0, 4.0, 8.0)
        cases.append((blocks, Kc, extrinsic, h, w))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Debug):
        capfd.readouterr()
        for blocks, Kc, extrinsic, h, w in cases:
            backend.grid.ray_cast(blocks, o3d.core.Tensor(Kc), o3d.core.Tensor(extrinsic), w, h, ["depth"], 1.0,
                                  0.1, 4.0, 1.0, 8.0, 8)
        log = _open3d_range_log(capfd.readouterr().out)
    ours = [int(range_map_fragments(b.numpy(), Kc, e, h, w, block_resolution=16, voxel_size=0.02, depth_min=0.1,
                                    depth_max=4.0).sum()) for b, Kc, e, h, w in cases]
    assert [n for _, n in log] == ours and min(ours) > 10


@pytest.mark.parametrize("height, width", [(6, 8), (8, 8), (12, 20), (17, 9)])
def test_tiny_views_render(height, width):
    """Views whose range map has a side under 2 pixels take no fragment: Open3D's cast runs without growing
    anything, and our cast (issue 33) gives its depth and colour."""
    views = {}
    for caster in ("open3d", "radiomap"):
        backend = TSDFBackend(voxel_size=0.02, depth_max=3.0, ray_caster=caster)
        depth = _plane()
        for _ in range(2):
            backend.integrate(depth, np.ones((H, W, 3), np.float32), K, np.eye(4))
        capacity = backend.fragment_capacity
        Ks = K * np.array([[width / W], [height / H], [1]])
        views[caster] = view = backend.render_for_frame(np.full((height, width), 1.5, np.float32), Ks, np.eye(4))
        assert view.depth.shape == (height, width) and backend.ray_casts == 2
        if caster == "open3d":
            assert capacity > 0 and backend.fragment_capacity == capacity
    np.testing.assert_array_equal(views["open3d"].depth, views["radiomap"].depth)
    np.testing.assert_array_equal(views["open3d"].colour, views["radiomap"].colour)


def test_the_memory_estimate_counts_the_default_grid():
    """The memory pre-check (mapping.validation) counts the bytes of the grid the backend makes by default."""
    from mapping.fusion.tsdf import COLOUR_STORAGE, TSDFBackend
    from mapping.validation import TSDF_BYTES_PER_VOXEL

    assert TSDF_BYTES_PER_VOXEL == COLOUR_STORAGE[TSDFBackend(voxel_size=0.02).colour_storage]
