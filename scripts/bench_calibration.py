#!/usr/bin/env python3
"""Benchmark: accuracy of the response calibration against the truth, per curve of the test set, ours vs OpenCV.

Curves and brackets come from ``tests/response_curves.py`` (independent of radiomap's simulator): gamma 2.2,
an S-curve, two kinked curves (4x steeper above level 180; near-flat 185..200 then steep) and the real EuRoC
pcalib when ``../shared/data`` is present. Each is rendered into 12 exposures of a scene spanning 16 stops
(photon and read noise, 8-bit, a saturated lamp), in two designs:

- ``2x``: exposure times exactly 2x apart (1/2048 .. 1 s), the usual bracket;
- ``varied``: the same times, each moved by a random factor 2^(-0.35..0.35) (fixed seed), so that the
  exposure ratios are not all equal.

Methods: ``debevec`` (lambda 10, the default), ``debevec`` with lambda chosen by cross-validation
(``lam="auto"``), ``engel``, OpenCV's ``CalibrateDebevec`` and ``CalibrateRobertson``. For each the table
gives the largest ``|f^-1 - truth|`` over levels 5..250 and 5..240 in % of the range (R/G/B, both curves
normalised ``f^-1(255) = 1``) and the fit time. The vignetting part of issue 15 is not here yet.

Usage::

    python scripts/bench_calibration.py [--size 640x480] [--design 2x varied] [--methods ...]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for path in (REPO, REPO / "tests"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

METHODS = {
    "debevec": ("debevec", {}),
    "debevec-cv": ("debevec", {"lam": "auto"}),
    "engel": ("engel", {}),
    "opencv-debevec": ("opencv-debevec", {}),
    "robertson": ("robertson", {}),
}
VARIED_SEED = 5


def design_times(design: str) -> np.ndarray:
    from response_curves import TIMES

    if design == "2x":
        return TIMES.copy()
    jitter = np.random.default_rng(VARIED_SEED).uniform(-0.35, 0.35, TIMES.size)
    return TIMES * 2.0 ** jitter


def run(size: tuple[int, int], designs: list[str], methods: list[str], seed: int = 0) -> list[dict]:
    from radiometry.response_fit import fit_response
    from response_curves import curves, max_error_percent, render_brackets, scene

    width, height = size
    radiance = scene(height, width, seed=seed)
    rows = []
    for design in designs:
        times = design_times(design)
        for name, table in curves().items():
            images = render_brackets(table, radiance, times, seed=seed)
            for label in methods:
                method, kwargs = METHODS[label]
                start = time.perf_counter()
                response = fit_response(images, times, method=method, **kwargs)
                seconds = time.perf_counter() - start
                meta = response.meta
                note = ""
                if label == "debevec-cv":
                    note = f"lambda {meta['lambda']:g}"
                elif label == "engel":
                    note = f"{max(meta['iterations'])} rounds"
                elif meta.get("repaired"):
                    note = "repaired"
                e250 = max_error_percent(response.inverse_table, table, (5, 250))
                e240 = max_error_percent(response.inverse_table, table, (5, 240))
                rows.append({"brackets": design, "curve": name, "method": label,
                             "max err 5..250 [%] R/G/B": "/".join(f"{v:.2f}" for v in e250),
                             "max err 5..240 [%] R/G/B": "/".join(f"{v:.2f}" for v in e240),
                             "worst 5..250 [%]": float(e250.max()), "time [s]": seconds, "note": note})
                print(f"  {design:6s} {name:16s} {label:15s} {e250.max():7.2f} % {seconds:6.1f} s", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    parser.add_argument("--design", nargs="+", choices=("2x", "varied"), default=["2x", "varied"],
                        help="exposure designs (default both)")
    parser.add_argument("--methods", nargs="+", choices=tuple(METHODS), default=list(METHODS),
                        help="methods (default all)")
    parser.add_argument("--seed", type=int, default=0, help="scene and noise seed")
    args = parser.parse_args(argv)
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        parser.error(f"--size must be WxH, e.g. 640x480, got {args.size!r}")
    import logging

    import cv2

    from radiometry.tables import format_table

    quiet = logging.getLogger("radiometry")  # repaired / equal-ratio warnings: the table shows them
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        rows = run((width, height), args.design, args.methods, seed=args.seed)
    finally:
        quiet.setLevel(level)  # main() may run inside another program (the tests): leave its logging as it was
    print(f"response calibration vs truth ({width}x{height}, 12 exposures, OpenCV {cv2.__version__})")
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
