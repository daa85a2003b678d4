"""What is physically sensible for an RGB-D camera, in one place: option ranges, the run's memory estimate and
the rule for a run that fused too little.

Every numeric option of ``reconstruct``, ``compare``, ``simulate``, ``correct`` and ``vignetting`` (and the
library's :class:`~mapping.factory.ReconstructConfig`, :func:`~mapping.factory.build_run`,
:func:`~mapping.factory.make_backend`, :func:`~mapping.compare.compare`) is checked here, before anything is read
or written (options that click already bounds, such as image sizes, keep their click ranges); a value outside
its range raises :class:`ImplausibleValueError` (a ``ValueError`` for the library, a one-line error with exit 1
for the CLI) naming the option, the value and the range. The ranges come from real sensors:

============================  ================  ===========================================================
quantity                      range             why
============================  ================  ===========================================================
field of view (each axis)     10 .. 140 deg     Kinect v1 57 x 43, RealSense D435 87 x 58, Azure Kinect
                                                WFOV 120 x 120 (fisheye, rectified); a pinhole image wider
                                                than ~140 deg stretches its edges > 8x. 1 px focal lengths
                                                (179 deg) or a slipped decimal point (26.25 for 262.5) fall
                                                outside.
pixel aspect fx / fy          0.5 .. 2          real sensors: 0.99 .. 1.01
principal point               inside the image  (cx in (0, W), cy in (0, H)); else K is for another size
voxel size                    1 mm .. 20 cm     object scans 1-2 mm, KinectFusion rooms 4-6 mm, coarse 5 cm
depth_max                     0.2 .. 20 m       D405 0.07-0.5 m, Kinect 0.5-4.5 m, D455 up to ~20 m
depth range vs truncation     truncation        the TSDF band (voxel x trunc multiplier) must be narrower
                              < depth range     than the fused depth range (else it covers the whole range)
depth scale                   1 .. 100000       raw units per metre: 1 float metres, 1000 mm, 5000 TUM,
                                                100000 = 10 um (finer than any sensor)
exposure factors              1e-4 .. 1e4       +-13 stops around the first frame
block resolution              4 .. 64           voxels per block edge (Open3D uses 8 or 16)
truncation multiplier         1 .. 32           truncation in voxels (Open3D 8, KinectFusion ~4)
exposure time (simulate)      1 us .. 60 s      global shutters 1 us; Debevec's brackets reach 32 s
light change (simulate)       0.01 .. 100 x     a light switched to 1 % .. 100x of its brightness
lens (simulate --lensfun)     1..2000 mm, f/0.7..f/64   phone lenses to super-telephotos; the fastest lenses
LUT smoothing (vignetting)    0 .. 50 px        default 1, 2-3 for thin sweeps; OpenCV fails on huge kernels
gamma (response --gamma)      0.2 .. 5          sRGB ~2.2, Rec. 709 ~1.9-2.4; the extremes of display curves
flicker (simulate)            0 .. 0.5 (excl.)  relative amplitude of a light's flicker (mains: 0.05-0.3)
smoothness (response)         1e-6 .. 1e6       Debevec's default 10, the log-log prior's 0.1
============================  ================  ===========================================================

Every number given on the command line is finite: ``inf``, ``-inf`` and ``nan`` are refused by the same
:func:`check_range` (click's own ranges let ``nan`` through, as every comparison with it is false); the CLI's
option type :class:`mapping.cli._common.Number` applies these checks to every float option of every command.

Memory (:func:`estimate_memory`) is estimated before a run starts and compared with ``MemAvailable`` of
``/proc/meminfo``: a run that cannot fit raises :class:`MemoryEstimateError` in one line.

A run that fused nothing, or too little to mean anything (:func:`check_fused`: fewer than
``MIN_FUSED_FRAMES`` frames, or fewer than ``MIN_FUSED_FRACTION`` of the frames), fails.
"""

from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radiometry.errors import RadiomapError
from radiometry.quorum import MIN_USED_FRACTION, MIN_USED_FRAMES, rule_text, too_little
from radiometry.vignetting_calibration import MAX_SMOOTH_SIGMA

log = logging.getLogger(__name__)

