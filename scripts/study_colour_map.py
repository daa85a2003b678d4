#!/usr/bin/env python
"""Study (issue 20): does radiometric correction first make Zhou & Koltun's colour-map optimisation better, faster
or unnecessary? {no correction, LUT + exposure compensation} x {no colour map, rigid, non-rigid}, on a simulated
room (with the colour error against the true radiance) and on the real 7-Scenes kitchen.

Per dataset, every 5th frame (positions 4, 9, ...) is withheld from fusion; the others are fused into a TSDF
(``voxel`` 2 cm) at the poses below; the colour-map stage (:func:`mapping.colour_map.colour_map_stage`: keyframes
the sharpest of each 5 fused frames, rigid 100 / non-rigid 50 iterations) runs on the fused mesh with the withheld
frames as its check; every variant is then judged on the withheld frames at their ground-truth poses
(:func:`mapping.holdout.evaluate_holdout`: PSNR and mean L1 per valid pixel, levels summed over channels, the
distance the disagreement histogram bins; each withheld frame's exposure fitted against the render). ``hist L1``
is the fusion's disagreement-histogram mean (the same map for every colour-map variant of a method). The
optimised mesh's figures are reported even when the stage rejected it (``kept`` says which mesh it kept).
``keyframes, 0 it`` is Open3D's re-colouring from the keyframes without optimisation (it separates the effect of
re-colouring from that of the optimisation); ``kf pose err cm`` the keyframes' median camera-centre error against
the ground truth before -> after the optimisation.

- room: ``radiomap simulate room`` with the ``asymmetric`` camera (S-shaped response per channel, strong non-radial
  vignetting, auto exposure and white balance), seed 1, ``--frames`` frames at ``--size``; LUT = the true V, the
  true response. Two pose conditions: ``gt`` (exact poses: nothing for the optimiser to fix) and ``noisy`` (every
  fused pose moved by N(0, 1 cm) per axis and N(0, 0.3 deg) per axis, seeded: pose error the optimiser should
  remove). ``colour err`` is :func:`mapping.compare.colour_error` (mean 8-bit display difference per channel
  against the true radiance after one global scale per channel).
- kitchen: 7-Scenes redkitchen frames 50-99 (640x480), ground-truth poses, gamma 2.2 assumed; LUT self-calibrated on
  frames 0-49 (``radiomap self-calibrate``), as in docs/guides/self_calibrate.md.

    nice -n 10 python scripts/study_colour_map.py -o /tmp/study_cm   # the full study: 9-11 min at load 9-14, 2 cores
    nice -n 10 python scripts/study_colour_map.py -o /tmp/study_cm --only room --frames 30
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
KITCHEN = REPO.parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"
EVERY = 5


def _noisy(poses: list, sigma_m: float, sigma_deg: float, seed: int) -> list:
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    out = []
    for pose in poses:
        p = np.array(pose, dtype=np.float64)
        p[:3, :3] = Rotation.from_rotvec(np.radians(rng.normal(0, sigma_deg, 3))).as_matrix() @ p[:3, :3]
        p[:3, 3] += rng.normal(0, sigma_m, 3)
        out.append(p)
    return out


def _models(response, lut):
    from mapping.colour import IrradianceColour, RawIntensity
    from mapping.exposure_compensation import CompensatedColour

    return {"none": RawIntensity, "lut+ec": lambda: CompensatedColour(IrradianceColour(response, lut, name="lut"))}


def run_dataset(name: str, dataset, fuse_poses: list, gt_poses: list, models: dict, *, scene, display_response,
                voxel: float, depth_max: float) -> list[dict]:
    """The six variants on one dataset (see the module doc); one row each."""
    from mapping.colour_map import MeshRenderer, colour_map_stage
    from mapping.compare.colour_error import colour_error
    from mapping.compare.geometry import MapGeometry, map_geometry
    from mapping.compare.run import FixedPoses, _poses_by_frame
    from mapping.factory import make_backend
    from mapping.holdout import evaluate_holdout, is_held_out
    from mapping.pipeline import reconstruct

    n = len(dataset)
    held = [i for i in range(n) if is_held_out(i, EVERY)]
    poses = [None if i in held else fuse_poses[i] for i in range(n)]
    held_frames = [dataset[i] for i in held]
    held_poses = [gt_poses[i] for i in held]
    rows = []
    for method, make in models.items():
        colour_model = make()
        backend = make_backend("tsdf", voxel_size=voxel, depth_max=depth_max)
        t0 = time.perf_counter()
        run = reconstruct(FixedPoses(dataset, poses), colour_model=colour_model, backend=backend, poses="gt",
                          progress=False, write_mesh=False)
        geometry = map_geometry(backend)
        fuse_s = time.perf_counter() - t0
        fused = _poses_by_frame(run, n)

        def error(colours):
            if scene is None:
                return None
            err = colour_error(MapGeometry(geometry.vertices, geometry.triangles, colours, geometry.normals),
                               colour_model, scene, display_response=display_response,
                               max_distance=max(3 * voxel, 0.03))
            return None if err is None else round(err.mean, 2)

        plain = evaluate_holdout(held_frames, held_poses, MeshRenderer(geometry.vertices, geometry.triangles,
                                                                       geometry.colours), colour_model)
        base = {"dataset": name, "method": method, "frames": n, "fused": run.fused, "held out": len(held),
                "vertices": len(geometry), "hist L1": round(run.histogram.stats()["mean"], 2)}
        rows.append({**base, "colour map": "-", "psnr": round(plain.psnr, 2), "L1": round(plain.l1, 2),
                     "colour err": error(geometry.colours), "seconds": round(fuse_s, 1), "kept": "-",
                     "keyframes": "-", "kf pose err cm": "-"})
        print(_line(rows[-1]), flush=True)
        for label, optimiser, iterations in (("keyframes, 0 it", "rigid", 0), ("rigid", "rigid", None),
                                             ("non-rigid", "non-rigid", None)):
            t0 = time.perf_counter()
            outcome = colour_map_stage(geometry.vertices, geometry.triangles, geometry.colours, dataset, fused,
                                       colour_model, method=optimiser, iterations=iterations,
                                       holdout=[(i, fuse_poses[i]) for i in held], depth_max=depth_max)
            stage_s = time.perf_counter() - t0
            r = outcome.result
            if r is None:
                rows.append({**base, "colour map": label, "psnr": None, "L1": None, "colour err": None,
                             "seconds": round(stage_s, 1), "kept": outcome.reason})
                print(_line(rows[-1]), flush=True)
                continue
            judged = evaluate_holdout(held_frames, held_poses, MeshRenderer(r.vertices, r.triangles, r.colours),
                                      colour_model)
            truth = np.stack([gt_poses[k] for k in r.keyframes])
            start = np.stack([fuse_poses[k] for k in r.keyframes])
            rows.append({**base, "colour map": label, "psnr": round(judged.psnr, 2), "L1": round(judged.l1, 2),
                         "colour err": error(r.colours), "seconds": round(r.seconds, 1),
                         "stage seconds": round(stage_s, 1), "kept": outcome.kept, "reason": outcome.reason,
                         "keyframes": len(r.keyframes),
                         "kf pose err cm": f"{_pose_error(start, truth):.2f}->{_pose_error(r.poses, truth):.2f}"})
            print(_line(rows[-1]), flush=True)
        del backend
    return rows


def _pose_error(poses: np.ndarray, truth: np.ndarray) -> float:
    """Median distance (cm) of the camera centres from the true ones."""
    return float(np.median(np.linalg.norm(poses[:, :3, 3] - truth[:, :3, 3], axis=1)) * 100)


COLUMNS = ("dataset", "method", "colour map", "psnr", "L1", "colour err", "hist L1", "seconds", "kept", "keyframes",
           "kf pose err cm")


def _line(row: dict) -> str:
    return "  ".join(f"{k}={row.get(k)}" for k in COLUMNS)


def room(out: Path, frames: int, size: tuple[int, int], voxel: float) -> list[dict]:
    from mapping.datasets import open_dataset
    from mapping.simulation.sequences import simulate_room
    from radiometry.vignetting import LUTVignetting

    seq = out / f"room_{frames}_{size[0]}x{size[1]}"
    if not (seq / "radiomap_sequence.json").is_file():
        simulate_room(seq, camera="asymmetric", seed=1, n_frames=frames, width=size[0], height=size[1],
                      progress=False, force=True)
    dataset = open_dataset(seq)
    response = dataset.true_response()
    lut = LUTVignetting(np.asarray(dataset.true_vignetting(), dtype=np.float32))
    gt = [dataset[i].pose for i in range(len(dataset))]
    rows = []
    for label, poses in (("room gt", gt), ("room noisy", _noisy(gt, 0.01, 0.3, seed=3))):
        rows += run_dataset(label, dataset, poses, gt, _models(response, lut), scene=dataset.true_room(),
                            display_response=response, voxel=voxel, depth_max=5.0)
    return rows


def kitchen(out: Path, voxel: float) -> list[dict]:
    from mapping.datasets import open_dataset
    from mapping.self_calibration import run_self_calibration
    from radiometry.api import read_vignetting
    from radiometry.response import CameraResponse

    if not KITCHEN.is_dir():
        print(f"skipping the kitchen: {KITCHEN} is absent", file=sys.stderr)
        return []
    response = CameraResponse.gamma(2.2)
    selfcal = out / "kitchen_selfcal"
    t0 = time.perf_counter()
    if not (selfcal / "vignetting.npz").is_file():
        run_self_calibration(KITCHEN, selfcal, response=None, poses="gt", frames=slice(0, 50), plots=False,
                             force=True, progress=False)
    print(f"self-calibration (frames 0-49): {time.perf_counter() - t0:.1f} s", flush=True)
    lut = read_vignetting(selfcal / "vignetting.npz")
    dataset = open_dataset(KITCHEN, frames=slice(50, 100))
    gt = [dataset[i].pose for i in range(len(dataset))]
    return run_dataset("kitchen", dataset, gt, gt, _models(response, lut), scene=None, display_response=response,
                       voxel=voxel, depth_max=3.0)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-o", "--output", type=Path, default=Path("/tmp/study_colour_map"))
    parser.add_argument("--only", choices=("room", "kitchen"), default=None)
    parser.add_argument("--frames", type=int, default=60, help="room frames (default 60)")
    parser.add_argument("--size", default="320x240", help="room image size (default 320x240)")
    parser.add_argument("--voxel", type=float, default=0.02, help="TSDF voxel in metres (default 0.02)")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    args.output.mkdir(parents=True, exist_ok=True)
    load = open("/proc/loadavg").read().split()[:3] if os.path.exists("/proc/loadavg") else []
    print(f"load average at start: {' '.join(load)}", flush=True)
    t0 = time.perf_counter()
    rows = []
    if args.only in (None, "room"):
        rows += room(args.output, args.frames, (width, height), args.voxel)
    if args.only in (None, "kitchen"):
        rows += kitchen(args.output, args.voxel)
    from radiometry.tables import format_table

    table = format_table([{k: r.get(k) for k in COLUMNS} for r in rows])
    print(table)
    end_load = open("/proc/loadavg").read().split()[:3] if os.path.exists("/proc/loadavg") else []
    print(f"total {time.perf_counter() - t0:.0f} s; load average at the end: {' '.join(end_load)}")
    (args.output / "study_colour_map.json").write_text(json.dumps(
        {"rows": rows, "load_start": load, "load_end": end_load, "seconds": time.perf_counter() - t0,
         "room": {"frames": args.frames, "size": args.size}, "voxel": args.voxel}, indent=1, default=str))
    (args.output / "study_colour_map.txt").write_text(table + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
