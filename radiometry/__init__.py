"""radiometry: camera response, vignetting and exposure calibration and correction.

Image formation, per colour channel c::

    I(x) = f(k_c * V_c(x) * L(x))

``f`` is the camera response function (CRF), ``V`` the vignetting response (1 at its centre), ``k_c``
the exposure time times the white-balance gain and ``L`` the scene radiance. Channel order is RGB.

From Python (:mod:`radiometry.api`): ``calibrate_response(folder)``, ``calibrate_vignetting(frames, response)``,
``correct(image, response, vignetting)``; models load with ``load_response`` / ``load_vignetting``.
"""

__version__ = "0.1.0"

from radiometry.errors import (  # noqa: F401  (re-exported)
    CalibrationError,
    CalibrationFileError,
    DatasetError,
    ImageError,
    ModelMismatchError,
    OutputError,
    RadiomapError,
)
from radiometry.response import CameraResponse  # noqa: F401
from radiometry.api import calibrate_response, calibrate_vignetting, correct  # noqa: F401
from radiometry.formats import load_response, load_vignetting  # noqa: F401
