"""Evaluation in 8-bit levels: an estimated vignetting against the truth (simulations), a model against a
session's mean flat, the paper's repeatability experiment (Fig. 6), and a calibration's summary (centres,
corner falloff, fit error, coverage)."""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

from radiometry.errors import RadiomapError
from radiometry.registry import validate_name
from radiometry.response import CameraResponse
from radiometry.vignetting import VignettingModel
from radiometry.vignetting_calibration.accumulate import VignettingAccumulation
from radiometry.vignetting_calibration.fit import MODELS, fit_vignetting, observed_flat

log = logging.getLogger(__name__)


def vignetting_error_levels(estimate: np.ndarray | VignettingModel, truth: np.ndarray, response: CameraResponse, *,
                            level: float = 200.0, mask: np.ndarray | None = None) -> np.ndarray:
    """RMS error of an estimated ``V`` against the true one, in 8-bit intensity levels, per channel.

    A flat field whose centre (``V = 1``) images at ``level`` is observed as ``f(f^-1(level) V_true(x))``;
    the estimate predicts ``f(a f^-1(level) V_est(x))``, with ``a`` the median of ``V_true / V_est`` (the
    global scale of ``V`` is absorbed by exposure, so it is not counted). Returns the RMS over pixels
    (or over ``mask``) of the difference of the two, float64 ``(C,)``.
    """
    truth = np.asarray(truth, dtype=np.float64)
    if truth.ndim == 2:
        truth = truth[:, :, None]
    est = estimate.evaluate(truth.shape[0], truth.shape[1]) if isinstance(estimate, VignettingModel) else estimate
    est = np.asarray(est, dtype=np.float64)
    if est.ndim == 2:
        est = est[:, :, None]
    if est.shape[:2] != truth.shape[:2]:
        raise ValueError(f"estimate {est.shape} and truth {truth.shape} must have the same size")
    channels = max(est.shape[2], truth.shape[2])
    est = np.broadcast_to(est, (*truth.shape[:2], channels))
    truth = np.broadcast_to(truth, est.shape)
    sel = np.ones(truth.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    tables = response.channel_tables(channels).astype(np.float64)
    out = np.empty(channels)
    for c in range(channels):
        t, e = truth[:, :, c][sel], est[:, :, c][sel]
        a = float(np.median(t / e))
        base = float(np.interp(level, np.arange(256.0), tables[:, c]))
        obs = np.interp(base * t, tables[:, c], np.arange(256.0))
        pred = np.interp(a * base * e, tables[:, c], np.arange(256.0))
        out[c] = float(np.sqrt(np.mean((pred - obs) ** 2)))
    return out


def flat_rms_levels(model: VignettingModel, accumulation: VignettingAccumulation,
                    response: CameraResponse | None = None, *, joint_scale: bool = True,
                    min_samples: int = 1) -> np.ndarray:
    """How well ``model`` explains a session's mean flat image, in 8-bit levels, per channel.

    The observed flat is ``O(x) = f(E(x))`` with ``E`` the session's (drift-corrected) mean irradiance;
    the model predicts ``P(x) = f(a V(x))`` with ``a`` the median of ``E / V`` (the flat's brightness).
    Returns the RMS of ``P - O`` over pixels with at least ``min_samples`` samples (``(C,)``). With the
    model fitted on the same session this is the fit residual; on another session it is the paper's
    repeatability error (Fig. 6).
    """
    response = response or accumulation.response
    if response is None:
        raise ValueError("pass the response: the accumulation does not carry one")
    flat, weights = observed_flat(accumulation, joint_scale, min_samples)
    h, w, ch = accumulation.shape
    v = model.evaluate(h, w).astype(np.float64)
    v = np.broadcast_to(v, (h, w, ch))
    tables = response.channel_tables(ch).astype(np.float64)
    levels = np.arange(256.0)
    out = np.empty(ch)
    for c in range(ch):
        sel = (weights[:, :, c] > 0) & np.isfinite(flat[:, :, c])
        e, vv = flat[:, :, c][sel], v[:, :, c][sel]
        if e.size == 0:
            out[c] = np.nan
            continue
        a = float(np.median(e / vv))
        obs = np.interp(e, tables[:, c], levels)
        pred = np.interp(a * vv, tables[:, c], levels)
        out[c] = float(np.sqrt(np.mean((pred - obs) ** 2)))
    return out


def model_centre(model: VignettingModel, channel: int) -> tuple[float, float]:
    """``(x, y)`` in pixels where ``model``'s channel is brightest: a polynomial's centre, else the maximum of
    the LUT smoothed by a Gaussian of 2 % of the image diagonal (so that noise does not pick a stray pixel)."""
    from radiometry.vignetting import PolynomialVignetting

    c = min(channel, model.channels - 1)
    if isinstance(model, PolynomialVignetting):
        cx, cy = model.centres[c]
        return float(cx), float(cy)
    import cv2

    v = model.evaluate()[:, :, c].astype(np.float32)
    w, h = model.resolution
    smooth = cv2.GaussianBlur(v, (0, 0), 0.02 * float(np.hypot(w, h)))
    y, x = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    return float(x), float(y)


def calibration_summary(model: VignettingModel, accumulation: VignettingAccumulation, response: CameraResponse,
                        min_samples: int) -> tuple[list[dict], dict]:
    """What a calibration reports: per-channel rows (centre, corner/centre ratio, fit RMS in levels from
    :func:`flat_rms_levels`) and the run's facts (frames used and skipped, coverage against ``min_samples``)."""
    v = model.evaluate()
    rms = flat_rms_levels(model, accumulation, response)
    names = ("R", "G", "B") if model.channels == 3 else ("grey",)
    rows = []
    for c in range(model.channels):
        cx, cy = model_centre(model, c)
        vc = v[:, :, c]
        corners = float(np.mean([vc[0, 0], vc[0, -1], vc[-1, 0], vc[-1, -1]]))
        row = int(round(np.clip(cy, 0, vc.shape[0] - 1)))
        col = int(round(np.clip(cx, 0, vc.shape[1] - 1)))
        centre_value = float(vc[row, col])
        rows.append({"channel": names[c], "centre_x": round(cx, 2), "centre_y": round(cy, 2),
                     "corner/centre": round(corners / centre_value, 4),
                     "fit_rms_levels": round(float(rms[min(c, len(rms) - 1)]), 3)})
    report = accumulation.coverage_report(min_samples)
    facts = {"frames_used": accumulation.frames_used, "frames_skipped": accumulation.frames_skipped,
             "skipped": accumulation.skipped, "coverage": str(report),
             "fraction_below_min_samples": report.fraction_below, "thin_regions": report.thin_regions(),
             "channels": rows}
    budget = model.info.get("error_budget")
    if isinstance(budget, dict):
        facts["error_budget"] = budget
    return rows, facts


def budget_text(budget: dict, channels: int) -> str:
    """One line per part of a LUT's error budget (:func:`radiometry.vignetting_calibration.uncertainty.error_budget`),
    in levels of a flat field at its level, per channel."""
    names = "R/G/B" if channels == 3 else "grey"
    wanted = budget.get("min_samples", "?")
    parts = [("noise", f"noise (were there >= {wanted} samples everywhere)"),
             ("coverage", f"coverage (pixels with < {wanted} samples or none)"),
             ("normalisation", "normalisation (V = 1 at the centre)"),
             ("response", "response (propagated; its roughness only: a lower bound)"
              if budget.get("response_source", "roughness") == "roughness"
              else "response (assumed, not calibrated: its error is unknown, not in the total)"
              if budget.get("response_source") == "assumed"
              else f"response (propagated: {budget['response_source']})"), ("total", "total")]
    lines = [f"expected error, levels of a flat field at {budget.get('level', 200):g} ({names}):"]
    for key, label in parts:
        values = budget.get(key)
        if values is None:
            continue
        text = "/".join("n/a" if not np.isfinite(v) else f"{v:.3f}" for v in np.asarray(values, dtype=float))
        lines.append(f"  {label}: {text}")
    return "\n".join(lines)


def repeatability(accumulations: Sequence[VignettingAccumulation], response: CameraResponse, *,
                  models: Sequence[str] = ("poly", "poly-fixed-center", "lut"),
                  fit_options: dict | None = None) -> dict[str, np.ndarray]:
    """The paper's repeatability experiment (Fig. 6): fit each model on each of K sessions and measure
    :func:`flat_rms_levels` against each of the other K - 1.

    Returns ``{model: errors}`` with ``errors`` float64 ``(K * (K - 1), C)`` in 8-bit levels.
    """
    k = len(accumulations)
    if k < 2:
        raise ValueError(f"repeatability needs at least 2 sessions, got {k}")
    for name in models:
        validate_name(name, MODELS, MODELS.kind)
    results: dict[str, list[np.ndarray]] = {name: [] for name in models}
    for i, acc in enumerate(accumulations):
        for name in models:
            model = fit_vignetting(acc, model=name, **(fit_options or {}))
            for j, other in enumerate(accumulations):
                if j != i:
                    results[name].append(flat_rms_levels(model, other, response))
    return {name: np.array(errs) for name, errs in results.items()}


def split_half_levels(accumulation: VignettingAccumulation, response: CameraResponse, *, model: str = "lut",
                      **fit_options) -> np.ndarray | None:
    """A truth-free figure for a calibration: the model fitted on the even and on the odd frames of the sweep, their
    RMS difference in levels of a flat field at 200 (:func:`vignetting_error_levels`, one half against the other),
    halved: each half has twice the full fit's noise variance, so the difference has twice its standard deviation.
    It covers what the frames leave uncertain (noise, the sheet's texture, drift the correction did not absorb), not
    an error shared by every frame (a wrong response, a lens-shading correction in the camera). None when the
    halves are not available (fewer than 4 frames, or an accumulation saved without them)."""
    halves = accumulation.halves()
    if halves is None:
        return None
    try:
        a, b = (fit_vignetting(half, model=model, **fit_options).evaluate() for half in halves)
    except (ValueError, RadiomapError) as exc:  # a half too thin to fit: no figure rather than no calibration
        log.info("split-half figure not computed: %s", exc)
        return None
    return vignetting_error_levels(a, b, response) / 2.0
