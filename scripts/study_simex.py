#!/usr/bin/env python3
"""Study: SIMEX (simulation-extrapolation, Cook & Stefanski 1994) against the level noise that blurs a response fit.

Noise added after the response (an ISP's, JPEG's) is noise on the level ``z``, the fit's regressor: the fitted
``ln f^-1`` is the truth blurred over ~sigma levels (docs/calibration_pipelines.md). SIMEX measures how the fit moves
when more such noise is added and extrapolates back to no noise, without a model of the curve. Per channel:

1. the default fit (:func:`radiometry.response.loglog.fit_response_loglog`'s steps: levels found from the data,
   stall test, edge mask and outlier rounds on JPEG stacks) on the data: ``g_0 = ln f^-1``;
2. for each ``lambda`` in ``--lambdas``, ``--draws`` times: every reading of the channel plus ``round(d)``,
   ``d ~ N(0, s^2)``, clipped to 0..255 (a channel with an exact pile keeps its pile and is clipped below it: the
   noise of such a camera comes before its clip), the stall test again on the noisy readings, the same level window,
   the same fit; the ``draws`` curves averaged. ``round(d)`` of an integer reading is exact, so the variance added is
   ``Var(round(d))`` (computed, not approximated); ``s`` is chosen so that it is ``lambda * V0``, ``V0`` the
   level-error variance of the data: ``sigma^2 + 1/12`` (the noise plus the 8-bit rounding; ``--no-rounding``:
   ``sigma^2``);
3. per level, ``g(lambda)`` (normalised at the top level of the data's fit) extrapolated to ``lambda = -1`` by
   ``linear`` / ``quadratic`` in lambda, ``sigma-linear`` / ``sigma-quadratic`` in ``s = sqrt(1 + lambda)``
   (a knee's bias grows like sigma, not like its square) and ``rational`` (``a + b / (c + lambda)``, c > 1 on a grid,
   the classical nonlinear extrapolant).

Reported, per stack: the largest ``|f^-1 - truth|`` over the fit's declared levels, % of the range, R/G/B
(``tests/camera_pipelines.py: max_error_scale_free``, as ``bench_calibration.py --pipelines``), for the fit and each
extrapolant; the sigma used; seconds.

``--sigma true`` uses the noise the pipeline adds (1.5 for ``post-noise``, 0 otherwise: then only the rounding's
1/12 is left to extrapolate); ``--sigma NUMBER`` that value everywhere; ``--sigma estimate`` the estimate from the
data alone (``--estimators`` lists them; :func:`sigma_estimates`). ``--estimate-only`` prints the estimators
against the truth without SIMEX fits (``--noise`` sets the post-noise levels to render). ``--real`` runs the real
stacks in ``../shared/data/brackets`` (no truth: how far SIMEX moves the curve).

Variants (measured 2026-11-28, docs/calibration_pipelines.md; none passed): ``--stall noisy`` / ``window`` (which
readings the noisy refits may use), ``--freeze-top K``, ``--lambdas``, ``--draws``, ``--no-rounding``; ``--dump DIR``
saves each stack's curves per lambda.

Usage::

    python scripts/study_simex.py --size 320x240 --curves kink-4x flat-then-steep --pipelines post-noise
    python scripts/study_simex.py --size 320x240 --sigma estimate --pipelines clean post-noise wb-jpeg92 jpeg75
    python scripts/study_simex.py --size 320x240 --estimate-only --noise 0 1 1.5 3
    python scripts/study_simex.py --real
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
for path in (REPO, REPO / "tests", REPO / "scripts"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

EXTRAPOLANTS = ("linear", "quadratic", "sigma-linear", "sigma-quadratic", "rational")
TRUE_SIGMA = {"post-noise": 1.5}


# --------------------------------------------------------------------------------------------------
# the added noise
# --------------------------------------------------------------------------------------------------
def rounded_variance(s: float) -> float:
    """``Var(round(d))`` for ``d ~ N(0, s^2)`` (exact sum over the integers)."""
    if s <= 0:
        return 0.0
    from scipy.stats import norm

    k = np.arange(1, int(12 * s) + 3)
    p = norm.cdf((k + 0.5) / s) - norm.cdf((k - 0.5) / s)
    return float(2.0 * np.sum(k * k * p))


def spread_for(variance: float) -> float:
    """The ``s`` whose rounded normal has ``variance`` (bisection; ``Var(round(d))`` grows with s)."""
    if variance <= 0:
        return 0.0
    lo, hi = 1e-3, math.sqrt(variance) + 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if rounded_variance(mid) < variance:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


# --------------------------------------------------------------------------------------------------
# the fit, as fit_response_loglog does it, on one channel's readings
# --------------------------------------------------------------------------------------------------
def _channel_fit(values, t, window, valid_flat, pile, stall_test, jpeg, ceiling, seed, lam, smooth):
    """``ln`` of the completed table (256,) and the observed levels of one channel's readings ``values`` (N, P)."""
    from radiometry.response.deblur import outliers
    from radiometry.response.engel import DEFAULT_PIXELS, _complete, _observations
    from radiometry.response.levels import stalled_observations
    from radiometry.response.loglog import TRIM_ROUNDS, _keep, _solve_channel

    log_t = np.log(t)
    rng = np.random.default_rng(seed)
    if isinstance(stall_test, np.ndarray):  # the data's stall test, given
        stalled = stall_test
    else:
        stalled = stalled_observations(values, t, pile) if stall_test else None
    pix, img, z, n_pix = _observations(values, t, window, DEFAULT_PIXELS, valid_flat, rng, stalled)
    sol = _solve_channel(pix, img, z, n_pix, log_t, lam, smooth)
    for _ in range(TRIM_ROUNDS if stall_test is not False and jpeg else 0):
        drop = outliers(_complete(sol["u"], sol["observed"], sol["counts"])[0], pix, img, z, n_pix, log_t,
                        ceiling, trim=jpeg)
        if not drop.any():
            break
        pix, img, z, n_pix = _keep(pix, img, z, ~drop)
        sol = _solve_channel(pix, img, z, n_pix, log_t, lam, smooth)
    table = _complete(sol["u"], sol["observed"], sol["counts"])[0]
    with np.errstate(divide="ignore"):  # f^-1(0) = 0
        g = np.log(table)
    return g, np.flatnonzero(sol["observed"]), (pix, img, z, n_pix, sol)


