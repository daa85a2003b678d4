"""Debevec & Malik's sparse solve of one channel (:func:`_solve_debevec_channel`), its samples
(:func:`select_samples`), hat weights and the model it builds (:func:`_finish`).

Below :mod:`~radiometry.response.fit` (``fit_response_debevec``), :mod:`~radiometry.response.smoothness` (the
cross-validation of the smoothness weight, which re-solves channels) and :mod:`~radiometry.response.opencv`, so
that they share it without importing each other.
"""

from __future__ import annotations

import logging
import math
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError, TooFewLevelsError
from radiometry.response.model import LEVELS, CameraResponse

log = logging.getLogger(__name__)

DEFAULT_LAMBDA = 10.0
DEFAULT_SAMPLES = 50
GAUGE_LEVEL = 128

_LEVELS = np.arange(LEVELS)
#: Debevec's hat weight ``w(z) = min(z, 255 - z)``: 0 at the empty (0) and saturated (255) levels.
HAT_WEIGHTS = np.minimum(_LEVELS, 255 - _LEVELS).astype(np.float64)


def select_samples(values: np.ndarray, times: np.ndarray, *, samples: int = DEFAULT_SAMPLES,
                   valid: np.ndarray | None = None, levels: tuple[int, int] = (1, 254),
                   seed: int = 0) -> np.ndarray:
    """Pixel indices stratified over intensity, as radical samples (one channel).

    ``values`` is ``(P, N)`` uint8 (P exposures, N pixels); ``valid`` an optional ``(N,)`` boolean mask.
    From the top of ``levels`` (valid range, inclusive) down, pixels of each level in the longest
    exposure are taken in random (spatially spread) order until the level has ``samples`` valid
    observations, counted over all exposures of the pixels taken so far (radical's rule). Levels still
    short of observations are then filled the same way from the next longest exposure (among the pixels
    not taken yet), and so on: this reaches the pixels saturated in the longest exposure and the levels
    that only the shorter ones show.
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1 observation per level, got {samples}")
    values = np.asarray(values)
    n_img, n_pix = values.shape
    rng = np.random.default_rng(seed)
    lo, hi = levels
    usable = (values >= lo) & (values <= hi)
    free = np.ones(n_pix, bool) if valid is None else np.asarray(valid, bool).copy()
    hist = np.zeros(LEVELS, dtype=np.int64)
    chosen: list[np.ndarray] = []
    for j in np.argsort(-np.asarray(times), kind="stable"):
        if np.all(hist[lo:hi + 1] >= samples):
            break
        short = np.zeros(LEVELS, bool)
        short[lo:hi + 1] = hist[lo:hi + 1] < samples
        pool = np.flatnonzero(free & short[values[j]])  # pixels of the levels still short, not taken yet
        if pool.size == 0:
            continue
        pool = pool[rng.permutation(pool.size)]
        pool_levels = values[j, pool]
        by_level = np.argsort(pool_levels, kind="stable")
        bounds = np.searchsorted(pool_levels[by_level], np.arange(LEVELS + 1))
        for z in range(hi, lo - 1, -1):
            need = samples - hist[z]
            if need <= 0:
                continue
            # every candidate adds at least its own observation of z: `need` of them always suffice
            cand = pool[by_level[bounds[z]:min(bounds[z + 1], bounds[z] + need)]]
            if cand.size == 0:
                continue
            gain = (values[:, cand] == z).sum(axis=0)
            picked = cand[:int(np.searchsorted(np.cumsum(gain), need)) + 1]
            chosen.append(picked)
            free[picked] = False
            hist += np.bincount(values[:, picked][usable[:, picked]], minlength=LEVELS)
    if not chosen:
        return np.empty(0, dtype=np.intp)
    return np.sort(np.concatenate(chosen))


def _solve_debevec_channel(values: np.ndarray, log_t: np.ndarray, lam: float,
                           levels: tuple[int, int] = (1, 254), *, stderr: bool = False,
                           stalled: np.ndarray | None = None) -> dict[str, Any]:
    """Solve one channel. ``values`` is ``(P, S)`` uint8 of the sampled pixels.

    Returns ``g`` (256,), ``ln_e`` (S,) and the observations used (image, pixel, level index arrays);
    ``stderr=True`` adds ``log_stderr`` (:func:`_log_stderr`).
    The unknowns are ordered ``ln E`` first, then ``g`` (without the gauge level), so that factorising the
    sparse normal equations in natural order eliminates the diagonal ``ln E`` block first: the only fill-in
    is the 255 x 255 block of ``g`` and the cost grows linearly with the number of samples.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import splu

    n_img, n_pix = values.shape
    inside = (values >= levels[0]) & (values <= levels[1])
    if stalled is not None:  # saturated pixels below the level cut (radiometry.response.levels)
        inside &= ~stalled
    w_obs = np.where(inside, HAT_WEIGHTS[values], 0.0)
    seen = (w_obs > 0).any(axis=0)
    if not seen.all():  # pixels left with no usable observation carry no information (and no row for their ln E)
        values, w_obs = values[:, seen], w_obs[:, seen]
        n_pix = values.shape[1]
    img_idx, pix_idx = np.nonzero(w_obs > 0)
    z = values[img_idx, pix_idx].astype(np.intp)
    w = w_obs[img_idx, pix_idx]
    n_obs = z.size
    if n_obs == 0:
        raise CalibrationError("no usable observations (every sampled pixel is outside the valid levels); "
                               "check the exposures, the mask and the levels")
    per_pixel = np.bincount(pix_idx, minlength=n_pix)
    multi = per_pixel[pix_idx] >= 2
    if not multi.any() or np.unique(log_t[img_idx[multi]]).size < 2:
        raise TooFewLevelsError("no pixel is unsaturated in two different exposures, so the response is not "
                                "observable", "add exposures that overlap (e.g. one stop apart)")

    gcol = n_pix + np.where(_LEVELS < GAUGE_LEVEL, _LEVELS, _LEVELS - 1)
    gcol[GAUGE_LEVEL] = -1
    n_cols = n_pix + LEVELS - 1
    # data rows w (g(z) - ln E_i) = w ln t_j (the weights are applied in the normal equations)
    keep = z != GAUGE_LEVEL
    r = np.arange(n_obs)
    data = sp.csr_matrix((np.concatenate([-np.ones(n_obs), np.ones(int(keep.sum()))]),
                          (np.concatenate([r, r[keep]]), np.concatenate([pix_idx, gcol[z[keep]]]))),
                         shape=(n_obs, n_cols))
    # smoothness rows: lam' w(k) (g(k-1) - 2 g(k) + g(k+1)) = 0, k = 1..254, lam' = lam sqrt(obs per level)
    k = np.arange(1, LEVELS - 1)
    sw = lam * math.sqrt(n_obs / (LEVELS - 2)) * HAT_WEIGHTS[k]
    rows, cols, vals = [], [], []
    for offset, coef in ((-1, 1.0), (0, -2.0), (1, 1.0)):
        lev = k + offset
        m = lev != GAUGE_LEVEL
        rows.append(np.arange(k.size)[m])
        cols.append(gcol[lev[m]])
        vals.append(coef * sw[m])
    smooth = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                           shape=(k.size, n_cols))
    dw = sp.diags(w * w) @ data
    ata = ((data.T @ dw) + (smooth.T @ smooth)).tocsc()
    atb = dw.T @ log_t[img_idx]
    try:
        lu = splu(ata, permc_spec="NATURAL", diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        x = lu.solve(atb)
    except RuntimeError as exc:  # "Factor is exactly singular"
        raise CalibrationError(f"the least-squares system is singular ({exc}); add overlapping exposures "
                               "or more samples") from None
    if not np.all(np.isfinite(x)):
        raise CalibrationError("the least-squares solve gave non-finite values; add overlapping exposures "
                               "or more samples")
    g = np.insert(x[n_pix:], GAUGE_LEVEL, 0.0)
    out = {"g": g, "ln_e": x[:n_pix], "img": img_idx, "pix": pix_idx, "z": z}
    if stderr:
        out["log_stderr"] = _log_stderr(lu, n_pix, g[z] - x[pix_idx] - log_t[img_idx], w, pix_idx, z, n_obs - n_cols)
    return out


def _log_stderr(lu, n_pix: int, residual: np.ndarray, w: np.ndarray, pix: np.ndarray, z: np.ndarray,
                dof: int) -> np.ndarray:
    """Standard error of ``g(z) - g(255)`` (= of ``ln f^-1(z)`` normalised to 1 at 255) per level, (256,).

    The sandwich covariance of the solve, ``M^-1 A^T W^2 diag(s^2) W^2 A M^-1`` with ``M`` the factorised normal
    equations (``lu``; the smoothness rows are a fixed part of the estimator, not random) and ``s^2`` the data
    rows' residual variance at each level (levels differ: quantisation in ``ln`` grows towards the dark end),
    inflated by ``observations / dof``; the normalisation at level 255 is propagated with its covariance. It
    measures the noise of the sampled pixels, not the prior's bias (a rounded knee) nor the factor periodic in
    ``ln E`` that equal exposure ratios leave undetermined.
    """
    import scipy.sparse as sp

    n_g = LEVELS - 1
    unit = np.zeros((n_pix + n_g, n_g))
    unit[n_pix + np.arange(n_g), np.arange(n_g)] = 1.0
    inv = np.asarray(lu.solve(unit)).T  # rows of M^-1 for the g unknowns (M symmetric), (255, n_cols)
    g_of_level = np.insert(inv[:, n_pix:], GAUGE_LEVEL, 0.0, axis=1)  # d g / d (A^T b) at each level's column
    per_pixel = inv[:, :n_pix]
    count = np.maximum(np.bincount(z, minlength=LEVELS), 1)
    var_level = np.bincount(z, weights=residual ** 2, minlength=LEVELS) / count * (residual.size / max(dof, 1))
    c = w ** 4 * var_level[z]  # a data row's weight w^2, squared, times its noise variance
    # sum over rows of c (G_z - G_pix)(G_z - G_pix)^T, grouped by level, by pixel and by (level, pixel)
    by_level = (g_of_level * np.bincount(z, weights=c, minlength=LEVELS)) @ g_of_level.T
    by_pixel = (per_pixel * np.bincount(pix, weights=c, minlength=n_pix)) @ per_pixel.T
    pairs = sp.csr_matrix((c, (z, pix)), shape=(LEVELS, n_pix))
    cross = g_of_level @ np.asarray(pairs @ per_pixel.T)
    cov = by_level + by_pixel - cross - cross.T
    cov = np.insert(np.insert(cov, GAUGE_LEVEL, 0.0, axis=0), GAUGE_LEVEL, 0.0, axis=1)  # g(128) = 0 exactly
    var = np.diag(cov) + cov[-1, -1] - 2.0 * cov[:, -1]
    return np.sqrt(np.maximum(var, 0.0))


def _finish(g: np.ndarray, meta: dict[str, Any]) -> CameraResponse:
    """Build the model from ``g = ln f^-1``; repair monotonicity only if needed and record it."""
    g = np.asarray(g, dtype=np.float64)
    bad = [np.flatnonzero(np.diff(g[:, c]) <= 0).tolist() for c in range(g.shape[1])]
    repaired = any(bad)
    meta = dict(meta, repaired=repaired)
    if repaired:
        meta["repaired_levels"] = [[int(i) + 1 for i in b] for b in bad]
        log.warning("the fitted response is not strictly increasing at %d level(s); repaired (running maximum)",
                    sum(len(b) for b in bad))
    return CameraResponse.from_log_table(g, repair=repaired, **meta)
