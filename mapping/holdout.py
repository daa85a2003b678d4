"""Held-out frames: a colour metric for real data without a ground truth (issue 16).

Every ``every``-th frame of a run (dataset positions ``every - 1``, ``2 every - 1``, ...) is withheld from
fusion: it is tracked (by the run's tracker) or given its ground-truth pose, but never integrated, never
measured by the disagreement histogram and not counted as skipped. After the run the final map, made of the
fused frames only, is rendered at each withheld frame's pose, and the colour model predicts the 8-bit image the
camera recorded there
(:meth:`mapping.colour.ColourModel.predict_observed`): the frame's exposure is fitted against the render
(per channel, the median over the valid pixels of observed / rendered, in the model's map units: irradiance
``f^-1(I) / V`` for a corrected map, levels for the raw one), and the render goes back through the camera
model, ``f(k V(x) E_map)`` or ``k * level``. The prediction is compared with the observed levels:

- ``psnr``: ``10 log10(255^2 / MSE)``, the MSE over every channel value of the valid pixels (pooled: over all
  evaluated frames' valid pixels together, not a mean of per-frame figures);
- ``l1``: the mean over valid pixels of ``sum_c |predicted - observed|`` in levels, the distance the
  disagreement histogram bins (so the two read on one scale);
- ``psnr_periphery`` and ``psnr_lowpass``: the PSNR over the valid pixels beyond :data:`PERIPHERY` of the
  half-diagonal, and of local means over :data:`LOWPASS_WINDOW`-square windows. Vignetting is a smooth field
  strongest in the corners, while the full-resolution PSNR is dominated by fine texture that a voxel map blurs
  and every method shares; these two show the low-frequency part of the error.

Valid pixels (:func:`valid_pixels`, thresholds in :data:`DEFAULTS`): the render has a surface; the observed
pixel measures irradiance (every channel in ``[dark, saturated)``, i.e. 5..249 by default); render and frame
depth agree within ``depth_tolerance`` metres plus ``depth_relative`` of the depth (an occlusion test); and
neither depth image has a discontinuity within 2 pixels (colour and depth are misregistered by a few pixels
along silhouettes). A frame with fewer than ``min_pixels`` valid pixels is not evaluated (its record says
why). The map is a low-pass image of the scene (voxels, trilinear look-ups) while the frame is sharp, so even
a perfect radiometric model leaves a residual on textured surfaces; the figures compare methods on the same
frames, not against zero.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from radiometry.errors import RadiomapError

HELD_OUT = "held out for evaluation"
DEFAULTS = {"depth_tolerance": 0.05, "depth_relative": 0.02, "dark": 5, "saturated": 250, "edge_dilation": 2,
            "min_pixels": 200}
#: the two views of the error that a low-frequency effect such as vignetting shows in (beside the full resolution):
#: pixels beyond this fraction of the half-diagonal from the image centre, and local means over square windows of
#: this side (pixels whose window is at least half valid)
PERIPHERY = 0.7
LOWPASS_WINDOW = 31

Renderer = Callable[[np.ndarray, np.ndarray, int, int], "tuple[np.ndarray, np.ndarray]"]


class HoldoutError(RadiomapError):
    """A held-out evaluation that cannot be made (a bad ``--holdout-every``)."""


def check_holdout_every(every: Any, frames: int) -> int:
    """``every`` as an int when it withholds at least one frame and fuses the others, else a one-line
    :class:`HoldoutError` naming the option and the valid range (``2 <= every < frames``)."""
    ok = isinstance(every, (int, np.integer)) and not isinstance(every, bool)
    if not ok or not 2 <= every < frames:
        if frames < 3:
            raise HoldoutError(f"--holdout-every: the run has {frames} frame(s); holding frames out needs at least 3 "
                               "(check --frames)")
        raise HoldoutError(f"--holdout-every must be a whole number in 2..{frames - 1} for {frames} frames (every "
                           f"N-th frame is withheld from fusion), got {every!r}")
    return int(every)


def is_held_out(position: int, every: int) -> bool:
    """Whether the frame at ``position`` (0-based, in the run's frame order) is withheld (``every`` 0: none)."""
    return every > 0 and (position + 1) % every == 0


@dataclass
class HoldoutFrame:
    """One withheld frame's figures: ``index`` (the dataset's frame index), ``psnr`` (dB; inf for an exact
    prediction), ``l1`` (levels, summed over channels), ``pixels`` (valid pixels), ``gain`` (the fitted
    per-channel exposure, in the model's units), ``reason`` (why it was not evaluated, else empty)."""

    index: int
    psnr: float = math.nan
    l1: float = math.nan
    pixels: int = 0
    gain: tuple[float, float, float] = (math.nan, math.nan, math.nan)
    reason: str = ""
    sse: float = field(default=0.0, repr=False)    # sum of squared errors over the channel values
    sae: float = field(default=0.0, repr=False)    # sum over pixels of sum_c |error|
    periphery: tuple[float, int] = field(default=(0.0, 0), repr=False)  # (sse, channel values) beyond PERIPHERY
    lowpass: tuple[float, int] = field(default=(0.0, 0), repr=False)    # (sse, channel values) of local means

    @property
    def psnr_periphery(self) -> float:
        """PSNR (dB) over the valid pixels beyond :data:`PERIPHERY` of the half-diagonal (NaN: none there)."""
        return _psnr(*self.periphery)

    @property
    def psnr_lowpass(self) -> float:
        """PSNR (dB) of :data:`LOWPASS_WINDOW`-square local means of prediction and observation (NaN: none)."""
        return _psnr(*self.lowpass)

    @property
    def evaluated(self) -> bool:
        return not self.reason

    def to_dict(self) -> dict:
        return {"index": self.index, "psnr": self.psnr, "l1": self.l1, "pixels": self.pixels,
                "psnr_periphery": self.psnr_periphery, "psnr_lowpass": self.psnr_lowpass,
                "gain": list(self.gain), "reason": self.reason}


@dataclass
class HoldoutResult:
    """Per-frame records and the pooled figures (``psnr``, ``l1``, ``pixels``) of :func:`evaluate_holdout`."""

    frames: list[HoldoutFrame]
    settings: dict = field(default_factory=dict)
    seconds: float = math.nan     # wall time of the evaluation (renders included)

    @property
    def evaluated(self) -> list[HoldoutFrame]:
        return [f for f in self.frames if f.evaluated]

    @property
    def pixels(self) -> int:
        return sum(f.pixels for f in self.evaluated)

    @property
    def psnr(self) -> float:
        """Pooled PSNR (dB) over every evaluated frame's valid pixels; NaN when none was evaluated."""
        return _psnr(sum(f.sse for f in self.evaluated), 3 * self.pixels)

    @property
    def l1(self) -> float:
        """Pooled mean L1 (levels, summed over channels) per valid pixel; NaN when none was evaluated."""
        n = self.pixels
        return sum(f.sae for f in self.evaluated) / n if n else math.nan

    @property
    def psnr_periphery(self) -> float:
        """Pooled PSNR (dB) over the valid pixels beyond :data:`PERIPHERY` of the half-diagonal."""
        return _psnr(sum(f.periphery[0] for f in self.evaluated), sum(f.periphery[1] for f in self.evaluated))

    @property
    def psnr_lowpass(self) -> float:
        """Pooled PSNR (dB) of :data:`LOWPASS_WINDOW`-square local means (the error a smooth field makes)."""
        return _psnr(sum(f.lowpass[0] for f in self.evaluated), sum(f.lowpass[1] for f in self.evaluated))

    def to_dict(self) -> dict:
        return {"psnr": self.psnr, "l1": self.l1, "pixels": self.pixels, "psnr_periphery": self.psnr_periphery,
                "psnr_lowpass": self.psnr_lowpass, "frames_held_out": len(self.frames),
                "frames_evaluated": len(self.evaluated), "seconds": self.seconds, "settings": dict(self.settings),
                "per_frame": [f.to_dict() for f in self.frames]}

    def csv(self, method: str | None = None) -> str:
        """``holdout.csv``: one row per withheld frame (``method`` first when given, for a comparison)."""
        head = "index,psnr_db,l1_levels,pixels,gain_r,gain_g,gain_b,psnr_periphery_db,psnr_lowpass_db,reason"
        lines = [("method," if method else "") + head]
        for f in self.frames:
            g = ",".join(f"{v:.6g}" for v in f.gain)
            reason = f.reason.replace('"', "'")
            lines.append((f"{method}," if method else "") +
                         f"{f.index},{f.psnr:.4f},{f.l1:.4f},{f.pixels},{g},{f.psnr_periphery:.4f},"
                         f"{f.psnr_lowpass:.4f},\"{reason}\"")
        return "\n".join(lines) + "\n"


def _psnr(sse: float, values: int) -> float:
    if values == 0:
        return math.nan
    mse = sse / values
    return math.inf if mse == 0 else 10.0 * math.log10(255.0 ** 2 / mse)


def valid_pixels(rgb: np.ndarray, depth: np.ndarray, render_depth: np.ndarray, *,
                 depth_tolerance: float = DEFAULTS["depth_tolerance"],
                 depth_relative: float = DEFAULTS["depth_relative"], dark: int = DEFAULTS["dark"],
                 saturated: int = DEFAULTS["saturated"], edge_dilation: int = DEFAULTS["edge_dilation"]) -> np.ndarray:
    """The pixels a held-out frame is judged on, bool (H, W) (see the module doc)."""
    from mapping.exposure_compensation.masks import depth_edges

    rgb = np.asarray(rgb)
    depth = np.asarray(depth, dtype=np.float32)
    rdepth = np.asarray(render_depth, dtype=np.float32)
    if rgb.shape[:2] != depth.shape or rdepth.shape != depth.shape:
        raise ValueError(f"rgb {rgb.shape}, depth {depth.shape} and render depth {rdepth.shape} must be the same size")
    measured = np.all((rgb >= dark) & (rgb < saturated), axis=2)
    both = (depth > 0) & (rdepth > 0) & np.isfinite(depth) & np.isfinite(rdepth)
    agree = np.abs(depth - rdepth) <= depth_tolerance + depth_relative * depth
    ok = measured & both & agree
    if edge_dilation >= 0:
        ok &= ~depth_edges(depth, dilation=edge_dilation) & ~depth_edges(rdepth, dilation=edge_dilation)
    return ok


def evaluate_holdout(frames: Sequence[Any], poses: Sequence[np.ndarray | None], render: Renderer, colour_model, *,
                     depth_tolerance: float = DEFAULTS["depth_tolerance"],
                     depth_relative: float = DEFAULTS["depth_relative"], dark: int = DEFAULTS["dark"],
                     saturated: int = DEFAULTS["saturated"], edge_dilation: int = DEFAULTS["edge_dilation"],
                     min_pixels: int = DEFAULTS["min_pixels"]) -> HoldoutResult:
    """Judge a map by the frames it was not made from.

    frames:        the withheld :class:`mapping.datasets.base.RGBDFrame` s (``rgb`` uint8, ``depth`` metres, ``K``).
    poses:         one camera-to-world (4, 4) pose per frame, or None (the frame is recorded as not evaluated).
    render:        ``render(pose, K, height, width) -> (colour (H, W, 3) float32 map units, depth (H, W) float32
                   metres, 0 where no surface)``: the final map seen from ``pose``
                   (:func:`backend_renderer` for a fusion backend; a mesh renderer for a coloured mesh).
    colour_model:  the run's :class:`mapping.colour.ColourModel` (its ``predict_observed`` fits the exposure and
                   predicts levels).
    depth_tolerance, depth_relative, dark, saturated, edge_dilation: :func:`valid_pixels`.
    min_pixels:    fewer valid pixels than this: the frame is not evaluated.
    """
    if len(frames) != len(poses):
        raise ValueError(f"frames and poses must have the same length, got {len(frames)} and {len(poses)}")
    if not (depth_tolerance >= 0 and depth_relative >= 0):
        raise ValueError(f"depth_tolerance and depth_relative must be >= 0, got {depth_tolerance}, {depth_relative}")
    if not 0 <= dark < saturated <= 256:
        raise ValueError(f"need 0 <= dark < saturated <= 256, got {dark}, {saturated}")
    settings = {"depth_tolerance_m": depth_tolerance, "depth_relative": depth_relative, "dark": dark,
                "saturated": saturated, "edge_dilation": edge_dilation, "min_pixels": min_pixels,
                "gain_fit": "per-channel median of observed / rendered over the valid pixels, in map units",
                "l1": "mean over valid pixels of sum_c |predicted - observed| (levels)",
                "psnr": "10 log10(255^2 / MSE), MSE over the channel values of the valid pixels"}
    started = time.perf_counter()
    records = []
    for frame, pose in zip(frames, poses):
        records.append(_evaluate_frame(frame, pose, render, colour_model, min_pixels,
                                       dict(depth_tolerance=depth_tolerance, depth_relative=depth_relative, dark=dark,
                                            saturated=saturated, edge_dilation=edge_dilation)))
    return HoldoutResult(records, settings, time.perf_counter() - started)


def _evaluate_frame(frame, pose, render: Renderer, colour_model, min_pixels: int, thresholds: dict) -> HoldoutFrame:
    record = HoldoutFrame(int(frame.index))
    if pose is None:
        record.reason = "no pose"
        return record
    rgb = np.asarray(frame.rgb)
    h, w = rgb.shape[:2]
    colour, rdepth = render(np.asarray(pose, dtype=np.float64), np.asarray(frame.K, dtype=np.float64), h, w)
    colour = np.asarray(colour, dtype=np.float32)
    if colour.shape != (h, w, 3) or np.shape(rdepth) != (h, w):
        raise ValueError(f"render must return colour ({h}, {w}, 3) and depth ({h}, {w}), got {colour.shape} and "
                         f"{np.shape(rdepth)}")
    valid = valid_pixels(rgb, frame.depth, rdepth, **thresholds) & np.all(colour > 0, axis=2)
    record.pixels = int(np.count_nonzero(valid))
    if record.pixels < min_pixels:
        record.reason = f"{record.pixels} valid pixels (fewer than {min_pixels})"
        record.pixels = 0
        return record
    predicted, gain = colour_model.predict_observed(colour, rgb, valid)
    record.gain = tuple(float(g) for g in np.asarray(gain, dtype=np.float64).reshape(3))
    err = np.asarray(predicted, dtype=np.float64)[valid] - rgb[valid].astype(np.float64)
    record.sse = float(np.square(err).sum())
    record.sae = float(np.abs(err).sum())
    record.psnr = _psnr(record.sse, err.size)
    record.l1 = record.sae / record.pixels
    outer = valid & (_radius(h, w) > PERIPHERY)
    diff = np.asarray(predicted, dtype=np.float64)[outer] - rgb[outer].astype(np.float64)
    record.periphery = (float(np.square(diff).sum()), int(diff.size))
    record.lowpass = _lowpass_error(np.asarray(predicted, dtype=np.float64), rgb.astype(np.float64), valid)
    return record


def _radius(h: int, w: int) -> np.ndarray:
    """Distance of each pixel centre from the image centre, as a fraction of the half-diagonal, (H, W)."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    return np.hypot(x - (w - 1) / 2, y - (h - 1) / 2) / (0.5 * math.hypot(w, h))


def _lowpass_error(predicted: np.ndarray, observed: np.ndarray, valid: np.ndarray) -> tuple[float, int]:
    """``(sse, channel values)`` of the difference between :data:`LOWPASS_WINDOW`-square means of prediction and
    observation over the valid pixels, at valid pixels whose window is at least half valid."""
    import cv2

    k = (LOWPASS_WINDOW, LOWPASS_WINDOW)
    m = valid.astype(np.float64)
    count = cv2.boxFilter(m, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    keep = valid & (count >= 0.5 * LOWPASS_WINDOW ** 2)
    if not keep.any():
        return 0.0, 0
    diff = (predicted - observed) * m[..., None]
    sums = cv2.boxFilter(diff, -1, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    local = sums[keep] / count[keep][:, None]
    return float(np.square(local).sum()), int(local.size)


def backend_renderer(backend) -> Renderer:
    """``render`` for :func:`evaluate_holdout` from a :class:`mapping.fusion.base.FusionBackend`."""
    def render(pose: np.ndarray, K: np.ndarray, height: int, width: int):
        view = backend.render(pose, K, height, width)
        return view.colour, view.depth

    return render


def fit_gain(observed: np.ndarray, rendered: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per-channel exposure of a frame against a render, float64 (3,): the median over ``valid`` pixels (where
    the render is positive) of ``observed / rendered``, both (H, W, 3) in the same units."""
    obs = np.asarray(observed, dtype=np.float64)[valid]
    ren = np.asarray(rendered, dtype=np.float64)[valid]
    gain = np.full(3, np.nan)
    for c in range(3):
        ok = ren[:, c] > 0
        if ok.any():
            gain[c] = np.median(obs[ok, c] / ren[ok, c])
    return gain


__all__ = ["DEFAULTS", "HELD_OUT", "LOWPASS_WINDOW", "PERIPHERY", "HoldoutError", "HoldoutFrame", "HoldoutResult",
           "Renderer", "backend_renderer", "check_holdout_every", "evaluate_holdout", "fit_gain", "is_held_out",
           "valid_pixels"]
