"""Colour error against ground truth (simulated sequences, ``scene=`` of :func:`mapping.compare.compare`).

For every mesh vertex the true radiance ``L`` of the surface it lies on is looked up
(:meth:`mapping.simulation.room.Room.radiance_at`, vertices farther than ``max(3 voxels, 3 cm)`` from any surface
are left out). The vertex colour in linear units ``C`` (the map's irradiance, or ``f^-1`` of the averaged
intensities for no correction) is compared with ``s_c L`` where ``s_c`` is one global scale per channel (the
median of ``C / L``: exposure and white balance are not observable in absolute terms); both are mapped to display
levels by the response at the reference exposure, and the error is the mean absolute difference per channel in
8-bit levels.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from mapping.colour import FastForward
from mapping.compare.geometry import MapGeometry
from radiometry.response import CameraResponse


@dataclass
class ColourError:
    """Mesh colours against the true radiance, in 8-bit display levels (per channel, after a global scale)."""

    mean: float                 # mean |display(C) - display(s L)| over vertices and channels
    rmse: float
    median: float               # of the per-vertex mean over channels
    p90: float
    vertices: int               # vertices compared
    fraction: float             # of all vertices
    scale: list[float]          # s_c per channel (map units per unit radiance)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def linear_colours(colours: np.ndarray, colour_model, display_response: CameraResponse | None) -> np.ndarray | None:
    """Map colours in units linear in radiance: irradiance as is; averaged intensities through ``f^-1`` of
    ``display_response`` (None when raw intensities cannot be linearised without a response)."""
    if colour_model.display_exposure() is not None:
        return np.asarray(colours, np.float32)
    if display_response is None:
        return None
    levels = np.clip(np.nan_to_num(np.asarray(colours, np.float32)), 0.0, 255.0)
    return display_response.inverse(levels)


def colour_error(geometry: MapGeometry, colour_model, scene, *, display_response: CameraResponse | None,
                 max_distance: float = 0.03) -> ColourError | None:
    """Error of the geometry's vertex colours against ``scene.radiance_at`` (see the module doc), or None when
    it cannot be measured (no vertices near the scene's surfaces, or raw colours without a response)."""
    if len(geometry) == 0:
        return None
    lin = linear_colours(geometry.colours, colour_model, display_response)
    if lin is None:
        return None
    to_display = colour_model.to_display if colour_model.display_exposure() is not None else FastForward(display_response)
    truth = scene.radiance_at(geometry.vertices, geometry.normals, max_distance=max_distance)
    ok = np.all(np.isfinite(truth), axis=1) & np.all(np.isfinite(lin), axis=1)
    ok &= np.all(truth > 0, axis=1) & np.all(lin > 0, axis=1)
    if np.count_nonzero(ok) < 10:
        return None
    scale = np.exp(np.median(np.log(lin[ok]) - np.log(truth[ok]), axis=0))
    shown = np.asarray(to_display(lin[ok]), np.float64)
    expected = np.asarray(to_display((truth[ok] * scale[None, :]).astype(np.float32)), np.float64)
    diff = np.abs(shown - expected)
    per_vertex = diff.mean(axis=1)
    return ColourError(mean=float(diff.mean()), rmse=float(np.sqrt(np.mean(diff ** 2))),
                       median=float(np.median(per_vertex)), p90=float(np.percentile(per_vertex, 90)),
                       vertices=int(np.count_nonzero(ok)), fraction=float(np.mean(ok)),
                       scale=[float(s) for s in scale])
