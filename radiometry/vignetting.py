"""Vignetting models: a per-pixel look-up table and the radial polynomial of Alexandrov et al.

``V(x)`` is the attenuation of irradiance at pixel ``x`` relative to the optical centre, per colour
channel (RGB order), float32 ``(H, W, C)`` with ``C`` in {1, 3}. Every model

- knows the resolution it was calibrated at (``resolution = (width, height)``) and evaluates ``V`` at
  any resolution of the same aspect ratio (``evaluate(height, width)``); a different aspect ratio is a
  :class:`~radiometry.errors.ModelMismatchError` (a cropped image needs a model calibrated on crops);
- is immutable, validated on construction (finite, strictly positive ``V``, consistent shapes), and
  saved/loaded in radiomap's versioned model format (:mod:`radiometry.fileio`, kind ``"vignetting"``,
  ``meta["model"]`` in {"lut", "polynomial"}).

Pixel coordinates follow OpenCV: the centre of pixel (column ``x``, row ``y``) is at ``(x, y)``, so the
image centre is ``((W - 1) / 2, (H - 1) / 2)``. Evaluating at another resolution maps pixel centres
to pixel centres: ``x_cal = (x + 0.5) * W_cal / W - 0.5`` (the same convention as ``cv2.resize``).

Polynomial: ``V_c(x) = scale_c * (1 + b1 r^2 + b2 r^4 + b3 r^6)`` with ``r = |x - centre_c| / R`` and
``R`` the half-diagonal of the calibration image, ``0.5 * sqrt(W^2 + H^2)``, so that ``b`` does not
depend on the resolution (``r = 1`` at the corners for a centred model, as in lensfun). radical stores
``b`` per squared pixel instead; :mod:`radiometry.formats.vgn` converts.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from radiometry.errors import CalibrationFileError, ModelMismatchError
from radiometry.fileio import check_model_suffix, load_model_file, save_model_file

KIND = "vignetting"
# V above this is not vignetting but corrupt data (a gain of 1/V would also be meaningless)
MAX_V = 1000.0
# V below this is a numerical accident, not a lens (1/V overflows the correction; DSO's 16-bit files reach 1.5e-5)
MIN_V = 1e-6


def read_model_file(path: str | os.PathLike, kind: str) -> tuple[dict, dict[str, np.ndarray]]:
    """:func:`radiometry.fileio.load_model_file` (kept as the name this module's loaders call)."""
    return load_model_file(path, kind)


def _as_resolution(resolution: Any) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in resolution)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"resolution must be (width, height), got {resolution!r}") from None
    if width < 1 or height < 1:
        raise ValueError(f"resolution must be positive (width, height), got {resolution!r}")
    return width, height


def same_aspect_ratio(size_a: tuple[int, int], size_b: tuple[int, int]) -> bool:
    """Whether two (width, height) sizes have the same aspect ratio, allowing one pixel of rounding.

    ``(640, 480)`` matches ``(320, 240)`` and ``(321, 241)`` (odd pixel counts after halving), not
    ``(640, 360)``.
    """
    (wa, ha), (wb, hb) = size_a, size_b
    # height of b predicted from its width at a's aspect ratio, and vice versa
    return abs(wb * ha / wa - hb) <= 1.0 or abs(hb * wa / ha - wb) <= 1.0


