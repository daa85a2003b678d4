"""Colour-map optimisation (Zhou & Koltun, "Color Map Optimization for 3D Reconstruction with Consumer Depth
Cameras", SIGGRAPH 2014) after radiometric correction: an optional stage after fusion.

Open3D ships the method (``o3d.pipelines.color_map.run_rigid_optimizer`` / ``run_non_rigid_optimizer``): it
optimises each keyframe's camera pose (rigid) or pose plus a smooth image warp on a grid of anchors (non-rigid)
to maximise the photometric consistency of the keyframes on the mesh, then gives every vertex the average colour
of the keyframes that see it. It works on 8-bit images, so this stage feeds it images in *display levels*:

- with a response (irradiance maps), the radiometrically corrected frames: ``f^-1(I) / V / k`` (the frame's
  exposure ``k`` as the run's exposure compensation estimated it; 1 without it) shown through the run's export
  display (``colour_model.display_for_export()``: the response at the reference exposure, or at the sequence's
  median exposure with exposure compensation), so exposure and vignetting are gone before the optimiser sees
  them;
- without a response (``none``, raw intensities), the raw frames.

The optimised vertex colours come back in those display levels and are converted to map units through the
inverse of the same display (:meth:`mapping.colour.ColourModel.from_display`: ``f^-1(d) / k_ref`` per channel; the
identity for raw intensities), so the optimised mesh is rendered, compared and exported exactly as the plain one.

Keyframes (:func:`select_keyframes`): the fused frames are cut into consecutive windows of ``window`` frames
(default 5) and the sharpest frame of each window is kept (largest variance of the Laplacian of its grey image;
Zhou & Koltun also keep the sharpest frame of each interval). Iterations: ``iterations`` (default 100 for rigid,
50 for non-rigid, whose iteration costs 4-7x as much in scripts/study_colour_map.py; Open3D's tutorial uses 300 for
both).

Depth. The RGB-D images given to the optimiser carry the *mesh's* depth rendered at each keyframe's pose
(:class:`MeshRenderer`), not the sensor's: Open3D uses depth only to decide which vertices a keyframe sees, and
sensor depth has holes (a vertex over a hole counts as unseen, Open3D issue #4776) and, on Kinect v1 data such as
7-Scenes, is not registered to the colour image. The visibility depth range is the fusion's ``depth_max`` (Open3D's
default 2.5 m hides the far half of a room: black vertices). Poses go in as world-to-camera extrinsics (the inverse
of our camera-to-world poses; the wrong one gives the misaligned colours of Open3D issue #823). Open3D counts a
vertex as unseen where the Sobel gradient of the depth image exceeds ``depth_threshold_for_discontinuity_check``
(default 0.1 m): on floors and box tops seen at a slant that is most of the surface at 320x240 (each unseen vertex
then takes the colour of its 3 nearest seen ones, a smear); measured on the 30-frame sample room, raw colours, all
30 frames as keyframes, no iteration, PSNR at 10 of the frames: 22.8 dB at 0.1 against 27.2 dB at 0.3, 1 or 10 (the
fused mesh: 27.1 dB). This stage uses 0.3 (a depth step of ~7 cm between neighbours).

Vertices no keyframe sees. Open3D leaves them black or (``invisible_vertex_color_knn``, default 3) gives them the
mean colour of the 3 nearest seen vertices, which may lie far away: a smear wherever the keyframes miss what the
other fused frames saw (the border strips of the view, since Open3D also ignores a 10-pixel image margin). This
stage asks for black (knn 0) and gives those vertices their plain (fused) colour instead; the fraction is reported
(``unseen``).

Failure detection (:func:`colour_map_stage`). The optimiser can still fail (keyframes that see almost nothing of the
mesh, colours smeared by a pose that went astray). The stage renders the plain and the optimised mesh at check
frames through :func:`mapping.holdout.evaluate_holdout` and keeps the optimised mesh only if its held-out PSNR is
not more than ``tolerance_db`` (0.5 dB) below the plain mesh's, the optimiser moved the keyframes by at most 10 cm
(median; ``max_pose_change``: further is divergence, not refinement), the keyframes saw at least 10 % of the vertices
(``max_unseen`` 0.9: the others keep their plain colours, so this only catches keyframes that see almost nothing,
e.g. a depth range shorter than the scene) and at most ``max_black`` (1 %) of the vertices went black (all channels
below 2 levels where the plain mesh is not); otherwise the plain mesh is kept and the reason reported. Check frames
are frames withheld from fusion when the run withheld any (``--holdout-every``); else fused frames that are not
keyframes, which the plain mesh has averaged in and the optimised one has not: then the check favours the plain
mesh and catches failures, not small gains.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from radiometry.errors import RadiomapError
from radiometry.registry import validate_name

log = logging.getLogger(__name__)

#: the optimisers by name (``--colour-map``)
OPTIMISERS = ("rigid", "non-rigid")
#: default iterations per optimiser
ITERATIONS = {"rigid": 100, "non-rigid": 50}


class ColourMapError(RadiomapError):
    """The colour-map stage cannot run on this input (no mesh, too few keyframes, bad settings)."""


# ------------------------------------------------------------------ rendering a vertex-coloured mesh
class MeshRenderer:
    """Ray casting of a vertex-coloured triangle mesh (``o3d.t.geometry.RaycastingScene``): per pixel the hit
    triangle and its barycentric coordinates give the colour interpolated between the three vertex colours, and
    the hit distance along the ray the depth.

    ``renderer(pose, K, height, width) -> (colour (H, W, 3) float32, depth (H, W) float32 metres)``; ``pose``
    camera-to-world, pixel ``(u, v)`` centred at ``K^-1 (u, v, 1)``; colour in the units of ``colours`` (map
    units for the meshes of this module), 0 with depth 0 where no surface is hit (or a vertex colour is not
    finite)."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray) -> None:
        from mapping._open3d import o3d

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float32).reshape(-1, 3)
        self.triangles = np.ascontiguousarray(triangles, dtype=np.uint32).reshape(-1, 3)
        self.colours = np.asarray(colours, dtype=np.float32).reshape(-1, 3)
        if len(self.colours) != len(self.vertices):
            raise ValueError(f"colours must have one row per vertex ({len(self.vertices)}), got {len(self.colours)}")
        if len(self.triangles) and (int(self.triangles.max()) >= len(self.vertices)):
            raise ValueError("triangles index vertices that do not exist")
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(self.triangles):
            self.scene.add_triangles(o3d.core.Tensor(self.vertices), o3d.core.Tensor(self.triangles))
        self._o3d = o3d

    def __call__(self, pose: np.ndarray, K: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        pose = np.asarray(pose, dtype=np.float64)
        K = np.asarray(K, dtype=np.float64)
        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)  # z = 1
        dirs = cam @ pose[:3, :3].T
        origins = np.broadcast_to(pose[:3, 3], dirs.shape)
        colour = np.zeros((height, width, 3), np.float32)
        depth = np.zeros((height, width), np.float32)
        if not len(self.triangles):
            return colour, depth
        rays = self._o3d.core.Tensor(np.concatenate([origins, dirs], axis=-1).astype(np.float32))
        hit = self.scene.cast_rays(rays)
        t = hit["t_hit"].numpy()             # along a direction of camera z = 1: the depth itself
        ids = hit["primitive_ids"].numpy().astype(np.int64)
        uv = hit["primitive_uvs"].numpy()
        ok = np.isfinite(t) & (ids >= 0) & (ids < len(self.triangles))
        tri = self.triangles[ids[ok]].astype(np.int64)
        a, b = uv[ok, 0:1], uv[ok, 1:2]       # p = (1 - a - b) v0 + a v1 + b v2
        c = (1.0 - a - b) * self.colours[tri[:, 0]] + a * self.colours[tri[:, 1]] + b * self.colours[tri[:, 2]]
        finite = np.all(np.isfinite(c), axis=1)
        rows = np.flatnonzero(ok.reshape(-1))[finite]
        colour.reshape(-1, 3)[rows] = c[finite]
        depth.reshape(-1)[rows] = t[ok][finite]
        return colour, depth


