"""Benchmark of the simulator: frames per second of rendering a room sequence, and of writing it.

Measures, on the same machine in the same run:

- ``raycast``: Open3D ``RaycastingScene.cast_rays`` alone for the same rays (the peer: the least any
  ray-cast renderer must spend),
- ``render``: :class:`mapping.simulation.Renderer` (ray cast + texture look-up + shading),
- ``frame``: a full simulated frame in memory (render + camera model + depth sensor),
- ``write``: ``simulate_room`` end to end (frames + PNG writing + ground truth files),

and prints frames/s for each plus the ratio render / raycast. A 100-frame 640 x 480 sequence must
take under a minute on 2 cores (the ``write`` line says how long it took).

    python scripts/bench_render.py [--frames 100] [--width 640] [--height 480]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-n", "--num-frames", type=int, default=100)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    from mapping.simulation import DepthSensor, Renderer, iter_room_frames, make_room, room_trajectory
    from mapping.simulation.sequences import resolve_camera, simulate_room
    from radiometry.simulation import default_intrinsics

    t0 = time.perf_counter()
    room = make_room(args.seed)
    _ = room.raycaster
    t_room = time.perf_counter() - t0
    K = default_intrinsics(args.width, args.height)
    n = args.num_frames
    poses = room_trajectory(room, n, seed=args.seed)
    renderer = Renderer(room, K, args.width, args.height)
    renderer.render(poses[0])   # warm up

    rays = [renderer.rays(p) for p in poses]
    t0 = time.perf_counter()
    for r in rays:
        room.cast(r)
    t_cast = time.perf_counter() - t0

    t0 = time.perf_counter()
    for p in poses:
        renderer.render(p)
    t_render = time.perf_counter() - t0

    cam = resolve_camera("xtion", args.width, args.height)
    t0 = time.perf_counter()
    for _ in iter_room_frames(room, cam, poses, K=K, seed=args.seed, depth_sensor=DepthSensor()):
        pass
    t_frame = time.perf_counter() - t0

    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        simulate_room(Path(tmp) / "seq", camera=cam, seed=args.seed, n_frames=n, room=room, progress=False)
        t_write = time.perf_counter() - t0

    size = f"{args.width}x{args.height}"
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"{os.cpu_count()} cores, load average {load:.1f} (other processes slow every line alike)")
    print(f"room generation + BVH: {t_room:.2f} s")
    print(f"{'stage':<10} {'frames/s':>9} {'ms/frame':>9}   ({n} frames, {size})")
    for name, t in (("raycast", t_cast), ("render", t_render), ("frame", t_frame), ("write", t_write)):
        print(f"{name:<10} {n / t:9.1f} {1000 * t / n:9.1f}")
    print(f"ratio render / raycast: {t_render / t_cast:.2f}")
    print(f"simulate_room end to end: {t_write:.1f} s for {n} frames "
          f"({'within' if t_write < 60 else 'OVER'} the 60 s budget for 100 frames: "
          f"{t_write * 100 / n:.1f} s per 100 frames)")


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
