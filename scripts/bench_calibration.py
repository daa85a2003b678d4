#!/usr/bin/env python3
"""Benchmark: accuracy of the response calibration against the truth, per curve of the test set, ours vs OpenCV.

Curves and brackets come from ``tests/response_curves.py`` (independent of radiomap's simulator): gamma 2.2,
an S-curve, two kinked curves (4x steeper above level 180; near-flat 185..200 then steep) and the real EuRoC
pcalib when ``../shared/data`` is present. Each is rendered into 12 exposures of a scene spanning 16 stops
(photon and read noise, 8-bit, a saturated lamp), in two designs:

- ``2x``: exposure times exactly 2x apart (1/2048 .. 1 s), the usual bracket;
- ``varied``: the same times, each moved by a random factor 2^(-0.35..0.35) (fixed seed), so that the
  exposure ratios are not all equal.

Methods: ``debevec`` (lambda 10), ``debevec`` with lambda chosen by cross-validation (``lam="auto"``), ``engel``
(the eigen solver), ``engel-prior`` (Engel's energy with the log-log curvature prior, weight 1), ``loglog``
(:func:`radiometry.response.loglog.fit_response_loglog`: Debevec's data term over all pixels with the log-log
curvature prior), ``auto`` (the default: what :func:`radiometry.response.fit.fit_response` picks), OpenCV's
``CalibrateDebevec`` and ``CalibrateRobertson``. For each the table
gives the largest ``|f^-1 - truth|`` over levels 5..250 and 5..240 in % of the range (R/G/B, both curves
normalised ``f^-1(255) = 1``) and the fit time.

``--end-to-end`` runs instead, per curve and vignette (EuRoC DSO vignette, two lensfun profiles, the asymmetric
preset) and per response method (ours and OpenCV's), the response's error and the vignetting LUT calibrated with
that response against the truth, in one table (:mod:`bench_vignetting`; its options follow, e.g.
``--end-to-end --design 2x``).

``--curve-set break`` runs the curves built to break the priors instead (``tests/response_curves.py``'s
``break_curves``: knees and a flat stretch in the dark octaves, a shoulder, linear, gamma 3, sRGB).

``--pipelines`` runs instead the default fit through real camera pipelines (``tests/camera_pipelines.py``: white
balance after the sensor clips, JPEG q92 and q75, noise after the response; issue 28): per curve, pipeline and design
the largest ``|f^-1 - truth|`` over the levels the fit declares constrained (after a per-channel scale), whether
those levels stay below every channel's true ceiling, what the fit found, and the truth-free quality figure.

``--ambiguity`` prints instead, per curve and smoothness prior, the error of the member of the exact-2x ambiguity
family (``g + q(g mod ln 2)``, ``g = ln f^-1``, ``q`` periodic) that the prior prefers, computed from the true
curve: what a fit with that prior cannot get below however many pixels it has (:func:`ambiguity_bound`).

Usage::

    python scripts/bench_calibration.py [--size 640x480] [--design 2x varied] [--methods ...]
    python scripts/bench_calibration.py --ambiguity
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

#: label -> (a method of fit_response, or "module:function", keyword arguments)
METHODS = {
    "debevec": ("debevec", {}),
    "debevec-cv": ("debevec", {"lam": "auto"}),
    "engel": ("engel", {}),
    "engel-prior": ("engel", {"prior": 1.0}),
    "loglog": ("loglog", {}),
    "auto": ("auto", {}),
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


def _fitter(method: str):
    """``fit_response`` with ``method``, or the function ``module:function`` names."""
    if ":" in method:
        import importlib

        module, name = method.split(":")
        return getattr(importlib.import_module(module), name)
    from radiometry.response.fit import fit_response

    return lambda images, times, **kwargs: fit_response(images, times, method=method, **kwargs)


def run(size: tuple[int, int], designs: list[str], methods: list[str], seed: int = 0,
        curve_set: str = "test") -> list[dict]:
    from response_curves import break_curves, curves, max_error_percent, render_brackets, scene

    width, height = size
    radiance = scene(height, width, seed=seed)
    rows = []
    tables = curves() if curve_set == "test" else break_curves()
    for design in designs:
        times = design_times(design)
        for name, table in tables.items():
            images = render_brackets(table, radiance, times, seed=seed)
            for label in methods:
                method, kwargs = METHODS[label]
                start = time.perf_counter()
                response = _fitter(method)(images, times, **kwargs)
                seconds = time.perf_counter() - start
                meta = response.meta
                note = ""
                if label == "debevec-cv":
                    note = f"lambda {meta['lambda']:g}"
                elif label.startswith("engel"):
                    note = f"{meta['solver']}, {max(meta['iterations'])} rounds"
                elif label == "auto":
                    note = meta["method"]
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


#: priors for the exact-2x ambiguity bound: (name, rows, weights by level, robust)
AMBIGUITY_PRIORS = (
    ("Debevec's: (ln f^-1)'' squared, hat-weighted", "second", "hat", False),
    ("(ln f^-1)'' squared, unweighted", "second", "flat", False),
    ("(ln f^-1)'' absolute (L1), hat-weighted", "second", "hat", True),
    ("log-log curvature squared, 1/z-weighted", "loglog", "inverse", False),
    ("log-log curvature absolute (L1)", "loglog", "flat", True),
)


def ambiguity_bound(table: np.ndarray, rows: str, weights: str, robust: bool, *, knots: int = 128,
                    low: int = 3) -> np.ndarray:
    """The member of the exact-2x ambiguity family of ``table`` that a prior prefers: the infinite-data limit of a
    fit whose only choice is the prior's (its error is what no amount of data can remove).

    With every exposure ratio 2, ``g = ln f^-1`` and ``g + q(g mod ln 2)`` (``q`` any periodic function) predict
    every image alike. ``q`` is a periodic piecewise-linear function on ``knots`` knots; the prior's rows act on
    ``g`` over levels ``low``..254: ``second`` the second difference, ``loglog`` the change of the elasticity
    ``(z + 1/2) (g(z+1) - g(z))`` (0 for any gamma curve); ``robust`` minimises absolute values (10 reweighted
    rounds) instead of squares. Returns the chosen member's table, normalised to 1 at level 255.
    """
    g = np.log(table[low:])  # levels low..255
    phase = np.mod(g / np.log(2.0), 1.0) * knots
    left = np.floor(phase).astype(int) % knots
    frac = phase - np.floor(phase)
    basis = np.zeros((g.size, knots))
    basis[np.arange(g.size), left] += 1 - frac
    basis[np.arange(g.size), (left + 1) % knots] += frac
    z = np.arange(low + 1, 254, dtype=float)  # the rows' centre levels (levels low..254 carry data)
    diff = np.zeros((z.size, g.size - 1))
    for i in range(z.size):
        diff[i, i:i + 3] = (1.0, -2.0, 1.0) if rows == "second" else (z[i] - 0.5, -2 * z[i], z[i] + 0.5)
    base = {"hat": np.minimum(z, 255 - z), "flat": np.ones_like(z), "inverse": 1.0 / z}[weights]
    w = base.copy()
    op, g0 = diff @ basis[:-1], diff @ g[:-1]
    for _ in range(10 if robust else 1):
        design = np.vstack([op * w[:, None], 1e-5 * np.eye(knots)])
        q = np.linalg.lstsq(design, np.concatenate([-g0 * w, np.zeros(knots)]), rcond=None)[0]
        if robust:  # iteratively reweighted least squares for the absolute values
            w = base / np.sqrt(np.maximum(np.abs(g0 + op @ q), 1e-6))
    out = table.copy()
    out[low:] = np.exp(g + basis @ q)
    return out / out[-1]


def ambiguity_rows() -> list[dict]:
    """Per curve and prior, :func:`ambiguity_bound`'s max |f^-1 - truth| over levels 5..250 (% of the range)."""
    from response_curves import curves, max_error_percent

    rows = []
    for label, kind, weights, robust in AMBIGUITY_PRIORS:
        row = {"prior (infinite data, exact 2x)": label}
        for name, table in curves().items():
            row[name] = float(max_error_percent(ambiguity_bound(table, kind, weights, robust), table)[0])
        rows.append(row)
    return rows