# ------------------------------------------------------------------ display levels <-> map units
def display_frame(frame, colour_model, exposure: np.ndarray | None = None) -> np.ndarray:
    """A frame as the optimiser sees it, uint8 (H, W, 3): the raw frame for raw intensities, else its corrected
    irradiance ``f^-1(I) / V / k`` through the export display (exposure and vignetting removed)."""
    if colour_model.display_exposure() is None:
        return np.ascontiguousarray(frame.rgb, dtype=np.uint8)
    E = colour_model.unexposed(frame.rgb)[0]
    if exposure is not None:
        E = E / np.asarray(exposure, dtype=np.float32).reshape(1, 1, -1)
    shown = colour_model.display_for_export()(E)
    return np.ascontiguousarray(np.clip(np.rint(np.nan_to_num(shown)), 0, 255).astype(np.uint8))


# ------------------------------------------------------------------ keyframes
def sharpness(rgb: np.ndarray) -> float:
    """Variance of the 4-neighbour Laplacian of the grey image (higher: sharper)."""
    g = np.asarray(rgb, dtype=np.float32).mean(axis=2)
    lap = g[1:-1, :-2] + g[1:-1, 2:] + g[:-2, 1:-1] + g[2:, 1:-1] - 4.0 * g[1:-1, 1:-1]
    return float(lap.var()) if lap.size else 0.0


