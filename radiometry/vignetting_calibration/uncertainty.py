"""Uncertainty of a vignetting LUT: the per-pixel, per-channel standard error of ``V`` (from the accumulated sums,
sums of squares and counts, inflated where filled) and the calibration's error budget in 8-bit levels (noise,
coverage, normalisation, and the camera response propagated to first order).

Standard error (:func:`lut_stderr`), relative (``se(V) / V``): a pixel's samples give the per-sample variance
``s^2 = (sum sq - sum^2 / n) / (n - 1)`` of its irradiance (the median relative variance of its channel where
``n < 2``); the LUT's value is a count-weighted Gaussian average of the ratio to the radial fit (see
:func:`~radiometry.vignetting_calibration.fit.fit_vignetting_lut`), whose variance is the same average with the
squared kernel; the normaliser's own standard error is added in quadrature (a uniform part). Pixels no sheet
covered (filled from the radial fit) get the observed pixels' median standard error combined with the spread of
what the radial fit does not explain (the non-radial part they may miss) and with the fit's extrapolation error,
measured by holding out the observed pixels next to the uncovered ones and growing in proportion to a pixel's
distance from the data (:func:`~radiometry.vignetting_calibration.fit.extrapolation_slope`), so they are never
reported as exact, nor as known far from any sheet.

Budget (:func:`error_budget`): every standard error is turned into 8-bit levels of a flat field imaged at
``level`` where ``V = 1`` (the measure of :func:`~radiometry.vignetting_calibration.evaluate.vignetting_error_levels`):
``dI = E f'(E) dlnV``. Parts, each an RMS over all pixels so that the squares add up:

- ``noise``: the error the sweep would leave if every pixel had at least ``min_samples`` samples (a pixel's
  standard error scaled by ``sqrt(n / max(n, min_samples))``);
- ``coverage``: what pixels with fewer samples (thin) or none (filled) add to it: sweeping longer removes it;
- ``normalisation``: the uniform error of ``V = 1`` at the centre;
- ``response``: the response's error propagated, ``dlnV(x) = d ln f^-1(z_x) - d ln f^-1(z_centre)`` at the mean
  level ``z`` each pixel saw, averaged over the levels a pixel's noise spreads its samples. When the response's
  ``meta`` carries its own standard error (``"inverse_stderr"``, relative, per level and channel, as
  :func:`~radiometry.response.fit.fit_response_debevec` and
  :func:`~radiometry.response.loglog.fit_response_loglog` record it), that and the levels' 8-bit width
  (:func:`radiometry.response.relative_uncertainty`) are propagated (``dlnV = sqrt(se(z_x)^2 + se(z_centre)^2)``:
  the errors at the pixel's level and the centre's taken as independent, an overestimate where the two are close,
  e.g. near the centre; the bias that noise on the levels, JPEG or a sharp bend put on the fit is not in it: on
  simulated 2x and varied brackets it was 1.1-2.3x the LUT's measured error, docs/guides/calibrate.md); else its
  roughness, the departure of
  ``ln f^-1`` from a local quadratic over 9 levels, as one signed error pattern. Roughness is what a
  fit without a smoothness prior (Engel) leaves as level-to-level error; a smooth error of the whole curve's shape
  (a rounded knee) is invisible to it, so this part is a lower bound.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from radiometry.response import CameraResponse, relative_stderr, relative_uncertainty


def _blur(a: np.ndarray, sigma: float, *, squared: bool = False) -> np.ndarray:
    """Gaussian blur as the LUT fit does it (OpenCV, reflected borders); ``squared``: with the kernel squared."""
    import cv2

    if sigma <= 0:
        return a
    if not squared:
        out = cv2.GaussianBlur(a.astype(np.float64), (0, 0), sigma, borderType=cv2.BORDER_REFLECT)
        return out.reshape(a.shape)
    size = int(round(sigma * 8 + 1)) | 1
    g = cv2.getGaussianKernel(size, sigma, cv2.CV_64F)
    kernel = (g @ g.T) ** 2
    out = cv2.filter2D(a.astype(np.float64), -1, kernel, borderType=cv2.BORDER_REFLECT)
    return out.reshape(a.shape)


def relative_sample_variance(count: np.ndarray, total: np.ndarray, total_sq: np.ndarray) -> np.ndarray:
    """Per pixel and channel, the relative variance ``s^2 / mean^2`` of one sample, float64 ``(H, W, C)``; where
    fewer than 2 samples were taken, the channel's median over the pixels that have them (1e-4 if none)."""
    n = count.astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = total / n
        var = (total_sq - total * mean) / (n - 1.0)
        rel = np.maximum(var, 0.0) / mean ** 2
    rel = np.where((n >= 2) & np.isfinite(rel), rel, np.nan)
    out = np.empty_like(rel)
    for c in range(rel.shape[2]):
        valid = rel[:, :, c][np.isfinite(rel[:, :, c])]
        fill = float(np.median(valid)) if valid.size else 1e-4
        out[:, :, c] = np.where(np.isfinite(rel[:, :, c]), rel[:, :, c], fill)
    return out


