"""Engel-style response calibration: maximum likelihood of ``f^-1`` over all pixels, no smoothness prior.

Model (Engel, Usenko & Cremers, "A Photometrically Calibrated Benchmark For Monocular Visual Odometry", 2016;
TUM's ``mono_dataset_code`` ``responseCalib`` and radical's ``engel_calibration``): every valid observation of
pixel ``i`` in exposure ``j`` satisfies ``U(z_ij) = t_j B_i + noise``, with ``U = f^-1`` one free value per
level and ``B_i`` the pixel's irradiance. Under Gaussian noise in irradiance the maximum-likelihood estimate
minimises ``sum (U(z_ij) - t_j B_i)^2``. Engel alternates the two closed-form updates

- irradiance per pixel: ``B_i = sum_j t_j U(z_ij) / sum_j t_j^2``;
- response per level: ``U(k) = mean of t_j B_i`` over the observations of level ``k``,

until ``U`` stops changing (``solver="alternate"``). The default, ``solver="eigen"``, finds the same minimum
directly: with ``B_i`` eliminated the energy is a quadratic form ``U^T N U`` (``N = diag(counts) - V^T V``,
``V[i, z_ij] += t_j / sqrt(sum_j t_j^2)``, 256 x 256), and one alternation round is ``U <- (I - C^-1 N) U``
(``C = diag(counts)``) followed by a renormalisation: a power iteration, whose fixed point is the eigenvector of
the generalised eigenproblem ``N U = mu C U`` with the smallest ``mu``. Solved directly it takes about 1 s a
channel at 640x480 (the alternation: 80 rounds on varied brackets, 1000-1300 on exact 2x ones, 20-150 s a fit)
and agrees with the alternation to 1e-6 (``tests/test_response_engel.py``). When that eigenvector is not
increasing, the alternation (isotonic in every update, below) continues from it. Without a smoothness term a
knee in the response stays a knee: each level is estimated from its own observations only.

``prior > 0`` (eigen only) adds ``prior * |rows ln U|^2`` with the log-log curvature rows of
:func:`loglog_curvature_rows` to the energy per unit normalisation (relative to its minimum) and minimises that by
Newton's method in ``ln U``. Measured on the test set (640x480, worst channel): on varied brackets weight 1
changes little (0.67 / 0.75 / 0.68 / 0.82 / 0.69 % against 0.68 / 0.78 / 0.69 / 0.82 / 0.70 % without); on exact
2x brackets no weight helps (worst curve 6.2 % at 0, 4.8 % at 100; from 1000 on the prior rounds the knees, 3.6 %
and more): Engel's energy itself prefers a member of the 2x ambiguity
family 6-7 % off (its noise model, relative to ``U^2``, differs from phase to phase of ``ln E``), and a prior
that overrides that also overrides the data at a knee. :mod:`radiometry.response.loglog` is the fit for those.

The exposure design matters more than for Debevec. If the exposure times are all one ratio apart (a bracket
at exactly 2x steps), the data constrain ``f^-1`` only up to a factor that is periodic in ``ln E`` with the
period of that ratio: ``U'(z) = U(z) p(ln U(z))`` with ``p(x + ln 2) = p(x)`` predicts every image exactly as
well, and only noise and quantisation tell them apart. Without a prior the estimate then settles along
that direction where the noise model is least wrong (5.5-6.2 % of the range on 640x480 brackets at 2x steps
of the test set, 14-18 % on the embedded 4x sample). With ratios that differ (the same times moved by up to
2^+-0.35, or an exposure sweep as in TUM's dataset) it is within 0.82 % on every curve of the test set, knees
included (``scripts/bench_calibration.py``). Equal ratios are detected (``meta["equal_ratios"]``) and warned
about.

Choices made here (recorded in the model's ``meta``):

- Observations at level 0 and at 255 (saturated) are excluded, as are levels outside ``levels``.
  Pixels with fewer than two valid observations carry no information on ``U`` and are dropped; at most
  ``pixels`` of the rest (a seeded random subset) are used.
- Monotonicity: the response update is the least-squares fit of ``U`` to the per-level means under the
  constraint "non-decreasing" (weighted pool-adjacent-violators, weights = observations per level), i.e. the
  exact minimiser of the energy over monotone ``U`` for the current ``B`` -- not a repair applied afterwards
  (the eigen solver's minimum needs no constraint when it is increasing; else the alternation continues).
  Levels pooled into one value in the final iteration are listed in ``meta["pooled_levels"]``, and a step of
  ``1e-6`` of the range is then added between them so that the table is strictly increasing.
- Levels without observations: inside the observed span they are interpolated linearly; outside it
  (always level 255, usually level 0 and a few dark levels) they are extrapolated linearly from a line fitted
  to the 8 nearest observed levels (towards 0 at the dark end if the line would go negative).
  ``meta["observed_range"]`` is the span constrained by data, ``meta["extrapolated_levels"]`` the levels
  outside it and ``meta["unobserved_levels"]`` every level in 1..254 without an observation.
- Normalisation ``f^-1(255) = 1`` (radiomap's convention) after the extrapolation.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError, TooFewLevelsError
from radiometry.response.model import LEVELS, CameraResponse, repair_monotone
from radiometry.response.inputs import _as_stack, _check_brightness_order, _check_levels, _check_mask, equal_ratios

log = logging.getLogger(__name__)

DEFAULT_PIXELS = 200_000
DEFAULT_MAX_ITER = 2000
DEFAULT_TOLERANCE = 1e-7
SOLVERS = ("eigen", "alternate")
EXTRAPOLATION_SPAN = 8
MIN_STEP = 1e-6
_LEVELS_F = np.arange(LEVELS, dtype=np.float64)


def isotonic_increasing(values: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, list[list[int]]]:
    """Weighted least-squares non-decreasing fit (pool adjacent violators).

    Returns the fitted values and the blocks of more than one index that were pooled to one value.
    """
    blocks: list[list[float]] = []  # [weighted mean, weight, first index, last index]
    for k, (v, w) in enumerate(zip(values.tolist(), weights.tolist())):
        blocks.append([v, w, k, k])
        while len(blocks) > 1 and blocks[-2][0] > blocks[-1][0]:
            v2, w2, _, last = blocks.pop()
            v1, w1, first, _ = blocks.pop()
            blocks.append([(v1 * w1 + v2 * w2) / (w1 + w2), w1 + w2, first, last])
    out = np.empty(len(values))
    pooled = []
    for v, _, first, last in blocks:
        out[first:last + 1] = v
        if last > first:
            pooled.append(list(range(first, last + 1)))
    return out, pooled


def _observations(values: np.ndarray, t: np.ndarray, levels: tuple[int, int], pixels: int | None,
                  valid: np.ndarray | None, rng: np.random.Generator,
                  stalled: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
    """Flatten the usable observations of one channel: (pixel index, exposure index, level) arrays. ``stalled``:
    ``(P, N)`` boolean, observations to leave out (saturated pixels, :mod:`radiometry.response.levels`)."""
    lo, hi = levels
    usable = (values >= lo) & (values <= hi)
    if stalled is not None:
        usable &= ~stalled
    if valid is not None:
        usable &= valid[None, :]
    keep = np.flatnonzero(usable.sum(axis=0) >= 2)
    if keep.size == 0:
        raise CalibrationError(f"no pixel has a level in {lo}..{hi} in two exposures (every pixel is saturated, "
                               "empty or masked); use exposures that overlap, e.g. one stop apart")
    if pixels is not None and keep.size > pixels:
        keep = np.sort(rng.choice(keep, size=int(pixels), replace=False))
    img, pix = np.nonzero(usable[:, keep])
    z = values[img, keep[pix]].astype(np.intp)
    if np.unique(t[img]).size < 2:
        raise TooFewLevelsError("no pixel is unsaturated in two different exposures, so the response is not "
                                "observable", "add exposures that overlap (e.g. one stop apart)")
    return pix, img, z, keep.size


def _normal_matrix(pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int, t: np.ndarray) -> np.ndarray:
    """Engel's energy with the irradiances eliminated, as a quadratic form in ``U``: ``E(U) = U^T N U``.

    Per pixel, ``B_i = sum_j t_j U(z_ij) / sum_j t_j^2`` leaves ``sum_j U(z_ij)^2 - (sum_j t_j U(z_ij))^2 /
    sum_j t_j^2``; summed over pixels, ``N = diag(counts) - V^T V`` with ``V[i, z_ij] += t_j / sqrt(sum_j t_j^2)``.
    """
    import scipy.sparse as sp

    t_obs = t[img]
    t2 = np.bincount(pix, weights=t_obs * t_obs, minlength=n_pix)
    v = sp.csr_matrix((t_obs / np.sqrt(t2[pix]), (pix, z)), shape=(n_pix, LEVELS))  # duplicates are summed
    counts = np.bincount(z, minlength=LEVELS).astype(np.float64)
    return np.diag(counts) - (v.T @ v).toarray()


def loglog_curvature_rows(levels: np.ndarray) -> np.ndarray:
    """Rows of the log-log curvature prior on ``g = ln U`` at the given (observed, increasing) levels: for each
    inner level ``z``, the change of the elasticity ``d g / d ln z`` between its two neighbours' midpoints, weighted
    by ``1/z`` (zero for every gamma curve ``U = z^gamma``). The same rows as ``scripts/bench_calibration.py``'s
    ``--ambiguity`` bound "log-log curvature squared, 1/z-weighted" on consecutive levels."""
    x = np.log(levels.astype(np.float64))
    rows = np.zeros((max(levels.size - 2, 0), levels.size))
    for i in range(1, levels.size - 1):
        up, down = 1.0 / (x[i + 1] - x[i]), 1.0 / (x[i] - x[i - 1])
        rows[i - 1, i - 1:i + 2] = np.array([down, -up - down, up]) / levels[i]
    return rows


def _penalised(n_obs: np.ndarray, c_obs: np.ndarray, g0: np.ndarray, penalty: np.ndarray, r_min: float,
               max_iter: int, tol: float) -> tuple[np.ndarray, int, bool, str]:
    """Minimise ``R(U) / R_min - 1 + g^T penalty g`` over ``g = ln U`` (``U`` at the observed levels, the top one
    fixed at 1), ``R = U^T N U / U^T C U`` the eliminated Engel energy per unit normalisation and ``R_min`` its
    minimum (the smallest eigenvalue): the data term is 0 at Engel's estimate and counts relative excess energy.
    Newton with a trust region (exact Hessian; one unknown per observed level)."""
    from scipy.optimize import minimize

    def parts(free: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        g = np.append(free, 0.0)
        u = np.exp(g)
        cu = c_obs * u
        a, b = float(u @ n_obs @ u), float(u @ cu)
        r = a / b
        grad_u = 2.0 * (n_obs @ u - r * cu) / b
        hess_u = 2.0 * (n_obs - r * np.diag(c_obs)) / b - (2.0 / b) * (np.outer(cu, grad_u) + np.outer(grad_u, cu))
        value = r / r_min - 1.0 + float(g @ penalty @ g)
        grad = u * grad_u / r_min + 2.0 * (penalty @ g)
        hess = (u[:, None] * hess_u * u[None, :] + np.diag(u * grad_u)) / r_min + 2.0 * penalty
        return value, grad[:-1], hess[:-1, :-1]

    res = minimize(lambda f: parts(f)[0], g0[:-1], jac=lambda f: parts(f)[1], hess=lambda f: parts(f)[2],
                   method="trust-exact", options={"maxiter": int(max_iter), "gtol": float(tol)})
    return np.append(res.x, 0.0), int(res.nit), bool(res.success), str(res.message)


def _solve_channel_eigen(pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int, t: np.ndarray, *,
                         prior: float, max_iter: int, tol: float) -> dict[str, Any]:
    """Engel's energy minimised directly: the generalised eigenproblem ``N U = mu diag(counts) U`` (smallest
    ``mu``), which is the fixed point the alternation converges to; with ``prior > 0`` the log-log curvature
    prior is added and the penalised energy minimised from there. Falls back to the alternation (isotonic in
    every update) started from that solution when it is not increasing."""
    from scipy.linalg import eigh

    counts = np.bincount(z, minlength=LEVELS).astype(np.float64)
    observed = counts > 0
    lv = np.flatnonzero(observed)
    n_full = _normal_matrix(pix, img, z, n_pix, t)
    n_obs, c_obs = n_full[np.ix_(lv, lv)], counts[lv]
    mu, vec = eigh(n_obs, np.diag(c_obs), subset_by_index=[0, 0])
    u_obs = vec[:, 0] * (1.0 if vec[:, 0].sum() > 0 else -1.0)
    iterations, converged = 0, True
    if prior > 0 and lv.size > 2:
        rows = loglog_curvature_rows(lv)
        g0 = np.log(np.maximum(u_obs / u_obs[-1], 1e-9))  # a level the eigenvector puts <= 0 starts near 0
        g, iterations, converged, message = _penalised(n_obs, c_obs, g0, prior * (rows.T @ rows), float(mu[0]),
                                                       max_iter, tol)
        if not converged:
            log.warning("the prior's Newton iterations stopped after %d: %s", iterations, message)
        u_obs = np.exp(g)
    u = np.zeros(LEVELS)
    u[lv] = u_obs / u_obs[-1]
    pooled: list[list[int]] = []
    last_change = 0.0
    if lv.size > 1 and not np.all(np.diff(u_obs) > 0):
        sol = _solve_channel(pix, img, z, n_pix, t, max_iter=max_iter, tol=tol, start=u)
        u, pooled, last_change = sol["u"], sol["pooled"], sol["last_change"]
        iterations, converged = iterations + sol["iterations"], converged and sol["converged"]
    b = np.bincount(pix, weights=t[img] * u[z], minlength=n_pix) / np.bincount(pix, weights=t[img] ** 2,
                                                                                 minlength=n_pix)
    residual = u[z] - t[img] * b[pix]
    return {"u": u, "observed": observed, "counts": counts, "pooled": pooled, "iterations": iterations,
            "converged": converged, "last_change": last_change, "b": b, "eigenvalue": float(mu[0]),
            "rms_irradiance": float(np.sqrt(np.mean(residual ** 2)))}


def _solve_channel(pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int, t: np.ndarray, *,
                   max_iter: int, tol: float, start: np.ndarray | None = None) -> dict[str, Any]:
    """Alternate the irradiance and response updates on one channel's observations (from a linear response, or
    from ``start``)."""
    counts = np.bincount(z, minlength=LEVELS).astype(np.float64)
    observed = counts > 0
    t_obs = t[img]
    t2 = np.bincount(pix, weights=t_obs * t_obs, minlength=n_pix)
    u = _LEVELS_F / 255.0 if start is None else start.copy()  # radical's start: a linear response
    converged, change = False, float("inf")
    for iteration in range(1, max_iter + 1):
        b = np.bincount(pix, weights=t_obs * u[z], minlength=n_pix) / t2
        sums = np.bincount(z, weights=t_obs * b[pix], minlength=LEVELS)
        means = sums[observed] / counts[observed]
        fitted, pooled_idx = isotonic_increasing(means, counts[observed])
        new = u.copy()
        new[observed] = fitted / fitted[-1]  # gauge: the top observed level is 1 during the iterations
        change = float(np.abs(new - u)[observed].max())
        u = new
        if change < tol:
            converged = True
            break
    obs_levels = np.flatnonzero(observed)
    pooled = [[int(obs_levels[k]) for k in block] for block in pooled_idx]
    b = np.bincount(pix, weights=t_obs * u[z], minlength=n_pix) / t2
    residual = u[z] - t_obs * b[pix]
    return {"u": u, "observed": observed, "counts": counts, "pooled": pooled, "iterations": iteration,
            "converged": converged, "last_change": change, "b": b,
            "rms_irradiance": float(np.sqrt(np.mean(residual ** 2)))}


def _line(levels: np.ndarray, values: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
    """Weighted least-squares line ``values ~ a + b levels``: returns ``(a, b)``."""
    w = np.sqrt(weights)
    design = np.stack([w, w * levels], axis=1)
    (a, b), *_ = np.linalg.lstsq(design, w * values, rcond=None)
    return float(a), float(b)


def _complete(u: np.ndarray, observed: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Fill the unobserved levels (interpolate inside the observed span, extrapolate outside); return the
    table and the extrapolated levels."""
    lv = np.flatnonzero(observed)
    out = u.copy()
    first, last = int(lv[0]), int(lv[-1])
    inside = np.arange(first, last + 1)
    out[inside] = np.interp(inside, lv, u[lv])
    span = min(EXTRAPOLATION_SPAN, lv.size)
    if last < LEVELS - 1:
        top = lv[-span:]
        _, slope = _line(top.astype(float), u[top], counts[top])
        slope = max(slope, MIN_STEP)
        above = np.arange(last + 1, LEVELS)
        out[above] = u[last] + slope * (above - last)
    if first > 0:
        bottom = lv[:span]
        _, slope = _line(bottom.astype(float), u[bottom], counts[bottom])
        below = np.arange(0, first)
        if slope > 0 and u[first] - slope * first >= 0:
            out[below] = u[first] - slope * (first - below)
        else:  # the line would cross zero before level 0: a ramp from 0 at level 0 instead
            out[below] = u[first] * below / first
    extrapolated = [int(k) for k in range(LEVELS) if k < first or k > last]
    return out, extrapolated


