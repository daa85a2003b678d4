#!/usr/bin/env python
"""Does radiometric correction help dense tracking? (issue 18: the paper's hypothesis, measured.)

Three frame-to-model trackers (``mapping.factory.TRACKERS``: point-to-plane ``icp``, Open3D's ``hybrid`` RGB-D
odometry, ``coloured-icp``) on the colour the map holds, for each colour model: ``raw`` levels, ``response``
(``f^-1(I)``), ``poly`` (``f^-1(I) / V`` with a radial polynomial) and ``lut`` (``f^-1(I) / V`` with the full
per-pixel V), each with exposure compensation on (``+ec``) and off (raw only off: compensation acts on
irradiance).

1. Sequences: simulated rooms (``xtion`` camera: S-shaped response, strong vignetting, corners at 0.45-0.52,
   auto white balance, noise; hand-held trajectory, structured-light depth) for several seeds. Auto exposure is
   made to act: the room's light follows ``1 + 0.35 sin(3 pi i / n)`` and the AE loop has no dead band
   (smoothing 0.6), so the exposure time changes about 2x over the sequence and the images' brightness by up to
   +-15 % (the AE lags the light); without it the AE of a 30-frame walk moves the exposure by under 2 %.
   ``--exposure fixed`` is the control: the same rooms with fixed exposure and white balance (vignetting only).
   Also the real 7-Scenes kitchen sample (Kinect v1, AE/AWB on; no vignetting calibration exists for it, so only
   ``raw`` and ``response`` with an assumed gamma 2.2). Reported per run: ATE RMSE (Horn-aligned) against the
   ground truth, tracking failures (frames the tracker rejected), lost runs (``TrackingError``), time per
   tracked frame (tracking stage only).
2. Convergence basin (simulated room of the first seed): the map fused with ground-truth poses from frames
   ``0..m-1``, frame ``m`` aligned against the view at frame ``m-1``'s pose from its true pose perturbed by a random
   rotation of ``a`` degrees about a random axis and a translation of ``t`` cm in a random direction, for several
   sizes ``(t, a)``; success = accepted and within 1 cm and 0.5 degrees of the truth; mean iterations.

Models: the simulation's TRUE response and V (``truth/``) for ``response`` and ``lut``; ``poly`` is the least-
squares radial polynomial (``1 + b1 r^2 + b2 r^4 + b3 r^6`` about the image centre) fitted to the true V, so it
keeps the polynomial's model error (the shifted blue centre, the non-radial field) and nothing else. With the
calibrated models of the demo instead, ``lut`` and ``poly`` would add calibration noise of 0.3-1 level.

    python scripts/study_tracking.py --out /tmp/study            # the study (sizes in --help)
    python scripts/study_tracking.py --out /tmp/study --seeds 0 --frames 20 --no-kitchen --basin-trials 3  # quick
    python scripts/study_tracking.py --out /tmp/study --exposure fixed --trackers icp hybrid \
        --colours raw response lut --no-kitchen --basin-trials 0                # the control (vignetting only)

The summary table goes to OUT/summary.txt, every run to OUT/runs.csv and everything to OUT/study.json. The
figures of the last run are in docs/tracking.md (summary: docs/guides/reconstruct.md, "Tracking on irradiance").
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
KITCHEN = ROOT.parent / "shared" / "data" / "rgbd" / "redkitchen_7scenes_000-099"
TRACKERS = ("icp", "hybrid", "coloured-icp")
COLOURS = ("raw", "response", "response+ec", "poly", "poly+ec", "lut", "lut+ec")


def fit_radial_polynomial(V: np.ndarray):
    """The least-squares ``s_c (1 + b1 r^2 + b2 r^4 + b3 r^6)`` per channel about the image centre, r = 1 at the
    half diagonal (a :class:`radiometry.vignetting.PolynomialVignetting`)."""
    from radiometry.vignetting import PolynomialVignetting

    h, w = V.shape[:2]
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    cx, cy = (w - 1) / 2, (h - 1) / 2
    r2 = ((u - cx) ** 2 + (v - cy) ** 2).ravel() / (cx ** 2 + cy ** 2)
    A = np.stack([np.ones_like(r2), r2, r2 ** 2, r2 ** 3], axis=1)
    coeffs, scales = [], []
    for c in range(3):
        a = np.linalg.lstsq(A, V[..., c].ravel().astype(np.float64), rcond=None)[0]
        scales.append(a[0])
        coeffs.append(a[1:] / a[0])
    return PolynomialVignetting(np.array(coeffs), np.array([[cx, cy]] * 3), (w, h), np.array(scales))


def colour_model(name: str, response, vignetting: dict):
    """A colour model of the study by name (``vignetting``: ``{"poly": model, "lut": model}``)."""
    from mapping.colour import IrradianceColour, RawIntensity
    from mapping.exposure_compensation import CompensatedColour

    if name == "raw":
        return RawIntensity()
    base, _, ec = name.partition("+")
    model = IrradianceColour(response, vignetting.get(base), name=base)
    return CompensatedColour(model) if ec else model


def run_one(dataset, tracker_name: str, colour: str, response, vignetting: dict, *, depth_max: float,
            voxel_size: float) -> dict:
    from mapping.factory import make_backend, make_tracker
    from mapping.pipeline import TrackingError, reconstruct

    model = colour_model(colour, response, vignetting)
    tracker = make_tracker(tracker_name, depth_max=depth_max)
    backend = make_backend("tsdf", voxel_size=voxel_size, depth_max=depth_max)
    row = {"tracker": tracker_name, "colour": colour}
    t0 = time.perf_counter()
    try:
        run = reconstruct(dataset, colour_model=model, backend=backend, tracker=tracker, progress=False,
                          write_mesh=False)
    except TrackingError as exc:
        return {**row, "ate_cm": math.nan, "failures": math.nan, "lost": 1, "ms_per_frame": math.nan,
                "error": str(exc)[:120]}
    tracked = max(len(run.records) - 1, 1)
    failures = sum(1 for r in run.records[1:] if not r.fused and not r.reason.startswith("colour"))
    return {**row, "ate_cm": run.ate.rmse * 100 if run.ate else math.nan, "failures": failures, "lost": 0,
            "ms_per_frame": run.stage_seconds["track"] / tracked * 1000,
            "fallbacks": getattr(tracker, "exposure_fallbacks", 0), "seconds": time.perf_counter() - t0}


def random_rotation(axis_rng, degrees: float) -> np.ndarray:
    axis = axis_rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    a = np.radians(degrees)
    Kx = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(a) * Kx + (1 - np.cos(a)) * Kx @ Kx


def basin(dataset, m: int, colours: list[str], response, vignetting: dict, sizes: list[tuple[float, float]],
          trials: int, *, depth_max: float, voxel_size: float, seed: int = 0) -> list[dict]:
    """Success rate and iterations from perturbed initial poses (module doc, part 2)."""
    from mapping.factory import make_backend, make_tracker
    from mapping.metrics import rotation_angle
    from mapping.tracking_photometric import tracking_colour

    rows = []
    for colour in colours:
        model = colour_model(colour, response, vignetting)
        backend = make_backend("tsdf", voxel_size=voxel_size, depth_max=depth_max)
        for i in range(m):
            f = dataset[i]
            view = backend.render_for_frame(f.depth, f.K, f.pose)
            c = model.to_map(f, view, f.pose)
            backend.integrate(f.depth, c.colour, f.K, f.pose, view=view, valid=c.valid, frame_index=i)
        prev = dataset[m - 1]
        view = backend.render(prev.pose, prev.K, prev.height, prev.width)
        frame = dataset[m]
        tc = tracking_colour(model, frame.rgb)
        for name in TRACKERS:
            for t_cm, a_deg in sizes:
                rng = np.random.default_rng([seed, int(t_cm * 10), int(a_deg * 10)])
                ok, iters, secs = 0, [], []
                for _ in range(trials):
                    tracker = make_tracker(name, depth_max=depth_max)
                    tracker.start(prev.pose)
                    d = rng.normal(size=3)
                    init = frame.pose.copy()
                    init[:3, :3] = random_rotation(rng, a_deg) @ init[:3, :3]
                    init[:3, 3] += d / np.linalg.norm(d) * t_cm / 100
                    t0 = time.perf_counter()
                    res = tracker.align(frame.depth, frame.K, view, prev.pose, init, colour=tc)
                    secs.append(time.perf_counter() - t0)
                    err = np.linalg.inv(frame.pose) @ res.pose
                    good = res.ok and np.linalg.norm(err[:3, 3]) < 0.01 and \
                        np.degrees(rotation_angle(err[:3, :3])) < 0.5
                    ok += bool(good)
                    iters.append(res.iterations)
                rows.append({"tracker": name, "colour": colour, "t_cm": t_cm, "deg": a_deg,
                             "success": ok / trials, "iterations": float(np.mean(iters)),
                             "ms": float(np.median(secs)) * 1000})
                print(f"  basin {name:12s} {colour:12s} {t_cm:4.1f} cm {a_deg:4.1f} deg: {ok}/{trials}, "
                      f"{np.mean(iters):.1f} it", flush=True)
    return rows


def summarise(rows: list[dict]) -> list[dict]:
    """Mean over seeds per (sequence kind, tracker, colour)."""
    out = []
    keys = sorted({(r["sequence"].split(":")[0], r["tracker"], r["colour"]) for r in rows},
                  key=lambda k: (k[0], TRACKERS.index(k[1]), COLOURS.index(k[2])))
    for kind, tracker, colour in keys:
        sel = [r for r in rows if r["sequence"].split(":")[0] == kind and r["tracker"] == tracker
               and r["colour"] == colour]
        ate = [r["ate_cm"] for r in sel if np.isfinite(r["ate_cm"])]
        out.append({"sequences": kind, "tracker": tracker, "colour": colour, "runs": len(sel),
                    "lost": sum(r["lost"] for r in sel),
                    "ate_cm_mean": float(np.mean(ate)) if ate else math.nan,
                    "ate_cm_max": float(np.max(ate)) if ate else math.nan,
                    "failures": int(np.nansum([r["failures"] for r in sel])),
                    "ms_per_frame": float(np.nanmedian([r["ms_per_frame"] for r in sel]))})
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="folder for the rooms and the results (created)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--frames", type=int, default=30, help="frames per simulated room")
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--exposure", choices=("auto", "fixed"), default="auto",
                    help="auto: the rooms' AE acting on a changing light (module doc); fixed: the control, vignetting "
                         "only (no AE, no AWB, constant light)")
    ap.add_argument("--trackers", nargs="+", default=list(TRACKERS), choices=TRACKERS)
    ap.add_argument("--colours", nargs="+", default=list(COLOURS), choices=COLOURS)
    ap.add_argument("--kitchen", type=Path, default=KITCHEN)
    ap.add_argument("--kitchen-stride", type=int, default=4)
    ap.add_argument("--no-kitchen", action="store_true")
    ap.add_argument("--basin-frame", type=int, default=10)
    ap.add_argument("--basin-trials", type=int, default=6)
    ap.add_argument("--basin-colours", nargs="+", default=["raw", "response", "lut+ec"], choices=COLOURS)
    ap.add_argument("--voxel-size", type=float, default=0.02)
    args = ap.parse_args(argv)

    from mapping._open3d import o3d
    from mapping.datasets import open_dataset
    from mapping.simulation.sequences import simulate_room
    from radiometry.response import CameraResponse
    from radiometry.simulation import CameraSpec
    from radiometry.simulation.exposure import AutoExposure
    from radiometry.tables import csv_text, format_table
    from radiometry.vignetting import VignettingModel

    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    args.out.mkdir(parents=True, exist_ok=True)
    rows, started = [], time.perf_counter()
    basin_rows: list[dict] = []
    for seed in args.seeds:
        seq = args.out / f"room_{seed}" if args.exposure == "auto" else args.out / f"room_fixed_{seed}"
        if not (seq / "radiomap_sequence.json").exists():
            if args.exposure == "auto":
                camera = CameraSpec.preset("xtion", width=args.width, height=args.height,
                                           auto_exposure=AutoExposure(deadband_ev=0.0, smoothing=0.6))
                light = 1 + 0.35 * np.sin(3 * np.pi * np.arange(args.frames) / args.frames)
            else:  # the control: vignetting only (fixed exposure and white balance, constant light)
                camera = CameraSpec.preset("xtion", width=args.width, height=args.height, auto_exposure=None,
                                           auto_white_balance=None)
                light = None
            simulate_room(seq, camera=camera, seed=seed, n_frames=args.frames, light_scale=light, progress=False)
        dataset = open_dataset(seq)
        response = CameraResponse.load(seq / "truth" / "response.npz")
        lut = VignettingModel.load(seq / "truth" / "vignetting.npz")
        vignetting = {"lut": lut, "poly": fit_radial_polynomial(lut.evaluate(args.height, args.width))}
        for tracker in args.trackers:
            for colour in args.colours:
                kind = seq.name.rsplit("_", 1)[0]      # room, or room_fixed (the control)
                row = {"sequence": f"{kind}:{seed}", **run_one(dataset, tracker, colour, response, vignetting,
                                                               depth_max=4.0, voxel_size=args.voxel_size)}
                rows.append(row)
                print(f"{kind} {seed} {tracker:12s} {colour:12s} ATE {row['ate_cm']:6.2f} cm  failures "
                      f"{row['failures']}  lost {row['lost']}  {row['ms_per_frame']:.0f} ms/frame", flush=True)
        if seed == args.seeds[0] and args.basin_trials:
            sizes = [(1.0, 1.0), (3.0, 3.0), (6.0, 5.0), (10.0, 8.0)]
            basin_rows = basin(dataset, args.basin_frame, args.basin_colours, response, vignetting, sizes,
                               args.basin_trials, depth_max=4.0, voxel_size=args.voxel_size, seed=seed)
    if not args.no_kitchen:
        if not args.kitchen.is_dir():
            print(f"no kitchen sample at {args.kitchen}: skipped", file=sys.stderr)
        else:
            dataset = open_dataset(args.kitchen, frames=slice(0, 100, args.kitchen_stride))
            gamma = CameraResponse.gamma()
            for tracker in args.trackers:
                for colour in ("raw", "response", "response+ec"):
                    row = {"sequence": "kitchen", **run_one(dataset, tracker, colour, gamma, {}, depth_max=3.0,
                                                            voxel_size=args.voxel_size)}
                    rows.append(row)
                    print(f"kitchen {tracker:12s} {colour:12s} ATE {row['ate_cm']:6.2f} cm  failures "
                          f"{row['failures']}  lost {row['lost']}  {row['ms_per_frame']:.0f} ms/frame", flush=True)
    summary = summarise(rows)
    cols = ["sequences", "tracker", "colour", "runs", "lost", "ate_cm_mean", "ate_cm_max", "failures", "ms_per_frame"]
    text = format_table(summary, cols)
    if basin_rows:
        text += "\n\nconvergence basin (success rate, mean iterations)\n" + format_table(
            basin_rows, ["tracker", "colour", "t_cm", "deg", "success", "iterations", "ms"])
    with open("/proc/loadavg") as fh:
        load = fh.read().split()[:3]
    text += f"\n\n{time.perf_counter() - started:.0f} s, load {' '.join(load)}\n"
    columns = list(dict.fromkeys(k for r in rows for k in r))   # a lost run's row has other keys than the rest
    (args.out / "runs.csv").write_text(csv_text(rows, columns))
    (args.out / "summary.txt").write_text(text)
    (args.out / "study.json").write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()},
                                                     "runs": rows, "summary": summary, "basin": basin_rows},
                                                    indent=1, default=float))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
