#!/usr/bin/env python
"""Benchmark radiomap's mapping pipeline against Open3D's own dense SLAM loop, in one run.

Both methods get the same frames, voxel size, block resolution, initial block count, truncation and depth
range, on the same device, each in a fresh process (so that peak memory, ``ru_maxrss``, is per method), in
alternating order, ``--repeats`` times; the table reports medians.

- open3d:   ``o3d.t.pipelines.slam.Model`` (``track_frame_to_model``, ``integrate``,
            ``synthesize_model_frame``), frames read with ``o3d.t.io.read_image`` (Open3D's example loop
            ``examples/python/t_reconstruction_system/dense_slam.py``); uint16 colour, no correction. As in
            the example, the model frame is ray cast without colour (``enable_color=False``).
- open3d-colour: the same loop casting colour too (``enable_color=True``): the like-for-like peer, since
            radiomap's histogram and exposure compensation need the map's colour at every pixel (the colour
            costs Open3D's ray cast ~30 ms of ~125 ms per 640x480 frame here).
- radiomap: :func:`mapping.pipeline.reconstruct`: loading through the dataset loader, radiometric
            correction to float irradiance (a gamma-2.2 response and a polynomial vignetting model),
            frame-to-model ICP, TSDF fusion of irradiance in the default 16-bit grid, the colour-disagreement
            histogram.
- radiomap-float32: the same with the float32 grid (``colour_storage="float32"``; not run unless listed in
            ``--methods``): the 16-bit grid's memory saving and its effect on the histogram mean, ATE and time,
            measured in the same run.
- radiomap-o3dcast: radiomap casting the map with Open3D's ``VoxelBlockGrid.ray_cast`` and its separate colour
            kernel (``ray_caster="open3d"``, the path before issue 33; not run unless listed): the own cast's
            saving and its results (histogram, ATE: the same bits expected) in the same run.
- radiomap-serial: radiomap reading each frame when its turn comes (``reconstruct(prefetch=0)``; not run unless
            listed): the default reads the next frame in a background thread (:mod:`mapping.prefetch`) while the
            current one is tracked, fused and cast; this measures what that overlap saves, in the same run.
- radiomap-scalar: radiomap with its AVX-512 paths off (``RADIOMAP_SIMD=0``: the ray cast's scalar march and colour,
            the correction's scalar look-up; not run unless listed): what the AVX-512 kernels save, in the same run.
- radiomap-numba: radiomap with its Numba kernels (``RADIOMAP_KERNELS=numba``; not run unless listed): what
            the compiled kernels save in memory and time, in the same run.

Reported: ms per frame, frames/s, the time ratios (ours / each Open3D loop; issue 17's target: <= 1.0 against
open3d-colour), ATE RMSE after Horn alignment against the dataset's ground truth (target: no worse than Open3D's),
peak RSS (target <= 1.2x Open3D's). Each run records the load average (``/proc/loadavg``, 1 minute) at its start
and end: the machine's load is printed beside every figure.

    python scripts/bench_pipeline.py                       # 7-Scenes sample, every frame, 1 cm voxels
    python scripts/bench_pipeline.py --frames 0:100:2 --voxel-size 0.02 --repeats 3 --json bench.json
    radiomap simulate room -o /tmp/room -n 500
    python scripts/bench_pipeline.py --sequence /tmp/room --frames 0:500 --scaling 100,250,500 \
        --methods open3d-colour,radiomap              # a 500-frame simulated room, time per frame as the map grows
    python scripts/bench_pipeline.py --methods open3d-colour,radiomap,radiomap-float32   # 16-bit vs float grid

The time ratio is the median over back-to-back pairs (the machine's load drifts between runs). ``--scaling``
adds the time per frame over the ``--window`` frames before each listed frame number (every method times each
frame: from the end of one frame to the end of the next, its loading included).

The figures are in docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_SEQUENCE = REPO.parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"
METHODS = ("open3d", "open3d-colour", "radiomap", "radiomap-float32", "radiomap-numba", "radiomap-o3dcast",
           "radiomap-serial", "radiomap-scalar")
PEERS = ("open3d", "open3d-colour")
OURS = ("radiomap", "radiomap-float32", "radiomap-numba", "radiomap-o3dcast", "radiomap-serial", "radiomap-scalar")


def parse_frames(text: str) -> slice:
    parts = [int(p) if p.strip() else None for p in text.split(":")]
    parts += [None] * (3 - len(parts))
    return slice(*parts[:3])


def _ate(stamps, poses, dataset) -> float | None:
    from mapping.metrics import absolute_trajectory_error

    gt = dataset.ground_truth()
    if gt is None or len(stamps) < 3:
        return None
    return absolute_trajectory_error(stamps, poses, gt[0], gt[1]).rmse


def _open(args):
    """The sequence as radiomap reads it (its loader: the folder's intrinsics file or ``--intrinsics``, the depth
    scale radiomap detects or ``--depth-scale``): both loops get the same frames, K and depth in metres."""
    from mapping.datasets import open_dataset

    return open_dataset(args.sequence, frames=parse_frames(args.frames), intrinsics=args.intrinsics,
                        depth_scale=args.depth_scale)


def _peak_mb() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def worker_open3d(args) -> dict:
    import numpy as np

    from mapping._open3d import o3d

    ds = _open(args)
    files = ds.frame_files
    device = o3d.core.Device(args.device)
    K = o3d.core.Tensor(ds.K)
    first = ds[0]
    T = o3d.core.Tensor(first.pose if first.pose is not None else np.eye(4))
    model = o3d.t.pipelines.slam.Model(args.voxel_size, args.block_resolution, args.block_count, T, device)
    input_frame = o3d.t.pipelines.slam.Frame(ds.height, ds.width, K, device)
    raycast_frame = o3d.t.pipelines.slam.Frame(ds.height, ds.width, K, device)
    stamps, poses = [], []
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        t0, cpu0 = time.perf_counter(), time.process_time()
        marks = []
        for i, f in enumerate(files):
            marks.append(time.perf_counter())
            depth = o3d.t.io.read_image(str(f.depth)).to(device)
            color = o3d.t.io.read_image(str(f.rgb)).to(device)
            input_frame.set_data_from_image("depth", depth)
            input_frame.set_data_from_image("color", color)
            if i > 0:
                result = model.track_frame_to_model(input_frame, raycast_frame, ds.depth_scale, args.depth_max,
                                                    args.depth_diff)
                T = T @ result.transformation
            poses.append(T.cpu().numpy())
            stamps.append(f.timestamp)
            model.update_frame_pose(i, T)
            model.integrate(input_frame, ds.depth_scale, args.depth_max, args.trunc)
            model.synthesize_model_frame(raycast_frame, ds.depth_scale, 0.1, args.depth_max, args.trunc,
                                         args.worker == "open3d-colour")
        marks.append(time.perf_counter())
        seconds, cpu = marks[-1] - t0, time.process_time() - cpu0
    return {"method": args.worker, "frames": len(files), "fused": len(files), "seconds": seconds, "cpu_seconds": cpu,
            "ate_m": _ate(np.array(stamps), np.array(poses), ds), "peak_rss_mb": _peak_mb(),
            "blocks": int(model.get_hashmap().size()), "frame_ms": (1000 * np.diff(marks)).tolist()}


class _FrameMarks:
    """Notes when each frame is done, from the pipeline's DEBUG line "frame K of N: ..." (the frames are read ahead
    in another thread, so the time a frame is asked for is not when the loop starts it)."""

    def __init__(self) -> None:
        import logging

        self.marks = [time.perf_counter()]
        self.handler = logging.Handler(logging.DEBUG)
        self.handler.emit = self._emit
        self.logger = logging.getLogger("mapping.pipeline")
        self.logger.addHandler(self.handler)
        self.logger.setLevel(logging.DEBUG)
        self.logger.propagate = False

    def _emit(self, record) -> None:
        if record.msg.startswith("frame %d of %d"):
            self.marks.append(time.perf_counter())

    def close(self) -> None:
        self.logger.removeHandler(self.handler)


def worker_radiomap(args) -> dict:
    import gc

    import numpy as np

    from mapping.colour import IrradianceColour
    from mapping.datasets.in_memory import ArrayDataset
    from mapping.factory import make_backend, make_tracker
    from mapping.pipeline import reconstruct
    from radiometry.response import CameraResponse
    from radiometry.vignetting import PolynomialVignetting

    ds = _open(args)
    w, h = ds.width, ds.height
    vignetting = PolynomialVignetting(np.tile([-0.3, 0.05, -0.02], (3, 1)),
                                      np.tile([w / 2 - 0.5, h / 2 - 0.5], (3, 1)), (w, h))
    colour = IrradianceColour(CameraResponse.gamma(2.2), vignetting)
    # load the kernels (C, or Numba's compiled and cached on disk) outside the timed loop, as Open3D's C++ is: a
    # throw-away run over the first three frames, freed before the measured run starts
    reconstruct(ArrayDataset([ds[0], ds[1], ds[2]]),
                colour_model=IrradianceColour(CameraResponse.gamma(2.2), vignetting),
                backend=make_backend("tsdf", voxel_size=0.05, depth_max=args.depth_max, block_count=64),
                tracker=make_tracker(depth_max=args.depth_max), progress=False)
    gc.collect()
    backend = make_backend("tsdf", voxel_size=args.voxel_size, depth_max=args.depth_max,
                           block_resolution=args.block_resolution, trunc_voxel_multiplier=args.trunc,
                           block_count=args.block_count, device=args.device,
                           colour_storage="float32" if args.worker == "radiomap-float32" else "uint16",
                           ray_caster="open3d" if args.worker == "radiomap-o3dcast" else "radiomap")
    tracker = make_tracker(depth_max=args.depth_max, depth_diff=args.depth_diff, motion_model=args.motion_model)
    timed = _FrameMarks()
    cpu0 = time.process_time()
    run = reconstruct(ds, colour_model=colour, backend=backend, tracker=tracker, progress=False,
                      prefetch=0 if args.worker == "radiomap-serial" else 1)
    cpu = time.process_time() - cpu0
    timed.close()
    stages = {k: 1000.0 * v / run.frames for k, v in run.stage_seconds.items()}
    from radiometry._native import compiled

    return {"method": args.worker, "kernels": "C" if compiled("mapping._ckernels") else "Numba",
            "frames": run.frames, "fused": run.fused, "seconds": run.seconds, "cpu_seconds": cpu,
            "ate_m": None if run.ate is None else run.ate.rmse, "peak_rss_mb": _peak_mb(),
            "blocks": run.map_stats.get("blocks"), "stage_ms": stages,
            "histogram_mean": run.histogram.mean(), "frame_ms": (1000 * np.diff(timed.marks)).tolist()}


def run_worker(method: str, args) -> dict:
    cmd = [sys.executable, __file__, "--worker", method, "--sequence", str(args.sequence), "--frames", args.frames,
           "--voxel-size", str(args.voxel_size), "--block-resolution", str(args.block_resolution),
           "--block-count", str(args.block_count), "--trunc", str(args.trunc), "--depth-max", str(args.depth_max),
           "--depth-diff", str(args.depth_diff), "--device", args.device, "--motion-model", args.motion_model]
    if args.intrinsics:
        cmd += ["--intrinsics", args.intrinsics]
    if args.depth_scale:
        cmd += ["--depth-scale", str(args.depth_scale)]
    load = _load()
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    if method == "radiomap-numba":
        env["RADIOMAP_KERNELS"] = "numba"
    if method == "radiomap-scalar":
        env["RADIOMAP_SIMD"] = "0"
    out = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if out.returncode != 0:
        how = f"signal {-out.returncode}" if out.returncode < 0 else f"exit code {out.returncode}"
        raise SystemExit(f"{method} worker failed ({how}):\n{out.stderr[-3000:]}")
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "load": [load, _load()]}


def _load() -> float:
    """The 1-minute load average (/proc/loadavg; NaN where there is none)."""
    try:
        return float(Path("/proc/loadavg").read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return float("nan")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--sequence", type=Path, default=DEFAULT_SEQUENCE)
    p.add_argument("--frames", default="0:100:1", help="A:B:S of the sequence (default every frame of 0..99)")
    p.add_argument("--intrinsics", help="fx,fy,cx,cy or a file, for a folder without an intrinsics file (as "
                   "radiomap's --intrinsics; default: the folder's file or the format's default)")
    p.add_argument("--depth-scale", type=float, help="raw depth units per metre (default: as radiomap detects it)")
    p.add_argument("--voxel-size", type=float, default=0.01)
    p.add_argument("--block-resolution", type=int, default=16)
    p.add_argument("--block-count", type=int, default=4000, help="initial hash-map capacity (both grow)")
    p.add_argument("--trunc", type=float, default=8.0, help="truncation in voxels")
    p.add_argument("--depth-max", type=float, default=3.0)
    p.add_argument("--depth-diff", type=float, default=0.07, help="ICP association threshold (m)")
    p.add_argument("--motion-model", default="constant_velocity", choices=("constant_velocity", "previous"))
    p.add_argument("--device", default="CPU:0")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--methods", default="open3d,open3d-colour,radiomap",
                   help=f"comma-separated subset of {', '.join(METHODS)}")
    p.add_argument("--scaling", help="comma-separated frame numbers (e.g. 100,250,500): time per frame before each")
    p.add_argument("--window", type=int, default=25, help="frames averaged before each --scaling frame number")
    p.add_argument("--json", type=Path, help="also write the results here")
    p.add_argument("--worker", choices=METHODS, help=argparse.SUPPRESS)
    args = p.parse_args(argv)

    if args.worker:
        result = (worker_radiomap if args.worker in OURS else worker_open3d)(args)
        print(json.dumps(result))
        return 0

    if not args.sequence.exists():
        print(f"bench_pipeline: {args.sequence} is absent (the shared data lives beside the checkout)", file=sys.stderr)
        return 1
    methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
    if "radiomap" not in methods or not set(methods) <= set(METHODS) or not set(methods) & set(PEERS):
        print(f"bench_pipeline: --methods must list radiomap and at least one of {', '.join(PEERS)}, got "
              f"{args.methods!r}", file=sys.stderr)
        return 1
    peers = tuple(m for m in PEERS if m in methods)
    runs: dict[str, list[dict]] = {m: [] for m in methods}
    for rep in range(args.repeats):
        order = methods if rep % 2 == 0 else methods[::-1]
        for method in order:
            r = run_worker(method, args)
            runs[method].append(r)
            print(f"  run {rep + 1} {method:16s} {1000 * r['seconds'] / r['frames']:7.1f} ms/frame  "
                  f"CPU {1000 * r['cpu_seconds'] / r['frames']:7.1f} ms/frame  "
                  f"ATE {100 * r['ate_m'] if r['ate_m'] is not None else float('nan'):5.2f} cm  "
                  f"peak {r['peak_rss_mb']:6.0f} MB  load {r['load'][0]:.1f}-{r['load'][1]:.1f}"
                  + (f"  {r['kernels']} kernels" if "kernels" in r else ""), file=sys.stderr)

    def med(method, key):
        vals = [r[key] for r in runs[method] if r.get(key) is not None]
        return statistics.median(vals) if vals else None

    summary = {}
    for m in methods:
        ms = statistics.median(1000 * r["seconds"] / r["frames"] for r in runs[m])
        summary[m] = {"ms_per_frame": ms, "fps": 1000.0 / ms, "ate_cm": None if med(m, "ate_m") is None
                      else 100 * med(m, "ate_m"), "peak_rss_mb": med(m, "peak_rss_mb"), "blocks": med(m, "blocks"),
                      "histogram_mean": med(m, "histogram_mean"),
                      "load": [min(r["load"][0] for r in runs[m]), max(r["load"][1] for r in runs[m])]}
    ours = tuple(m for m in OURS if m in methods)
    stages = {m: {} for m in ours}
    for m in ours:
        for r in runs[m]:
            for k, v in r.get("stage_ms", {}).items():
                stages[m].setdefault(k, []).append(v)
    # the machine's load drifts between runs: the ratio of each back-to-back pair, then their median
    pairs = {f"{m}/{peer}": [r["seconds"] / r["frames"] / (o["seconds"] / o["frames"])
                             for r, o in zip(runs[m], runs[peer])] for m in ours for peer in peers}
    ratios = {key: statistics.median(v) for key, v in pairs.items()}
    # CPU time (user + sys of the worker's loop, all its threads): what the work costs, less swayed by the load
    cpu_pairs = {f"{m}/{peer}": [r["cpu_seconds"] / o["cpu_seconds"] for r, o in zip(runs[m], runs[peer])]
                 for m in ours for peer in peers}
    cpu_ratios = {key: statistics.median(v) for key, v in cpu_pairs.items()}
    a, b = summary["radiomap"]["ate_cm"], summary[peers[0]]["ate_cm"]
    ate_ratio = a / b if (a is not None and b) else None
    from radiometry.tables import format_table

    rows = [{"method": m, "ms/frame": s["ms_per_frame"], "frames/s": s["fps"],
             "ATE cm": "-" if s["ate_cm"] is None else round(s["ate_cm"], 2), "peak MB": round(s["peak_rss_mb"]),
             "blocks": s["blocks"], "histogram mean": "-" if s["histogram_mean"] is None
             else round(s["histogram_mean"], 4), "load": f"{s['load'][0]:.1f}-{s['load'][1]:.1f}"}
            for m, s in summary.items()]
    print(f"sequence {args.sequence.name}, frames {args.frames}, voxel {args.voxel_size} m, block resolution "
          f"{args.block_resolution}, trunc {args.trunc} voxels, depth max {args.depth_max} m, {args.device}, "
          f"{args.repeats} repeats (medians)")
    print(format_table(rows))
    for key, value in ratios.items():
        note = " (the same loop casting colour too, as radiomap must; target <= 1.0)" \
            if key == "radiomap/open3d-colour" else ""
        print(f"time ratio {key}{note}: {value:.3f} (median of back-to-back pairs "
              f"{', '.join(f'{x:.3f}' for x in pairs[key])})")
    for key, value in cpu_ratios.items():
        print(f"CPU-time ratio {key}: {value:.3f} (pairs {', '.join(f'{x:.3f}' for x in cpu_pairs[key])})")
    peak_ratios = {m: summary[m]["peak_rss_mb"] / summary[peers[-1]]["peak_rss_mb"] for m in ours}
    for m, value in peak_ratios.items():
        print(f"peak memory ratio {m} / {peers[-1]}: {value:.2f} (target <= 1.2)")
    peak_ratio = peak_ratios["radiomap"]
    if "radiomap-float32" in ours and summary["radiomap-float32"]["histogram_mean"]:
        print(f"histogram mean radiomap / radiomap-float32: "
              f"{summary['radiomap']['histogram_mean'] / summary['radiomap-float32']['histogram_mean']:.5f} "
              f"(16-bit grid against float; target within 1 %)")
    if ate_ratio is not None:
        print(f"ATE ratio radiomap / {peers[0]}: {ate_ratio:.3f} (target <= 1.0; radiomap ATE {a:.2f} cm)")
    scaling = _scaling(runs, args) if args.scaling else []
    if scaling:
        loads = [x for rs in runs.values() for r in rs for x in r["load"]]
        print(f"time per frame (ms, median over repeats) over the {args.window} frames before frame n (1-minute load "
              f"average {min(loads):.1f}-{max(loads):.1f} at the runs' starts and ends):")
        print(format_table(scaling))
    for m in ours:
        print(f"{m} stage ms/frame: " + ", ".join(f"{k} {statistics.median(v):.1f}" for k, v in stages[m].items()))
    if args.json:
        args.json.write_text(json.dumps({"config": {k: str(v) for k, v in vars(args).items()}, "summary": summary,
                                         "time_ratios": ratios, "pair_ratios": pairs,
                                         "cpu_ratios": cpu_ratios, "cpu_pair_ratios": cpu_pairs, "ate_ratio": ate_ratio,
                                         "peak_ratio": peak_ratio, "peak_ratios": peak_ratios, "scaling": scaling,
                                         "runs": runs}, indent=2))
    return 0


def _scaling(runs: dict[str, list[dict]], args) -> list[dict]:
    """Rows of the scaling table: per frame number n of ``--scaling``, each method's median (over repeats) of
    its mean time per frame over frames ``n - window .. n - 1``, and radiomap's ratio to each peer."""
    rows = []
    for n in (int(x) for x in args.scaling.split(",") if x.strip()):
        row: dict = {"frame": n}
        for m, rs in runs.items():
            means = [statistics.fmean(r["frame_ms"][max(0, n - args.window):n]) for r in rs
                     if len(r["frame_ms"]) >= n]
            row[m] = round(statistics.median(means), 1) if means else "-"
        for ours in OURS:
            for peer in PEERS:
                if isinstance(row.get(peer), float) and isinstance(row.get(ours), float):
                    row[f"{ours}/{peer}"] = round(row[ours] / row[peer], 3)
        rows.append(row)
    return rows


if __name__ == "__main__":
    sys.exit(main())
