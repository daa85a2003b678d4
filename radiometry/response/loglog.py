"""The default response calibration (any exposure design): Debevec's data term over all pixels with a log-log
curvature prior.

Why a separate fit. With every exposure ratio equal (the usual bracket at exactly 2x steps) the images fix
``g = ln f^-1`` only up to ``g + q(g mod ln 2)``, ``q`` any periodic function (Grossberg & Nayar, PAMI 2003):
only a prior can choose the member. Debevec's prior (``g''`` squared, hat-weighted) prefers members 1.4-2.2 % of
the range off on kinked curves even with infinite data; a prior on the log-log curvature (the change of the
elasticity ``d ln f^-1 / d ln z``, zero for every gamma curve) prefers members within 0.6 % on every curve of
the test set (``scripts/bench_calibration.py --ambiguity``). This fit puts that prior on a data term that does not
pull along the ambiguity by itself.

The fit, per channel:

- data: Debevec & Malik's ``sum_ij w(z_ij) (g(z_ij) - ln E_i - ln t_j)^2`` with the hat weight
  ``w(z) = max(min(z, 255 - z), 1)``, over all pixels with at least two valid observations (at most ``pixels`` of
  them, a seeded random subset) instead of 50 sampled pixels a level; the irradiances are eliminated in closed form
  (``ln E_i`` is the weighted mean of ``g(z_ij) - ln t_j``), leaving a 256 x 256 linear system in ``g``, divided by
  the sum of weights (so ``lam`` keeps its meaning whatever the number of pixels);
- prior: ``lam * sum_z (rho(z) d_z)^2`` with ``d_z`` the change of the elasticity between the midpoints around
  observed level ``z`` (:func:`radiometry.response.engel.loglog_curvature_rows`, ``1/z`` weighted) and the extra
  weight ``rho(z) = (128 / z)^2``: a knee at a bright level costs little, a periodic wiggle repeated in the dark
  octaves (where an octave spans few levels) costs a lot;
- knee-preserving smoothness: ``smooth * sum_z w(z) huber(g''(z))`` (Huber threshold 1e-4, by 6 rounds of
  reweighting): the prior above is weak at bright levels, where level-to-level noise of 0.3-0.5 % was left that
  a vignetting LUT sees (EuRoC curve, 320x240: 0.57 levels of flat-field error in blue without it, 0.35 with it,
  Debevec 0.32; ``tests/test_vignetting_end_to_end.py``'s measure); a knee is one large ``g''`` and costs
  little under Huber;
- outliers (a JPEG stack, levels found from the data): after a fit, an observation whose pixel's other
  observations put it at or above the channel's ceiling (a saturated pixel that JPEG reads below it) or more than
  5 robust standard deviations off is left out and the channel fitted again, twice. Not without JPEG: there the
  wild ones are the observations next to a knee and the censored ones the top levels' own (flat-then-steep clean
  0.81 -> 1.10 %, EuRoC noise after the response 0.80 -> 1.44 % with it) (:func:`radiometry.response.deblur.outliers`);
- level noise (``deblur=True``, off by default: its results are mixed, docs/calibration_pipelines.md): the bias the
  noise puts on the fit, measured by fitting stacks simulated from it, is taken off
  (:mod:`radiometry.response.deblur`);
- gauge ``g = 0`` at the top observed level; each round one dense solve (about 1 s a fit at 640x480 on an idle
  machine).

Measured (``scripts/bench_calibration.py``, 640x480, 12 exposures, photon and read noise, max |f^-1 - truth| over
levels 5..250, % of the range, worst channel): exact 2x 0.27 / 0.20 / 0.58 / 0.82 / 0.61 (gamma 2.2, S-curve,
kink 4x, flat-then-steep, EuRoC), varied ratios 0.25 / 0.24 / 0.34 / 0.73 / 0.39; Debevec (lambda 10) 0.42 / 0.72
/ 0.98 / 1.59 / 0.92 on 2x. ``lam`` 0.1, the ``(128/z)^2`` weight and ``smooth`` were chosen on those stacks
(with the vignetting measure above); on another scene and noise seed (640x480) the worst curve is 0.89 % (2x) and
0.74 % (varied), at 320x240 0.78 % and 0.74 %.

Levels without observations and normalisation as :mod:`radiometry.response.engel`: unobserved levels inside the
observed span are interpolated, outside it extrapolated (``meta["extrapolated_levels"]``), ``f^-1(255) = 1``.
Monotonicity is a constraint of the last solve, not a repair: where the minimum decreases, neighbouring levels are
tied and the energy minimised again over the tied values until it does not (``meta["pooled_levels"]``; ties are
then separated by ``1e-6`` of the range, ``meta["ties_separated"]``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError
from radiometry.response.model import LEVELS, CameraResponse, repair_monotone
from radiometry.response.engel import (DEFAULT_PIXELS, MIN_STEP, _complete, _observations, equal_ratios,
                                       loglog_curvature_rows)
from radiometry.response.deblur import outliers
from radiometry.response.levels import BLOCKY
from radiometry.response.inputs import _as_stack, _check_brightness_order, _check_levels, _check_mask

log = logging.getLogger(__name__)

DEFAULT_LAM = 0.1
#: rounds of leaving out the outliers (:func:`radiometry.response.deblur.outliers`) and fitting again
TRIM_ROUNDS = 2
#: weight of the knee-preserving smoothness (Huber on the hat-weighted second differences of ``g``), its Huber
#: threshold (in ``g`` per level^2) and reweighting rounds
DEFAULT_SMOOTH = 5e-3
SMOOTH_DELTA = 1e-4
SMOOTH_ROUNDS = 6
#: the prior's extra weight is (REFERENCE_LEVEL / z)^DARK_POWER on top of the rows' own 1/z
REFERENCE_LEVEL = 128.0
DARK_POWER = 2.0
_LEVELS_F = np.arange(LEVELS, dtype=np.float64)
#: what the stated standard error leaves out (docs/calibration_pipelines.md, "The stated standard error")
BIAS_NOT_IN = ("the fit's bias is not in it: the prior's choice where equal exposure ratios leave the curve open, "
               "the rounding of bends and the top levels by noise on the levels, the extrapolation; on simulated "
               "stacks the bias was the larger part at most levels. Where radiomap states the response's error "
               "(the plot's band, a vignetting budget) it adds the levels' 8-bit width "
               "(radiometry.response.relative_uncertainty), which covered most levels of a clean camera's error on "
               "simulated stacks, not the bias from JPEG or later processing: judge a curve by quality.grade and "
               "quality.bends")
_HAT = np.maximum(np.minimum(_LEVELS_F, 255.0 - _LEVELS_F), 1.0)


def prior_rows(levels: np.ndarray) -> np.ndarray:
    """The prior's rows on ``g`` at the observed ``levels``: the log-log curvature rows times ``(128 / z)^2``."""
    rows = loglog_curvature_rows(levels)
    return rows * (REFERENCE_LEVEL / levels[1:-1, None].astype(np.float64)) ** DARK_POWER