# ------------------------------------------------------------------------------------------------------------
# the ranges (see the module doc for their sources)
# ------------------------------------------------------------------------------------------------------------
FOV_DEG = (10.0, 140.0)
PIXEL_ASPECT = (0.5, 2.0)
VOXEL_SIZE_M = (0.001, 0.2)
DEPTH_MAX_M = (0.2, 20.0)
POSE_TIME_DIFFERENCE_S = (0.0, 10.0)  # --poses-max-difference: evo's --t_max_diff is 0.01-0.02 s; 10 s is absurd
DEPTH_MIN_M = (0.0, 5.0)
DEPTH_SCALE = (1.0, 100000.0)
EXPOSURE_FACTOR = (1e-4, 1e4)
BLOCK_RESOLUTION = (4, 64)
TRUNC_VOXEL_MULTIPLIER = (1.0, 32.0)

EXPOSURE_TIME_S = (1e-6, 60.0)      # shutters: 1 us (global-shutter sensors) .. 60 s (brackets reach 32 s)
LIGHT_CHANGE = (0.01, 100.0)        # a light switched to 1 % .. 100x of its brightness
LENS_FOCAL_MM = (1.0, 2000.0)       # phone lenses 1.5-9 mm .. super-telephoto 800 mm (lensfun's range)
LENS_APERTURE = (0.7, 64.0)         # f-numbers: f/0.7 (the fastest lenses made) .. f/64
SMOOTH_SIGMA_PX = (0.0, MAX_SMOOTH_SIGMA)  # LUT denoising (radiometry.vignetting_calibration): default 1, 2-3 thin
GAMMA = (0.2, 5.0)                  # standard responses: sRGB ~2.2, Rec. 709 1.9-2.4
FLICKER = (0.0, 0.5)                # relative flicker amplitude, 0.5 excluded (the light would go out)
SMOOTHNESS = (1e-6, 1e6)            # response smoothness / prior weights (debevec 10, loglog 0.1)

#: a run fails when it fuses fewer frames than this (or all of a shorter sequence), or fewer than this fraction of
#: its frames: the rule of radiometry/quorum.py, which vignetting calibration shares
MIN_FUSED_FRAMES = MIN_USED_FRAMES
MIN_FUSED_FRACTION = MIN_USED_FRACTION

#: bytes of one TSDF voxel of the default grid (tsdf: float32; weight and 3 colours: uint16), as
#: mapping.fusion.tsdf.COLOUR_STORAGE["uint16"] (the float32 storage, a backend option, takes 20)
TSDF_BYTES_PER_VOXEL = 4 + 2 + 6
#: bytes of one surfel (position, normal, colour: 3 x float32; radius, confidence: float32; 2 x int32)
SURFEL_BYTES = 13 * 4
#: Open3D's hash map and the surfel arrays double their capacity when full: up to 2x the used memory
GROWTH_FACTOR = 2.0
#: what the process holds before the map (Python, NumPy, Open3D, Numba; measured ~370 MB)
BASE_BYTES = 400 * 2 ** 20
#: a surfel map of a room holds about this many frames' worth of pixels (ElasticFusion on room scans:
#: 2-4 M surfels at 640x480 over 1000s of frames, i.e. ~10 frames; 30 leaves a wide margin)
SURFEL_FRAMES_CAP = 30


class ImplausibleValueError(RadiomapError, ValueError):
    """An option outside the range that makes sense for an RGB-D camera (a ValueError for library callers;
    the CLI prints it as one line)."""


class MemoryEstimateError(RadiomapError):
    """A run that would not fit in the machine's available memory."""


class TooLittleFusedError(RadiomapError):
    """A run that fused nothing, or too little to make a map."""


# ------------------------------------------------------------------------------------------------------------
# single values
# ------------------------------------------------------------------------------------------------------------
# config fields whose command-line option has another name
_OPTION_NAMES = {"reference_exposure": "--display-exposure", "exposure_reference": "--mesh-exposure"}


def _label(name: str) -> str:
    """``voxel_size`` -> ``--voxel-size`` (the CLI's spelling; the library's is the same with underscores)."""
    if name.startswith("-"):
        return name
    return _OPTION_NAMES.get(name, "--" + name.replace("_", "-"))