def select_keyframes(candidates: Sequence[int], frames, *, window: int = 5) -> list[int]:
    """One keyframe per run of ``window`` consecutive candidates (dataset positions): the sharpest
    (:func:`sharpness`). ``frames[i]`` is read once per candidate."""
    if not (isinstance(window, (int, np.integer)) and window >= 1):
        raise ValueError(f"window must be a whole number >= 1, got {window!r}")
    chosen = []
    candidates = list(candidates)
    for start in range(0, len(candidates), window):
        group = candidates[start:start + window]
        scores = [sharpness(frames[i].rgb) for i in group]
        chosen.append(group[int(np.argmax(scores))])
    return chosen


# ------------------------------------------------------------------ the optimisation
@dataclass
class ColourMapResult:
    """The optimised mesh and what it took.

    colours: (N, 3) float32 map units; display: (N, 3) float32 levels the optimiser returned; keyframes: dataset
    positions; poses: (K, 4, 4) the keyframes' camera-to-world poses after optimisation; unseen: fraction of the
    vertices no keyframe saw (they keep their plain colour); black: fraction of the vertices black in the result
    (all channels below 2 levels) that the plain mesh does not show black."""

    method: str
    vertices: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray
    display: np.ndarray
    keyframes: list[int]
    poses: np.ndarray
    iterations: int
    seconds: float
    unseen: float
    black: float
    pose_change: dict = field(default_factory=dict)

    def describe(self) -> dict:
        return {"method": self.method, "keyframes": [int(k) for k in self.keyframes], "iterations": self.iterations,
                "seconds": round(self.seconds, 3), "unseen_vertices": self.unseen, "black_vertices": self.black,
                "pose_change": self.pose_change}