def _noisy(values: np.ndarray, s: float, pile: int | None, rng: np.random.Generator) -> np.ndarray:
    d = np.rint(s * rng.standard_normal(values.shape)).astype(np.int16)
    out = values.astype(np.int16) + d
    if pile is not None:  # an exact ceiling: the saturated read it whatever the noise, the others stay below
        out = np.where(values == pile, pile, np.minimum(out, pile))
    return np.clip(out, 0, 255).astype(np.uint8)


def extrapolate(lams: np.ndarray, curves: np.ndarray, how: str) -> np.ndarray:
    """``curves`` (K, L): per lambda in ``lams`` (K,), a value per level; the value at lambda = -1 per level."""
    if how in ("linear", "quadratic"):
        deg = 1 if how == "linear" else 2
        coef = np.polynomial.polynomial.polyfit(lams, curves, deg)
        return np.polynomial.polynomial.polyval(-1.0, coef)
    if how in ("sigma-linear", "sigma-quadratic"):
        deg = 1 if how == "sigma-linear" else 2
        coef = np.polynomial.polynomial.polyfit(np.sqrt(1.0 + lams), curves, deg)
        return coef[0]
    if how == "rational":  # a + b / (c + lambda), c > 1 on a grid, (a, b) by least squares per level
        best, best_res = None, None
        for c in np.geomspace(1.02, 200.0, 80):
            x = 1.0 / (c + lams)
            design = np.stack([np.ones_like(x), x], axis=1)
            coef, *_ = np.linalg.lstsq(design, curves, rcond=None)
            res = np.sum((design @ coef - curves) ** 2, axis=0)
            value = coef[0] + coef[1] / (c - 1.0)
            if best is None:
                best, best_res = value, res
            else:
                better = res < best_res
                best = np.where(better, value, best)
                best_res = np.where(better, res, best_res)
        return best
    raise ValueError(f"extrapolant must be one of {', '.join(EXTRAPOLANTS)}, got {how!r}")


