"""What level noise (JPEG, an ISP) does to a fitted response: the observations to leave out (:func:`outliers`, used
by the default fit on JPEG stacks) and a parametric-bootstrap correction of the blur (:func:`correct`, opt-in:
``fit_response(..., deblur=True)``).

A JPEG file or an ISP adds noise to the level after the response: ``z = f(E t) + n``. The fit then maps each level
to the mean exposure of the pixels that read it, ``E[ln(E t) | z]``, which is ``g = ln f^-1`` blurred by the noise
and weighted by how many exposures fall on each side: at a knee (one level above covers four or fifty times the
irradiance of one below) the blurred curve rounds the corner by 1.5-2.6 % of the range; at the top declared levels
the pixels whose noise would take them above the cut are missing, so the levels there read too dark.

The correction measures that bias on the fit itself. Per channel:

1. the noise: the residuals of the observations about the fitted curve, in levels, per level of the fitted
   (noise-free) level, variance corrected for the pixel's own weight in its irradiance (leverage) and less the
   rounding's 1/12, smoothed over :data:`NOISE_WINDOW` levels (:func:`level_noise`);
2. a stack simulated from the fit: every fitted pixel irradiance through every exposure, the fitted curve (clipped at
   the channel's ceiling), Gaussian noise of that spread, rounding; the same level window and stall test as the data;
3. the same fit on it; its difference from the curve it was simulated from is the bias; the curve is moved against
   it, and (rounds > 1) simulated again from the moved curve until the fit of its simulation matches the fit of the
   data: ``g_(k+1) = g_k + (g_0 - fit(sim(g_k)))``.

Known limits, measured (docs/calibration_pipelines.md): the simulation's own noise adds to the fit's (about sqrt 2);
the noise estimate overstates the noise where a pixel's irradiance is itself noisy; two rounds do not converge at a
sharp knee and more rounds diverge; JPEG's error is neither Gaussian nor independent per pixel. It halves the knee
error under Gaussian noise after the response on some stacks and doubles the error of a nearly linear curve on
others, hence not the default.
"""

from __future__ import annotations

import numpy as np

#: levels over which the noise estimate is smoothed (a running mean of the variance)
NOISE_WINDOW = 9
#: simulation rounds (each one fit of a simulated stack)
ROUNDS = 2
_LEVELS_F = np.arange(256, dtype=np.float64)
_HAT = np.maximum(np.minimum(_LEVELS_F, 255.0 - _LEVELS_F), 1.0)


def _forward(table: np.ndarray, x: np.ndarray) -> np.ndarray:
    return np.interp(x, table, _LEVELS_F)


def pixel_log_irradiance(g: np.ndarray, pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int,
                         log_t: np.ndarray) -> np.ndarray:
    """Per pixel, the hat-weighted mean of ``g(z_ij) - ln t_j`` (the irradiance the fit eliminates)."""
    w = _HAT[z]
    return (np.bincount(pix, weights=w * (g[z] - log_t[img]), minlength=n_pix)
            / np.bincount(pix, weights=w, minlength=n_pix))


def level_noise(table: np.ndarray, ln_e: np.ndarray, pix: np.ndarray, img: np.ndarray, z: np.ndarray,
                log_t: np.ndarray, span: tuple[int, int] = (0, 255)) -> np.ndarray:
    """Standard deviation (levels) of the noise on an observation, per noise-free level (256,), measured on the
    observations whose noise-free level is within ``span`` (the observed levels) and held constant beyond."""
    true = _forward(table, np.exp(ln_e[pix] + log_t[img]))
    w = _HAT[z]
    sw = np.bincount(pix, weights=w)
    leverage = np.minimum(w / sw[pix], 0.9)
    r2 = (z - true) ** 2 / (1.0 - leverage)
    r2 = np.minimum(r2, 25.0 * np.median(r2) + 1.0)  # one wild pixel (an edge left in) does not set the noise
    at = np.clip(np.rint(true), 0, 255).astype(np.intp)
    inside = (at >= span[0]) & (at <= span[1])
    at, r2 = at[inside], r2[inside]
    count = np.bincount(at, minlength=256).astype(np.float64)
    total = np.bincount(at, weights=r2, minlength=256)
    kernel = np.ones(NOISE_WINDOW)
    count_s = np.convolve(count, kernel, mode="same")
    total_s = np.convolve(total, kernel, mode="same")
    var = np.where(count_s > 0, total_s / np.maximum(count_s, 1.0), np.nan)
    seen = np.flatnonzero(np.isfinite(var))
    var = np.interp(_LEVELS_F, seen.astype(np.float64), var[seen])
    return np.sqrt(np.maximum(var - 1.0 / 12.0, 0.0))