def check_range(name: str, value, limits: tuple[float, float], unit: str = "", why: str = "", *,
                open_max: bool = False) -> float:
    """``value`` as a float when it is a finite number within ``limits`` (inclusive; the upper limit excluded
    with ``open_max``), else :class:`ImplausibleValueError` naming the option, the value and the range."""
    lo, hi = limits
    u = f" {unit}" if unit else ""
    span = f"{lo:g}..{hi:g}{u}" + (f" ({hi:g} excluded)" if open_max else "")
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ImplausibleValueError(f"{_label(name)} must be a number in {span}, got {quote(value)}")
    try:
        v = float(value)
    except OverflowError:       # an integer beyond float's range
        v = math.inf if value > 0 else -math.inf
    hint = f" ({why})" if why else ""
    if not math.isfinite(v):
        raise ImplausibleValueError(f"{_label(name)} {v:g} is not a finite number; pass a value in the sensible "
                                    f"range {span}{hint}")
    if not (lo <= v <= hi) or (open_max and v >= hi):
        raise ImplausibleValueError(f"{_label(name)} {v:g}{u} is outside the sensible range {span}"
                                    f"{hint}; pass a value in that range")
    return v


def check_finite(name: str, value) -> float:
    """``value`` as a float when it is a finite number (any size), else :class:`ImplausibleValueError`."""
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        v = math.nan
    if isinstance(value, bool) or not math.isfinite(v):
        raise ImplausibleValueError(f"{_label(name)} must be a finite number, got {quote(value)}")
    return v


#: the longest piece of user input an error line quotes (a 60 MB token of a broken list once filled a terminal)
QUOTE_MAX = 80


def quote(value, limit: int = QUOTE_MAX) -> str:
    """``repr(value)`` cut to ``limit`` characters (the length said): what error lines quote of user input."""
    if isinstance(value, str) and len(value) > limit:
        return f"{value[:limit]!r}... ({len(value):,} characters)"
    text = repr(value)
    return text if len(text) <= limit else f"{text[:limit]}... ({len(text):,} characters)"


def option_range(limits: tuple[float, float], unit: str = "", why: str = ""):
    """A click option callback applying :func:`check_range` to the option's value (None passes): how the CLI's
    simulate/vignetting/... options use these ranges. The error is one line (``radiomap: error: ...``, exit 1)."""
    def callback(ctx, param, value):
        if value is None:
            return value
        return check_range(max(param.opts, key=len), value, limits, unit, why)
    return callback


#: the mesh files a run can write (``--formats``): PLY (sRGB-encoded display colours, what most tools show as they
#: are), binary glTF (linear COLOR_0, as glTF defines it), OBJ, and npz (``mesh_colours.npz``: vertices, triangles,
#: map-unit colours and display colours, for evaluation); docs/outputs.md says which file suits which tool
MESH_FORMATS = ("ply", "glb", "obj", "npz")
#: one mesh by default (issue 32: the same mesh three times made the demo 223 MB)
DEFAULT_MESH_FORMATS = ("ply",)


def check_mesh_formats(value, name: str = "formats") -> tuple[str, ...]:
    """``"ply,glb"`` (or a sequence of names) -> ``("ply", "glb")``: each of :data:`MESH_FORMATS` at most once, in
    the order given; an empty list or an unknown name is an :class:`ImplausibleValueError` naming the option and
    the accepted values."""
    accepted = ", ".join(MESH_FORMATS)
    if isinstance(value, str):
        names = value.split(",")
    elif isinstance(value, (list, tuple)) and all(isinstance(v, str) for v in value):
        names = list(value)
    else:
        raise ImplausibleValueError(f"{_label(name)} must be a comma-separated list of mesh formats ({accepted}), "
                                    f"got {quote(value)}")
    names = [n.strip().lower().lstrip(".") for n in names]
    unknown = [n for n in names if n not in MESH_FORMATS]
    if unknown or not any(names):
        what = f"unknown mesh format {quote(unknown[0])}" if unknown and unknown[0] else "an empty format"
        raise ImplausibleValueError(f"{_label(name)} {quote(value if isinstance(value, str) else ','.join(value))}: "
                                    f"{what}; choose from {accepted}, comma-separated (e.g. {_label(name)} ply,glb)")
    return tuple(dict.fromkeys(names))


def check_voxel_size(value, name: str = "voxel_size") -> float:
    return check_range(name, value, VOXEL_SIZE_M, "m", "1 mm for small objects, 5 mm-2 cm for rooms")