def simex_fit(images, times, sigma: float | list[float], *, lambdas=(0.5, 1.0, 2.0), draws: int = 4,
              rounding: bool = True, seed: int = 0, lam: float | None = None,
              smooth: float | None = None, stall: str = "data", freeze_top: int = 0) -> dict:
    """The default fit and its SIMEX corrections: ``{"base": table (256, C), extrapolant: table (256, C), ...,
    "declared": [(lo, hi)], "sigma": [...], "seconds_base": s, "seconds": s, "g": per channel (K, 256)}``.
    ``sigma``: the level noise (levels) per channel or one for all. ``stall``: ``"data"`` leaves out, in every
    noisy refit, the observations the data's stall test left out; ``"noisy"`` runs the stall test on the noisy
    readings (its 4-level tolerance then lets far more saturated readings in as the noise grows); ``"window"``:
    as ``"data"``, and the readings outside the data's level window left out too (no influx across the window's
    ends: a saturated reading that the stall test missed stays out however much noise is added). ``freeze_top``: the
    levels above ``top - freeze_top`` take that level's correction (0: none)."""
    from radiometry.response.inputs import _as_stack
    from radiometry.response.levels import BLOCKY, _pile, prepare, stalled_observations
    from radiometry.response.loglog import DEFAULT_LAM, DEFAULT_SMOOTH, _saturates_at

    lam = DEFAULT_LAM if lam is None else lam
    smooth = DEFAULT_SMOOTH if smooth is None else smooth
    start = time.perf_counter()
    stack, t = _as_stack(images, times)
    n_img, h, w, n_ch = stack.shape
    windows, valid_flat, level_meta = prepare(stack, t, None, "auto", edges="auto", seed=seed)
    jpeg = level_meta.get("blockiness", 0.0) > BLOCKY
    flat = stack.reshape(n_img, h * w, n_ch)
    sigmas = [float(sigma)] * n_ch if np.isscalar(sigma) else [float(s) for s in sigma]
    lams = np.array([0.0, *lambdas])
    out = {"declared": [], "sigma": sigmas, "g": [], "lambdas": lams.tolist(), "added_variance": []}
    tables = {k: [] for k in ("base", *EXTRAPOLANTS)}
    base_seconds = 0.0
    for c in range(n_ch):
        values = np.ascontiguousarray(flat[:, :, c])
        pile = _pile(level_meta, c)
        ceiling = _saturates_at(level_meta, c)
        fit_args = (t, windows[c], valid_flat, pile, True, jpeg, ceiling, seed + c, float(lam), float(smooth))
        t0 = time.perf_counter()
        g0, observed, _ = _channel_fit(values, *fit_args)
        base_seconds += time.perf_counter() - t0
        top = int(observed[-1])
        data_stalled = stalled_observations(values, t, pile)
        if stall == "window":  # only the data's own observations, censored where the noise takes them out
            data_stalled = data_stalled | (values < windows[c][0]) | (values > windows[c][1])
        out["declared"].append((int(observed[0]), top))
        v0 = sigmas[c] ** 2 + (1.0 / 12.0 if rounding else 0.0)
        rng = np.random.default_rng(10_000 + 97 * seed + c)
        curves = [g0 - g0[top]]
        added = []
        for lam_k in lambdas:
            s = spread_for(lam_k * v0)
            added.append(rounded_variance(s))
            acc = np.zeros(256)
            for _ in range(int(draws)):
                noisy = _noisy(values, s, pile, rng)
                args = fit_args if stall == "noisy" else (*fit_args[:4], data_stalled, *fit_args[5:])
                g, _, _ = _channel_fit(noisy, *args)
                acc += g - g[top]
            curves.append(acc / draws)
        curves = np.array(curves)
        out["g"].append(curves)
        out["added_variance"].append(added)
        real_lams = np.array([0.0, *added]) / v0 if v0 > 0 else lams
        tables["base"].append(np.exp(curves[0]))
        for how in EXTRAPOLANTS if len(lambdas) and draws else ():
            g = np.full(256, -np.inf)  # level 0: f^-1 = 0 (ln = -inf) in every fit
            g[1:] = extrapolate(real_lams, curves[:, 1:], how)
            if freeze_top:  # the top levels take the correction of level top - freeze_top
                keep = top - int(freeze_top)
                g[keep + 1:] = curves[0, keep + 1:] + (g[keep] - curves[0, keep])
            g = np.maximum.accumulate(g)  # keep f^-1 non-decreasing
            tables[how].append(np.exp(g))
    for key, cols in tables.items():
        if not cols:
            continue
        table = np.stack(cols, axis=1)
        out[key] = table / table[-1]
    out["seconds_base"] = base_seconds  # the data's fit alone (without the level detection)
    out["seconds"] = time.perf_counter() - start
    out["level_meta"] = level_meta
    return out


