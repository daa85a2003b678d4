#!/usr/bin/env python
"""Why a sequence's frames render slowly: per-frame statistics of the TSDF ray cast in radiomap's pipeline (issue 33).

Runs :func:`mapping.pipeline.reconstruct` (ICP, 16-bit grid, the settings of ``scripts/bench_pipeline.py``) over a
sequence and, for every ray cast, records what drives its cost: the blocks listed for the frame (the range map is
built from them), the blocks in the map, the rays that have a range to march (pixels whose 8x8 tile some listed
block covers), the march steps per ray, the pixels that found a surface, the measured depth (median, 90th
percentile, share beyond ``--depth-max``) and the holes (pixels without depth). The cast's own time (CPU time of
the kernel, which runs on every core) is divided by its steps: ns per step, whether the steps or their price
differ. Prints medians over the frames and the stages' ms/frame. Usage::

    python scripts/profile_render.py                                    # the 7-Scenes kitchen
    python scripts/profile_render.py --sequence ../shared/data/rgbd/realsense_office_d435 --intrinsics 615,615,320,240
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = REPO.parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    p.add_argument("--intrinsics")
    p.add_argument("--frames", default="0:100")
    p.add_argument("--depth-max", type=float, default=3.0)
    p.add_argument("--voxel-size", type=float, default=0.01)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)

    from mapping.colour import IrradianceColour
    from mapping.datasets import open_dataset
    from mapping.factory import make_backend, make_tracker
    from mapping.fusion import tsdf
    from mapping.pipeline import reconstruct
    from radiometry.response import CameraResponse
    from radiometry.vignetting import PolynomialVignetting

    a, b = (int(x) for x in args.frames.split(":")[:2])
    ds = open_dataset(args.sequence, frames=slice(a, b), intrinsics=args.intrinsics)
    w, h = ds.width, ds.height
    vig = PolynomialVignetting(np.tile([-0.3, 0.05, -0.02], (3, 1)), np.tile([w / 2 - 0.5, h / 2 - 0.5], (3, 1)),
                               (w, h))
    backend = make_backend("tsdf", voxel_size=args.voxel_size, depth_max=args.depth_max, block_count=4000)
    rows = []
    cast = tsdf.TSDFBackend._cast_depth

    def timed_cast(self, blocks, *args):
        c0, t0 = time.process_time(), time.perf_counter()
        depth, colour = cast(self, blocks, *args)
        rows.append({"listed": int(blocks.shape[0]), "map_blocks": int(self.grid.hashmap().size()),
                     "rays": self.cast_rays, "steps_per_ray": self.cast_steps / max(self.cast_rays, 1),
                     "hits": int(np.count_nonzero(depth)), "cast_cpu_ms": 1000 * (time.process_time() - c0),
                     "cast_wall_ms": 1000 * (time.perf_counter() - t0),
                     "ns_per_step": 1e9 * (time.process_time() - c0) / max(self.cast_steps, 1)})
        return depth, colour

    tsdf.TSDFBackend._cast_depth = timed_cast
    depth_rows = []
    for i in range(0, len(ds), 10):
        d = ds[i].depth
        valid = d[d > 0]
        depth_rows.append({"holes": float(np.mean(d == 0)), "median": float(np.median(valid)),
                           "p90": float(np.percentile(valid, 90)), "beyond": float(np.mean(valid > args.depth_max))})
    run = reconstruct(ds, colour_model=IrradianceColour(CameraResponse.gamma(2.2), vig), backend=backend,
                      tracker=make_tracker(depth_max=args.depth_max), progress=False)
    med = {k: float(np.median([r[k] for r in rows])) for k in rows[0]}
    dep = {k: float(np.median([r[k] for r in depth_rows])) for k in depth_rows[0]}
    stages = {k: 1000 * v / run.frames for k, v in run.stage_seconds.items()}
    print(f"{args.sequence.name}: {run.frames} frames, {run.fused} fused, {len(rows)} casts (medians over the casts; "
          f"casts beyond one per fused frame: the pipeline cast the map again for tracking where the frame's view "
          f"covered too little)")
    print("  cast: " + ", ".join(f"{k} {v:.1f}" for k, v in med.items()))
    print(f"  depth: holes {100 * dep['holes']:.1f} %, median {dep['median']:.2f} m, p90 {dep['p90']:.2f} m, "
          f"beyond depth max {100 * dep['beyond']:.1f} %")
    print("  stages ms/frame: " + ", ".join(f"{k} {v:.1f}" for k, v in stages.items()))
    if args.json:
        args.json.write_text(json.dumps({"casts": rows, "depth": depth_rows, "stages": stages}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