def calibration_coordinates(height: int, width: int,
                            resolution: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre coordinates of a ``height x width`` grid expressed at the calibration resolution.

    Returns ``xs (width,)`` and ``ys (height,)`` float64 (``x_cal = (x + 0.5) * W_cal / W - 0.5``).
    """
    wc, hc = resolution
    xs = (np.arange(width, dtype=np.float64) + 0.5) * (wc / width) - 0.5
    ys = (np.arange(height, dtype=np.float64) + 0.5) * (hc / height) - 0.5
    return xs, ys


def half_diagonal(resolution: tuple[int, int]) -> float:
    """``R = 0.5 * sqrt(W^2 + H^2)``: the radius that normalises ``r`` in the polynomial model."""
    w, h = resolution
    return 0.5 * float(np.hypot(w, h))


class VignettingModel:
    """Base class: ``channels``, ``resolution`` (width, height), ``evaluate``, ``save``, ``load``."""

    model_name: ClassVar[str] = ""
    _registry: ClassVar[dict[str, type["VignettingModel"]]] = {}

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.model_name:
            VignettingModel._registry[cls.model_name] = cls

    # subclasses set these in __init__
    _channels: int
    _resolution: tuple[int, int]
    _info: dict[str, Any]

    @property
    def channels(self) -> int:
        """Number of colour channels (1 or 3, RGB order)."""
        return self._channels

    @property
    def resolution(self) -> tuple[int, int]:
        """``(width, height)`` of the images the model was calibrated on."""
        return self._resolution

    @property
    def info(self) -> dict[str, Any]:
        """Provenance and fit diagnostics (a copy)."""
        return dict(self._info)

    def check_size(self, height: int, width: int) -> None:
        """Raise :class:`ModelMismatchError` unless ``width x height`` has the model's aspect ratio."""
        if not (isinstance(height, (int, np.integer)) and isinstance(width, (int, np.integer))):
            raise TypeError(f"height and width must be integers, got {height!r} and {width!r}")
        if height < 1 or width < 1:
            raise ValueError(f"height and width must be positive, got {height} x {width}")
        if not same_aspect_ratio(self.resolution, (int(width), int(height))):
            wc, hc = self.resolution
            raise ModelMismatchError(
                f"the vignetting model was calibrated at {wc}x{hc} (aspect {wc / hc:.4g}) but the images are "
                f"{width}x{height} (aspect {width / height:.4g}); vignetting cannot be rescaled to another aspect "
                "ratio: calibrate vignetting at this resolution (or on images cropped the same way)")

    def evaluate(self, height: int | None = None, width: int | None = None) -> np.ndarray:
        """``V`` as float32 ``(height, width, channels)``; defaults to the calibration resolution."""
        if height is None and width is None:
            width, height = self.resolution
        if height is None or width is None:
            raise ValueError("pass both height and width, or neither for the calibration resolution")
        self.check_size(height, width)
        out = self._evaluate(int(height), int(width))
        return np.ascontiguousarray(out, dtype=np.float32)

    def _evaluate(self, height: int, width: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # ---------------------------------------------------------------- persistence
    def _arrays(self) -> dict[str, np.ndarray]:  # pragma: no cover - abstract
        raise NotImplementedError

    def save(self, path: str | os.PathLike) -> Path:
        """Write the model in radiomap's format (``.npz``, JSON meta, no pickle), atomically; ValueError for another
        suffix, naming its writer (``radiometry.formats.save_vignetting`` writes ``.vgn`` and ``.png``)."""
        path = check_model_suffix(path, type(self).__name__, {
            ".vgn": "radiometry.formats.save_vignetting(model, path) (radical)",
            ".png": "radiometry.formats.save_vignetting(model, path) (DSO 16-bit vignette.png)"})
        return save_model_file(path, KIND, self._arrays(),
                               {"model": self.model_name, "channels": self.channels,
                                "resolution": list(self.resolution), "channel_order": "RGB",
                                "info": self._info})

    @classmethod
    def load(cls, path: str | os.PathLike) -> "VignettingModel":
        """Read a model written by :meth:`save`; the subclass is chosen by ``meta["model"]``."""
        meta, arrays = read_model_file(path, KIND)
        name = meta.get("model")
        model_cls = VignettingModel._registry.get(name) if isinstance(name, str) else None
        if model_cls is None:
            raise CalibrationFileError(
                f"{path}: unknown vignetting model {name!r} (radiomap knows "
                f"{', '.join(sorted(VignettingModel._registry))}); re-create the file")
        if cls is not VignettingModel and not issubclass(model_cls, cls):
            raise CalibrationFileError(f"{path}: holds a {name!r} vignetting model, not a {cls.model_name!r} one")
        info = meta.get("info", {})
        try:
            resolution = _as_resolution(meta.get("resolution"))
            return model_cls._from_arrays(arrays, resolution, info if isinstance(info, dict) else {})
        except (ValueError, TypeError, KeyError) as exc:
            raise CalibrationFileError(f"{path}: invalid {name} vignetting model: {exc}; re-create the file") from None

    @classmethod
    def _from_arrays(cls, arrays: dict[str, np.ndarray], resolution: tuple[int, int],
                     info: dict[str, Any]) -> "VignettingModel":  # pragma: no cover - abstract
        raise NotImplementedError

    def to_lut(self) -> "LUTVignetting":
        """The model sampled at its calibration resolution, as a LUT."""
        return LUTVignetting(self.evaluate(), info={**self._info, "converted_from": self.model_name})


class LUTVignetting(VignettingModel):
    """A per-pixel, per-channel table of ``V`` (float32 ``(H, W, C)``, or ``(H, W)`` for one channel).

    At another resolution the table is resampled bilinearly (``cv2.resize``, ``INTER_LINEAR``, pixel
    centres aligned: the same mapping as :func:`calibration_coordinates`).
    """

    model_name = "lut"

    def __init__(self, lut: np.ndarray, *, info: dict[str, Any] | None = None,
                 stderr: np.ndarray | None = None) -> None:
        arr = np.asarray(lut)
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim != 3 or arr.shape[2] not in (1, 3) or arr.shape[0] < 1 or arr.shape[1] < 1:
            raise ValueError(f"lut must have shape (H, W), (H, W, 1) or (H, W, 3), got {np.shape(lut)}")
        if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
            raise TypeError(f"lut must be a real numeric array, got dtype {arr.dtype}")
        arr = arr.astype(np.float32)
        if not np.all(np.isfinite(arr)):
            raise ValueError("lut contains NaN or infinite values; fill unobserved pixels before building the model")
        if np.any(arr <= 0):
            raise ValueError(f"lut must be strictly positive (V > 0), got a minimum of {float(arr.min()):.4g}")
        if float(arr.min()) < MIN_V:
            raise ValueError(f"lut falls to {float(arr.min()):.4g}; a vignetting factor below {MIN_V:g} is not "
                             "plausible (corrupt data?)")
        if float(arr.max()) > MAX_V:
            raise ValueError(f"lut reaches {float(arr.max()):.4g}; a vignetting factor above {MAX_V:g} is not "
                             "plausible (corrupt data?)")
        arr = np.ascontiguousarray(arr)
        arr.setflags(write=False)
        self._lut = arr
        self._channels = int(arr.shape[2])
        self._resolution = (int(arr.shape[1]), int(arr.shape[0]))
        self._info = dict(info or {})
        self._stderr = None if stderr is None else _checked_stderr(stderr, arr.shape)

    @property
    def lut(self) -> np.ndarray:
        """The read-only table, float32 ``(H, W, C)``."""
        return self._lut

    @property
    def stderr(self) -> np.ndarray | None:
        """The relative standard error of ``V`` (``se(V) / V``) per pixel and channel, read-only float32
        ``(H, W, C)``, or None when the model does not carry one (made elsewhere, or an older file)."""
        return self._stderr

    def evaluate_stderr(self, height: int | None = None, width: int | None = None) -> np.ndarray:
        """:attr:`stderr` resampled like :meth:`evaluate` (float32 ``(height, width, C)``); ValueError without one."""
        if self._stderr is None:
            raise ValueError("this vignetting model carries no standard error (fitted before radiomap kept one, or "
                             "not a fit); re-calibrate it with radiomap vignetting")
        if height is None and width is None:
            width, height = self.resolution
        if height is None or width is None:
            raise ValueError("pass both height and width, or neither for the calibration resolution")
        self.check_size(height, width)
        return np.ascontiguousarray(self._resample(self._stderr, int(height), int(width)), dtype=np.float32)

    def _resample(self, table: np.ndarray, height: int, width: int) -> np.ndarray:
        if (width, height) == self.resolution:
            return table.copy()
        import cv2

        out = cv2.resize(table, (width, height), interpolation=cv2.INTER_LINEAR)
        return out.reshape(height, width, self.channels)

    def _evaluate(self, height: int, width: int) -> np.ndarray:
        return self._resample(self._lut, height, width)

    def _arrays(self) -> dict[str, np.ndarray]:
        if self._stderr is None:
            return {"lut": self._lut}
        return {"lut": self._lut, "stderr": self._stderr}

    @classmethod
    def _from_arrays(cls, arrays, resolution, info):
        if "lut" not in arrays:
            raise KeyError("no 'lut' entry")
        lut = arrays["lut"]
        if lut.ndim == 3 and (lut.shape[1], lut.shape[0]) != resolution:
            raise ValueError(f"lut shape {lut.shape} disagrees with the resolution {resolution} in meta")
        return cls(lut, info=info, stderr=arrays.get("stderr"))

    def __repr__(self) -> str:
        w, h = self.resolution
        return f"LUTVignetting({w}x{h}, channels={self.channels}, min={float(self._lut.min()):.3f})"


def _checked_stderr(stderr: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A LUT's relative standard error: finite, non-negative, the LUT's shape; read-only float32."""
    arr = np.asarray(stderr)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.shape != shape:
        raise ValueError(f"stderr must have the lut's shape {shape}, got {np.shape(stderr)}")
    if not np.issubdtype(arr.dtype, np.number) or np.issubdtype(arr.dtype, np.complexfloating):
        raise TypeError(f"stderr must be a real numeric array, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.all(np.isfinite(arr)) or np.any(arr < 0):
        raise ValueError("stderr must be finite and non-negative (a relative standard error of V)")
    arr.setflags(write=False)
    return arr


class PolynomialVignetting(VignettingModel):
    """``V_c = scale_c (1 + b1 r^2 + b2 r^4 + b3 r^6)``, ``r = |x - centre_c| / R`` (see the module doc).

    Parameters
    ----------
    coefficients : ``(C, 3)`` ``b1, b2, b3`` per channel (``(3,)`` for one channel).
    centres : ``(C, 2)`` ``(cx, cy)`` in pixels at the calibration resolution (``(2,)`` for one channel);
        they scale with the resolution when evaluated elsewhere.
    resolution : ``(width, height)`` of calibration.
    scale : ``(C,)`` per-channel factor, default 1 (``V = 1`` at each channel's centre, which is how fits
        and radical files store it).
    """

    model_name = "polynomial"

    def __init__(self, coefficients: np.ndarray, centres: np.ndarray, resolution: tuple[int, int],
                 scale: np.ndarray | None = None, *, info: dict[str, Any] | None = None) -> None:
        coeffs = np.array(coefficients, dtype=np.float64, ndmin=2)
        cents = np.array(centres, dtype=np.float64, ndmin=2)
        if coeffs.ndim != 2 or coeffs.shape[1] != 3 or coeffs.shape[0] not in (1, 3):
            raise ValueError(f"coefficients must have shape (C, 3) with C in (1, 3), got {np.shape(coefficients)}")
        channels = coeffs.shape[0]
        if cents.shape != (channels, 2):
            raise ValueError(f"centres must have shape ({channels}, 2) to match the coefficients, "
                             f"got {np.shape(centres)}")
        sc = np.ones(channels) if scale is None else np.array(scale, dtype=np.float64, ndmin=1)
        if sc.shape != (channels,):
            raise ValueError(f"scale must have shape ({channels},), got {np.shape(scale)}")
        self._resolution = _as_resolution(resolution)
        for name, arr in (("coefficients", coeffs), ("centres", cents), ("scale", sc)):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contains NaN or infinite values: {arr.tolist()}")
        if np.any(sc <= 0):
            raise ValueError(f"scale must be positive, got {sc.tolist()}")
        w, h = self._resolution
        if np.any(cents[:, 0] < -0.5) or np.any(cents[:, 0] > w - 0.5) or np.any(cents[:, 1] < -0.5) \
                or np.any(cents[:, 1] > h - 0.5):
            raise ValueError(f"centres {cents.tolist()} lie outside the {w}x{h} image; "
                             "they are pixel coordinates at the calibration resolution")
        for arr in (coeffs, cents, sc):
            arr.setflags(write=False)
        self._coefficients, self._centres, self._scale = coeffs, cents, sc
        self._channels = int(channels)
        self._info = dict(info or {})
        # V must stay positive over the whole image: check the radial profile up to the farthest corner
        r_max = self._max_radius()
        r = np.linspace(0.0, r_max, 2048)
        for c in range(channels):
            with np.errstate(over="ignore", invalid="ignore"):
                v = self._profile(r, c)
            if not np.all(np.isfinite(v)) or float(np.max(v)) > MAX_V:
                raise ValueError(
                    f"channel {c}: V reaches {float(np.nanmax(np.abs(v))):.4g} inside the image (r <= {r_max:.3f}); "
                    f"a vignetting factor above {MAX_V:g} is not plausible (corrupt coefficients?)")
            if np.any(v <= 0):
                raise ValueError(
                    f"channel {c}: V = {sc[c]:.4g} (1 + {coeffs[c, 0]:.4g} r^2 + {coeffs[c, 1]:.4g} r^4 + "
                    f"{coeffs[c, 2]:.4g} r^6) reaches {float(v.min()):.4g} <= 0 inside the image (r <= {r_max:.3f})")
            if float(v.min()) < MIN_V:
                raise ValueError(f"channel {c}: V falls to {float(v.min()):.4g} inside the image; a vignetting factor "
                                 f"below {MIN_V:g} is not plausible (corrupt coefficients or scale?)")

    @property
    def coefficients(self) -> np.ndarray:
        """``(C, 3)`` ``b1, b2, b3`` (``r`` normalised by the half-diagonal)."""
        return self._coefficients

    @property
    def centres(self) -> np.ndarray:
        """``(C, 2)`` centres ``(cx, cy)`` in pixels at the calibration resolution."""
        return self._centres

    @property
    def scale(self) -> np.ndarray:
        """``(C,)`` per-channel factor."""
        return self._scale

    def _max_radius(self) -> float:
        w, h = self._resolution
        corners = np.array([[-0.5, -0.5], [w - 0.5, -0.5], [-0.5, h - 0.5], [w - 0.5, h - 0.5]])
        d = np.linalg.norm(corners[None, :, :] - self._centres[:, None, :], axis=2)
        return float(d.max() / half_diagonal(self._resolution))

    def _profile(self, r: np.ndarray, channel: int) -> np.ndarray:
        b1, b2, b3 = self._coefficients[channel]
        r2 = np.square(r)
        return self._scale[channel] * (1.0 + r2 * (b1 + r2 * (b2 + r2 * b3)))

    def radial_profile(self, r: np.ndarray, channel: int = 0) -> np.ndarray:
        """``V`` of one channel at normalised radii ``r`` (1 = the half-diagonal), float64."""
        if not 0 <= channel < self.channels:
            raise ValueError(f"channel must be in 0..{self.channels - 1}, got {channel}")
        return self._profile(np.asarray(r, dtype=np.float64), channel)

    def _evaluate(self, height: int, width: int) -> np.ndarray:
        xs, ys = calibration_coordinates(height, width, self._resolution)
        radius = half_diagonal(self._resolution)
        out = np.empty((height, width, self.channels), dtype=np.float32)
        for c in range(self.channels):
            cx, cy = self._centres[c]
            r = np.hypot((xs - cx)[None, :], (ys - cy)[:, None]) / radius
            out[..., c] = self._profile(r, c)
        return out

    def _arrays(self) -> dict[str, np.ndarray]:
        return {"coefficients": self._coefficients, "centres": self._centres, "scale": self._scale}

    @classmethod
    def _from_arrays(cls, arrays, resolution, info):
        for key in ("coefficients", "centres"):
            if key not in arrays:
                raise KeyError(f"no {key!r} entry")
        return cls(arrays["coefficients"], arrays["centres"], resolution, arrays.get("scale"), info=info)

    def normalised(self) -> "PolynomialVignetting":
        """The same model with ``scale = 1`` (``V = 1`` at every channel's centre)."""
        return PolynomialVignetting(self._coefficients, self._centres, self._resolution, info=self._info)

    def __repr__(self) -> str:
        w, h = self.resolution
        cents = ", ".join(f"({cx:.1f}, {cy:.1f})" for cx, cy in self._centres)
        return f"PolynomialVignetting({w}x{h}, channels={self.channels}, centres=[{cents}])"


__all__ = ["VignettingModel", "LUTVignetting", "PolynomialVignetting", "same_aspect_ratio",
           "calibration_coordinates", "half_diagonal", "KIND"]