def _pose_change(before: np.ndarray, after: np.ndarray) -> dict:
    """Largest and median change of the keyframe poses by the optimisation (cm, degrees)."""
    if not len(before):
        return {}
    shift = np.linalg.norm(after[:, :3, 3] - before[:, :3, 3], axis=1) * 100
    rel = np.einsum("kij,kil->kjl", before[:, :3, :3], after[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    return {"translation_cm_max": float(shift.max()), "translation_cm_median": float(np.median(shift)),
            "rotation_deg_max": float(angle.max()), "rotation_deg_median": float(np.median(angle))}


def optimise_colour_map(vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray, frames,
                        poses: Sequence[np.ndarray | None], colour_model, *, method: str = "rigid",
                        keyframes: Sequence[int] | None = None, window: int = 5, iterations: int | None = None,
                        depth_max: float = 3.0, anchors: int = 16, discontinuity: float = 0.3) -> ColourMapResult:
    """Run Zhou & Koltun's optimisation (Open3D) on a fused mesh; see the module doc.

    vertices, triangles, colours: the fused mesh, colours in map units of ``colour_model``.
    frames:     the run's frames (``frames[i]`` an :class:`~mapping.datasets.base.RGBDFrame`, a dataset).
    poses:      per position of ``frames``, the camera-to-world pose it was fused at, or None (not fused).
    method:     ``rigid`` or ``non-rigid``.
    keyframes:  positions to use (default: :func:`select_keyframes` over the fused frames, one per ``window``).
    iterations: optimiser iterations (default :data:`ITERATIONS`); 0 only re-colours from the keyframes.
    depth_max:  the visibility range (the fusion's depth range).
    anchors:    non-rigid: anchors of the image warp along the image height (Open3D's default 16).
    discontinuity: Open3D's ``depth_threshold_for_discontinuity_check`` (metres of its Sobel depth gradient, which
                is ~4x the depth step between neighbouring pixels); see the module doc."""
    from mapping._open3d import o3d

    method = validate_name(method, OPTIMISERS, "colour-map method")
    iterations = ITERATIONS[method] if iterations is None else iterations
    if not (isinstance(iterations, (int, np.integer)) and iterations >= 0):
        raise ValueError(f"iterations must be a whole number >= 0, got {iterations!r}")
    if not (np.isfinite(depth_max) and depth_max > 0):
        raise ValueError(f"depth_max must be a positive number of metres, got {depth_max!r}")
    if len(poses) != len(frames):
        raise ValueError(f"poses must have one entry per frame ({len(frames)}), got {len(poses)}")
    vertices = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    triangles = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    colours = np.asarray(colours, dtype=np.float32).reshape(-1, 3)
    if not len(vertices) or not len(triangles):
        raise ColourMapError("the map has no mesh to optimise the colours of (nothing fused often enough)")
    fused = [i for i, p in enumerate(poses) if p is not None]
    exposures = colour_model.frame_exposures()
    if exposures is not None:
        fused = [i for i in fused if int(frames[i].index) in exposures]
    chosen = list(keyframes) if keyframes is not None else select_keyframes(fused, frames, window=window)
    bad = [k for k in chosen if k not in fused]
    if bad:
        raise ColourMapError(f"keyframes {bad[:5]} were not fused (or their exposure fell back); choose fused frames")
    if len(chosen) < 2:
        raise ColourMapError(f"colour-map optimisation needs at least 2 keyframes, got {len(chosen)} (of {len(fused)} "
                             "fused frames); fuse more frames or use a smaller keyframe window")
    started = time.perf_counter()
    renderer = MeshRenderer(vertices, triangles, colours)
    to_display = colour_model.display_for_export()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(vertices.astype(np.float64)),
                                     o3d.utility.Vector3iVector(triangles.astype(np.int32)))
    plain_display = np.clip(np.nan_to_num(np.asarray(to_display(colours), np.float64)), 0, 255)
    mesh.vertex_colors = o3d.utility.Vector3dVector(plain_display / 255.0)
    images, params, before = [], [], []
    for k in chosen:
        frame = frames[k]
        pose = np.asarray(poses[k], dtype=np.float64)
        _, depth = renderer(pose, frame.K, frame.height, frame.width)
        shown = display_frame(frame, colour_model, None if exposures is None else exposures[int(frame.index)])
        images.append(o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(shown), o3d.geometry.Image(np.ascontiguousarray(depth)), depth_scale=1.0,
            depth_trunc=float(depth_max), convert_rgb_to_intensity=False))
        p = o3d.camera.PinholeCameraParameters()
        K = frame.K
        p.intrinsic = o3d.camera.PinholeCameraIntrinsic(frame.width, frame.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        p.extrinsic = np.linalg.inv(pose)       # world-to-camera (Open3D issue #823)
        params.append(p)
        before.append(pose)
    trajectory = o3d.camera.PinholeCameraTrajectory()
    trajectory.parameters = params
    common = dict(maximum_iteration=int(iterations), maximum_allowable_depth=float(depth_max),
                  invisible_vertex_color_knn=0,
                  depth_threshold_for_discontinuity_check=float(discontinuity))
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        if method == "rigid":
            out, traj = o3d.pipelines.color_map.run_rigid_optimizer(
                mesh, images, trajectory, o3d.pipelines.color_map.RigidOptimizerOption(**common))
        else:
            out, traj = o3d.pipelines.color_map.run_non_rigid_optimizer(
                mesh, images, trajectory,
                o3d.pipelines.color_map.NonRigidOptimizerOption(number_of_vertical_anchors=int(anchors), **common))
    display = np.asarray(out.vertex_colors, dtype=np.float64).reshape(-1, 3) * 255.0
    if len(display) != len(vertices):
        raise ColourMapError(f"Open3D's optimiser returned {len(display)} vertex colours for {len(vertices)} "
                             "vertices")
    display = np.clip(np.nan_to_num(display), 0.0, 255.0).astype(np.float32)
    after = np.stack([np.linalg.inv(np.asarray(p.extrinsic)) for p in traj.parameters])
    unseen = ~np.any(display > 0, axis=1)          # knn 0: Open3D leaves exactly 0 where no keyframe looked
    display[unseen] = plain_display[unseen]
    black = np.all(display < 2.0, axis=1) & ~np.all(plain_display < 2.0, axis=1)
    result_colours = colour_model.from_display(display).astype(np.float32)
    result_colours[unseen] = colours[unseen]
    return ColourMapResult(method=method, vertices=vertices, triangles=triangles.astype(np.int32),
                           colours=result_colours, display=display,
                           keyframes=chosen, poses=after, iterations=int(iterations),
                           seconds=time.perf_counter() - started, unseen=float(unseen.mean()),
                           black=float(black.mean()),
                           pose_change=_pose_change(np.stack(before), after))


# ------------------------------------------------------------------ the stage: optimise, check, keep or reject
@dataclass
class ColourMapOutcome:
    """What the stage did: the optimisation (None when it could not run), which mesh is kept (``optimised`` or
    ``plain``) and why (``reason`` in full, ``brief`` in a few words for a table column: ``check passed``, ``not
    run``, or the failed checks, e.g. ``PSNR fell, diverged``), the held-out figures of both meshes on the check
    frames and the stage's time in seconds (:func:`colour_map_for_run`: with the mesh extraction)."""

    method: str
    kept: str
    reason: str
    check: str
    plain: Any = None          # mapping.holdout.HoldoutResult of the plain mesh
    optimised: Any = None      # ... of the optimised mesh
    result: ColourMapResult | None = None
    brief: str = ""
    seconds: float = float("nan")

    @property
    def accepted(self) -> bool:
        return self.kept == "optimised"

    def to_dict(self) -> dict:
        def figures(h):
            return None if h is None else {"psnr": h.psnr, "l1": h.l1, "pixels": h.pixels,
                                           "frames_evaluated": len(h.evaluated), "frames": len(h.frames)}
        return {"method": self.method, "kept": self.kept, "reason": self.reason, "check_frames": self.check,
                "holdout_plain": figures(self.plain), "holdout_optimised": figures(self.optimised),
                "optimisation": None if self.result is None else self.result.describe(), "brief": self.brief,
                "seconds": round(self.seconds, 3)}

    def summary_line(self) -> str:
        return summary_line(self.to_dict())


def summary_line(doc: dict) -> str:
    """One line on a stage's outcome from its record (:meth:`ColourMapOutcome.to_dict`, ``colour_map.json``)."""
    plain, optimised = doc["holdout_plain"], doc["holdout_optimised"]
    if plain is None or optimised is None:
        return f"colour map ({doc['method']}): {doc['kept']} mesh kept: {doc['reason']}"
    return (f"colour map ({doc['method']}): {doc['kept']} mesh kept ({doc['reason']}); held-out PSNR "
            f"{plain['psnr']:.2f} -> {optimised['psnr']:.2f} dB, L1 {plain['l1']:.2f} -> {optimised['l1']:.2f} on "
            f"{doc['check_frames']}")


def check_positions(poses: Sequence[np.ndarray | None], keyframes: Sequence[int], *, count: int = 10) -> list[int]:
    """Up to ``count`` fused positions that are not keyframes, evenly spread: the check frames of a run that
    withheld none."""
    rest = [i for i, p in enumerate(poses) if p is not None and i not in set(keyframes)]
    if len(rest) <= count:
        return rest
    return [rest[int(j)] for j in np.linspace(0, len(rest) - 1, count).round().astype(int)]


def colour_map_stage(vertices: np.ndarray, triangles: np.ndarray, colours: np.ndarray, frames,
                     poses: Sequence[np.ndarray | None], colour_model, *, method: str = "rigid",
                     holdout: Sequence[tuple[int, np.ndarray]] | None = None, window: int = 5,
                     iterations: int | None = None, depth_max: float = 3.0, tolerance_db: float = 0.5,
                     max_black: float = 0.01, max_unseen: float = 0.9, min_pixel_ratio: float = 0.95,
                     max_pose_change: float = 0.1) -> ColourMapOutcome:
    """Optimise the colour map of a fused mesh and keep it only if the held-out metric does not call it a failure
    (see the module doc).

    frames, poses:  the run's frames and, per position, the pose it was fused at (None: not fused).
    holdout:        ``(position, pose)`` of frames withheld from fusion; None: check on fused non-keyframes.
    tolerance_db:   reject when the optimised mesh's held-out PSNR is more than this below the plain mesh's.
    max_black:      reject when more than this fraction of the vertices went black.
    max_unseen:     reject when no keyframe saw more than this fraction of the vertices.
    max_pose_change: reject when the optimiser moved the keyframes by more than this (metres, median over the
                    keyframes): a refinement of tracked poses that moves them this far has diverged.
    min_pixel_ratio: reject when the optimised mesh leaves fewer valid check pixels than this fraction of the
                    plain mesh's (black surfaces drop out of the metric instead of lowering it).
    Other keywords: :func:`optimise_colour_map`. An optimisation that cannot run (too few keyframes, Open3D
    raising) keeps the plain mesh with the reason."""
    from mapping.holdout import evaluate_holdout

    method = validate_name(method, OPTIMISERS, "colour-map method")
    if not (tolerance_db >= 0 and max_pose_change > 0 and all(0 <= v <= 1 for v in (max_black, max_unseen,
                                                                                     min_pixel_ratio))):
        raise ValueError(f"need tolerance_db >= 0, max_pose_change > 0 and max_black, max_unseen, min_pixel_ratio in "
                         f"[0, 1], got {tolerance_db}, {max_pose_change}, {max_black}, {max_unseen}, {min_pixel_ratio}")
    started = time.perf_counter()
    try:
        result = optimise_colour_map(vertices, triangles, colours, frames, poses, colour_model, method=method,
                                     window=window, iterations=iterations, depth_max=depth_max)
    except (ColourMapError, RuntimeError) as exc:   # Open3D raises RuntimeError on what it cannot handle
        log.warning("colour map (%s) not run: %s; the plain mesh is kept", method, exc)
        return ColourMapOutcome(method, "plain", f"not run: {exc}", "none", brief="not run",
                                seconds=time.perf_counter() - started)
    if holdout:
        positions = [int(i) for i, _ in holdout]
        check_poses = [np.asarray(p, dtype=np.float64) for _, p in holdout]
        check = f"{len(positions)} frames withheld from fusion"
    else:
        positions = check_positions(poses, result.keyframes)
        check_poses = [poses[i] for i in positions]
        check = f"{len(positions)} fused non-keyframes (favours the plain mesh)"
    check_frames = [frames[i] for i in positions]
    plain = evaluate_holdout(check_frames, check_poses, MeshRenderer(vertices, triangles, colours), colour_model)
    optimised = evaluate_holdout(check_frames, check_poses,
                                 MeshRenderer(result.vertices, result.triangles, result.colours), colour_model)
    reasons = {}   # brief -> in full
    moved = result.pose_change.get("translation_cm_median", 0.0) / 100
    if moved > max_pose_change:
        reasons["diverged"] = (f"the optimiser moved the keyframes by {100 * moved:.1f} cm (median; limit "
                               f"{100 * max_pose_change:g} cm): it diverged")
    if result.unseen > max_unseen:
        reasons["unseen"] = (f"no keyframe saw {100 * result.unseen:.1f} % of the vertices (check the depth range "
                             "and the poses)")
    if result.black > max_black:
        reasons["went black"] = f"{100 * result.black:.1f} % of the vertices went black"
    if not plain.pixels:
        reasons["no check frame"] = "no check frame could be evaluated"
    else:
        if optimised.pixels < min_pixel_ratio * plain.pixels:
            reasons["lost pixels"] = (f"the optimised mesh leaves {optimised.pixels} valid check pixels of the plain "
                                      f"mesh's {plain.pixels} (black or missing colour)")
        if not optimised.psnr >= plain.psnr - tolerance_db:
            reasons["PSNR fell"] = (f"held-out PSNR fell by {plain.psnr - optimised.psnr:.2f} dB (limit "
                                    f"{tolerance_db:g}; misaligned keyframes)")
    seconds = time.perf_counter() - started
    if reasons:
        log.warning("colour map (%s) rejected: %s; the plain mesh is kept", method, "; ".join(reasons.values()))
        return ColourMapOutcome(method, "plain", "rejected: " + "; ".join(reasons.values()), check, plain, optimised,
                                result, brief=", ".join(reasons), seconds=seconds)
    return ColourMapOutcome(method, "optimised", "passed the held-out check", check, plain, optimised, result,
                            brief="check passed", seconds=seconds)


def write_colour_map(folder, outcome: ColourMapOutcome, colour_model, *, normals: np.ndarray | None = None,
                     formats: Sequence[str] = ("ply",)) -> dict:
    """Write the optimised mesh beside the plain one (``mesh_colourmap.<fmt>``, and ``mesh_colourmap_colours.npz``
    with ``npz`` among the formats; only when it was kept) and ``colour_map.json`` (the outcome) into ``folder``;
    returns ``{name: path}``. The
    names are in :data:`mapping.export.RESULT_NAMES` (a ``--force`` run removes them)."""
    from pathlib import Path

    from mapping.export import write_mesh
    from radiometry.fileio import atomic_write_json

    folder = Path(folder)
    files = {}
    if outcome.accepted:
        r = outcome.result
        written = write_mesh(folder, r.vertices, r.triangles, r.colours, colour_model.display_for_export(),
                             normals=normals, formats=tuple(formats), stem="mesh_colourmap")
        files.update({k.replace("mesh", "colour_map_mesh", 1): v for k, v in written.items()})
    files["colour_map"] = atomic_write_json(folder / "colour_map.json", outcome.to_dict())
    return files


def colour_map_for_run(run, dataset, backend, colour_model, *, method: str, depth_max: float, folder=None,
                       formats: Sequence[str] = ("ply",), **options: Any) -> ColourMapOutcome:
    """The stage after :func:`mapping.pipeline.reconstruct`: the backend's fused surface
    (:func:`mapping.compare.geometry.map_geometry`), the run's poses by dataset position (``run.records``,
    ``run.poses``) and its withheld frames (``run.held_out_poses``, ``--holdout-every``) as the check; written into
    ``folder`` (a path, or None) by :func:`write_colour_map`. ``options``: :func:`colour_map_stage` keywords. The
    outcome's ``seconds`` count the mesh extraction, the optimisation and the check (not the writing).

    :func:`mapping.pipeline.reconstruct` runs it (its ``colour_map`` argument) before the results folder is marked
    complete: a crash or Ctrl-C here leaves the folder marked unfinished."""
    from mapping.compare.geometry import map_geometry

    started = time.perf_counter()
    geometry = map_geometry(backend)
    poses: list[np.ndarray | None] = [None] * len(run.records)
    fused = iter(run.poses)
    for i, record in enumerate(run.records):
        if record.fused:
            poses[i] = next(fused)
    holdout = [(i, p) for i, p in sorted(run.held_out_poses.items()) if p is not None]
    outcome = colour_map_stage(geometry.vertices, geometry.triangles, geometry.colours, dataset, poses, colour_model,
                               method=method, holdout=holdout or None, depth_max=depth_max, **options)
    outcome.seconds = time.perf_counter() - started
    if folder is not None:
        write_colour_map(folder, outcome, colour_model, normals=geometry.normals, formats=formats)
    return outcome


__all__ = ["ColourMapError", "ColourMapOutcome", "ColourMapResult", "ITERATIONS", "MeshRenderer", "OPTIMISERS",
           "check_positions", "colour_map_for_run", "colour_map_stage", "display_frame",
           "optimise_colour_map", "select_keyframes", "sharpness",
           "summary_line", "write_colour_map"]
