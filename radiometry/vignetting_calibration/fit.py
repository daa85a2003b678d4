"""Fits of a vignetting model to an accumulation, one function per method (:func:`fit_vignetting_lut`,
:func:`fit_vignetting_polynomial` with the centre fixed or free), and :func:`fit_vignetting`, which picks one
by name from :data:`MODELS`."""

from __future__ import annotations

from typing import Any

import numpy as np

from radiometry.errors import AdvisedCalibrationError, CalibrationError
from radiometry.registry import Registry
from radiometry.vignetting import LUTVignetting, PolynomialVignetting, VignettingModel, half_diagonal
from radiometry.vignetting_calibration.accumulate import VignettingAccumulation
from radiometry.vignetting_calibration.collect import SWEEP_FIX
from radiometry.vignetting_calibration.uncertainty import error_budget, lut_stderr, relative_sample_variance

#: the largest LUT denoising (pixels): beyond it the "fine" residual is a constant and OpenCV's kernel overflows
MAX_SMOOTH_SIGMA = 50.0
#: a model is fitted only when the sheet was seen at this fraction of the image at least (simulated sweeps of
#: 30-40 frames: 100 %; ordinary room frames where a plain wall passed for a sheet: 15 %)
MIN_OBSERVED_FRACTION = 0.5
#: the LUT's normaliser is fitted over a disk of this fraction of the image diagonal around V's peak
CENTRE_RADIUS = 0.08


def observed_flat(acc: VignettingAccumulation, joint_scale: bool,
                  min_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """The session's flat (:meth:`VignettingAccumulation.flat`) where a pixel has at least ``min_samples``
    samples, NaN elsewhere, and the sample counts as weights (0 elsewhere), both float64 ``(H, W, C)``."""
    flat = acc.flat(joint_scale=joint_scale)
    weights = np.where(acc.count >= min_samples, acc.count, 0).astype(np.float64)
    flat = np.where(weights > 0, flat, np.nan)
    return flat, weights


def centre_normalisers(smooth: np.ndarray, flat: np.ndarray, weights: np.ndarray, *,
                       radius_fraction: float = CENTRE_RADIUS) -> tuple[np.ndarray, dict[str, Any]]:
    """The value of ``V``'s unnormalised estimate at its centre, per channel, without the upward bias of a maximum.

    The centre is the maximum of ``smooth`` (the estimate smoothed at a coarse scale). Around it, in a disk of
    ``radius_fraction`` of the image diagonal, a quadratic surface ``a + b x + c y + d x^2 + e xy + f y^2`` is
    fitted to the session's flat ``flat`` by least squares weighted by the sample counts ``weights``, and its
    largest value in the disk is the normaliser: thousands of pixels average the noise out, where the maximum of
    a noisy field sits a few of its standard deviations above the truth. Returns ``(C,)`` normalisers and what
    the fit saw (``centre`` (x, y) per channel, ``pixels``, ``stderr``: the relative standard error of each
    normaliser, the uniform part of the LUT's error).
    """
    h, w, ch = flat.shape
    radius = max(3.0, radius_fraction * float(np.hypot(h, w)))
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    norms, centres, pixels, stderrs = [], [], [], []
    for c in range(ch):
        sm = np.where(np.isfinite(smooth[:, :, c]), smooth[:, :, c], -np.inf)
        py, px = np.unravel_index(int(np.argmax(sm)), sm.shape)
        disk = ((xx - px) ** 2 + (yy - py) ** 2 <= radius ** 2)
        sel = disk & (weights[:, :, c] > 0) & np.isfinite(flat[:, :, c])
        if np.count_nonzero(sel) < 30:  # too few observed pixels near the peak: the smooth estimate's peak
            norms.append(float(sm[py, px]))
            centres.append([float(px), float(py)])
            pixels.append(int(np.count_nonzero(sel)))
            stderrs.append(float("nan"))
            continue
        u, v = (xx[sel] - px) / radius, (yy[sel] - py) / radius
        design = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], axis=1)
        wt = weights[:, :, c][sel]
        d = flat[:, :, c][sel]
        sw = np.sqrt(wt)
        coef, *_ = np.linalg.lstsq(design * sw[:, None], d * sw, rcond=None)
        fitted = design @ coef
        k = int(np.argmax(fitted))
        norm = float(fitted[k])
        # standard error of the fitted value there: residual variance per unit weight times x^T (A^T W A)^-1 x
        dof = max(1, d.size - design.shape[1])
        sigma2 = float(np.sum(wt * (d - fitted) ** 2) / dof)
        cov = sigma2 * np.linalg.pinv((design * wt[:, None]).T @ design)
        se = float(np.sqrt(max(0.0, design[k] @ cov @ design[k]))) / norm if norm > 0 else float("nan")
        if not norm > 0:
            norm = float(sm[py, px])
        norms.append(norm)
        centres.append([float(xx[sel][k]), float(yy[sel][k])])
        pixels.append(int(d.size))
        stderrs.append(se)
    info = {"method": "centre-quadratic", "radius_px": round(radius, 2), "centre": centres, "pixels": pixels,
            "stderr": stderrs}
    return np.array(norms), info