def fit_response_engel(images: Sequence[np.ndarray], times: Sequence[float], *, pixels: int | None = DEFAULT_PIXELS,
                       mask: np.ndarray | None = None, levels: tuple[int, int] = (1, 254),
                       max_iter: int = DEFAULT_MAX_ITER, tol: float = DEFAULT_TOLERANCE,
                       seed: int = 0, solver: str = "eigen", prior: float = 0.0) -> CameraResponse:
    """Engel-style maximum-likelihood response (see the module docstring).

    ``pixels``: at most this many pixels per channel (seeded random subset; None = all). ``mask``: boolean
    ``(H, W)``, True = usable. ``levels``: the valid intensity range (inclusive); observations outside it are
    ignored. ``solver``: ``"eigen"`` (default; the energy's minimum as a generalised eigenproblem, about 1 s a
    channel) or ``"alternate"`` (Engel's alternation; same minimum, 20-150 s on 2x brackets). ``prior``: weight of
    the log-log curvature prior (0 = none, Engel's maximum likelihood; ``"eigen"`` only). ``max_iter``/``tol``: the
    alternation stops when no level's value changes by more than ``tol`` (in units of the top observed level's
    value) or after ``max_iter`` rounds; they bound the prior's Newton iterations likewise (``meta["converged"]``).
    """
    if pixels is not None and (int(pixels) != pixels or pixels < 2):
        raise ValueError(f"pixels must be a whole number >= 2 (pixels used per channel) or None for all, "
                         f"got {pixels}")
    if int(max_iter) != max_iter or max_iter < 1:
        raise ValueError(f"max_iter must be a positive whole number, got {max_iter}")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number, got {tol}")
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, got {solver!r}")
    if not (np.isfinite(prior) and prior >= 0):
        raise ValueError(f"prior must be a number >= 0, got {prior}")
    if prior > 0 and solver != "eigen":
        raise ValueError("prior needs solver='eigen' (the alternation has no prior)")
    lo, hi = _check_levels(levels)
    start = time.perf_counter()
    stack, t = _as_stack(images, times)
    _check_brightness_order(stack, t)
    equal = equal_ratios(t)
    if equal:
        log.warning("the exposure times are all %.3gx apart: the response is then determined only up to a factor "
                    "periodic in ln E, and the Engel fit can be several %% off; use times whose ratios differ, "
                    "or --method loglog (the default, auto)", equal)
    n_img, h, w, n_ch = stack.shape
    valid = _check_mask(mask, (h, w))
    valid_flat = None if valid is None else valid.ravel()
    flat = stack.reshape(n_img, h * w, n_ch)
    tables, per_channel = [], []
    for c in range(n_ch):
        rng = np.random.default_rng(seed + c)
        pix, img, z, n_pix = _observations(np.ascontiguousarray(flat[:, :, c]), t, (lo, hi),
                                           None if pixels is None else int(pixels), valid_flat, rng)
        if solver == "eigen":
            sol = _solve_channel_eigen(pix, img, z, n_pix, t, prior=float(prior), max_iter=int(max_iter),
                                       tol=float(tol))
        else:
            sol = _solve_channel(pix, img, z, n_pix, t, max_iter=int(max_iter), tol=float(tol))
        if not sol["converged"] and solver == "alternate":
            log.warning("channel %d: the alternation did not converge in %d rounds (last change %.2g); raise "
                        "max_iter", c, max_iter, sol["last_change"])
        elif not sol["converged"]:
            log.warning("channel %d: the fit did not converge (the prior's Newton iterations, or the alternation "
                        "continued from the eigenvector, within max_iter %d)", c, max_iter)
        table, extrapolated = _complete(sol["u"], sol["observed"], sol["counts"])
        tables.append(table)
        # fit residual in 8-bit levels: observed level vs f(t_j B_i), both in the units of the completed table
        pred = np.interp(t[img] * sol["b"][pix] / table[-1], table / table[-1], _LEVELS_F)
        sol.update(extrapolated=extrapolated, pixels=n_pix, observations=int(z.size),
                   sq_levels=float(np.sum((pred - z) ** 2)))
        per_channel.append(sol)
    table = np.stack(tables, axis=1)
    strict = bool(np.all(np.diff(table, axis=0) > 0))
    if not strict:  # ties left by pooled levels (or a flat extrapolation): the smallest strict step
        table = repair_monotone(table, min_step=MIN_STEP)
    observed = [np.flatnonzero(s["observed"]) for s in per_channel]
    meta: dict[str, Any] = {
        "method": "engel", "solver": solver, "prior": float(prior), "levels": [lo, hi], "seed": int(seed),
        "max_pixels": None if pixels is None else int(pixels),
        "images": int(n_img), "times": t.tolist(), "masked": valid is not None,
        "pixels": [s["pixels"] for s in per_channel], "observations": [s["observations"] for s in per_channel],
        "iterations": [s["iterations"] for s in per_channel],
        "converged": all(s["converged"] for s in per_channel), "equal_ratios": equal,
        "observed_range": [[int(o[0]), int(o[-1])] for o in observed],
        "extrapolated_levels": [s["extrapolated"] for s in per_channel],
        "unobserved_levels": [[int(k) for k in range(1, LEVELS - 1) if not s["observed"][k]] for s in per_channel],
        "pooled_levels": [s["pooled"] for s in per_channel],
        "monotonicity": ("isotonic (pool adjacent violators) in every response update" if solver == "alternate" else
                         "the minimum is increasing, or the alternation (isotonic in every update) continues from it"),
        "repaired": False, "ties_separated": not strict,
        "fit_rms_irradiance": [s["rms_irradiance"] for s in per_channel],
    }
    response = CameraResponse(table / table[-1], meta)
    sq = sum(s["sq_levels"] for s in per_channel)
    response.meta["fit_rms_levels"] = math.sqrt(sq / sum(s["observations"] for s in per_channel))
    response.meta["fit_seconds"] = time.perf_counter() - start
    return response


__all__ = ["fit_response_engel", "isotonic_increasing", "equal_ratios", "loglog_curvature_rows", "DEFAULT_PIXELS",
           "SOLVERS"]