def pipeline_rows(size: tuple[int, int], designs: list[str], seed: int = 0, quality: bool = True,
                  deblur: bool = False) -> list[dict]:
    """The ``--pipelines`` table (see the module docstring); ``deblur``: the fit with ``deblur=True`` (opt-in)."""
    from camera_pipelines import PIPELINES, ceiling_level, max_error_scale_free, render
    from response_curves import curves, scene

    from radiometry.response.fit import fit_response
    from radiometry.response.quality import assess

    width, height = size
    radiance = scene(height, width, seed=seed + 1)
    rows = []
    for name, table in curves().items():
        for pipeline, options in PIPELINES.items():
            gains = options.get("gains", (1.0, 1.0, 1.0))
            ceilings = [ceiling_level(table, g) for g in gains]
            for design in designs:
                times = design_times(design)
                images = render(table, radiance, times, seed=seed + 2, **options)
                start = time.perf_counter()
                response = fit_response(images, times, **({"deblur": True} if deblur else {}))
                seconds = time.perf_counter() - start
                declared = response.meta["declared_levels"]
                err = max_error_scale_free(response.inverse_table, table, declared)
                row = {"curve": name, "pipeline": pipeline, "design": design,
                       "max err [%] R/G/B": "/".join(f"{v:.2f}" for v in err),
                       "levels used (top) R/G/B": "/".join(str(hi) for _, hi in declared),
                       "true ceiling R/G/B": "/".join(f"{c:.0f}" for c in ceilings),
                       "below ceiling": all(hi <= c for (_, hi), c in zip(declared, ceilings)),
                       "found": response.meta.get("levels_summary", "").split("; levels used")[0] or "-",
                       "fit [s]": round(seconds, 1)}
                if quality:
                    q = assess(images, times, response, method=None)
                    row["held-out RMS [levels]"] = round(q["holdout_rms_levels"], 2)
                    row["grade (fast)"] = q["grade"]
                rows.append(row)
                print(" ".join(str(v) for v in row.values()), flush=True)
    return rows


