"""The ray cast's AVX-512 march (``mapping/_ckernels_raycast_simd.h``) gives the scalar march's results bit for bit.

``mapping._ckernels.raycast_depth`` marches 16 rays per vector where the CPU has AVX-512 and the scalar march
otherwise or when asked (its ``simd`` argument, ``RADIOMAP_SIMD=0``). The scalar march is Open3D's cast bit for
bit (tests/test_raycast.py); here the two marches are compared with each other: depth bits, surface colour and
the step, ray and outside-the-table counts, on

- synthetic grids handed to the kernel directly (random TSDF fields, uint16 and float32 weights and colours,
  tables with absent blocks, slots past the end of the buffers and huge slots, poses outside the map, rays
  that find nothing, image sizes that are not multiples of 16), built here independently of the kernel;
- the maps of ``scripts/stress_raycast.py`` (box rooms with spheres fused by Open3D's grid) through
  ``TSDFBackend``;
- the 7-Scenes kitchen.

Tests that need the AVX-512 march skip on CPUs (or builds) without it.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from radiometry._native import compiled
from tests.conftest import build_without_simd, shared_path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "stress_raycast.py"
KERNELS = compiled("mapping._ckernels")
needs_c = pytest.mark.skipif(KERNELS is None, reason="the compiled kernels are not built")
needs_simd = pytest.mark.skipif(not getattr(KERNELS, "raycast_simd", 0),
                                reason="this CPU (or build) has no AVX-512: the ray cast marches in scalar code only")


def _stress():
    spec = importlib.util.spec_from_file_location("radiomap_script_stress_raycast", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _look(origin, target) -> np.ndarray:
    return _stress()._look(np.asarray(origin, float), np.asarray(target, float))


def synthetic_cast(seed: int, simd: bool, u16: bool, rows: int, cols: int, kernels=None):
    """Cast a random grid with the kernel (``kernels``: the module, the installed one by default): (depth,
    colour, steps, whether the AVX-512 march ran)."""
    rng = np.random.default_rng(seed)
    f32 = np.float32
    res = int(rng.choice([1, 2, 4, 8, 16]))
    voxel = float(rng.uniform(0.01, 0.05))
    size = res * voxel
    dims = rng.integers(2, 7, 3)
    lo = rng.integers(-4, 4, 3).astype(np.int64)
    present = rng.random(tuple(dims)) < 0.8
    n_blocks = int(present.sum())
    index = np.full(tuple(dims), -1, np.int32)
    index[present] = rng.permutation(n_blocks)
    slots = index[present]          # every buffer slot's block (before some table entries are spoilt below)
    extra = present & (rng.random(tuple(dims)) < 0.05)      # slots past the buffers' end, some huge
    index[extra] = rng.choice([n_blocks, n_blocks + 3, 2 ** 20, 2 ** 30 + 5, 2 ** 31 - 1], int(extra.sum()))
    coords = np.argwhere(present) + lo
    # the TSDF of a sphere (plus noise) at the voxel centres, truncated: a surface inside the grid
    centre = (lo + dims * rng.uniform(0.3, 0.7, 3)) * size
    radius = float(rng.uniform(0.2, 0.5)) * dims.min() * size
    trunc = voxel * float(rng.uniform(2, 6))
    v = (np.arange(res) + 0.5) * voxel
    vz, vy, vx = np.meshgrid(v, v, v, indexing="ij")                # the buffer's voxel order: z, y, x
    tsdf = np.empty((n_blocks, res, res, res), f32)
    for (bx, by, bz), slot in zip(coords, slots):
        p = np.stack([bx * size + vx, by * size + vy, bz * size + vz], -1)
        d = np.linalg.norm(p - centre, axis=-1) - radius
        tsdf[slot] = np.clip(d / trunc + rng.normal(0, 0.05, d.shape), -1, 1)
    n = n_blocks * res ** 3
    if u16:
        weight = rng.integers(0, 4, n).astype(np.uint16)
        colour = rng.integers(0, 65536, 3 * n).astype(np.uint16)
    else:
        weight = rng.choice([0.0, 0.5, 1.0, 2.0, 3.0], n).astype(f32)
        colour = rng.uniform(0, 255, 3 * n).astype(f32)
    # the camera: outside the grid looking at it, inside it, or looking away from it
    box_centre = (lo + dims / 2) * size
    away = rng.normal(0, 1, 3)
    origin = box_centre + away / np.linalg.norm(away) * rng.uniform(0.8, 2.0) * dims.max() * size
    where = rng.integers(0, 4)
    if where <= 1:
        pose = _look(origin, box_centre + rng.normal(0, 0.2, 3) * size)
    elif where == 2:
        pose = _look(box_centre + rng.normal(0, 0.1, 3) * size, box_centre + rng.normal(0, 1, 3))
    else:
        pose = _look(origin, 2 * origin - box_centre)
    f = float(rng.uniform(0.6, 1.2)) * cols
    cx, cy = cols / 2 + rng.uniform(-5, 5), rows / 2 + rng.uniform(-5, 5)
    hi = lo + dims - 1
    return kernel_cast(kernels, simd, coords=coords, index=index, lo=lo, tsdf=tsdf, weight=weight, colour=colour,
                       pose=pose, K=(f, f, cx, cy), res=res, voxel=voxel, trunc=trunc,
                       depth=(float(rng.uniform(0, 0.3)), float(rng.uniform(2, 8))),
                       weight_threshold=float(rng.integers(1, 3)), scale=float(rng.uniform(0.5, 2)),
                       box=(lo - 2, hi + 2), shape=(rows, cols))     # the map's box beyond the table


def kernel_cast(kernels, simd, *, coords, index, lo, tsdf, weight, colour, pose, K, res, voxel, trunc, depth,
                weight_threshold, scale, box, shape, directions=None):
    """``raycast_depth`` of a grid given as buffers: (depth, colour, steps, whether the AVX-512 march ran).
    ``directions``: the rotation that turns pixels into ray directions, if not the pose's."""
    f32 = np.float32
    E = np.linalg.inv(pose)
    Rinv = E[:3, :3].T if directions is None else directions
    tinv = -(E[:3, :3].T @ E[:3, 3])
    out = np.empty(shape, f32)
    out_colour = np.empty(shape + (3,), f32)
    steps = np.concatenate([np.zeros(3, np.int64), box[0], box[1]]).astype(np.int64)
    used = (kernels or KERNELS).raycast_depth(
        np.ascontiguousarray(coords, np.int32), np.ascontiguousarray(E[:3, :3], f32),
        np.ascontiguousarray(E[:3, 3], f32), np.ascontiguousarray(Rinv, f32), np.ascontiguousarray(tinv, f32), *K, res, voxel, trunc, *depth,
        weight_threshold, tsdf.reshape(-1), weight, index, np.asarray(lo, np.int64), out, steps,
        np.ascontiguousarray(pose[:3, :3], f32), np.ascontiguousarray(pose[:3, 3], f32), colour, scale, out_colour,
        simd)
    return out, out_colour, steps[:3].copy(), used


