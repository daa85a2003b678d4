#!/usr/bin/env python3
"""Benchmark: our sparse Debevec & Malik against OpenCV's CalibrateDebevec on the same images, one run.

Stacks: the embedded sample (``data_samples/brackets``, true response known), a larger synthetic stack
rendered here through a known gamma-2.2 response (640 x 480, 7 exposures), and the real memorial and
taipei stacks from ``../shared/data/brackets`` when present. For each stack both methods run with their
defaults (ours: 50 observations per level, lambda 10; OpenCV: 70 grid samples, lambda 10) and we report

- time: the best of ``--repeats`` runs, on one pinned core with one OpenCV thread, and the ratio ours/OpenCV;
- accuracy where the truth is known: the largest |f^-1 - truth| over levels 5..250 in % of the range
  (both normalised f^-1(255) = 1), and the ratio ours/OpenCV (< 1: ours is closer to the truth);
- on every stack: the prediction RMS in 8-bit levels (each exposure predicted from the merged radiance
  map, unsaturated unmasked pixels; memorial masks its blue fill for both), and the ratio ours/OpenCV;
- the RMS difference between the two curves over levels 10..245 after a least-squares scale.

Usage::

    python scripts/bench_response.py [--repeats 3] [--shared ../shared/data]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from _bench import pin_to_one_core  # before NumPy: one BLAS/OpenMP/Numba thread

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))


def synthetic_gamma(width: int = 640, height: int = 480, seed: int = 7):
    """A 7-exposure stack (one stop apart) of a log-gradient scene with 60 patches, gamma 2.2, noisy."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:height, 0:width]
    radiance = np.exp(np.log(2e-3) + np.log(2e3) * xx / (width - 1)) * (0.6 + 0.4 * yy / (height - 1))
    radiance = radiance[..., None] * np.array([1.0, 0.85, 0.7])
    for _ in range(60):
        y0, x0 = rng.integers(0, height - 40), rng.integers(0, width - 40)
        radiance[y0:y0 + 40, x0:x0 + 40] = np.exp(rng.uniform(np.log(2e-3), np.log(4.0), 3))
    times = 2.0 ** np.arange(-6, 1)
    images = []
    for t in times:
        e = rng.poisson(np.clip(radiance * t, 0, 2) * 20000.0) + rng.normal(0, 2.0, radiance.shape)
        images.append(np.clip(np.rint(255 * np.clip(e / 20000.0, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.uint8))
    truth = np.repeat(((np.arange(256) / 255.0) ** 2.2)[:, None], 3, axis=1)
    return images, times, truth


def best_time(fn, repeats: int):
    best, result = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        best = min(best, time.perf_counter() - start)
    return best, result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="timing runs per method (best is kept)")
    parser.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data", help="real data root")
    args = parser.parse_args(argv)
    pinned = pin_to_one_core()
    import cv2

    cv2.setNumThreads(1)
    from radiometry.tables import format_table
    from radiometry.response import CameraResponse
    from radiometry.response.fit import blue_fill_mask, fit_response_debevec, load_brackets, prediction_rms
    from radiometry.response.opencv import fit_response_opencv_debevec

    stacks = []
    sample = REPO / "data_samples" / "brackets"
    images, times, _ = load_brackets(sample)
    stacks.append(("data_samples (160x120, 5)", images, times, None,
                   CameraResponse.load(sample / "ground_truth_response.npz").inverse_table))
    images, times, truth = synthetic_gamma()
    stacks.append(("synthetic gamma (640x480, 7)", images, times, None, truth))
    for name in ("memorial_debevec1997", "taipei"):
        folder = args.shared / "brackets" / name
        if not folder.is_dir():
            print(f"skipping {name}: {folder} is absent")
            continue
        images, times, _ = load_brackets(folder)
        mask = blue_fill_mask(images) if name.startswith("memorial") else None
        h, w = images[0].shape[:2]
        stacks.append((f"{name} ({w}x{h}, {len(images)})", images, times, mask, None))

    rows = []
    levels, compare = np.arange(5, 251), np.arange(10, 246)
    for label, images, times, mask, truth in stacks:
        t_ours, ours = best_time(lambda: fit_response_debevec(images, times, mask=mask), args.repeats)
        t_cv, theirs = best_time(lambda: fit_response_opencv_debevec(images, times), args.repeats)
        row = {"stack": label, "ours [s]": t_ours, "opencv [s]": t_cv, "time ours/cv": t_ours / t_cv}
        if truth is not None:
            e_ours = 100 * np.abs(ours.inverse_table[levels] - truth[levels]).max()
            e_cv = 100 * np.abs(theirs.inverse_table[levels] - truth[levels]).max()
            row.update({"max err ours [%]": e_ours, "max err cv [%]": e_cv, "err ours/cv": e_ours / e_cv})
        else:
            row.update({"max err ours [%]": "-", "max err cv [%]": "-", "err ours/cv": "-"})
        p_ours = prediction_rms(images, times, ours, mask=mask)
        p_cv = prediction_rms(images, times, theirs, mask=mask)
        a, b = ours.inverse_table[compare], theirs.inverse_table[compare]
        diff = np.sqrt(((a - (a * b).sum(0) / (b * b).sum(0) * b) ** 2).mean(0))
        row.update({"pred RMS ours": p_ours, "pred RMS cv": p_cv, "pred ours/cv": p_ours / p_cv,
                    "cv repaired": theirs.meta["repaired"], "curve diff [%] R/G/B": "/".join(
                        f"{100 * d:.2f}" for d in diff)})
        rows.append(row)
    print(f"radiomap response benchmark ({pinned}, OpenCV {cv2.__version__}, best of {args.repeats})")
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