def _end_to_end(args: argparse.Namespace, rest: list[str]) -> int:
    """``--end-to-end``: :mod:`bench_vignetting` once per design, with this command's ``--seed`` and, when given,
    the ``--methods`` that are :func:`radiometry.response.fit.fit_response` methods; ``rest`` (its own options,
    e.g. ``--vignettes``, ``-n``, ``--out``) goes through. With two designs, ``--out FILE`` gets the design in its
    name."""
    from radiometry.response.fit import METHODS as FIT_METHODS

    scripts = str(Path(__file__).resolve().parent)
    if scripts not in sys.path:
        sys.path.insert(0, scripts)
    import bench_vignetting

    extra = ["--seed", str(args.seed)]
    if args.methods is not None:
        chosen = [m for m in args.methods if m in FIT_METHODS]
        if not chosen:
            print(f"bench_calibration: --end-to-end needs --methods among {', '.join(FIT_METHODS)}")
            return 2
        extra += ["--methods", *chosen]
    status = 0
    for design in args.design:
        own = list(rest)
        if "--out" in own and len(args.design) > 1:
            at = own.index("--out") + 1
            if at < len(own):
                out = Path(own[at])
                own[at] = str(out.with_name(f"{out.stem}_{design}{out.suffix}"))
        status = max(status, bench_vignetting.main(["--design", design, *extra, *own]))
    return status


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--size", default="640x480", help="image size WxH (default 640x480)")
    parser.add_argument("--design", nargs="+", choices=("2x", "varied"), default=["2x", "varied"],
                        help="exposure designs (default both)")
    parser.add_argument("--methods", nargs="+", choices=tuple(METHODS), default=None,
                        help="methods (default all; with --end-to-end, bench_vignetting's)")
    parser.add_argument("--seed", type=int, default=0, help="scene and noise seed")
    parser.add_argument("--curve-set", choices=("test", "break"), default="test",
                        help="test: the test set (gamma, S, two kinks, EuRoC); break: curves built to break the "
                             "priors (dark kink and flat, shoulder, mid kink, linear, gamma 3, sRGB)")
    parser.add_argument("--end-to-end", action="store_true",
                        help="instead: response and vignetting LUT end to end per curve x vignette x method "
                             "(scripts/bench_vignetting.py; its options follow)")
    parser.add_argument("--deblur", action="store_true",
                        help="with --pipelines: the fit with deblur=True (the level-noise correction, opt-in)")
    parser.add_argument("--pipelines", action="store_true",
                        help="instead: the default fit through real camera pipelines (white balance after the clip, "
                             "JPEG, noise after the response; tests/camera_pipelines.py)")
    parser.add_argument("--ambiguity", action="store_true",
                        help="instead: the exact-2x ambiguity bound per prior (no rendering, no fits)")
    args, rest = parser.parse_known_args(argv)
    if args.end_to_end:  # the response and the LUT calibrated with it, per curve x vignette x method
        return _end_to_end(args, rest)
    if rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    try:
        width, height = (int(v) for v in args.size.lower().split("x"))
    except ValueError:
        parser.error(f"--size must be WxH, e.g. 640x480, got {args.size!r}")
    import logging

    import cv2

    from radiometry.tables import format_table

    if args.ambiguity:
        print("what a prior chooses when the data leave only the exact-2x ambiguity (max err 5..250 [%] of the "
              "member of the truth's family that it prefers)")
        print(format_table(ambiguity_rows()))
        return 0

    quiet = logging.getLogger("radiometry")  # repaired / equal-ratio warnings: the table shows them
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    if args.pipelines:
        try:
            rows = pipeline_rows((width, height), args.design, seed=args.seed, deblur=args.deblur)
        finally:
            quiet.setLevel(level)
        print(f"the default response fit through camera pipelines vs truth ({width}x{height}, 12 exposures, "
              f"OpenCV {cv2.__version__} JPEG)")
        print(format_table(rows))
        return 0
    try:
        rows = run((width, height), args.design, args.methods or list(METHODS), seed=args.seed,
                   curve_set=args.curve_set)
    finally:
        quiet.setLevel(level)  # main() may run inside another program (the tests): leave its logging as it was
    print(f"response calibration vs truth ({width}x{height}, 12 exposures, OpenCV {cv2.__version__})")
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