# --------------------------------------------------------------------------------------------------
# the level noise from the data alone
# --------------------------------------------------------------------------------------------------
def sigma_estimates(images, times, *, seed: int = 0) -> dict[str, list[float]]:
    """Per channel, estimates (levels) of the noise after the response, from the stack alone:

    - ``ceiling``: :func:`radiometry.response.levels.ceiling_noise`, the spread of the saturated readings;
    - ``residual``: :func:`_split_residuals`, the leave-one-out residuals in levels split by regression into the
      part constant in levels (noise after the response) and the parts that scale with the level slope (the
      sensor's noise, photon and constant in ``ln x``);
    - ``residual-flat``: :func:`_flat_residuals`, the leave-one-out residual variance where the level slope
      ``dz / d ln x`` is smallest (the sensor's noise in levels is then smallest), less what the other
      observations' level noise and the rounding put in.
    """
    from radiometry.response.inputs import _as_stack
    from radiometry.response.levels import BLOCKY, _pairs, _pile, ceiling_noise, prepare
    from radiometry.response.loglog import DEFAULT_LAM, DEFAULT_SMOOTH, _saturates_at

    stack, t = _as_stack(images, times)
    n_img, h, w, n_ch = stack.shape
    windows, valid_flat, level_meta = prepare(stack, t, None, "auto", edges="auto", seed=seed)
    jpeg = level_meta.get("blockiness", 0.0) > BLOCKY
    out = {"ceiling": [], "residual": [], "residual-flat": []}
    flat = stack.reshape(n_img, h * w, n_ch)
    for c in range(n_ch):
        values = np.ascontiguousarray(flat[:, :, c])
        found = level_meta["level_detection"][c]
        ceil = found.get("pile") or found.get("saturates_at") or 255
        out["ceiling"].append(ceiling_noise(values, _pairs(t, longer=True), int(ceil)))
    log_t = np.log(t)
    for c in range(n_ch):
        values = np.ascontiguousarray(flat[:, :, c])
        g, observed, (pix, img, z, n_pix, sol) = _channel_fit(
            values, t, windows[c], valid_flat, _pile(level_meta, c), True, jpeg, _saturates_at(level_meta, c),
            seed + c, DEFAULT_LAM, DEFAULT_SMOOTH)
        table = np.exp(g)
        out["residual"].append(_split_residuals(table, g, pix, img, z, n_pix, log_t))
        out["residual-flat"].append(_flat_residuals(table, g, pix, img, z, n_pix, log_t))
    return out


