"""The compiled C kernels against their Numba twins (radiometry._native): the same bits on every kernel of the TSDF
path, the display look-ups, the depth pyramid and the uint8 correction, over varied random inputs with the
awkward values in them (no depth, NaN normals and colours, colour past the 16-bit range, saturated weights,
blocks missing next to the ones read); the same reconstruction end to end; Numba never imported on the C path;
the choice and its errors."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
import shutil
from pathlib import Path

import numpy as np
import pytest

from mapping import _native
from radiometry._native import choice, compiled

REPO = Path(__file__).resolve().parents[1]


def _have_c() -> bool:
    try:
        return compiled("mapping._ckernels") is not None and compiled("radiometry._ckernels") is not None
    except ImportError:
        return False


needs_c = pytest.mark.skipif(not _have_c(), reason="the C extensions are not built (no C compiler at install, "
                                                   "or RADIOMAP_KERNELS=numba)")


def _same(a, b) -> bool:
    """Bit-identical arrays (NaN where NaN)."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@pytest.mark.slow
def test_the_extensions_are_built_where_a_compiler_is():
    """An install with a C compiler builds both extensions (setup.py makes them optional: a build that fails
    silently would leave radiomap on Numba's kernels and its memory)."""
    if choice() == "numba":
        pytest.skip("RADIOMAP_KERNELS=numba")
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(cc) is None:
        pytest.skip(f"no C compiler ({cc}) on this machine: the Numba kernels run")
    assert _have_c(), "mapping._ckernels / radiometry._ckernels were not built: pip install -e . prints why"


def _build(tmp_path, cc: str) -> subprocess.CompletedProcess:
    """``setup.py build_ext`` into ``tmp_path`` (never over the installed extensions) with compiler ``cc``."""
    env = dict(os.environ, CC=cc)
    env.pop("LDSHARED", None)
    return subprocess.run([sys.executable, "setup.py", "build_ext", "--build-lib", str(tmp_path / "lib"),
                           "--build-temp", str(tmp_path / "tmp")], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)


@pytest.mark.slow
def test_an_install_without_a_c_compiler_goes_on(tmp_path):
    """No working compiler: both extensions are skipped with a warning, the build succeeds (Numba's kernels run)."""
    proc = _build(tmp_path, "/bin/false")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert 'building extension "mapping._ckernels" failed' in proc.stdout + proc.stderr
    assert not list(tmp_path.rglob("*.so"))


@pytest.mark.slow
def test_a_compiler_without_openmp_builds_serial_kernels(tmp_path):
    """A compiler that refuses -fopenmp: the extensions build without it, run on one thread, same bits."""
    cc = (sysconfig.get_config_var("CC") or "cc").split()[0]
    if shutil.which(cc) is None or sys.platform == "win32":
        pytest.skip(f"no C compiler ({cc})")
    wrapper = tmp_path / "cc-no-openmp"
    wrapper.write_text(f'#!/bin/sh\nfor a in "$@"; do [ "$a" = -fopenmp ] && exit 1; done\nexec {shutil.which(cc)} "$@"\n')
    wrapper.chmod(0o755)
    proc = _build(tmp_path, str(wrapper))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "did not build with OpenMP; trying without" in proc.stdout
    script = ("import sys, numpy as np; sys.path.insert(0, sys.argv[1]); import mapping._ckernels as c; "
              "assert c.__file__.startswith(sys.argv[1]), c.__file__; "
              "from mapping._native import _colour; from mapping.colour import FastForward; "
              "from radiometry.response import CameraResponse; ff = FastForward(CameraResponse.gamma(2.2)); "
              "a = np.random.default_rng(0).random((999, 3), np.float32); b = a[::-1].copy(); "
              "t = (ff._tables, ff._inv_slope, ff._starts, ff._lo, ff._inv_width); "
              "x, y = np.empty(999, np.float32), np.empty(999, np.float32); c.l1(a, b, *t, x); "
              "_colour(False).l1(a, b, *t, y); print(c.get_num_threads(), x.tobytes() == y.tobytes())")
    run = subprocess.run([sys.executable, "-c", script, str(tmp_path / "lib")], cwd=tmp_path, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-2000:]
    assert run.stdout.split() == ["1", "True"]