def check_depth_max(value, name: str = "depth_max") -> float:
    return check_range(name, value, DEPTH_MAX_M, "m", "RGB-D cameras measure up to 4-10 m, 20 m at most")


def check_depth_scale(value, name: str = "depth_scale") -> float | None:
    if value is None:
        return None
    return check_range(name, value, DEPTH_SCALE, "raw units per metre",
                       "1 for float metres, 1000 for millimetres, 5000 for TUM")


def check_exposure_factor(value, name: str = "reference_exposure") -> float:
    return check_range(name, value, EXPOSURE_FACTOR, "", "an exposure factor: 13 stops either way")


def check_fusion(*, backend: str = "tsdf", voxel_size: float = 0.01, depth_max: float = 3.0, depth_min: float = 0.1,
                 block_resolution: int = 16, trunc_voxel_multiplier: float = 8.0) -> None:
    """The fusion options alone and together (the TSDF band must be narrower than the depth range)."""
    voxel_size = check_voxel_size(voxel_size)
    depth_max = check_depth_max(depth_max)
    depth_min = check_range("depth_min", depth_min, DEPTH_MIN_M, "m")
    check_range("block_resolution", block_resolution, BLOCK_RESOLUTION, "voxels")
    trunc = check_range("trunc_voxel_multiplier", trunc_voxel_multiplier, TRUNC_VOXEL_MULTIPLIER, "voxels")
    if depth_min >= depth_max:
        raise ImplausibleValueError(f"--depth-max {depth_max:g} m must exceed the minimum fused depth "
                                    f"{depth_min:g} m; pass a larger --depth-max")
    band = voxel_size * trunc
    if backend == "tsdf" and band >= depth_max - depth_min:
        raise ImplausibleValueError(
            f"--voxel-size {voxel_size:g} m gives a truncation band of {band:g} m ({trunc:g} voxels), as wide as "
            f"the fused depth range {depth_min:g}..{depth_max:g} m; pass a --voxel-size below "
            f"{(depth_max - depth_min) / trunc:.3g} m or a larger --depth-max")