def lut_stderr(rel_var: np.ndarray, weights: np.ndarray, ratio: np.ndarray, fine: np.ndarray, observed: np.ndarray,
               q_coarse: np.ndarray, *, smooth_sigma: float, shrink: float,
               normaliser_stderr: np.ndarray, extrapolation: np.ndarray | None = None) -> np.ndarray:
    """Relative standard error of the LUT, float32 ``(H, W, C)`` (see the module doc). ``rel_var``: each pixel's
    :func:`relative_sample_variance`; the others are the LUT fit's intermediates: ``weights`` the counts used,
    ``ratio`` the flat over the radial fit, ``fine`` the denoised ratio, ``observed`` the pixels with data,
    ``q_coarse`` the ratio smoothed coarsely; ``normaliser_stderr`` ``(C,)`` the relative standard error of each
    channel's normaliser (NaN: unknown, taken as 0); ``extrapolation`` ``(C,)`` how fast the fill's error grows per
    pixel of distance from the observed pixels (:func:`~radiometry.vignetting_calibration.fit.extrapolation_slope`;
    NaN or None: not measured), added in quadrature at each filled pixel times its distance."""
    w = np.where(observed, weights, 0.0)
    numerator = _blur(w * rel_var * np.where(observed, ratio, 0.0) ** 2, smooth_sigma, squared=True)
    denominator = _blur(w, smooth_sigma) + shrink
    with np.errstate(invalid="ignore", divide="ignore"):
        se = np.sqrt(numerator) / denominator / np.abs(fine)
    norm_se = np.nan_to_num(np.asarray(normaliser_stderr, dtype=np.float64), nan=0.0)
    se = np.sqrt(np.where(np.isfinite(se), se, 0.0) ** 2 + norm_se[None, None, :] ** 2)
    for c in range(se.shape[2]):
        obs = observed[:, :, c]
        if obs.all():
            continue
        typical = float(np.median(se[:, :, c][obs])) if obs.any() else 0.1
        nonradial = float(np.std(q_coarse[:, :, c][obs])) if obs.any() else 0.1
        filled = np.hypot(typical, nonradial)
        slope = np.nan if extrapolation is None else float(extrapolation[c])
        if np.isfinite(slope) and obs.any():
            import cv2

            distance = cv2.distanceTransform((~obs).astype(np.uint8), cv2.DIST_L2, 5)  # to the nearest observed
            filled = np.hypot(filled, slope * distance)
        se[:, :, c] = np.where(obs, se[:, :, c], filled)
    return se.astype(np.float32)


def response_log_stderr(response: CameraResponse, channels: int) -> np.ndarray | None:
    """The response's own relative standard error of ``f^-1`` per level and channel (``meta["inverse_stderr"]``,
    ``(256,)`` or ``(256, C)``), float64 ``(256, C)``; None when it carries none (or an unusable one)."""
    return relative_stderr(response, channels)


def response_log_roughness(response: CameraResponse, channels: int, *, window: int = 9) -> np.ndarray:
    """``d ln f^-1`` per level and channel, float64 ``(256, C)``: the departure of ``ln f^-1`` from a quadratic
    fitted over ``window`` levels around each level (0 at levels 0 and 255 and where ``f^-1 = 0``)."""
    tables = response.channel_tables(channels).astype(np.float64)
    half = window // 2
    out = np.zeros((256, channels))
    x = np.arange(-half, half + 1, dtype=np.float64)
    design = np.stack([np.ones_like(x), x, x * x], axis=1)
    proj = design @ np.linalg.pinv(design)  # hat matrix: fitted values of the window's quadratic
    centre_row = proj[half]
    for c in range(channels):
        with np.errstate(divide="ignore"):
            ln = np.log(tables[:, c])
        for z in range(1 + half, 255 - half):
            seg = ln[z - half:z + half + 1]
            if np.all(np.isfinite(seg)):
                out[z, c] = ln[z] - float(centre_row @ seg)
    return out


def _levels_per_log_v(response: CameraResponse, v: np.ndarray, level: float) -> np.ndarray:
    """``dI / d ln V`` (8-bit levels) of a flat field imaged at ``level`` where ``V = 1``, at each pixel's ``V``."""
    ch = v.shape[2]
    tables = response.channel_tables(ch).astype(np.float64)
    levels = np.arange(256.0)
    out = np.empty_like(v, dtype=np.float64)
    for c in range(ch):
        base = float(np.interp(level, levels, tables[:, c]))
        e = base * v[:, :, c]
        z = np.interp(e, tables[:, c], levels)
        slope = np.gradient(tables[:, c])  # d f^-1 / d level
        out[:, :, c] = e / np.maximum(np.interp(z, levels, slope), 1e-12)
    return out


