#!/usr/bin/env python
"""The ray cast's march with AVX-512 against the scalar march, in the same run (issue 33).

Fuses a sequence at its ground-truth poses (``TSDFBackend`` defaults: 1 cm voxels, 16^3 blocks, 16-bit storage),
then casts the map at some of its frames' poses with :meth:`TSDFBackend._cast_depth` (radiomap's kernel), turn
about with ``RADIOMAP_SIMD`` on and off (the kernel's AVX-512 march, ``mapping/_ckernels_raycast_simd.h``, and
its scalar march), without the colour pass (the march alone) and with it. Prints per variant the median CPU time
(every thread's, ``time.process_time``) and wall time per cast, ns of CPU per march step, the ratio SIMD / scalar,
and checks that both give the same depth, colour and step counts. Usage::

    python scripts/bench_raycast_simd.py                      # the 7-Scenes kitchen, 100 frames
    python scripts/bench_raycast_simd.py --frames 0:100 --casts 10 --repeats 5
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = REPO.parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"


def cast(backend, blocks, K, pose, h, w, colour: bool, simd: bool):
    """One cast by the kernel: (depth, colour, steps, rays, used SIMD, CPU s, wall s)."""
    os.environ["RADIOMAP_SIMD"] = "1" if simd else "0"
    hp, wp = -(-h // 8) * 8, -(-w // 8) * 8
    extrinsic = np.linalg.inv(pose)
    table = backend._frustum_table(blocks, K, pose, extrinsic, hp, wp)
    weight = min(backend.weight_threshold, float(max(backend.frames_integrated, 1)))
    c0, t0 = time.process_time(), time.perf_counter()
    depth, col = backend._cast_depth(blocks, table, K, pose, extrinsic, hp, wp, weight, (h, w) if colour else (0, 0))
    cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    return depth, col, backend.cast_steps, backend.cast_rays, backend.cast_simd, cpu, wall


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    p.add_argument("--intrinsics")
    p.add_argument("--frames", default="0:100", help="frames fused, a:b")
    p.add_argument("--casts", type=int, default=8, help="poses cast (spread over the fused frames)")
    p.add_argument("--repeats", type=int, default=5, help="casts per pose and variant")
    args = p.parse_args(argv)

    from mapping.datasets import open_dataset
    from mapping.fusion.tsdf import TSDFBackend

    a, b = (int(x) for x in args.frames.split(":")[:2])
    ds = open_dataset(args.sequence, frames=slice(a, b), intrinsics=args.intrinsics)
    backend = TSDFBackend(voxel_size=0.01, block_count=4000)
    for i in range(len(ds)):
        f = ds[i]
        backend.integrate(f.depth, f.rgb.astype(np.float32) / 255, ds.K, f.pose)
    picks = np.linspace(0, len(ds) - 1, args.casts).round().astype(int)
    times = {(c, s): [] for c in (False, True) for s in (False, True)}
    steps = rays = 0
    for i in picks:
        f = ds[i]
        blocks = backend._prepare(f.depth, ds.K, f.pose).blocks
        for colour in (False, True):
            ref = None
            for r in range(args.repeats):
                for simd in ((True, False) if r % 2 else (False, True)):    # alternate the order
                    d, c, n_steps, n_rays, used, cpu, wall = cast(backend, blocks, ds.K, f.pose, ds.height, ds.width,
                                                                  colour, simd)
                    if used != simd and simd:
                        print("the AVX-512 march did not run (CPU or build without it)")
                        return 1
                    got = (d.view(np.uint32).copy(), c.copy(), n_steps, n_rays)
                    if ref is None:
                        ref = got
                    elif not (np.array_equal(ref[0], got[0]) and np.array_equal(ref[1], got[1])
                              and ref[2:] == got[2:]):
                        print(f"frame {i}: the SIMD and scalar casts DIFFER")
                        return 1
                    times[(colour, simd)].append((cpu, wall))
            if not colour:
                steps, rays = steps + ref[2], rays + ref[3]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    per_cast_steps = steps / len(picks)
    print(f"{args.sequence.name}: {len(ds)} frames fused, {len(picks)} poses x {args.repeats} casts per variant, "
          f"{per_cast_steps / 1e6:.2f} M steps / {rays / len(picks):,.0f} rays per cast, {os.cpu_count()} cores, "
          f"load average {load:.1f}; identical depth, colour and counts")
    print(f"{'variant':<22} {'CPU ms':>8} {'wall ms':>8} {'ns/step':>8}")
    med = {}
    for colour in (False, True):
        for simd in (False, True):
            cpu = float(np.median([t[0] for t in times[(colour, simd)]]))
            wall = float(np.median([t[1] for t in times[(colour, simd)]]))
            med[(colour, simd)] = (cpu, wall)
            name = f"{'AVX-512' if simd else 'scalar'} {'+ colour' if colour else 'march only'}"
            print(f"{name:<22} {1000 * cpu:8.1f} {1000 * wall:8.1f} {1e9 * cpu / per_cast_steps:8.1f}")
    for colour in (False, True):
        (cs, ws), (cv, wv) = med[(colour, False)], med[(colour, True)]
        print(f"{'with colour' if colour else 'march only'}: SIMD / scalar CPU {cv / cs:.3f} ({cs / cv:.2f}x faster), "
              f"wall {wv / ws:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
