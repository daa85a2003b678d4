"""The simulated camera: :class:`CameraSpec` (every parameter, JSON round trip, presets) and
:class:`SimulatedCamera`, which turns a radiance field into the images a camera delivers (:class:`Capture`).

Image formation and conventions are described in :mod:`radiometry.simulation`.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any

import numpy as np

from radiometry.errors import CalibrationFileError
from radiometry.fileio import atomic_write_json, json_safe
from radiometry.registry import validate_name
from radiometry.response import CameraResponse
from radiometry.simulation._checks import check_size, per_channel
from radiometry.simulation.curves import CRF_FAMILIES, CRF_PRESETS, make_crf
from radiometry.simulation.exposure import AutoExposure, AutoWhiteBalance, ExposureController
from radiometry.simulation.vignetting import VignettingSpec, vignetting_preset

CAMERA_FORMAT = "radiomap-camera"
CAMERA_FORMAT_VERSION = 1


def default_intrinsics(width: int, height: int, *, focal: float | None = None) -> np.ndarray:
    """Pinhole ``K`` of a Kinect/Xtion-like camera: ``fx = fy = 525 * W / 640`` (a 62 degree horizontal
    field of view) unless ``focal`` is given, principal point at the image centre ``((W-1)/2, (H-1)/2)``."""
    width, height = check_size(width, height)
    f = 525.0 * width / 640.0 if focal is None else float(focal)
    if not (np.isfinite(f) and f > 0):
        raise ValueError(f"focal must be a positive number of pixels, got {focal!r}")
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class CameraSpec:
    """All parameters of a simulated camera; JSON round-trip with :meth:`to_dict`/:meth:`from_dict`,
    :meth:`save`/:meth:`load`.

    crf:            ``{"family": ..., **params}`` for :func:`make_crf`.
    vignetting:     :class:`VignettingSpec`.
    exposure_time:  initial (or fixed) exposure in seconds.
    gains:          initial (or fixed) white-balance gains (R, G, B).
    auto_exposure / auto_white_balance: controllers, or None for fixed settings.
    full_well:      electrons at saturation (shot noise ~ sqrt(E / full_well)); None = no shot noise.
    read_noise:     standard deviation of the additive read noise, in units of the saturation level.
    jpeg_quality:   1..100 to pass every frame through JPEG, None for lossless frames.
    """

    width: int = 640
    height: int = 480
    crf: dict = field(default_factory=lambda: dict(CRF_PRESETS["s_curve"]))
    vignetting: VignettingSpec = field(default_factory=lambda: vignetting_preset("xtion"))
    exposure_time: float = 0.01
    gains: tuple = (1.0, 1.0, 1.0)
    auto_exposure: AutoExposure | None = field(default_factory=AutoExposure)
    auto_white_balance: AutoWhiteBalance | None = None
    full_well: float | None = 6000.0
    read_noise: float = 0.0015
    jpeg_quality: int | None = None
    name: str = "custom"

    def __post_init__(self) -> None:
        check_size(self.width, self.height)
        if not isinstance(self.crf, Mapping) or "family" not in self.crf:
            raise ValueError(f"crf must be a mapping with a 'family' key, got {self.crf!r}")
        validate_name(self.crf["family"], CRF_FAMILIES, "crf family")
        object.__setattr__(self, "crf", json_safe(dict(self.crf)))
        if isinstance(self.vignetting, Mapping):
            object.__setattr__(self, "vignetting", VignettingSpec.from_dict(self.vignetting))
        if not isinstance(self.vignetting, VignettingSpec):
            raise TypeError(f"vignetting must be a VignettingSpec, got {type(self.vignetting).__name__}")
        if not (np.isfinite(self.exposure_time) and self.exposure_time > 0):
            raise ValueError(f"exposure_time must be a positive number of seconds, got {self.exposure_time!r}")
        object.__setattr__(self, "gains", tuple(per_channel(self.gains, "gains", 3).tolist()))
        for name, cls in (("auto_exposure", AutoExposure), ("auto_white_balance", AutoWhiteBalance)):
            value = getattr(self, name)
            if isinstance(value, Mapping):
                object.__setattr__(self, name, cls(**value))
            elif value is not None and not isinstance(value, cls):
                raise TypeError(f"{name} must be {cls.__name__} or None, got {type(value).__name__}")
        if self.full_well is not None and not (np.isfinite(self.full_well) and self.full_well > 0):
            raise ValueError(f"full_well must be a positive number of electrons or None, got {self.full_well!r}")
        if not (np.isfinite(self.read_noise) and self.read_noise >= 0):
            raise ValueError(f"read_noise must be >= 0, got {self.read_noise!r}")
        if self.jpeg_quality is not None and not (isinstance(self.jpeg_quality, int) and 1 <= self.jpeg_quality <= 100):
            raise ValueError(f"jpeg_quality must be a whole number in 1..100 or None, got {self.jpeg_quality!r}")

    # ---------------------------------------------------------------- construction
    @classmethod
    def preset(cls, name: str = "xtion", *, width: int = 640, height: int = 480, **overrides: Any) -> "CameraSpec":
        """Named cameras: ``xtion`` (S-shaped CRF differing per channel, strong vignetting with a
        shifted blue centre and a non-radial field, auto exposure and white balance, shot and read
        noise), ``mild`` (gamma 2.2, mild vignetting, auto exposure, noise) and ``ideal`` (linear,
        no vignetting, no noise, fixed exposure); ``asymmetric`` is ``xtion`` with a strong non-radial
        vignetting field (the demo's camera). ``overrides`` replace any field."""
        if name in ("xtion", "asymmetric"):
            spec = cls(width, height, dict(CRF_PRESETS["s_curve"]), vignetting_preset(name), 0.01,
                       (1.0, 1.0, 1.0), AutoExposure(), AutoWhiteBalance(), 6000.0, 0.0015, None, name)
        elif name == "mild":
            spec = cls(width, height, dict(CRF_PRESETS["gamma"]), vignetting_preset("mild"), 0.01,
                       (1.0, 1.0, 1.0), AutoExposure(), None, 10000.0, 0.001, None, "mild")
        elif name == "ideal":
            spec = cls(width, height, dict(CRF_PRESETS["linear"]), vignetting_preset("none"), 0.01,
                       (1.0, 1.0, 1.0), None, None, None, 0.0, None, "ideal")
        else:
            raise ValueError(f"unknown camera preset {name!r}; valid names: {', '.join(CAMERA_PRESETS)}")
        return replace(spec, **overrides) if overrides else spec

    def replace(self, **changes: Any) -> "CameraSpec":
        return replace(self, **changes)

    def response(self) -> CameraResponse:
        params = {k: v for k, v in self.crf.items() if k != "family"}
        return make_crf(self.crf["family"], **params)

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": CAMERA_FORMAT, "version": CAMERA_FORMAT_VERSION, "name": self.name,
            "width": self.width, "height": self.height, "crf": json_safe(self.crf),
            "vignetting": self.vignetting.to_dict(), "exposure_time": self.exposure_time,
            "gains": list(self.gains),
            "auto_exposure": None if self.auto_exposure is None else asdict(self.auto_exposure),
            "auto_white_balance": None if self.auto_white_balance is None else asdict(self.auto_white_balance),
            "full_well": self.full_well, "read_noise": self.read_noise, "jpeg_quality": self.jpeg_quality,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "CameraSpec":
        data = dict(data)
        fmt, version = data.pop("format", CAMERA_FORMAT), data.pop("version", CAMERA_FORMAT_VERSION)
        if fmt != CAMERA_FORMAT:
            raise ValueError(f"not a radiomap camera description (format {fmt!r})")
        if not isinstance(version, int) or version > CAMERA_FORMAT_VERSION:
            raise ValueError(f"camera description version {version!r} is newer than this radiomap reads "
                             f"({CAMERA_FORMAT_VERSION}); upgrade radiomap")
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown camera fields {sorted(unknown)}; valid: {sorted(known)}")
        if isinstance(data.get("vignetting"), Mapping):
            data["vignetting"] = VignettingSpec.from_dict(data["vignetting"])
        return cls(**data)

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_json(cls, text: str) -> "CameraSpec":
        return cls.from_dict(json.loads(text))

    def save(self, path: str | os.PathLike) -> Path:
        """Write the camera description as JSON, atomically."""
        return atomic_write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "CameraSpec":
        path = Path(path)
        if not path.is_file():
            raise CalibrationFileError(f"{path}: no such camera description; check the path")
        try:
            return cls.from_dict(json.loads(path.read_text(encoding="utf-8")))
        except (json.JSONDecodeError, ValueError, TypeError) as exc:
            raise CalibrationFileError(f"{path}: not a valid radiomap camera description ({exc}); "
                                       "re-create it with radiomap simulate") from None


CAMERA_PRESETS = ("xtion", "asymmetric", "mild", "ideal")


@dataclass(frozen=True, eq=False)
class Capture:
    """One simulated frame.

    image:       uint8 ``(H, W, 3)`` RGB, what the camera delivers (after JPEG if enabled).
    intensity:   float32 ``(H, W, 3)`` ``f(signal)`` before 8-bit rounding (and before JPEG), in 0..255.
    signal:      float32 noisy irradiance ``E'`` (before the response).
    irradiance:  float32 noise-free ``E = k g V L``.
    exposure_time, gains: the settings used.
    """

    image: np.ndarray
    intensity: np.ndarray
    signal: np.ndarray
    irradiance: np.ndarray
    exposure_time: float
    gains: np.ndarray


class SimulatedCamera:
    """A camera built from a :class:`CameraSpec`: ``response`` (:class:`CameraResponse`) and
    ``vignetting`` (float32 ``(H, W, 3)``, read-only) are the ground truth."""

    def __init__(self, spec: CameraSpec | None = None) -> None:
        self.spec = spec if spec is not None else CameraSpec.preset("xtion")
        if not isinstance(self.spec, CameraSpec):
            raise TypeError(f"spec must be a CameraSpec, got {type(self.spec).__name__}")
        self.response = self.spec.response()
        if self.response.channels != 3:
            self.response = CameraResponse(np.repeat(self.response.inverse_table, 3, axis=1), self.response.meta)
        vig = self.spec.vignetting.render(self.spec.width, self.spec.height)
        vig.setflags(write=False)
        self.vignetting = vig

    @property
    def width(self) -> int:
        return self.spec.width

    @property
    def height(self) -> int:
        return self.spec.height

    def controller(self, *, auto_exposure: bool | AutoExposure | None = None,
                   auto_white_balance: bool | AutoWhiteBalance | None = None,
                   exposure_time: float | None = None, gains: Sequence[float] | None = None) -> ExposureController:
        """A fresh :class:`ExposureController` with the spec's settings; ``True``/``False`` switch a loop
        on (with the spec's or default parameters) or off, an instance replaces the parameters."""
        ae = _resolve_loop(auto_exposure, self.spec.auto_exposure, AutoExposure)
        awb = _resolve_loop(auto_white_balance, self.spec.auto_white_balance, AutoWhiteBalance)
        return ExposureController(self.response, exposure_time=self.spec.exposure_time if exposure_time is None
                                  else exposure_time, gains=self.spec.gains if gains is None else gains,
                                  auto_exposure=ae, auto_white_balance=awb)

    def _check_radiance(self, radiance: np.ndarray) -> np.ndarray:
        arr = np.asarray(radiance)
        if arr.shape != (self.height, self.width, 3):
            raise ValueError(f"radiance must have shape ({self.height}, {self.width}, 3) for this camera, "
                             f"got {arr.shape}")
        if not np.issubdtype(arr.dtype, np.floating):
            raise TypeError(f"radiance must be a float array, got {arr.dtype}")
        arr = arr.astype(np.float32, copy=False)
        if not np.all(np.isfinite(arr)) or float(arr.min(initial=0.0)) < 0:
            raise ValueError("radiance must be finite and >= 0")
        return arr

    def irradiance(self, radiance: np.ndarray, *, exposure_time: float, gains: Sequence[float] = (1, 1, 1)) -> np.ndarray:
        """Noise-free sensor irradiance ``E = k * g_c * V_c * L``, float32 ``(H, W, 3)``."""
        if not (np.isfinite(exposure_time) and exposure_time > 0):
            raise ValueError(f"exposure_time must be a positive number of seconds, got {exposure_time!r}")
        g = per_channel(gains, "gains", 3)
        L = self._check_radiance(radiance)
        out = self.vignetting * (float(exposure_time) * g).astype(np.float32)
        out *= L
        return out

    def capture(self, radiance: np.ndarray, *, exposure_time: float | None = None,
                gains: Sequence[float] | None = None, rng: np.random.Generator | None = None,
                noise: bool = True, jpeg: bool = True) -> Capture:
        """Image of a radiance field ``(H, W, 3)`` with the given settings (the spec's by default).

        ``noise=True`` needs ``rng`` (a ``numpy.random.Generator``) when the spec has any noise;
        ``noise=False`` and ``jpeg=False`` give the exact, deterministic image formation.
        """
        k = self.spec.exposure_time if exposure_time is None else exposure_time
        g = self.spec.gains if gains is None else gains
        E = self.irradiance(radiance, exposure_time=k, gains=g)
        signal = E
        noisy = noise and (self.spec.full_well is not None or self.spec.read_noise > 0)
        if noisy:
            if not isinstance(rng, np.random.Generator):
                raise ValueError("noise=True needs rng=np.random.default_rng(seed) (or pass noise=False)")
            # Gaussian approximation of Poisson shot noise (variance E / full_well) plus read noise
            if self.spec.full_well is not None:
                std = E * np.float32(1.0 / self.spec.full_well)
                std += np.float32(self.spec.read_noise) ** 2
                np.sqrt(std, out=std)
            else:
                std = np.float32(self.spec.read_noise)
            signal = rng.standard_normal(E.shape, dtype=np.float32)
            signal *= std
            signal += E
            np.maximum(signal, 0.0, out=signal)
        intensity = self.response.forward(signal)
        image = np.clip(np.rint(intensity), 0, 255).astype(np.uint8)
        if jpeg and self.spec.jpeg_quality is not None:
            image = jpeg_roundtrip(image, self.spec.jpeg_quality)
        return Capture(image, intensity, signal.astype(np.float32, copy=False), E, float(k),
                       per_channel(g, "gains", 3))


def _resolve_loop(value: Any, from_spec: Any, cls: type) -> Any:
    if value is None:
        return from_spec
    if value is True:
        return from_spec if from_spec is not None else cls()
    if value is False:
        return None
    if isinstance(value, cls):
        return value
    raise TypeError(f"expected True, False, None or a {cls.__name__}, got {value!r}")


def jpeg_roundtrip(image: np.ndarray, quality: int) -> np.ndarray:
    """Encode an RGB uint8 image as JPEG at ``quality`` (1..100) and decode it again (OpenCV)."""
    import cv2

    if not (isinstance(quality, (int, np.integer)) and 1 <= quality <= 100):
        raise ValueError(f"quality must be a whole number in 1..100, got {quality!r}")
    ok, buf = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:  # pragma: no cover - OpenCV always encodes uint8 RGB
        raise RuntimeError("OpenCV could not encode the frame as JPEG")
    return cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


__all__ = ["CAMERA_PRESETS", "CameraSpec", "Capture", "SimulatedCamera", "default_intrinsics", "jpeg_roundtrip"]