# --------------------------------------------------------------------------------------------------
# a random sparse grid (blocks of res^3 voxels; a dense table of their slots) and a camera looking at it
# --------------------------------------------------------------------------------------------------
def _grid(rng, storage: str, res: int = 8, n_blocks: int = 48, offset=(0, 0, 0)):
    cells = np.array([(x, y, z) for x in range(-2, 2) for y in range(-2, 2) for z in range(-2, 2)], np.int32)
    cells += np.asarray(offset, np.int32)
    keys = cells[rng.choice(len(cells), n_blocks, replace=False)]
    slots = rng.permutation(n_blocks + 8)[:n_blocks].astype(np.int32)   # gaps: unused slots in the buffers
    n_vox = (n_blocks + 8) * res ** 3
    tsdf = rng.uniform(-1, 1, n_vox).astype(np.float32)
    if storage == "uint16":
        weight = rng.integers(0, 4, n_vox).astype(np.uint16)
        colour = rng.integers(0, 65536, 3 * n_vox).astype(np.uint16)
        scale = 8192.0
    else:
        weight = (rng.integers(0, 4, n_vox) * rng.uniform(0.5, 2, n_vox)).astype(np.float32)
        colour = (rng.uniform(0, 1.5, 3 * n_vox) * 255).astype(np.float32)
        scale = 255.0
    lo = keys.min(0).astype(np.int64) - 1
    hi = keys.max(0).astype(np.int64) + 1
    index = np.full(tuple(hi - lo + 1), -1, np.int32)
    index[tuple((keys - lo).T)] = slots
    return dict(keys=keys, slots=slots, tsdf=tsdf, weight=weight, colour=colour, scale=scale, lo=lo, index=index,
                res=res)


