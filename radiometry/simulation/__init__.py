"""The simulated CAMERA: response, vignetting, exposure control and noise, every radiometric quantity known.

The other homes of made-up data: :mod:`mapping.simulation` renders simulated scenes and sequences with
this camera and writes them to folders with their ground truth; :mod:`mapping.datasets.simulated` reads
those folders back; :mod:`mapping.datasets.in_memory` is a dataset over frames already in memory.

Image formation, per colour channel ``c`` (RGB) and pixel ``x``::

    E_c(x) = k * g_c * V_c(x) * L_c(x)           irradiance on the sensor, saturating at E = 1
    E'_c   = E_c + sqrt(E_c / full_well + read_noise^2) * N(0, 1)      shot + read noise
    I_c    = clip(round(f_c(E'_c)), 0, 255)      8-bit intensity (optionally JPEG-compressed)

``L`` is scene radiance (arbitrary linear units), ``k`` the exposure time in seconds, ``g_c`` the
white-balance gain, ``V_c`` the vignetting (1 at its maximum), ``f_c`` the camera response whose
inverse is a :class:`~radiometry.response.CameraResponse` (``f^-1(255) = 1``: irradiance 1 is the
saturation level). Shot noise is the Gaussian approximation of Poisson noise with ``full_well``
electrons at saturation; read noise is additive, in units of the saturation irradiance.

Building blocks, one module each, everything re-exported here:

- :mod:`~radiometry.simulation.curves`: CRFs :func:`crf_linear`, :func:`crf_gamma`, :func:`crf_s_curve`
  (parametric), :func:`crf_from_table` and :func:`crf_from_pcalib` (tabulated); :func:`make_crf` picks a
  family by name from :data:`CRF_FAMILIES`.
- :mod:`~radiometry.simulation.vignetting`: :class:`VignettingSpec` (per-channel even polynomial with its own
  centre, times a smooth non-radial field; or a DSO ``vignette.png``; or lensfun ``pa`` coefficients),
  :func:`vignetting_preset`.
- :mod:`~radiometry.simulation.lensfun`: the lensfun database, :func:`find_lensfun_vignetting`.
- :mod:`~radiometry.simulation.exposure`: :class:`AutoExposure`, :class:`AutoWhiteBalance` and the stateful
  :class:`ExposureController` that meters the previous frame like a camera does.
- :mod:`~radiometry.simulation.camera`: :class:`CameraSpec` holds all parameters and round-trips through
  JSON; :class:`SimulatedCamera` turns radiance into images (:meth:`SimulatedCamera.capture`).

Conventions. Pixel ``(x, y)`` has its centre at ``(x, y)`` (OpenCV); vignetting centres are given as
fractions of the image size, ``x = cx * W - 0.5`` (so ``0.5`` is the image centre at any resolution)
and the radius is normalised by the half-diagonal ``R = 0.5 * sqrt(W^2 + H^2)`` as in
:mod:`radiometry.vignetting` and lensfun. Randomness only comes from a ``numpy.random.Generator``
passed explicitly.
"""

from radiometry.simulation.camera import (CAMERA_PRESETS, CameraSpec, Capture, SimulatedCamera, default_intrinsics,
                                          jpeg_roundtrip)
from radiometry.simulation.curves import (CRF_FAMILIES, CRF_PRESETS, crf_from_pcalib, crf_from_table, crf_gamma,
                                          crf_linear, crf_s_curve, crf_spec_from_file, make_crf)
from radiometry.simulation.exposure import AutoExposure, AutoWhiteBalance, ExposureController
from radiometry.simulation.lensfun import (LensfunVignetting, default_lensfun_db, find_lensfun_vignetting,
                                           lensfun_vignetting_entries)
from radiometry.simulation.vignetting import (VIGNETTING_PRESETS, VignettingSpec, nonradial_field,
                                              polynomial_for_corner, polynomial_vignetting, vignette_map_from_png,
                                              vignetting_preset)

__all__ = [
    "AutoExposure", "AutoWhiteBalance", "CAMERA_PRESETS", "CRF_FAMILIES", "CRF_PRESETS", "CameraSpec", "Capture",
    "ExposureController", "LensfunVignetting", "SimulatedCamera", "VIGNETTING_PRESETS", "VignettingSpec",
    "crf_from_pcalib", "crf_from_table", "crf_gamma", "crf_linear", "crf_s_curve", "crf_spec_from_file",
    "default_intrinsics", "default_lensfun_db", "find_lensfun_vignetting", "jpeg_roundtrip",
    "lensfun_vignetting_entries", "make_crf", "nonradial_field", "polynomial_for_corner", "polynomial_vignetting",
    "vignette_map_from_png", "vignetting_preset",
]
