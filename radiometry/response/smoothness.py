"""Debevec's smoothness weight chosen from the data: cross-validation on held-out pixels.

For each candidate ``lambda`` in :data:`LAMBDA_GRID` and each of ``folds`` random splits of the sampled
pixels, the response is fitted on the other folds' pixels (:func:`radiometry.response.fit._solve_debevec_channel`)
and scored on the held-out ones: each held-out pixel's irradiance is merged from its own observations (hat
weights, as :func:`radiometry.response.fit.merge_radiance` does) and every observation is predicted back as
``f(E t_j)``; the score is the mean squared prediction error in 8-bit levels over all channels. The lambda with
the lowest score wins (ties: the larger lambda, the smoother curve).

What it can and cannot see: a smoothness prior that rounds a knee predicts the held-out levels near the knee
badly, so a kinked response gets a smaller lambda. A change of ``f^-1`` by a factor periodic in ``ln E`` with
the period of the exposure ratio (exactly 2x brackets) predicts every image equally well: no criterion on
the images can see it, and only the prior suppresses it.
"""

from __future__ import annotations

import numpy as np

from radiometry.response.debevec import HAT_WEIGHTS, _solve_debevec_channel
from radiometry.response.model import LEVELS

LAMBDA_GRID = (0.3, 1.0, 3.0, 10.0, 30.0, 100.0)
DEFAULT_FOLDS = 3
_LEVELS_F = np.arange(LEVELS, dtype=np.float64)


def held_out_error(g: np.ndarray, values: np.ndarray, log_t: np.ndarray, levels: tuple[int, int]) -> tuple[float, int]:
    """Sum of squared level errors and observation count of predicting ``values`` (``(P, S)`` uint8 of held-out
    pixels) through ``g = ln f^-1`` (256,)."""

    lo, hi = levels
    usable = (values >= lo) & (values <= hi)
    w = np.where(usable, HAT_WEIGHTS[values], 0.0)
    den = w.sum(axis=0)
    ok = den > 0
    ln_e = (w * (g[values] - log_t[:, None])).sum(axis=0)[ok] / den[ok]
    table = np.exp(g - g[-1])
    x = np.exp(ln_e[None, :] + log_t[:, None] - g[-1])
    pred = np.interp(x, table, _LEVELS_F)
    err = (pred - values[:, ok])[usable[:, ok]]
    return float(np.sum(err ** 2)), int(err.size)


def cross_validate_lambda(channels: list[np.ndarray], log_t: np.ndarray, levels: tuple[int, int], *,
                          grid: tuple[float, ...] = LAMBDA_GRID, folds: int = DEFAULT_FOLDS,
                          seed: int = 0) -> tuple[float, dict[str, float]]:
    """Pick lambda for :func:`radiometry.response.fit.fit_response_debevec`.

    ``channels``: per channel, the ``(P, S)`` uint8 values of the sampled pixels. Returns the chosen lambda and
    the score (mean squared held-out error, levels^2) of every candidate.
    """
    from radiometry.errors import CalibrationError

    rng = np.random.default_rng(seed)
    splits = [rng.integers(0, folds, values.shape[1]) for values in channels]
    scores: dict[str, float] = {}
    for lam in grid:
        sq, n = 0.0, 0
        for values, fold in zip(channels, splits):
            for k in range(folds):
                train, test = values[:, fold != k], values[:, fold == k]
                if train.shape[1] == 0 or test.shape[1] == 0:
                    continue
                try:
                    g = _solve_debevec_channel(train, log_t, float(lam), levels)["g"]
                except CalibrationError:  # a fold without overlapping exposures: it cannot score
                    continue
                s, m = held_out_error(g, test, log_t, levels)
                sq, n = sq + s, n + m
        scores[f"{lam:g}"] = sq / n if n else float("inf")
    best = min(grid, key=lambda lam: (scores[f"{lam:g}"], -lam))
    if not np.isfinite(scores[f"{best:g}"]):
        raise CalibrationError("cross-validation could not score any lambda (too few sampled pixels); "
                               "pass a number as lam")
    return float(best), scores


__all__ = ["LAMBDA_GRID", "cross_validate_lambda", "held_out_error"]
