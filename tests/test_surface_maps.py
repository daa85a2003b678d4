"""Vertex and normal maps (mapping.surface_maps) against Open3D's own calls, bit for bit (issue 33)."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from surface_cases import SIZES, depth_case, same

from mapping import surface_maps
from mapping._open3d import o3d

NAN = float("nan")


def open3d_maps(depth, K):
    image = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(np.ascontiguousarray(depth)))
    Kt = o3d.core.Tensor(np.asarray(K, np.float64))
    vertex = image.create_vertex_map(Kt, NAN).as_tensor().numpy()
    normal = image.filter_bilateral(5, 5.0, 10.0).create_vertex_map(Kt, NAN).create_normal_map(NAN).as_tensor().numpy()
    return vertex, normal


def compiled():
    return surface_maps._c() is not None


@pytest.mark.parametrize("seed", range(4))
def test_maps_equal_open3d_bit_for_bit(seed):
    rng = np.random.default_rng(seed)
    for shape in SIZES:
        depth, K = depth_case(rng, shape)
        vertex, normal = surface_maps.maps(depth, K)
        ref_v, ref_n = open3d_maps(depth, K)
        assert same(vertex, ref_v), shape
        assert same(normal, ref_n), shape


def test_the_cases_reach_open3d_s_normal_floor():
    """The cases include normals shorter than 1e-5 before division (Open3D divides those by 1e-5): the floor is
    exercised, not assumed."""
    rng = np.random.default_rng(0)
    short = 0
    for _ in range(10):
        depth, K = depth_case(rng, (61, 83))
        _, ref_n = open3d_maps(depth, K)
        length = np.linalg.norm(ref_n, axis=2)
        short += int(np.count_nonzero(np.isfinite(length) & (length < 0.999)))
    assert short > 0


@pytest.mark.parametrize("parts", [2, 3, 4])
def test_bands_give_the_whole_image_s_bits(monkeypatch, parts):
    monkeypatch.setattr(surface_maps, "_threads", lambda: parts)
    rng = np.random.default_rng(10 + parts)
    for shape in ((480, 640), (240, 320), (129, 50), (64, 64)):
        depth, _ = depth_case(rng, shape)
        whole = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(depth)).filter_bilateral(5, 5.0, 10.0)
        assert same(surface_maps.bilateral(depth), whole.as_tensor().numpy().reshape(shape)), shape


def test_without_compiled_kernels_open3d_runs(monkeypatch):
    monkeypatch.setattr(surface_maps, "_c", lambda: None)
    depth, K = depth_case(np.random.default_rng(3), (120, 160))
    vertex, normal = surface_maps.maps(depth, K)
    ref_v, ref_n = open3d_maps(depth, K)
    assert same(vertex, ref_v) and same(normal, ref_n)


@pytest.mark.skipif(not compiled(), reason="the compiled kernels are not built here")
def test_concurrent_calls_from_many_threads_agree():
    """The band pool is shared: calls from several threads at once (a batch, the read-ahead thread) each get
    their own image's maps."""
    rng = np.random.default_rng(7)
    cases = [depth_case(rng, (240, 320)) for _ in range(6)]
    expected = [open3d_maps(d, K) for d, K in cases]
    errors = []

    def work(i):
        for _ in range(5):
            v, n = surface_maps.maps(*cases[i])
            if not (same(v, expected[i][0]) and same(n, expected[i][1])):
                errors.append(i)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(len(cases))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="no fork on this platform")
def test_a_forked_child_makes_its_own_band_pool():
    """A process that forks after the bands ran gets a pool of its own in the child (the parent's threads do not
    exist there: submitting to the parent's pool would wait forever). Only the pool is exercised in the child:
    OpenMP (GNU libgomp) itself does not survive a fork after use, which holds for every compiled kernel."""
    import os

    depth, _ = depth_case(np.random.default_rng(2), (240, 320))
    surface_maps.bilateral(depth)               # the parent's pool exists now
    parent_pool = surface_maps._executor()
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:                                # the child: use the pool, report, exit without pytest's teardown
        try:
            pool = surface_maps._executor()
            ok = pool is not parent_pool and pool.submit(lambda: 41 + 1).result(timeout=30) == 42
            os.write(write, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.close(write)
    answer = os.read(read, 1)
    os.waitpid(pid, 0)
    assert answer == b"1"


def test_bands_after_interpreter_shutdown_began():
    """Once the interpreter shuts down, ThreadPoolExecutor refuses new futures: a call then (an atexit handler here;
    a non-daemon thread still mapping after the main thread ended alike) filters every band in the calling thread
    and gives the same bits instead of RuntimeError. A child process, so that this one's pool is untouched."""
    import subprocess
    import sys
    from pathlib import Path

    script = (
        "import atexit, sys, numpy as np\n"
        "sys.path.insert(0, 'tests')\n"
        "from surface_cases import depth_case, same\n"
        "from mapping import surface_maps\n"
        "from mapping._open3d import o3d\n"
        "surface_maps._threads = lambda: 3\n"
        "depth, K = depth_case(np.random.default_rng(5), (240, 320))\n"
        "surface_maps.bilateral(depth)\n"                     # the pool exists and ran before the shutdown
        "def late():\n"
        "    whole = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(depth)).filter_bilateral(5, 5.0, 10.0)\n"
        "    ok = same(surface_maps.bilateral(depth), whole.as_tensor().numpy().reshape(depth.shape))\n"
        "    print('same' if ok else 'differ', flush=True)\n"
        "atexit.register(late)\n")
    proc = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).resolve().parents[1],
                          capture_output=True, text=True, timeout=300)
    assert proc.stdout.split() == ["same"], proc.stderr[-2000:]


@pytest.mark.parametrize("shape", [(0, 0), (5, 0), (0, 7), (64, 0)])
def test_an_image_without_pixels_gets_empty_maps(monkeypatch, shape):
    """A side of 0 (Open3D's calls fail on it with a multi-line error): empty maps of the right shape, with the
    compiled kernels and without."""
    for compiled_kernels in (True, False):
        if not compiled_kernels:
            monkeypatch.setattr(surface_maps, "_c", lambda: None)
        depth = np.zeros(shape, np.float32)
        vertex, normal = surface_maps.maps(depth, np.eye(3))
        assert vertex.shape == normal.shape == shape + (3,) and vertex.dtype == normal.dtype == np.float32
        assert surface_maps.bilateral(depth).shape == shape


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="K must be a 3x3"):
        surface_maps.vertex_map(np.ones((4, 4), np.float32), np.eye(4))
    with pytest.raises(ValueError, match=r"depth must be \(H, W\)"):
        surface_maps.smoothed_normals(np.ones((4, 4, 1), np.float32), np.eye(3))
