"""A sequence to a coloured map in one call: :func:`reconstruct_sequence` (``radiomap reconstruct`` for Python).

>>> import mapping                                                                           # doctest: +SKIP
>>> result = mapping.reconstruct_sequence("room_seq", response="crf.npz", vignetting="vgn.npz", depth_max=5)
>>> result.fused, result.histogram.stats()["mean"]
>>> mesh = result.mesh_trimesh()          # trimesh.Trimesh, vertex colours as in mesh.ply (display sRGB)
>>> o3d_mesh = result.mesh_open3d()       # open3d.geometry.TriangleMesh, the same colours in [0, 1]

Keyword names are ``radiomap reconstruct``'s long option names with underscores (``--voxel-size`` ->
``voxel_size``; ``--no-progress`` is ``progress=False``); their values and defaults are the command's
(:class:`mapping.factory.ReconstructConfig`). The work is :func:`mapping.factory.build_run` and
:func:`mapping.pipeline.reconstruct`, exactly as the command does it.

Import cost: this module imports neither Open3D nor trimesh; they are loaded when a run or a mesh needs them.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

# the arguments reconstruct_sequence names itself; every other ReconstructConfig field is an **option
_OWN = ("sequence", "output", "response", "vignetting", "exposure_compensation", "poses", "force", "progress")


# radiomap reconstruct's option names whose ReconstructConfig field is spelled otherwise
_FIELD_OF = {"display_exposure": "reference_exposure", "mesh_exposure": "exposure_reference", "formats": "mesh_formats"}


def _option_fields() -> dict[str, str]:
    """``{keyword option: ReconstructConfig field}`` for every option beyond the named arguments."""
    from mapping.factory import ReconstructConfig

    option_of = {field: option for option, field in _FIELD_OF.items()}
    return {option_of.get(f.name, f.name): f.name for f in dataclasses.fields(ReconstructConfig) if f.name not in _OWN}


def option_names() -> list[str]:
    """The keyword options :func:`reconstruct_sequence` takes beyond its named arguments (the command's long
    option names with underscores)."""
    return list(_option_fields())


def reconstruct_sequence(path: str | os.PathLike, output: str | os.PathLike | None = None, *, response=None,
                         vignetting=None, exposure_compensation: bool = True, poses="icp", force: bool = False,
                         progress: bool = True, **options: Any) -> "Reconstruction":
    """Track (or take ground-truth poses), correct and fuse an RGB-D sequence; returns a :class:`Reconstruction`.

    path:        the sequence folder (TUM, 7-Scenes, Redwood or a radiomap simulation).
    output:      a results folder to write (``mesh.ply``, ``trajectory.txt``, ``metrics.json``, ... as
                 ``radiomap reconstruct -o``), or None: nothing is written anywhere (the mesh is taken
                 from the map in memory when asked for, through a temporary folder removed at once).
    response:    the camera response, a :class:`~radiometry.response.CameraResponse` or a file; None fuses raw
                 intensities (no correction).
    vignetting:  a vignetting model, an array V (H, W[, C]) or a file (``.npz``, ``.vgn``, ``vignette.png``,
                 ``.npy``); needs a response.
    exposure_compensation: estimate every frame's exposure and white balance against the map. It acts on
                 irradiance, so it applies when a response is given; without one the run fuses raw
                 intensities and ``result.exposure_compensation`` is False.
    poses:       ``icp`` (frame-to-model tracking), ``gt`` (the sequence's ground truth) or a trajectory file (a TUM
                 file, a Redwood ``.log``, a folder of 7-Scenes pose files: :mod:`mapping.pose_files`).
    force:       overwrite the results of an earlier run in ``output``.
    progress:    a progress bar on stderr when it is a terminal.
    options:     the command's other options: ``voxel_size``, ``frames`` (a slice or frame positions),
                 ``depth_max``, ``depth_scale``, ``intrinsics``, ``backend``, ``surfel_mesh``, ``format``, ...
                 (:func:`option_names`).
    """
    from mapping.factory import ReconstructConfig, build_run
    from mapping.pipeline import reconstruct
    from radiometry.response import CameraResponse

    fields = _option_fields()
    unknown = sorted(set(options) - set(fields))
    if unknown:
        raise TypeError(f"reconstruct_sequence() got unknown options {', '.join(unknown)}; valid: {', '.join(fields)}")
    sequence = Path(path)
    if not sequence.is_dir():
        from radiometry.errors import DatasetError

        raise DatasetError(f"{sequence}: no such sequence folder; pass the folder of an RGB-D sequence")
    if response is not None and not isinstance(response, (CameraResponse, str, os.PathLike)):
        raise TypeError(f"response must be a CameraResponse, a response file or None, got {type(response).__name__}")
    if isinstance(vignetting, np.ndarray):
        from radiometry.api import as_vignetting

        vignetting = as_vignetting(vignetting)
    compensate = bool(exposure_compensation) and response is not None
    if exposure_compensation and response is None:
        log.info("no response given: fusing raw intensities without exposure compensation")
    if options.get("mesh_exposure") is not None and not compensate:
        raise ValueError("mesh_exposure applies with exposure compensation only (a response and "
                         "exposure_compensation=True); without it the mesh colours are at display_exposure")
    options = {fields[k]: v for k, v in options.items() if not (k == "mesh_exposure" and v is None)}
    config = ReconstructConfig(sequence=sequence, output=None if output is None else Path(output),
                               response=_as_path(response), vignetting=_as_path(vignetting), poses=poses,
                               exposure_compensation=compensate, force=force, progress=progress, **options)
    kwargs = build_run(config)   # opens the dataset and loads the models: fails before anything is written
    folder = None
    if output is not None:
        from mapping.export import ResultsFolder

        folder = ResultsFolder(output, force=force)
    try:
        if folder is not None:
            folder.write_json("config.json", _config_record(config, kwargs))
        run = reconstruct(**kwargs, output=folder)   # as the command
    finally:
        if folder is not None:
            folder.release()  # the lock goes with the call: a later run into OUT (a shell, a notebook) may start
    return Reconstruction(run, config=config, colour_model=kwargs["colour_model"],
                          backend=kwargs["backend"] if folder is None else None,
                          output=None if folder is None else folder.path, exposure_compensation=compensate)


def _as_path(value):
    return Path(value) if isinstance(value, (str, os.PathLike)) else value


def _plain(value):
    """A JSON value for config.json: as the commands record it (:func:`mapping.export.plain_value`), arrays as
    lists and model objects as their description."""
    from mapping.export import plain_value

    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    try:
        return plain_value(value)
    except TypeError:
        return f"(object) {value!r}"


def _config_record(config, kwargs: dict) -> dict:
    """config.json of a run started from Python (the parameters in the command's names)."""
    from mapping.datasets import describe_dataset
    from radiometry import __version__

    dataset = kwargs["dataset"]
    return {"command": "mapping.reconstruct_sequence",
            "parameters": {f.name: _plain(getattr(config, f.name)) for f in dataclasses.fields(config)},
            "radiomap_version": __version__, "python": sys.version.split()[0],
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "dataset": describe_dataset(dataset),
            "colour_model": kwargs["colour_model"].describe()}


class Reconstruction:
    """The outcome of :func:`reconstruct_sequence`: the run (:class:`mapping.results.RunResult`, whose
    attributes it passes on: ``poses``, ``stamps``, ``histogram``, ``ate``, ``records``, ``metrics()``, ``fused``,
    ``status``, ``files``, ...) and the map's mesh in display colours.

    output:                the results folder, or None for a run without files.
    config:                the :class:`~mapping.factory.ReconstructConfig` it ran with.
    colour_model:          the colour model (``describe()``; with exposure compensation its ``estimator``).
    exposure_compensation: whether exposure compensation ran.

    Passed on with the run's attributes: ``colour_map``, the colour-map stage's outcome
    (:class:`mapping.colour_map.ColourMapOutcome`) with ``colour_map="rigid"`` or ``"non-rigid"``, else None, and
    ``holdout`` when ``holdout_every`` was given.
    """

    def __init__(self, run, *, config, colour_model, backend, output: Path | None,
                 exposure_compensation: bool) -> None:
        self.run = run
        self.config = config
        self.colour_model = colour_model
        self.output = output
        self.exposure_compensation = exposure_compensation
        self._backend = backend        # kept only without an output folder, to extract the mesh on demand
        self._mesh: dict[str, np.ndarray] | None = None

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        return getattr(self.run, name)

    def __repr__(self) -> str:
        stats = self.run.histogram.stats()
        where = "no files" if self.output is None else str(self.output)
        return (f"Reconstruction({self.run.fused} of {self.run.frames} frames fused, L1 mean {stats['mean']:.2f}, "
                f"{self.run.status}, {where})")

    # ------------------------------------------------------------------ the mesh
    def mesh_arrays(self) -> dict[str, np.ndarray]:
        """``vertices`` (N, 3) float, ``triangles`` (M, 3) int, ``colours`` (N, 3) uint8 display RGB (what
        ``mesh.ply`` holds) and ``normals`` (N, 3) or None. Raises :class:`RadiomapError` when the map has no
        mesh (no surface, or the surfel backend without ``surfel_mesh=True``)."""
        if self._mesh is None:
            if self.output is not None:
                self._mesh = _read_mesh(self._mesh_file(self.run.files, self.output))
            else:
                with tempfile.TemporaryDirectory(prefix="radiomap-mesh-") as tmp:
                    files = self._backend.export(Path(tmp), self.colour_model.display_for_export())
                    self._mesh = _read_mesh(self._mesh_file(files, Path(tmp)))
        return dict(self._mesh)

    def _mesh_file(self, files: dict, folder: Path) -> Path:
        from radiometry.errors import RadiomapError

        for key in ("mesh_ply", "mesh"):
            if key in files and Path(files[key]).suffix == ".ply":
                return Path(files[key])
        if self.config.backend == "surfel" and not self.config.surfel_mesh:
            raise RadiomapError("the surfel backend makes a mesh only with surfel_mesh=True (a Poisson mesh of the "
                                f"stable surfels); the surfels themselves are in {folder / 'surfels.ply'}"
                                if self.output is not None else
                                "the surfel backend makes a mesh only with surfel_mesh=True (a Poisson mesh of the "
                                "stable surfels); pass surfel_mesh=True or backend='tsdf'")
        raise RadiomapError(f"the map has no surface to mesh ({self.run.fused} of {self.run.frames} frames fused); "
                            "fuse more frames or check depth_max and the poses")

    def mesh_trimesh(self):
        """The map's mesh as a ``trimesh.Trimesh`` with RGBA uint8 vertex colours in display units (the
        bytes of ``mesh.ply``). A new object on every call."""
        import trimesh

        m = self.mesh_arrays()
        colours = np.concatenate([m["colours"], np.full((len(m["colours"]), 1), 255, np.uint8)], axis=1)
        extra = {} if m["normals"] is None else {"vertex_normals": m["normals"]}
        return trimesh.Trimesh(vertices=m["vertices"], faces=m["triangles"], vertex_colors=colours, process=False,
                               **extra)

    def mesh_open3d(self):
        """The map's mesh as an ``open3d.geometry.TriangleMesh`` (vertex colours = display colours / 255).
        A new object on every call."""
        from mapping._open3d import o3d

        m = self.mesh_arrays()
        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m["vertices"].astype(np.float64)),
                                         o3d.utility.Vector3iVector(m["triangles"].astype(np.int32)))
        mesh.vertex_colors = o3d.utility.Vector3dVector(m["colours"].astype(np.float64) / 255.0)
        if m["normals"] is not None:
            mesh.vertex_normals = o3d.utility.Vector3dVector(m["normals"].astype(np.float64))
        return mesh


def _read_mesh(path: Path) -> dict[str, np.ndarray]:
    """Vertices, triangles, uint8 RGB colours and normals of a vertex-coloured PLY."""
    import trimesh

    mesh = trimesh.load(path, file_type="ply", process=False, force="mesh")
    colours = np.asarray(mesh.visual.vertex_colors, dtype=np.uint8)[:, :3].copy()
    normals = mesh.vertex_normals if _has_normals(path) else None   # trimesh would compute them otherwise
    return {"vertices": np.asarray(mesh.vertices, dtype=np.float64).copy(),
            "triangles": np.asarray(mesh.faces, dtype=np.int64).copy(), "colours": colours,
            "normals": None if normals is None else np.asarray(normals, dtype=np.float64).copy()}


def _has_normals(path: Path) -> bool:
    with open(path, "rb") as fh:
        header = fh.read(4096).split(b"end_header", 1)[0]
    return b"property float nx" in header or b"property double nx" in header


__all__ = ["Reconstruction", "option_names", "reconstruct_sequence"]
