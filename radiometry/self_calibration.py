"""Self-calibration of vignetting, per-frame exposure and white balance from surface points seen many times.

A surface point ``i`` of radiance ``L_i`` seen in frame ``j`` at pixel ``x_ij`` images, per channel, at the
irradiance ``E_ij = f^-1(I_ij) = k_j V(x_ij) L_i`` (the response ``f`` is given), so that

    log E_ij = log k_j + log V(x_ij) + log L_i

is linear in ``log k`` and ``log L`` and smooth in the few parameters of ``V``. ``V`` is a free-centre even
polynomial ``1 + b1 r^2 + b2 r^4 + b3 r^6`` (``r`` normalised by the half-diagonal, as
:class:`radiometry.vignetting.PolynomialVignetting`) times ``exp(g(x))``, ``g`` a smooth non-radial residual,
bilinear on the nodes of a grid (8 x 6 cells, finer where the sightings are dense enough: :func:`choose_grid`) and
regularised by its second differences.
The gauge: ``k_0 = 1`` (the first frame) and ``V = 1`` at the polynomial's centre (``g`` is shifted to 0 there;
the constant goes into ``L``).

The solver (:func:`self_calibrate`) works per channel, in log space, by iteratively reweighted least squares
(IRLS) for a Huber loss on the log residuals:

1. start: ``V = 1``; exposures and radiances by one exact weighted linear least-squares solve, the radiances
   eliminated (each ``log L_i`` is a weighted mean given ``log k``), which leaves a dense frames x frames system
   (the Schur complement; frames are few, points many);
2. each round: one Gauss-Newton step on ALL unknowns at once (exposures, radiances, the polynomial's centre and
   coefficients and the grid), the radiances again eliminated exactly, so the dense system has only
   frames + 5 + nodes unknowns; step halving keeps the cost falling and ``V`` positive. (Alternating between
   ``V`` and the exposures converges very slowly along the directions a panning camera hardly sees: measured,
   15 alternating rounds left 1.4 % median exposure error where the joint step leaves 0.4 %.)
3. Huber weights from the new residuals (threshold ``huber`` times a robust scale, the MAD).

``V``'s terms are evaluated on observations binned by image position (:data:`POSITION_BINS` across), each
sighting corrected by the first-order change of ``log V`` between it and its bin's centre (:class:`_SubBin`).

A camera that only pans moves points by a common image shift, and then a tilt of ``log V`` is indistinguishable
from a drift of the exposures; parallax and rotation break the tie, more or less. How much, per axis, is measured
before the solve (:func:`radiometry.self_calibration_checks.tilt_visibility`) and sets one of three regimes: where
the data pin the tilt well the grid's tilt is free; in between, the grid carries no tilt (penalised) and a tilt
can only come from the polynomial's centre, which has a weak prior at the principal point (``centre``;
``centre_sigma`` in half-diagonals, default 1: measured on the simulated room, a strong prior (0.05) pinned a
centre that is truly 8 px off and left a 4 % exposure drift in that channel; the joint step finds it); where the
tilt is open, the centre is held at the principal point (the plausible member) and the stated standard error
carries the spread of real lenses' centres and shading along that axis. Known exposures (``exposures``) are held
at their values, which pins the tilt they would trade against.

Why not ``scipy.optimize.least_squares(loss="huber")`` on the whole sparse Jacobian: its unknowns are every
point's radiance (tens of thousands) and each trust-region step runs LSMR over all observations; the exact
elimination above solves a small dense system per step instead.

A sequence constrains ``V`` only when each image region sees points that are also seen elsewhere in the image
(:func:`check_constrained`); otherwise :class:`SelfCalibrationError` says what to record.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from radiometry.errors import CalibrationError
from radiometry.self_calibration_lsq import exposures_and_radiance as _exposures_and_radiance
from radiometry.vignetting import LUTVignetting, half_diagonal
from radiometry.vignetting_calibration.accumulate import REGIONS

log = logging.getLogger(__name__)

#: grid cells (columns, rows) of the non-radial residual: the coarsest, and the finer ones ``grid="auto"`` takes
#: when the sightings are dense enough (:func:`choose_grid`)
DEFAULT_GRID = (8, 6)
GRIDS = ((8, 6), (12, 9), (16, 12), (24, 18))
#: ``grid="auto"``: the finest of :data:`GRIDS` whose sparsest tenth of cells still holds this many sightings each
MIN_PER_CELL = 1000
#: image-position bins across the width used by the V update (observations within a bin share its centre)
POSITION_BINS = 80
#: weight of the rows that keep the grid residual free of a tilt (relative to its second differences), and along
#: an axis whose tilt the data pin well (:data:`radiometry.self_calibration_checks.FREE_VISIBILITY`)
TILT_WEIGHT = 30.0
TILT_WEIGHT_VISIBLE = 0.3
#: the polynomial centre's prior spread (half-diagonals) along an axis whose tilt the data leave open
OPEN_CENTRE_SIGMA = 0.03


class SelfCalibrationError(CalibrationError):
    """The observations cannot constrain the vignetting (too few frames, too little motion)."""


@dataclass(frozen=True, eq=False)
class Observations:
    """Surface points seen in frames: one row per sighting.

    point, frame: int ``(N,)`` indices (points ``0..P-1``, frames ``0..F-1``); x, y: float ``(N,)`` pixel
    coordinates (OpenCV convention); irradiance: float ``(N, C)`` ``f^-1(I)`` per channel (> 0);
    resolution: (width, height) of the images; n_frames: F (frames without sightings are allowed but get no
    exposure).
    """

    point: np.ndarray
    frame: np.ndarray
    x: np.ndarray
    y: np.ndarray
    irradiance: np.ndarray
    resolution: tuple[int, int]
    n_frames: int

    def __post_init__(self) -> None:
        n = np.shape(self.point)[0] if np.ndim(self.point) == 1 else -1
        shapes = [np.shape(a) for a in (self.point, self.frame, self.x, self.y)]
        if n < 0 or any(s != (n,) for s in shapes):
            raise ValueError(f"point, frame, x and y must be 1-D of one length, got shapes {shapes}")
        irr = np.asarray(self.irradiance)
        if irr.ndim != 2 or irr.shape[0] != n:
            raise ValueError(f"irradiance must be (N, C) with N = {n}, got shape {irr.shape}")
        if n and not (np.all(np.isfinite(irr)) and np.all(irr > 0)):
            raise ValueError("irradiance must be finite and > 0 (leave out dark and saturated pixels)")
        if n and (np.min(self.frame) < 0 or np.max(self.frame) >= self.n_frames or np.min(self.point) < 0):
            raise ValueError(f"frame must lie in [0, {self.n_frames}) and point be >= 0")

    @property
    def channels(self) -> int:
        return int(np.shape(self.irradiance)[1])

    @property
    def n_points(self) -> int:
        return int(np.max(self.point)) + 1 if len(self.point) else 0


@dataclass
class SelfCalibration:
    """The result of :func:`self_calibrate`.

    vignetting: the LUT model (``stderr``: relative standard error of ``V`` per pixel and channel in its gauge,
    exposures and radiances marginalised, cluster-robust over blocks of frames and over points: :func:`_covariance`);
    exposures: ``(F, C)`` ``k_j`` (``k_0 = 1``; NaN for frames without
    sightings); radiance: ``(P, C)``; sightings: ``(F,)`` observations per frame used; residuals_before /
    residuals_after: the log residuals per channel with ``V = 1`` and with the fitted ``V`` (``(N,)`` each);
    coverage: ``(gh, gw)`` sightings per position bin; info: parameters and diagnostics.
    """

    vignetting: LUTVignetting
    exposures: np.ndarray
    radiance: np.ndarray
    sightings: np.ndarray
    residuals_before: list[np.ndarray]
    residuals_after: list[np.ndarray]
    coverage: np.ndarray
    info: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------------
# the model of log V
# --------------------------------------------------------------------------------------------------
class _LogV:
    """``log V(x) = log(1 + b1 r^2 + b2 r^4 + b3 r^6) + g(x)`` at fixed positions, with its Jacobian."""

    def __init__(self, x: np.ndarray, y: np.ndarray, resolution: tuple[int, int], grid: tuple[int, int]) -> None:
        w, h = resolution
        self.x, self.y, self.radius = x, y, half_diagonal(resolution)
        gw, gh = grid
        self.nodes = (gh + 1, gw + 1)
        # bilinear weights of the grid nodes: node (r, c) sits at ((c / gw) * W - 0.5, (r / gh) * H - 0.5)
        wx, wy = _hat_weights(x, w, gw), _hat_weights(y, h, gh)
        self.bilinear = (wy[:, :, None] * wx[:, None, :]).reshape(len(x), -1)

    def poly(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cx, cy, b1, b2, b3 = p[:5]
        r2 = ((self.x - cx) ** 2 + (self.y - cy) ** 2) / self.radius ** 2
        return r2, 1 + b1 * r2 + b2 * r2 ** 2 + b3 * r2 ** 3

    def value(self, p: np.ndarray) -> np.ndarray:
        _, q = self.poly(p)
        return np.log(np.maximum(q, 1e-6)) + self.bilinear @ p[5:]

    def jacobian(self, p: np.ndarray) -> np.ndarray:
        cx, cy, b1, b2, b3 = p[:5]
        r2, q = self.poly(p)
        q = np.maximum(q, 1e-6)
        dq_dr2 = b1 + 2 * b2 * r2 + 3 * b3 * r2 ** 2
        jac = np.empty((len(self.x), 5 + self.bilinear.shape[1]))
        jac[:, 0] = dq_dr2 * (-2 * (self.x - cx) / self.radius ** 2) / q
        jac[:, 1] = dq_dr2 * (-2 * (self.y - cy) / self.radius ** 2) / q
        jac[:, 2], jac[:, 3], jac[:, 4] = r2 / q, r2 ** 2 / q, r2 ** 3 / q
        jac[:, 5:] = self.bilinear
        return jac


def _hat_weights(x: np.ndarray, size: int, cells: int) -> np.ndarray:
    """Linear-interpolation weights ``(N, cells + 1)`` of grid nodes at ``(k / cells) * size - 0.5``."""
    u = np.clip((np.asarray(x, dtype=np.float64) + 0.5) / size * cells, 0, cells)
    return np.maximum(0.0, 1.0 - np.abs(u[:, None] - np.arange(cells + 1)[None, :]))


def log_v_image(p: np.ndarray, resolution: tuple[int, int], grid: tuple[int, int]) -> np.ndarray:
    """``log V`` of parameters ``p`` (centre, b1..b3, grid nodes) on every pixel, float64 ``(H, W)``."""
    w, h = resolution
    xs, ys = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    r2 = ((xs[None, :] - p[0]) ** 2 + (ys[:, None] - p[1]) ** 2) / half_diagonal(resolution) ** 2
    q = 1 + p[2] * r2 + p[3] * r2 ** 2 + p[4] * r2 ** 3
    nodes = p[5:].reshape(grid[1] + 1, grid[0] + 1)
    g = _hat_weights(ys, h, grid[1]) @ nodes @ _hat_weights(xs, w, grid[0]).T
    return np.log(np.maximum(q, 1e-6)) + g


def _grid_penalty(nodes: tuple[int, int], tilt_weight=(TILT_WEIGHT, TILT_WEIGHT)) -> np.ndarray:
    """Rows of second differences along both grid axes, plus first differences at the borders' ends (so that a
    plane, which trades against the polynomial's centre, is not free either)."""
    nr, nc = nodes
    idx = np.arange(nr * nc).reshape(nr, nc)
    rows = []
    for line in list(idx) + list(idx.T):
        for a, b, c in zip(line[:-2], line[1:-1], line[2:]):
            r = np.zeros(nr * nc)
            r[[a, b, c]] = (1.0, -2.0, 1.0)
            rows.append(r)
    ridge = np.eye(nr * nc) * 0.05
    # the plane (tilt) of the residual: a camera that mostly pans sees a tilt of log V only as a drift of its
    # exposures, so the tilt is left to the polynomial's centre (held near the principal point by its prior)
    yy, xx = np.mgrid[0:nr, 0:nc]
    plane = np.stack([np.ones(nr * nc), (xx.ravel() - (nc - 1) / 2) / (nc - 1), (yy.ravel() - (nr - 1) / 2) / (nr - 1)],
                     axis=1)
    tilt = np.linalg.pinv(plane)[1:] * np.asarray(tilt_weight, dtype=np.float64)[:, None]
    return np.vstack([np.array(rows), ridge, tilt])


