"""Compare radiometric corrections on one sequence with identical poses: the paper's Fig. 9 experiment.

:func:`compare` fuses the same frames once per :class:`Method` (no correction, the response alone, the
response with a polynomial or a LUT vignetting model, each optionally with exposure compensation) and
collects, per method: the colour-disagreement histogram (L1 between the map's colour and each sample about
to be averaged into it, 8-bit display levels summed over R, G, B; :mod:`mapping.histogram`), the map as a
mesh, and, for simulated sequences, the mesh colours' error against the true radiance.

One job per module:

- :mod:`~mapping.compare.methods`: :class:`Method`, :func:`make_methods`, the model-kind checks,
  :func:`load_method_vignetting` and equal brightness (:func:`equal_brightness`);
- :mod:`~mapping.compare.geometry`: a fused map's surface (:class:`MapGeometry`, :func:`map_geometry`,
  :func:`surfel_discs`);
- :mod:`~mapping.compare.colour_error`: the mesh colours against the true radiance (:func:`colour_error`);
- :mod:`~mapping.compare.results`: :class:`MethodResult`, :class:`CompareResult` and the folder's layout and
  policy (:class:`ComparisonFolder`);
- :mod:`~mapping.compare.outputs`: the table, figures, renders, report and ``compare.json``;
- :mod:`~mapping.compare.run`: :func:`compare` itself (identical poses, :class:`FixedPoses`).
"""

from mapping.compare.colour_error import ColourError, colour_error, linear_colours
from mapping.compare.geometry import MapGeometry, map_geometry, surfel_discs
from mapping.compare.methods import (BASE_METHODS, BRIGHTNESS, DEFAULT_METHODS, EC_SUFFIX, METHOD_NAMES, Method,
                                     equal_brightness, load_method_vignetting, make_methods)
from mapping.compare.results import TABLE_COLUMNS, CompareResult, ComparisonFolder, MethodResult
from mapping.compare.run import FixedPoses, compare

__all__ = ["BASE_METHODS", "BRIGHTNESS", "ColourError", "CompareResult", "ComparisonFolder", "DEFAULT_METHODS",
           "EC_SUFFIX", "FixedPoses", "MapGeometry", "Method", "METHOD_NAMES", "MethodResult", "TABLE_COLUMNS",
           "colour_error", "compare", "equal_brightness", "linear_colours",
           "load_method_vignetting", "make_methods", "map_geometry", "surfel_discs"]