def _loo_terms(table, g, pix, img, z, n_pix, log_t):
    """Per observation with others: the squared leave-one-out residual (levels) and the regressors of its variance
    (see :func:`_split_residuals`)."""
    from radiometry.response.deblur import leave_one_out_levels

    hat = np.maximum(np.minimum(np.arange(256.0), 255.0 - np.arange(256.0)), 1.0)
    pred = leave_one_out_levels(table, pix, img, z, n_pix, log_t)
    dg = np.maximum(np.gradient(g[1:]), 1e-9)  # d ln f^-1 / dz, levels 1..255
    dg = np.concatenate([[dg[0]], dg])
    w = hat[z]
    sw = np.bincount(pix, weights=w, minlength=n_pix)
    rest = sw[pix] - w
    # the others' sums: sum w^2 g'^2 (level noise), sum w^2 / u (photon), sum w^2 (constant in ln x)
    lvl = np.bincount(pix, weights=w * w * dg[z] ** 2, minlength=n_pix)[pix] - w * w * dg[z] ** 2
    pho = np.bincount(pix, weights=w * w / table[z], minlength=n_pix)[pix] - w * w / table[z]
    con = np.bincount(pix, weights=w * w, minlength=n_pix)[pix] - w * w
    ok = np.isfinite(pred) & (rest > 0)
    slope2 = (1.0 / dg[z]) ** 2  # (dz / d ln x)^2 at the observation
    with np.errstate(invalid="ignore", divide="ignore"):
        r1 = 1.0 + slope2 * lvl / rest ** 2
        r2 = slope2 * (1.0 / table[z] + pho / rest ** 2)
        r3 = slope2 * (1.0 + con / rest ** 2)
    res2 = (z - pred) ** 2
    return res2[ok], np.stack([r1[ok], r2[ok], r3[ok]], axis=1), slope2[ok]


def _split_residuals(table, g, pix, img, z, n_pix, log_t) -> float:
    """The noise after the response (levels) from the leave-one-out residuals: ``E r^2 = V_level R1 + a R2 + b R3``
    with ``R1 = 1 + slope^2 sum_k w_k^2 g'(z_k)^2 / W^2`` (noise constant in levels, on the observation and, through
    the curve's slope, on the others that predict it), ``R2 = slope^2 (1/u + sum_k w_k^2 / u_k / W^2)`` (photon
    noise, variance in ``ln x`` proportional to ``1/x``), ``R3 = slope^2 (1 + sum_k w_k^2 / W^2)`` (noise constant in
    ``ln x``); ``slope = dz / d ln x``, ``u = f^-1``; non-negative least squares, wild residuals clipped;
    ``sigma = sqrt(V_level - 1/12)`` (less the rounding)."""
    from scipy.optimize import nnls

    res2, design, _ = _loo_terms(table, g, pix, img, z, n_pix, log_t)
    res2 = np.minimum(res2, 25.0 * np.median(res2) + 1.0)
    scale = np.sqrt(np.mean(design ** 2, axis=0))
    scale[scale == 0] = 1.0
    rng = np.random.default_rng(0)
    pick = rng.choice(res2.size, size=min(res2.size, 400_000), replace=False)
    coef, _ = nnls(design[pick] / scale, res2[pick])
    v_level = coef[0] / scale[0]
    return math.sqrt(max(v_level - 1.0 / 12.0, 0.0))


def _flat_residuals(table, g, pix, img, z, n_pix, log_t) -> float:
    """The leave-one-out residual variance at the tenth of the observations with the smallest level slope, divided
    by ``R1`` (:func:`_split_residuals`), less the rounding: the sensor's part is smallest there, not removed."""
    res2, design, slope2 = _loo_terms(table, g, pix, img, z, n_pix, log_t)
    res2 = np.minimum(res2, 25.0 * np.median(res2) + 1.0)
    low = slope2 <= np.quantile(slope2, 0.1)
    return math.sqrt(max(float(np.mean(res2[low]) / np.mean(design[low, 0])) - 1.0 / 12.0, 0.0))


