#!/usr/bin/env python3
"""Benchmark: vignetting LUT calibrated END TO END (response from brackets, then the LUT from a white-paper sweep)
against the truth, per vignette x response curve, with the response calibrated by each method and with the true
response.

Everything is rendered independently of radiomap's camera code: brackets by ``tests/response_curves.py`` (12
exposures at 2x steps, or each moved by 2^(-0.35..0.35): ``--design``), sweeps by ``tests/vignetting_sweeps.py``
(a white sheet at random places, photon and read noise, 8-bit). Vignettes: the EuRoC DSO ``vignette.png`` (blue
shifted), two lensfun profiles, radiomap's ``asymmetric`` preset; curves: the EuRoC ``pcalib.txt``, ``kink-4x``
(4x steeper above level 180), gamma 2.2. Needs ``../shared/data``.

Measure: RMS over all pixels, per channel, in 8-bit levels, of a flat field imaged at level 200 where ``V = 1``,
predicted through the calibrated ``V`` vs the true one, both through the true response (``strict``: a uniform
error of the normalisation counts; the issue's goal is <= 0.5). ``budget`` is the error the calibration expects of
itself (``info["error_budget"]["total"]``), ``response err`` the response's own max ``|f^-1 - truth|`` over
levels 5..250 (% of the range), ``response part`` the RMS between the LUT with the calibrated response
and the LUT with the true one (what the response's error costs).

Usage::

    python scripts/bench_vignetting.py [--design varied] [--methods auto debevec opencv-debevec] [-n 64] [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for path in (REPO, REPO / "tests"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

CURVES = ("euroc", "kink-4x", "gamma-2.2")


def run(vignettes: list[str], curve_names: list[str], methods: list[str], design: str, frames: int,
        bracket_size: tuple[int, int], seed: int = 0) -> list[dict]:
    """One row per vignette x curve x response (``"truth"`` and each of ``methods``), as printed."""
    from radiometry.response import CameraResponse
    from radiometry.response.fit import fit_response
    from radiometry.vignetting_calibration import collect_vignetting, fit_vignetting
    from response_curves import TIMES, curves, max_error_percent, render_brackets, scene
    from vignetting_sweeps import bracket_times, default_size, flat_rms_vs_truth, render_sweep, vignette_field

    tables = curves()
    times = TIMES.copy() if design == "2x" else bracket_times()
    bw, bh = bracket_size
    radiance = scene(bh, bw, seed=seed)
    rows = []
    for cname in curve_names:
        table = tables[cname]
        images = render_brackets(table, radiance, times, seed=seed)
        responses = {"truth": CameraResponse.from_table(table)}
        for method in methods:
            start = time.perf_counter()
            responses[method] = fit_response(images, times, method=method)
            print(f"  {cname:10s} response {method:8s} {time.perf_counter() - start:5.1f} s", flush=True)
        response_errors = {label: "/".join(f"{v:.2f}" for v in max_error_percent(r.inverse_table, table, (5, 250)))
                           for label, r in responses.items()}
        for vname in vignettes:
            width, height = default_size(vname)
            truth = vignette_field(vname, width, height)
            sweep = render_sweep(table, truth, frames=frames, seed=seed)
            luts = {}
            for label, response in responses.items():
                start = time.perf_counter()
                acc = collect_vignetting(sweep, response, progress=False)
                model = fit_vignetting(acc, model="lut")
                seconds = time.perf_counter() - start
                est = model.evaluate()
                luts[label] = est
                strict = flat_rms_vs_truth(est, truth, table)
                budget = model.info["error_budget"]["total"]
                part = flat_rms_vs_truth(est, luts["truth"], table) if label != "truth" else np.zeros(3)
                rows.append({"vignette": vname, "curve": cname, "response": label,
                             "response err 5..250 [%] R/G/B": response_errors[label],
                             "LUT RMS [levels] R/G/B": "/".join(f"{v:.2f}" for v in strict),
                             "worst": float(strict.max()),
                             "response part R/G/B": "/".join(f"{v:.2f}" for v in part),
                             "budget R/G/B": "/".join(f"{v:.2f}" for v in budget),
                             "<= 0.5": "yes" if strict.max() <= 0.5 else "no", "time [s]": seconds})
                print(f"  {vname:15s} {cname:10s} {label:8s} {strict.max():5.2f} levels", flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    from vignetting_sweeps import VIGNETTES, shared_available

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--design", choices=("2x", "varied"), default="varied")
    parser.add_argument("--methods", nargs="+", default=["auto", "debevec", "engel", "opencv-debevec", "robertson"],
                        help="response methods (fit_response names; default: ours and OpenCV's)")
    parser.add_argument("--vignettes", nargs="+", choices=VIGNETTES, default=list(VIGNETTES))
    parser.add_argument("--curves", nargs="+", choices=CURVES, default=list(CURVES))
    parser.add_argument("-n", "--num-frames", type=int, default=64, help="frames of each sweep")
    parser.add_argument("--bracket-size", default="320x240", help="WxH of the bracket images")
    parser.add_argument("--out", type=Path, default=None, help="also write the table (text) here")
    parser.add_argument("--seed", type=int, default=0, help="scene, noise and sweep seed")
    args = parser.parse_args(argv)
    if not shared_available():
        print("bench_vignetting: ../shared/data (EuRoC vignette, lensfun) is absent; nothing to measure")
        return 1
    warnings.simplefilter("ignore")
    from radiometry.tables import format_table

    bw, bh = (int(v) for v in args.bracket_size.lower().split("x"))
    rows = run(args.vignettes, args.curves, args.methods, args.design, args.num_frames, (bw, bh), seed=args.seed)
    shown = [{k: (f"{v:.1f}" if k == "time [s]" else v) for k, v in row.items() if k != "worst"} for row in rows]
    text = format_table(shown)
    print(f"\nvignetting LUT end to end ({args.design} brackets {bw}x{bh}, {args.num_frames}-frame sweeps): flat field at "
          "level 200, RMS vs truth")
    print(text)
    if args.out:
        args.out.write_text(text + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
