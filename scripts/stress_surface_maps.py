#!/usr/bin/env python
"""Stress radiomap's vertex and normal maps against Open3D's own calls: the same bits on varied inputs (issue 33).

:mod:`mapping.surface_maps` relies on two things Open3D does not document: the float32 operations (and the 1e-5
floor on a normal's length) of ``create_vertex_map`` / ``create_normal_map``, which our C kernels repeat, and its
bilateral filter giving each pixel the same value whether the image is filtered whole or in bands with two rows
of overlap. Each case draws a depth image and intrinsics (``tests/surface_cases.py``: sizes from 1x5 to 640x480,
holes, zeros, depth steps, noise, millimetre scenes whose normals fall under the floor, flat planes, principal
points outside the image) and a band count (1-4), and compares vertex map, normals and filtered depth with
Open3D's whole-image calls bit for bit. Prints each failing case and a summary; exits 1 on any failure.

    python scripts/stress_surface_maps.py --runs 500
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=300, help="cases (default 300)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    from surface_cases import SIZES, depth_case, same

    from mapping import surface_maps
    from mapping._open3d import o3d

    if surface_maps._c() is None:
        print("stress_surface_maps: the compiled kernels are not built; nothing of ours to compare", file=sys.stderr)
        return 2
    rng = np.random.default_rng(args.seed)
    nan = float("nan")
    failed, pixels, start = 0, 0, time.perf_counter()
    for case in range(args.runs):
        shape = SIZES[rng.integers(len(SIZES))] if rng.random() < 0.7 else (int(rng.integers(1, 300)),
                                                                          int(rng.integers(1, 400)))
        depth, K = depth_case(rng, shape)
        parts = int(rng.integers(1, 5))
        surface_maps._threads = lambda parts=parts: parts   # noqa: B023 - this case's band count
        image = o3d.t.geometry.Image(o3d.core.Tensor.from_numpy(depth))
        Kt = o3d.core.Tensor(K)
        filtered = image.filter_bilateral(5, 5.0, 10.0)
        expected = (image.create_vertex_map(Kt, nan).as_tensor().numpy(),
                    filtered.create_vertex_map(Kt, nan).create_normal_map(nan).as_tensor().numpy(),
                    filtered.as_tensor().numpy().reshape(shape))
        got = (*surface_maps.maps(depth, K), surface_maps.bilateral(depth))
        bad = [name for name, a, b in zip(("vertex", "normal", "bilateral"), got, expected) if not same(a, b)]
        pixels += depth.size
        if bad:
            failed += 1
            print(f"case {case}: {shape}, {parts} bands: {', '.join(bad)} differ", flush=True)
    print(f"{args.runs} cases, {pixels:,} pixels, {failed} failed ({time.perf_counter() - start:.1f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