# --------------------------------------------------------------------------------------------------
# the tables
# --------------------------------------------------------------------------------------------------
def _fmt(err) -> str:
    return "/".join(f"{v:.2f}" for v in err)


def _stacks(args):
    """The curves ``args`` selects and the scene's radiance at ``args.size``; :func:`_render` makes their stacks."""
    from response_curves import curves, scene

    width, height = (int(v) for v in args.size.lower().split("x"))
    return ([(name, table) for name, table in curves().items() if not args.curves or name in args.curves],
            scene(height, width, seed=args.seed + 1))


def _render(args, table, radiance, design: str, options: dict):
    """``(times, images)``: the bracket of ``design`` rendered through ``tests/camera_pipelines.py``."""
    from camera_pipelines import render

    from bench_calibration import design_times

    times = design_times(design)
    return times, render(table, radiance, times, seed=args.seed + 2, **options)


def synthetic_rows(args) -> list[dict]:
    from camera_pipelines import PIPELINES, max_error_scale_free

    selected, radiance = _stacks(args)
    rows = []
    for name, table in selected:
        for pipeline in args.pipelines:
            options = dict(PIPELINES.get(pipeline, {}))
            if pipeline.startswith("post-noise-"):  # post-noise-3: noise of 3 levels after the response
                options = {"post_noise": float(pipeline.split("-", 2)[2])}
            elif pipeline not in PIPELINES:
                raise SystemExit(f"unknown pipeline {pipeline!r}: one of {', '.join(PIPELINES)} or post-noise-S")
            true_sigma = float(options.get("post_noise", 0.0))
            for design in args.design:
                times, images = _render(args, table, radiance, design, options)
                estimated = None
                if args.sigma == "true":
                    sigma = true_sigma
                elif args.sigma == "estimate":
                    estimated = sigma_estimates(images, times, seed=0)[args.estimator]
                    sigma = estimated
                else:
                    sigma = float(args.sigma)
                res = simex_fit(images, times, sigma, lambdas=tuple(args.lambdas), draws=args.draws,
                                rounding=not args.no_rounding, stall=args.stall, freeze_top=args.freeze_top)
                row = {"curve": name, "pipeline": pipeline, "design": design,
                       "sigma": "/".join(f"{s:.2f}" for s in res["sigma"]),
                       "fit": _fmt(max_error_scale_free(res["base"], table, res["declared"]))}
                for how in args.extrapolants:
                    row[how] = _fmt(max_error_scale_free(res[how], table, res["declared"]))
                row["fit [s]"] = round(res["seconds_base"], 1)
                row["simex [s]"] = round(res["seconds"], 1)
                rows.append(row)
                print(" | ".join(str(v) for v in row.values()), flush=True)
                if args.dump:
                    Path(args.dump).mkdir(parents=True, exist_ok=True)
                    np.savez(Path(args.dump) / f"{name}_{pipeline}_{design}.npz", truth=table,
                             g=np.array(res["g"]), declared=np.array(res["declared"]),
                             added=np.array(res["added_variance"]),
                             **{k: res[k] for k in ("base", *EXTRAPOLANTS) if k in res})
    return rows


def estimate_rows(args) -> list[dict]:
    from camera_pipelines import PIPELINES

    selected, radiance = _stacks(args)
    rows = []
    for name, table in selected:
        for noise in args.noise:
            cases = [("post-noise", {"post_noise": noise} if noise > 0 else {})]
            if noise == 0:
                cases += [(p, PIPELINES[p]) for p in ("wb-jpeg92", "jpeg75") if p in args.pipelines]
            for pipeline, options in cases:
                for design in args.design:
                    times, images = _render(args, table, radiance, design, options)
                    est = sigma_estimates(images, times)
                    row = {"curve": name, "pipeline": pipeline if options.get("quality") else
                           f"noise {noise:g}", "design": design}
                    for key, vals in est.items():
                        row[key] = "/".join(f"{v:.2f}" for v in vals)
                    rows.append(row)
                    print(" | ".join(str(v) for v in row.values()), flush=True)
    return rows