SEED = 1                                                 # a synthetic case with rays (below)
SIZES = [(24, 40), (48, 56), (64, 104), (136, 200)]     # cols not multiples of 16


@needs_simd
@pytest.mark.parametrize("u16", [True, False], ids=["uint16", "float32"])
def test_simd_march_equals_scalar_on_synthetic_grids(u16):
    found = rays = outside = misses = 0
    for seed in range(24):
        rows, cols = SIZES[seed % len(SIZES)]
        a = synthetic_cast(seed, True, u16, rows, cols)
        b = synthetic_cast(seed, False, u16, rows, cols)
        assert a[3] is True and b[3] is False
        np.testing.assert_array_equal(a[0].view(np.uint32), b[0].view(np.uint32), err_msg=f"seed {seed}")
        np.testing.assert_array_equal(a[1], b[1], err_msg=f"seed {seed}")
        np.testing.assert_array_equal(a[2], b[2], err_msg=f"seed {seed}")
        found += int(np.count_nonzero(a[0]))
        rays += int(a[2][1])
        outside += int(a[2][2])
        misses += int(a[2][1]) - int(np.count_nonzero(a[0]))
    # the cases reach what they are meant to: surfaces, rays that find nothing, look-ups outside the table
    assert found > 1000 and misses > 1000 and outside > 0 and rays > found


