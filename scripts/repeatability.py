"""Vignetting repeatability (Alexandrov et al. 2016, Fig. 6) on simulated calibration sessions.

K white-paper sweeps of one simulated camera (different sheets, paths, noise; ``mapping.simulation``)
are each collected and fitted with every model (polynomial with free centre, polynomial with the centre
fixed at the image centre, LUT). Each fit is scored on each of the other K - 1 sessions by
``flat_rms_levels``: the RMS difference, in 8-bit levels, between that session's mean flat image and
the flat the model predicts (``f(a V(x))``). Writes a box plot per model and channel, a table
(printed, ``.txt`` and ``.json``), and also the error of every fit against the true ``V``.

    python scripts/repeatability.py -o results/repeatability [--sessions 10 --frames 150 --width 160]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

MODELS = ("poly", "poly-fixed-center", "lut")
CHANNELS = ("R", "G", "B")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path, default=Path("results/repeatability"))
    parser.add_argument("--sessions", type=int, default=10)
    parser.add_argument("-n", "--num-frames", type=int, default=150)
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--camera", default="xtion", help="simulated camera preset")
    parser.add_argument("--flicker", type=float, default=0.0, help="light drift amplitude during each sweep")
    parser.add_argument("--keep", action="store_true", help="keep the simulated sweeps in OUTPUT/sessions")
    args = parser.parse_args(argv)
    if args.sessions < 2:
        parser.error("--sessions must be at least 2")

    import shutil
    import tempfile

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mapping.simulation.sequences import simulate_paper
    from radiometry.fileio import atomic_path, atomic_write_json, atomic_write_text, ensure_dir
    from radiometry.plots_vignetting import plot_repeatability
    from radiometry.response import CameraResponse
    from radiometry.vignetting_calibration import (collect_vignetting, fit_vignetting, repeatability,
                                                   vignetting_error_levels)

    out = ensure_dir(args.output)
    work = ensure_dir(out / "sessions") if args.keep else Path(tempfile.mkdtemp(prefix="radiomap-repeat-"))
    accumulations, truth_errors = [], {m: [] for m in MODELS}
    response = truth = None
    start = time.time()
    try:
        for k in range(args.sessions):
            seq = simulate_paper(work / f"session_{k:02d}", camera=args.camera, seed=100 + k, n_frames=args.num_frames,
                                 width=args.width, height=args.height, flicker=args.flicker, force=True,
                                 progress=False, write_depth_images=False)
            response = CameraResponse.load(seq / "truth" / "response.npz")
            truth = np.load(seq / "truth" / "vignetting.npy")
            acc = collect_vignetting(seq / "rgb", response, progress=False)
            accumulations.append(acc)
            for m in MODELS:
                truth_errors[m].append(vignetting_error_levels(fit_vignetting(acc, model=m), truth, response))
            print(f"session {k + 1}/{args.sessions}: {acc.frames_used} frames used, {acc.frames_skipped} skipped "
                  f"({time.time() - start:.0f} s)", file=sys.stderr)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    errors = repeatability(accumulations, response, models=MODELS)

    rows = []
    for m in MODELS:
        for c, name in enumerate(CHANNELS):
            e = errors[m][:, c]
            t = np.array(truth_errors[m])[:, c]
            rows.append({"model": m, "channel": name, "pairs": len(e), "median": float(np.median(e)),
                         "mean": float(np.mean(e)), "p90": float(np.percentile(e, 90)), "max": float(np.max(e)),
                         "vs_truth_median": float(np.median(t))})
    header = (f"vignetting repeatability: {args.sessions} simulated sessions of camera '{args.camera}', "
              f"{args.width}x{args.height}, {args.num_frames} frames each, flicker {args.flicker}\n"
              "RMS error in 8-bit levels of a model fitted on one session against the mean flat of each other "
              "session; vs_truth: RMS error against the true V (flat at level 200)")
    cols = ["model", "channel", "pairs", "median", "mean", "p90", "max", "vs_truth_median"]
    widths = [max(len(c), 17) if i == 0 else max(len(c), 8) for i, c in enumerate(cols)]
    lines = [header, "", "  ".join(c.ljust(w) for c, w in zip(cols, widths))]
    for r in rows:
        cells = [f"{r[c]:.3f}" if isinstance(r[c], float) else str(r[c]) for c in cols]
        lines.append("  ".join(v.ljust(w) for v, w in zip(cells, widths)))
    table = "\n".join(lines)
    print(table)
    atomic_write_text(out / "repeatability.txt", table + "\n")
    atomic_write_json(out / "repeatability.json", {"parameters": vars(args) | {"output": str(args.output)},
                                                   "rows": rows, "errors": {m: errors[m] for m in MODELS},
                                                   "truth_errors": {m: np.array(v) for m, v in truth_errors.items()}})
    fig, ax = plt.subplots(figsize=(8, 4.5))
    plot_repeatability(ax, errors)
    with atomic_path(out / "repeatability.png") as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)
    print(f"wrote {out / 'repeatability.png'}, .txt, .json ({time.time() - start:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
