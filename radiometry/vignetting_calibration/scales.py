"""Per-frame brightness drift: the scales ``s_t`` of ``E_t(x) = s_t V(x) L``, solved jointly with the cell-level
vignetting in ``log`` (see :mod:`radiometry.vignetting_calibration`), and the filling of unobserved cells."""

from __future__ import annotations

import numpy as np


def fill_nan_cells(cell: np.ndarray, iterations: int = 64) -> np.ndarray:
    """Fill NaN cells by repeatedly averaging valid 4-neighbours; any left over get the global mean."""
    import warnings

    out = cell.copy()
    for _ in range(iterations):
        nan = np.isnan(out)
        if not nan.any():
            break
        padded = np.pad(out, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
        neigh = np.stack([padded[:-2, 1:-1], padded[2:, 1:-1], padded[1:-1, :-2], padded[1:-1, 2:]])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN neighbourhoods
            avg = np.nanmean(neigh, axis=0)
        grow = nan & ~np.isnan(avg)
        if not grow.any():
            break
        out[grow] = avg[grow]
    if np.isnan(out).any():
        fill = np.ones(out.shape[2]) if np.isnan(out).all() else np.nanmean(out, axis=(0, 1))
        out = np.where(np.isnan(out), np.broadcast_to(np.nan_to_num(fill, nan=1.0), out.shape), out)
    return out


def estimate_frame_scales(cell_sums: np.ndarray, cell_counts: np.ndarray, *, robust_rounds: int = 3,
                          min_fill: float = 0.5) -> np.ndarray:
    """Per-frame brightness scales ``s_t`` jointly with the (cell-level) vignetting, per channel.

    Model ``log m_tb = a_t + v_b`` with ``m_tb`` the mean irradiance of frame ``t`` in cell ``b`` (cells
    at least ``min_fill`` full), weights the cell counts. Alternating ``v`` and ``a`` (the textbook
    scheme) converges to the least-squares solution; we eliminate ``v`` and solve the ``T x T`` system
    for ``a`` directly (plus a tiny ridge for frames that share no cell with another), then re-weight
    with Tukey's biweight for ``robust_rounds`` rounds. Returns ``(T, C)`` with geometric mean 1.
    """
    sums = np.asarray(cell_sums, dtype=np.float64)
    counts = np.asarray(cell_counts, dtype=np.float64)
    n_frames = sums.shape[0]
    channels = sums.shape[-1]
    if n_frames == 0:
        return np.ones((0, channels))
    full = counts.reshape(n_frames, -1, channels).max(axis=(0, 1))  # pixels in a full cell, per channel
    scales = np.ones((n_frames, channels))
    for c in range(channels):
        s = sums[..., c].reshape(n_frames, -1)
        n = counts[..., c].reshape(n_frames, -1)
        ok = (n >= max(1.0, min_fill * full[c])) & (s > 0)
        cols = np.flatnonzero(ok.any(axis=0))
        if cols.size == 0:
            continue
        ok = ok[:, cols]
        y = np.where(ok, np.log(np.where(ok, s[:, cols], 1.0) / np.maximum(n[:, cols], 1.0)), 0.0)
        w0 = np.where(ok, n[:, cols], 0.0)
        w = w0.copy()
        a = np.zeros(n_frames)
        for round_ in range(robust_rounds + 1):
            a = _solve_log_scales(y, w)
            if round_ == robust_rounds:
                break
            wb = w.sum(axis=0)
            v = (w * (y - a[:, None])).sum(axis=0) / np.maximum(wb, 1e-12)
            res = np.where(ok, y - a[:, None] - v[None, :], 0.0)
            sigma = 1.4826 * np.median(np.abs(res[ok])) + 1e-9
            u = res / (4.685 * sigma)
            w = w0 * np.where(np.abs(u) < 1.0, (1.0 - u ** 2) ** 2, 0.0)
        scales[:, c] = np.exp(a - a.mean())
    return scales


def _solve_log_scales(y: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Weighted least squares for ``y_tb = a_t + v_b``: eliminate ``v`` (Schur complement) and solve for
    ``a`` with the gauge ``mean(a) = 0``."""
    wb = w.sum(axis=0)
    inv = np.where(wb > 0, 1.0 / np.maximum(wb, 1e-300), 0.0)
    wt = w.sum(axis=1)
    matrix = np.diag(wt) - (w * inv[None, :]) @ w.T
    rhs = (w * y).sum(axis=1) - (w * inv[None, :]) @ (w * y).sum(axis=0)
    n = matrix.shape[0]
    ridge = 1e-9 * max(float(np.mean(wt)), 1e-12)
    matrix = matrix + ridge * np.eye(n) + np.full((n, n), float(np.mean(wt)) / n)  # gauge: sum(a) = 0
    try:
        a = np.linalg.solve(matrix, rhs)
    except np.linalg.LinAlgError:
        a = np.linalg.lstsq(matrix, rhs, rcond=None)[0]
    return a - a.mean()