# --------------------------------------------------------------------------------------------------
# the solver
# --------------------------------------------------------------------------------------------------
def _huber_weights(res: np.ndarray, huber: float) -> tuple[np.ndarray, float]:
    scale = max(1.4826 * float(np.median(np.abs(res - np.median(res)))), 1e-4)
    a = np.abs(res) / (huber * scale)
    return np.where(a <= 1, 1.0, 1.0 / np.maximum(a, 1e-12)), scale


class _SubBin:
    """The first-order change of ``log V`` between each sighting and its position bin's centre, for the current
    parameters: subtracted from the sightings' ``log E`` before each step (a fixed point over the rounds). Without
    it a point keeps one offset within its bin while it drifts a few pixels across the image, and the slow vertical
    drift of a panning camera's points (perspective: what alone pins V's vertical profile there) was lost to the
    8-pixel bins: on exact data of the model's own form, a steady pan with known exposures came out 1.65 levels
    off with the bins' centres, 0.52 with bins half as wide and 0.04 with this correction (docs/self_calibration.md)."""

    def __init__(self, obs: Observations, bx: np.ndarray, by: np.ndarray, bin_of: np.ndarray,
                 grid: tuple[int, int]) -> None:
        self.dx = np.asarray(obs.x, dtype=np.float64) - bx[bin_of]
        self.dy = np.asarray(obs.y, dtype=np.float64) - by[bin_of]
        self.bin_of = bin_of
        self.models = [_LogV(bx + dx, by + dy, obs.resolution, grid) for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1))]

    def correction(self, p: np.ndarray) -> np.ndarray:
        xp, xm, yp, ym = (m.value(p) for m in self.models)
        return (0.5 * (xp - xm))[self.bin_of] * self.dx + (0.5 * (yp - ym))[self.bin_of] * self.dy