def check_intrinsics(K: np.ndarray, width: int, height: int, *, source: str = "intrinsics") -> None:
    """A pinhole matrix for ``width x height`` images: field of view, pixel aspect and principal point
    within :data:`FOV_DEG`, :data:`PIXEL_ASPECT` and the image. ``source`` names where K came from."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    where = "--intrinsics" if source in ("intrinsics", "option") else f"the intrinsics ({source})"
    values = f"fx={fx:g}, fy={fy:g}, cx={cx:g}, cy={cy:g}"
    if not (np.all(np.isfinite(K)) and fx > 0 and fy > 0):
        raise ImplausibleValueError(f"{where} ({values}): focal lengths must be positive and finite; pass "
                                    "--intrinsics fx,fy,cx,cy of the camera (e.g. 525,525,319.5,239.5 at 640x480)")
    lo, hi = FOV_DEG
    for axis, f, size in (("horizontal", fx, width), ("vertical", fy, height)):
        fov = math.degrees(2 * math.atan(size / (2 * f)))
        if not lo <= fov <= hi:
            sensible = (size / (2 * math.tan(math.radians(hi / 2))), size / (2 * math.tan(math.radians(lo / 2))))
            raise ImplausibleValueError(
                f"{where} ({values}) gives a {axis} field of view of {fov:.1f} deg on {width}x{height} images, "
                f"outside the sensible {lo:g}..{hi:g} deg of RGB-D cameras; {'fx' if axis == 'horizontal' else 'fy'} "
                f"should be in {sensible[0]:.4g}..{sensible[1]:.4g} px (a slipped decimal point?)")
    aspect = fx / fy
    if not PIXEL_ASPECT[0] <= aspect <= PIXEL_ASPECT[1]:
        raise ImplausibleValueError(f"{where} ({values}): fx / fy = {aspect:.3g} is outside "
                                    f"{PIXEL_ASPECT[0]:g}..{PIXEL_ASPECT[1]:g} (real sensors: 0.99..1.01); "
                                    "check the order fx,fy,cx,cy")
    problem = principal_point_problem(K, width, height)
    if problem:
        raise ImplausibleValueError(f"{where} ({values}): {problem}")


def principal_point_problem(K: np.ndarray, width: int, height: int) -> str | None:
    """Why the principal point of ``K`` cannot belong to ``width x height`` images (outside them), or None."""
    cx, cy = float(K[0, 2]), float(K[1, 2])
    if 0 < cx < width and 0 < cy < height:
        return None
    return (f"the principal point ({cx:g}, {cy:g}) lies outside the {width}x{height} images; the intrinsics belong "
            "to another resolution, pass the right --intrinsics")


# ------------------------------------------------------------------------------------------------------------
# memory
# ------------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MemoryEstimate:
    """The memory a run needs (bytes) and how it was reckoned."""

    bytes: int
    detail: str

    @property
    def gib(self) -> float:
        return self.bytes / 2 ** 30


def estimate_memory(*, backend: str, K: np.ndarray, width: int, height: int, frames: int, voxel_size: float = 0.01,
                    depth_min: float = 0.1, depth_max: float = 3.0, block_resolution: int = 16,
                    trunc_voxel_multiplier: float = 8.0, scene_depth: float | None = None) -> MemoryEstimate:
    """The memory of a run's map, before it starts (an order of magnitude: it refuses runs that are off by far).

    TSDF: the blocks allocated around the surfaces one view sees, the frustum's far "wall" at the depth the
    sequence reaches (``scene_depth``, capped by ``depth_max``) tiled by blocks and thickened by the truncation
    band, ``(W d / fx B + 1)(H d / fy B + 1)(2 trunc / B + 1)``, but no more than ``frames`` frames of depth can
    touch (``pixels x (2 trunc / B + 1)`` each: voxels finer than a pixel's footprint give every pixel its own
    blocks); times ``block_resolution^3`` voxels of :data:`TSDF_BYTES_PER_VOXEL` bytes; times
    :data:`GROWTH_FACTOR`. Measured: a simulated 160x120 room (20 frames, 3 m) allocates 1/1.8-1/1.5 of the
    blocks estimated at voxel sizes of 3-10 mm (peak RSS 0.51-1.19 GB against 0.52-1.76 GiB estimated); the 7-Scenes
    kitchen (50 frames at 640x480, 1 cm) 1019 blocks against 705 (peak RSS 0.54 GB against 0.50 GiB): an estimate
    of the order of magnitude, which refuses runs that are off by far (a 1 mm grid of the room: 12.5 GiB).
    Surfels: at most one surfel per pixel and frame, capped at :data:`SURFEL_FRAMES_CAP` frames' worth,
    :data:`SURFEL_BYTES` each, times :data:`GROWTH_FACTOR`. Both plus :data:`BASE_BYTES`.
    """
    K = np.asarray(K, dtype=np.float64)
    pixels = int(width) * int(height)
    far = min(float(depth_max), float(scene_depth)) if scene_depth is not None else float(depth_max)
    far = max(far, depth_min)
    if backend == "surfel":
        surfels = pixels * min(int(frames), SURFEL_FRAMES_CAP)
        total = surfels * SURFEL_BYTES * GROWTH_FACTOR
        detail = f"{surfels:,} surfels of {SURFEL_BYTES} B"
    else:
        block = voxel_size * block_resolution
        thickness = 2 * voxel_size * trunc_voxel_multiplier / block + 1.0
        shell = (width * far / (K[0, 0] * block) + 1) * (height * far / (K[1, 1] * block) + 1) * thickness
        touched = float(frames) * pixels * thickness
        blocks = min(shell, touched)
        total = blocks * block_resolution ** 3 * TSDF_BYTES_PER_VOXEL * GROWTH_FACTOR
        detail = (f"{blocks:,.0f} voxel blocks of {block * 100:.3g} cm: the surfaces of a view to {far:.3g} m "
                  f"{shell:,.0f}, {frames} frames x {pixels:,} pixels {touched:,.0f}")
    return MemoryEstimate(int(min(total, 2 ** 62)) + BASE_BYTES, detail)


def available_memory() -> int | None:
    """The memory this process may still take, in bytes: ``MemAvailable`` of ``/proc/meminfo``, bounded by the
    process's address-space limit (``ulimit -v``: the limit minus what the process maps already) and its cgroup's
    (``memory.max`` minus ``memory.current``, in a container or a batch slot); None where none is known."""
    import resource

    bounds = []
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    bounds.append(int(line.split()[1]) * 1024)
                    break
    except (OSError, ValueError, IndexError):
        pass
    soft, _hard = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        bounds.append(max(0, soft - _status_bytes("VmSize")))
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            bounds.append(max(0, int(limit) - int(Path("/sys/fs/cgroup/memory.current").read_text())))
    except (OSError, ValueError):
        pass
    return min(bounds) if bounds else None


def _status_bytes(key: str) -> int:
    """``VmSize``/``VmRSS``/... of ``/proc/self/status`` in bytes (0 where unknown)."""
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def headroom() -> int | None:
    """What the process may still allocate, in bytes: ``RADIOMAP_MEMORY_LIMIT`` (bytes for the whole process, for
    tests and batch systems) minus its resident size when set, else :func:`available_memory`."""
    limit = os.environ.get("RADIOMAP_MEMORY_LIMIT")
    if limit:
        return int(float(limit)) - _status_bytes("VmRSS")
    return available_memory()


#: what a growth must leave free (the rest of a frame's work: images, ray casts, Python)
GROWTH_RESERVE = 256 * 2 ** 20


def check_growth(needed: int, *, what: str, available: int | None = None) -> None:
    """:class:`MemoryEstimateError` when an allocation of ``needed`` bytes (a map about to grow) would not leave
    :data:`GROWTH_RESERVE` free: the bound that stops a run before Open3D's allocation fails inside native code
    (a segfault, or the kernel's OOM killer). ``what`` says what grows."""
    available = headroom() if available is None else available
    if available is None or needed + GROWTH_RESERVE <= available:
        return
    raise MemoryEstimateError(
        f"{what} needs {needed / 2 ** 30:,.2f} GiB more but {max(available, 0) / 2 ** 30:.2f} GiB are available; use "
        "a larger --voxel-size, a smaller --depth-max or a shorter --frames range")


def check_memory(estimate: MemoryEstimate, *, available: int | None = None) -> None:
    """:class:`MemoryEstimateError` when ``estimate`` exceeds the available memory (``RADIOMAP_MEMORY_LIMIT``
    bytes, when set, stands for it: tests and batch systems)."""
    limit = os.environ.get("RADIOMAP_MEMORY_LIMIT")
    if available is None:
        available = int(float(limit)) if limit else available_memory()
    if available is None:
        return
    log.info("memory estimate: %.2f GiB (%s); available %.2f GiB", estimate.gib, estimate.detail,
             available / 2 ** 30)
    if estimate.bytes > available:
        raise MemoryEstimateError(
            f"this run would need about {estimate.gib:,.1f} GiB ({estimate.detail}) but {available / 2 ** 30:.1f} "
            "GiB are available; use a larger --voxel-size, a smaller --depth-max or a shorter --frames range")


def scene_depth(dataset, samples: int = 3) -> float | None:
    """The depth the sequence reaches (99.9th percentile of the valid depth of up to ``samples`` frames spread
    over it; frames that cannot be read are left to the run), or None when no sampled frame has depth."""
    n = len(dataset)
    picks = sorted({int(round(i)) for i in np.linspace(0, n - 1, min(samples, n))})
    values = []
    for i in picks:
        try:
            depth = dataset[i].depth
        except RadiomapError:  # a bad frame is the run's to report, at its place in the sequence
            continue
        valid = depth[depth > 0]
        if valid.size:
            values.append(float(np.percentile(valid, 99.9)))
    return max(values) if values else None


def config_options(config) -> dict:
    """The fusion options of a :class:`~mapping.factory.ReconstructConfig` (or anything with those attributes)
    as keyword arguments of :func:`check_fusion` and :func:`check_run`."""
    names = ("backend", "voxel_size", "depth_max", "block_resolution", "trunc_voxel_multiplier")
    return {k: getattr(config, k) for k in names if hasattr(config, k)}


def check_colour_map(colour_map: str | None, backend: str) -> None:
    """The colour-map stage optimises a mesh's colours: ValueError (one line naming the options) unless the
    backend is the TSDF, whose surface is a mesh (the surfel backend's discs are not)."""
    if colour_map is not None and backend != "tsdf":
        raise ValueError(f"--colour-map applies to --backend tsdf only (it optimises a mesh's colours), got --backend "
                         f"{backend}; drop --colour-map or use --backend tsdf")


def check_config(config) -> None:
    """The options of a :class:`~mapping.factory.ReconstructConfig` that need no data: fusion options, depth
    scale, exposure factors, the colour-map stage's backend."""
    check_fusion(**config_options(config))
    check_colour_map(config.colour_map, config.backend)
    check_depth_scale(getattr(config, "depth_scale", None))
    if isinstance(getattr(config, "reference_exposure", None), (int, float)):
        check_exposure_factor(config.reference_exposure, "reference_exposure")


def check_run(dataset, *, poses: str = "icp", **fusion) -> MemoryEstimate:
    """Everything about a run that can be checked before it starts: the fusion options (``fusion``: the keywords
    of :func:`check_fusion`), the intrinsics against the image size (:func:`check_intrinsics`), ground truth for
    ``poses="gt"``, and the memory (:func:`estimate_memory`, :func:`check_memory`). Returns the estimate."""
    from radiometry.errors import DatasetError

    check_fusion(**fusion)
    name = getattr(dataset, "root", None) or getattr(dataset, "name", "the sequence")
    check_intrinsics(dataset.K, dataset.width, dataset.height,
                     source=getattr(dataset, "intrinsics_source", None) or "intrinsics")
    if poses == "gt" and dataset.ground_truth() is None:
        raise DatasetError(f"{name}: has no ground-truth poses for the selected frames (--poses gt); track with "
                           "--poses icp, or add the trajectory (TUM groundtruth.txt, 7-Scenes pose files, "
                           "Redwood trajectory.log)")
    if poses == "gt":   # camera-to-world expected; world-to-camera given is refused with the fix
        from mapping.pose_convention import refuse_inverted_poses

        refuse_inverted_poses(dataset, name=str(name), quaternion_file=getattr(dataset, "ground_truth_file", None))
    estimate = estimate_memory(K=dataset.K, width=dataset.width, height=dataset.height, frames=len(dataset),
                               scene_depth=scene_depth(dataset), **{"backend": "tsdf", **fusion})
    check_memory(estimate)
    return estimate


# ------------------------------------------------------------------------------------------------------------
# results
# ------------------------------------------------------------------------------------------------------------
def too_little_fused(fused: int, frames: int) -> bool:
    """True when a run of ``frames`` frames that fused ``fused`` of them made no meaningful map
    (:func:`radiometry.quorum.too_little`)."""
    return too_little(fused, frames)


def check_fused(fused: int, frames: int, reasons: dict[str, int], name: str = "the sequence") -> None:
    """:class:`TooLittleFusedError` (one line: counts, reasons, fix) when :func:`too_little_fused`."""
    if not too_little_fused(fused, frames):
        return
    why = ", ".join(f"{k}: {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])) or "no reason recorded"
    hint = ""
    if any("ground-truth" in k for k in reasons):
        hint = "track with --poses icp or give the sequence its trajectory; "
    elif any("depth" in k for k in reasons):
        hint = "check --depth-scale and --depth-max; "
    raise TooLittleFusedError(
        f"{name}: fused {fused} of {frames} frames ({why}); a map needs {rule_text()}; {hint}see frames.csv in "
        "the results folder")


__all__ = ["BLOCK_RESOLUTION", "DEPTH_MAX_M", "DEPTH_MIN_M", "DEPTH_SCALE", "EXPOSURE_FACTOR", "EXPOSURE_TIME_S",
           "FLICKER", "FOV_DEG", "GAMMA", "GROWTH_RESERVE", "ImplausibleValueError", "LENS_APERTURE",
           "LENS_FOCAL_MM", "LIGHT_CHANGE", "MIN_FUSED_FRACTION", "MIN_FUSED_FRAMES", "MemoryEstimate",
           "MemoryEstimateError", "PIXEL_ASPECT", "POSE_TIME_DIFFERENCE_S", "QUOTE_MAX", "SMOOTHNESS",
           "SMOOTH_SIGMA_PX", "TRUNC_VOXEL_MULTIPLIER", "TooLittleFusedError", "VOXEL_SIZE_M", "available_memory",
           "check_config", "check_depth_max", "check_depth_scale", "check_exposure_factor", "check_finite",
           "check_fused", "check_fusion", "check_growth", "check_intrinsics", "check_memory", "check_range",
           "check_run", "check_voxel_size", "config_options", "estimate_memory", "headroom", "option_range",
           "principal_point_problem", "quote", "scene_depth", "too_little_fused"]
