"""Self-validation of a self-calibration: does V predict frames it was not fitted on better than no V?

The frames are split (:func:`holdout_frames`: every N-th frame, or a final block); the solver sees only the
sightings of the others. Each withheld frame is then predicted from what the fit learned: a sighting of point ``i``
at pixel ``x`` in withheld frame ``j`` is predicted as ``k_j V(x) L_i`` (``L_i`` from the fitted frames, ``k_j``
the median ratio over the frame's own sightings: one number per frame and channel from hundreds of sightings),
and the same without V (``V = 1``, the radiances refitted without it). Both predictions go back through the
response to 8-bit levels and are compared with what the camera recorded: L1 (mean absolute level difference) and
PSNR, per channel. V "helps" when it lowers the mean L1 over the channels; when it does not, V should not be used
(a V fitted to what moves with the camera, a wrong response, too little motion).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from radiometry.self_calibration import Observations, SelfCalibration
from radiometry.self_calibration_lsq import exposures_and_radiance as _exposures_and_radiance

#: the default split: every 5th frame withheld
DEFAULT_HOLDOUT = "every:5"
_SPEC = re.compile(r"^(?:(none)|every:(\d+)|last:(\d+(?:\.\d+)?)%)$")


def parse_holdout(spec: str) -> tuple[str, float]:
    """``"every:N"`` (N >= 2), ``"last:P%"`` (0 < P <= 50) or ``"none"`` as ``(kind, number)``; ValueError
    naming the accepted forms otherwise."""
    m = _SPEC.match(str(spec).strip().lower())
    bad = ValueError(f"holdout must be 'every:N' (N >= 2: every N-th frame withheld), 'last:P%' (0 < P <= 50: "
                     f"the final P % of the frames) or 'none', got {spec!r}")
    if not m:
        raise bad
    if m.group(1):
        return "none", 0.0
    if m.group(2):
        n = int(m.group(2))
        if n < 2:
            raise bad
        return "every", float(n)
    p = float(m.group(3))
    if not 0 < p <= 50:
        raise bad
    return "last", p


def holdout_frames(n_frames: int, spec: str = DEFAULT_HOLDOUT) -> np.ndarray:
    """Bool ``(n_frames,)``: the frames withheld by ``spec`` (:func:`parse_holdout`); frame 0 (the exposures'
    reference) is never withheld; none when fewer than 6 frames."""
    kind, number = parse_holdout(spec)
    held = np.zeros(n_frames, bool)
    if kind == "none" or n_frames < 6:
        return held
    if kind == "every":
        held[int(number) - 1::int(number)] = True
    else:
        held[n_frames - max(1, int(round(n_frames * number / 100.0))):] = True
    held[0] = False
    return held


def subset(obs: Observations, keep: np.ndarray) -> Observations:
    """The sightings ``keep`` (bool ``(N,)``) of ``obs``; point numbers and frames unchanged."""
    return Observations(point=obs.point[keep], frame=obs.frame[keep], x=obs.x[keep], y=obs.y[keep],
                        irradiance=obs.irradiance[keep], resolution=obs.resolution, n_frames=obs.n_frames)


@dataclass(frozen=True)
class Validation:
    """Held-out prediction of the withheld frames (module doc): per channel L1 (levels) and PSNR (dB) with and
    without V; ``helps``: V lowers the mean L1."""

    frames: int
    sightings: int
    l1_without: tuple[float, ...]
    l1_with: tuple[float, ...]
    psnr_without: tuple[float, ...]
    psnr_with: tuple[float, ...]
    how: str
    exposures: np.ndarray      # (F, C) k of the withheld frames as predicted with V (NaN elsewhere)

    @property
    def helps(self) -> bool:
        return float(np.mean(self.l1_with)) < float(np.mean(self.l1_without))

    def as_dict(self) -> dict:
        return {"withheld_frames": self.frames, "sightings": self.sightings, "holdout": self.how,
                "l1_without_v": [round(v, 3) for v in self.l1_without], "l1_with_v": [round(v, 3) for v in self.l1_with],
                "psnr_without_v": [round(v, 2) for v in self.psnr_without],
                "psnr_with_v": [round(v, 2) for v in self.psnr_with], "v_helps": self.helps}

    def text(self) -> str:
        a, b = float(np.mean(self.l1_without)), float(np.mean(self.l1_with))
        pa, pb = float(np.mean(self.psnr_without)), float(np.mean(self.psnr_with))
        return (f"validation on {self.frames} withheld frames ({self.how}, {self.sightings} sightings): L1 "
                f"{a:.2f} -> {b:.2f} levels, PSNR {pa:.2f} -> {pb:.2f} dB without -> with V ("
                f"{'V helps' if self.helps else 'V does NOT help'}; per channel L1 "
                + ", ".join(f"{ch} {x:.2f}->{y:.2f}" for ch, x, y in zip("RGB", self.l1_without, self.l1_with)) + ")")


def _levels(e: np.ndarray, table: np.ndarray) -> np.ndarray:
    return np.interp(e, table, np.arange(table.size, dtype=np.float64))


def validate(result: SelfCalibration, train: Observations, test: Observations, tables: np.ndarray,
             how: str = DEFAULT_HOLDOUT) -> Validation | None:
    """Predict ``test``'s sightings (withheld frames) from ``result`` fitted on ``train`` (module doc); ``tables``
    the inverse response ``(256, C)``. None when no withheld sighting is of a point seen at least twice in the
    fitted frames."""
    counts = np.bincount(train.point, minlength=max(train.n_points, test.n_points))
    use = counts[test.point] >= 2
    if not use.any():
        return None
    point, frame = test.point[use], test.frame[use]
    w, h = test.resolution
    xi = np.clip(np.rint(test.x[use]).astype(np.int64), 0, w - 1)
    yi = np.clip(np.rint(test.y[use]).astype(np.int64), 0, h - 1)
    v = result.vignetting.evaluate(h, w)
    n_frames = test.n_frames
    l1a, l1b, pa, pb = [], [], [], []
    held_k = np.full((n_frames, test.channels), np.nan)
    for c in range(test.channels):
        e = test.irradiance[use, c]
        observed = _levels(e, tables[:, c])
        # without V: radiances from the fitted frames with V = 1
        _, lp0 = _exposures_and_radiance(np.log(train.irradiance[:, c]), np.ones(len(train.point)), train.point,
                                         train.frame, max(train.n_points, test.n_points), n_frames)
        lp1 = np.log(np.maximum(result.radiance[:, c], 1e-300))
        out = []
        for log_l, log_v in ((lp0[point], 0.0), (lp1[point], np.log(np.maximum(v[yi, xi, c], 1e-6)))):
            pred_log = log_v + log_l
            ratio = np.log(e) - pred_log
            k = np.zeros(n_frames)
            for j in np.unique(frame):
                k[j] = np.median(ratio[frame == j])
            predicted = _levels(np.exp(pred_log + k[frame]), tables[:, c])
            diff = predicted - observed
            out.append((float(np.mean(np.abs(diff))), float(10 * np.log10(255.0 ** 2 / max(np.mean(diff ** 2), 1e-12)))))
        held = np.unique(frame)
        held_k[held, c] = np.exp(k[held])
        l1a.append(out[0][0])
        l1b.append(out[1][0])
        pa.append(out[0][1])
        pb.append(out[1][1])
    return Validation(len(np.unique(frame)), int(use.sum()), tuple(l1a), tuple(l1b), tuple(pa), tuple(pb), how, held_k)


__all__ = ["DEFAULT_HOLDOUT", "Validation", "holdout_frames", "parse_holdout", "subset", "validate"]
