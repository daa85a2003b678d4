"""Response calibration for brackets at one exposure ratio: Debevec's data term over all pixels with a log-log
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
  observed level ``z`` (:func:`radiometry.response_engel.loglog_curvature_rows`, ``1/z`` weighted) and the extra
  weight ``rho(z) = (128 / z)^2``: a knee at a bright level costs little, a periodic wiggle repeated in the dark
  octaves (where an octave spans few levels) costs a lot;
- gauge ``g = 0`` at the top observed level; solved directly (one Cholesky-sized solve, about 1 s a channel at
  640x480).

Measured (``scripts/bench_calibration.py``, 640x480, 12 exposures, photon and read noise, max |f^-1 - truth| over
levels 5..250, % of the range, worst channel): exact 2x 0.38 / 0.33 / 0.62 / 0.78 / 0.78 (gamma 2.2, S-curve,
kink 4x, flat-then-steep, EuRoC), varied ratios 0.39 / 0.34 / 0.37 / 0.66 / 0.61; Debevec (lambda 10) 0.42 / 0.72
/ 0.98 / 1.59 / 0.92 on 2x. ``lam`` 0.1 and the ``(128/z)^2`` weight were chosen on those stacks; another scene and
noise seed and 320x240 stay within 0.82 % (2x) and 0.71 % (varied).

Levels without observations, monotonicity and normalisation as :mod:`radiometry.response_engel`: unobserved levels
inside the observed span are interpolated, outside it extrapolated (``meta["extrapolated_levels"]``); a solution
that is not increasing is made so by weighted pool-adjacent-violators on ``f^-1`` (``meta["pooled_levels"]``,
``meta["repaired"]``); ``f^-1(255) = 1``.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError
from radiometry.response import LEVELS, CameraResponse, repair_monotone
from radiometry.response_engel import (DEFAULT_PIXELS, MIN_STEP, _complete, _observations, equal_ratios,
                                       isotonic_increasing, loglog_curvature_rows)
from radiometry.response_fit import _as_stack, _check_brightness_order, _check_levels, _check_mask

log = logging.getLogger(__name__)

DEFAULT_LAM = 0.1
#: the prior's extra weight is (REFERENCE_LEVEL / z)^DARK_POWER on top of the rows' own 1/z
REFERENCE_LEVEL = 128.0
DARK_POWER = 2.0
_LEVELS_F = np.arange(LEVELS, dtype=np.float64)
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


def _solve_channel(pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int, log_t: np.ndarray,
                   lam: float) -> dict[str, Any]:
    counts = np.bincount(z, minlength=LEVELS).astype(np.float64)
    observed = counts > 0
    lv = np.flatnonzero(observed)
    m, b = _normal_equations(pix, img, z, n_pix, log_t)
    m_obs, b_obs = m[np.ix_(lv, lv)], b[lv]
    if lv.size > 2:
        rows = prior_rows(lv)
        m_obs = m_obs + lam * (rows.T @ rows)
    g = np.zeros(lv.size)
    try:  # gauge: g = 0 at the top observed level
        g[:-1] = np.linalg.solve(m_obs[:-1, :-1], b_obs[:-1])
    except np.linalg.LinAlgError:
        raise CalibrationError("the observed levels are not linked by pixels seen in two exposures and the prior "
                               "cannot bridge them; use exposures that overlap (e.g. one stop apart)") from None
    u = np.zeros(LEVELS)
    u[lv] = np.exp(g)
    pooled: list[list[int]] = []
    if not np.all(np.diff(u[lv]) > 0):
        fitted, blocks = isotonic_increasing(u[lv], counts[lv])
        u[lv] = fitted
        pooled = [[int(lv[k]) for k in block] for block in blocks]
    ln_e_num = np.bincount(pix, weights=_HAT[z] * (np.log(u[z]) - log_t[img]), minlength=n_pix)
    ln_e = ln_e_num / np.bincount(pix, weights=_HAT[z], minlength=n_pix)
    return {"u": u, "observed": observed, "counts": counts, "pooled": pooled, "ln_e": ln_e}


def fit_response_loglog(images: Sequence[np.ndarray], times: Sequence[float], *, lam: float = DEFAULT_LAM,
                        pixels: int | None = DEFAULT_PIXELS, mask: np.ndarray | None = None,
                        levels: tuple[int, int] = (1, 254), seed: int = 0) -> CameraResponse:
    """Debevec's data term over all pixels with the log-log curvature prior (see the module docstring).

    ``lam``: the prior's weight (per unit of data weight; default 0.1). ``pixels``: at most this many pixels per
    channel (seeded random subset; None = all). ``mask``: boolean ``(H, W)``, True = usable. ``levels``: the valid
    intensity range (inclusive); observations outside it are ignored.
    """
    if pixels is not None and (int(pixels) != pixels or pixels < 2):
        raise ValueError(f"pixels must be a whole number >= 2 (pixels used per channel) or None for all, "
                         f"got {pixels}")
    if isinstance(lam, bool) or not isinstance(lam, (int, float)) or not (math.isfinite(lam) and lam > 0):
        raise ValueError(f"lam must be a positive number (the prior's weight), got {lam!r}")
    lo, hi = _check_levels(levels)
    start = time.perf_counter()
    stack, t = _as_stack(images, times)
    _check_brightness_order(stack, t)
    n_img, h, w, n_ch = stack.shape
    valid = _check_mask(mask, (h, w))
    valid_flat = None if valid is None else valid.ravel()
    flat = stack.reshape(n_img, h * w, n_ch)
    log_t = np.log(t)
    tables, per_channel, sq, n_obs = [], [], 0.0, 0
    for c in range(n_ch):
        rng = np.random.default_rng(seed + c)
        pix, img, z, n_pix = _observations(np.ascontiguousarray(flat[:, :, c]), t, (lo, hi),
                                           None if pixels is None else int(pixels), valid_flat, rng)
        sol = _solve_channel(pix, img, z, n_pix, log_t, float(lam))
        table, extrapolated = _complete(sol["u"], sol["observed"], sol["counts"])
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
        "levels": [lo, hi], "seed": int(seed), "max_pixels": None if pixels is None else int(pixels),
        "images": int(n_img), "times": t.tolist(), "masked": valid is not None,
        "equal_ratios": equal_ratios(t),
        "pixels": [s["pixels"] for s in per_channel], "observations": [s["observations"] for s in per_channel],
        "observed_range": [[int(o[0]), int(o[-1])] for o in observed],
        "extrapolated_levels": [s["extrapolated"] for s in per_channel],
        "unobserved_levels": [[int(k) for k in range(1, LEVELS - 1) if not s["observed"][k]] for s in per_channel],
        "pooled_levels": [s["pooled"] for s in per_channel],
        "repaired": any(s["pooled"] for s in per_channel),
        "repaired_levels": [[k for block in s["pooled"] for k in block] for s in per_channel],
        "ties_separated": not strict,
        "fit_rms_levels": math.sqrt(sq / n_obs),
    }
    if meta["repaired"]:
        log.warning("the fitted response is not increasing at %d level(s); made so by pool-adjacent-violators",
                    sum(len(b) for s in per_channel for b in s["pooled"]))
    response = CameraResponse(table / table[-1], meta)
    response.meta["fit_seconds"] = time.perf_counter() - start
    return response


__all__ = ["fit_response_loglog", "prior_rows", "DEFAULT_LAM"]