def exact_grid(spoil: str | None, present: bool, u16: bool):
    """A grid whose march is exact in float32: camera at the origin looking along +z, blocks 0.25 m (res 8, voxel
    2^-5 m), the listed blocks from z = 1 to 2 m (so every covered pixel marches t = 1, 1.25, 1.5, 1.75 and ends
    when t reaches 2 exactly: 4 steps), the table's blocks absent or (``present``) of TSDF +1 and truncation
    0.25 m (steps of 0.25 too). ``spoil``: ray directions with a NaN (z) or an infinity (x): every look-up is
    out of range, the rays cross nothing and count no block outside the table though the map's box is huge."""
    res, voxel = 8, 2.0 ** -5
    coords = np.array([(x, y, z) for x in range(-4, 4) for y in range(-3, 3) for z in range(4, 8)])
    lo, dims = np.array([-8, -8, 0]), (16, 16, 10)
    index = np.full(dims, -1, np.int32)
    n_blocks = 0
    if present:
        for x, y, z in coords:
            index[x + 8, y + 8, z] = n_blocks
            n_blocks += 1
    n = max(n_blocks, 1) * res ** 3
    tsdf = np.ones(n, np.float32)
    weight = np.full(n, 3, np.uint16 if u16 else np.float32)
    colour = np.full(3 * n, 7, np.uint16 if u16 else np.float32)
    directions = None
    if spoil:
        directions = np.eye(3)
        directions[2 if spoil == "nan" else 0] = np.nan if spoil == "nan" else np.inf
    huge = 2 ** 40
    box = (np.full(3, -huge), np.full(3, huge)) if spoil else (lo, lo + np.array(dims) - 1)
    return dict(coords=coords, index=index, lo=lo, tsdf=tsdf, weight=weight, colour=colour, pose=np.eye(4),
                K=(60.0, 60.0, 31.5, 23.5), res=res, voxel=voxel, trunc=0.25, depth=(0.1, 3.0), weight_threshold=1.0,
                scale=1.0, box=box, shape=(48, 64), directions=directions)


@needs_c
@pytest.mark.parametrize("spoil, present", [(None, False), (None, True), ("nan", False), ("inf", True)])
def test_exact_march_ends_at_t_max_and_skips_out_of_range(spoil, present):
    """Built by hand: 4 steps per ray (the last lands on t_max exactly and stops), no surface, no look-up counted
    outside the table; the AVX-512 march (where the CPU has it) and the scalar one agree."""
    for u16 in (True, False):
        grid = exact_grid(spoil, present, u16)
        runs = [kernel_cast(None, simd, **grid) for simd in ((False, True) if KERNELS.raycast_simd else (False,))]
        for depth, colour, steps, _ in runs:
            assert steps[1] > 1000 and steps[0] == 4 * steps[1] and steps[2] == 0
            assert not depth.any() and not colour.any()
        if len(runs) == 2:
            assert runs[1][3] is True
            np.testing.assert_array_equal(runs[0][2], runs[1][2])


@needs_c
def test_forcing_the_scalar_march():
    a = synthetic_cast(SEED, False, True, 48, 56)
    assert a[3] is False and a[2][0] > a[2][1] > 0
    if KERNELS.raycast_simd:
        assert synthetic_cast(SEED, True, True, 48, 56)[3] is True


@needs_simd
@pytest.mark.parametrize("seed", [pytest.param(0, marks=pytest.mark.slow), 1, pytest.param(4, marks=pytest.mark.slow),
                                  7, 9])   # 0 and 4: 5-7 s each
