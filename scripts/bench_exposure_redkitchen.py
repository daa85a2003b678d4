#!/usr/bin/env python
"""Exposure and white-balance compensation on real data: the 7-Scenes kitchen (Kinect v1, auto exposure and
auto white balance ON), colour disagreement with and without compensation, in one run.

Every method fuses the same frames at the ground-truth poses (so that only colour differs) into the same TSDF,
as irradiance ``f^-1(I) / V``:

- none:         no exposure compensation (every frame's own exposure);
- clip-mask:    no compensation, but clipped pixels (a channel >= 254, or all <= 3) are not fused (ablation);
- compensated:  exposure and white balance estimated per frame against the map (and frame to frame as a
                cross-check), fused irradiance divided by them, clipped pixels and fallback frames not fused.

The response of this camera is unknown: the documented assumption is ``CameraResponse.gamma(2.2)`` (sRGB-like).
Vignetting: none by default; ``--vignetting mild`` uses the mild polynomial ``V = 1 - 0.3 r^2 + 0.05 r^4 -
0.02 r^6`` (r = 1 at the half-diagonal), the same as ``bench_pipeline.py``. The histogram is in display levels
at the first frame's exposure (a fixed reference, the same for every method).

Reported: L1 disagreement mean / median / p90 (8-bit levels summed over R, G, B), the ratio compensated / none,
the range of the estimates, fallbacks and the map-vs-frame-to-frame cross-check.

    python scripts/bench_exposure_redkitchen.py                    # all 100 frames, 1 cm voxels
    python scripts/bench_exposure_redkitchen.py --frames 0:100:3 --json out.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = REPO.parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"
METHODS = ("none", "clip-mask", "compensated")


def parse_frames(text: str) -> slice:
    parts = [int(p) if p.strip() else None for p in text.split(":")]
    parts += [None] * (3 - len(parts))
    return slice(*parts[:3])


def mild_vignetting(width: int, height: int):
    from radiometry.vignetting import PolynomialVignetting

    return PolynomialVignetting(np.tile([-0.3, 0.05, -0.02], (3, 1)),
                                np.tile([width / 2 - 0.5, height / 2 - 0.5], (3, 1)), (width, height))


def run_method(method: str, args) -> dict:
    from mapping.colour import IrradianceColour
    from mapping.datasets import open_dataset
    from mapping.exposure_compensation import CompensatedColour
    from mapping.factory import make_backend
    from mapping.pipeline import reconstruct
    from radiometry.response import CameraResponse

    ds = open_dataset(args.sequence, frames=parse_frames(args.frames))
    vignetting = mild_vignetting(ds.width, ds.height) if args.vignetting == "mild" else None
    base = IrradianceColour(CameraResponse.gamma(2.2), vignetting)
    if method == "none":
        model = base
    else:
        model = CompensatedColour(base, compensate=(method == "compensated"))
    backend = make_backend("tsdf", voxel_size=args.voxel_size, depth_max=args.depth_max)
    t0 = time.perf_counter()
    run = reconstruct(ds, colour_model=model, backend=backend, poses="gt", progress=not args.no_progress)
    seconds = time.perf_counter() - t0
    out = {"method": method, "frames": run.frames, "fused": run.fused, "seconds": seconds,
           "histogram": run.histogram.stats(), "colour_ms_per_frame": 1000 * run.stage_seconds["colour"] / run.frames}
    est = getattr(model, "estimator", None)
    if est is not None:
        k = est.estimates()
        out["exposure"] = {"summary": est.summary(), "k_first": k[0].tolist(), "k_last": k[-1].tolist(),
                           "k_median": est.reference("median").tolist(),
                           "frames": [r.to_dict() for r in est.records]}
    return out


def warm_up(args) -> None:
    """Two frames through every stage, so that no method pays for Numba's first compilation."""
    short = argparse.Namespace(**{**vars(args), "frames": "0:2", "no_progress": True})
    run_method("compensated", short)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    p.add_argument("--frames", default="0:100:1", help="A:B:S of the sequence (default every frame of 0..99)")
    p.add_argument("--voxel-size", type=float, default=0.01)
    p.add_argument("--depth-max", type=float, default=3.0)
    p.add_argument("--vignetting", choices=("none", "mild"), default="none")
    p.add_argument("--json", type=Path, help="also write the results here")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if not args.sequence.exists():
        print(f"bench_exposure_redkitchen: {args.sequence} is absent (the shared data lives beside the checkout)",
              file=sys.stderr)
        return 1

    warm_up(args)   # compile the Numba kernels (colour, TSDF pairs) outside the timed runs
    results = {m: run_method(m, args) for m in METHODS}
    from radiometry.tables import format_table

    rows = []
    for m, r in results.items():
        h = r["histogram"]
        ex = r.get("exposure", {}).get("summary", {})
        rows.append({"method": m, "frames": r["frames"], "pairs": h["count"], "L1 mean": round(h["mean"], 2),
                     "L1 median": h["median"], "L1 p90": h["p90"], "fallbacks": ex.get("fallbacks", "-"),
                     "colour ms/frame": round(r["colour_ms_per_frame"], 1)})
    print(f"sequence {args.sequence.name}, frames {args.frames}, voxel {args.voxel_size} m, ground-truth poses, "
          f"response gamma 2.2 (assumed), vignetting {args.vignetting}")
    print(format_table(rows))
    none, comp = results["none"]["histogram"], results["compensated"]["histogram"]
    print(f"compensated / none: mean {comp['mean'] / none['mean']:.3f}, p90 {comp['p90'] / none['p90']:.3f}, "
          f"median {comp['median'] / max(none['median'], 1e-9):.3f}")
    ex = results["compensated"]["exposure"]
    s = ex["summary"]
    print(f"estimates (relative to frame {args.frames.split(':')[0] or 0}): last k = "
          f"{np.round(ex['k_last'], 3).tolist()}, range k_min {np.round(s['k_min'], 3).tolist()} .. k_max "
          f"{np.round(s['k_max'], 3).tolist()}, median {np.round(ex['k_median'], 3).tolist()}")
    print(f"sources {s['sources']}, fallbacks {s['fallbacks']} {s['fallback_reasons']}; map vs frame-to-frame "
          f"disagreement median {100 * (s['disagreement_median'] or float('nan')):.2f} %, p90 "
          f"{100 * (s['disagreement_p90'] or float('nan')):.2f} %")
    if args.json:
        from radiometry.fileio import atomic_write_json

        atomic_write_json(args.json, {"args": {k: str(v) for k, v in vars(args).items()}, "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