def simulate(table: np.ndarray, ln_e: np.ndarray, log_t: np.ndarray, sigma: np.ndarray, ceiling: float,
             rng: np.random.Generator, *, exact: bool = False, ceiling_noise: float = 0.0) -> np.ndarray:
    """``(N, P)`` uint8: every pixel irradiance through every exposure, the curve, noise of ``sigma`` (per
    noise-free level), rounding. ``exact``: the saturated pixels read exactly ``ceiling`` (the noise comes before
    the clip, as a sensor's); else the clip comes first and the saturated readings spread about ``ceiling`` too
    (noise after the response, JPEG)."""
    x = np.exp(ln_e[None, :] + log_t[:, None])
    true = _forward(table, x)
    beyond = x > table[-1]  # past the table: on along its last step (a sensor's noise does not pull these down)
    true[beyond] = 255.0 + (x[beyond] - table[-1]) / max(table[-1] - table[-2], 1e-12)
    spread = sigma[np.clip(np.rint(true), 0, 255).astype(np.intp)]
    if not exact:
        saturated = true >= ceiling
        true = np.where(saturated, ceiling, true)
        spread = np.where(saturated, ceiling_noise, spread)
    noisy = true + spread * rng.standard_normal(true.shape)
    if exact:
        noisy = np.minimum(noisy, ceiling)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def correct(u: np.ndarray, observed: np.ndarray, counts: np.ndarray, pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int,
            log_t: np.ndarray, ceiling: float, refit, complete, rng: np.random.Generator,
            rounds: int = ROUNDS, exact: bool = False,
            ceiling_noise: float = 0.0) -> tuple[np.ndarray, dict]:
    """The fitted ``u`` (``f^-1`` at the observed levels, unnormalised; 0 elsewhere) moved against the bias its fit
    shows on stacks simulated from it. ``refit(values (N, P) uint8) -> table (256,)``: the same fit (level window,
    stall test, completion) on a simulated channel; ``complete(u, observed, counts) -> table (256,)``. Returns the corrected ``u`` and
    a record (noise per level, the largest correction per round in % of the range)."""
    lv = np.flatnonzero(observed)
    g0 = np.log(u[lv])
    g = g0.copy()
    record: dict = {"rounds": [], "noise_levels": None}
    for _ in range(int(rounds)):
        cur = np.zeros_like(u)
        cur[lv] = np.exp(g)
        table = complete(cur, observed, counts)
        full_g = np.log(np.maximum(table, 1e-300))
        ln_e = pixel_log_irradiance(full_g, pix, img, z, n_pix, log_t)
        sigma = level_noise(table, ln_e, pix, img, z, log_t, (int(lv[0]), int(lv[-1])))
        if record["noise_levels"] is None:
            record["noise_levels"] = sigma
        sim_table = refit(simulate(table, ln_e, log_t, sigma, ceiling, rng, exact=exact,
                                       ceiling_noise=ceiling_noise))
        step = g0 - np.log(sim_table[lv])
        step -= step[-1]  # the gauge: 0 at the top observed level, like the fit
        g = g + step
        record["rounds"].append(float(100 * np.max(np.abs(np.exp(g0) - np.exp(g0 - step)))))
    out = np.zeros_like(u)
    out[lv] = np.exp(g)
    return out, record


def leave_one_out_levels(table: np.ndarray, pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int,
                         log_t: np.ndarray) -> np.ndarray:
    """Per observation, the level the curve ``table`` predicts from the pixel's other observations (its irradiance
    as the hat-weighted mean of ``g(z) - ln t`` over them); NaN for a pixel's only observation."""
    g = np.log(np.maximum(table, 1e-300))
    w = _HAT[z]
    term = w * (g[z] - log_t[img])
    total = np.bincount(pix, weights=term, minlength=n_pix)
    weight = np.bincount(pix, weights=w, minlength=n_pix)
    rest = weight[pix] - w
    with np.errstate(invalid="ignore", divide="ignore"):
        ln_e = np.where(rest > 0, (total[pix] - term) / np.where(rest > 0, rest, 1.0), np.nan)
    return _forward(table, np.exp(ln_e + log_t[img]))


def outliers(table: np.ndarray, pix: np.ndarray, img: np.ndarray, z: np.ndarray, n_pix: int, log_t: np.ndarray,
             ceiling: float | None, *, trim: bool = True) -> np.ndarray:
    """Boolean per observation: the ones to leave out of the next fit. An observation is an outlier when the level
    its pixel's other observations predict (:func:`leave_one_out_levels`) is at or above the channel's ``ceiling``
    (a saturated pixel that JPEG or the ISP reads below the ceiling, which the stall test misses when the next
    exposure reads higher), or when it is more than :data:`TRIM` robust standard deviations from that level
    (a pixel mixed with a saturated or edge neighbour by JPEG's blocks and chroma subsampling; ``trim``). The fit
    (:mod:`radiometry.response.loglog`) uses it on JPEG stacks only: without JPEG the wild ones are the observations
    next to a knee, which the leave-one-out curve misses (flat-then-steep, clean camera: 0.81 % -> 1.10 % with them
    left out), and the censored ones the top levels' own."""
    pred = leave_one_out_levels(table, pix, img, z, n_pix, log_t)
    known = np.isfinite(pred)
    res = np.where(known, z - pred, 0.0)
    spread = 1.4826 * float(np.median(np.abs(res[known]))) if known.any() else 0.0
    out = known & (np.abs(res) > TRIM * max(spread, MIN_SPREAD)) if trim else np.zeros(z.size, bool)
    if ceiling is not None:
        out |= known & (pred >= ceiling)
    return out


#: the outlier threshold (robust standard deviations of the leave-one-out residual) and the least spread it uses
TRIM = 5.0
MIN_SPREAD = 1.0