def test_simd_march_equals_scalar_through_the_backend(seed):
    """Maps fused by Open3D's grid (``scripts/stress_raycast.py``'s scenes: 160x120, 212x160 and 320x240, uint16
    and float32 storage, casts from outside the room and towards empty space)."""
    stress = _stress()
    case = stress.build_case(seed)
    assert case is not None
    backend, K, h, w, casts, desc, render = case
    empty = 0
    for pose in casts:
        try:
            blocks = backend._prepare(render(pose), K, pose).blocks
        except RuntimeError:
            blocks = backend._last_blocks
        (a, steps, rays, used), (b, steps_s, rays_s, used_s) = stress.own_casts(backend, blocks, K, pose, h, w)
        assert used and not used_s, desc
        np.testing.assert_array_equal(a.depth.view(np.uint32), b.depth.view(np.uint32), err_msg=desc)
        np.testing.assert_array_equal(a.colour, b.colour, err_msg=desc)
        assert (steps, rays) == (steps_s, rays_s) and steps > rays > 0, desc
        empty += int(np.count_nonzero(a.depth == 0))
    assert empty > 0, desc


@needs_simd
def test_simd_march_equals_scalar_on_the_kitchen():
    from mapping.datasets import open_dataset
    from mapping.fusion.tsdf import TSDFBackend

    stress = _stress()
    ds = open_dataset(shared_path("rgbd", "redkitchen_7scenes_000-099"), frames=slice(0, 40, 8))
    backend = TSDFBackend(voxel_size=0.01, block_count=500)
    compared = 0
    for i in range(len(ds)):
        frame = ds[i]
        if backend.frames_integrated:
            blocks = backend._prepare(frame.depth, ds.K, frame.pose).blocks
            (a, steps, rays, used), (b, steps_s, rays_s, used_s) = stress.own_casts(backend, blocks, ds.K,
                                                                                    frame.pose, ds.height, ds.width)
            assert used and not used_s
            assert np.count_nonzero(a.depth) > 0.5 * a.depth.size
            np.testing.assert_array_equal(a.depth.view(np.uint32), b.depth.view(np.uint32))
            np.testing.assert_array_equal(a.colour, b.colour)
            assert (steps, rays) == (steps_s, rays_s) and steps > rays > 0
            compared += 1
        backend.integrate(frame.depth, frame.rgb.astype(np.float32) / 255, ds.K, frame.pose)
    assert compared == len(ds) - 1


@needs_c
@pytest.mark.slow
def test_a_build_without_simd_marches_in_scalar_code(tmp_path):
    """``-DRM_NO_SIMD`` (what other compilers and CPUs build): ``raycast_simd`` is 0, the cast says it did not use
    AVX-512 although allowed, and its results are the installed module's (AVX-512 where this CPU has it)."""
    built = build_without_simd(tmp_path, "mapping")
    repo = SCRIPT.parents[1]
    out = tmp_path / "casts.npz"
    script = ("import sys, importlib.util, numpy as np; "
              "spec = importlib.util.spec_from_file_location('mapping._ckernels', sys.argv[1]); "
              "c = importlib.util.module_from_spec(spec); spec.loader.exec_module(c); "
              "from tests.test_raycast_simd import synthetic_cast, SIZES; "
              "r = [synthetic_cast(s, True, s % 2 == 0, *SIZES[s % 4], kernels=c) for s in range(8)]; "
              "np.savez(sys.argv[2], *[a for x in r for a in x[:3]]); "
              "print(c.raycast_simd, sum(x[3] for x in r))")
    run = subprocess.run([sys.executable, "-c", script, str(built), str(out)], cwd=repo, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["0", "0"]
    theirs = np.load(out)
    for s in range(8):
        ours = synthetic_cast(s, True, s % 2 == 0, *SIZES[s % 4])
        for i in range(3):
            np.testing.assert_array_equal(theirs[f"arr_{3 * s + i}"], ours[i], err_msg=f"seed {s}")
