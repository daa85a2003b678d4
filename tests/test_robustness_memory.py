"""The memory check is a bound where Open3D would crash (issue 31): every growth of the TSDF hash map is checked
against what the process may still allocate before Open3D allocates (a failed allocation inside Open3D was a
segfault: ``reconstruct`` of the 7-Scenes kitchen at ``--voxel-size 0.001`` passed the up-front estimate and
died). The headroom is bounded by MemAvailable, ``ulimit -v`` and the cgroup's limit.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from test_robustness import REPO, error_line, room, run  # noqa: F401 (fixture)

import mapping.validation as validation
from mapping.validation import GROWTH_RESERVE, MemoryEstimateError, check_growth


def test_check_growth_names_the_memory_and_the_options():
    with pytest.raises(MemoryEstimateError) as exc:
        check_growth(3 * 2 ** 30, what="the map growing to 9 blocks", available=2 * 2 ** 30)
    text = str(exc.value)
    assert "needs 3.00 GiB more but 2.00 GiB are available" in text and "--voxel-size" in text
    check_growth(2 ** 30, what="x", available=2 ** 30 + GROWTH_RESERVE)      # fits with the reserve: no error


def _frames(room, n):
    from mapping.datasets import open_dataset

    ds = open_dataset(room)
    return [ds[i] for i in range(n)]


@pytest.mark.slow
def test_the_hash_map_never_grows_past_the_headroom(room, monkeypatch):
    """At 5 mm the room's first frame needs more blocks than the initial capacity: the growth is refused when the
    headroom cannot hold it, and allowed when it can (the same frame, the same grid)."""
    from mapping.factory import make_backend

    frame = _frames(room, 1)[0]
    backend = make_backend("tsdf", voxel_size=0.005, depth_max=4.0)
    capacity = backend.grid.hashmap().capacity()
    monkeypatch.setattr(validation, "headroom", lambda: GROWTH_RESERVE + 10 * 2 ** 20)   # 10 MiB beyond the reserve
    with pytest.raises(MemoryEstimateError) as exc:
        backend.integrate(frame.depth, frame.rgb.astype(np.float32), frame.K, frame.pose)
    assert "growing to" in str(exc.value) and "--voxel-size" in str(exc.value)
    assert backend.grid.hashmap().capacity() == capacity                   # refused before Open3D allocated
    monkeypatch.setattr(validation, "headroom", lambda: 64 * 2 ** 30)
    backend.integrate(frame.depth, frame.rgb.astype(np.float32), frame.K, frame.pose)
    assert backend.grid.hashmap().capacity() > capacity


def test_a_run_that_outgrows_the_memory_is_one_line(room, tmp_path, monkeypatch):
    """Through the command: the up-front estimate lets the run start, the growth bound stops it (exit 1, one line);
    the results folder says the run failed."""
    import json

    monkeypatch.setattr(validation, "headroom", lambda: GROWTH_RESERVE)
    out = tmp_path / "out"
    error_line(run("reconstruct", room, "-o", out, "--poses", "gt", "--no-progress", "--voxel-size", "0.003",
                   "--depth-max", "4"), "growing to", "GiB are available", "--voxel-size")
    assert json.loads((out / "metrics.json").read_text())["status"] != "complete"


@pytest.mark.slow
def test_an_address_space_limit_bounds_the_headroom():
    """``ulimit -v`` (RLIMIT_AS) is part of the bound: a child with a limit sees at most that limit."""
    code = ("import resource; resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, resource.RLIM_INFINITY)); "
            "from mapping.validation import available_memory; print(available_memory())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert out.returncode == 0, out.stderr
    assert 0 <= int(out.stdout) < 3 * 2 ** 30