def real_rows(args) -> list[dict]:
    from radiometry.response.fit import blue_fill_mask, load_brackets

    shared = REPO.parent / "shared" / "data" / "brackets"
    rows = []
    for folder in sorted(shared.iterdir()) if shared.is_dir() else []:
        if not folder.is_dir():
            continue
        images, times, _ = load_brackets(folder, progress=False)
        if "memorial" in folder.name:  # the registration fill: mask, as `--mask-blue` does
            images = _masked(images, blue_fill_mask(images))
        est = sigma_estimates(images, times)
        for estimator in args.estimators:
            sigma = est[estimator]
            res = simex_fit(images, times, sigma, lambdas=tuple(args.lambdas), draws=args.draws,
                            rounding=not args.no_rounding, stall=args.stall)
            row = {"stack": folder.name, "sigma from": estimator, "sigma": "/".join(f"{s:.2f}" for s in sigma)}
            for how in args.extrapolants:  # the largest move of f^-1 over the declared levels, % of the range
                moves = []
                for c, (lo, hi) in enumerate(res["declared"]):
                    moves.append(100 * float(np.max(np.abs(res[how][lo:hi + 1, c] - res["base"][lo:hi + 1, c]))))
                row[f"move {how}"] = _fmt(moves)
            row["fit [s]"] = round(res["seconds_base"], 1)
            row["simex [s]"] = round(res["seconds"], 1)
            rows.append(row)
            print(" | ".join(str(v) for v in row.values()), flush=True)
    return rows


def _masked(images, mask):
    """The images with the masked-out pixels set to 0 (level 0 is outside every fit's window)."""
    return [np.where(mask[..., None], im, 0).astype(np.uint8) for im in images]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0], allow_abbrev=False)
    parser.add_argument("--size", default="320x240")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--curves", nargs="*", default=None, help="default: all of tests/response_curves.py")
    parser.add_argument("--pipelines", nargs="+", default=["clean", "post-noise"],
                        help="of tests/camera_pipelines.py, or post-noise-S (S levels of noise after the response)")
    parser.add_argument("--design", nargs="+", choices=("2x", "varied"), default=["2x", "varied"])
    parser.add_argument("--sigma", default="true", help="true, estimate, or a number of levels")
    parser.add_argument("--estimator", default="residual", help="with --sigma estimate: which estimate")
    parser.add_argument("--estimators", nargs="+", default=["residual"], help="with --real")
    parser.add_argument("--lambdas", nargs="+", type=float, default=[0.5, 1.0, 2.0])
    parser.add_argument("--draws", type=int, default=4)
    parser.add_argument("--stall", choices=("data", "noisy", "window"), default="data",
                        help="the noisy refits leave out the data's stalled observations, or test the noisy ones")
    parser.add_argument("--freeze-top", type=int, default=0,
                        help="the top K levels take the correction of level top - K (0: none)")
    parser.add_argument("--no-rounding", action="store_true", help="V0 = sigma^2 (not + 1/12)")
    parser.add_argument("--extrapolants", nargs="+", choices=EXTRAPOLANTS, default=list(EXTRAPOLANTS))
    parser.add_argument("--estimate-only", action="store_true")
    parser.add_argument("--noise", nargs="+", type=float, default=[0.0, 1.0, 1.5, 3.0])
    parser.add_argument("--real", action="store_true")
    parser.add_argument("--dump", default=None, help="save each stack's curves (npz) in this folder")
    args = parser.parse_args(argv)
    import logging

    logging.getLogger("radiometry").setLevel(logging.ERROR)
    from radiometry.tables import format_table

    if args.estimate_only:
        rows = estimate_rows(args)
    elif args.real:
        rows = real_rows(args)
    else:
        rows = synthetic_rows(args)
    print(format_table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