def _bins(obs: Observations) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """Each observation's position bin, and the bins' centres: ``(bin (N,), bx, by, (bins_y, bins_x))``."""
    w, h = obs.resolution
    size = max(w / POSITION_BINS, 1.0)
    nx, ny = int(np.ceil(w / size)), int(np.ceil(h / size))
    ix = np.clip(((np.asarray(obs.x) + 0.5) / size).astype(np.int64), 0, nx - 1)
    iy = np.clip(((np.asarray(obs.y) + 0.5) / size).astype(np.int64), 0, ny - 1)
    gx, gy = np.meshgrid((np.arange(nx) + 0.5) * size - 0.5, (np.arange(ny) + 0.5) * size - 0.5)
    return iy * nx + ix, gx.ravel(), gy.ravel(), (ny, nx)


def _occupied(bin_of: np.ndarray, bx: np.ndarray, by: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Renumber the bins to the occupied ones: ``(bin (N,) into them, their bx, their by)``."""
    used, inverse = np.unique(bin_of, return_inverse=True)
    return inverse, bx[used], by[used]


def check_constrained(obs: Observations, *, min_frames: int = 3, min_points: int = 20) -> dict[str, int]:
    """Raise :class:`SelfCalibrationError` unless the sightings can constrain ``V``: at least ``min_frames``
    frames with sightings, and in every region of a 3 x 3 split of the image at least ``min_points`` points that
    are also seen outside that region (a point seen only at one image position says nothing about ``V``).
    Returns those counts per region."""
    frames = int(np.count_nonzero(np.bincount(np.asarray(obs.frame), minlength=obs.n_frames)))
    if frames < min_frames:
        raise SelfCalibrationError(
            f"only {frames} frame(s) have usable surface points (need {min_frames}); use more frames (--frames) "
            "with valid depth and poses, not over- or under-exposed")
    w, h = obs.resolution
    col = np.clip((np.asarray(obs.x) + 0.5) * 3 / w, 0, 2).astype(np.int64)
    row = np.clip((np.asarray(obs.y) + 0.5) * 3 / h, 0, 2).astype(np.int64)
    region = row * 3 + col
    point = np.asarray(obs.point)
    n_points = obs.n_points
    counts = {}
    for r, name in enumerate(REGIONS):
        inside = np.zeros(n_points, bool)
        outside = np.zeros(n_points, bool)
        inside[point[region == r]] = True
        outside[point[region != r]] = True
        counts[name] = int(np.count_nonzero(inside & outside))
    thin = [name for name, n in counts.items() if n < min_points]
    if thin:
        raise SelfCalibrationError(
            f"the sequence cannot constrain vignetting: too few surface points are seen both in "
            f"{', '.join(thin)} and elsewhere in the image ({', '.join(str(counts[t]) for t in thin)} < {min_points}); "
            "use a sequence (or a longer --frames range) in which the camera pans and turns so that surfaces "
            "cross the whole image")
    return counts


def choose_grid(obs: Observations, min_per_cell: int = MIN_PER_CELL) -> tuple[int, int]:
    """The finest grid of :data:`GRIDS` (aspect of a 4:3 image; columns, rows) on which 90 % of the cells hold
    at least ``min_per_cell`` sightings: the non-radial part of V as fine as the coverage allows (dust shadows
    and sensor shading sit well below the 8 x 6 grid's cells); cells thinner than that are held smooth by the
    second-difference penalty and get a larger standard error."""
    w, h = obs.resolution
    chosen = GRIDS[0]
    for gw, gh in GRIDS:
        ix = np.clip(((np.asarray(obs.x) + 0.5) * gw / w).astype(np.int64), 0, gw - 1)
        iy = np.clip(((np.asarray(obs.y) + 0.5) * gh / h).astype(np.int64), 0, gh - 1)
        counts = np.bincount(iy * gw + ix, minlength=gw * gh)
        if np.quantile(counts, 0.1) >= min_per_cell:
            chosen = (gw, gh)
    return chosen


def self_calibrate(obs: Observations, *, grid: tuple[int, int] | str = "auto", iterations: int = 15,
                   huber: float = 2.0, smoothness: float = 0.01, min_frames: int = 3, min_points: int = 20,
                   centre: tuple[float, float] | None = None, centre_sigma: float = 1.0,
                   stderr_bins: int = 40, stderr_block: int | None = None,
                   exposures: np.ndarray | None = None) -> SelfCalibration:
    """Estimate ``V``, ``k_j`` and ``L_i`` per channel from ``obs`` (see the module doc).

    grid: (columns, rows) of the non-radial residual, or ``"auto"`` (:func:`choose_grid`); iterations: IRLS rounds; huber: the Huber threshold in
    robust standard deviations of the log residuals; smoothness: weight of the residual's second differences
    (relative to the number of sightings per grid cell); min_frames, min_points: :func:`check_constrained`;
    centre: the principal point (default: the image centre), the prior of the polynomial's centre, with
    ``centre_sigma`` half-diagonals of spread; stderr_bins: grid across the width on which the standard error of
    ``V`` is evaluated (then resized); stderr_block: consecutive frames per cluster of the standard error
    (:func:`_covariance`; default a sixth of the frames: six clusters); exposures: known ``k`` per frame and
    channel ``(F, C)`` (NaN where unknown): held at their values (only the rest is fitted), and the result's
    exposures are then scaled to the first frame (``k_0 = 1``).
    """
    from radiometry.self_calibration_checks import tilt_stderr, tilt_visibility

    regions = check_constrained(obs, min_frames=min_frames, min_points=min_points)
    width, height = obs.resolution
    point = np.asarray(obs.point, dtype=np.int64)
    frame = np.asarray(obs.frame, dtype=np.int64)
    n_points, n_frames = obs.n_points, obs.n_frames
    fixed0 = np.arange(n_frames) == 0
    if exposures is not None:
        fixed0 = np.all(np.isfinite(np.broadcast_to(exposures, (n_frames, obs.channels))), axis=1) | fixed0
    visibility = tilt_visibility(obs.x, obs.y, np.ones(len(point)), point, frame, obs.resolution, n_points,
                                 n_frames, fixed0)
    tilt_open = np.array(visibility.open)     # known exposures pin the tilt (their frames are held)
    from radiometry.self_calibration_checks import FREE_VISIBILITY

    tilt_free = np.array(visibility.visibility) >= FREE_VISIBILITY
    grid_how = "auto" if isinstance(grid, str) else "given"
    if isinstance(grid, str):
        if grid != "auto":
            raise ValueError(f"grid must be 'auto' or (columns, rows), got {grid!r}")
        # where the data pin a tilt only weakly, every slow trend along that axis is nearly open too (a horizontal
        # pan never moves points up or down): the coarse grid; a finer one only where both axes are well seen
        grid = choose_grid(obs) if tilt_free.all() else DEFAULT_GRID
    logs = np.log(np.asarray(obs.irradiance, dtype=np.float64))
    all_bins, bx, by, bin_shape = _bins(obs)
    coverage = np.bincount(all_bins, minlength=bx.size).reshape(bin_shape)
    used_bins = np.unique(all_bins)
    bin_of, bx, by = _occupied(all_bins, bx, by)
    n_bins = bx.size
    model = _LogV(bx, by, obs.resolution, grid)
    sub_bin = _SubBin(obs, bx, by, bin_of, grid)
    penalty = _grid_penalty(model.nodes, np.where(tilt_free, TILT_WEIGHT_VISIBLE, TILT_WEIGHT))
    per_cell = len(point) / float(grid[0] * grid[1])
    lam = smoothness * per_cell
    centre0 = np.array([(width - 1) / 2.0, (height - 1) / 2.0]) if centre is None else np.asarray(centre, float)
    centre_weight = 1.0 / np.where(tilt_open, min(centre_sigma, OPEN_CENTRE_SIGMA), centre_sigma) ** 2
    block = stderr_block or max(1, -(-n_frames // 6))      # six blocks of consecutive frames
    luts, ses, kappas, radiances = [], [], [], []
    before, after, params_out, scales = [], [], [], []
    known = None if exposures is None else np.log(np.broadcast_to(np.asarray(exposures, dtype=np.float64),
                                                                  (n_frames, obs.channels)))
    for c in range(obs.channels):
        y_seen = logs[:, c]
        fixed = np.arange(n_frames) == 0
        kappa_fixed = np.zeros(n_frames)
        if known is not None and np.isfinite(known[:, c]).any():
            fixed, kappa_fixed = np.isfinite(known[:, c]), np.nan_to_num(known[:, c])
        p = np.concatenate([centre0, np.zeros(3 + model.bilinear.shape[1])])
        w = np.ones(len(y_seen))
        scale = 0.01
        y = y_seen - sub_bin.correction(p)
        v_obs = model.value(p)[bin_of]
        kappa, lp = _exposures_and_radiance(y - v_obs, w, point, frame, n_points, n_frames, fixed, kappa_fixed)
        before.append(y - v_obs - np.nan_to_num(kappa)[frame] - lp[point])
        kappa = np.nan_to_num(kappa)
        for _ in range(iterations):
            wb = np.bincount(bin_of, w, minlength=n_bins)
            prior = (centre0, centre_weight * float(wb.sum()) * scale ** 2 / model.radius ** 2)
            p, kappa, lp = _joint_step(model, p, kappa, lp, y, w, point, frame, bin_of, penalty, lam, prior,
                                       obs.resolution, fixed)
            y = y_seen - sub_bin.correction(p)
            res = y - model.value(p)[bin_of] - kappa[frame] - lp[point]
            w, scale = _huber_weights(res, huber)
        cov = _covariance(model, p, kappa, lp, y, w, point, frame, bin_of, penalty, lam, prior, scale, block, fixed)
        kappa[(np.bincount(frame, minlength=n_frames) == 0) & ~fixed] = np.nan      # known ones stay
        if np.isfinite(kappa[0]) and kappa[0] != 0:     # known exposures: scaled to the first frame's
            lp += kappa[0]
            kappa -= kappa[0]
        # gauge: V = 1 at the polynomial's centre (g shifted to 0 there), k_0 = 1 (kappa_0 = 0 already)
        centre_model = _LogV(np.array([p[0]]), np.array([p[1]]), obs.resolution, grid)
        g_centre = float(centre_model.bilinear[0] @ p[5:])
        p[5:] -= g_centre
        lp += g_centre
        after.append(res)
        scales.append(scale)
        luts.append(np.exp(log_v_image(p, obs.resolution, grid)))
        se = _stderr(p, cov, obs.resolution, grid, stderr_bins)
        se = np.sqrt(se ** 2 + _misfit(res, w, bin_of, used_bins, bin_shape, scale, obs.resolution) ** 2
                     ).astype(np.float32)
        if not tilt_free.all():      # what the data leave open (or pin weakly) is not known: the plausible spread
            se = np.sqrt(se ** 2 + tilt_stderr(visibility, obs.resolution, p, ~tilt_free) ** 2).astype(np.float32)
        ses.append(se)
        kappas.append(kappa)
        radiances.append(np.exp(lp))
        params_out.append(p)
    lut = np.stack(luts, axis=2)
    info = {"method": "self-calibration (IRLS, Huber, joint Gauss-Newton with the radiances eliminated)",
            "grid": list(grid), "grid_chosen": grid_how, "iterations": iterations, "huber": huber, "smoothness": smoothness,
            "observations": int(len(point)), "points": n_points, "frames": n_frames,
            "centre": [[round(float(q[0]), 2), round(float(q[1]), 2)] for q in params_out],
            "polynomial": [[float(v) for v in q[2:5]] for q in params_out],
            "residual_scale_log": [float(s) for s in scales], "points_per_region": regions,
            "tilt_visibility": [round(v, 5) for v in visibility.visibility],
            "tilt_open": [bool(o) for o in visibility.open],
            "exposures_known": 0 if exposures is None else int(np.count_nonzero(
                np.all(np.isfinite(np.broadcast_to(exposures, (n_frames, obs.channels))), axis=1)))}
    ambiguity = visibility.text()
    if ambiguity:
        info["ambiguity"] = ambiguity
    weak = visibility.weak_text()
    if weak:
        info["weak_tilt"] = weak
    vign = LUTVignetting(np.clip(lut, 1e-3, 10.0).astype(np.float32), info=info,
                         stderr=np.stack(ses, axis=2).astype(np.float32))
    sightings = np.bincount(frame, minlength=n_frames)
    return SelfCalibration(vignetting=vign, exposures=np.exp(np.stack(kappas, axis=1)),
                           radiance=np.stack(radiances, axis=1), sightings=sightings, residuals_before=before,
                           residuals_after=after, coverage=coverage, info=info)


@dataclass
class _Reduced:
    """The Gauss-Newton system of one IRLS round with the radiances eliminated: ``schur`` (square, frames + V
    parameters), its right-hand side ``rhs``, the radiances' couplings ``c`` ``(P, F + nv)`` and inverse diagonal
    ``inv_l``, their gradient ``g_l``, the free unknowns ``free`` (``kappa_0`` and unseen frames held) and the V
    Jacobian ``jv`` on the position bins."""

    schur: np.ndarray
    rhs: np.ndarray
    c: np.ndarray
    inv_l: np.ndarray
    g_l: np.ndarray
    free: np.ndarray
    jv: np.ndarray


def _reduced_system(model: _LogV, p: np.ndarray, kappa: np.ndarray, lp: np.ndarray, y: np.ndarray, w: np.ndarray,
                    point: np.ndarray, frame: np.ndarray, bin_of: np.ndarray, penalty: np.ndarray, lam: float,
                    prior: tuple[np.ndarray, float], fixed: np.ndarray | None = None) -> _Reduced:
    """The normal equations of all unknowns at ``(p, kappa, lp)`` with weights ``w``, the radiances eliminated
    exactly (Schur complement)."""
    from scipy import sparse

    n_points, n_frames, n_bins = lp.size, kappa.size, model.x.size
    jv = model.jacobian(p)                                      # (bins, nv)
    nv = jv.shape[1]
    r = y - model.value(p)[bin_of] - kappa[frame] - lp[point]
    wr = w * r
    g_l = np.bincount(point, wr, minlength=n_points)
    g_k = np.bincount(frame, wr, minlength=n_frames)
    g_v = jv.T @ np.bincount(bin_of, wr, minlength=n_bins)
    reg = lam * (penalty.T @ penalty)
    g_v[5:] -= reg @ p[5:]
    g_v[:2] -= prior[1] * (p[:2] - prior[0])
    m_pf = sparse.coo_matrix((w, (point, frame)), shape=(n_points, n_frames)).tocsr()
    m_pb = sparse.coo_matrix((w, (point, bin_of)), shape=(n_points, n_bins)).tocsr()
    m_fb = sparse.coo_matrix((w, (frame, bin_of)), shape=(n_frames, n_bins)).tocsr()
    wb = np.bincount(bin_of, w, minlength=n_bins)
    d_l = np.asarray(m_pf.sum(axis=1)).ravel()
    d_k = np.asarray(m_pf.sum(axis=0)).ravel()
    c = np.hstack([m_pf.toarray(), m_pb @ jv])                 # (P, F + nv): couplings of radiances to the rest
    n_rr = np.zeros((n_frames + nv, n_frames + nv))
    n_rr[:n_frames, :n_frames] = np.diag(d_k)
    n_rr[:n_frames, n_frames:] = m_fb @ jv
    n_rr[n_frames:, :n_frames] = n_rr[:n_frames, n_frames:].T
    n_rr[n_frames:, n_frames:] = jv.T @ (jv * wb[:, None]) + np.pad(reg, ((5, 0), (5, 0)))
    n_rr[n_frames, n_frames] += np.broadcast_to(prior[1], (2,))[0]
    n_rr[n_frames + 1, n_frames + 1] += np.broadcast_to(prior[1], (2,))[1]
    inv_l = np.where(d_l > 0, 1.0 / np.maximum(d_l, 1e-300), 0.0)
    cs = c * np.sqrt(inv_l)[:, None]
    schur = n_rr - cs.T @ cs
    rhs = np.concatenate([g_k, g_v]) - c.T @ (inv_l * g_l)
    free = np.ones(n_frames + nv, bool)
    free[:n_frames] &= (d_k > 0) & ~(np.arange(n_frames) == 0 if fixed is None else fixed)
    return _Reduced(schur, rhs, c, inv_l, g_l, free, jv)


def _joint_step(model: _LogV, p: np.ndarray, kappa: np.ndarray, lp: np.ndarray, y: np.ndarray, w: np.ndarray,
                point: np.ndarray, frame: np.ndarray, bin_of: np.ndarray, penalty: np.ndarray, lam: float,
                prior: tuple[np.ndarray, float], resolution: tuple[int, int], fixed: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One Gauss-Newton step on all unknowns at once (exposures, radiances, ``V``), the radiances eliminated
    exactly (:func:`_reduced_system`), with step halving; the ``fixed`` frames' kappa (default ``kappa_0``) stay."""
    n_frames = kappa.size
    w_, h_ = resolution

    def cost(q, k, l):
        r = y - model.value(q)[bin_of] - k[frame] - l[point]
        return float(np.sum(w * r * r) + lam * np.sum((penalty @ q[5:]) ** 2)
                     + np.sum(prior[1] * (q[:2] - prior[0]) ** 2))

    red = _reduced_system(model, p, kappa, lp, y, w, point, frame, bin_of, penalty, lam, prior, fixed)
    free = red.free
    step = np.zeros(free.size)
    sub = red.schur[np.ix_(free, free)]
    sub[np.diag_indices_from(sub)] += 1e-9 * max(float(np.max(np.diag(sub))), 1.0)
    step[free] = np.linalg.solve(sub, red.rhs[free])
    step_l = red.inv_l * (red.g_l - red.c @ step)
    current = cost(p, kappa, lp)
    t = 1.0
    while t > 1e-3:
        q = p + t * step[n_frames:]
        q[0] = np.clip(q[0], -0.25 * w_, 1.25 * w_)
        q[1] = np.clip(q[1], -0.25 * h_, 1.25 * h_)
        k, l = kappa + t * step[:n_frames], lp + t * step_l
        if np.all(model.poly(q)[1] > 0.02) and cost(q, k, l) <= current:
            return q, k, l
        t *= 0.5
    return p, kappa, lp


def _covariance(model: _LogV, p: np.ndarray, kappa: np.ndarray, lp: np.ndarray, y: np.ndarray, w: np.ndarray,
                point: np.ndarray, frame: np.ndarray, bin_of: np.ndarray, penalty: np.ndarray, lam: float,
                prior: tuple[np.ndarray, float], scale: float, block: int, fixed: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Covariances (cluster-robust, model-based) of ``V``'s parameters at the solution, exposures and radiances
    marginalised (not held fixed).

    Sightings are not independent: a frame's pose error or an exposure that follows the camera's pitch moves
    many sightings of neighbouring frames alike, and a point's texture all its sightings. So the covariance is
    cluster-robust (a sandwich ``B M B``, ``B`` the inverse of the reduced normal matrix): the scores summed over
    blocks of ``block`` consecutive frames plus those summed over points, less the single sightings' part that
    both count (two-way clustering, Cameron, Gelbach & Miller 2011; each clustering scaled by ``G / (G - 1)``), and
    never below the model-based ``s^2 B`` (``s`` the robust residual scale) at any pixel.
    Measured: synthetic sightings with independent noise, 95-99 % of pixels within 2 standard errors; simulated
    rooms (true response): on the demo's room (60 frames, 320x240) the model-based error alone was 6-10x below the
    true error of ``V``, this one 1.4-1.6x (78-84 % within 2); on a 640x480 room of 100 frames 2.2x (60-67 %
    within 2): what drifts over the whole walk (a tilt of ``V`` traded against the exposures) stays understated."""
    from scipy import sparse

    red = _reduced_system(model, p, kappa, lp, y, w, point, frame, bin_of, penalty, lam, prior, fixed)
    n_frames, n_points, n_bins = kappa.size, lp.size, model.x.size
    free = red.free
    sub = red.schur[np.ix_(free, free)]
    bread = np.linalg.pinv(sub + np.eye(len(sub)) * 1e-9 * max(float(np.max(np.diag(sub))), 1.0))
    wr = w * (y - model.value(p)[bin_of] - kappa[frame] - lp[point])
    cbar = red.c * red.inv_l[:, None]                   # each point's weighted mean Jacobian (its radiance's pull)
    # scores per frame (the radiances' part projected out), then summed over blocks of consecutive frames
    by_frame = np.zeros((n_frames, free.size))
    by_frame[np.arange(n_frames), np.arange(n_frames)] = np.bincount(frame, wr, minlength=n_frames)
    by_frame[:, n_frames:] = sparse.coo_matrix((wr, (frame, bin_of)), shape=(n_frames, n_bins)).tocsr() @ red.jv
    by_frame -= sparse.coo_matrix((wr, (frame, point)), shape=(n_frames, n_points)).tocsr() @ cbar
    by_block = np.add.reduceat(by_frame[:, free], np.arange(0, n_frames, block), axis=0)
    # scores per point
    by_point = np.hstack([sparse.coo_matrix((wr, (point, frame)), shape=(n_points, n_frames)).toarray(),
                          sparse.coo_matrix((wr, (point, bin_of)), shape=(n_points, n_bins)).tocsr() @ red.jv])
    by_point = (by_point - cbar * red.g_l[:, None])[:, free]
    meat = -_sighting_meat(wr, frame, point, bin_of, red.jv, cbar, n_frames, n_bins)[np.ix_(free, free)]
    for scores in (by_block, by_point):
        g = len(scores)
        if g > 1:
            meat += g / (g - 1.0) * (scores.T @ scores)
    full = np.zeros((free.size, free.size))
    full[np.ix_(free, free)] = bread @ meat @ bread
    model_based = np.zeros_like(full)
    model_based[np.ix_(free, free)] = scale ** 2 * bread
    return full[n_frames:, n_frames:], model_based[n_frames:, n_frames:]


def _sighting_meat(wr: np.ndarray, frame: np.ndarray, point: np.ndarray, bin_of: np.ndarray, jv: np.ndarray,
                   cbar: np.ndarray, n_frames: int, n_bins: int) -> np.ndarray:
    """``sum_n (w r)_n^2 j_n j_n^T`` over single sightings (``j_n`` the sighting's Jacobian of exposures and ``V``
    less its point's mean ``cbar``): the part the frame-block and the point clusterings both count."""
    from scipy import sparse

    u = wr * wr
    n_points = cbar.shape[0]
    out = np.zeros((n_frames + jv.shape[1],) * 2)
    out[np.arange(n_frames), np.arange(n_frames)] = np.bincount(frame, u, minlength=n_frames)
    out[:n_frames, n_frames:] = sparse.coo_matrix((u, (frame, bin_of)), shape=(n_frames, n_bins)).tocsr() @ jv
    out[n_frames:, :n_frames] = out[:n_frames, n_frames:].T
    out[n_frames:, n_frames:] = jv.T @ (jv * np.bincount(bin_of, u, minlength=n_bins)[:, None])
    cross = np.vstack([sparse.coo_matrix((u, (frame, point)), shape=(n_frames, n_points)).tocsr() @ cbar,
                       jv.T @ (sparse.coo_matrix((u, (bin_of, point)), shape=(n_bins, n_points)).tocsr() @ cbar)])
    return out - cross - cross.T + cbar.T @ (cbar * np.bincount(point, u, minlength=n_points)[:, None])


def _stderr(p: np.ndarray, cov: tuple[np.ndarray, np.ndarray], resolution: tuple[int, int], grid: tuple[int, int],
            bins: int) -> np.ndarray:
    """Relative standard error of ``V`` per pixel in its gauge (``V = 1`` at the polynomial's centre):
    ``sqrt(j(x)^T cov j(x))``, ``j`` the Jacobian of ``log V(x) - log V(centre)``; the larger of the cluster-robust
    and the model-based covariance (:func:`_covariance`) at each pixel. Evaluated on ``bins`` points across the
    width and resized."""
    import cv2

    width, height = resolution
    gx = np.linspace(0, width - 1, bins)
    gy = np.linspace(0, height - 1, max(2, int(round(bins * height / width))))
    xx, yy = np.meshgrid(gx, gy)
    jac = _LogV(xx.ravel(), yy.ravel(), resolution, grid).jacobian(p)
    jac[:, 5:] -= _LogV(np.array([p[0]]), np.array([p[1]]), resolution, grid).bilinear[0]
    var = np.max([np.einsum("ij,jk,ik->i", jac, c, jac) for c in cov], axis=0)
    se = np.sqrt(np.maximum(var, 0.0)).reshape(xx.shape)
    return cv2.resize(se.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)


def _misfit(res: np.ndarray, w: np.ndarray, bin_of: np.ndarray, used: np.ndarray, shape: tuple[int, int],
            scale: float, resolution: tuple[int, int], pool: int = 4, min_weight: float = 50.0) -> np.ndarray:
    """What V's model leaves unexplained at each image position, ``(H, W)`` in log units: the weighted mean
    residual over blocks of ``pool`` x ``pool`` position bins holding at least ``min_weight`` (Huber-weighted)
    sightings, less nine times its noise variance (``scale^2 / n``: what is within three standard errors of 0
    counts as 0; pure noise passes in 0.3 % of blocks), smoothed over neighbouring blocks. A dust shadow finer
    than the grid, or a grid held smooth where sightings are thin, shows here: a standard error from the noise
    alone would not cover it."""
    import cv2

    ny, nx = shape
    sums = np.zeros(ny * nx)
    weights = np.zeros(ny * nx)
    sums[used] = np.bincount(bin_of, w * res, minlength=used.size)
    weights[used] = np.bincount(bin_of, w, minlength=used.size)
    by, bx = -(-ny // pool), -(-nx // pool)
    pad = ((0, by * pool - ny), (0, bx * pool - nx))
    s4 = np.pad(sums.reshape(ny, nx), pad).reshape(by, pool, bx, pool).sum(axis=(1, 3))
    w4 = np.pad(weights.reshape(ny, nx), pad).reshape(by, pool, bx, pool).sum(axis=(1, 3))
    mean = s4 / np.maximum(w4, 1e-12)
    bias2 = np.where(w4 >= min_weight, np.maximum(mean ** 2 - 9 * scale ** 2 / np.maximum(w4, 1e-12), 0.0), 0.0)
    smooth = cv2.GaussianBlur(bias2.astype(np.float32), (0, 0), 0.7)
    return np.sqrt(cv2.resize(smooth, tuple(resolution), interpolation=cv2.INTER_LINEAR).astype(np.float64))


def coverage_text(coverage: np.ndarray, min_samples: int = 3) -> tuple[str, list[str]]:
    """The coverage of image positions as the white-paper calibration reports it: the share of position bins
    with at least ``min_samples`` sightings, and the 3 x 3 regions with more than 5 % of their bins below."""
    below = coverage < min_samples
    h, w = below.shape
    ys, xs = [0, h // 3, h - h // 3, h], [0, w // 3, w - w // 3, w]
    thin = []
    parts = []
    for i in range(3):
        for j in range(3):
            frac = float(below[ys[i]:ys[i + 1], xs[j]:xs[j + 1]].mean())
            if frac > 0.05:
                thin.append(REGIONS[3 * i + j])
                parts.append(f"{REGIONS[3 * i + j]} {100 * frac:.0f}% below")
    head = (f"coverage: {100 * (1 - below.mean()):.1f}% of image positions ({h}x{w} bins) have >= {min_samples} "
            f"sightings (median {np.median(coverage):.0f})")
    if parts:
        head += f"; thin: {', '.join(parts)}; move the camera so that surfaces pass through these regions"
    return head, thin


__all__ = ["DEFAULT_GRID", "GRIDS", "Observations", "choose_grid", "SelfCalibration", "SelfCalibrationError", "check_constrained",
           "coverage_text", "self_calibrate"]
