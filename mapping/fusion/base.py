"""The interface every fusion backend (TSDF, surfel) implements.

Colours handed to a backend are float32 in *map units*: irradiance ``f^-1(I) / V / k`` when the run
corrects, or raw intensity levels (0..255 as float) when it does not. Backends never convert colours;
the pipeline owns the conversion to display units (``to_display``) for histograms and exports.

Poses are camera-to-world (4, 4) float64; K is the (3, 3) colour intrinsics; depth is float32 metres
with 0 = invalid.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np


@dataclass
class ModelView:
    """The map rendered at one camera pose (what a ray cast or a surfel splat returns).

    depth:  (H, W) float32 metres along the optical axis, 0 where no surface.
    colour: (H, W, 3) float32 map units, 0 where no surface.
    vertex: (H, W, 3) float32 points in the camera frame (0 where none), for ICP; or None.
    normal: (H, W, 3) float32 unit normals in the camera frame (0 where none), for ICP; or None.
    pose:   (4, 4) camera-to-world pose it was rendered at (set by the backend that rendered it; exposure
            compensation re-projects with it); or None.
    prepared: what the backend prepared for fusing the frame this view was rendered for
            (:meth:`FusionBackend.render_for_frame`; the TSDF's voxel block list), reused by
            :meth:`FusionBackend.integrate` of that frame; None for a plain :meth:`FusionBackend.render`.
    """

    depth: np.ndarray
    colour: np.ndarray
    vertex: np.ndarray | None = None
    normal: np.ndarray | None = None
    pose: np.ndarray | None = None
    prepared: Any = None

    @property
    def valid(self) -> np.ndarray:
        return self.depth > 0


@dataclass
class ColourPairs:
    """Colour samples compared before fusion, for the disagreement histogram.

    map_colour, sample_colour: (N, 3) float32 in map units; row i of each is one comparison between the
    map's current colour and the incoming sample that is about to be averaged into it.
    """

    map_colour: np.ndarray
    sample_colour: np.ndarray

    def __len__(self) -> int:
        return int(self.map_colour.shape[0])


class FusionBackend(Protocol):
    """A map that can be rendered at a pose and that fuses RGB-D frames.

    The frame contract (what :func:`mapping.pipeline.reconstruct` does with every frame, in this order)::

        view  = backend.render_for_frame(depth, K, pose)     # the map before this frame, at its pose
        pairs = backend.integrate(depth, colour, K, pose, view=view, valid=valid)

    ``depth_min`` and ``depth_max`` (metres) are the one depth range the backend fuses and renders: depth
    outside it is neither fused nor tracked against.
    """

    depth_min: float
    depth_max: float

    def render(self, pose: np.ndarray, K: np.ndarray, height: int, width: int) -> ModelView:
        """The map as seen from ``pose``; an empty map gives all-zero depth."""
        ...

    def render_for_frame(self, depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> ModelView:
        """The map as seen from ``pose`` before the frame of ``depth`` is fused there; the view carries what
        the backend prepared for fusing that frame (:attr:`ModelView.prepared`) and its pose."""
        ...

    def integrate(self, depth: np.ndarray, colour: np.ndarray, K: np.ndarray, pose: np.ndarray, *,
                  view: ModelView | None = None, valid: np.ndarray | None = None,
                  frame_index: int = 0) -> ColourPairs | None:
        """Fuse one frame. ``view`` is :meth:`render_for_frame`'s view of this frame (a backend need not ray
        cast twice). ``valid`` (bool (H, W), or None for all) marks the pixels whose colour may be fused;
        the others add neither colour nor geometry. Returns the colour pairs this backend compared (map
        colour vs the sample about to be merged into it), or None."""
        ...

    def export(self, folder: Path, to_display: Callable[[np.ndarray], np.ndarray], *,
               formats: tuple[str, ...] = ("ply",)) -> dict[str, Path]:
        """Write the map's geometry with colours mapped through ``to_display`` ((N, 3) map units ->
        (N, 3) float display levels 0..255), a mesh in each of ``formats`` (:data:`mapping.validation.MESH_FORMATS`)
        where the backend makes one; returns {kind: path} of the written files."""
        ...

    def stats(self) -> dict:
        """Size figures for metrics.json (voxel blocks, surfels, memory)."""
        ...


def masked_depth(depth: np.ndarray, valid: np.ndarray | None) -> np.ndarray:
    """``depth`` with 0 ("no measurement") where ``valid`` is False; ``depth`` itself when ``valid`` is None."""
    if valid is None:
        return depth
    return np.where(valid, depth, np.float32(0))