def _normal_equations(pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int,
                      log_t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(M, b)`` with ``sum w (g(z) - ln E - ln t)^2 / sum w = g^T M g - 2 b^T g + const`` after eliminating
    ``ln E`` per pixel: ``M = diag(sum w per level) - V^T V``, ``V[i, z_ij] += w_ij / sqrt(sum_j w_ij)``."""
    import scipy.sparse as sp

    w = _HAT[z]
    lt = log_t[img]
    sw = np.bincount(pix, weights=w, minlength=n_pix)
    v = sp.csr_matrix((w / np.sqrt(sw[pix]), (pix, z)), shape=(n_pix, LEVELS))
    c = np.bincount(pix, weights=w * lt, minlength=n_pix) / np.sqrt(sw)
    m = np.diag(np.bincount(z, weights=w, minlength=LEVELS)) - (v.T @ v).toarray()
    b = np.bincount(z, weights=w * lt, minlength=LEVELS) - v.T @ c
    total = float(w.sum())
    return m / total, b / total


def _second_differences(n: int) -> np.ndarray:
    rows = np.zeros((max(n - 2, 0), n))
    for i in range(n - 2):
        rows[i, i:i + 3] = (1.0, -2.0, 1.0)
    return rows


def _solve_increasing(a: np.ndarray, b: np.ndarray, *,
                      constrained: bool = True) -> tuple[np.ndarray, list[list[int]]]:
    """Minimise ``g^T a g - 2 b^T g`` with the last entry of ``g`` fixed at 0. If the minimum is not increasing
    (and ``constrained``), neighbours where it decreases are tied to one value and the energy minimised again over
    the tied ``g``, until it is non-decreasing (an active set that only grows: pool-adjacent-violators on the
    quadratic form). Returns ``g`` and the blocks of indices (more than one) that share one value."""
    from scipy.linalg import cho_factor, cho_solve

    n = b.size
    group = np.arange(n)  # group of each index; groups are runs of consecutive indices
    while True:
        n_groups = int(group[-1]) + 1
        tie = np.zeros((n, n_groups))
        tie[np.arange(n), group] = 1.0
        reduced_a, reduced_b = tie.T @ a @ tie, tie.T @ b
        h = np.zeros(n_groups)
        if n_groups > 1:
            try:
                h[:-1] = cho_solve(cho_factor(reduced_a[:-1, :-1]), reduced_b[:-1])
            except np.linalg.LinAlgError:
                raise CalibrationError("the observed levels are not linked by pixels seen in two exposures and the "
                                       "prior cannot bridge them; use exposures that overlap (e.g. one stop "
                                       "apart)") from None
        g = tie @ h
        falling = np.flatnonzero(np.diff(h) < 0)
        if not constrained or falling.size == 0:
            break
        merge = np.zeros(n_groups, dtype=np.intp)
        merge[falling + 1] = 1  # group j+1 joins group j
        group = np.cumsum(1 - merge)[group] - 1
    blocks = [np.flatnonzero(group == k).tolist() for k in range(int(group[-1]) + 1)]
    return g, [block for block in blocks if len(block) > 1]


def _solve_channel(pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int, log_t: np.ndarray,
                   lam: float, smooth: float) -> dict[str, Any]:
    counts = np.bincount(z, minlength=LEVELS).astype(np.float64)
    observed = counts > 0
    lv = np.flatnonzero(observed)
    m, b = _normal_equations(pix, img, z, n_pix, log_t)
    m_obs, b_obs = m[np.ix_(lv, lv)], b[lv]
    if lv.size > 2:
        rows = prior_rows(lv)
        m_obs = m_obs + lam * (rows.T @ rows)
    system = m_obs
    curvature = m_obs  # the energy's Hessian at the solution (Huber: 1 inside its threshold, 0 beyond)
    if smooth > 0 and lv.size > 2:  # Huber on the hat-weighted second differences, by reweighting
        second = _second_differences(lv.size)
        hat = _HAT[lv[1:-1]]
        g = _solve_increasing(system, b_obs, constrained=False)[0]
        for _ in range(SMOOTH_ROUNDS):
            robust = np.minimum(1.0, SMOOTH_DELTA / np.maximum(np.abs(second @ g), 1e-300))
            system = m_obs + smooth * (second.T * (hat * robust)) @ second
            g = _solve_increasing(system, b_obs, constrained=False)[0]
        inside = (np.abs(second @ g) <= SMOOTH_DELTA).astype(np.float64)
        curvature = m_obs + smooth * (second.T * (hat * inside)) @ second
    g, blocks = _solve_increasing(system, b_obs)
    u = np.zeros(LEVELS)
    u[lv] = np.exp(g)
    pooled = [[int(lv[k]) for k in block] for block in blocks]
    ln_e_num = np.bincount(pix, weights=_HAT[z] * (np.log(u[z]) - log_t[img]), minlength=n_pix)
    ln_e = ln_e_num / np.bincount(pix, weights=_HAT[z], minlength=n_pix)
    cov = _log_covariance(curvature, pix, z, n_pix, lv, np.log(u[z]) - ln_e[pix] - log_t[img])
    return {"u": u, "observed": observed, "counts": counts, "pooled": pooled, "ln_e": ln_e, "log_cov": cov}


def _log_covariance(curvature: np.ndarray, pix: np.ndarray, z: np.ndarray, n_pix: int, lv: np.ndarray,
                    residual: np.ndarray) -> np.ndarray | None:
    """Covariance of ``g`` at the observed levels ``lv`` relative to the top one (its row and column are 0):
    the sandwich ``H^-1 (sum_i s_i s_i^T / W^2) H^-1`` with ``H`` the energy's Hessian at the solution (data,
    prior, the smoothness rows inside the Huber threshold; the ties of the monotone solve are ignored),
    ``s_i = sum_j w_ij r_ij e_(z_ij)`` the score of pixel ``i`` from its residuals (pixels are independent, their
    observations need not be; the eliminated irradiance drops out since ``sum_j w_ij r_ij = 0``) and ``W`` the sum
    of weights. It measures the noise of the pixels, not the prior's bias nor the factor periodic in ``ln E`` that
    equal exposure ratios leave undetermined. None when ``H`` is singular (or so ill-conditioned that its inverse
    means nothing): the data and prior leave a direction undetermined, and no error is stated rather than 0."""
    import scipy.sparse as sp

    column = np.full(LEVELS, -1, dtype=np.intp)
    column[lv] = np.arange(lv.size)
    w = _HAT[z]
    scores = sp.csr_matrix((w * residual, (pix, column[z])), shape=(n_pix, lv.size))
    meat = (scores.T @ scores).toarray()[:-1, :-1] / float(w.sum()) ** 2
    cov = np.zeros((lv.size, lv.size))
    if lv.size > 1:
        h = curvature[:-1, :-1]
        d = np.diag(h)
        if not (np.all(np.isfinite(h)) and np.all(d > 0)):
            return None
        scale = 1.0 / np.sqrt(d)  # the condition of the scaled Hessian: not the prior's spread of weights
        if np.linalg.cond(h * scale[:, None] * scale[None, :]) > _MAX_CONDITION:
            return None
        inv = np.linalg.inv(h)
        cov[:-1, :-1] = inv @ meat @ inv
        if not np.all(np.isfinite(cov)):
            return None
    return cov


#: the largest condition number of the diagonally scaled Hessian whose inverse is taken as a covariance:
#: numerically singular beyond it (1 / machine epsilon). Unscaled, the prior's (128/z)^2 weights alone reach
#: 5e15 on real stacks at a large lam (taipei, lam 30) while the fit is well determined; scaled, see the test.
_MAX_CONDITION = 1.0 / np.finfo(np.float64).eps


def _normalised_log_stderr(cov: np.ndarray | None, u: np.ndarray, observed: np.ndarray, counts: np.ndarray,
                           table: np.ndarray) -> np.ndarray | None:
    """Standard error of ``ln(table[z] / table[255])`` at every level, (256,): ``cov`` (of ``g`` at the observed
    levels) carried through the completion of ``u`` into ``table`` (interpolation, the extrapolation's line fits,
    the normalisation at 255, usually extrapolated) by its Jacobian, taken by finite differences. None when
    ``cov`` is (the Hessian was singular)."""
    if cov is None:
        return None
    lv = np.flatnonzero(observed)
    with np.errstate(divide="ignore", invalid="ignore"):
        ref = np.log(table) - np.log(table[-1])
    eps = 1e-6
    jac = np.zeros((LEVELS, lv.size))
    for i, level in enumerate(lv):
        moved = u.copy()
        moved[level] *= math.exp(eps)
        moved_table, _ = _complete(moved, observed, counts)
        with np.errstate(divide="ignore", invalid="ignore"):
            jac[:, i] = (np.log(moved_table) - np.log(moved_table[-1]) - ref) / eps
    with np.errstate(invalid="ignore"):
        var = np.einsum("ij,jk,ik->i", jac, cov, jac)
    var[~np.isfinite(var)] = 0.0  # level 0 (f^-1 = 0: no relative error)
    return np.sqrt(np.maximum(var, 0.0))


def _saturates_at(level_meta: dict, channel: int) -> float | None:
    """The level from which channel ``channel`` saturates, when its saturated readings spread (no exact pile)."""
    found = level_meta.get("level_detection")
    if not found or found[channel].get("pile") is not None:
        return None
    return found[channel].get("saturates_at")


def _keep(pix: np.ndarray, img: np.ndarray, z: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, ...]:
    """The observations ``keep`` of the pixels left with two or more, pixels renumbered."""
    pix, img, z = pix[keep], img[keep], z[keep]
    count = np.bincount(pix)
    ok = count[pix] >= 2
    pix, img, z = pix[ok], img[ok], z[ok]
    used, pix = np.unique(pix, return_inverse=True)
    return pix, img, z, int(used.size)


def _ceiling(level_meta: dict, channel: int) -> tuple[float, float]:
    """Where channel ``channel`` saturates in a simulation (its exact pile, else the detected ceiling, else 255) and
    the saturated readings' spread there (0: they read the ceiling; their spread across pixels under JPEG is not
    measured, one of the reasons the simulation does not fit JPEG)."""
    found = level_meta.get("level_detection")
    if not found:
        return 255.0, 0.0
    entry = found[channel]
    return float(entry.get("pile") or entry.get("saturates_at") or 255), 0.0


def _deblur(sol: dict, pix, img, z, n_pix: int, t: np.ndarray, log_t: np.ndarray, levels: tuple[int, int],
            stall_test: bool, pile: int | None, ceiling: tuple[float, float], lam: float, smooth: float, seed: int):
    """:func:`radiometry.response.deblur.correct` with this fit as the refit."""
    from radiometry.response.deblur import correct
    from radiometry.response.levels import stalled_observations

    rng = np.random.default_rng(seed + 7919)

    def refit(values):
        stalled = stalled_observations(values, t, pile) if stall_test else None
        p, i, zz, n = _observations(values, t, levels, None, None, rng, stalled)
        s = _solve_channel(p, i, zz, n, log_t, lam, smooth)
        return _complete(s["u"], s["observed"], s["counts"])[0]

    def complete(u, observed, counts):
        return _complete(u, observed, counts)[0]

    return correct(sol["u"], sol["observed"], sol["counts"], pix, img, z, n_pix, log_t, ceiling[0], refit, complete,
                   rng, exact=pile is not None, ceiling_noise=ceiling[1])


def fit_response_loglog(images: Sequence[np.ndarray], times: Sequence[float], *, lam: float = DEFAULT_LAM,
                        smooth: float = DEFAULT_SMOOTH, pixels: int | None = DEFAULT_PIXELS,
                        mask: np.ndarray | None = None,
                        levels: tuple[int, int] | str = "auto", edges: bool | str = "auto",
                        deblur: bool | str = False, seed: int = 0) -> CameraResponse:
    """Debevec's data term over all pixels with the log-log curvature prior (see the module docstring).

    ``lam``: the prior's weight (per unit of data weight; default 0.1). ``smooth``: weight of the knee-preserving
    smoothness (0 = none). ``pixels``: at most this many pixels per
    channel (seeded random subset; None = all). ``mask``: boolean ``(H, W)``, True = usable. ``levels``: the valid
    intensity range (inclusive) for every channel; observations outside it are ignored; ``"auto"`` (default): per
    channel, the levels between the floor and the ceiling found in the data (:mod:`radiometry.response.levels`: a
    channel that saturates at 241 is fitted below it, the levels above are extrapolated and declared so in
    ``meta["declared_levels"]``). ``edges``: drop the pixels near strong edges (JPEG ringing and chroma
    subsampling; :func:`radiometry.response.levels.edge_mask`): True, False, or ``"auto"`` (default) when the stack
    looks JPEG-compressed. ``deblur``: take off the bias that noise on the levels puts on the fit (at knees and the
    top levels), measured on stacks simulated from the fit with the noise measured from its residuals
    (:mod:`radiometry.response.deblur`): True, False (default), or ``"auto"``: with the levels found from the data
    and a stack that does not look JPEG-compressed (JPEG's noise is not the Gaussian, pixel-independent noise the
    simulation adds). It costs two more fits. Measured at 320x240 (docs/calibration_pipelines.md): noise after the
    response, kink 1.13-1.47 % -> 0.67-0.98 %, flat-then-steep -> 0.80-1.22 %, but the EuRoC curve 0.38-0.48 % ->
    0.70-0.85 % on a clean camera and held-out predictions 1.5-2x worse (the blurred curve predicts noisy levels
    best), so it is not the default.
    """
    from radiometry.response.levels import _pile, prepare, stalled_observations

    if pixels is not None and (int(pixels) != pixels or pixels < 2):
        raise ValueError(f"pixels must be a whole number >= 2 (pixels used per channel) or None for all, "
                         f"got {pixels}")
    if isinstance(lam, bool) or not isinstance(lam, (int, float)) or not (math.isfinite(lam) and lam > 0):
        raise ValueError(f"lam must be a positive number (the prior's weight), got {lam!r}")
    if isinstance(smooth, bool) or not isinstance(smooth, (int, float)) or not (math.isfinite(smooth) and smooth >= 0):
        raise ValueError(f"smooth must be a number >= 0 (0 = no smoothness term), got {smooth!r}")
    if not isinstance(levels, str):
        levels = _check_levels(levels)
    start = time.perf_counter()
    if not (deblur == "auto" or isinstance(deblur, bool)):
        raise ValueError(f"deblur must be True, False or 'auto' (on unless the stack looks JPEG-compressed), "
                         f"got {deblur!r}")
    stack, t = _as_stack(images, times)
    _check_brightness_order(stack, t)
    n_img, h, w, n_ch = stack.shape
    valid = _check_mask(mask, (h, w))
    valid_flat = None if valid is None else valid.ravel()
    channel_levels, valid_flat, level_meta = prepare(stack, t, valid_flat, levels, edges=edges, seed=seed)
    stall_test = isinstance(levels, str)  # with levels given, exactly those
    jpeg = level_meta.get("blockiness", 0.0) > BLOCKY
    if deblur == "auto":  # the noise model is Gaussian and independent per pixel: a sensor's or an ISP's, not JPEG's
        deblur = stall_test and not jpeg
    flat = stack.reshape(n_img, h * w, n_ch)
    log_t = np.log(t)
    tables, per_channel, sq, n_obs = [], [], 0.0, 0
    for c in range(n_ch):
        rng = np.random.default_rng(seed + c)
        values = np.ascontiguousarray(flat[:, :, c])
        stalled = stalled_observations(values, t, _pile(level_meta, c)) if stall_test else None
        pix, img, z, n_pix = _observations(values, t, channel_levels[c],
                                           None if pixels is None else int(pixels), valid_flat, rng, stalled)
        sol = _solve_channel(pix, img, z, n_pix, log_t, float(lam), float(smooth))
        ceiling = _saturates_at(level_meta, c) if stall_test else None
        record = []
        for _ in range(TRIM_ROUNDS if stall_test and jpeg else 0):
            drop = outliers(_complete(sol["u"], sol["observed"], sol["counts"])[0], pix, img, z, n_pix, log_t,
                            ceiling, trim=jpeg)
            record.append(int(drop.sum()))
            if not drop.any():
                break
            pix, img, z, n_pix = _keep(pix, img, z, ~drop)
            sol = _solve_channel(pix, img, z, n_pix, log_t, float(lam), float(smooth))
        sol["outliers"] = record
        if deblur:
            sol["u"], sol["deblur"] = _deblur(sol, pix, img, z, n_pix, t, log_t, channel_levels[c],
                                              stall_test, _pile(level_meta, c),
                                              _ceiling(level_meta, c), float(lam), float(smooth), seed + c)
        table, extrapolated = _complete(sol["u"], sol["observed"], sol["counts"])
        sol["log_stderr"] = _normalised_log_stderr(sol["log_cov"], sol["u"], sol["observed"], sol["counts"], table)
        tables.append(table)
        # fit residual in 8-bit levels: observed level vs f(E_i t_j), in the units of the completed table
        pred = np.interp(np.exp(sol["ln_e"][pix] + log_t[img]) / table[-1], table / table[-1], _LEVELS_F)
        sq += float(np.sum((pred - z) ** 2))
        n_obs += int(z.size)
        sol.update(extrapolated=extrapolated, pixels=n_pix, observations=int(z.size))
        per_channel.append(sol)
    table = np.stack(tables, axis=1)
    strict = bool(np.all(np.diff(table, axis=0) > 0))
    if not strict:  # ties left by pooled levels (or a flat extrapolation): the smallest strict step
        table = repair_monotone(table, min_step=MIN_STEP)
    observed = [np.flatnonzero(s["observed"]) for s in per_channel]
    meta: dict[str, Any] = {
        "method": "loglog", "lambda": float(lam), "prior": "log-log curvature, rows weighted (1/z) (128/z)^2",
        "smooth": float(smooth), "smooth_term": f"Huber ({SMOOTH_DELTA:g}) on hat-weighted g''",
        "levels": levels if isinstance(levels, str) else list(levels), "seed": int(seed),
        "max_pixels": None if pixels is None else int(pixels),
        "images": int(n_img), "times": t.tolist(), "masked": valid is not None,
        "equal_ratios": equal_ratios(t),
        "pixels": [s["pixels"] for s in per_channel], "observations": [s["observations"] for s in per_channel],
        "observed_range": [[int(o[0]), int(o[-1])] for o in observed],
        "declared_levels": [[int(o[0]), int(o[-1])] for o in observed],
        "extrapolated_levels": [s["extrapolated"] for s in per_channel],
        "unobserved_levels": [[int(k) for k in range(1, LEVELS - 1) if not s["observed"][k]] for s in per_channel],
        "pooled_levels": [s["pooled"] for s in per_channel],
        "monotonicity": "the energy's minimum over non-decreasing g when the free minimum is not increasing",
        "repaired": False, "ties_separated": not strict,
        "fit_rms_levels": math.sqrt(sq / n_obs),
        **level_meta,
    }
    meta["outliers_dropped"] = [s["outliers"] for s in per_channel]
    meta["deblur"] = bool(deblur)
    if deblur:  # the level noise measured (median over the observed levels) and the corrections made (% of range)
        meta["level_noise"] = [round(float(np.median(s["deblur"]["noise_levels"][o[0]:o[-1] + 1])), 3)
                               for s, o in zip(per_channel, observed)]
        meta["deblur_steps_percent"] = [[round(v, 3) for v in s["deblur"]["rounds"]] for s in per_channel]
    singular = [c for c, s in enumerate(per_channel) if s["log_stderr"] is None]
    if singular:  # no standard error rather than a false 0 (the budget then uses its other terms)
        meta["inverse_stderr_source"] = (f"none: the energy's Hessian is singular in channel(s) "
                                         f"{', '.join(map(str, singular))} (a direction the brackets and the prior "
                                         f"leave undetermined)")
        log.warning("loglog response: no standard error stated (%s)", meta["inverse_stderr_source"])
    else:
        meta["inverse_stderr"] = np.stack([s["log_stderr"] for s in per_channel], axis=1).tolist()
        meta["inverse_stderr_source"] = ("loglog: sandwich covariance over pixels, carried through the extrapolation "
                                         "and the normalisation at 255 (the pixels' noise only: " + BIAS_NOT_IN + ")")
    response = CameraResponse(table / table[-1], meta)
    response.meta["fit_seconds"] = time.perf_counter() - start
    return response


__all__ = ["fit_response_loglog", "prior_rows", "DEFAULT_LAM"]
