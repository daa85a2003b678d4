"""OpenCV's response calibrations (``CalibrateDebevec``, ``CalibrateRobertson``) behind radiomap's interface, for
comparison (:func:`radiometry.response.fit.fit_response` with ``method="opencv-debevec"`` or ``"robertson"``)."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError
from radiometry.response.model import LEVELS, CameraResponse
from radiometry.response.debevec import _LEVELS, DEFAULT_LAMBDA, _finish
from radiometry.response.inputs import _as_stack, _check_brightness_order

log = logging.getLogger(__name__)


def _fill_log_table(ln_f: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Replace invalid entries of a log table by linear inter/extrapolation of the valid ones (per channel)."""
    out = ln_f.copy()
    for c in range(out.shape[1]):
        ok = valid[:, c]
        if ok.sum() < 2:
            raise CalibrationError("the OpenCV fit observed fewer than 2 intensity levels; use more exposures")
        lv = np.flatnonzero(ok)
        out[~ok, c] = np.interp(np.flatnonzero(~ok), lv, out[lv, c])
        for side in (slice(None, lv[0]), slice(lv[-1] + 1, None)):
            idx = _LEVELS[side]
            if idx.size == 0:
                continue
            near = lv[:8] if side.stop is not None else lv[-8:]
            slope = np.polyfit(near, out[near, c], 1)[0]
            slope = max(slope, 1e-3)
            anchor = near[0] if side.stop is not None else near[-1]
            out[idx, c] = out[anchor, c] + slope * (idx - anchor)
    return out


def _opencv_table(result: np.ndarray, n_ch: int) -> np.ndarray:
    table = np.asarray(result, dtype=np.float64).reshape(LEVELS, -1)
    return table[:, :n_ch]


def fit_response_opencv_debevec(images: Sequence[np.ndarray], times: Sequence[float], *,
                                lam: float = DEFAULT_LAMBDA, samples: int = 70,
                                random: bool = False) -> CameraResponse:
    """OpenCV's ``CalibrateDebevec`` (``samples`` pixel locations on a grid, or random; weight lam).

    OpenCV takes no mask. Levels without a finite positive value are extrapolated in the log domain and
    a non-monotone result is repaired (both recorded in ``meta``). ``lam`` is OpenCV's lambda (relative
    to one data row, unlike :func:`fit_response_debevec`'s).
    """
    import cv2

    if not (np.isfinite(lam) and lam >= 0):
        raise ValueError(f"lam must be a finite number >= 0, got {lam}")
    if int(samples) != samples or samples < 1:
        raise ValueError(f"samples must be a positive whole number of pixel locations, got {samples}")
    start = time.perf_counter()
    stack, t = _as_stack(images, times)
    _check_brightness_order(stack, t)
    n_ch = stack.shape[-1]
    src = [np.ascontiguousarray(im if n_ch == 3 else im[..., 0]) for im in stack]
    calib = cv2.createCalibrateDebevec(int(samples), float(lam), bool(random))
    table = _opencv_table(calib.process(src, t.astype(np.float32)), n_ch)
    response = _from_opencv(table, {"method": "opencv-debevec", "lambda": float(lam), "samples": int(samples),
                                    "random": bool(random), "images": int(len(t)), "times": t.tolist()})
    _declare_levels(response, stack, t)
    response.meta["fit_seconds"] = time.perf_counter() - start
    return response


def fit_response_robertson(images: Sequence[np.ndarray], times: Sequence[float], *, max_iter: int = 30,
                           threshold: float = 0.01) -> CameraResponse:
    """OpenCV's ``CalibrateRobertson`` (Gauss-Seidel iterations on all pixels).

    Level 255 only sees clipped irradiance (Robertson's average of saturated pixels is biased) and some
    levels may never be observed (NaN): those are extrapolated in the log domain, recorded in ``meta``.
    Grayscale stacks are fed as 3 equal channels (OpenCV 5.0 corrupts memory on 1-channel input).
    """
    import cv2

    if int(max_iter) != max_iter or max_iter < 1:
        raise ValueError(f"max_iter must be a positive whole number, got {max_iter}")
    if not (np.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number, got {threshold}")
    start = time.perf_counter()
    stack, t = _as_stack(images, times)
    _check_brightness_order(stack, t)
    n_ch = stack.shape[-1]
    src = [np.ascontiguousarray(im if n_ch == 3 else np.repeat(im, 3, axis=2)) for im in stack]
    calib = cv2.createCalibrateRobertson(int(max_iter), float(threshold))
    table = _opencv_table(calib.process(src, t.astype(np.float32)), n_ch)
    table[LEVELS - 1] = np.nan  # saturated level: extrapolate instead of the clipped average
    response = _from_opencv(table, {"method": "robertson", "max_iter": int(max_iter),
                                    "threshold": float(threshold), "images": int(len(t)), "times": t.tolist()})
    _declare_levels(response, stack, t)
    response.meta["fit_seconds"] = time.perf_counter() - start
    return response


def _declare_levels(response: CameraResponse, stack: np.ndarray, t: np.ndarray) -> None:
    """Record which levels the data constrain (:func:`radiometry.response.levels.detect_levels`), as radiomap's own
    fits do: OpenCV fits every level it sees, saturated and dark ones included, so ``meta["declared_levels"]`` (what
    the quality figures and a vignetting budget judge) is the levels found from the data, and ``levels_summary``
    says what OpenCV did with the others."""
    from radiometry.response.levels import describe, detect_levels

    try:
        found = detect_levels(stack, t)
    except CalibrationError as exc:  # OpenCV fitted anyway: say that the data do not support it
        log.warning("%s; OpenCV fitted every level anyway: this curve is not constrained by the data", exc)
        response.meta["levels_summary"] = (f"levels found from the data: {exc}; OpenCV fitted every level anyway, "
                                           "so this curve is not constrained by the data")
        return
    response.meta["level_detection"] = [lv.as_dict() for lv in found]
    response.meta["saturation_levels"] = [lv.ceiling for lv in found]
    response.meta["declared_levels"] = [[lv.low, lv.high] for lv in found]
    response.meta["levels_summary"] = (describe(found).replace("levels used", "levels the data constrain")
                                       .replace("(the others extrapolated)", "(found from the data; OpenCV "
                                                "fitted the others too, from saturated or dark pixels: do not trust "
                                                "them)"))


def _from_opencv(table: np.ndarray, meta: dict[str, Any]) -> CameraResponse:
    ok = np.isfinite(table) & (table > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ln_f = np.where(ok, np.log(np.where(ok, table, 1.0)), np.nan)
    extrapolated = [np.flatnonzero(~ok[:, c]).tolist() for c in range(table.shape[1])]
    if not ok.all():
        ln_f = _fill_log_table(ln_f, ok)
    meta = dict(meta, extrapolated_levels=extrapolated)
    return _finish(ln_f, meta)
