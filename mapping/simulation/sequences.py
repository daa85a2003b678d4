"""Simulated sequences with ground truth: a room (RGB-D, TUM layout), a white-paper sweep and
bracketed exposures; in memory (``iter_*``) or written to a folder (``simulate_*``).

Folder layout (other modules' loaders depend on it exactly)::

    SEQ/rgb/<timestamp>.png          uint8 RGB frames
    SEQ/depth/<timestamp>.png        uint16 depth, metres * 5000 (0 = no reading)
    SEQ/rgb.txt, SEQ/depth.txt       TUM lists: '# ' header lines, then 'timestamp rgb/<timestamp>.png'
    SEQ/groundtruth.txt              TUM 'timestamp tx ty tz qx qy qz qw', camera-to-world, OpenCV axes
    SEQ/intrinsics.txt               K, three rows of three numbers
    SEQ/radiomap_sequence.json       manifest: format "radiomap-sim", version 1, kind, width, height, K,
                                     depth_scale 5000, seed, n_frames, fps, ...
    SEQ/truth/response.npz           CameraResponse.save
    SEQ/truth/vignetting.npy         float32 (H, W, 3) true V (and vignetting.npz, a LUTVignetting)
    SEQ/truth/exposures.txt          'timestamp k gain_r gain_g gain_b' (effective exposure k * gain_c)
    SEQ/truth/light_scale.txt        'timestamp scale' (multiplies all scene radiance; 1 = nominal)
    SEQ/truth/camera.json            CameraSpec (re-create the camera with CameraSpec.load)
    room:     SEQ/truth/room.json (load_room; records the pictures hung on the walls by absolute path),
              SEQ/truth/room_mesh.ply (vertex colour = radiance / scale)
    paper:    SEQ/truth/paper.json, SEQ/truth/masks/<timestamp>.png (255 = sheet)
    brackets: SEQ/<name>.png, SEQ/times.txt ('name seconds'), SEQ/truth/radiance.npy (float32 (H, W, 3))

Timestamps start at :data:`TIMESTAMP_START` and step 1/30 s. Everything is deterministic for a seed:
noise and depth holes of frame ``i`` come from ``SeedSequence([seed, stream, i])``.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapping.export import RUNNING_MARKER
from mapping.publication import StagedResultsFolder
from mapping.simulation.render import Renderer, RenderResult
from mapping.simulation.room import Room, make_room
from mapping.simulation.sensor import DepthSensor
from mapping.simulation.targets import PaperScene, hdr_chart, make_paper_scene
from mapping.simulation.trajectory import (HandheldMotion, PaperSweep, paper_trajectory, pose_to_tum,
                                           room_trajectory)
from radiometry import __version__
from radiometry.fileio import atomic_write_json, atomic_write_text
from radiometry.images import write_depth, write_image
from radiometry.simulation import (Capture, CameraSpec, ExposureController, SimulatedCamera, default_intrinsics)
from radiometry.vignetting import LUTVignetting

SEQUENCE_FORMAT = "radiomap-sim"
SEQUENCE_VERSION = 1
MANIFEST = "radiomap_sequence.json"
DEPTH_SCALE = 5000
FPS = 30.0
TIMESTAMP_START = 1_600_000_000.0
KINDS = ("room", "paper", "brackets")

_STREAM_NOISE = 11
_STREAM_DEPTH = 12
_STREAM_FLICKER = 13


def timestamps(n: int, *, start: float = TIMESTAMP_START, fps: float = FPS) -> np.ndarray:
    """``start + i / fps`` for ``i < n``, float64."""
    return start + np.arange(n, dtype=np.float64) / fps


def stamp(t: float) -> str:
    """The file-name form of a timestamp (6 decimals, as TUM)."""
    return f"{t:.6f}"


def _rng(seed: int, stream: int, index: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), stream, int(index)]))


def resolve_camera(camera: CameraSpec | SimulatedCamera | str | None, width: int | None = None,
                   height: int | None = None, *, jpeg_quality: int | None = None) -> SimulatedCamera:
    """A :class:`SimulatedCamera` from a preset name, a spec or a camera, resized to ``width x
    height`` when they are given (the vignetting spec is resolution independent) and with
    ``jpeg_quality`` set when given."""
    if isinstance(camera, SimulatedCamera):
        spec = camera.spec
    elif isinstance(camera, CameraSpec):
        spec = camera
    elif camera is None or isinstance(camera, str):
        spec = CameraSpec.preset(camera or "xtion")
    else:
        raise TypeError(f"camera must be a preset name, a CameraSpec or a SimulatedCamera, got {type(camera).__name__}")
    changes: dict[str, Any] = {}
    if width is not None and width != spec.width:
        changes["width"] = width
    if height is not None and height != spec.height:
        changes["height"] = height
    if jpeg_quality is not None and jpeg_quality != spec.jpeg_quality:
        changes["jpeg_quality"] = jpeg_quality
    if isinstance(camera, SimulatedCamera) and not changes:
        return camera
    return SimulatedCamera(spec.replace(**changes) if changes else spec)


def settle_exposure(camera: SimulatedCamera, radiance: np.ndarray, controller: ExposureController, *,
                    frames: int = 60) -> ExposureController:
    """Let the controller's AE/AWB converge on a still view (noise-free frames), as a camera does in
    the seconds before recording starts. Returns the controller."""
    if controller.auto_exposure is None and controller.auto_white_balance is None:
        return controller
    for _ in range(frames):
        k, g = controller.settings()
        cap = camera.capture(radiance, exposure_time=k, gains=g, noise=False, jpeg=False)
        controller.observe(cap.image)
    return controller


@dataclass(frozen=True, eq=False)
class SimFrame:
    """One simulated frame: the image and (room) sensor depth, with everything that made them."""

    index: int
    timestamp: float
    pose: np.ndarray
    rgb: np.ndarray
    depth: np.ndarray | None
    capture: Capture
    render: RenderResult | None
    light_scale: float

    @property
    def exposure_time(self) -> float:
        return self.capture.exposure_time

    @property
    def gains(self) -> np.ndarray:
        return self.capture.gains


def _light_schedule(light_scale: Sequence[float] | Callable[[int], float] | float | None, n: int) -> np.ndarray:
    if light_scale is None:
        out = np.ones(n)
    elif callable(light_scale):
        out = np.array([float(light_scale(i)) for i in range(n)])
    elif np.isscalar(light_scale):
        out = np.full(n, float(light_scale))
    else:
        out = np.asarray(light_scale, dtype=np.float64)
        if out.shape != (n,):
            raise ValueError(f"light_scale must have one value per frame ({n}), got shape {out.shape}")
    if not np.all(np.isfinite(out)) or np.any(out <= 0):
        raise ValueError("light_scale values must be finite and positive")
    return out


def _awb_switch(auto_exposure: bool, auto_white_balance: bool | None) -> bool | None:
    """The AWB argument of :meth:`SimulatedCamera.controller` (None = as the spec says)."""
    if auto_white_balance is None:
        return None if auto_exposure else False
    return bool(auto_white_balance)


def light_step(n_frames: int, factor: float, *, at: float = 0.5) -> np.ndarray:
    """A light switched to ``factor`` times its brightness at fraction ``at`` of the sequence."""
    if not (factor > 0 and np.isfinite(factor)):
        raise ValueError(f"factor must be a positive number, got {factor!r}")
    out = np.ones(n_frames)
    out[int(round(at * n_frames)):] = factor
    return out


# ==================================================================================================
# room
# ==================================================================================================
def iter_room_frames(room: Room, camera: SimulatedCamera, poses: np.ndarray, *, K: np.ndarray, seed: int,
                     auto_exposure: bool = True, auto_white_balance: bool | None = None,
                     exposure_time: float | None = None, light_scale: Any = None,
                     depth_sensor: DepthSensor | None = DepthSensor(), supersample: int = 1,
                     settle: bool = True, start: float = TIMESTAMP_START, fps: float = FPS) -> Iterator[SimFrame]:
    """Render, expose and measure each pose in turn.

    The exposure loop (auto or fixed) is first settled on the first view (:func:`settle_exposure`)
    unless ``settle=False`` or ``exposure_time`` is given; with ``auto_exposure=False`` the settled
    (or given) exposure and gains stay fixed. ``auto_white_balance=None``: as the camera spec says
    with auto exposure, off without it.
    ``depth_sensor=None`` returns the true depth.
    """
    poses = np.asarray(poses, dtype=np.float64)
    n = poses.shape[0]
    scales = _light_schedule(light_scale, n)
    renderer = Renderer(room, K, camera.width, camera.height, supersample=supersample)
    awb = _awb_switch(auto_exposure, auto_white_balance)
    ctrl = camera.controller(auto_exposure=True, auto_white_balance=awb, exposure_time=exposure_time)
    first = None
    if settle and exposure_time is None and n:
        first = renderer.render(poses[0], light_scale=scales[0])
        settle_exposure(camera, first.radiance, ctrl)
    if not auto_exposure:
        ctrl = camera.controller(auto_exposure=False, auto_white_balance=awb,
                                 exposure_time=ctrl.exposure_time, gains=ctrl.gains)
    ts = timestamps(n, start=start, fps=fps)
    for i in range(n):
        r = first if (i == 0 and first is not None) else renderer.render(poses[i], light_scale=scales[i])
        k, g = ctrl.settings()
        cap = camera.capture(r.radiance, exposure_time=k, gains=g, rng=_rng(seed, _STREAM_NOISE, i))
        ctrl.observe(cap.image)
        depth = r.depth if depth_sensor is None else depth_sensor.measure(
            r, rng=_rng(seed, _STREAM_DEPTH, i), pose=poses[i], scene=room)
        yield SimFrame(i, float(ts[i]), poses[i], cap.image, depth, cap, r, float(scales[i]))


def simulate_room(out_dir: str | os.PathLike, *, camera: CameraSpec | SimulatedCamera | str | None = None,
                  seed: int = 0, n_frames: int = 100, width: int | None = None, height: int | None = None,
                  auto_exposure: bool = True, auto_white_balance: bool | None = None,
                  exposure_time: float | None = None, room: Room | None = None, light_scale: Any = None,
                  jpeg_quality: int | None = None, depth_sensor: DepthSensor | None = DepthSensor(),
                  supersample: int = 1, motion: HandheldMotion | None = None, mesh_spacing: float = 0.04,
                  pictures: Sequence[str | os.PathLike] = (), force: bool = False, progress: bool = True) -> Path:
    """Write a room RGB-D sequence with ground truth to ``out_dir`` (layout in the module doc);
    returns the folder. ``room`` defaults to ``make_room(seed, pictures=pictures)`` (``pictures``:
    PNG/JPEG files pasted on its walls); the hand-held trajectory comes from ``seed`` too. See
    :func:`iter_room_frames` for the exposure options."""
    _check_frames(n_frames)
    if room is not None and len(pictures):
        raise ValueError("pictures are pasted by make_room: give them to make_room(seed, pictures=...) when "
                         "passing room, or drop room")
    cam = resolve_camera(camera, width, height, jpeg_quality=jpeg_quality)
    room = room if room is not None else make_room(seed, pictures=pictures)   # bad pictures fail early
    with SequenceFolder(out_dir, force=force) as folder:
        out = folder.path
        K = default_intrinsics(cam.width, cam.height)
        poses = room_trajectory(room, n_frames, seed=seed, motion=motion or HandheldMotion())
        scales = _light_schedule(light_scale, n_frames)
        ts = timestamps(n_frames)
        exposures = []
        frames = iter_room_frames(room, cam, poses, K=K, seed=seed, auto_exposure=auto_exposure,
                                  auto_white_balance=auto_white_balance, exposure_time=exposure_time,
                                  light_scale=scales, depth_sensor=depth_sensor, supersample=supersample)
        for fr in _progress(frames, n_frames, "room", progress):
            name = stamp(fr.timestamp)
            write_image(out / "rgb" / f"{name}.png", fr.rgb)
            write_depth(out / "depth" / f"{name}.png", fr.depth, DEPTH_SCALE)
            exposures.append((fr.exposure_time, fr.gains))
        _write_tum_lists(out, ts, kind="room", seed=seed, depth=True)
        _write_groundtruth(out / "groundtruth.txt", ts, poses)
        _write_intrinsics(out / "intrinsics.txt", K)
        truth = _write_camera_truth(out, cam)
        _write_exposures(out / "truth" / "exposures.txt", [stamp(t) for t in ts], exposures)
        _write_light(out / "truth" / "light_scale.txt", ts, scales)
        room.save(out / "truth" / "room.json")
        colour_scale = room.write_mesh(out / "truth" / "room_mesh.ply", spacing=mesh_spacing)
        truth.update({"room": "truth/room.json", "room_mesh": "truth/room_mesh.ply"})
        ae = "auto" if auto_exposure else "fixed"
        awb = _awb_switch(auto_exposure, auto_white_balance)
        awb = cam.spec.auto_white_balance is not None if awb is None else awb
        _write_manifest(out, "room", cam, K, seed, n_frames, truth, {
            "exposure": ae, "white_balance": "auto" if awb else "fixed",
            "room_seed": room.seed, "mesh_colour": {"encoding": "linear radiance / scale", "scale": colour_scale},
            "supersample": supersample, "light_scale": "truth/light_scale.txt",
            "depth_sensor": None if depth_sensor is None else _dc(depth_sensor),
            "motion": _dc(motion or HandheldMotion())})
        folder.complete()
    return folder.final_path


# ==================================================================================================
# paper
# ==================================================================================================
def paper_exposure(camera: SimulatedCamera, scene: PaperScene, *, gains: Sequence[float], headroom: float = 0.72) -> float:
    """Exposure time that puts the sheet at irradiance ``headroom`` (of saturation) where ``V`` is 1,
    so that neither noise nor flicker of up to ~25 % clips it."""
    g = float(np.max(np.asarray(gains, float)))
    peak = scene.params.sheet_albedo * (1 + 3 * scene.params.paper_texture) * scene.params.irradiance / np.pi
    return headroom / (g * peak)


def flicker_schedule(n_frames: int, amplitude: float, *, seed: int) -> np.ndarray:
    """Per-frame light scale ``1 + amplitude * x`` with ``x`` a smooth random signal in [-1, 1] (mains
    flicker beating with the frame rate, plus a slow drift)."""
    if not (0 <= amplitude < 0.5):
        raise ValueError(f"flicker amplitude must be within [0, 0.5), got {amplitude!r}")
    if amplitude == 0:
        return np.ones(n_frames)
    rng = _rng(seed, _STREAM_FLICKER, 0)
    t = np.arange(n_frames) / FPS
    x = 0.6 * np.sin(2 * np.pi * rng.uniform(0.2, 0.6) * t + rng.uniform(0, 6.3)) \
        + 0.4 * np.sin(2 * np.pi * rng.uniform(1.5, 4.0) * t + rng.uniform(0, 6.3))
    return 1.0 + amplitude * x


def iter_paper_frames(scene: PaperScene, camera: SimulatedCamera, poses: np.ndarray, *, K: np.ndarray, seed: int,
                      exposure_time: float | None = None, gains: Sequence[float] | None = None,
                      light_scale: Any = None, depth_sensor: DepthSensor | None = None,
                      start: float = TIMESTAMP_START, fps: float = FPS) -> Iterator[SimFrame]:
    """Frames of the white-paper sweep with fixed exposure and gains (default: the spec's gains and
    :func:`paper_exposure`). ``render.face == scene.sheet_face`` is the true sheet mask."""
    poses = np.asarray(poses, dtype=np.float64)
    n = poses.shape[0]
    scales = _light_schedule(light_scale, n)
    g = np.asarray(camera.spec.gains if gains is None else gains, float)
    k = paper_exposure(camera, scene, gains=g) if exposure_time is None else float(exposure_time)
    renderer = Renderer(scene, K, camera.width, camera.height)
    ts = timestamps(n, start=start, fps=fps)
    for i in range(n):
        r = renderer.render(poses[i], light_scale=scales[i])
        cap = camera.capture(r.radiance, exposure_time=k, gains=g, rng=_rng(seed, _STREAM_NOISE, i))
        depth = None if depth_sensor is None else depth_sensor.measure(r, rng=_rng(seed, _STREAM_DEPTH, i))
        yield SimFrame(i, float(ts[i]), poses[i], cap.image, depth, cap, r, float(scales[i]))


def simulate_paper(out_dir: str | os.PathLike, *, camera: CameraSpec | SimulatedCamera | str | None = None,
                   seed: int = 0, n_frames: int = 300, width: int | None = None, height: int | None = None,
                   exposure_time: float | None = None, flicker: float = 0.0, jpeg_quality: int | None = None,
                   sweep: PaperSweep | None = None, scene: PaperScene | None = None, write_depth_images: bool = True,
                   force: bool = False, progress: bool = True) -> Path:
    """Write a white-paper vignetting-calibration sweep (exposure and white balance fixed; optional
    smooth light ``flicker`` of that relative amplitude, recorded in truth/light_scale.txt)."""
    _check_frames(n_frames)
    cam = resolve_camera(camera, width, height, jpeg_quality=jpeg_quality)
    scales = flicker_schedule(n_frames, flicker, seed=seed)
    with SequenceFolder(out_dir, force=force) as folder:
        out = folder.path
        scene = scene if scene is not None else make_paper_scene(seed)
        K = default_intrinsics(cam.width, cam.height)
        poses = paper_trajectory(n_frames, K, cam.width, cam.height, seed=seed, sweep=sweep or PaperSweep())
        ts = timestamps(n_frames)
        gains = np.asarray(cam.spec.gains, float)
        k = paper_exposure(cam, scene, gains=gains) if exposure_time is None else float(exposure_time)
        sensor = DepthSensor(projector_shadow=False) if write_depth_images else None
        coverage = np.zeros((cam.height, cam.width), np.int32)
        frames = iter_paper_frames(scene, cam, poses, K=K, seed=seed, exposure_time=k, gains=gains,
                                   light_scale=scales, depth_sensor=sensor)
        for fr in _progress(frames, n_frames, "paper", progress):
            name = stamp(fr.timestamp)
            write_image(out / "rgb" / f"{name}.png", fr.rgb)
            if fr.depth is not None:
                write_depth(out / "depth" / f"{name}.png", fr.depth, DEPTH_SCALE)
            mask = fr.render.face == scene.sheet_face
            coverage += mask
            write_image(out / "truth" / "masks" / f"{name}.png", mask.astype(np.uint8) * 255)
        _write_tum_lists(out, ts, kind="paper", seed=seed, depth=write_depth_images)
        _write_groundtruth(out / "groundtruth.txt", ts, poses)
        _write_intrinsics(out / "intrinsics.txt", K)
        truth = _write_camera_truth(out, cam)
        _write_exposures(out / "truth" / "exposures.txt", [stamp(t) for t in ts], [(k, gains)] * n_frames)
        _write_light(out / "truth" / "light_scale.txt", ts, scales)
        atomic_write_json(out / "truth" / "paper.json", scene.to_dict())
        truth.update({"paper": "truth/paper.json", "masks": "truth/masks"})
        _write_manifest(out, "paper", cam, K, seed, n_frames, truth, {
            "exposure": "fixed", "white_balance": "fixed", "exposure_time": k, "flicker": flicker,
            "light_scale": "truth/light_scale.txt", "sheet_coverage_min": int(coverage.min()),
            "sheet_coverage_median": float(np.median(coverage)), "sweep": _dc(sweep or PaperSweep()),
            "depth": write_depth_images})
        folder.complete()
    return folder.final_path


# ==================================================================================================
# brackets
# ==================================================================================================
def bracket_times(n: int = 9, *, shortest: float = 1e-3, ratio: float = 2.0) -> np.ndarray:
    """``shortest * ratio**i`` seconds for ``i < n`` (default 1/1000 s ... 0.256 s, doubling)."""
    if not (isinstance(n, (int, np.integer)) and 2 <= n <= 30):
        raise ValueError(f"n must be a whole number of exposures in 2..30, got {n!r}")
    if not (shortest > 0 and ratio > 1):
        raise ValueError(f"need shortest > 0 and ratio > 1, got {shortest!r}, {ratio!r}")
    return shortest * ratio ** np.arange(n, dtype=np.float64)


BRACKET_SCENES = ("chart", "room")


def bracket_radiance(width: int, height: int, *, seed: int, scene: str = "chart", times: Sequence[float]) -> np.ndarray:
    """The static radiance of a bracket stack: the HDR chart (``scene="chart"``) spanning the range
    the exposure ``times`` can record, or a view of :func:`make_room` (``scene="room"``) scaled so that
    its median reaches 30 % of saturation at the middle exposure (the geometric mean of ``times``)."""
    t = np.asarray(times, float)
    if scene == "chart":
        return hdr_chart(width, height, seed=seed, radiance_range=(0.3 / t.max(), 0.5 / t.min()))
    if scene == "room":
        from mapping.simulation.trajectory import look_at

        room = make_room(seed)
        lo, hi = room.camera_bounds
        eye = (lo + hi) / 2
        target = np.array([room.size[0] * 0.9, room.size[1] * 0.8, 0.7])
        r = Renderer(room, default_intrinsics(width, height), width, height).render(look_at(eye, target))
        rad = r.radiance
        t_mid = float(np.sqrt(t.min() * t.max()))
        return (rad * (0.3 / t_mid) / max(float(np.median(rad)), 1e-9)).astype(np.float32)
    raise ValueError(f"unknown bracket scene {scene!r}; valid names: chart, room")


def iter_brackets(camera: SimulatedCamera, radiance: np.ndarray, times: Sequence[float], *, seed: int,
                  gains: Sequence[float] | None = None) -> Iterator[Capture]:
    """Captures of one static radiance field at each exposure time (fixed gains, independent noise)."""
    g = camera.spec.gains if gains is None else gains
    for i, k in enumerate(times):
        yield camera.capture(radiance, exposure_time=float(k), gains=g, rng=_rng(seed, _STREAM_NOISE, i))


def simulate_brackets(out_dir: str | os.PathLike, *, camera: CameraSpec | SimulatedCamera | str | None = None,
                      seed: int = 0, times: Sequence[float] | None = None, n_exposures: int = 9,
                      width: int | None = None, height: int | None = None, scene: str = "chart",
                      jpeg_quality: int | None = None, force: bool = False, progress: bool = True) -> Path:
    """Write a bracketed exposure stack: ``SEQ/exposure_XX.png``, ``SEQ/times.txt`` ('name seconds')
    and the truth (response, vignetting, exposures, camera, the radiance image)."""
    cam = resolve_camera(camera, width, height, jpeg_quality=jpeg_quality)
    times = bracket_times(n_exposures) if times is None else np.asarray(times, dtype=np.float64)
    if times.ndim != 1 or times.size < 2 or not np.all(np.isfinite(times)) or np.any(times <= 0):
        raise ValueError(f"times must be at least 2 positive exposure times in seconds, got {times!r}")
    if scene not in BRACKET_SCENES:
        raise ValueError(f"unknown bracket scene {scene!r}; valid names: {', '.join(BRACKET_SCENES)}")
    with SequenceFolder(out_dir, force=force) as folder:
        out = folder.path
        radiance = bracket_radiance(cam.width, cam.height, seed=seed, scene=scene, times=times)
        names = [f"exposure_{i:02d}.png" for i in range(times.size)]
        gains = np.asarray(cam.spec.gains, float)
        caps = iter_brackets(cam, radiance, times, seed=seed, gains=gains)
        for name, cap in zip(names, _progress(caps, times.size, "brackets", progress)):
            write_image(out / name, cap.image)
        atomic_write_text(out / "times.txt", "".join(f"{n} {t:.9g}\n" for n, t in zip(names, times)))
        truth = _write_camera_truth(out, cam)
        _write_exposures(out / "truth" / "exposures.txt", names, [(t, gains) for t in times], key="name")
        _save_npy(out / "truth" / "radiance.npy", radiance)
        truth.update({"radiance": "truth/radiance.npy"})
        K = default_intrinsics(cam.width, cam.height)
        _write_manifest(out, "brackets", cam, K, seed, int(times.size), truth, {
            "images": names, "times": times.tolist(), "times_file": "times.txt", "scene": scene,
            "exposure": "bracketed", "white_balance": "fixed"})
        folder.complete()
    return folder.final_path


# ==================================================================================================
# writing
# ==================================================================================================
class SequenceFolder(StagedResultsFolder):
    """A simulated sequence's folder (the layout in the module doc), locked while it is written and marked
    ``RUNNING`` until it is complete (:class:`mapping.export.ResultsFolder`). A non-empty folder is refused unless
    ``force``; with ``force`` an earlier simulation there (its manifest, or ``RUNNING`` if it was interrupted) is
    replaced so that no stale frame survives (a complete one stands until the new one is complete and published
    as one set, its manifest last: :class:`mapping.publication.StagedResultsFolder`; an interrupted one is removed
    first), other content is left alone, and a folder that holds no simulation is written into as it is (with a
    warning)."""

    what = "simulation"
    markers = (MANIFEST, RUNNING_MARKER)
    refusal = refusal_other = "is not empty; pass --force to overwrite it or choose an empty folder"
    result_names = frozenset({"rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.txt", "times.txt", MANIFEST,
                              RUNNING_MARKER, "exposure_*.png"})
    owned_folders = frozenset({"rgb", "depth", "truth"})
    clean_unmarked = False
    listing = False
    status_file = None
    primary = MANIFEST

    def _previous_complete(self) -> bool:
        return (self.path / MANIFEST).is_file() and not (self.path / RUNNING_MARKER).exists()


def _check_frames(n_frames: int) -> None:
    if not (isinstance(n_frames, (int, np.integer)) and n_frames >= 1):
        raise ValueError(f"n_frames must be a whole number >= 1, got {n_frames!r}")


def _progress(it, total: int, kind: str, enabled: bool):
    from radiometry.progress import progress_bar

    return progress_bar(it, total=total, desc=f"simulate {kind}", enabled=enabled, leave=False)


def _dc(obj: Any) -> dict[str, Any]:
    from dataclasses import fields

    return {f.name: (list(v) if isinstance(v := getattr(obj, f.name), tuple) else v) for f in fields(obj)}


def _write_tum_lists(out: Path, ts: np.ndarray, *, kind: str, seed: int, depth: bool) -> None:
    head = f"# radiomap simulation: {kind}, seed {seed}\n# timestamp filename\n"
    atomic_write_text(out / "rgb.txt", "# color images\n" + head
                      + "".join(f"{stamp(t)} rgb/{stamp(t)}.png\n" for t in ts))
    if depth:
        atomic_write_text(out / "depth.txt", "# depth maps (uint16, metres * 5000)\n" + head
                          + "".join(f"{stamp(t)} depth/{stamp(t)}.png\n" for t in ts))


def _write_groundtruth(path: Path, ts: np.ndarray, poses: np.ndarray) -> None:
    lines = ["# ground truth trajectory: camera-to-world, camera x right, y down, z forward\n",
             "# timestamp tx ty tz qx qy qz qw\n"]
    for t, T in zip(ts, poses):
        tr, q = pose_to_tum(T)
        lines.append(f"{stamp(t)} {tr[0]:.9f} {tr[1]:.9f} {tr[2]:.9f} {q[0]:.9f} {q[1]:.9f} {q[2]:.9f} {q[3]:.9f}\n")
    atomic_write_text(path, "".join(lines))


def _write_intrinsics(path: Path, K: np.ndarray) -> None:
    atomic_write_text(path, "".join(" ".join(f"{v:.10g}" for v in row) + "\n" for row in K))


def _save_npy(path: Path, array: np.ndarray) -> None:
    from radiometry.fileio import atomic_path

    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.save(fh, np.ascontiguousarray(array), allow_pickle=False)


def _write_camera_truth(out: Path, cam: SimulatedCamera) -> dict[str, str]:
    truth = out / "truth"
    cam.response.save(truth / "response.npz")
    _save_npy(truth / "vignetting.npy", cam.vignetting)
    cam.spec.save(truth / "camera.json")
    LUTVignetting(cam.vignetting, info={"source": "radiomap simulation (ground truth)",
                                        "vignetting": cam.spec.vignetting.to_dict()}).save(truth / "vignetting.npz")
    return {"response": "truth/response.npz", "vignetting": "truth/vignetting.npy", "camera": "truth/camera.json",
            "exposures": "truth/exposures.txt", "vignetting_model": "truth/vignetting.npz"}


def _write_exposures(path: Path, keys: Sequence[str], exposures: Sequence[tuple[float, Any]], *,
                     key: str = "timestamp") -> None:
    lines = [f"# per-frame exposure: {key} exposure_time_s gain_r gain_g gain_b\n",
             "# the effective exposure of channel c is exposure_time_s * gain_c\n"]
    for name, (k, g) in zip(keys, exposures):
        g = np.asarray(g, float)
        lines.append(f"{name} {k:.9g} {g[0]:.9g} {g[1]:.9g} {g[2]:.9g}\n")
    atomic_write_text(path, "".join(lines))


def _write_light(path: Path, ts: np.ndarray, scales: np.ndarray) -> None:
    lines = ["# per-frame light scale: timestamp scale (multiplies the radiance of every scene point)\n"]
    lines += [f"{stamp(t)} {s:.9g}\n" for t, s in zip(ts, scales)]
    atomic_write_text(path, "".join(lines))


def _write_manifest(out: Path, kind: str, cam: SimulatedCamera, K: np.ndarray, seed: int, n_frames: int,
                    truth: dict[str, str], extra: dict[str, Any]) -> None:
    manifest = {
        "format": SEQUENCE_FORMAT, "version": SEQUENCE_VERSION, "kind": kind,
        "width": cam.width, "height": cam.height, "K": np.asarray(K).tolist(), "depth_scale": DEPTH_SCALE,
        "seed": int(seed), "n_frames": int(n_frames), "fps": FPS, "timestamp_start": TIMESTAMP_START,
        "camera": cam.spec.name, "jpeg_quality": cam.spec.jpeg_quality,
        "files": {"rgb": "rgb.txt", "depth": "depth.txt", "groundtruth": "groundtruth.txt",
                  "intrinsics": "intrinsics.txt"} if kind != "brackets" else {"times": "times.txt"},
        "truth": truth, "generator": {"name": "radiomap simulate", "version": __version__},
    }
    manifest.update(extra)
    atomic_write_json(out / MANIFEST, manifest)
