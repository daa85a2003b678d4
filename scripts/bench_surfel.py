#!/usr/bin/env python
"""Benchmark of the surfel backend at 640x480 on one core, against peers in the same run.

Scene: an analytic textured room (6 x 3 x 6 m) seen by a camera moving inside it. The map is built by
fusing the first ``--warmup`` frames (a realistic in-view map: the surfels a real run would have where the
camera looks), then padded with stable surfels of other "rooms" far away to reach each total size
(0.3M, 1M, 3M by default): these cost only the per-frame pass over the map (cull, unstable rule), which is
what the map size changes in a real session; that pass skips blocks of the map out of view (see
``mapping.fusion.surfel``), so the padding shows what a large map costs beyond the part in view. Each size
starts from the same fused state and integrates and renders the same ``--frames`` frames.

Times are CPU time of the process (``time.process_time``), so that other jobs on a shared machine do not
inflate them; wall time of integrate is printed beside.

"Fusion" is what the issue counts: association and update (``integrate``) plus the histogram of the colour
pairs, timed as the pipeline does it (``mapping.pipeline._Loop._measure``): the display conversion of the
pairs (``ColourModel.display_l1``: for ``--colour irradiance``, the default, the corrected runs' response
forward at k_ref through a gamma 2.2 response; for ``--colour raw`` a clip) and
``DisagreementHistogram.add_distances``. The ``hist`` column is that step alone, ``fusion fps`` counts both.

Peers measured in the same run (ratios printed):
- ``np transform``: one vectorised ``pos @ R.T + t`` of the whole map, the floor of any method that touches
  every surfel per frame;
- Open3D's VoxelBlockGrid TSDF integration of the same frames (``--voxel``, one thread), the engine of the
  other backend.

Run:  python scripts/bench_surfel.py                 (pins itself to CPU 0, one Numba/OpenCV thread)
      python scripts/bench_surfel.py --sizes 0.3,1 --frames 20
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one core: before NumPy loads
    os.environ.setdefault(_var, "1")

import argparse  # noqa: E402
import copy  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from mapping.simulation.trajectory import look_at  # noqa: E402

TARGET_FPS = 30.0  # fusion (integrate + histogram) frames/s with 1M surfels in the map, one core


# --------------------------------------------------------------------------------------------------
# analytic room
# --------------------------------------------------------------------------------------------------
def intrinsics(w: int = 640, h: int = 480, f: float = 525.0) -> np.ndarray:
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])


def albedo(p: np.ndarray) -> np.ndarray:
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.stack([130 + 60 * np.sin(1.3 * x + 0.4) * np.cos(0.9 * y),
                     120 + 70 * np.sin(0.8 * y + 1.1 * z),
                     125 + 65 * np.cos(1.0 * z - 0.7 * x)], axis=-1)


def render_room(pose, K, w, h, lo=(-3.0, -1.5, -3.0), hi=(3.0, 1.5, 3.0)):
    u, v = np.meshgrid(np.arange(w), np.arange(h))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((h, w))], -1).reshape(-1, 3)
    d = rays @ pose[:3, :3].T
    o = pose[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        tb = np.where(d > 0, (np.asarray(hi) - o) / d, (np.asarray(lo) - o) / d)
    t = np.min(np.where(np.isfinite(tb) & (tb > 0), tb, np.inf), axis=1)
    pts = o + d * t[:, None]
    return t.reshape(h, w).astype(np.float32), pts.reshape(h, w, 3)


def trajectory(i: int) -> np.ndarray:
    a = 0.05 * i
    eye = [0.6 * np.sin(0.3 * a), 0.1 * np.cos(0.5 * a), 0.6 * np.cos(0.3 * a) - 0.3]
    target = [2.5 * np.sin(a), 0.2 * np.sin(0.7 * a), 2.5 * np.cos(a) + 1.0]
    return look_at(eye, target, up=(0.0, -1.0, 0.0))  # world axes as the first camera's: y down


def make_frames(start: int, count: int, K, w, h, seed: int, response=None):
    """Frames of the room: depth with Kinect-like noise, colour in intensity levels (float32) or, with a
    ``response``, relative irradiance ``f^-1(I)`` (the map units of a corrected run)."""
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(start, start + count):
        pose = trajectory(i)
        depth, pts = render_room(pose, K, w, h)
        depth = depth + rng.normal(0, 1, depth.shape).astype(np.float32) * 0.0015 * depth ** 2
        colour = (albedo(pts) + rng.normal(0, 5, pts.shape)).astype(np.float32)
        if response is not None:
            colour = response.inverse(colour)
        frames.append((depth.astype(np.float32), colour, pose))
    return frames


# --------------------------------------------------------------------------------------------------
# measurements
# --------------------------------------------------------------------------------------------------
def pad_map(backend, total: int) -> None:
    """Add stable surfels outside the room (copies of the fused ones, 100 m away per copy)."""
    smap = backend.map
    base = backend.surfels()
    n0 = base["position"].shape[0]
    k = 1
    while len(smap) < total:
        m = min(n0, total - len(smap))
        smap.append(base["position"][:m] + np.float32(100.0 * k), base["normal"][:m], base["radius"][:m],
                    np.full(m, 50.0, np.float32), base["colour"][:m], 0, backend._tick - 1)
        k += 1


def time_backend(backend, frames, K, w, h, first_index: int, colour_model):
    """Per frame: median CPU seconds (process time: the machine may be shared) of integrate, of the histogram
    step (display conversion of the pairs and binning, as the pipeline does it) and of render; the median wall
    seconds of integrate, mean colour pairs, mean surfels in view, the mean CPU ms per stage and the
    histogram (its mean L1, a check that the pairs were counted)."""

    from mapping.histogram import DisagreementHistogram

    histogram = DisagreementHistogram(label="bench")
    t_int, t_hist, t_ren, t_wall, pairs, visible = [], [], [], [], [], []
    backend.timings.clear()
    for i, (depth, colour, pose) in enumerate(frames):
        w0, t0 = time.perf_counter(), time.process_time()
        p = backend.integrate(depth, colour, K, pose, frame_index=first_index + i)
        w1, t1 = time.perf_counter(), time.process_time()
        if len(p):
            histogram.add_distances(colour_model.display_l1(p.map_colour, p.sample_colour))
        t2 = time.process_time()
        backend.render(pose, K, h, w)
        t3 = time.process_time()
        t_int.append(t1 - t0)
        t_hist.append(t2 - t1)
        t_ren.append(t3 - t2)
        t_wall.append(w1 - w0)
        pairs.append(len(p))
        visible.append(backend.last_frame["visible"])
    stages = {k: 1000 * v / len(frames) for k, v in backend.timings.items()}
    return {"integrate": statistics.median(t_int), "hist": statistics.median(t_hist),
            "fusion": statistics.median(np.add(t_int, t_hist)), "render": statistics.median(t_ren),
            "wall": statistics.median(t_wall), "pairs": statistics.mean(pairs), "visible": statistics.mean(visible),
            "stages": stages, "histogram": histogram}


def time_numpy_transform(pos: np.ndarray, pose: np.ndarray, repeats: int = 5) -> float:
    """CPU seconds of one vectorised world-to-camera transform of every surfel (best of ``repeats``)."""
    rot = pose[:3, :3].T.astype(np.float32)
    t = (-pose[:3, :3].T @ pose[:3, 3]).astype(np.float32)
    best = np.inf
    for _ in range(repeats):
        t0 = time.process_time()
        _ = pos @ rot.T + t
        best = min(best, time.process_time() - t0)
    return best


def time_open3d_tsdf(frames, K, w, h, voxel: float, depth_max: float) -> float | None:
    try:
        from mapping._open3d import o3d
    except Exception as exc:  # pragma: no cover - optional peer
        print(f"open3d peer skipped: {exc}")
        return None
    core = o3d.core
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                        attr_dtypes=(core.float32, core.float32, core.float32),
                                        attr_channels=((1), (1), (3)), voxel_size=voxel, block_resolution=16,
                                        block_count=100000)
    intr = core.Tensor(K, core.float64)
    times = []
    for depth, colour, pose in frames:
        t0 = time.process_time()
        dimg = o3d.t.geometry.Image(core.Tensor(depth))
        cimg = o3d.t.geometry.Image(core.Tensor(np.ascontiguousarray(colour / 255.0, dtype=np.float32)))
        extr = core.Tensor(np.linalg.inv(pose), core.float64)
        blocks = vbg.compute_unique_block_coordinates(dimg, intr, extr, 1.0, depth_max)
        vbg.integrate(blocks, dimg, cimg, intr, extr, 1.0, depth_max)
        times.append(time.process_time() - t0)
    return statistics.median(times[2:] if len(times) > 4 else times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="0.3,1,3", help="map sizes in millions of surfels")
    ap.add_argument("-n", "--num-frames", type=int, default=30, help="timed frames per size")
    ap.add_argument("--warmup", type=int, default=25, help="frames fused before timing (in-view map)")
    ap.add_argument("--stride", type=int, default=2, help="pixel_stride of the backend (2 = ElasticFusion)")
    ap.add_argument("--max-depth", type=float, default=4.0, help="fusion depth cut-off, metres (the room is 6 m)")
    ap.add_argument("--cpu", type=int, default=0, help="CPU to pin to (-1: no pinning)")
    ap.add_argument("--voxel", type=float, default=0.01, help="voxel size of the Open3D TSDF peer, metres")
    ap.add_argument("--no-tsdf", action="store_true", help="skip the Open3D TSDF peer")
    ap.add_argument("--colour", choices=("irradiance", "raw"), default="irradiance",
                    help="map units: irradiance through a gamma 2.2 response (a corrected run) or raw levels")
    args = ap.parse_args()

    if args.cpu >= 0 and hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {args.cpu})
    import cv2
    import numba

    from mapping import _native

    numba.set_num_threads(1)        # the surfel kernels
    _native.set_num_threads(1)      # the display look-ups (C by default)
    cv2.setNumThreads(1)
    from mapping.colour import RawIntensity, make_colour_model
    from mapping.fusion.surfel import SurfelBackend
    from radiometry.response import CameraResponse

    w, h = 640, 480
    K = intrinsics(w, h)
    response = CameraResponse.gamma(2.2) if args.colour == "irradiance" else None
    colour_model = RawIntensity() if response is None else make_colour_model(response)
    warm = make_frames(0, args.warmup, K, w, h, seed=1, response=response)
    timed = make_frames(args.warmup, args.num_frames, K, w, h, seed=2, response=response)

    base = SurfelBackend(pixel_stride=args.stride, depth_max=args.max_depth)
    for i, (depth, colour, pose) in enumerate(warm):
        base.integrate(depth, colour, K, pose, frame_index=i)
    base.stats()  # applies the pending unstable rule
    base.map.compact()
    n_local = len(base.map)
    print(f"640x480, one core (CPU {args.cpu}, numba threads {numba.get_num_threads()}), pixel_stride {args.stride}, "
          f"colour {args.colour}; in-room map after {args.warmup} frames: {n_local} surfels "
          f"({base.stats()['stable_surfels']} stable)")

    tsdf = None if args.no_tsdf else time_open3d_tsdf(timed, K, w, h, args.voxel, args.max_depth)
    header = (f"{'surfels':>9} {'in view':>8} {'integrate':>10} {'(wall)':>8} {'hist':>7} {'fusion fps':>10} "
              f"{'render':>8} {'fus+ren fps':>11} {'pairs':>7} {'np transform':>12} {'int/np':>7}")
    print("CPU time per frame (process time), medians; wall time in brackets; fusion = integrate + hist")
    print(header)
    rows = []
    for size in (float(s) for s in args.sizes.split(",")):
        total = int(round(size * 1e6))
        backend = copy.deepcopy(base)
        if total > n_local:
            pad_map(backend, total)
        n = len(backend.map)
        r = time_backend(backend, timed, K, w, h, args.warmup, colour_model)
        t_np = time_numpy_transform(backend.map.position, timed[-1][2])
        rows.append((n, r))
        print(f"{n:>9} {r['visible']:>8.0f} {1000 * r['integrate']:>8.1f}ms {1000 * r['wall']:>6.1f}ms "
              f"{1000 * r['hist']:>5.2f}ms {1 / r['fusion']:>10.1f} {1000 * r['render']:>6.1f}ms "
              f"{1 / (r['fusion'] + r['render']):>11.1f} {r['pairs']:>7.0f} {1000 * t_np:>10.1f}ms "
              f"{r['integrate'] / t_np:>7.1f}")
    print("\nper-stage mean CPU ms per frame (integrate; hist = display conversion + binning of the pairs):")
    for n, r in rows:
        print(f"  {n:>9}: " + ", ".join(f"{k} {v:.1f}" for k, v in r["stages"].items())
              + f"; hist {1000 * r['hist']:.2f} ({r['histogram'].total} pairs, "
              f"L1 mean {r['histogram'].stats()['mean']:.2f})")
    for n, r in rows:
        if abs(n - 1e6) < 1e5:
            fps = 1 / r["fusion"]
            print(f"\ntarget >= {TARGET_FPS:.0f} fusion frames/s at 1M surfels (issue 17): "
                  f"{'met' if fps >= TARGET_FPS else 'NOT met'} ({fps:.1f})")
    if tsdf is not None:
        print(f"\npeer: Open3D VoxelBlockGrid TSDF integrate ({args.voxel * 1000:.0f} mm voxels, one thread) "
              f"{1000 * tsdf:.1f} CPU ms/frame ({1 / tsdf:.1f} fps)")
        for n, r in rows:
            print(f"  surfel integrate / TSDF integrate at {n} surfels: {r['integrate'] / tsdf:.2f}")

if __name__ == "__main__":
    main()