def _camera(rng, rows=36, cols=44):
    angle = rng.uniform(-0.3, 0.3, 3)
    Rc = _rotation(angle)
    o = np.array([0.0, 0.0, -1.2]) + rng.uniform(-0.1, 0.1, 3)
    depth = rng.uniform(0.4, 2.0, (rows, cols)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = 0.0
    depth[rng.random(depth.shape) < 0.02] = np.nan
    K = np.array([[40.0 + rng.uniform(-2, 2), 0, cols / 2 + 0.3], [0, 41.0, rows / 2 - 0.2], [0, 0, 1]])
    return Rc, o, depth, K


def _extrinsic(Rc, o) -> np.ndarray:
    """World-to-camera (3 x 4, float32) of a camera at ``o`` with camera-to-world rotation ``Rc``."""
    E = np.linalg.inv(np.block([[Rc, o[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))[:3]
    return np.ascontiguousarray(E, np.float32)


def _rotation(a):
    cx, cy, cz = np.cos(a)
    sx, sy, sz = np.sin(a)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


@pytest.fixture(scope="module")
def kernels():
    if not _have_c():
        pytest.skip("the C extensions are not built")
    return _native._tsdf(True), _native._tsdf(False)


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("storage", ["uint16", "float32"])
@pytest.mark.parametrize("seed", range(6))
def test_surface_colour_and_block_table(kernels, storage, seed):
    c, nb = kernels
    rng = np.random.default_rng(seed)
    g = _grid(rng, storage)
    Rc, o, depth, K = _camera(rng)
    f32 = np.float32
    Rc32, o32 = np.ascontiguousarray(Rc, f32), np.ascontiguousarray(o, f32)
    args = (depth, Rc32, o32, f32(K[0, 0]), f32(K[1, 1]), f32(K[0, 2]), f32(K[1, 2]))
    bs = f32(0.05 * g["res"])
    bounds_c, bounds_n = c.hit_bounds(*args, bs), nb.hit_bounds(*args, bs)
    assert _same(bounds_c[0], bounds_n[0]) and _same(bounds_c[1], bounds_n[1])
    tables = []
    for k in (c, nb):
        index = np.full(g["index"].shape, -1, np.int32)
        k.fill_block_table(g["keys"], g["slots"], g["lo"], index)
        tables.append(index)
    assert _same(tables[0], tables[1]) and _same(tables[0], g["index"])
    outs = []
    for k in (c, nb):
        out = np.full(depth.shape + (3,), 7.0, f32)
        k.surface_colour(*args, g["colour"], g["weight"], g["index"], g["lo"], g["res"], f32(0.05), f32(g["scale"]),
                         out)
        outs.append(out)
    assert _same(outs[0], outs[1])
    assert (outs[0] != 0).any(axis=2).mean() > 0.2         # the rays do reach observed voxels


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("storage", ["uint16", "float32"])
@pytest.mark.parametrize("seed", range(4))
def test_refine(kernels, storage, seed):
    c, nb = kernels
    rng = np.random.default_rng(100 + seed)
    g = _grid(rng, storage)
    # a plane of zero crossings: the TSDF of z = 0.02 x + 0.1 in voxel units, so that brackets change sign
    res, vs = g["res"], 0.05
    slot_of = {int(s): k for s, k in zip(g["slots"], g["keys"])}
    for s, key in slot_of.items():
        iz, iy, ix = np.meshgrid(np.arange(res), np.arange(res), np.arange(res), indexing="ij")
        x, z = (key[0] * res + ix) * vs, (key[2] * res + iz) * vs
        g["tsdf"][s * res ** 3:(s + 1) * res ** 3] = np.clip((0.02 * x + 0.1 - z) / (4 * vs), -1, 1).ravel()
    g["weight"][:] = np.where(rng.random(g["weight"].size) < 0.01, 0, 2)   # a few unobserved voxels
    Rc, o, depth, K = _camera(rng)
    depth = (np.where(depth > 0, 1.3, depth) + rng.normal(0, 0.03, depth.shape)).astype(np.float32)
    results = []
    for k in (c, nb):
        d, vertex = depth.copy(), rng.random(depth.shape + (3,)).astype(np.float32)
        vertex[:] = 0.25
        n = k.refine(d, vertex, K[0, 0], K[1, 1], K[0, 2], K[1, 2], np.ascontiguousarray(Rc), o.copy(), g["tsdf"],
                     g["weight"], g["index"], g["lo"], 3, vs)
        results.append((n, d, vertex))
    assert results[0][0] == results[1][0] > 0
    assert _same(results[0][1], results[1][1]) and _same(results[0][2], results[1][2])


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("seed", range(6))
def test_integrate_u16(kernels, seed):
    c, nb = kernels
    rng = np.random.default_rng(200 + seed)
    g = _grid(rng, "uint16")
    g["weight"][rng.random(g["weight"].size) < 0.05] = 65535          # saturated weights stay
    Rc, o, depth, K = _camera(rng)
    depth[rng.random(depth.shape) < 0.02] = np.inf
    colour = rng.uniform(0, 1.2, depth.shape + (3,)).astype(np.float32)
    colour[rng.random(colour.shape) < 0.03] = np.nan
    colour[rng.random(colour.shape) < 0.03] = -0.5
    colour[rng.random(colour.shape) < 0.03] = 9.0                     # past 65535 / 8192
    E = _extrinsic(Rc, o)
    f32 = np.float32
    outs = []
    for k in (c, nb):
        tsdf, weight, buf = g["tsdf"].copy(), g["weight"].copy(), g["colour"].copy()
        clipped = np.zeros(len(g["slots"]), np.int64)
        k.integrate_u16(depth, colour, f32(K[0, 0]), f32(K[1, 1]), f32(K[0, 2]), f32(K[1, 2]),
                        E, g["keys"], g["slots"].astype(np.int64), g["res"], f32(0.05),
                        f32(f32(4.0) * f32(0.05)), f32(1.8), 8192.0, tsdf, weight, buf, clipped)
        outs.append((tsdf, weight, buf, clipped))
    for a, b in zip(*outs):
        assert _same(a, b)
    assert (outs[0][1] != g["weight"]).sum() > 1000 and outs[0][3].sum() > 0   # voxels fused, colour clamped


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("debias", [True, False])
@pytest.mark.parametrize("seed", range(4))
def test_finish_view_and_colour_pairs(kernels, debias, seed):
    c, nb = kernels
    rng = np.random.default_rng(300 + seed)
    Rc, o, depth, K = _camera(rng)
    vertex = rng.normal(0, 1, depth.shape + (3,)).astype(np.float32)
    normal = rng.normal(0, 1, depth.shape + (3,)).astype(np.float32)
    normal[rng.random(depth.shape) < 0.05, 1] = np.nan
    vertex[rng.random(depth.shape) < 0.02] *= 1e-9                    # n.v below 1e-6: no debias there
    cvec = (Rc.T @ np.ones(3)).astype(np.float32)
    outs = []
    for k in (c, nb):
        v, n, d = vertex.copy(), normal.copy(), depth.copy()
        back = k.finish_view(v, n, d, cvec, np.float32(0.5 * 0.03), debias)
        assert back is d
        outs.append((v, n, d))
    for a, b in zip(*outs):
        assert _same(a, b)
    map_depth = (depth * rng.uniform(0.98, 1.02, depth.shape)).astype(np.float32)
    map_colour, colour = (rng.random(depth.shape + (3,)).astype(np.float32) for _ in range(2))
    f32 = np.float32
    pairs = []
    for k in (c, nb):
        om, os_ = np.empty((depth.size, 3), f32), np.empty((depth.size, 3), f32)
        n = k.colour_pairs(map_depth, depth, map_colour, colour, f32(0.01), f32(0.012), f32(0.3), f32(1.9), om, os_)
        pairs.append((n, om[:n], os_[:n]))
    assert pairs[0][0] == pairs[1][0] > 0
    assert _same(pairs[0][1], pairs[1][1]) and _same(pairs[0][2], pairs[1][2])


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("seed", range(5))
def test_range_fragments(kernels, seed):
    c, nb = kernels
    rng = np.random.default_rng(400 + seed)
    blocks = rng.integers(-40, 40, (3000, 3)).astype(np.int32)
    R = _rotation(rng.uniform(-np.pi, np.pi, 3)).astype(np.float32)
    t = rng.uniform(-1, 1, 3).astype(np.float32)
    f32 = np.float32
    outs = []
    for k in (c, nb):
        out = np.empty(len(blocks), np.int64)
        total = k.range_fragments(blocks, R, t, f32(525.0), f32(525.0), f32(319.5), f32(239.5), f32(8.0), 8,
                                  f32(0.01 * (1 + seed)), 60, 80, f32(0.1), f32(3.0), out)
        outs.append((total, out))
    assert outs[0][0] == outs[1][0] > 0 and _same(outs[0][1], outs[1][1])


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("diff", [0.14, 0.0, -1.0, 1e9])
@pytest.mark.parametrize("shape", [(480, 640), (37, 51), (1, 1), (2, 3)])
def test_pyrdown(shape, diff):
    rng = np.random.default_rng(sum(shape))
    depth = rng.uniform(0.5, 3, shape).astype(np.float32)
    depth[rng.random(shape) < 0.1] = 0.0
    depth[rng.random(shape) < 0.02] = np.nan
    depth[rng.random(shape) < 0.02] = np.inf    # a centre no neighbour is within diff of: NaN
    outs = []
    for kernel in (_native._pyrdown(True), _native._pyrdown(False)):
        out = np.empty(((shape[0] + 1) // 2, (shape[1] + 1) // 2), np.float32)
        outs.append(kernel(depth, diff, out))      # a Python float: each kernel takes it as float32
    assert _same(outs[0], outs[1])
    if diff <= 0:
        assert np.isnan(outs[0]).all()


@needs_c
def test_pyrdown_twins_agree_on_a_small_image():
    """The fast tier's check of the two depth-pyramid kernels (the C one and its Numba twin in
    mapping/_pyramid_kernels.py); test_pyrdown runs every shape and threshold."""
    test_pyrdown((37, 51), 0.14)


@needs_c
@pytest.mark.parametrize("gamma", [1.0, 2.2, 3.0])
def test_display_lookups(gamma):
    from mapping.colour import FastForward
    from radiometry.response import CameraResponse

    ff = FastForward(CameraResponse.gamma(gamma), reference_exposure=0.7)
    rng = np.random.default_rng(int(gamma * 10))
    a = (rng.random((20_001, 3)) * 2.0 - 0.2).astype(np.float32)
    b = (a * rng.uniform(0.8, 1.2, a.shape)).astype(np.float32)
    a[::97, 0], b[::89, 1], b[::83, 2] = np.nan, np.inf, -1.0
    tables = (ff._tables, ff._inv_slope, ff._starts, ff._lo, ff._inv_width)
    c, nb = _native._colour(True), _native._colour(False)
    fc, fn = np.empty_like(a), np.empty_like(a)
    assert c.forward(a, *tables, fc) is fc
    nb.forward(a, *tables, fn)
    assert _same(fc, fn)
    lc, ln = np.empty(len(a), np.float32), np.empty(len(a), np.float32)
    c.l1(a, b, *tables, lc)
    nb.l1(a, b, *tables, ln)
    assert _same(lc, ln)


@pytest.mark.slow
@needs_c
def test_parallel_kernels_do_not_depend_on_the_number_of_threads(kernels):
    c, _ = kernels
    rng = np.random.default_rng(9)
    g = _grid(rng, "uint16")
    Rc, o, depth, K = _camera(rng, 120, 160)
    f32 = np.float32
    threads = _native.get_num_threads()
    outs = []
    try:
        for n in (1, 2, 3):
            _native.set_num_threads(n)
            out = np.empty(depth.shape + (3,), f32)
            c.surface_colour(depth, np.ascontiguousarray(Rc, f32), o.astype(f32), f32(K[0, 0]), f32(K[1, 1]),
                             f32(K[0, 2]), f32(K[1, 2]), g["colour"], g["weight"], g["index"], g["lo"], g["res"],
                             f32(0.05), f32(g["scale"]), out)
            outs.append(out)
    finally:
        _native.set_num_threads(threads)
    assert _same(outs[0], outs[1]) and _same(outs[0], outs[2])
    with pytest.raises(ValueError, match="at least 1"):
        _native.set_num_threads(0)


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("channels,per_value", [(3, True), (3, False), (1, False), (4, False)])
def test_correction_lookups(channels, per_value):
    from radiometry import correction
    from radiometry.correction import Corrector
    from radiometry.response import CameraResponse
    from radiometry.vignetting import LUTVignetting

    rng = np.random.default_rng(channels)
    h, w = 48, 64
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = ((xx - 0.55 * w) ** 2 + (yy - 0.45 * h) ** 2) / (w * w / 4)
    falloff = np.stack([1 - 0.4 * r2 * (1 + 0.1 * c) for c in range(channels)], axis=2)  # per channel
    lut = falloff if per_value else falloff[:, :, 0]
    response = CameraResponse.gamma(2.2, channels=1 if channels != 3 else 3)
    corr = Corrector(response, LUTVignetting(np.clip(lut, 0.2, 1).astype(np.float32)))
    img = rng.integers(0, 256, (h, w, channels)).astype(np.uint8)
    q, k, table = corr._fast_tables(h, w, channels, 1.3)
    assert q.shape[1] == (channels if per_value else 1)
    c, nb = compiled("radiometry._ckernels"), correction._numba_kernels()
    src = img.reshape(-1)
    outs = []
    for lookup_rgb, lookup_shared in ((c.lookup_rgb, c.lookup_shared), nb[:2]):
        for qq in (q, q.astype(np.uint32)):            # uint32 past 65536 gain steps
            out = np.empty_like(src)
            if per_value:
                lookup_rgb(src, qq.reshape(-1), k, table, out)
            else:
                lookup_shared(src, qq.reshape(-1), k, table, out, channels)
            outs.append(out)
    assert all(_same(outs[0], out) for out in outs[1:])
    lut = rng.random((channels, 256)).astype(np.float32)
    for cg in {1, channels}:
        gain = rng.uniform(1, 2, (h * w, cg)).astype(np.float32)
        ic, inb = np.empty((h * w, channels), np.float32), np.empty((h * w, channels), np.float32)
        c.irradiance(img.reshape(-1, channels), lut, gain, ic)
        nb[2](img.reshape(-1, channels), lut, gain, inb)
        assert _same(ic, inb)


@pytest.mark.slow
@needs_c
@pytest.mark.parametrize("storage", ["uint16", "float32"])
def test_surface_colour_at_block_boundaries(kernels, storage):
    """Surface points a float32 step or so either side of block faces: where ``floor(p / block)`` rounds up, the
    voxel index inside the block is -1 and the neighbour is read through a Python-style modulo (blocks 16-19
    along z: the rounding needs coordinates of that size)."""
    c, nb = kernels
    rng = np.random.default_rng(77)
    g = _grid(rng, storage, offset=(0, 0, 18))
    f32 = np.float32
    rows, cols = 40, 48
    Rc, o = np.eye(3, dtype=f32), np.array([0.013, -0.021, -1.2], f32)
    bs = f32(0.05) * f32(g["res"])
    candidates = []
    for face in range(16, 21):                        # depths t with o_z + t within 6 float32 steps of a face
        t = f32(f32(bs * f32(face)) - o[2])
        for _ in range(6):
            t = np.nextafter(t, f32(-np.inf))
        for _ in range(13):
            candidates.append(t)
            t = np.nextafter(t, f32(np.inf))
    candidates = np.array(candidates, f32)
    zg = (o[2] + candidates * f32(1.0)).astype(f32)
    rounds_up = (zg - np.floor(zg / bs).astype(f32) * bs) < 0
    assert rounds_up.any()
    pick = np.where(rng.random((rows, cols)) < 0.5, rng.choice(np.flatnonzero(rounds_up), (rows, cols)),
                    rng.integers(0, len(candidates), (rows, cols)))
    t = candidates[pick]
    args = (t, Rc, o, f32(400.0), f32(400.0), f32(cols / 2), f32(rows / 2))   # rays within blocks x, y -2..1
    outs = []
    for k in (c, nb):
        out = np.empty((rows, cols, 3), f32)
        k.surface_colour(*args, g["colour"], g["weight"], g["index"], g["lo"], g["res"], f32(0.05), f32(g["scale"]),
                         out)
        outs.append(out)
    assert _same(outs[0], outs[1]) and (outs[0][rounds_up[pick]] != 0).any(axis=1).mean() > 0.3


@pytest.mark.slow
@needs_c
def test_python_float_scalars_give_the_same_bits(kernels):
    """Scalars are taken in the kernels' own types (float32, or float64 for refine and the colour scale), whatever
    the caller passes: Python floats give what NumPy float32 scalars give, in C and in Numba."""
    c, nb = kernels
    rng = np.random.default_rng(5)
    f32 = np.float32
    depth = np.full((6, 7), f32(0.1))
    depth[0, 0] = f32(0.30000001)
    colour = rng.random((6, 7, 3)).astype(f32)
    results = []
    for k in (c, nb):
        for scalars in ((0.0, 0.0, 0.05, 0.1), (f32(0.0), f32(0.0), f32(0.05), f32(0.1))):
            om, os_ = np.empty((42, 3), f32), np.empty((42, 3), f32)
            results.append(k.colour_pairs(depth, depth, colour, colour, *scalars, om, os_))
    assert len(set(results)) == 1 and results[0] == 41     # dmax 0.1 keeps the float32 0.1 pixels
    g = _grid(rng, "uint16")
    Rc, o, d, K = _camera(rng)
    d = np.nan_to_num(d, nan=0.0)
    E = _extrinsic(Rc, o)
    fused = []
    for k in (c, nb):
        for cast in (float, f32):
            tsdf, weight, buf = g["tsdf"].copy(), g["weight"].copy(), g["colour"].copy()
            k.integrate_u16(d, colour[:1, :1].repeat(36, 0).repeat(44, 1), cast(K[0, 0]), cast(K[1, 1]),
                            cast(K[0, 2]), cast(K[1, 2]), E, g["keys"], g["slots"].astype(np.int64), g["res"],
                            cast(0.05), cast(0.2), cast(1.8), 8192.0, tsdf, weight, buf,
                            np.zeros(len(g["slots"]), np.int64))
            fused.append(tsdf.tobytes() + weight.tobytes() + buf.tobytes())
    assert len(set(fused)) == 1


@pytest.mark.slow
@needs_c
def test_display_lookups_stay_inside_their_tables():
    """Tables whose bucket origin lies above a value (a caller's mistake) give bucket 0, never a read before the
    table, in both kernels; a table without buckets is refused."""
    from mapping.colour import FastForward
    from radiometry.response import CameraResponse

    ff = FastForward(CameraResponse.gamma(2.2))
    lo = np.full(3, 0.6, np.float32)
    x = np.array([[0.5, 0.55, 0.7]], np.float32)
    outs = []
    for k in (_native._colour(True), _native._colour(False)):
        out = np.empty_like(x)
        k.forward(x, ff._tables, ff._inv_slope, ff._starts, lo, ff._inv_width, out)
        outs.append(out)
    assert _same(outs[0], outs[1]) and ((outs[0] >= 0) & (outs[0] <= 255)).all()
    with pytest.raises(ValueError, match="starts: needs at least one bucket"):
        _native._colour(True).forward(x, ff._tables, ff._inv_slope, ff._starts[:0], ff._lo, ff._inv_width,
                                      np.empty_like(x))


@pytest.mark.slow
@needs_c
def test_integrate_and_l1_do_not_depend_on_the_number_of_threads(kernels):
    c, _ = kernels
    rng = np.random.default_rng(12)
    g = _grid(rng, "uint16")
    Rc, o, depth, K = _camera(rng, 120, 160)
    depth = np.nan_to_num(depth, nan=0.0)
    colour = rng.uniform(0, 1.2, depth.shape + (3,)).astype(np.float32)
    E = _extrinsic(Rc, o)
    from mapping.colour import FastForward
    from radiometry.response import CameraResponse

    ff = FastForward(CameraResponse.gamma(2.2))
    a = rng.random((30_001, 3)).astype(np.float32)
    f32 = np.float32
    threads = _native.get_num_threads()
    outs = []
    try:
        for n in (1, 2, 3):
            _native.set_num_threads(n)
            tsdf, weight, buf = g["tsdf"].copy(), g["weight"].copy(), g["colour"].copy()
            c.integrate_u16(depth, colour, f32(K[0, 0]), f32(K[1, 1]), f32(K[0, 2]), f32(K[1, 2]), E, g["keys"],
                            g["slots"].astype(np.int64), g["res"], f32(0.05), f32(0.2), f32(1.8), 8192.0, tsdf,
                            weight, buf, np.zeros(len(g["slots"]), np.int64))
            outs.append(tsdf.tobytes() + weight.tobytes() + buf.tobytes() + ff.l1(a, a[::-1].copy()).tobytes())
    finally:
        _native.set_num_threads(threads)
    assert outs[0] == outs[1] == outs[2]


# --------------------------------------------------------------------------------------------------
# bad arguments: a ValueError naming the argument, never a read past an array
# --------------------------------------------------------------------------------------------------
@needs_c
def test_bad_arguments_name_the_argument(kernels):
    c, _ = kernels
    f32 = np.float32
    depth = np.ones((4, 5), f32)
    with pytest.raises(ValueError, match="out: axis 0"):
        c.surface_colour(depth, np.eye(3, dtype=f32), np.zeros(3, f32), f32(1), f32(1), f32(2), f32(2),
                         np.zeros(24, np.uint16), np.zeros(8, np.uint16), np.zeros((1, 1, 1), np.int32),
                         np.zeros(3, np.int64), 2, f32(0.1), f32(1), np.zeros((3, 5, 3), f32))
    with pytest.raises(ValueError, match="depth: needs 2-d f32"):
        c.hit_bounds(depth.astype(np.float64), np.eye(3, dtype=f32), np.zeros(3, f32), 1, 1, 2, 2, 0.1)
    with pytest.raises(ValueError, match="C-contiguous"):
        c.colour_pairs(depth[:, ::2], depth[:, ::2], np.zeros((4, 3, 3), f32), np.zeros((4, 3, 3), f32), 0.1, 0.1,
                       0, 9, np.zeros((12, 3), f32), np.zeros((12, 3), f32))
    with pytest.raises(ValueError, match="slots: slot 5 is outside"):
        c.integrate_u16(depth, np.zeros((4, 5, 3), f32), 1, 1, 2, 2, np.zeros((3, 4), f32),
                        np.zeros((1, 3), np.int32), np.array([5], np.int64), 2, 0.1, 0.4, 3, 1.0,
                        np.zeros(16, f32), np.zeros(16, np.uint16), np.zeros(48, np.uint16), np.zeros(1, np.int64))
    with pytest.raises(ValueError, match="slots: slot 2305843009213693951 is outside"):   # (slot + 1) * 8 wraps to 0
        c.integrate_u16(depth, np.zeros((4, 5, 3), f32), 1, 1, 2, 2, np.zeros((3, 4), f32),
                        np.zeros((1, 3), np.int32), np.array([2 ** 61 - 1], np.int64), 2, 0.1, 0.4, 3, 1.0,
                        np.zeros(16, f32), np.zeros(16, np.uint16), np.zeros(48, np.uint16), np.zeros(1, np.int64))
    rc = compiled("radiometry._ckernels")
    with pytest.raises(ValueError, match="past the end of table"):
        rc.lookup_rgb(np.full(3, 255, np.uint8), np.zeros(3, np.uint16), np.full((3, 256), 9, np.uint32),
                      np.zeros(5, np.uint8), np.zeros(3, np.uint8))


def test_the_choice_and_its_errors(monkeypatch):
    from radiometry.errors import InstallationError

    monkeypatch.setenv("RADIOMAP_KERNELS", "fortran")
    with pytest.raises(InstallationError, match="RADIOMAP_KERNELS='fortran'.*auto, c or numba"):
        choice()
    monkeypatch.setenv("RADIOMAP_KERNELS", "numba")
    assert compiled("mapping._ckernels") is None
    monkeypatch.setenv("RADIOMAP_KERNELS", "c")
    with pytest.raises(InstallationError, match="RADIOMAP_KERNELS=c but mapping._no_such_kernels cannot be loaded "
                                                "\\(ModuleNotFoundError.*pip install -e ."):
        compiled("mapping._no_such_kernels")
    monkeypatch.setenv("RADIOMAP_KERNELS", "auto")
    assert compiled("mapping._no_such_kernels") is None


@pytest.mark.slow
def test_a_stale_or_broken_build_is_not_used(monkeypatch, tmp_path, caplog):
    """An extension built for other kernels (its ABI differs) or one that fails as it loads is not used: Numba runs,
    said once at INFO (not at every kernel call), and --version's summary says why."""
    import types

    from radiometry import _native as rn

    monkeypatch.setitem(sys.modules, "radiometry._stale_kernels", types.SimpleNamespace(ABI=rn.ABI - 1))
    (tmp_path / "broken_kernels_pkg").mkdir()
    (tmp_path / "broken_kernels_pkg" / "__init__.py").write_text("")
    (tmp_path / "broken_kernels_pkg" / "_ck.py").write_text("raise RuntimeError('invalid ELF header')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setenv("RADIOMAP_KERNELS", "auto")
    with caplog.at_level("INFO", logger="radiometry._native"):
        for _ in range(3):
            assert compiled("radiometry._stale_kernels") is None
            assert compiled("broken_kernels_pkg._ck") is None
    assert caplog.text.count(f"_stale_kernels was built for other kernels (ABI {rn.ABI - 1}, this radiomap needs "
                             f"{rn.ABI})") == 1
    assert caplog.text.count("broken_kernels_pkg._ck cannot be loaded (RuntimeError: invalid ELF header)") == 1
    monkeypatch.setattr(_native, "_c", lambda: (_ for _ in ()).throw(OSError("disk gone")))
    monkeypatch.setattr(_native, "unusable", lambda module: "")
    assert _native.summary() == "none usable: disk gone"


@pytest.mark.slow
@needs_c
def test_the_extensions_carry_the_abi_of_this_radiomap():
    from radiometry import _native as rn

    assert compiled("mapping._ckernels").ABI == compiled("radiometry._ckernels").ABI == rn.ABI
    assert _native.summary().startswith("C (OpenMP, ") or _native.summary() == "C (no OpenMP: one thread)"


@pytest.mark.slow
def test_a_wrong_choice_fails_before_a_command_writes_anything(tmp_path):
    env = dict(os.environ, RADIOMAP_KERNELS="fortran")
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-m", "mapping.cli", "correct", str(tmp_path / "in.png"), "-r", "x.npz",
                           "--vignetting", "v.npz", "-o", str(out)], capture_output=True, text=True, env=env,
                          timeout=120)
    assert proc.returncode in (1, 2) and not out.exists()
    proc = subprocess.run([sys.executable, "-m", "mapping.cli", "simulate", "room", "-o", str(out), "-n", "2"],
                          capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 1 and not out.exists()
    assert proc.stderr.strip().splitlines() == ["radiomap: error: RADIOMAP_KERNELS='fortran' is not a kernel choice: "
                                                "set it to auto, c or numba (or unset it)"]


# --------------------------------------------------------------------------------------------------
# end to end: the same reconstruction from both, and no Numba on the C path (ground-truth poses: Open3D's ICP
# sums in parallel, so two runs of the same kernels differ by ~0.2 mm; the kernels themselves are deterministic)
# --------------------------------------------------------------------------------------------------
_RUN = r"""
import json, sys
import numpy as np
from mapping.datasets import open_dataset
from mapping.factory import make_backend, make_tracker
from mapping.colour import make_colour_model
from mapping.pipeline import reconstruct
from mapping.simulation import sample_sequence
from radiometry.response import CameraResponse

ds = open_dataset(sample_sequence("room"))
colour = make_colour_model(CameraResponse.gamma(2.2)) if len(sys.argv) > 2 else None
backend = make_backend("tsdf", voxel_size=0.03, depth_max=4.0)
run = reconstruct(ds, colour_model=colour, backend=backend, poses="gt", progress=False)
mesh = backend.extract_mesh()
rows = np.concatenate([mesh.vertices, mesh.colours], axis=1)      # Open3D extracts in a parallel, varying order
rows = rows[np.lexsort(rows.T[::-1])]
np.savez(sys.argv[1], counts=run.histogram.counts, mesh=rows)
print(json.dumps({"numba": "numba" in sys.modules, "llvmlite": "llvmlite" in sys.modules}))
"""


def _reconstruct(tmp_path, kernels: str, *extra) -> tuple[dict, dict]:
    out = tmp_path / f"{kernels}.npz"
    env = dict(os.environ, RADIOMAP_KERNELS=kernels)
    proc = subprocess.run([sys.executable, "-c", _RUN, str(out), *extra], capture_output=True, text=True, env=env,
                          cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1]), dict(np.load(out))


@needs_c
@pytest.mark.slow
def test_the_same_reconstruction_from_both_and_no_numba_on_the_c_path(tmp_path):
    modules_c, run_c = _reconstruct(tmp_path, "c", "irradiance")
    modules_n, run_n = _reconstruct(tmp_path, "numba", "irradiance")
    assert modules_c == {"numba": False, "llvmlite": False}
    assert modules_n["numba"]
    assert run_c.keys() == run_n.keys()
    for key in run_c:
        assert _same(run_c[key], run_n[key]), key
    assert run_c["counts"].sum() > 10_000 and len(run_c["mesh"]) > 10_000
