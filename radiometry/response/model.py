"""Camera response function (CRF) model.

:class:`CameraResponse` holds the inverse response ``f^-1`` as a table of 256 relative irradiance
values per channel (1 or 3 channels, RGB order). Convention: strictly increasing, finite, ``>= 0``,
and normalised so that ``f^-1(255) = 1`` in every channel (the absolute scale of irradiance is not
observable from images; a per-channel scale is a white-balance gain and is absorbed by exposure).

``inverse(I)`` maps intensities to relative irradiance (a table look-up for integers, linear
interpolation between levels for floats); ``forward(E)`` maps irradiance back to intensity by
interpolating the table, so ``forward(inverse(I)) == I`` for every level.

Fitting lives in :mod:`radiometry.response.fit`; foreign formats in :mod:`radiometry.formats`.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import CalibrationFileError, ModelMismatchError
from radiometry.fileio import check_model_suffix, load_model_file, save_model_file

LEVELS = 256
KIND = "response"


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) undone: encoded values in ``[0, 1]`` to linear light
    (float64)."""
    v = np.asarray(values, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def validate_inverse_table(table: np.ndarray, *, source: str = "inverse response") -> np.ndarray:
    """Check an inverse-response table; return it as float64 ``(256, C)``.

    Raises :class:`CalibrationFileError` naming ``source`` for wrong shape, NaN/inf, negative or
    non-increasing values.
    """
    table = np.asarray(table)
    if table.ndim == 1:
        table = table[:, None]
    if table.ndim != 2 or table.shape[0] != LEVELS or table.shape[1] not in (1, 3):
        raise CalibrationFileError(
            f"{source}: expected 256 values for 1 or 3 channels, got shape {tuple(np.shape(table))}; "
            "re-create the response")
    if not np.issubdtype(table.dtype, np.number):
        raise CalibrationFileError(f"{source}: values are not numbers ({table.dtype}); re-create the response")
    table = table.astype(np.float64)
    if not np.all(np.isfinite(table)):
        raise CalibrationFileError(f"{source}: contains NaN or infinite values; re-create the response")
    if np.any(table < 0):
        raise CalibrationFileError(f"{source}: contains negative irradiance; re-create the response")
    steps = np.diff(table, axis=0)
    if np.any(steps <= 0):
        level = int(np.argwhere(steps <= 0)[0, 0]) + 1
        raise CalibrationFileError(
            f"{source}: not strictly increasing (at level {level}); a response must be monotone, "
            "re-calibrate or repair it with CameraResponse.from_table(..., repair=True)")
    return table


def repair_monotone(table: np.ndarray, *, min_step: float = 1e-6) -> np.ndarray:
    """Make a table strictly increasing: clip negatives, take the running maximum, then enforce a minimum
    step of ``min_step`` times the channel's range. Documented repair for fits that wiggle at the ends."""
    table = np.array(table, dtype=np.float64, copy=True)
    if table.ndim == 1:
        table = table[:, None]
    table = np.nan_to_num(table, nan=0.0, posinf=0.0, neginf=0.0)
    table = np.maximum(table, 0.0)
    out = np.maximum.accumulate(table, axis=0)
    rng = np.maximum(out[-1] - out[0], 1e-12)
    step = min_step * rng
    for c in range(out.shape[1]):
        for i in range(1, LEVELS):
            if out[i, c] < out[i - 1, c] + step[c]:
                out[i, c] = out[i - 1, c] + step[c]
    return out


def relative_stderr(response: "CameraResponse", channels: int | None = None) -> np.ndarray | None:
    """A response's own relative standard error of ``f^-1`` per level (``meta["inverse_stderr"]``, ``(256,)`` or
    ``(256, C)``, as the Debevec and loglog fits record it) as float64 ``(256, channels)`` (default: the
    response's channel count); None when it carries none or an unusable one (wrong shape, NaN, negative)."""
    given = response.meta.get("inverse_stderr")
    if given is None:
        return None
    channels = response.channels if channels is None else channels
    try:
        arr = np.asarray(given, dtype=np.float64).reshape(LEVELS, -1)
    except (TypeError, ValueError):
        return None
    if arr.shape[1] not in (1, channels) or not np.all(np.isfinite(arr)) or np.any(arr < 0):
        return None
    return np.repeat(arr, channels, axis=1) if arr.shape[1] == 1 else arr


def level_width(response: "CameraResponse", channels: int | None = None) -> np.ndarray:
    """The relative width of each 8-bit level in ``f^-1``, as a standard uncertainty: ``f^-1'(z) / (sqrt(12)
    f^-1(z))`` per level, float64 ``(256, channels)``, at most 1 (level 0, where ``f^-1`` may be 0: level 1's).

    A fit maps a level to the mean exposure of the pixels that read it, which lies anywhere in the level's span
    depending on how the scene's irradiances and the noise fall in it; on simulated clean stacks the fits' errors
    were of this size (docs/calibration_pipelines.md), far above the pixels' noise that :func:`relative_stderr`
    states."""
    channels = response.channels if channels is None else channels
    tables = response.channel_tables(channels).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        width = np.gradient(tables, axis=0) / (np.sqrt(12.0) * tables)
    width[0] = np.where(tables[0] > 0, width[0], width[1])
    return np.minimum(np.where(np.isfinite(width) & (width >= 0), width, 1.0), 1.0)


def relative_uncertainty(response: "CameraResponse", channels: int | None = None) -> np.ndarray | None:
    """The relative standard uncertainty of ``f^-1`` per level that radiomap states for a fitted response (the
    response plot's band, the response part of a vignetting calibration's error budget): its own standard error
    (:func:`relative_stderr`, the pixels' noise) and the levels' 8-bit width (:func:`level_width`) in quadrature,
    float64 ``(256, channels)``; None when the response carries no standard error. Still not in it: the bias that
    noise on the levels (JPEG, processing after the response) puts on a fit, the rounding of sharp bends and the
    extrapolation past the declared levels."""
    se = relative_stderr(response, channels)
    return None if se is None else np.hypot(se, level_width(response, se.shape[1]))


@dataclass(frozen=True, eq=False)
class CameraResponse:
    """Inverse camera response: ``inverse_table[I, c] = f_c^-1(I)``, normalised to 1 at I = 255."""

    inverse_table: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        table = validate_inverse_table(self.inverse_table)
        table = table / table[-1]
        table.setflags(write=False)
        object.__setattr__(self, "inverse_table", table)
        object.__setattr__(self, "meta", dict(self.meta))
        lut32 = table.astype(np.float32)
        lut32.setflags(write=False)
        object.__setattr__(self, "_lut32", lut32)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_table(cls, table: np.ndarray, *, repair: bool = False, **meta: Any) -> "CameraResponse":
        """Build from any positive scale of ``f^-1``; ``repair=True`` applies :func:`repair_monotone`."""
        if repair:
            table = repair_monotone(table)
            meta.setdefault("repaired", True)
        return cls(np.asarray(table, dtype=np.float64), meta)

    @classmethod
    def from_log_table(cls, g: np.ndarray, *, repair: bool = False, **meta: Any) -> "CameraResponse":
        """Build from Debevec's ``g = ln f^-1`` (any additive gauge)."""
        g = np.asarray(g, dtype=np.float64)
        if g.ndim == 1:
            g = g[:, None]
        return cls.from_table(np.exp(g - g[-1]), repair=repair, **meta)

    @classmethod
    def linear(cls, channels: int = 3) -> "CameraResponse":
        """The identity response ``f^-1(I) = I / 255`` (a linear camera); level 0 maps to 0."""
        table = np.repeat((np.arange(LEVELS) / 255.0)[:, None], channels, axis=1)
        return cls(table, {"method": "linear"})

    @classmethod
    def gamma(cls, gamma: float = 2.2, channels: int = 3) -> "CameraResponse":
        """The gamma-like response ``f^-1(I) = (I / 255) ** gamma``: the documented default assumption
        for cameras whose response is unknown (sRGB is close to gamma 2.2)."""
        if not (gamma > 0 and np.isfinite(gamma)):
            raise ValueError(f"gamma must be a positive number, got {gamma}")
        table = np.repeat(((np.arange(LEVELS) / 255.0) ** gamma)[:, None], channels, axis=1)
        return cls(table, {"method": "gamma", "gamma": float(gamma)})

    # ---------------------------------------------------------------- properties
    @property
    def channels(self) -> int:
        return int(self.inverse_table.shape[1])

    def channel_tables(self, channels: int) -> np.ndarray:
        """The float32 table broadcast to ``channels`` columns (a 1-channel response serves 3 channels)."""
        if self.channels == channels:
            return self._lut32
        if self.channels == 1:
            return np.repeat(self._lut32, channels, axis=1)
        raise ModelMismatchError(
            f"the response has {self.channels} channels but the image has {channels}; "
            "use a response calibrated for this camera's channel count")

    def _channels_of(self, shape: tuple[int, ...]) -> int:
        if self.channels == 1 and (len(shape) < 3 or shape[-1] not in (1, 3)):
            return 1
        if len(shape) >= 1 and shape[-1] in (1, 3):
            return shape[-1]
        raise ModelMismatchError(
            f"image of shape {shape} has no channel axis of size {self.channels}; "
            "pass (..., 3) RGB or (..., 1) images, or a 1-channel response for grayscale")

    # ---------------------------------------------------------------- evaluation
    def inverse(self, intensity: np.ndarray) -> np.ndarray:
        """Intensity (uint8, uint16 scaled to 8 bits is not accepted: pass levels 0..255) -> relative
        irradiance, float32 of the same shape. Integer input is a table look-up; float input is
        clipped to [0, 255] and interpolated linearly between levels."""
        arr = np.asarray(intensity)
        channels = self._channels_of(arr.shape)
        tables = self.channel_tables(channels)
        if arr.dtype == np.uint8:
            if channels == 1 and (arr.ndim < 3 or arr.shape[-1] != 1):
                return tables[:, 0][arr]
            out = np.empty(arr.shape, dtype=np.float32)
            for c in range(channels):
                out[..., c] = tables[:, c][arr[..., c]]
            return out
        if np.issubdtype(arr.dtype, np.integer):
            if arr.size and (arr.min() < 0 or arr.max() > 255):
                raise ValueError(f"intensity must be within 0..255, got values in [{arr.min()}, {arr.max()}]")
            return self.inverse(arr.astype(np.uint8))
        if not np.issubdtype(arr.dtype, np.floating):
            raise TypeError(f"intensity must be an integer or float array, got {arr.dtype}")
        x = np.clip(np.nan_to_num(arr.astype(np.float32), nan=0.0), 0.0, 255.0)
        lo = np.minimum(np.floor(x).astype(np.intp), LEVELS - 2)
        t = x - lo
        out = np.empty(arr.shape, dtype=np.float32)
        if channels == 1 and (arr.ndim < 3 or arr.shape[-1] != 1):
            tab = tables[:, 0]
            return (tab[lo] * (1 - t) + tab[lo + 1] * t).astype(np.float32)
        for c in range(channels):
            tab = tables[:, c]
            lc, tc = lo[..., c], t[..., c]
            out[..., c] = tab[lc] * (1 - tc) + tab[lc + 1] * tc
        return out

    def forward(self, irradiance: np.ndarray, *, dtype: type | np.dtype = np.float32) -> np.ndarray:
        """Relative irradiance -> intensity, interpolated between levels and clipped to [0, 255].

        ``dtype=np.float32`` (default) keeps fractional levels; ``dtype=np.uint8`` rounds. Irradiance
        above ``f^-1(255) = 1`` saturates at 255, below ``f^-1(0)`` clips to 0.
        """
        arr = np.asarray(irradiance, dtype=np.float32)
        channels = self._channels_of(arr.shape)
        tables = self.channel_tables(channels)
        levels = np.arange(LEVELS, dtype=np.float32)
        arr = np.nan_to_num(arr, nan=0.0, posinf=np.float32(np.finfo(np.float32).max), neginf=0.0)
        if channels == 1 and (arr.ndim < 3 or arr.shape[-1] != 1):
            out = np.interp(arr, tables[:, 0], levels).astype(np.float32)
        else:
            out = np.empty(arr.shape, dtype=np.float32)
            for c in range(channels):
                out[..., c] = np.interp(arr[..., c], tables[:, c], levels)
        if np.dtype(dtype) == np.uint8:
            return np.clip(np.rint(out), 0, 255).astype(np.uint8)
        return out.astype(dtype, copy=False)

    # ---------------------------------------------------------------- persistence
    def save(self, path: str | os.PathLike) -> Path:
        """Write the response in radiomap's model format (``.npz``, no pickle), atomically; ValueError for another
        suffix, naming its writer (``radiometry.formats.crf.write_radical_crf``, ``...pcalib.write_pcalib``)."""
        path = check_model_suffix(path, "CameraResponse", {
            ".crf": "radiometry.formats.crf.write_radical_crf(path, response)",
            ".txt": "radiometry.formats.pcalib.write_pcalib(path, response) (DSO pcalib)"})
        return save_model_file(path, KIND, {"inverse_table": self.inverse_table},
                               {"channels": self.channels, "levels": LEVELS, "normalisation": "f^-1(255)=1",
                                "info": self.meta})

    @classmethod
    def load(cls, path: str | os.PathLike) -> "CameraResponse":
        """Read a response file; rejects wrong kind, NaN, non-monotone or wrong-shape content."""
        meta, arrays = load_model_file(path, KIND)
        if "inverse_table" not in arrays:
            raise CalibrationFileError(f"{path}: no 'inverse_table' entry; re-create the response file")
        table = validate_inverse_table(arrays["inverse_table"], source=str(path))
        info = meta.get("info", {})
        return cls(table, info if isinstance(info, dict) else {})

    def __repr__(self) -> str:
        method = self.meta.get("method", "?")
        return f"CameraResponse(channels={self.channels}, method={method!r})"
