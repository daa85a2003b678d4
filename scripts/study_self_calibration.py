#!/usr/bin/env python3
"""Self-calibration against the truth of a camera built independently of radiomap (issue 29).

The camera is ``tests/selfcal_camera.py`` (a real vignette and response from ``../shared/data``, auto exposure
and white balance, sensor noise on irradiance, full-well clip, 8 bits); the poses are the ground truth. For each
motion (a hand-held scan back and forth, one steady pan) and with or without the true exposures given, it runs
what ``radiomap self-calibrate`` runs (sightings, the solver on the fitted frames, validation on every 5th frame,
the ambiguity and plausibility checks) and prints per channel: V's error (RMS, 8-bit levels at level 200,
:func:`radiometry.vignetting_calibration.evaluate.vignetting_error_levels`), the median exposure error, the share
of pixels whose true V lies within 2 stated standard errors (both in V's gauge: 1 at the fitted centre), and
what the run told its user (ambiguity line, validation, warnings).

    python scripts/study_self_calibration.py --size 640 --frames 80

``--exact`` gives every sighting the exact value ``k V L`` of the truth (no noise, no clip): what is left is the
error the motion's geometry and V's model leave (docs/self_calibration.md).

``--real`` runs ``radiomap self-calibrate`` itself on the shared real recordings instead (the Kinect kitchen with
its poses, the two RealSense recordings tracked by radiomap; gamma 2.2 assumed: no response was calibrated for
these cameras) and prints what it told its user: validation, ambiguity, plausibility, V's corner/centre.

    python scripts/study_self_calibration.py --real
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def study(motion: str, *, frames: int, size: int, known: bool, seed: int = 0, exact: bool = False) -> dict:
    from selfcal_camera import selfcal_sequence

    from mapping.self_calibration import _solve_and_check, collect_observations
    from radiometry.response import CameraResponse
    from radiometry.self_calibration_validation import holdout_frames
    from radiometry.vignetting_calibration.evaluate import vignetting_error_levels

    t0 = time.perf_counter()
    ds, truth = selfcal_sequence(motion, frames=frames, width=size, height=size * 3 // 4, seed=seed)
    seq = [ds[i] for i in range(len(ds))]
    response = CameraResponse.from_table(truth.table)
    obs, _ = collect_observations(seq, [f.pose for f in seq], response, progress=False)
    if exact:       # the same sightings, values exactly k V L (no noise, no clip): what the geometry allows
        import dataclasses

        from scipy.ndimage import map_coordinates

        at = np.stack([np.asarray(obs.y, np.float64), np.asarray(obs.x, np.float64)])   # bilinear, sub-pixel
        v = np.stack([map_coordinates(truth.vignetting[:, :, c], at, order=1, mode="nearest") for c in range(3)],
                     axis=1)
        radiance = np.random.default_rng(seed).uniform(0.1, 0.5, (obs.n_points, 3))
        obs = dataclasses.replace(obs, irradiance=truth.exposures[obs.frame] * v * radiance[obs.point])
    K = seq[0].K
    held = holdout_frames(len(seq), "every:5")
    result, checks = _solve_and_check(obs, held, response, truth.exposures if known else None, "every:5",
                                      {"centre": (float(K[0, 2]), float(K[1, 2]))})
    v = result.vignetting.evaluate()
    se = result.vignetting.stderr
    levels = vignetting_error_levels(v, truth.vignetting, response)
    k_err = 100 * np.nanmedian(np.abs(result.exposures / truth.exposures - 1), axis=0)
    covered = []
    h, w = v.shape[:2]
    for c in range(3):
        cx, cy = result.info["centre"][c]
        tv = truth.vignetting[:, :, c] / truth.vignetting[int(np.clip(round(cy), 0, h - 1)),
                                                          int(np.clip(round(cx), 0, w - 1)), c]
        err = np.abs(np.log(v[:, :, c]) - np.log(tv))
        covered.append(float(np.mean(err <= 2 * se[:, :, c])))
    return {"motion": motion, "exposures_given": known, "exact_values": exact, "frames": frames,
            "size": f"{size}x{size * 3 // 4}",
            "v_error_levels": [round(float(x), 2) for x in levels],
            "exposure_error_median_pct": [round(float(x), 2) for x in k_err],
            "within_2_stderr_pct": [round(100 * x, 1) for x in covered],
            "stderr_median_pct": [round(100 * float(np.median(se[:, :, c])), 2) for c in range(3)],
            "tilt_visibility": result.info["tilt_visibility"], "ambiguity": bool(result.info.get("ambiguity")),
            "validation": checks["validation"], "warnings": checks["warnings"], "lines": checks["lines"],
            "seconds": round(time.perf_counter() - t0, 1)}


SHARED = Path(__file__).resolve().parents[2] / "shared" / "data" / "rgbd"
#: (name, folder, options): the shared real recordings as users have them
REAL = (
    ("kitchen 0-99, every 5th withheld", "redkitchen_7scenes_000-099", ["--poses", "gt"]),
    ("kitchen: fit 0-49, judge 50-99", "redkitchen_7scenes_000-099", ["--poses", "gt", "--holdout", "last:50%"]),
    ("RealSense office", "realsense_office_d435", ["--poses", "icp", "--intrinsics", "615,615,320,240"]),
    ("RealSense office: fit 0-49, judge 50-99", "realsense_office_d435",
     ["--poses", "icp", "--intrinsics", "615,615,320,240", "--holdout", "last:50%"]),
    ("RealSense lampshade", "realsense_lampshade", ["--poses", "icp"]),
)


def tempfile_dir() -> str:
    import tempfile

    return tempfile.gettempdir()


def real(out: Path) -> list[dict]:
    import subprocess
    import tempfile

    rows = []
    radiomap = [sys.executable, "-m", "mapping.cli"]
    for name, folder, options in REAL:
        seq = SHARED / folder
        if not seq.is_dir():
            print(f"skipped {name}: {seq} is absent", flush=True)
            continue
        with tempfile.TemporaryDirectory(dir=out) as tmp:
            t0 = time.perf_counter()
            proc = subprocess.run([*radiomap, "self-calibrate", str(seq), "-o", str(Path(tmp) / "sc"), "--no-progress",
                                   "--no-plots", *options], capture_output=True, text=True)
            doc = {}
            if proc.returncode == 0:
                doc = json.loads((Path(tmp) / "sc" / "self_calibration.json").read_text(encoding="utf-8"))
            summary = [line for line in proc.stdout.splitlines() if line.startswith(("R ", "G ", "B "))]
            row = {"case": name, "exit": proc.returncode, "validation": doc.get("validation"),
                   "ambiguity": doc.get("ambiguity"), "plausibility": doc.get("plausibility"),
                   "tilt_visibility": doc.get("solver", {}).get("tilt_visibility"),
                   "grid": doc.get("solver", {}).get("grid"), "channels": summary,
                   "warnings": doc.get("warnings"), "stderr": proc.stderr.strip().splitlines()[-3:],
                   "seconds": round(time.perf_counter() - t0, 1)}
            rows.append(row)
            print(json.dumps(row), flush=True)
    return rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=int, default=640, help="image width (height 3/4 of it)")
    ap.add_argument("--frames", type=int, default=80)
    ap.add_argument("--motions", default="scan,pan")
    ap.add_argument("--exact", action="store_true",
                    help="replace every sighting's value by k V L from the truth (no noise, no clip): the error the "
                         "motion's geometry and the model leave")
    ap.add_argument("--json", type=Path, help="also write the rows here")
    ap.add_argument("--real", action="store_true", help="the shared real recordings (see the module doc)")
    args = ap.parse_args()
    if args.real:
        out = Path(tempfile_dir())
        rows = real(out)
        if args.json:
            args.json.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
        return 0
    rows = []
    for motion in args.motions.split(","):
        for known in (False, True):
            row = study(motion, frames=args.frames, size=args.size, known=known, exact=args.exact)
            rows.append(row)
            print(json.dumps(row), flush=True)
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
