"""The linear core of self-calibration: exposures and radiances of log sightings by exact weighted least squares.

``y = kappa_frame + l_point`` (log irradiance less log V) is solved with the radiances eliminated (each ``l`` is a
weighted mean given ``kappa``), which leaves a dense frames x frames system (the Schur complement). Shared by the
solver (:mod:`radiometry.self_calibration`), the tilt analysis (:mod:`radiometry.self_calibration_checks`) and the
validation (:mod:`radiometry.self_calibration_validation`), below all three.
"""

from __future__ import annotations

import numpy as np


def exposures_and_radiance(y: np.ndarray, w: np.ndarray, point: np.ndarray, frame: np.ndarray, n_points: int,
                           n_frames: int, fixed: np.ndarray | None = None, kappa_fixed: np.ndarray | None = None
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares of ``y = kappa_frame + l_point`` with ``kappa`` held at ``kappa_fixed`` on the
    ``fixed`` frames (default: ``kappa_0 = 0``), exactly (Schur complement)."""
    if fixed is None:
        fixed = np.arange(n_frames) == 0
    known = np.zeros(n_frames) if kappa_fixed is None else np.where(fixed, np.nan_to_num(kappa_fixed), 0.0)
    y = y - known[frame]
    from scipy import sparse

    b = sparse.coo_matrix((w, (point, frame)), shape=(n_points, n_frames)).tocsr()
    dp = np.asarray(b.sum(axis=1)).ravel()
    df = np.asarray(b.sum(axis=0)).ravel()
    sy_p = np.bincount(point, w * y, minlength=n_points)
    sy_f = np.bincount(frame, w * y, minlength=n_frames)
    inv_dp = np.where(dp > 0, 1.0 / np.maximum(dp, 1e-300), 0.0)
    bs = sparse.diags(np.sqrt(inv_dp)) @ b
    schur = np.diag(df) - (bs.T @ bs).toarray()
    rhs = sy_f - b.T @ (inv_dp * sy_p)
    seen = (df > 0) & ~fixed      # the fixed frames keep their known kappa
    kappa = np.zeros(n_frames)
    sub = np.ix_(seen, seen)
    ridge = 1e-9 * max(float(np.max(df)), 1.0)
    kappa[seen] = np.linalg.solve(schur[sub] + ridge * np.eye(int(seen.sum())), rhs[seen])
    kappa[~fixed & (df == 0)] = np.nan
    kappa[fixed] = known[fixed]
    kf = np.nan_to_num(kappa) - known
    lp = inv_dp * np.bincount(point, w * (y - kf[frame]), minlength=n_points)
    return kappa, lp


__all__ = ["exposures_and_radiance"]
