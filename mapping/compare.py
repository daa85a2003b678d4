"""Compare radiometric corrections on one sequence with identical poses: the paper's Fig. 9 experiment.

:func:`compare` fuses the same frames once per :class:`Method` (no correction, the response alone, the
response with a polynomial or a LUT vignetting model, each optionally with exposure compensation) and
collects, per method: the colour-disagreement histogram (L1 between the map's colour and each sample about
to be averaged into it, 8-bit display levels summed over R, G, B; :mod:`mapping.histogram`), the map as a
mesh, and, for simulated sequences, the mesh colours' error against the true radiance.

Identical poses. With ``poses="gt"`` every run takes the dataset's ground truth. With ``poses="icp"`` the
first method's run tracks (frame-to-model ICP on depth only, so the choice of method does not matter) and
every later run fuses at exactly the poses it estimated, skipping exactly the frames it skipped
(:class:`FixedPoses`). ``CompareResult.poses_identical`` checks it after the fact.

Equal brightness (``brightness="mean"``, the default). Where ``V = 1`` is put is a convention (the optical
centre), yet it sets the brightness of the corrected images: ``f^-1(I) / V`` is brighter than the raw image
by ``1 / mean(V)`` on average (~1.2 for an Xtion), and through the S-shaped response a brighter display
changes every L1 distance. Methods are compared at equal brightness: each vignetting model is rescaled per
channel to an image mean of 1 (a :class:`~radiometry.vignetting.LUTVignetting` of ``V / mean(V)``), so the
corrected irradiance displays, on average, at the raw image's levels and only the *shape* of each
correction differs. ``brightness="calibrated"`` uses the models as calibrated (``V = 1`` at the centre).

Colour error against ground truth (simulated sequences, ``room=``). For every mesh vertex the true radiance
``L`` of the surface it lies on is looked up (:meth:`mapping.simulation.room.Room.radiance_at`, vertices
farther than ``max(3 voxels, 3 cm)`` from any surface are left out). The vertex colour in linear units
``C`` (the map's irradiance, or ``f^-1`` of the averaged intensities for no correction) is compared with
``s_c L`` where ``s_c`` is one global scale per channel (the median of ``C / L``: exposure and white balance
are not observable in absolute terms); both are mapped to display levels by the response at the reference
exposure, and the error is the mean absolute difference per channel in 8-bit levels.

Outputs (``OUT``)::

    OUT/compare.json, compare.csv, compare.txt   the table (and everything else, in JSON)
    OUT/histograms.png                           normalised histograms of all methods (Fig. 9), linear + log
    OUT/renders.jpg                              the meshes side by side from 2-3 trajectory viewpoints (their
                                                 poses and camera: "renders" in compare.json)
    OUT/report.html                              everything above in one self-contained page
    OUT/<method>/                                a reconstruct results folder per method (histogram,
                                                 trajectory, metrics, mesh.ply, mesh_colours.npz)
    OUT/config.json, summary.txt                 the CLI's options and printed summary (``config``, ``summary``)
    OUT/.radiomap-files.json                     the files and method folders the comparison wrote: the next
                                                 ``force`` run removes them (:class:`ComparisonFolder`)
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from mapping.colour import FastForward, IrradianceColour, RawIntensity
from mapping.export import MANIFEST, ResultsFolder
from radiometry.errors import CalibrationFileError, RadiomapError
from radiometry.response import CameraResponse
from radiometry.vignetting import LUTVignetting, VignettingModel
from radiometry.fileio import json_safe
from radiometry.tables import csv_text, format_table

log = logging.getLogger(__name__)

BASE_METHODS = ("none", "response", "poly", "lut")
EC_SUFFIX = "+ec"
METHOD_NAMES = BASE_METHODS + tuple(m + EC_SUFFIX for m in BASE_METHODS[1:])
DEFAULT_METHODS = ("none", "poly", "lut")
LABELS = {"none": "no correction", "response": "response only", "poly": "polynomial vignetting",
          "lut": "LUT vignetting"}
BRIGHTNESS = ("mean", "calibrated")
TABLE_COLUMNS = ["method", "description", "frames fused", "pairs", "L1 mean", "L1 median", "L1 p90",
                 "colour err", "colour err p90", "seconds"]
MARKER = "compare.json"
RUNNING = "RUNNING"


# --------------------------------------------------------------------------------------------------
# methods
# --------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class Method:
    """One way of turning frames into map colours.

    name:        short identifier (``none``, ``response``, ``poly``, ``lut``, each but ``none`` with ``+ec``);
                 also the name of the method's results folder.
    label:       what the figures call it.
    response:    the camera response, or None for raw intensities (no correction).
    vignetting:  a vignetting model, or None.
    exposure_compensation: divide each frame's irradiance by its estimated exposure.
    """

    name: str
    label: str
    response: CameraResponse | None = None
    vignetting: VignettingModel | None = None
    exposure_compensation: bool = False

    def __post_init__(self) -> None:
        if self.response is None and (self.vignetting is not None or self.exposure_compensation):
            raise ValueError(f"method {self.name!r}: vignetting correction and exposure compensation act on "
                             "irradiance and need the camera response")
        if not self.name or any(ch in self.name for ch in "/\\ "):
            raise ValueError(f"method name must be a non-empty word usable as a folder name, got {self.name!r}")

    def describe(self) -> dict[str, Any]:
        return {"name": self.name, "label": self.label,
                "response": None if self.response is None else repr(self.response),
                "vignetting": None if self.vignetting is None else repr(self.vignetting),
                "vignetting_model": None if self.vignetting is None else self.vignetting.info.get("method"),
                "exposure_compensation": self.exposure_compensation}


def make_methods(response: CameraResponse | None, *, vignetting_poly: VignettingModel | None = None,
                 vignetting_lut: VignettingModel | None = None, exposure_compensation: bool = False,
                 names: Sequence[str] | None = None) -> list[Method]:
    """The methods to compare, in order.

    names: among :data:`METHOD_NAMES`; default ``none, poly, lut`` plus ``poly+ec, lut+ec`` when
    ``exposure_compensation``. A method whose model is not given is an error naming the missing option.
    """
    if names is None:
        names = list(DEFAULT_METHODS)
        if exposure_compensation:
            names += ["poly" + EC_SUFFIX, "lut" + EC_SUFFIX]
    names = list(names)
    if not names:
        raise ValueError("names must list at least one method")
    bad = [n for n in names if n not in METHOD_NAMES]
    if bad:
        raise ValueError(f"unknown method(s) {', '.join(map(repr, bad))}; valid: {', '.join(METHOD_NAMES)} "
                         "('none' cannot be exposure-compensated: raw intensities are not linear in exposure)")
    if len(set(names)) != len(names):
        raise ValueError(f"names must not repeat a method, got {names}")
    models = {"poly": vignetting_poly, "lut": vignetting_lut}
    out = []
    for name in names:
        base = name.removesuffix(EC_SUFFIX)
        ec = name.endswith(EC_SUFFIX)
        if base == "none":
            out.append(Method("none", LABELS["none"]))
            continue
        if response is None:
            raise ValueError(f"method {name!r} needs the camera response (--response)")
        vig = models.get(base)
        if base in models and vig is None:
            raise ValueError(f"method {name!r} needs the {base} vignetting model (--vignetting-{base})")
        if vig is not None:
            _check_model_kind(base, vig)
        label = LABELS[base] + (" + exposure comp." if ec else "")
        out.append(Method(name, label, response, vig, ec))
    return out


def _check_model_kind(base: str, model: VignettingModel) -> None:
    """The ``poly`` method needs a polynomial model and ``lut`` a look-up table: a model of the other kind would be
    compared under the wrong label (ValueError: a model object passed as an argument)."""
    problem = _kind_mismatch(base, model)
    if problem is not None:
        source = model.info.get("source") if isinstance(getattr(model, "info", None), dict) else None
        raise ValueError(f"--vignetting-{base} holds {problem[0]}{f' ({source})' if source else ''}, {problem[1]}")


def _kind_mismatch(base: str, model: VignettingModel) -> tuple[str, str] | None:
    """None if ``model`` is of the kind the method ``base`` (``poly``, ``lut``) needs; else (what it holds, the fix)."""
    from radiometry.vignetting import LUTVignetting, PolynomialVignetting

    wanted = {"poly": PolynomialVignetting, "lut": LUTVignetting}[base]
    if isinstance(model, wanted):
        return None
    kind = "polynomial" if isinstance(model, PolynomialVignetting) else "look-up table (LUT)" \
        if isinstance(model, LUTVignetting) else type(model).__name__
    other = "lut" if base == "poly" else "poly"
    return (f"a {kind} vignetting model", f"not a {'polynomial' if base == 'poly' else 'look-up table'}; pass it as "
            f"--vignetting-{other}, or calibrate the other kind with 'radiomap vignetting --model {base}'")


def load_method_vignetting(path: str | Path, base: str) -> VignettingModel:
    """The vignetting model file of the method ``base`` (``poly`` or ``lut``; ``--vignetting-poly/-lut``): a file
    :func:`mapping.pipeline.load_vignetting_option` reads (a V array ``.npy`` is a LUT). A model of the other kind
    is a :class:`~radiometry.errors.CalibrationFileError` naming the file and the fix."""
    from mapping.colour import as_vignetting_model
    from mapping.pipeline import load_vignetting_option

    if base not in ("poly", "lut"):
        raise ValueError(f"base must be 'poly' or 'lut', got {base!r}")
    model = as_vignetting_model(load_vignetting_option(path))
    problem = _kind_mismatch(base, model)
    if problem is not None:
        raise CalibrationFileError(f"{path}: --vignetting-{base} holds {problem[0]}, {problem[1]}")
    return model


def equal_brightness(model: VignettingModel, height: int, width: int) -> LUTVignetting:
    """``V / mean(V)`` per channel at ``height x width`` as a LUT (see the module doc, "Equal brightness")."""
    v = model.evaluate(int(height), int(width)).astype(np.float64)
    mean = v.reshape(-1, v.shape[2]).mean(axis=0)
    info = {**model.info, "normalised": "per-channel image mean 1", "channel_means": mean.tolist(),
            "from": repr(model)}
    return LUTVignetting((v / mean).astype(np.float32), info=info)


# --------------------------------------------------------------------------------------------------
# exposure compensation (mapping/exposure_compensation.py, when installed)
# --------------------------------------------------------------------------------------------------
def exposure_compensation_available() -> bool:
    """Whether this installation has exposure compensation (:mod:`mapping.exposure_compensation`)."""
    try:
        _compensated_colour_class()
    except RadiomapError:
        return False
    return True


def _compensated_colour_class():
    """:class:`mapping.exposure_compensation.CompensatedColour`; :class:`RadiomapError` when not installed."""
    import importlib

    try:
        module = importlib.import_module("mapping.exposure_compensation")
    except ImportError as exc:
        raise RadiomapError(f"exposure compensation is not available in this installation ({exc}); "
                            "compare without it") from None
    cls = getattr(module, "CompensatedColour", None)
    if cls is None:
        raise RadiomapError("mapping/exposure_compensation.py has no CompensatedColour; compare without exposure "
                            "compensation")
    return cls


def irradiance_model(colour_model) -> IrradianceColour | None:
    """The :class:`~mapping.colour.IrradianceColour` behind a colour model (itself, or the one an exposure-
    compensating wrapper holds as ``base``); None for raw intensities."""
    if isinstance(colour_model, IrradianceColour):
        return colour_model
    base = getattr(colour_model, "base", None)
    return base if isinstance(base, IrradianceColour) else None


# --------------------------------------------------------------------------------------------------
# datasets with fixed poses and a shared progress bar
# --------------------------------------------------------------------------------------------------
class FixedPoses:
    """A dataset view whose frames carry given poses instead of their own (``None``: the frame has no pose,
    so :func:`mapping.pipeline.reconstruct` with ``poses="gt"`` skips it); ``on_frame`` is called once per
    frame read (the shared progress bar)."""

    def __init__(self, dataset, poses: Sequence[np.ndarray | None] | None = None, *,
                 on_frame: Callable[[], None] | None = None) -> None:
        if poses is not None and len(poses) != len(dataset):
            raise ValueError(f"poses must have one entry per frame ({len(dataset)}), got {len(poses)}")
        self.dataset = dataset
        self.poses = None if poses is None else list(poses)
        self.on_frame = on_frame
        self.name = getattr(dataset, "name", "")
        self.K = dataset.K
        self.width = dataset.width
        self.height = dataset.height

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int):
        frame = self.dataset[index]
        if self.on_frame is not None:
            self.on_frame()
        if self.poses is None:
            return frame
        pose = self.poses[index]
        return dataclasses.replace(frame, pose=None if pose is None else np.array(pose, dtype=np.float64))

    def ground_truth(self):
        return self.dataset.ground_truth()


# --------------------------------------------------------------------------------------------------
# map geometry and colour error
# --------------------------------------------------------------------------------------------------
@dataclass
class MapGeometry:
    """The surface of a map: a triangle mesh (TSDF) or surfels as small discs (6 triangles each).

    vertices (N, 3) float32 world, triangles (M, 3) int32, colours (N, 3) float32 map units, normals (N, 3)."""

    vertices: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray
    normals: np.ndarray
    kind: str = "mesh"

    def __len__(self) -> int:
        return int(self.vertices.shape[0])


def surfel_discs(position: np.ndarray, normal: np.ndarray, radius: np.ndarray, colour: np.ndarray, *,
                 sides: int = 6) -> MapGeometry:
    """Surfels as ``sides``-gons (centre + rim, ``sides`` triangles each) in their tangent planes, every
    vertex with the surfel's colour and normal: a mesh that ray casting can render."""
    p = np.asarray(position, np.float64).reshape(-1, 3)
    n = np.asarray(normal, np.float64).reshape(-1, 3)
    r = np.asarray(radius, np.float64).reshape(-1)
    c = np.asarray(colour, np.float32).reshape(-1, 3)
    count = p.shape[0]
    if count == 0:
        return MapGeometry(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32),
                           np.zeros((0, 3), np.float32), "surfel discs")
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    helper = np.where(np.abs(n[:, 0:1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    a = np.cross(n, helper)
    a /= np.maximum(np.linalg.norm(a, axis=1, keepdims=True), 1e-12)
    b = np.cross(n, a)
    angles = 2 * np.pi * np.arange(sides) / sides
    rim = p[:, None, :] + r[:, None, None] * (np.cos(angles)[None, :, None] * a[:, None, :]
                                              + np.sin(angles)[None, :, None] * b[:, None, :])
    verts = np.concatenate([p[:, None, :], rim], axis=1).reshape(-1, 3)
    base = (np.arange(count) * (sides + 1))[:, None]
    k = np.arange(sides)
    fan = np.stack([np.zeros(sides, np.int64), 1 + k, 1 + (k + 1) % sides], axis=1)  # (sides, 3)
    tris = (base[:, None, :] + fan[None, :, :]).reshape(-1, 3)
    return MapGeometry(verts.astype(np.float32), tris.astype(np.int32), np.repeat(c, sides + 1, axis=0),
                       np.repeat(n.astype(np.float32), sides + 1, axis=0), "surfel discs")


def map_geometry(backend) -> MapGeometry:
    """The fused surface of a backend: the TSDF's marching-cubes mesh, or the stable surfels as discs."""
    if hasattr(backend, "extract_mesh"):
        mesh = backend.extract_mesh()
        return MapGeometry(np.asarray(mesh.vertices, np.float32), np.asarray(mesh.triangles, np.int32),
                           np.asarray(mesh.colours, np.float32), np.asarray(mesh.normals, np.float32), "mesh")
    if hasattr(backend, "surfels"):
        s = backend.surfels(stable_only=True)
        return surfel_discs(s["position"], s["normal"], s["radius"], s["colour"])
    raise TypeError(f"cannot extract a surface from a {type(backend).__name__}: it has neither extract_mesh() "
                    "nor surfels()")


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
    if irradiance_model(colour_model) is not None:
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
    to_display = colour_model.to_display if irradiance_model(colour_model) is not None else FastForward(display_response)
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


# --------------------------------------------------------------------------------------------------
# results
# --------------------------------------------------------------------------------------------------
@dataclass
class MethodResult:
    """One method's run."""

    method: Method
    run: Any                        # mapping.pipeline.RunResult
    folder: Path
    colour_model: Any
    geometry: MapGeometry
    colour_error: ColourError | None
    files: dict[str, Path] = field(default_factory=dict)
    seconds: float = math.nan

    def row(self) -> dict[str, Any]:
        s = self.run.histogram.stats()
        err = self.colour_error
        return {"method": self.method.name, "description": self.method.label, "frames fused": self.run.fused,
                "pairs": s["count"], "L1 mean": s["mean"], "L1 median": s["median"], "L1 p90": s["p90"],
                "colour err": math.nan if err is None else err.mean,
                "colour err p90": math.nan if err is None else err.p90, "seconds": self.seconds}


@dataclass
class CompareResult:
    """The outcome of :func:`compare`."""

    results: list[MethodResult]
    stamps: np.ndarray
    poses: np.ndarray
    pose_source: str
    output: Path
    files: dict[str, Path]
    seconds: float
    ate: Any = None
    parameters: dict[str, Any] = field(default_factory=dict)
    renders: dict[str, Any] | None = None   # the side-by-side renders' camera and viewpoints (compare.json)

    def __getitem__(self, name: str) -> MethodResult:
        for r in self.results:
            if r.method.name == name:
                return r
        raise KeyError(f"no method {name!r}; the comparison ran {', '.join(self.names)}")

    @property
    def names(self) -> list[str]:
        return [r.method.name for r in self.results]

    def table(self) -> list[dict[str, Any]]:
        return [r.row() for r in self.results]

    def table_text(self) -> str:

        rows = []
        for row in self.table():
            rows.append({k: ("-" if isinstance(v, float) and not math.isfinite(v) else
                             round(v, 2) if isinstance(v, float) else v) for k, v in row.items()})
        return format_table(rows, TABLE_COLUMNS)

    @property
    def poses_identical(self) -> bool:
        """Every method fused the same frames at bit-identical poses."""
        first = self.results[0].run
        return all(np.array_equal(r.run.poses, first.poses) and np.array_equal(r.run.stamps, first.stamps)
                   for r in self.results[1:])

    def ranking(self, column: str = "L1 mean") -> list[str]:
        """Method names from best (smallest ``column``) to worst."""
        rows = self.table()
        return [r["method"] for r in sorted(rows, key=lambda r: (not math.isfinite(r[column]), r[column]))]


# --------------------------------------------------------------------------------------------------
# the comparison
# --------------------------------------------------------------------------------------------------
class ComparisonFolder(ResultsFolder):
    """The comparison's folder (``OUT``): a :class:`~mapping.export.ResultsFolder` whose results are the files of
    the module doc's layout and one results folder per method (:meth:`subfolder`). ``force`` removes the previous
    comparison's files and method folders (those its ``.radiomap-files.json`` lists, and folders named like a
    method) before the new one starts; the user's other files are left alone."""

    what = "comparison"
    markers = (MARKER, *ResultsFolder.markers)
    refusal = ("already holds a comparison or the results of a run; pass --force to overwrite them or choose another "
               "output folder")
    result_names = frozenset({MARKER, "compare.csv", "compare.txt", "histograms.png", "colour_error.png",
                              "renders.jpg", "report.html", "exposures.png", "trajectory.png", "config.json",
                              "summary.txt", RUNNING, MANIFEST})
    result_folders = frozenset(METHOD_NAMES)
    status_file = None


def compare(dataset, methods: Sequence[Method], *, output: str | Path, **options) -> CompareResult:
    """Compare ``methods`` on ``dataset`` into the folder ``output`` (see :func:`_compare`); the folder is locked
    against a second run (:class:`mapping.export.FolderLock`) from its creation until the comparison ends."""
    locks: list = []  # the folder's ComparisonFolder, then each method's ResultsFolder
    try:
        return _compare(dataset, methods, output=output, _locks=locks, **options)
    finally:
        for lock in reversed(locks):
            lock.release()


def _compare(dataset, methods: Sequence[Method], *, output: str | Path, _locks: list, backend: str = "tsdf",
             poses: str = "gt", voxel_size: float = 0.01, depth_max: float = 3.0,
             backend_options: Mapping[str, Any] | None = None, tracker_options: Mapping[str, Any] | None = None,
             brightness: str = "mean", scene=None, display_response: CameraResponse | None = None, views: int = 3,
             render_width: int = 320, progress: bool = True, force: bool = False, title: str | None = None,
             report_sections: Sequence[Any] | Callable[[CompareResult], Sequence[Any]] = (),
             parameters: Mapping[str, Any] | None = None,
             mesh_formats: Sequence[str] = ("ply", "glb"), config: Mapping[str, Any] | None = None,
             summary: Callable[[CompareResult], str] | None = None) -> CompareResult:
    """Fuse ``dataset`` once per method with identical poses; write the table, figures, meshes and report.

    dataset:          an :class:`~mapping.datasets.base.RGBDDataset` (range and stride applied).
    methods:          :class:`Method` list (:func:`make_methods`), in table order.
    output:           the comparison's folder (refused if it holds one, unless ``force``: then the previous
                      comparison's files and method folders are removed first, :class:`ComparisonFolder`).
    backend:          ``tsdf`` or ``surfel`` (:func:`mapping.pipeline.make_backend`), ``backend_options`` to it.
    poses:            ``gt`` (ground truth) or ``icp`` (tracked once by the first method, reused).
    brightness:       ``mean`` (equal brightness, the default) or ``calibrated`` (see the module doc).
    scene:            the true scene (a :class:`mapping.simulation.room.Room`) for the colour error and the
                      "truth" column of the renders; None for real data.
    display_response: linearises raw intensities for the colour error (default: the first method's response).
    views:            viewpoints of the side-by-side renders (0 for none); ``render_width`` pixels wide each.
    report_sections:  extra :class:`mapping.report.ReportSection` s placed before the results (e.g. the demo's
                      calibration accuracy), or a function of the (unfinished) :class:`CompareResult` returning them.
    mesh_formats:     formats of each method's mesh (:func:`mapping.export.write_mesh`: ply, glb, obj; PLY and GLB
                      by default, as :func:`mapping.pipeline.reconstruct` writes); the ``mesh_colours.npz`` with
                      map-unit colours is always written.
    config, summary:  written as ``config.json`` (a JSON document, e.g. the CLI's replay manifest) and
                      ``summary.txt`` (the text ``summary(result)`` returns) when the comparison has finished, in
                      the locked folder before it is marked complete: they belong to this run (its MANIFEST).
    """
    from mapping._open3d import o3d
    from mapping.export import write_mesh
    from mapping.pipeline import POSE_SOURCES, make_backend, make_tracker, reconstruct
    from radiometry.fileio import atomic_write_json, atomic_write_text

    methods = list(methods)
    if not methods:
        raise ValueError("methods must hold at least one Method")
    names = [m.name for m in methods]
    if len(set(names)) != len(names):
        raise ValueError(f"method names must be unique, got {names}")
    if poses not in POSE_SOURCES:
        raise ValueError(f"poses must be one of {', '.join(POSE_SOURCES)}, got {poses!r}")
    if brightness not in BRIGHTNESS:
        raise ValueError(f"brightness must be one of {', '.join(BRIGHTNESS)}, got {brightness!r}")
    if not (isinstance(voxel_size, (int, float)) and math.isfinite(voxel_size) and voxel_size > 0):
        raise ValueError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    if not (isinstance(views, (int, np.integer)) and views >= 0):
        raise ValueError(f"views must be a whole number >= 0 (0: no renders), got {views!r}")
    if views and not (isinstance(render_width, (int, np.integer)) and 16 <= render_width <= 4096):
        raise ValueError(f"render_width must be a whole number of pixels in 16..4096, got {render_width!r}")
    if len(dataset) == 0:
        raise RadiomapError(f"{getattr(dataset, 'name', 'the sequence')}: no frames to compare; check --frames")
    compensated = _compensated_colour_class() if any(m.exposure_compensation for m in methods) else None
    if display_response is None:
        display_response = next((m.response for m in methods if m.response is not None), None)

    from mapping.validation import check_run

    check_run(dataset, backend=backend, voxel_size=voxel_size, depth_max=depth_max, poses=poses,
              **{k: v for k, v in dict(backend_options or {}).items()
                 if k in ("block_resolution", "trunc_voxel_multiplier", "depth_min")})
    output = Path(output)
    top = ComparisonFolder(output, force=force)  # locked (created), marked RUNNING, the previous comparison removed
    _locks.append(top)
    start = time.perf_counter()
    height, width = dataset.height, dataset.width
    n = len(dataset)

    from radiometry.progress import progress_bar

    bar = progress_bar(total=n * len(methods), desc="compare", enabled=progress)
    results: list[MethodResult] = []
    fixed: list[np.ndarray | None] | None = None
    ate = None
    try:
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            for k, method in enumerate(methods):
                bar.set_postfix_str(method.name, refresh=True)
                colour_model = _colour_model(method, height, width, brightness, compensated)
                fusion = make_backend(backend, voxel_size=voxel_size, depth_max=depth_max, **dict(backend_options or {}))
                track = poses == "icp" and fixed is None
                view = FixedPoses(dataset, None if (poses == "gt" or track) else fixed, on_frame=bar.update)
                folder = top.subfolder(method.name)
                _locks.append(folder)  # released (and its files listed) when the comparison ends
                t0 = time.perf_counter()
                run = reconstruct(view, colour_model=colour_model, backend=fusion,
                                  tracker=make_tracker(depth_max=depth_max, **dict(tracker_options or {})) if track
                                  else None, poses="icp" if track else "gt", output=folder, progress=False,
                                  histogram_label=method.label, write_mesh=False)
                seconds = time.perf_counter() - t0
                if track:
                    fixed = _poses_by_frame(run, n)
                    ate = run.ate
                geometry = map_geometry(fusion)
                files = dict(run.files)
                if backend == "surfel" and hasattr(fusion, "export"):
                    files.update(fusion.export(folder.path, colour_model.to_display))
                files.update(write_mesh(folder.path, geometry.vertices, geometry.triangles, geometry.colours,
                                        colour_model.to_display, normals=geometry.normals, formats=mesh_formats))
                err = None
                if scene is not None:
                    err = colour_error(geometry, colour_model, scene, display_response=display_response,
                                       max_distance=max(3 * voxel_size, 0.03))
                result = MethodResult(method, run, folder.path, colour_model, geometry, err, files, seconds)
                results.append(result)
                atomic_write_json(folder.path / "compare_method.json",
                                  json_safe({"method": method.describe(), "row": result.row(),
                                           "colour_error": None if err is None else err.to_dict(),
                                           "geometry": {"kind": geometry.kind, "vertices": len(geometry),
                                                        "triangles": int(geometry.triangles.shape[0])}}))
                del fusion
    finally:
        bar.close()

    first = results[0].run
    result = CompareResult(results=results, stamps=first.stamps, poses=first.poses,
                           pose_source="ground truth" if poses == "gt" else f"ICP (tracked with '{methods[0].name}')",
                           output=output, files={}, seconds=0.0, ate=ate,
                           parameters={"backend": backend, "poses": poses, "voxel_size": voxel_size,
                                       "depth_max": depth_max, "brightness": brightness, "frames": n,
                                       "width": width, "height": height, **dict(parameters or {})})
    if not result.poses_identical:  # cannot happen by construction; never report a comparison that breaks it
        raise RadiomapError("the methods were fused at different poses; this is a bug, please report it")
    _write_outputs(result, dataset, scene, views=views, render_width=render_width, title=title,
                   report_sections=report_sections)
    if config is not None:
        result.files["config"] = atomic_write_json(output / "config.json", config)
    if summary is not None:
        result.files["summary"] = atomic_write_text(output / "summary.txt", summary(result))
    result.seconds = time.perf_counter() - start
    _write_json(result)
    top.complete()
    return result


def _colour_model(method: Method, height: int, width: int, brightness: str, compensated):
    if method.response is None:
        return RawIntensity()
    vig = method.vignetting
    if vig is not None and brightness == "mean":
        vig = equal_brightness(vig, height, width)
    base = IrradianceColour(method.response, vig, name=method.name)
    return compensated(base, compensate=True) if method.exposure_compensation else base


def _poses_by_frame(run, n: int) -> list[np.ndarray | None]:
    """Per dataset position: the pose the run fused that frame at, or None if it skipped it."""
    out: list[np.ndarray | None] = [None] * n
    k = 0
    for i, record in enumerate(run.records):
        if record.fused:
            out[i] = run.poses[k]
            k += 1
    return out


def _write_outputs(result: CompareResult, dataset, scene, *, views: int, render_width: int, title: str | None,
                   report_sections) -> None:
    from mapping.plots import save_histogram_figure
    from mapping.report import (ReportFigure, ReportSection, ReportTable, save_bar_chart, write_html_report)
    from radiometry.fileio import atomic_write_text

    out = result.output
    rows = result.table()
    files = result.files
    files["csv"] = atomic_write_text(out / "compare.csv", csv_text(rows, TABLE_COLUMNS))
    files["txt"] = atomic_write_text(out / "compare.txt", result.table_text() + "\n")
    histograms = {r.method.label: r.run.histogram for r in result.results if r.run.histogram.total}
    figures = []
    if histograms:
        save_histogram_figure(out / "histograms.png", histograms,
                              title="colour disagreement (L1, map vs new sample), normalised")
        files["histograms"] = out / "histograms.png"
        figures.append(ReportFigure(out / "histograms.png",
                                    "Normalised histograms of the L1 distance between the map's colour and each new "
                                    "sample before it is averaged in (the paper's Fig. 9); triangles on the top edge: means."))
    errors = {r.method.name: r.colour_error.mean for r in result.results if r.colour_error is not None}
    if errors:
        files["colour_error"] = save_bar_chart(out / "colour_error.png", errors,
                                               ylabel="mean |error| (8-bit levels)",
                                               title="mesh colour vs true radiance (after a global scale per channel)")
    if views > 0:
        grid = _render_views(result, dataset, scene, views=views, render_width=render_width)
        if grid is not None:
            files["renders"] = grid
    result.files = files

    # ---- the report
    p = result.parameters
    intro = [f"Sequence: {getattr(dataset, 'name', '') or '?'} ({p['frames']} frames, {p['width']}x{p['height']}); "
             f"backend {p['backend']}, voxel size {p['voxel_size']:g} m; poses: {result.pose_source}; every "
             "method fused the same frames at identical poses.",
             "L1: distance between the map's colour and each incoming sample just before it is averaged in, in 8-bit "
             "display levels summed over R, G, B (lower = more coherent colours). Colour err: mean absolute error "
             "per channel (8-bit levels) of the mesh colours against the true radiance after one global scale per "
             "channel (simulated sequences only).",
             "Brightness: " + ("each vignetting model is rescaled to a per-channel image mean of 1, so all methods "
                               "display at the raw images' average brightness and only the shape of the correction "
                               "differs." if p["brightness"] == "mean" else
                               "vignetting models as calibrated (V = 1 at the optical centre).")]
    sections = list(report_sections(result) if callable(report_sections) else report_sections)
    ranking = result.ranking()
    means = {r["method"]: r["L1 mean"] for r in rows}
    notes = [f"Ranking by L1 mean (best first): {', '.join(ranking)}."]
    if len(ranking) > 1 and math.isfinite(means[ranking[0]]) and math.isfinite(means[ranking[1]]):
        gap = means[ranking[1]] - means[ranking[0]]
        if gap < 0.01 * means[ranking[0]]:
            notes.append(f"{ranking[0]} leads {ranking[1]} by only {gap:.3f} levels ({100 * gap / means[ranking[0]]:.2f} "
                         "% of the mean): the L1 mean reacts to small errors of a correction only at second order, so "
                         "a gap this small says that both correct about equally well for this sequence"
                         + (" (the colour error against the truth is the finer measure)." if scene is not None else "."))
    if result.ate is not None:
        notes.append(f"ATE of the shared ICP trajectory: {100 * result.ate.rmse:.2f} cm RMSE over {result.ate.pairs} "
                     "frames.")
    summary = ReportSection("Results", notes,
                            tables=[ReportTable("", [_rounded(r) for r in rows], TABLE_COLUMNS)], figures=figures)
    sections.append(summary)
    if "colour_error" in files:
        sections.append(ReportSection("Colour against ground truth", [
            "Mean absolute error of every mesh vertex's colour against the true radiance of the surface it lies on, "
            "after one global scale per channel, in 8-bit display levels."],
            figures=[ReportFigure(files["colour_error"], "Mesh colour error per method")]))
    if "renders" in files:
        sections.append(ReportSection("The maps side by side", [
            "Each method's mesh ray cast on the CPU (Open3D RaycastingScene) from the same viewpoints of the "
            "trajectory; pixel colours are the vertex colours (display levels) interpolated with the hit "
            "triangle's barycentric coordinates, without shading. "
            + ("The last row is the simulated scene's true radiance (display scale of the LUT run)."
               if scene is not None else "")],
            figures=[ReportFigure(files["renders"], "Meshes from the same viewpoints (columns) per method (rows)")]))
    from mapping.report import run_sections, true_exposures_of

    per_run, run_files = run_sections(out, {r.method.label: r.folder for r in result.results},
                                      ground_truth=dataset.ground_truth(), true_exposures=true_exposures_of(dataset))
    sections += per_run
    files.update(run_files)
    links = []
    for r in result.results:
        for kind in ("mesh_ply", "mesh_glb", "surfels"):
            if kind in r.files:
                links.append((f"{r.method.name}: {Path(r.files[kind]).name}", str(r.files[kind])))
        links.append((f"{r.method.name}: metrics.json", str(r.folder / "metrics.json")))
    links += [("table (CSV)", str(files["csv"])), ("table (JSON)", str(out / MARKER))]
    sections.append(ReportSection("Files", ["PLY meshes (display colours) open in MeshLab or Blender; "
                                            "mesh_colours.npz beside each holds the map-unit colours."], links=links))
    files["report"] = write_html_report(out / "report.html", title=title or "radiomap: comparison of corrections",
                                        sections=sections, intro=intro)


def _rounded(row: dict[str, Any]) -> dict[str, Any]:
    return {k: (round(v, 2) if isinstance(v, float) and math.isfinite(v) else v) for k, v in row.items()}


def _render_views(result: CompareResult, dataset, scene, *, views: int, render_width: int) -> Path | None:
    from mapping.export import display_colours_uint8
    from mapping.report import MeshRaycaster, pick_viewpoints, render_scene_truth, save_render_grid, scaled_intrinsics

    if len(result.poses) == 0:
        return None
    picks = pick_viewpoints(result.poses, views)
    width = min(int(render_width), int(dataset.width))
    K, w, h = scaled_intrinsics(dataset.K, dataset.width, dataset.height, width)
    fused = [rec.index for rec in result.results[0].run.records if rec.fused]
    viewpoints = [{"pose_index": int(i), "frame": int(fused[i]) if i < len(fused) else None,
                   "timestamp": float(result.stamps[i]), "pose": np.asarray(result.poses[i], np.float64).tolist()}
                  for i in picks]
    columns: dict[str, list[np.ndarray]] = {}
    recorded: list[dict[str, Any]] = []      # per column: the viewpoints (pose indices) its tiles were rendered from

    def render_column(label: str, method: str | None, render_one) -> None:
        columns[label] = [render_one(np.asarray(v["pose"], np.float64)) for v in viewpoints]
        recorded.append({"label": label, "method": method, "views": [v["pose_index"] for v in viewpoints]})

    for r in result.results:
        g = r.geometry
        caster = MeshRaycaster(g.vertices, g.triangles, display_colours_uint8(g.colours, r.colour_model.to_display))
        render_column(r.method.label, r.method.name, lambda pose, caster=caster: caster.render(pose, K, w, h))
    if scene is not None:
        ref = _truth_reference(result)
        if ref is not None:
            model, scale = ref
            render_column("true radiance", None, lambda pose: render_scene_truth(
                scene, pose, K, w, h, lambda L: model.to_display((L * scale).astype(np.float32))))
    path = save_render_grid(result.output / "renders.jpg", columns,
                            row_labels=[f"view {j + 1}" for j in range(len(picks))])
    result.renders = {"file": path.name, "width": int(w), "height": int(h), "K": np.asarray(K).tolist(),
                      "viewpoints": viewpoints, "columns": recorded}
    return path


def _truth_reference(result: CompareResult):
    """(colour model, per-channel scale) used to display the true radiance: the LUT run's if there is one,
    else the run with the smallest colour error."""
    candidates = [r for r in result.results if r.colour_error is not None and irradiance_model(r.colour_model) is not None]
    if not candidates:
        return None
    lut = [r for r in candidates if r.method.name.removesuffix(EC_SUFFIX) == "lut"]
    best = lut[0] if lut else min(candidates, key=lambda r: r.colour_error.mean)
    return best.colour_model, np.asarray(best.colour_error.scale, np.float32)


def _write_json(result: CompareResult) -> None:
    from radiometry.fileio import atomic_write_json

    doc = {
        "format": "radiomap-compare", "version": 1,
        "parameters": result.parameters,
        "pose_source": result.pose_source, "poses_identical": result.poses_identical,
        "ate": None if result.ate is None else result.ate.to_dict(),
        "seconds": result.seconds,
        "ranking_l1_mean": result.ranking(),
        "columns": TABLE_COLUMNS,
        "table": result.table(),
        "methods": [{**r.method.describe(), "folder": r.folder.name,
                     "colour_model": r.colour_model.describe(),
                     "histogram": r.run.histogram.stats(),
                     "colour_error": None if r.colour_error is None else r.colour_error.to_dict(),
                     "geometry": {"kind": r.geometry.kind, "vertices": len(r.geometry),
                                  "triangles": int(r.geometry.triangles.shape[0])},
                     "files": {k: Path(v).relative_to(result.output).as_posix() for k, v in r.files.items()}}
                    for r in result.results],
        "files": {k: Path(v).name for k, v in result.files.items()},
        "renders": result.renders,
    }
    result.files["json"] = atomic_write_json(result.output / MARKER, doc)


__all__ = ["BASE_METHODS", "BRIGHTNESS", "ColourError", "CompareResult", "ComparisonFolder", "DEFAULT_METHODS",
           "FixedPoses", "MapGeometry", "Method", "METHOD_NAMES", "MethodResult", "colour_error", "compare",
           "equal_brightness", "exposure_compensation_available", "linear_colours", "load_method_vignetting",
           "make_methods", "map_geometry", "surfel_discs"]
