"""Self-validation of a self-calibration: does V predict frames it was not fitted on better than no V?

The frames are split (:func:`holdout_frames`: every N-th frame, or a final block); the solver sees only the
sightings of the others. Each withheld frame is then predicted from what the fit learned: a sighting of point ``i``
at pixel ``x`` in withheld frame ``j`` is predicted as ``k_j V(x) L_i`` (``L_i`` from the fitted frames, ``k_j``
the median ratio over the frame's own sightings: one number per frame and channel from hundreds of sightings),
and the same without V (``V = 1``, the radiances refitted without it). Both predictions go back through the
response to 8-bit levels and are compared with what the camera recorded: L1 (mean absolute level difference) and
PSNR, per channel. The verdict reads both means over the channels, each against its noise (the standard error of
the change, clustered by withheld frame: the sightings of one frame share its errors): V "helps" when at least one
figure improves and neither gets worse beyond its noise; "mixed" when one improves and the other gets worse beyond
its noise (e.g. L1 lower, PSNR lower by 0.8 dB: V fits most sightings better and some much worse); otherwise V
"does not help". Only "helps" means V may be used (a V that does not help: fitted to what moves with the camera, a
wrong response, too little motion).
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
    without V; ``l1_noise`` / ``psnr_noise``: the standard error of the change of the channels' mean L1 / PSNR;
    ``verdict``: ``"helps"``, ``"mixed"`` or ``"does not help"`` (module doc); ``helps``: the verdict is "helps"."""

    frames: int
    sightings: int
    l1_without: tuple[float, ...]
    l1_with: tuple[float, ...]
    psnr_without: tuple[float, ...]
    psnr_with: tuple[float, ...]
    how: str
    exposures: np.ndarray      # (F, C) k of the withheld frames as predicted with V (NaN elsewhere)
    l1_noise: float = 0.0
    psnr_noise: float = 0.0

    def _changes(self) -> tuple[float, float]:
        """(L1 gain in levels, PSNR gain in dB) of V, each positive when V is better."""
        return (float(np.mean(self.l1_without)) - float(np.mean(self.l1_with)),
                float(np.mean(self.psnr_with)) - float(np.mean(self.psnr_without)))

    @property
    def verdict(self) -> str:
        l1, psnr = self._changes()
        if l1 > 0 and psnr > 0:
            return "helps"
        if l1 <= 0 and psnr <= 0:
            return "does not help"
        worse_beyond_noise = -l1 > self.l1_noise if l1 <= 0 else -psnr > self.psnr_noise
        return "mixed" if worse_beyond_noise else "helps"

    @property
    def helps(self) -> bool:
        return self.verdict == "helps"

    def verdict_text(self) -> str:
        """"V helps", "V does NOT help" or "mixed: L1 better, PSNR worse by 0.83 dB, beyond its noise of 0.70 dB"."""
        verdict = self.verdict
        if verdict != "mixed":
            return "V helps" if verdict == "helps" else "V does NOT help"
        l1, psnr = self._changes()
        if l1 > 0:
            return f"mixed: L1 better, PSNR worse by {-psnr:.2f} dB, beyond its noise of {self.psnr_noise:.2f} dB"
        return f"mixed: PSNR better, L1 worse by {-l1:.2f} levels, beyond its noise of {self.l1_noise:.2f} levels"

    def as_dict(self) -> dict:
        return {"withheld_frames": self.frames, "sightings": self.sightings, "holdout": self.how,
                "l1_without_v": [round(v, 3) for v in self.l1_without], "l1_with_v": [round(v, 3) for v in self.l1_with],
                "psnr_without_v": [round(v, 2) for v in self.psnr_without],
                "psnr_with_v": [round(v, 2) for v in self.psnr_with], "l1_noise": round(self.l1_noise, 3),
                "psnr_noise": round(self.psnr_noise, 3), "verdict": self.verdict, "v_helps": self.helps}

    def text(self) -> str:
        a, b = float(np.mean(self.l1_without)), float(np.mean(self.l1_with))
        pa, pb = float(np.mean(self.psnr_without)), float(np.mean(self.psnr_with))
        return (f"validation on {self.frames} withheld frames ({self.how}, {self.sightings} sightings): L1 "
                f"{a:.2f} -> {b:.2f} levels, PSNR {pa:.2f} -> {pb:.2f} dB without -> with V ("
                f"{self.verdict_text()}; per channel L1 "
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
    l1_change, psnr_change = np.zeros(len(point)), np.zeros(len(point))     # per sighting, summed over channels
    held_k = np.full((n_frames, test.channels), np.nan)
    for c in range(test.channels):
        e = test.irradiance[use, c]
        observed = _levels(e, tables[:, c])
        # without V: radiances from the fitted frames with V = 1
        _, lp0 = _exposures_and_radiance(np.log(train.irradiance[:, c]), np.ones(len(train.point)), train.point,
                                         train.frame, max(train.n_points, test.n_points), n_frames)
        lp1 = np.log(np.maximum(result.radiance[:, c], 1e-300))
        out, diffs = [], []
        for log_l, log_v in ((lp0[point], 0.0), (lp1[point], np.log(np.maximum(v[yi, xi, c], 1e-6)))):
            pred_log = log_v + log_l
            ratio = np.log(e) - pred_log
            k = np.zeros(n_frames)
            for j in np.unique(frame):
                k[j] = np.median(ratio[frame == j])
            predicted = _levels(np.exp(pred_log + k[frame]), tables[:, c])
            diff = predicted - observed
            diffs.append(diff)
            out.append((float(np.mean(np.abs(diff))), float(10 * np.log10(255.0 ** 2 / max(np.mean(diff ** 2), 1e-12)))))
        l1_change += np.abs(diffs[0]) - np.abs(diffs[1])
        # PSNR gain in dB to first order: 10 / ln 10 * (MSE_without - MSE_with) / MSE, per sighting
        psnr_change += 10 / np.log(10) * (diffs[0] ** 2 / max(np.mean(diffs[0] ** 2), 1e-12)
                                          - diffs[1] ** 2 / max(np.mean(diffs[1] ** 2), 1e-12))
        held = np.unique(frame)
        held_k[held, c] = np.exp(k[held])
        l1a.append(out[0][0])
        l1b.append(out[1][0])
        pa.append(out[0][1])
        pb.append(out[1][1])
    channels = test.channels
    return Validation(len(np.unique(frame)), int(use.sum()), tuple(l1a), tuple(l1b), tuple(pa), tuple(pb), how, held_k,
                      _clustered_stderr(l1_change / channels, frame), _clustered_stderr(psnr_change / channels, frame))


def _clustered_stderr(values: np.ndarray, cluster: np.ndarray) -> float:
    """Standard error of ``values.mean()`` with the sightings of one frame correlated (cluster-robust); 0 with
    fewer than two clusters."""
    ids, inverse = np.unique(cluster, return_inverse=True)
    if ids.size < 2:
        return 0.0
    sums = np.bincount(inverse, weights=values - values.mean(), minlength=ids.size)
    return float(np.sqrt(ids.size / (ids.size - 1) * np.sum(sums ** 2)) / values.size)


__all__ = ["DEFAULT_HOLDOUT", "Validation", "holdout_frames", "parse_holdout", "subset", "validate"]
