"""From options to the parts of a run: :class:`ReconstructConfig` (what ``radiomap reconstruct`` and
:func:`mapping.reconstruct_sequence` collect) and :func:`build_run`, which checks it, opens the sequence, loads
the models and builds the colour model, the fusion backend (:data:`BACKENDS`, :func:`make_backend`) and the
tracker (:func:`make_tracker`): the keyword arguments of :func:`mapping.pipeline.reconstruct`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mapping.colour import make_colour_model
from radiometry.api import as_vignetting
from mapping.fusion.base import FusionBackend
from mapping.validation import check_mesh_formats
from radiometry.errors import ModelMismatchError
from radiometry.registry import Registry


@dataclass
class ReconstructConfig:
    """Everything ``radiomap reconstruct`` collects; :func:`build_run` turns it into :func:`reconstruct`'s
    arguments."""

    sequence: Path
    output: Path | None = None
    response: Path | None = None
    vignetting: Path | None = None
    poses: Any = "icp"                          # --poses: icp | gt | a trajectory file or folder (mapping.pose_files)
    poses_max_difference: float = 0.02         # --poses-max-difference: seconds between a frame and its pose (TUM file)
    voxel_size: float = 0.01
    frames: slice = field(default_factory=lambda: slice(None))
    depth_scale: float | None = None
    intrinsics: Any = None
    backend: str = "tsdf"
    surfel_mesh: bool = False                   # surfel backend: also write a Poisson mesh (surfels_mesh.ply)
    format: str | None = None
    depth_max: float = 3.0
    block_resolution: int = 16
    trunc_voxel_multiplier: float = 8.0
    motion_model: str = "constant_velocity"
    tracker: str = "auto"                       # --tracker: auto | icp | hybrid | coloured-icp (TRACKERS)
    reference_exposure: float = 1.0             # --display-exposure: the histogram's display reference
    exposure_compensation: bool | None = None   # None: on when a response is given
    exposure_reference: str = "median"          # --mesh-exposure: median | first | k | r,g,b (first frame = 1)
    exposures: str | None = None                # --exposures FILE: given per-frame exposures instead of estimates
    holdout_every: int | None = None            # --holdout-every: withhold every N-th frame (mapping.holdout)
    colour_map: str | None = None               # --colour-map: rigid | non-rigid after fusion (mapping.colour_map)
    mesh_formats: tuple[str, ...] = ("ply",)    # --formats: the mesh files (mapping.validation.MESH_FORMATS)
    force: bool = False
    progress: bool = True


def _tsdf(*, voxel_size: float, depth_max: float, block_resolution: int, trunc_voxel_multiplier: float, **options):
    from mapping.fusion.tsdf import TSDFBackend

    return TSDFBackend(voxel_size=voxel_size, depth_max=depth_max, block_resolution=block_resolution,
                       trunc_voxel_multiplier=trunc_voxel_multiplier, **options)


def _surfel(*, voxel_size: float, depth_max: float, block_resolution: int, trunc_voxel_multiplier: float,
            surfel_mesh: bool = False, depth_min: float | None = None, **options):
    """The grid options do not apply to surfels; ``depth_min`` may only say what surfels do (fuse every depth
    above 0)."""
    from mapping.fusion.surfel import SurfelBackend

    if depth_min not in (None, 0, 0.0):
        raise ValueError(f"depth_min applies to the TSDF backend, got depth_min={depth_min} for surfels (they fuse "
                         "every depth above 0); drop depth_min or use backend='tsdf'")

    return SurfelBackend(depth_max=depth_max, mesh=surfel_mesh, **options)


#: fusion backends by name: builders taking the run's fusion options (the backend's own keywords pass through)
BACKENDS = Registry("backend", {"tsdf": _tsdf, "surfel": _surfel})


def make_backend(name: str, *, voxel_size: float = 0.01, depth_max: float = 3.0, block_resolution: int = 16,
                 trunc_voxel_multiplier: float = 8.0, surfel_mesh: bool = False, **options) -> FusionBackend:
    """A fusion backend by name (:data:`BACKENDS`), imported on first use; grid options do not apply to surfels,
    ``surfel_mesh`` (the surfel backend's Poisson mesh) only to them; ``options``: the backend's own keywords."""
    build = BACKENDS[name]
    if surfel_mesh and name != "surfel":
        raise ValueError(f"surfel_mesh applies to the surfel backend only, got backend {name!r} (the TSDF "
                         "backend always writes mesh.ply); pass backend='surfel' or surfel_mesh=False")
    from mapping.validation import check_fusion

    check_fusion(backend=name, voxel_size=voxel_size, depth_max=depth_max, block_resolution=block_resolution,
                 trunc_voxel_multiplier=trunc_voxel_multiplier, depth_min=options.get("depth_min", 0.1))
    if surfel_mesh:
        options["surfel_mesh"] = True
    return build(voxel_size=voxel_size, depth_max=depth_max, block_resolution=block_resolution,
                 trunc_voxel_multiplier=trunc_voxel_multiplier, **options)


#: trackers by name: the default, point-to-plane ICP with coloured ICP where its system is ill-conditioned or it
#: fails (:mod:`mapping.tracking_auto`), point-to-plane ICP alone (depth only), hybrid RGB-D odometry and coloured ICP
#: (depth and the colour the map holds; :mod:`mapping.tracking_photometric`)
TRACKERS = Registry("tracker", {"auto": "mapping.tracking_auto:AutoTracker",
                                "icp": "mapping.tracking:FrameToModelTracker",
                                "hybrid": "mapping.tracking_photometric:HybridTracker",
                                "coloured-icp": "mapping.tracking_photometric:ColouredICPTracker"})


def make_tracker(name: str = "auto", *, depth_max: float = 3.0, motion_model: str = "constant_velocity", **kwargs):
    """A frame-to-model tracker by name (:data:`TRACKERS`; default ``auto``, point-to-plane ICP with coloured ICP
    where it is ill-conditioned, :class:`mapping.tracking_auto.AutoTracker`)."""
    return TRACKERS[name](depth_max=depth_max, motion_model=motion_model, **kwargs)


def _given_exposures(path, dataset, response, vignetting, max_difference: float, command: str = "reconstruct"):
    """A :class:`mapping.exposure_compensation.given.GivenExposures` of ``path`` matched to ``dataset``; every
    frame must have a value (:class:`mapping.exposure_files.ExposureFileError` naming the file and ``command``
    otherwise, and no warning before it that the missing ones are fitted); with a response, the file's alignment is
    checked against the images (:mod:`mapping.exposure_alignment`: refused when a shift of its rows clearly explains
    them better, a warning when less clearly; the verdict goes to the estimator's settings)."""
    from mapping.exposure_compensation.given import GivenExposures
    from mapping.exposure_files import match_exposure_file
    from mapping.pose_files import _frame_keys

    table = match_exposure_file(dataset, path, max_difference=max_difference, every_frame=command)
    check = None
    if response is not None:    # the images' own exposure changes against the file's (mapping.exposure_alignment)
        from mapping.exposure_alignment import check_alignment, enforce

        check = check_alignment(dataset, table, response, vignetting)
        enforce(check, path)
    numbers = _frame_keys(dataset)[1]
    return GivenExposures(response, vignetting, known=dict(zip(numbers.tolist(), table.values)),
                          source=table.describe(), check=None if check is None else check.to_json())


def build_run(config: ReconstructConfig) -> dict[str, Any]:
    """The keyword arguments of :func:`mapping.pipeline.reconstruct` for a configuration (the dataset opened,
    the models loaded, backend and tracker built)."""
    from mapping.datasets import open_dataset
    from mapping.pose_files import resolve_poses
    from mapping.validation import check_config, check_run, config_options
    from radiometry.formats import load_response

    check_config(config)  # the option ranges (mapping/validation.py), before anything is read
    dataset = open_dataset(config.sequence, format=config.format, depth_scale=config.depth_scale,
                           intrinsics=config.intrinsics, frames=config.frames)
    poses = resolve_poses(config.poses, dataset, max_difference=config.poses_max_difference)  # a file read, matched
    check_run(dataset, poses=poses, **config_options(config))  # intrinsics, ground truth, memory
    if config.holdout_every is not None:  # 2 .. frames - 1, before anything is written
        from mapping.holdout import check_holdout_every

        check_holdout_every(config.holdout_every, len(dataset))
    # a file is loaded; a model object (mapping.reconstruct_sequence) is used as it is
    response = load_response(config.response) if isinstance(config.response, (str, Path)) else config.response
    vignetting = as_vignetting(config.vignetting)
    if vignetting is not None:  # refuse a model of another aspect ratio now, before any result is written
        try:
            vignetting.check_size(dataset.height, dataset.width)
        except ModelMismatchError as exc:
            raise ModelMismatchError(f"{config.vignetting}: {exc}") from None
    colour_model = make_colour_model(response, vignetting, reference_exposure=config.reference_exposure)
    if config.exposure_compensation or (config.exposure_compensation is None and response is not None):
        if response is None:
            raise ValueError("exposure compensation needs a response (it acts on irradiance); pass --response, "
                             "or --no-exposure-compensation")
        from mapping.exposure_compensation import CompensatedColour, parse_reference

        estimator = None if config.exposures is None else _given_exposures(config.exposures, dataset, response,
                                                                            vignetting, config.poses_max_difference)
        colour_model = CompensatedColour(colour_model, estimator,
                                         export_reference=parse_reference(config.exposure_reference))
    backend = make_backend(config.backend, voxel_size=config.voxel_size, depth_max=config.depth_max,
                           block_resolution=config.block_resolution,
                           trunc_voxel_multiplier=config.trunc_voxel_multiplier, surfel_mesh=config.surfel_mesh)
    tracker = make_tracker(config.tracker, depth_max=config.depth_max, motion_model=config.motion_model) \
        if poses == "icp" else None
    return {"dataset": dataset, "colour_model": colour_model, "backend": backend, "tracker": tracker,
            "poses": poses, "progress": config.progress, "holdout_every": config.holdout_every,
            "colour_map": config.colour_map, "mesh_formats": check_mesh_formats(config.mesh_formats)}


__all__ = ["BACKENDS", "TRACKERS", "ReconstructConfig", "build_run", "make_backend", "make_tracker"]
