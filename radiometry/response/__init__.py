"""The camera response ``f^-1``: its model, and its calibration from bracketed exposures.

:class:`CameraResponse` (:mod:`~radiometry.response.model`) holds ``f^-1`` as 256 values per channel; the names of
the model module are importable from here as they were when it was ``radiometry/response.py``
(``from radiometry.response import CameraResponse``). :func:`fit_response` fits one from brackets.

Modules, one job each, in the order they build on each other (none imports a later one, and none imports this
package's ``__init__``; ``tests/test_architecture.py`` fails on an import cycle):

- :mod:`~radiometry.response.model`: the model (``CameraResponse``, ``LEVELS``, table checks and repair).
- :mod:`~radiometry.response.inputs`: the checks of a bracketed stack that every method shares (images, times,
  brightness order, levels, mask) and :func:`~radiometry.response.inputs.equal_ratios`.
- :mod:`~radiometry.response.levels`: which levels carry the response (ceiling, floor, saturation, JPEG edges),
  and the levels a fitted response declares.
- :mod:`~radiometry.response.debevec`: Debevec & Malik's sparse solve of one channel, its samples and hat weights.
- :mod:`~radiometry.response.smoothness`: Debevec's smoothness weight by cross-validation.
- :mod:`~radiometry.response.engel`, :mod:`~radiometry.response.loglog`, :mod:`~radiometry.response.opencv`:
  the other methods.
- :mod:`~radiometry.response.fit`: ``fit_response_debevec``, the ``method=`` dispatcher, merging and checking a
  response against the images, reading brackets and their times file.
- :mod:`~radiometry.response.noise`: the images' noise, in one image (the Laplacian) and between exposures.
- :mod:`~radiometry.response.quality`: the truth-free quality figure (held-out prediction, split halves).
"""

from radiometry.response.model import (KIND, LEVELS, CameraResponse, level_width, relative_stderr,
                                       relative_uncertainty, repair_monotone,
                                       srgb_to_linear, validate_inverse_table)

__all__ = ["KIND", "LEVELS", "CameraResponse", "level_width", "relative_stderr", "relative_uncertainty",
           "repair_monotone", "srgb_to_linear",
           "validate_inverse_table", "fit_response", "METHODS", "load_brackets"]


def __getattr__(name: str):
    """``fit_response``, ``METHODS`` and ``load_brackets`` from :mod:`~radiometry.response.fit`, loaded when first
    used (``import radiometry`` stays light: the model is all it needs)."""
    if name in ("fit_response", "METHODS", "load_brackets"):
        from radiometry.response import fit

        return getattr(fit, name)
    raise AttributeError(f"module 'radiometry.response' has no attribute {name!r}")
