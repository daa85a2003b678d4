"""Exposure control of the simulated camera: auto exposure and auto white balance, frame by frame.

:class:`AutoExposure` and :class:`AutoWhiteBalance` hold the parameters of the loops;
:class:`ExposureController` runs them as a camera does, metering each delivered frame and changing the
settings of a later one.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from radiometry.response import LEVELS, CameraResponse
from radiometry.simulation._checks import per_channel

# Rec. 601 luma weights: what a camera's metering calls "brightness"
_LUMA = np.array([0.299, 0.587, 0.114])


@dataclass(frozen=True)
class AutoExposure:
    """A camera-like auto-exposure loop.

    It meters the mean brightness (Rec. 601 luma of the 8-bit image) of the last frame, converts it
    to irradiance with the camera's (green) inverse response, and moves ``log2(k)`` a fraction
    ``smoothing`` of the way towards the exposure that would put the brightness at ``target``
    (fraction of 255), at most ``max_step_ev`` stops per frame, not at all inside ``deadband_ev``,
    clamped to ``[min_time, max_time]`` seconds. The new exposure takes effect ``latency`` frames
    after the metered one (1 = the next frame).
    """

    target: float = 0.45
    smoothing: float = 0.3
    max_step_ev: float = 0.5
    deadband_ev: float = 0.08
    min_time: float = 5e-5
    max_time: float = 1.0 / 30.0
    latency: int = 1

    def __post_init__(self) -> None:
        _check_range("target", self.target, 0.02, 0.98)
        _check_range("smoothing", self.smoothing, 1e-3, 1.0)
        _check_range("max_step_ev", self.max_step_ev, 1e-3, 10.0)
        _check_range("deadband_ev", self.deadband_ev, 0.0, 2.0)
        if not (0 < self.min_time < self.max_time and np.isfinite(self.max_time)):
            raise ValueError(f"need 0 < min_time < max_time, got min_time={self.min_time}, max_time={self.max_time}")
        if not (isinstance(self.latency, int) and 1 <= self.latency <= 10):
            raise ValueError(f"latency must be a whole number of frames in 1..10, got {self.latency!r}")


@dataclass(frozen=True)
class AutoWhiteBalance:
    """Grey-world auto white balance with a lag: per frame, ``log g_c`` moves a fraction
    ``smoothing`` towards the gains that equalise the channel means of the (pre-gain) irradiance of
    unsaturated pixels, at most ``max_step`` (natural log) per frame, green fixed at 1, gains clamped
    to ``[min_gain, max_gain]``."""

    smoothing: float = 0.1
    max_step: float = 0.05
    min_gain: float = 0.4
    max_gain: float = 3.0

    def __post_init__(self) -> None:
        _check_range("smoothing", self.smoothing, 1e-3, 1.0)
        _check_range("max_step", self.max_step, 1e-4, 2.0)
        if not (0 < self.min_gain <= 1.0 <= self.max_gain and np.isfinite(self.max_gain)):
            raise ValueError(f"need 0 < min_gain <= 1 <= max_gain, got {self.min_gain}, {self.max_gain}")


def _check_range(name: str, value: float, low: float, high: float) -> None:
    if not (isinstance(value, (int, float)) and np.isfinite(value) and low <= value <= high):
        raise ValueError(f"{name} must be a number within [{low}, {high}], got {value!r}")


class ExposureController:
    """Exposure time and white-balance gains of a camera, frame by frame.

    Use: read :attr:`exposure_time` and :attr:`gains`, capture a frame with them, then call
    :meth:`observe` with the 8-bit image; the controller updates the settings of a later frame as a
    camera's AE/AWB loop would. Without ``auto_exposure``/``auto_white_balance`` the respective
    settings stay fixed.
    """

    def __init__(self, response: CameraResponse, *, exposure_time: float, gains: Sequence[float] = (1.0, 1.0, 1.0),
                 auto_exposure: AutoExposure | None = None,
                 auto_white_balance: AutoWhiteBalance | None = None) -> None:
        if not (np.isfinite(exposure_time) and exposure_time > 0):
            raise ValueError(f"exposure_time must be a positive number of seconds, got {exposure_time!r}")
        self.response = response
        self.auto_exposure = auto_exposure
        self.auto_white_balance = auto_white_balance
        k = float(exposure_time)
        if auto_exposure is not None:
            k = float(np.clip(k, auto_exposure.min_time, auto_exposure.max_time))
        self._k = k
        self._g = per_channel(gains, "gains", 3).copy()
        self._sched_k = self._k
        self._sched_g = self._g.copy()
        self._frame = 0
        self._pending: deque[tuple[int, float, np.ndarray]] = deque()
        tables = response.channel_tables(3).astype(np.float64)
        self._tables = tables
        self._target_e = None if auto_exposure is None else float(
            np.interp(auto_exposure.target * 255.0, np.arange(LEVELS), tables[:, 1]))

    @property
    def exposure_time(self) -> float:
        return self._k

    @property
    def gains(self) -> np.ndarray:
        return self._g.copy()

    def settings(self) -> tuple[float, np.ndarray]:
        """``(exposure_time, gains (3,))`` for the next frame."""
        return self._k, self._g.copy()

    def observe(self, image: np.ndarray) -> None:
        """Meter an 8-bit RGB frame captured with the current settings and advance one frame."""
        img = np.asarray(image)
        if img.ndim != 3 or img.shape[2] != 3 or img.dtype != np.uint8:
            raise ValueError(f"image must be uint8 (H, W, 3) RGB, got {img.dtype} {img.shape}")
        step = max(1, int(min(img.shape[:2]) // 120))
        sample = img[::step, ::step].reshape(-1, 3)
        used_k, used_g = self._k, self._g
        new_k, new_g = self._sched_k, self._sched_g.copy()
        if self.auto_exposure is not None:
            new_k = self._next_exposure(sample, used_k)
        if self.auto_white_balance is not None:
            new_g = self._next_gains(sample, used_g)
        self._sched_k, self._sched_g = new_k, new_g
        latency = self.auto_exposure.latency if self.auto_exposure is not None else 1
        self._pending.append((self._frame + latency, new_k, new_g))
        self._frame += 1
        while self._pending and self._pending[0][0] <= self._frame:
            _, self._k, self._g = self._pending.popleft()

    def _next_exposure(self, sample: np.ndarray, used_k: float) -> float:
        ae = self.auto_exposure
        brightness = float(sample.astype(np.float64).mean(axis=0) @ _LUMA)
        measured = max(float(np.interp(brightness, np.arange(LEVELS), self._tables[:, 1])), 1e-6)
        error_ev = math.log2(self._target_e / measured)
        base = math.log2(self._sched_k)
        if abs(error_ev) <= ae.deadband_ev:
            return self._sched_k
        wanted = math.log2(used_k) + error_ev
        move = float(np.clip(ae.smoothing * (wanted - base), -ae.max_step_ev, ae.max_step_ev))
        return float(np.clip(2.0 ** (base + move), ae.min_time, ae.max_time))

    def _next_gains(self, sample: np.ndarray, used_g: np.ndarray) -> np.ndarray:
        awb = self.auto_white_balance
        ok = np.all((sample > 8) & (sample < 247), axis=1)
        if np.count_nonzero(ok) < 50:
            return self._sched_g.copy()
        valid = sample[ok]
        irr = np.stack([self._tables[valid[:, c], c] for c in range(3)], axis=1)
        raw = irr.mean(axis=0) / used_g
        if np.any(raw <= 0):
            return self._sched_g.copy()
        wanted = np.log(raw[1] / raw)
        base = np.log(self._sched_g)
        move = np.clip(awb.smoothing * (wanted - base), -awb.max_step, awb.max_step)
        g = np.exp(base + move)
        g[1] = 1.0
        return np.clip(g, awb.min_gain, awb.max_gain)


__all__ = ["AutoExposure", "AutoWhiteBalance", "ExposureController"]
