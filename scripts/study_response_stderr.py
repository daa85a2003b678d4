#!/usr/bin/env python3
"""How often the response fit's stated standard error covers its true error (docs/calibration_pipelines.md, "The
stated standard error is the pixels' noise only").

For each curve and camera pipeline of ``tests/camera_pipelines.py`` (written without radiometry) it renders a
bracket of ``tests/response_curves.py``'s scene, fits it with the default fit and prints, per channel: the largest
error of ``ln(f^-1(z) / f^-1(255))`` against the truth over the declared levels from 32 up (%), the share of those
levels where the truth lies within two stated standard errors (``meta["inverse_stderr"]``), the same share for the
stated uncertainty (:func:`radiometry.response.relative_uncertainty`: that and the levels' 8-bit width), and with
``--sensitivity`` the same share once the fit's sensitivity to its own weights (the largest change of ``ln f^-1``
with the prior's or the smoothness weight x4 and /4: four more fits) is added in quadrature::

    python scripts/study_response_stderr.py --curves gamma-2.2,euroc,kink-4x,s-curve \\
        --pipelines clean,post-noise,wb-jpeg92 --sensitivity
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))


def _log_table(response) -> np.ndarray:
    table = response.inverse_table
    with np.errstate(divide="ignore"):
        return np.log(table / table[-1])


def study(curve: str, pipeline: str, *, design: str = "2x", width: int = 320, height: int = 240,
          sensitivity: bool = False) -> list[dict]:
    """One row per channel: ``max_error_percent``, ``within_2se`` and, with ``sensitivity``, ``within_2se_with_
    sensitivity`` (shares of the declared levels from 32 up)."""
    from camera_pipelines import PIPELINES, render
    from radiometry.response.fit import fit_response
    from radiometry.response.levels import declared
    from radiometry.response.model import relative_stderr, relative_uncertainty
    from response_curves import TIMES, curves, scene

    times = TIMES if design == "2x" else TIMES * 2.0 ** np.random.default_rng(5).uniform(-0.35, 0.35, TIMES.size)
    table = curves()[curve]
    images = render(table, scene(height, width, seed=1), times, seed=2, **PIPELINES[pipeline])
    response = fit_response(images, times)
    se, stated = relative_stderr(response, 3), relative_uncertainty(response, 3)
    fitted = _log_table(response)
    sens = None
    if sensitivity:
        variants = [fit_response(images, times, method="loglog", lam=0.1 * f) for f in (0.25, 4.0)]
        variants += [fit_response(images, times, method="loglog", smooth=5e-3 * f) for f in (0.25, 4.0)]
        with np.errstate(invalid="ignore"):  # level 0: -inf on both sides
            sens = np.max([np.abs(_log_table(v) - fitted) for v in variants], axis=0)
    truth = np.asarray(table, dtype=np.float64).reshape(256, -1)
    truth = np.repeat(truth, 3, axis=1) if truth.shape[1] == 1 else truth
    rows = []
    for c, (lo, hi) in enumerate(declared(response, 3)):
        z = np.arange(max(lo, 32), hi + 1)
        err = np.abs(fitted[z, c] - np.log(truth[z, c] / truth[-1, c]))
        row = {"channel": "RGB"[c], "max_error_percent": round(100 * float(err.max()), 2),
               "within_2se": round(float(np.mean(err <= 2 * se[z, c])), 2),
               "within_2u": round(float(np.mean(err <= 2 * stated[z, c])), 2)}
        if sens is not None:
            wider = np.sqrt(se[z, c] ** 2 + sens[z, c] ** 2)
            row["within_2se_with_sensitivity"] = round(float(np.mean(err <= 2 * wider)), 2)
        rows.append(row)
    return rows


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not WIDTHxHEIGHT, e.g. 320x240") from None
    if width < 16 or height < 16:
        raise argparse.ArgumentTypeError(f"{text!r}: at least 16x16")
    return width, height


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--curves", default="gamma-2.2,euroc,kink-4x,s-curve")
    ap.add_argument("--pipelines", default="clean,post-noise,wb-jpeg92")
    ap.add_argument("--design", choices=("2x", "varied"), default="2x")
    ap.add_argument("--size", default="320x240", type=_size, help="WIDTHxHEIGHT of the bracket")
    ap.add_argument("--sensitivity", action="store_true", help="also add the fit's sensitivity to its weights")
    args = ap.parse_args(argv)
    width, height = args.size
    from camera_pipelines import PIPELINES
    from response_curves import curves

    known = set(curves()) | {"euroc"}
    for name, given, choices in (("--curves", args.curves, known), ("--pipelines", args.pipelines, set(PIPELINES))):
        unknown = sorted(set(given.split(",")) - choices)
        if unknown:
            ap.error(f"{name}: unknown {', '.join(unknown)}; choose from {', '.join(sorted(choices))}")
    for curve in args.curves.split(","):
        if curve not in curves():
            print(f"{curve}: not available (the EuRoC curve needs ../shared/data)")
            continue
        for pipeline in args.pipelines.split(","):
            rows = study(curve, pipeline, design=args.design, width=width, height=height,
                         sensitivity=args.sensitivity)
            cells = ", ".join(f"{r['channel']} {r['max_error_percent']:.2f} % / {100 * r['within_2se']:.0f} % / "
                              f"{100 * r['within_2u']:.0f} %"
                              + (f" / {100 * r['within_2se_with_sensitivity']:.0f} %" if args.sensitivity else "")
                              for r in rows)
            print(f"{curve:16s} {pipeline:14s} {args.design}: largest error / within 2 stderr / within 2 stated "
                  f"uncertainties (stderr and 8-bit width)"
                  f"{' / with sensitivity' if args.sensitivity else ''}: {cells}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
