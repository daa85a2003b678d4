#!/usr/bin/env python
"""Which tracker survives degenerate geometry? (issue 30: the default tracker chosen by measurement.)

Every tracker of ``mapping.factory.TRACKERS`` (and the auto tracker with either fallback) tracks and fuses:

- the shared RealSense office (``--intrinsics 615,615,320,240``, as the issue's target; its depth in millimetres,
  detected; a monitor and a desk fill the view),
- the shared RealSense lamp shade (no options: its ``camera_intrinsic.json``),
- the shared 7-Scenes kitchen (ATE against its poses),
- a simulated room with plain walls (no furniture, no posters; the camera looks level, at the walls; ATE against
  the simulation's truth), 6 x 5 m with depth to 5 m (the whole room), and 3.4 x 3.4 m with depth cut at 2 m
  (``small-plain-room-cut``: a view holds about one wall, the degenerate case).

Reported per run: frames fused of the sequence, whether tracking was lost (the run kept a partial map), ATE
(Horn-aligned RMSE, cm) where there is truth, the auto tracker's frames per method, and seconds. ``auto`` is the
default (ICP; hybrid odometry where ICP's system is ill-conditioned or it fails), ``auto+colour-check`` also doubts
ICP's pose when the colours agree less there than at the prediction by 5 %, ``auto-coloured`` falls back to coloured
ICP. Open3D's
threaded reductions make runs differ slightly: ``--repeats`` runs each case again (the table lists every run).

    python scripts/bench_tracking.py --out /tmp/bench_tracking                 # the table of docs/tracking.md
    python scripts/bench_tracking.py --out /tmp/bt --trackers icp auto --sequences office   # one case
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
DATA = ROOT.parent / "shared" / "data" / "rgbd"

#: name -> (tracker name, options)
TRACKERS = {"icp": ("icp", {}), "auto": ("auto", {}), "auto+colour-check": ("auto", {"photometric_margin": 0.05}),
            "auto-coloured": ("auto", {"fallback": "coloured-icp"}),
            "hybrid": ("hybrid", {}), "coloured-icp": ("coloured-icp", {})}
SEQUENCES = ("office", "lampshade", "kitchen", "plain-room", "small-plain-room-cut")


def sequence(name: str, out: Path):
    """(dataset, depth_max) of a named case; None when its data is absent."""
    from mapping.datasets import open_dataset

    if name == "office":
        path = DATA / "realsense_office_d435"
        return (open_dataset(path, intrinsics="615,615,320,240"), 3.0) if path.is_dir() else None
    if name == "lampshade":
        path = DATA / "realsense_lampshade"
        return (open_dataset(path), 3.0) if path.is_dir() else None
    if name == "kitchen":
        path = DATA / "redkitchen_7scenes_000-099"
        return (open_dataset(path), 3.0) if path.is_dir() else None
    if name == "small-plain-room-cut":
        from mapping.simulation.room import make_room
        from mapping.simulation.sequences import simulate_room
        from mapping.simulation.trajectory import HandheldMotion

        folder = out / "small_plain_room"
        if not (folder / "rgb.txt").is_file():
            simulate_room(folder, seed=4, n_frames=80, width=320, height=240,
                          room=make_room(4, n_boxes=0, n_posters=0, size=(3.4, 3.4, 2.7)),
                          motion=HandheldMotion(pitch=0.0, speed=1.0), progress=False, force=True)
        return open_dataset(folder), 2.0   # depth beyond 2 m cut: a view holds about one wall
    if name == "plain-room":
        from mapping.simulation.room import make_room
        from mapping.simulation.sequences import simulate_room
        from mapping.simulation.trajectory import HandheldMotion

        folder = out / "plain_room"
        if not (folder / "rgb.txt").is_file():
            simulate_room(folder, seed=3, n_frames=80, width=320, height=240, room=make_room(3, n_boxes=0, n_posters=0),
                          motion=HandheldMotion(pitch=0.0, speed=1.0), progress=False, force=True)
        return open_dataset(folder), 5.0
    raise ValueError(f"unknown sequence {name!r}; choose from {', '.join(SEQUENCES)}")


def run_case(dataset, depth_max: float, tracker_key: str) -> dict:
    from mapping.factory import make_backend, make_tracker
    from mapping.pipeline import TrackingError, TrackingLostError, reconstruct
    from radiometry.errors import RadiomapError

    name, options = TRACKERS[tracker_key]
    tracker = make_tracker(name, depth_max=depth_max, **options)
    backend = make_backend("tsdf", voxel_size=0.01, depth_max=depth_max)
    t0 = time.perf_counter()
    lost = ""
    try:
        run = reconstruct(dataset, backend=backend, tracker=tracker, poses="icp", progress=False, write_mesh=False)
    except TrackingLostError as exc:
        run, lost = exc.run, "lost (partial map)"
    except (TrackingError, RadiomapError) as exc:
        return {"fused": 0, "frames": len(dataset), "lost": f"failed: {str(exc)[:60]}", "ATE cm": None,
                "seconds": round(time.perf_counter() - t0, 1), "methods": None}
    stats = tracker.stats() if hasattr(tracker, "stats") else None
    return {"fused": run.fused, "frames": len(dataset), "lost": lost,
            "ATE cm": None if run.ate is None else round(100 * run.ate.rmse, 2),
            "seconds": round(time.perf_counter() - t0, 1),
            "methods": None if stats is None else stats["frames_by_method"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--trackers", nargs="+", default=list(TRACKERS), choices=list(TRACKERS))
    parser.add_argument("--sequences", nargs="+", default=list(SEQUENCES), choices=list(SEQUENCES))
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args(argv)
    import logging

    logging.basicConfig(level=logging.ERROR)
    from mapping._open3d import o3d
    from radiometry.tables import format_table

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seq in args.sequences:
        case = sequence(seq, args.out)
        if case is None:
            print(f"{seq}: data absent, skipped", file=sys.stderr)
            continue
        dataset, depth_max = case
        for key in args.trackers:
            for rep in range(args.repeats):
                row = {"sequence": seq, "tracker": key, "run": rep + 1, **run_case(dataset, depth_max, key)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    table = format_table(rows)
    (args.out / "summary.txt").write_text(table + "\n")
    (args.out / "runs.json").write_text(json.dumps(rows, indent=1) + "\n")
    print(table)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