def error_budget(lut: np.ndarray, stderr: np.ndarray, count: np.ndarray, flat: np.ndarray, normaliser: np.ndarray,
                 normaliser_stderr: np.ndarray, sample_rel_var: np.ndarray, response: CameraResponse | None, *,
                 min_samples: int = 20, level: float = 200.0) -> dict[str, Any]:
    """The LUT's error budget in 8-bit levels per channel (see the module doc): ``noise``, ``coverage``,
    ``normalisation``, ``response`` and ``total`` (their root sum of squares), each a list of ``C`` floats, plus
    the ``level`` and ``min_samples`` they refer to. ``flat`` is the unnormalised mean irradiance (NaN where
    unobserved), ``normaliser`` its value at the centre, ``sample_rel_var`` :func:`relative_sample_variance`;
    ``response`` None leaves the response part out (NaN); ``response_source`` says what was propagated."""
    ch = lut.shape[2]
    v = lut.astype(np.float64)
    if response is None:
        response = CameraResponse.linear(ch)
        with_response = False
    else:
        with_response = True
    gain = _levels_per_log_v(response, v, level)
    norm_se = np.nan_to_num(np.asarray(normaliser_stderr, dtype=np.float64), nan=0.0)
    pixel_se = np.sqrt(np.maximum(stderr.astype(np.float64) ** 2 - norm_se[None, None, :] ** 2, 0.0))
    d_pixel = gain * pixel_se
    n_pixels = lut.shape[0] * lut.shape[1]
    # noise: the error had every pixel min_samples samples at least (a standard error falls as 1/sqrt(n));
    # unobserved pixels count with the median of that over the observed ones
    m = max(1, min_samples)
    n = count.astype(np.float64)
    covered = d_pixel * np.sqrt(n / np.maximum(n, m))
    for c in range(ch):
        seen = count[:, :, c] > 0
        typical = float(np.median(covered[:, :, c][seen])) if seen.any() else 0.0
        covered[:, :, c] = np.where(seen, covered[:, :, c], typical)
    noise = np.sqrt(np.mean(covered ** 2, axis=(0, 1)))
    # coverage: what thin and unobserved pixels add to that
    coverage = np.sqrt(np.maximum(np.mean(d_pixel ** 2, axis=(0, 1)) - noise ** 2, 0.0))
    normalisation = np.sqrt(np.mean((gain * norm_se[None, None, :]) ** 2, axis=(0, 1)))
    resp = np.full(ch, np.nan)
    given = None
    assumed = with_response and response.meta.get("method") in ("gamma", "linear")  # not measured: error unknown
    if with_response and not assumed:
        given = relative_uncertainty(response, ch)
        rough = response_log_roughness(response, ch) if given is None else given
        tables = response.channel_tables(ch).astype(np.float64)
        levels = np.arange(256.0)
        for c in range(ch):
            obs = np.isfinite(flat[:, :, c])
            if not obs.any():
                continue
            m = flat[:, :, c][obs]
            z = np.interp(m, tables[:, c], levels)
            zc = float(np.interp(normaliser[c], tables[:, c], levels))
            # the noise spreads a pixel's samples over a few levels: the error it sees is the average over them
            slope = np.maximum(np.interp(z, levels, np.gradient(tables[:, c])), 1e-12)
            spread = float(np.median(np.sqrt(sample_rel_var[:, :, c][obs]) * m / slope))
            sigma = min(20.0, max(0.5, spread)) if np.isfinite(spread) else 0.5  # garbage data: a bounded kernel
            taps = np.arange(-int(np.ceil(3 * sigma)), int(np.ceil(3 * sigma)) + 1)
            kernel = np.exp(-0.5 * (taps / sigma) ** 2)
            smooth = np.convolve(rough[:, c], kernel / kernel.sum(), mode="same")
            if given is None:  # one signed pattern: the centre's part cancels where the levels are alike
                dlnv = np.interp(z, levels, smooth) - float(np.interp(zc, levels, smooth))
            else:  # standard errors: independent at the pixel's level and the centre's
                dlnv = np.hypot(np.interp(z, levels, smooth), float(np.interp(zc, levels, smooth)))
            resp[c] = float(np.sqrt(np.sum((gain[:, :, c][obs] * dlnv) ** 2) / n_pixels))
    parts = {"noise": noise, "coverage": coverage, "normalisation": normalisation, "response": resp}
    total = np.sqrt(sum(np.nan_to_num(p) ** 2 for p in parts.values()))
    out: dict[str, Any] = {name: [round(float(x), 4) for x in p] for name, p in parts.items()}
    out["total"] = [round(float(x), 4) for x in total]
    out["response_source"] = ("none" if not with_response else "assumed" if assumed else "roughness" if given is None
                              else "the response's own standard error and its levels' 8-bit width, independent at the "
                              "pixel's level and the centre's (not the bias of noise on the levels or of a bend)")
    out["level"] = float(level)
    out["min_samples"] = int(min_samples)
    return out