def _poly_design(r2: np.ndarray) -> np.ndarray:
    return np.stack([np.ones_like(r2), r2, r2 ** 2, r2 ** 3], axis=1)


def _fit_channel_poly(xs: np.ndarray, ys: np.ndarray, d: np.ndarray, w: np.ndarray, resolution: tuple[int, int],
                      free: bool) -> tuple[float, np.ndarray, np.ndarray, float]:
    """Fit ``d = s (1 + b1 r^2 + b2 r^4 + b3 r^6)`` to samples; returns ``s, b, centre, rms``."""
    from scipy.optimize import least_squares

    width, height = resolution
    radius = half_diagonal(resolution)
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    sw = np.sqrt(w)
    r2 = ((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / radius ** 2
    design = _poly_design(r2) * sw[:, None]
    coef, *_ = np.linalg.lstsq(design, d * sw, rcond=None)
    s = float(coef[0])
    if not s > 0:
        raise CalibrationError("the fitted vignetting is not positive at the image centre; the data do not look "
                               "like a flat field (check the response and the frames)")
    b = coef[1:] / s
    if free:
        # parameters: centre in units of R (well scaled), overall scale, b1..b3
        def residual(p):
            cx, cy, s_, b1, b2, b3 = p
            rr = ((xs - cx * radius) ** 2 + (ys - cy * radius) ** 2) / radius ** 2
            return sw * (d - s_ * (1.0 + rr * (b1 + rr * (b2 + rr * b3))))

        def jacobian(p):
            cx, cy, s_, b1, b2, b3 = p
            dx, dy = xs - cx * radius, ys - cy * radius
            rr = (dx * dx + dy * dy) / radius ** 2
            dp = b1 + rr * (2.0 * b2 + 3.0 * rr * b3)  # dP/d(rr)
            jac = np.empty((xs.size, 6))
            jac[:, 0] = sw * s_ * dp * (2.0 * dx / radius)
            jac[:, 1] = sw * s_ * dp * (2.0 * dy / radius)
            jac[:, 2] = -sw * (1.0 + rr * (b1 + rr * (b2 + rr * b3)))
            jac[:, 3] = -sw * s_ * rr
            jac[:, 4] = -sw * s_ * rr ** 2
            jac[:, 5] = -sw * s_ * rr ** 3
            return jac

        p0 = np.array([centre[0] / radius, centre[1] / radius, s, *b])
        sol = least_squares(residual, p0, jac=jacobian, method="lm", x_scale="jac", xtol=1e-12, ftol=1e-12,
                            max_nfev=2000)
        cx, cy, s, b1, b2, b3 = sol.x
        centre = np.array([cx * radius, cy * radius])
        b = np.array([b1, b2, b3])
        if not (-0.5 <= centre[0] <= width - 0.5 and -0.5 <= centre[1] <= height - 0.5) or not s > 0:
            raise CalibrationError(
                f"the free-centre fit put the optical centre at ({centre[0]:.1f}, {centre[1]:.1f}), outside the "
                f"{width}x{height} image: the data do not constrain it; cover the image more evenly or use "
                "--model poly-fixed-center")
        r2 = ((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2) / radius ** 2
    pred = s * (1.0 + r2 * (b[0] + r2 * (b[1] + r2 * b[2])))
    rms = float(np.sqrt(np.sum(w * (d - pred) ** 2) / np.sum(w)) / s)
    return float(s), np.asarray(b, dtype=np.float64), centre, rms


def fit_vignetting_polynomial(accumulation: VignettingAccumulation, *, fixed_centre: bool = False,
                              joint_scale: bool = True, min_samples: int = 1,
                              max_points: int = 200_000) -> PolynomialVignetting:
    """Polynomial model per channel, ``V = s_c (1 + b1 r^2 + b2 r^4 + b3 r^6)``, stored normalised (``V = 1``
    at its centre; ``s_c`` kept in ``info["fit_scale"]``).

    ``fixed_centre=True``: centre at the image centre, linear least squares weighted by the sample counts.
    ``fixed_centre=False``: centre free, Levenberg-Marquardt (``scipy.optimize.least_squares(method="lm")``)
    initialised from the fixed-centre fit. At most ``max_points`` pixels (a regular subsample) are used.
    """
    acc = accumulation
    flat, weights = observed_flat(acc, joint_scale, min_samples)
    h, w, ch = acc.shape
    step = max(1, int(np.ceil(np.sqrt(h * w / max_points))))
    yy, xx = np.mgrid[0:h:step, 0:w:step]
    coeffs, centres, scales, rms = [], [], [], []
    for c in range(ch):
        d = flat[::step, ::step, c]
        wt = weights[::step, ::step, c]
        sel = (wt > 0) & np.isfinite(d)
        if np.count_nonzero(sel) < 50:
            raise AdvisedCalibrationError(f"channel {c}: only {np.count_nonzero(sel)} observed pixels",
                                          "record a longer sweep")
        s, b, centre, err = _fit_channel_poly(xx[sel].astype(np.float64), yy[sel].astype(np.float64), d[sel],
                                              wt[sel], acc.resolution, free=not fixed_centre)
        coeffs.append(b)
        centres.append(centre)
        scales.append(s)
        rms.append(err)
    info = {"method": "poly-fixed-center" if fixed_centre else "poly", "joint_scale": bool(joint_scale),
            "fit_scale": scales, "fit_rms_relative": rms, "frames_used": acc.frames_used,
            "frames_skipped": acc.skipped, "source": acc.source}
    try:
        return PolynomialVignetting(np.array(coeffs), np.array(centres), acc.resolution, info=info)
    except ValueError as exc:
        raise CalibrationError(f"the fitted polynomial is not a valid vignetting ({exc}); the corners are probably "
                               "not covered: sweep the sheet into the corners, or use --model lut") from None


#: the band of observed pixels held out to measure how the radial fit extrapolates (a share of the image diagonal)
EXTRAPOLATION_BAND = 0.1


def extrapolation_slope(flat: np.ndarray, weights: np.ndarray, resolution: tuple[int, int], *, free: bool,
                        band: float = EXTRAPOLATION_BAND, max_points: int = 200_000) -> np.ndarray:
    """Per channel, how fast the radial fit's error grows away from the data it was fitted on (relative error of
    ``V`` per pixel of distance; 0 for a channel observed everywhere, NaN where it cannot be measured). The observed
    pixels within ``band`` of the image diagonal of the unobserved ones are held out, the polynomial (free or fixed
    centre, as the LUT's base) fitted on the rest predicts them, and ``|ln flat - ln prediction|`` (less its median
    over the fitted pixels: a scale) is taken as growing in proportion to the distance from the fitted pixels
    (least squares through 0). Measured on a sweep that never covered the right 40 % of a vignette centred in the
    top-left corner: 1.6 / 4.3 / 8.8 / 17 % predicted at 0-10 / 10-20 / 20-40 / 40-80 px from the data against
    3.9 / 6.2 / 9.2 / 16 % true; the filled pixels' standard error before was 2.5 % everywhere."""
    import cv2

    h, w, ch = flat.shape
    reach = max(4.0, band * float(np.hypot(h, w)))
    radius = half_diagonal(resolution)
    slopes = np.zeros(ch)
    for c in range(ch):
        obs = weights[:, :, c] > 0
        if obs.all():
            continue
        inside = cv2.distanceTransform(obs.astype(np.uint8), cv2.DIST_L2, 5)  # distance to the unobserved
        keep, held = obs & (inside >= reach), obs & (inside < reach)
        if np.count_nonzero(keep) < 50 or np.count_nonzero(held) < 50:
            slopes[c] = np.nan
            continue
        ky, kx = np.nonzero(keep)
        step = max(1, int(np.ceil(kx.size / max_points)))
        args = (kx[::step].astype(np.float64), ky[::step].astype(np.float64), flat[:, :, c][keep][::step],
                weights[:, :, c][keep][::step], resolution)
        try:
            s, b, centre, _ = _fit_channel_poly(*args, free=free)
        except CalibrationError:
            try:
                s, b, centre, _ = _fit_channel_poly(*args, free=False)
            except CalibrationError:
                slopes[c] = np.nan
                continue

        def log_model(x, y):
            r2 = ((x - centre[0]) ** 2 + (y - centre[1]) ** 2) / radius ** 2
            return np.log(np.maximum(s * (1.0 + r2 * (b[0] + r2 * (b[1] + r2 * b[2]))), 1e-12))

        hy, hx = np.nonzero(held)
        offset = float(np.median(np.log(flat[:, :, c][keep]) - log_model(kx, ky)))
        err = np.log(flat[:, :, c][held]) - log_model(hx, hy) - offset
        dist = reach - inside[held]
        slopes[c] = float(np.sqrt(np.sum(err ** 2 * dist ** 2) / max(np.sum(dist ** 4), 1e-12)))
    return slopes


def fit_vignetting_lut(accumulation: VignettingAccumulation, *, joint_scale: bool = True, min_samples: int = 1,
                       smooth_sigma: float = 1.0, thin_samples: int = 20) -> LUTVignetting:
    """Per-pixel, per-channel LUT: the session's (drift-corrected) mean flat, normalised and denoised.

    The flat ``D`` is factored as ``P(x) * q(x)`` with ``P`` a free-centre polynomial fit of the same data
    (fixed-centre if the free fit fails) and ``q = D / P`` what no radial model explains (the non-radial
    part and the noise). Then:

    - Denoising: ``q`` is averaged with count-weighted Gaussian weights of ``smooth_sigma`` pixels (``0``
      disables it). Smoothing ``q`` rather than ``D`` keeps the steep radial fall-off out of the average,
      so image borders and the edges of unobserved regions are not biased.
    - Unobserved pixels (fewer than ``min_samples`` samples) get ``P`` times ``q`` faded to 1 away from
      the observed region: never zero or NaN, and no seam. Pixels with only a few samples are pulled
      towards the local trend of ``q`` (with the weight of 3 samples), so a thinly covered corner does not
      carry single-frame noise into the LUT.
    - Normalisation (:func:`centre_normalisers`): ``V = 1`` at its peak, the value there taken from a quadratic
      surface fitted to the flat over a disk of 8 % of the image diagonal around the peak of ``P * q_coarse``
      (``q`` smoothed over 1 % of the diagonal), not from a maximum, which noise biases upwards.
    - Uncertainty (:mod:`~radiometry.vignetting_calibration.uncertainty`): the model carries the relative standard
      error of ``V`` per pixel and channel (``stderr``), and ``info["error_budget"]`` splits the expected error
      in levels (flat field at 200) into noise, coverage (pixels with fewer than ``thin_samples`` samples, or
      none), normalisation and the response (propagated).
    """
    import cv2

    if smooth_sigma < 0:
        raise ValueError(f"smooth_sigma must be >= 0, got {smooth_sigma}")
    if not smooth_sigma <= MAX_SMOOTH_SIGMA:  # also NaN; OpenCV's Gaussian fails on huge kernels
        raise ValueError(f"smooth_sigma must be at most {MAX_SMOOTH_SIGMA:g} pixels, got {smooth_sigma}")
    acc = accumulation
    flat, weights = observed_flat(acc, joint_scale, min_samples)
    h, w, ch = acc.shape
    observed = weights > 0
    if observed.mean() < 0.05:
        raise AdvisedCalibrationError(f"only {100 * observed.mean():.1f}% of the image was observed",
                                      "sweep the sheet over the whole image")
    try:
        poly = fit_vignetting_polynomial(acc, joint_scale=joint_scale, min_samples=min_samples)
    except CalibrationError:
        poly = fit_vignetting_polynomial(acc, fixed_centre=True, joint_scale=joint_scale, min_samples=min_samples)
    base = poly.evaluate(h, w).astype(np.float64) * np.asarray(poly.info["fit_scale"])[None, None, :]
    ratio = np.where(observed, flat / base, 0.0)
    big_sigma = 0.01 * float(np.hypot(h, w))

    def blur(a: np.ndarray, sigma: float) -> np.ndarray:
        if sigma <= 0:
            return a
        out = cv2.GaussianBlur(a.astype(np.float64), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return out.reshape(a.shape)

    with np.errstate(invalid="ignore", divide="ignore"):
        wc = blur(weights, big_sigma)
        coarse = blur(ratio * weights, big_sigma) / wc
        # away from the data the residual fades to 1 (the polynomial alone), with the weight of a tenth of
        # the typical pixel's samples
        prior = 0.1 * float(np.median(weights[observed]))
        faded = (blur(ratio * weights, big_sigma) + prior) / (wc + prior)
        # a pixel with few samples is pulled towards the local trend (the weight of `shrink` samples)
        shrink = 3.0
        trend = np.where(observed, coarse, faded)
        fine = (blur(ratio * weights, smooth_sigma) + shrink * trend) / (blur(weights, smooth_sigma) + shrink)
    q = np.where(observed, fine, faded)
    q_coarse = np.where(observed, coarse, faded)
    norm, centre_info = centre_normalisers(base * q_coarse, flat, weights)
    lut = base * q / norm
    lut = np.maximum(lut, 1e-3)
    norm_se = np.asarray(centre_info["stderr"], dtype=np.float64)
    rel_var = relative_sample_variance(acc.count, acc.sum, acc.sumsq)
    slopes = extrapolation_slope(flat, weights, acc.resolution, free=poly.info["method"] == "poly")
    stderr = lut_stderr(rel_var, weights, ratio, fine, observed, q_coarse, smooth_sigma=smooth_sigma, shrink=shrink,
                        normaliser_stderr=norm_se, extrapolation=slopes)
    budget = error_budget(lut, stderr, acc.count, flat, norm, norm_se, rel_var, acc.response,
                          min_samples=max(min_samples, thin_samples))
    info = {"method": "lut", "joint_scale": bool(joint_scale), "smooth_sigma": float(smooth_sigma),
            "filled_fraction": float(1.0 - observed.all(axis=2).mean()), "frames_used": acc.frames_used,
            "frames_skipped": acc.skipped, "source": acc.source, "base": poly.info["method"],
            "normalisation": centre_info, "error_budget": budget,
            "extrapolation_per_pixel": [None if not np.isfinite(v) else round(float(v), 6) for v in slopes]}
    return LUTVignetting(lut.astype(np.float32), info=info, stderr=stderr)


MODELS = Registry("model", {
    "lut": lambda acc, **kw: fit_vignetting_lut(acc, **kw),
    "poly": lambda acc, **kw: fit_vignetting_polynomial(acc, fixed_centre=False, **kw),
    "poly-fixed-center": lambda acc, **kw: fit_vignetting_polynomial(acc, fixed_centre=True, **kw),
})


def fit_vignetting(accumulation: VignettingAccumulation, *, model: str = "lut", **options: Any) -> VignettingModel:
    """Fit a vignetting model: ``model`` is ``"lut"``, ``"poly"`` (free centre) or ``"poly-fixed-center"``;
    ``options`` go to the method (``joint_scale``, ``min_samples``, ...)."""
    method = MODELS[model]  # ValueError listing the models on a wrong name
    observed = float(np.mean(accumulation.count.max(axis=2) > 0))
    if observed < MIN_OBSERVED_FRACTION:  # the rest of V would be extrapolated from a corner of the image
        raise AdvisedCalibrationError(
            f"{accumulation.source or 'the sweep'}: the sheet was seen at only {observed:.0%} of the image in "
            f"{accumulation.frames_used} frames",
            f"a model needs it swept over at least {MIN_OBSERVED_FRACTION:.0%} (the rest would be guessed); "
            f"{SWEEP_FIX}")
    return method(accumulation, **options)
