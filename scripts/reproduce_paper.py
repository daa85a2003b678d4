#!/usr/bin/env python
"""Reproduce the two central figures of Alexandrov, Prankl, Zillich, Vincze (IROS 2016) on simulated data.

- Fig. 6, repeatability of the vignetting models: K (default 10) white-paper calibration sessions of one
  simulated camera ("xtion" preset), each fitted with the free-centre polynomial, the fixed-centre polynomial
  and the LUT; every fit scored against the mean flat image of each other session (RMS, 8-bit levels).
  This is ``scripts/repeatability.py`` (itself ``radiometry.vignetting_calibration.repeatability``), run as is.
- Fig. 9, colour-disagreement histograms: the demo (``mapping.demo.run_demo``, its "asymmetric" camera with
  strong non-radial vignetting: response from brackets,
  LUT and polynomial vignetting from a paper sweep, a room with auto exposure, fused with no correction, the
  polynomial and the LUT at ground-truth poses) and its normalised L1 histograms.

Writes into OUT: ``fig6_repeatability.png``, ``fig9_histograms.png``, ``fig9_renders.jpg``,
``reproduce_paper.md`` (the figures, the numbers, and how they compare with the paper's findings),
``reproduce_paper.json``, and the full runs in ``OUT/fig6/`` and ``OUT/fig9/``.

    python scripts/reproduce_paper.py -o results/paper            # 1.5-4 minutes on 2 cores
    python scripts/reproduce_paper.py -o /tmp/paper --quick       # under 30 s: 4 sessions, the quick demo
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
MODELS = ("poly", "poly-fixed-center", "lut")
MODEL_LABELS = {"poly": "polynomial, free centre", "poly-fixed-center": "polynomial, fixed centre", "lut": "LUT"}


def _load_repeatability_script():
    spec = importlib.util.spec_from_file_location("radiomap_repeatability_script", HERE / "repeatability.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import os

    mem = ""
    try:
        kb = int(next(l for l in Path("/proc/meminfo").read_text().splitlines() if l.startswith("MemTotal")).split()[1])
        mem = f", {kb / 2 ** 20:.0f} GB RAM"
    except (OSError, StopIteration, ValueError):
        pass
    return f"{cpu}, {os.cpu_count()} cores{mem}, Python {platform.python_version()}"


# --------------------------------------------------------------------------------------------------
# Fig. 6
# --------------------------------------------------------------------------------------------------
def figure6(out: Path, *, sessions: int, frames: int, width: int, height: int) -> dict:
    script = _load_repeatability_script()
    folder = out / "fig6"
    t0 = time.perf_counter()
    code = script.main(["-o", str(folder), "--sessions", str(sessions), "--num-frames", str(frames),
                        "--width", str(width), "--height", str(height)])
    if code != 0:
        raise SystemExit(f"scripts/repeatability.py failed with exit code {code}")
    seconds = time.perf_counter() - t0
    doc = json.loads((folder / "repeatability.json").read_text())
    shutil.copyfile(folder / "repeatability.png", out / "fig6_repeatability.png")
    per_model = {}
    for m in MODELS:
        errs = np.asarray(doc["errors"][m], dtype=np.float64)            # (pairs, channels)
        truth = np.asarray(doc["truth_errors"][m], dtype=np.float64)      # (sessions, channels)
        per_model[m] = {"median": float(np.median(errs)), "p90": float(np.percentile(errs, 90)),
                        "max": float(errs.max()), "vs_truth_median": float(np.median(truth)),
                        "per_channel_median": np.median(errs, axis=0).tolist()}
    return {"sessions": sessions, "frames": frames, "size": f"{width}x{height}", "seconds": seconds,
            "models": per_model, "table": (folder / "repeatability.txt").read_text()}


# --------------------------------------------------------------------------------------------------
# Fig. 9
# --------------------------------------------------------------------------------------------------
def figure9(out: Path, *, quick: bool, seed: int) -> dict:
    from mapping.demo import run_demo, summary_text

    t0 = time.perf_counter()
    result = run_demo(out / "fig9", quick=quick, seed=seed, force=True, progress=False,
                      log=lambda msg: print(msg, file=sys.stderr))
    seconds = time.perf_counter() - t0
    comp = result.comparison
    shutil.copyfile(comp.files["histograms"], out / "fig9_histograms.png")
    if "renders" in comp.files:
        shutil.copyfile(comp.files["renders"], out / "fig9_renders.jpg")
    rows = comp.table()
    hist = {}
    for r in comp.results:
        h = r.run.histogram
        cdf = np.cumsum(h.normalised())
        hist[r.method.name] = {"label": r.method.label, "mean": h.mean(), "median": h.median(),
                               "p90": h.percentile(0.9), "within_10": float(cdf[10]), "within_20": float(cdf[20]),
                               "colour_err": None if r.colour_error is None else r.colour_error.mean}
    return {"seconds": seconds, "table": rows, "histograms": hist, "ranking": comp.ranking(),
            "exposure_compensation": result.exposure_compensation, "summary": summary_text(result),
            "calibration": result.calibration, "size": result.size.__dict__, "camera": result.camera}


# --------------------------------------------------------------------------------------------------
# the text
# --------------------------------------------------------------------------------------------------
def _verdict(ok: bool) -> str:
    return "as in the paper" if ok else "differs from the paper"


def markdown(f6: dict, f9: dict, *, quick: bool, total: float) -> str:
    m = f6["models"]
    lut, free, fixed = m["lut"], m["poly"], m["poly-fixed-center"]
    order6 = sorted(MODELS, key=lambda k: m[k]["median"])
    lines = [
        "# The paper's Fig. 6 and Fig. 9 reproduced on simulated data",
        "",
        f"**Reproduce:** `python scripts/reproduce_paper.py{' --quick' if quick else ''} -o OUT` (writes this page); "
        f"**measured:** {time.strftime('%Y-%m-%d')}, in {total:.0f} s on {machine()}.",
        "All data are simulated. Fig. 6: radiomap's 'xtion' camera (S-shaped response, vignetting down to ~0.5 in "
        "the corners with per-channel centres and a gentle non-radial field, noise, auto exposure and white "
        f"balance). Fig. 9: the demo's '{f9.get('camera', 'asymmetric')}' camera (the same with a strong non-radial "
        "field that the best radial polynomial misses by 2.5 % RMS, 7 % at worst). Everything is deterministic "
        "for the seeds used.",
        "",
        "## Fig. 6: repeatability of the vignetting models",
        "",
        f"{f6['sessions']} white-paper calibration sessions ({f6['frames']} frames each, {f6['size']}); every model "
        "fitted on one session is scored against the mean flat image of each other session (RMS difference in "
        "8-bit levels over all pixels). `vs truth` is the RMS error against the true V (a flat field at level 200).",
        "",
        "![Fig. 6](fig6_repeatability.png)",
        "",
        "| model | median | p90 | max | vs truth (median) |",
        "|---|---:|---:|---:|---:|",
    ]
    for k in MODELS:
        lines.append(f"| {MODEL_LABELS[k]} | {m[k]['median']:.3f} | {m[k]['p90']:.3f} | {m[k]['max']:.3f} | "
                     f"{m[k]['vs_truth_median']:.3f} |")
    lut_best = order6[0] == "lut" and lut["vs_truth_median"] <= min(free["vs_truth_median"], fixed["vs_truth_median"])
    fixed_worst = order6[-1] == "poly-fixed-center"
    # "close": nearer to the LUT than to the fixed-centre polynomial
    close = free["median"] - lut["median"] < fixed["median"] - free["median"]
    lines += [
        "",
        "Paper: the LUT is the most repeatable and accurate model, the polynomial with a free centre is close, "
        "the polynomial with the centre fixed at the image centre is worst.",
        "",
        f"- LUT most repeatable and most accurate: median {lut['median']:.3f} levels, {lut['vs_truth_median']:.3f} "
        f"against the truth: **{_verdict(lut_best)}**.",
        f"- Free-centre polynomial close behind: median {free['median']:.3f} "
        f"({free['median'] / lut['median']:.2f}x the LUT's, {free['median'] - lut['median']:.3f} levels more; the "
        f"fixed centre adds another {fixed['median'] - free['median']:.3f}): **{_verdict(close)}**.",
        f"- Fixed-centre polynomial worst: median {fixed['median']:.3f} ({fixed['median'] / lut['median']:.2f}x the "
        f"LUT's), {fixed['vs_truth_median']:.3f} against the truth: **{_verdict(fixed_worst)}**. The simulated "
        "camera's blue centre is off by ~1 % of the image size, which a fixed centre cannot follow.",
        "",
        "## Fig. 9: colour disagreement while fusing",
        "",
        f"The demo's room ({f9['size']['room_frames']} frames, {f9['size']['width']}x{f9['size']['height']}, TSDF "
        f"with {f9['size']['voxel_size']:g} m voxels, ground-truth poses, exposure compensation "
        f"{'on' if f9['exposure_compensation'] else 'off'}): before each sample is averaged into the map, the L1 "
        "distance (8-bit display levels, summed over R, G, B) between it and the map's colour is counted. "
        "Normalised histograms, linear and log scale:",
        "",
        "![Fig. 9](fig9_histograms.png)",
        "",
        "| method | L1 mean | median | p90 | samples with L1 <= 10 | L1 <= 20 | mesh colour err (levels) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    h = f9["histograms"]
    for name, s in h.items():
        err = "-" if s["colour_err"] is None else f"{s['colour_err']:.2f}"
        lines.append(f"| {s['label']} | {s['mean']:.2f} | {s['median']:.0f} | {s['p90']:.0f} | "
                     f"{100 * s['within_10']:.1f} % | {100 * s['within_20']:.1f} % | {err} |")
    names = list(h)
    lut_name = next(n for n in names if n.removesuffix("+ec") == "lut")
    poly_name = next(n for n in names if n.removesuffix("+ec") == "poly")
    lut_most = all(h[lut_name]["within_10"] >= h[n]["within_10"] for n in names)
    none_widest = all(h["none"]["p90"] >= h[n]["p90"] and h["none"]["mean"] >= h[n]["mean"] for n in names)
    lut_mean_best = f9["ranking"][0] == lut_name
    lines += [
        "",
        "Paper: the LUT's histogram is the most concentrated at low L1, no correction's the widest.",
        "",
        f"- Most concentrated at low L1: the LUT has {100 * h[lut_name]['within_10']:.1f} % of its samples within 10 "
        f"levels (polynomial {100 * h[poly_name]['within_10']:.1f} %, no correction "
        f"{100 * h['none']['within_10']:.1f} %): **{_verdict(lut_most)}**.",
        f"- Widest without correction: mean {h['none']['mean']:.2f} and p90 {h['none']['p90']:.0f}, against "
        f"{h[lut_name]['mean']:.2f} and {h[lut_name]['p90']:.0f} with the LUT: **{_verdict(none_widest)}**.",
        f"- Ranking by the L1 mean (best first): {', '.join(f9['ranking'])} "
        f"(**{_verdict(lut_mean_best and f9['ranking'][-1] == 'none')}**).",
        "",
        "How large the differences are matters as much as their order. Vignetting correction roughly halves the "
        f"disagreement; the LUT leads the free-centre polynomial by {h[poly_name]['mean'] - h[lut_name]['mean']:.2f} "
        "levels on the L1 mean although the polynomial misses this camera's V by ~2.5 % (RMS): over a short "
        "handheld sequence a point keeps nearly the same image position, so a smooth residual largely cancels "
        "between the map and the new sample, and what is left adds to the spread that texture, noise and voxel "
        "interpolation give every method alike only at second order. The mesh colours against the true radiance "
        "(last column) measure the residual at first order: "
        + (f"the polynomial's error is {h[poly_name]['colour_err'] / h[lut_name]['colour_err']:.2f}x the LUT's."
           if h[poly_name]["colour_err"] and h[lut_name]["colour_err"] else "no truth available."),
        "",
        "Renders of the meshes from the same viewpoints (last column: the true radiance):",
        "",
        "![renders](fig9_renders.jpg)",
        "",
        "## Demo output",
        "",
        "```",
        f9["summary"],
        "```",
        "",
    ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path, required=True, help="folder for figures and text")
    parser.add_argument("--quick", action="store_true", help="4 sessions of 60 frames and the quick demo")
    parser.add_argument("--sessions", type=int, default=None, help="calibration sessions for Fig. 6 (default 10)")
    parser.add_argument("-n", "--num-frames", type=int, default=None, help="frames per session (default 150)")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--seed", type=int, default=0, help="seed of the Fig. 9 demo")
    parser.add_argument("--skip-fig6", action="store_true")
    args = parser.parse_args(argv)
    sessions = args.sessions or (4 if args.quick else 10)
    frames = args.num_frames or (60 if args.quick else 150)
    if sessions < 2:
        parser.error("--sessions must be at least 2")

    import matplotlib

    matplotlib.use("Agg")
    from radiometry.fileio import atomic_write_json, atomic_write_text, ensure_dir

    out = ensure_dir(args.output)
    start = time.perf_counter()
    f6 = figure6(out, sessions=sessions, frames=frames, width=args.width, height=args.height) if not args.skip_fig6 \
        else json.loads((out / "reproduce_paper.json").read_text())["fig6"]
    print(f"Fig. 6 done ({f6['seconds']:.0f} s)", file=sys.stderr)
    f9 = figure9(out, quick=args.quick, seed=args.seed)
    print(f"Fig. 9 done ({f9['seconds']:.0f} s)", file=sys.stderr)
    total = time.perf_counter() - start
    text = markdown(f6, f9, quick=args.quick, total=total)
    atomic_write_text(out / "reproduce_paper.md", text)
    atomic_write_json(out / "reproduce_paper.json", {"fig6": f6, "fig9": f9, "seconds": total, "machine": machine(),
                                                     "quick": args.quick})
    print(text)
    print(f"wrote {out / 'reproduce_paper.md'} ({total:.0f} s)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
