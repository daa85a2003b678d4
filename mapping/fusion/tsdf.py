"""TSDF fusion of irradiance in Open3D's sparse voxel block grid (``o3d.t.geometry.VoxelBlockGrid``).

Voxels hold ``tsdf`` (float32), ``weight`` (+1 per observation) and ``color`` (3 values in map units, irradiance
above 1 included), in one of two storages (``colour_storage``):

- ``"uint16"`` (default): 16-bit weight and colour, 12 bytes per voxel as in Open3D's own SLAM model (against 20
  for float). Colour is stored as ``round(colour x colour_scale)``: a linear scale, so the map's colours are
  averaged, interpolated and meshed as with float; it holds ``[0, 65535 / colour_scale]`` in steps of
  ``1 / colour_scale``. By default ``colour_scale`` is fixed at the first fused frame: the largest power of two
  that holds 4x that frame's largest value (irradiance up to 1.5: steps of 1/8192 up to 8.0; intensities 0..255:
  steps of 1/64 up to 1024), recorded in :meth:`TSDFBackend.stats`. Colour above the range (or negative) is
  clamped to it, counted (``stats()['colour_clipped']``) and reported once as a warning; NaN stores 0. Open3D's
  integration kernel truncates a 16-bit colour at every update (a bias of about half a step per update that
  the running average accumulates: ``weight / 4`` steps after ``weight`` frames), so this storage is fused by our
  own kernel (:func:`mapping.fusion._tsdf_kernels.integrate_u16`): Open3D's integration voxel for voxel, in its
  float32 arithmetic (TSDF values and weights bit-identical to the float grid's, ``tests/test_tsdf.py``), with
  the colour rounded to the nearest step. The rounding error is unbiased; after ``w`` updates a voxel's colour
  is within ``(w + 1) / 4`` steps of the exact running average at worst, ~``0.3 sqrt(w)`` steps typically.
  Weights stop at 65535 frames. CPU only.
- ``"float32"``: float weight and colour, fused by Open3D's kernel (float colour stored x 255); nothing is
  clamped and colour below a step survives (e.g. 0.002 next to 250 in one map).

Integration is KinectFusion's running average; the map is rendered by ray casting the zero crossing, colours by
trilinear interpolation of the eight voxels around the surface point.

The ray cast (issue 33). By default (``ray_caster="radiomap"``) the map is cast by our kernel
(``mapping._ckernels.raycast_depth``): Open3D 0.20's ``VoxelBlockGrid.ray_cast`` of depth, its range map (each
listed block's corners projected to 1/8 resolution) and its march (steps of ``max(tsdf x truncation, voxel)``,
a block at a time through absent blocks) in the same float32 operations, so the same depth bit for bit
(``tests/test_raycast.py``, ``scripts/stress_raycast.py``), but with blocks looked up in a dense table of the
view frustum's blocks instead of Open3D's hash map, eight rays in flight per thread (a step is a long chain of
dependent divisions and loads: interleaving rays overlaps them; where the CPU has AVX-512, 2 x 16 rays in vectors,
the same bits, ``RADIOMAP_SIMD=0`` forces the scalar march), nothing written but depth, and each pixel's
surface colour (the kernel of :meth:`TSDFBackend._surface_colour`) computed in the same pass, eight rows at a
time while their voxels are in the caches. It needs the compiled kernels and a CPU grid; otherwise, or with
``ray_caster="open3d"``, Open3D's cast runs (with the fragment-buffer guard below).

Ray casts and block lists. :meth:`TSDFBackend.render_for_frame` computes the voxel blocks the frame's depth
touches at its pose (the same list integration needs), ray casts the map within them, and hands the list over
in the view (:attr:`ModelView.prepared`) so that :meth:`TSDFBackend.integrate` of the frame reuses it: one
block search and one ray cast per frame, as Open3D's own dense SLAM loop. When the colour model masks pixels
(``valid``), their depth is removed and the blocks are searched again for what is left.
:meth:`TSDFBackend.render` (the generic interface) casts within the blocks of the last integrated frame. Open3D
casts depth only; the colour of each surface point (the trilinear interpolation of its eight voxels, those
observed, as Open3D's cast computes it) is read straight from the grid's buffers by our kernel through a
dense table of block slots instead of the hash map (filled from the list of blocks and slots that the backend
keeps as it adds blocks, read afresh from the hash map only after it grows, which moves them): ~23 ms of CPU
per 640x480 frame at 1 cm voxels, where Open3D's cast spends ~41 ms more with colour than without (its march,
bound by memory reads, is the rest: ~11 steps per ray). The kernel's colour is the exact interpolation (a
float64 reference agrees to 0.003 levels); Open3D's departs from it by a median 0.05 levels (of ~180) and by
more than 5 levels at about 1 pixel in 10,000, next to unobserved voxels. The
view's vertex map is the depth back-projected and its normals those of the bilaterally smoothed vertex map
(Open3D's tracking recipe: the TSDF-gradient normals of a fine, noisy grid make worse ICP targets, and cost
10% more casting time).

Colour pairs for the disagreement histogram: a pixel is compared when the map's ray-cast depth agrees with the
measured depth within ``max(agreement_voxels * voxel_size, agreement_relative * depth)`` and the depth is in
the fused range; the pair is (map colour at that pixel, the incoming colour) in map units.

Corrections of Open3D's kernels (measured in ``tests/test_tsdf.py``):

- Integration looks a voxel up at pixel ``int(u)`` (truncation) while every other kernel puts pixel centres
  at integers: the principal point is shifted by half a pixel for integration (``pixel_centre_fix``; 4 mm
  on a plane tilted 30 degrees at 2 m).
- The ray marcher reads the voxel at ``floor(p / voxel_size)``, i.e. the TSDF of a point ``delta`` behind
  ``p`` (``delta`` in ``[0, voxel)^3``, half a voxel along (1, 1, 1) on average), so the zero crossing lies
  ``delta`` off the surface: rendered walls are ~half a voxel too far (1 cm at 2 cm voxels) and frame-to-model
  tracking drifts by about that much per frame. ``surface="debias"`` (default, ~2 ms per frame) removes the
  mean displacement along each ray, ``lambda = (n . h) z / (n . v)`` with ``h = voxel/2 (1, 1, 1)`` in the
  camera frame; ``surface="refine"`` then solves for the zero crossing of the trilinearly interpolated TSDF
  along each ray (secant steps on voxels read straight from the grid's buffers): exact, but 20-40 ms per
  640x480 frame. Colours (interpolated at the crossing, which lies on the right ray) are unaffected.
- The cast's range map is built at 1/8 resolution and read out of bounds unless both image sides are
  multiples of 8 (hangs or empty views): odd sizes are cast padded and cropped.
- The range map (the depth interval to march, per 8x8 pixels) is built from "fragments", 16x16 range-map pixel
  pieces of each listed block's projected rectangle, in a buffer that Open3D sizes lazily: a cast that needs
  more fragments than the buffer holds comes back incomplete (parts of the view silently empty), and only then
  is the buffer reallocated. Worse, in that cast the block whose fragments straddle the end of the buffer
  writes none of them, yet every slot below the end is read back: slots of uninitialised memory become pixel
  coordinates of a write into the range map, a segmentation fault when the leftover bytes are not small
  floats (issue 13: 6 of 6 runs under load). The backend therefore counts each cast's fragments exactly as
  Open3D does (:func:`range_map_fragments`) and, before a cast that would not fit, grows the buffer with a
  cast in which every listed block takes exactly one fragment, so that no slot is left unwritten: no cast
  overflows but these, and they cannot read garbage.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mapping._open3d import o3d
from mapping.fusion.base import ColourPairs, ModelView, masked_depth
from mapping.surface_maps import maps as surface_maps
from radiometry._native import simd_allowed

log = logging.getLogger(__name__)

_RANGE_FACTOR = 8          # Open3D's range map: one pixel per 8x8 image pixels
_FRAGMENT = 16             # its fragments: 16x16 range-map pixels
_ATTRS = ("tsdf", "weight", "color")
SURFACES = ("debias", "refine", "open3d")
#: colour storage of the grid: bytes per voxel (TSDF, weight, 3 colours)
COLOUR_STORAGE = {"uint16": 4 + 2 + 6, "float32": 4 + 4 + 12}
_CUBE = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], np.float64)   # a block's corners
RAY_CASTERS = ("radiomap", "open3d")
_HEADROOM = 4.0            # uint16 colour, colour_scale=None: room for 4x the first frame's largest colour


@dataclass
class MeshData:
    """A triangle mesh extracted from the map (colours in map units)."""

    vertices: np.ndarray   # (N, 3) float32 world
    triangles: np.ndarray  # (M, 3) int32
    colours: np.ndarray    # (N, 3) float32 map units
    normals: np.ndarray    # (N, 3) float32


def _padded(height: int, width: int) -> tuple[int, int]:
    """The image size Open3D's ray cast is given: both sides rounded up to multiples of the range-map factor."""
    return -(-int(height) // _RANGE_FACTOR) * _RANGE_FACTOR, -(-int(width) // _RANGE_FACTOR) * _RANGE_FACTOR


def range_map_fragments(blocks: np.ndarray, K: np.ndarray, extrinsic: np.ndarray, height: int, width: int, *,
                        block_resolution: int, voxel_size: float, depth_min: float, depth_max: float) -> np.ndarray:
    """The fragments Open3D's ``VoxelBlockGrid.ray_cast`` allots each block of ``blocks`` (N x 3 block
    coordinates) when it builds its range map for a ``height`` x ``width`` image (both multiples of 8) seen
    with ``K`` and ``extrinsic`` (world to camera): pass 0 of ``EstimateRange`` (Open3D 0.16-0.20), its
    float32 arithmetic in our kernel (:func:`mapping.fusion._tsdf_kernels.range_fragments`, compiled in C by
    default: :mod:`mapping._native`)."""
    b = np.ascontiguousarray(np.asarray(blocks).reshape(-1, 3), dtype=np.int32)
    E = np.asarray(extrinsic, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    f32 = np.float32
    out = np.empty(len(b), np.int64)
    _kernels().range_fragments(b, np.ascontiguousarray(E[:3, :3], f32), np.ascontiguousarray(E[:3, 3], f32),
                               f32(K[0, 0]), f32(K[1, 1]), f32(K[0, 2]), f32(K[1, 2]), f32(_RANGE_FACTOR),
                               int(block_resolution), f32(voxel_size), int(height) // _RANGE_FACTOR,
                               int(width) // _RANGE_FACTOR, f32(depth_min), f32(depth_max), out)
    return out


def first_colour_scale(colour: np.ndarray) -> float:
    """The uint16 grid's default ``colour_scale`` for a run whose first fused frame has colour ``colour``: the
    largest power of two ``S`` with ``65535 / S >= 4 x`` its largest finite value (1 when none is above 0), so
    that a run can grow 4x brighter than its first frame before colour is clamped."""
    finite = np.asarray(colour)[np.isfinite(colour)]
    top = float(finite.max()) if finite.size else 0.0
    top = top if top > 0 else 1.0
    return float(2.0 ** np.floor(np.log2(65535.0 / (_HEADROOM * top))))


def _tensor(array: np.ndarray, dtype=np.float32):
    return o3d.core.Tensor.from_numpy(np.ascontiguousarray(array, dtype=dtype))


def _kernels():
    """The kernels (compiled C, or Numba's: :mod:`mapping._native`)."""
    from mapping._native import tsdf_kernels

    return tsdf_kernels()


def _quiet():
    return o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error)


@dataclass
class _Prepared:
    """What :meth:`TSDFBackend.render_for_frame` prepares for fusing a frame (:attr:`ModelView.prepared`)."""

    blocks: object              # o3d.core.Tensor (B, 3) int32: the voxel blocks the frame's depth touches
    depth_image: object         # o3d.t.geometry.Image of the depth the blocks were found for
    extrinsic: np.ndarray       # world-to-camera (4, 4)
    extrinsic_t: object         # the same as an o3d.core.Tensor
    depth: np.ndarray           # the depth array they were found for (integrate fuses that array only)


class TSDFBackend:
    """A TSDF map of float colours in an Open3D voxel block grid (implements ``FusionBackend``).

    voxel_size:             metres (0.01 for room-scale Kinect data).
    block_resolution:       voxels per block edge (16).
    block_count:            initial hash-map capacity in blocks; it doubles when full.
    trunc_voxel_multiplier: truncation distance in voxels (Open3D's default 8).
    depth_min, depth_max:   metres; depth outside is not fused nor rendered.
    weight_threshold:       voxels with less weight are not rendered (capped by the number of fused frames,
                            so the first frames render as in Open3D's loop).
    agreement_voxels, agreement_relative: the depth-agreement test for colour pairs.
    pixel_centre_fix:       integrate with the nearest pixel rather than Open3D's truncated pixel index.
    surface:                how the rendered surface is located (module doc): "debias" (default), "refine" or
                            "open3d" (Open3D's ray cast as it is).
    colour_storage:         "uint16" (default: 16-bit weight and colour, 12 bytes per voxel, fused by our kernel)
                            or "float32" (float weight and colour, 20 bytes, fused by Open3D); module doc.
    ray_caster:             "radiomap" (default: our kernel, Open3D's cast bit for bit, faster) or "open3d"
                            (``VoxelBlockGrid.ray_cast``); module doc.
    colour_scale:           uint16 storage: stored levels per map unit (stored value = colour x colour_scale,
                            rounded; it holds colours up to 65535 / colour_scale). None: from the first fused
                            frame, the largest power of two that holds 4x its largest colour value.
    device:                 Open3D device ("CPU:0"; "CUDA:0" where Open3D has CUDA; uint16 storage: CPU only).
    """


    name = "tsdf"

    def __init__(self, *, voxel_size: float = 0.01, block_resolution: int = 16, block_count: int = 2000,
                 trunc_voxel_multiplier: float = 8.0, depth_min: float = 0.1, depth_max: float = 3.0,
                 weight_threshold: float = 3.0, agreement_voxels: float = 3.0, agreement_relative: float = 0.02,
                 pixel_centre_fix: bool = True, surface: str = "debias", colour_storage: str = "uint16",
                 colour_scale: float | None = None, ray_caster: str = "radiomap", device: str = "CPU:0") -> None:
        for name, value in (("voxel_size", voxel_size), ("trunc_voxel_multiplier", trunc_voxel_multiplier),
                            ("depth_max", depth_max), ("agreement_voxels", agreement_voxels)):
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        if not 0 <= depth_min < depth_max:
            raise ValueError(f"depth_min must be in [0, depth_max), got {depth_min}")
        if int(block_resolution) < 2 or int(block_count) < 1:
            raise ValueError(f"block_resolution must be >= 2 and block_count >= 1, got {block_resolution}, "
                             f"{block_count}")
        self.voxel_size = float(voxel_size)
        self.block_resolution = int(block_resolution)
        self.trunc_voxel_multiplier = float(trunc_voxel_multiplier)
        self.depth_min = float(depth_min)
        self.depth_max = float(depth_max)
        self.weight_threshold = float(weight_threshold)
        self.agreement_voxels = float(agreement_voxels)
        self.agreement_relative = float(agreement_relative)
        self.pixel_centre_fix = bool(pixel_centre_fix)
        if surface not in SURFACES:
            raise ValueError(f"surface must be one of {', '.join(SURFACES)}, got {surface!r}")
        if surface == "refine" and block_resolution & (block_resolution - 1):
            raise ValueError(f"surface='refine' needs a power-of-two block_resolution, got {block_resolution}")
        self.surface = surface
        if ray_caster not in RAY_CASTERS:
            raise ValueError(f"ray_caster must be one of {', '.join(RAY_CASTERS)}, got {ray_caster!r}")
        self.ray_caster = ray_caster
        self.cast_steps = self.cast_rays = 0   # march steps and rays of the last cast by our kernel
        self.cast_simd = False                 # whether that cast marched with AVX-512
        if colour_storage not in COLOUR_STORAGE:
            raise ValueError(f"colour_storage must be one of {', '.join(COLOUR_STORAGE)}, got {colour_storage!r}")
        if colour_scale is not None and not (isinstance(colour_scale, (int, float)) and np.isfinite(colour_scale)
                                             and colour_scale > 0):
            raise ValueError(f"colour_scale must be a positive number or None, got {colour_scale!r}")
        self.colour_storage = colour_storage
        self.colour_scale = None if colour_scale is None else float(colour_scale)
        if colour_storage == "float32":
            self.colour_scale = 255.0     # Open3D stores float colour x 255 (it takes float images as 0..1)
        self.colour_clipped = 0           # uint16 storage: colour values clamped to [0, 65535 / colour_scale]
        self.device = o3d.core.Device(device)
        if colour_storage == "uint16" and self.device.get_type() != o3d.core.Device.DeviceType.CPU:
            raise ValueError(f"colour_storage='uint16' runs on the CPU only, got device {device!r}; "
                             "pass colour_storage='float32'")
        value = o3d.core.uint16 if colour_storage == "uint16" else o3d.core.float32
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            list(_ATTRS), [o3d.core.float32, value, value], [[1], [1], [3]], voxel_size=self.voxel_size,
            block_resolution=self.block_resolution, block_count=int(block_count), device=self.device)
        self.frames_integrated = 0
        self._last_blocks = None          # block coordinates of the last fused frame (for render())
        self.ray_casts = 0
        self.fragment_capacity = 0        # fragments Open3D's range-map buffer is known to hold (module doc)
        self._blocks_known = None         # (coordinates, slots, capacity) of the grid's blocks (_known_blocks)

    def _integration_intrinsics(self, K: np.ndarray) -> np.ndarray:
        """Open3D's integration kernel looks a voxel up at pixel ``int(u)`` (truncation) while every other
        kernel (and this project) puts pixel centres at integer coordinates; shifting the principal point
        by half a pixel makes it the nearest pixel, ``int(u + 0.5)``. Without it the surface and its colours
        are displaced by half a pixel (4 mm on a plane tilted 30 degrees at 2 m, 320x240)."""
        K = np.asarray(K, dtype=np.float64).copy()
        if self.pixel_centre_fix:
            K[0, 2] += 0.5
            K[1, 2] += 0.5
        return K

    @property
    def truncation(self) -> float:
        return self.voxel_size * self.trunc_voxel_multiplier

    # ---------------------------------------------------------------- rendering
    def _ray_cast(self, blocks, K: np.ndarray, pose: np.ndarray, height: int, width: int, *,
                  extrinsic: np.ndarray | None = None) -> ModelView:
        """Depth and colour from Open3D's ray cast; vertex and normal maps from the depth (normals of the
        bilaterally smoothed vertex map, Open3D's own tracking recipe: the TSDF-gradient normals of a fine,
        noisy grid make worse ICP targets and cost 10% more ray-casting time); the surface bias removed."""
        weight = min(self.weight_threshold, float(max(self.frames_integrated, 1)))
        # Open3D's ray cast builds its range map at 1/8 resolution and reads it out of bounds (hanging or
        # returning nothing) unless both sides are multiples of 8: cast a padded image and crop it
        hp, wp = _padded(height, width)
        pose = np.asarray(pose, dtype=np.float64)
        if extrinsic is None:
            extrinsic = np.linalg.inv(pose)
        own = self.ray_caster == "radiomap" and hasattr(_kernels(), "raycast_depth") \
            and self.device.get_type() == o3d.core.Device.DeviceType.CPU
        table = self._frustum_table(blocks, K, pose, extrinsic, hp, wp) if own else None
        colour = None
        if table is not None:
            depth, colour = self._cast_depth(blocks, table, K, pose, extrinsic, hp, wp, weight, (height, width))
        else:
            self._fit_range_fragments(blocks.numpy(), K, extrinsic, hp, wp)
            result = self.grid.ray_cast(blocks, o3d.core.Tensor(np.asarray(K, dtype=np.float64)),
                                        o3d.core.Tensor(extrinsic), wp, hp, ["depth"], 1.0,
                                        self.depth_min, self.depth_max, weight, self.trunc_voxel_multiplier,
                                        _RANGE_FACTOR)
            depth = result["depth"].numpy()[:, :, 0]
        self.ray_casts += 1
        if (hp, wp) != (height, width):
            depth = np.ascontiguousarray(depth[:height, :width])
        if colour is None:
            colour, table = self._surface_colour(depth, K, pose)
        vertex, normal = surface_maps(np.where(depth > 0, depth, np.float32(np.nan)), K)   # Open3D's, on every core
        c = pose[:3, :3].T @ np.ones(3)  # the grid diagonal (1, 1, 1) in the camera frame
        _kernels().finish_view(vertex, normal, depth, c.astype(np.float32), np.float32(0.5 * self.voxel_size),
                               self.surface != "open3d")
        if self.surface == "refine":
            self._refine(table, K, pose, depth, vertex)
        return ModelView(depth=depth, colour=colour, vertex=vertex, normal=normal, pose=pose.copy())

    def _frustum_table(self, blocks, K: np.ndarray, pose: np.ndarray, extrinsic: np.ndarray, height: int,
                       width: int) -> tuple[np.ndarray, np.ndarray] | None:
        """A dense block table (:meth:`_block_table`) holding every block of the grid that the cast of ``blocks``
        can reach: the rays march from the camera to at most the farthest corner of a listed block (or
        ``depth_min``, where every tile's far end starts), so the
        bounding box of the view frustum cut there (two blocks of margin for rounding and the surface colour's
        neighbours), clipped to the grid's blocks. None when no block is listed or the table would take more than
        256 MB (Open3D's cast then runs)."""
        b = blocks.numpy()
        if len(b) == 0:
            return None
        size = self.block_resolution * self.voxel_size
        E = np.asarray(extrinsic, dtype=np.float64)
        corners = (b[:, None, :].astype(np.float64) + _CUBE[None]) * size
        far = float((corners @ E[2, :3] + E[2, 3]).max())
        if not far > 0:
            return None
        far = max(far, self.depth_min)   # a covered tile marches to at least depth_min (Open3D's range map starts there)
        K = np.asarray(K, dtype=np.float64)
        pix = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], np.float64)
        rays = np.column_stack([(pix[:, 0] - K[0, 2]) / K[0, 0], (pix[:, 1] - K[1, 2]) / K[1, 1], np.ones(4)])
        points = np.vstack([pose[:3, 3], pose[:3, 3] + far * (rays @ pose[:3, :3].T)]) / size
        keys, _ = self._known_blocks()
        lo = np.maximum(np.floor(points.min(axis=0)).astype(np.int64) - 2, keys.min(axis=0))
        hi = np.minimum(np.floor(points.max(axis=0)).astype(np.int64) + 2, keys.max(axis=0))
        if np.any(lo > hi):
            lo = hi = np.zeros(3, np.int64)
        if np.prod(hi - lo + 1) > 64 * 2 ** 20:
            return None
        return self._block_table(lo, hi)

    def _cast_depth(self, blocks, table: tuple[np.ndarray, np.ndarray], K: np.ndarray, pose: np.ndarray,
                    extrinsic: np.ndarray, height: int, width: int, weight: float,
                    colour_size: tuple[int, int], whole_map: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """Open3D's ray cast of depth (its range map and march, the same float32 operations: the same depth bit
        for bit) by our kernel, over the dense block table instead of Open3D's hash map (module doc), and the
        colour of :meth:`_surface_colour` (the same kernel code) of the top-left ``colour_size`` pixels. Should a
        ray reach a block of the map's bounding box outside ``table``, the cast is made again over that whole box
        (``whole_map``), where a block outside is absent."""
        f32 = np.float32
        colour = np.empty(tuple(colour_size) + (3,), f32)
        K = np.asarray(K, dtype=np.float64)
        E = np.asarray(extrinsic, dtype=np.float64)
        Rinv = E[:3, :3].T                               # Open3D's InverseTransformation, in float64
        tinv = -(Rinv @ E[:3, 3])
        depth = np.empty((height, width), f32)
        keys, _ = self._known_blocks()
        steps = np.concatenate([np.zeros(3, np.int64), keys.min(axis=0), keys.max(axis=0)]).astype(np.int64)
        cast = _kernels().raycast_depth
        self.cast_simd = bool(cast(np.ascontiguousarray(blocks.numpy(), np.int32), np.ascontiguousarray(E[:3, :3], f32),
                                   np.ascontiguousarray(E[:3, 3], f32), np.ascontiguousarray(Rinv, f32),
                                   np.ascontiguousarray(tinv, f32), K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                                   self.block_resolution, self.voxel_size,
                                   float(f32(self.voxel_size) * f32(self.trunc_voxel_multiplier)), self.depth_min,
                                   self.depth_max, weight, self.grid.attribute("tsdf").numpy().reshape(-1),
                                   self.grid.attribute("weight").numpy().reshape(-1), table[0], table[1], depth,
                                   steps, np.ascontiguousarray(pose[:3, :3], f32),
                                   np.ascontiguousarray(pose[:3, 3], f32),
                                   self.grid.attribute("color").numpy().reshape(-1), float(f32(self.colour_scale)),
                                   colour, simd_allowed()))
        self.cast_steps, self.cast_rays = int(steps[0]), int(steps[1])
        if steps[2] and whole_map is False:   # a ray looked beyond the table (never seen since the depth_min fix)
            log.debug("ray cast: %d look-ups outside the frustum table; cast again over the whole map", steps[2])
            whole = self._block_table(keys.min(axis=0).astype(np.int64), keys.max(axis=0).astype(np.int64))
            return self._cast_depth(blocks, whole, K, pose, extrinsic, height, width, weight, colour_size, True)
        return depth, colour

    def _fragments(self, blocks: np.ndarray, K: np.ndarray, extrinsic: np.ndarray, height: int,
                   width: int) -> np.ndarray:
        return range_map_fragments(blocks, K, extrinsic, height, width, block_resolution=self.block_resolution,
                                   voxel_size=self.voxel_size, depth_min=self.depth_min, depth_max=self.depth_max)

    def _fit_range_fragments(self, blocks: np.ndarray, K: np.ndarray, extrinsic: np.ndarray, height: int,
                             width: int) -> None:
        """Make sure the cast of ``blocks`` fits Open3D's fragment buffer (module doc): if its fragments, with
        an eighth to spare for rounding, reach the known capacity, first grow the buffer to twice as many."""
        needed = int(self._fragments(blocks, K, extrinsic, height, width).sum())
        if needed and needed + needed // 8 + _FRAGMENT >= self.fragment_capacity:  # 0 fits, reads nothing
            self._grow_range_fragments(K, height, width, 2 * needed + 256)

    def _grow_range_fragments(self, K: np.ndarray, height: int, width: int, count: int) -> None:
        """Grow Open3D's fragment buffer to ``count`` fragments with a cast that cannot read an unwritten one:
        ``count`` copies of block (0, 0, 0), placed on the ray through the image centre so far away that its
        projection spans about two range-map pixels, i.e. exactly one fragment per copy. Open3D then writes
        every fragment slot it reads back, however small its buffer was, and reallocates it to ``count``."""
        K = np.asarray(K, dtype=np.float64)
        size = self.block_resolution * self.voxel_size
        distance = max(K[0, 0], K[1, 1]) * size / (2.0 * _RANGE_FACTOR) + size
        extrinsic = np.eye(4)
        extrinsic[:3, 3] = distance * np.array([(width / 2 - K[0, 2]) / K[0, 0], (height / 2 - K[1, 2]) / K[1, 1],
                                                1.0]) - size / 2
        blocks = np.zeros((int(count), 3), np.int32)
        if self._fragments(blocks[:1], K, extrinsic, height, width)[0] != 1:
            # cannot happen once a cast needs fragments (both range-map sides >= 2); never risk an unsafe growth
            raise RuntimeError(f"cannot size Open3D's ray-cast buffer for a {width}x{height} view with K={K.tolist()}")
        with _quiet():  # Open3D reports the overflow and the reallocation as a warning and a note on stdout
            self.grid.ray_cast(o3d.core.Tensor(blocks), o3d.core.Tensor(K), o3d.core.Tensor(extrinsic), int(width),
                               int(height), ["depth"], 1.0, self.depth_min, self.depth_max, 1e9,
                               self.trunc_voxel_multiplier, _RANGE_FACTOR)
        self.fragment_capacity = max(self.fragment_capacity, int(count))

    def _surface_colour(self, depth: np.ndarray, K: np.ndarray, pose: np.ndarray
                        ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """The colour (H, W, 3) of each ray-cast surface point, as Open3D's ray cast computes it, but read
        straight from the grid's buffers through a dense block table (:meth:`_block_table`): the cast of depth
        alone plus this costs less than Open3D's cast of depth and colour (module doc). Also the table (None
        when no pixel has depth)."""
        f32 = np.float32
        K = np.asarray(K, dtype=np.float64)
        fx, fy, cx, cy = f32(K[0, 0]), f32(K[1, 1]), f32(K[0, 2]), f32(K[1, 2])
        Rc, o = np.ascontiguousarray(pose[:3, :3], f32), np.ascontiguousarray(pose[:3, 3], f32)
        colour = np.zeros(depth.shape + (3,), f32)
        block_size = f32(self.voxel_size * self.block_resolution)
        lo, hi = _kernels().hit_bounds(depth, Rc, o, fx, fy, cx, cy, block_size)
        if np.any(lo > hi):
            return colour, None
        table = self._block_table(lo, hi)
        _kernels().surface_colour(depth, Rc, o, fx, fy, cx, cy, self.grid.attribute("color").numpy().reshape(-1),
                                  self.grid.attribute("weight").numpy().reshape(-1), table[0], table[1],
                                  self.block_resolution, f32(self.voxel_size), f32(self.colour_scale), colour)
        return colour, table

    def _block_table(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A dense (X, Y, Z) table of hash-map buffer slots (-1 = no block) of the blocks from ``lo`` to ``hi``
        (block coordinates, inclusive), and ``lo``: voxel look-ups without the hash map."""
        keys, slots = self._known_blocks()
        index = np.full(tuple(hi - lo + 1), -1, np.int32)
        _kernels().fill_block_table(keys, slots, np.ascontiguousarray(lo, np.int64), index)
        return index, lo

    def _known_blocks(self) -> tuple[np.ndarray, np.ndarray]:
        """Coordinates (N, 3) and buffer slots (N,) of every block in the grid: the list :meth:`_activate` keeps,
        read afresh from the hash map (~1.5 ms for 16,000 blocks) only when it does not hold every block or was
        made at another capacity: the first time, and after the hash map grew, which moves every block. Open3D's
        hash map grows whenever its size plus the number of keys it is asked to activate exceeds its capacity,
        even if every key is present: Open3D's integrate (float storage) can move the blocks after
        :meth:`_activate`."""
        hashmap = self.grid.hashmap()
        capacity = hashmap.capacity()
        if self._blocks_known is None or len(self._blocks_known[1]) != hashmap.size() \
                or self._blocks_known[2] != capacity:
            slots = hashmap.active_buf_indices().numpy().astype(np.int32)
            self._blocks_known = (np.ascontiguousarray(hashmap.key_tensor().numpy()[slots], np.int32), slots,
                                  capacity)
        return self._blocks_known[:2]

    def _activate(self, blocks) -> None:
        """Add the frame's blocks to the hash map (as integration does; new blocks are zero) and note the new ones
        in the block list of :meth:`_known_blocks`, which is dropped when the hash map grows."""
        hashmap = self.grid.hashmap()
        capacity = hashmap.capacity()
        self._check_growth(int(hashmap.size()), capacity, int(blocks.shape[0]))
        slots, new = hashmap.activate(blocks)
        if hashmap.capacity() != capacity or self._blocks_known is None or self._blocks_known[2] != capacity:
            self._blocks_known = None
        else:
            new = new.numpy()
            if new.any():
                keys, known, _ = self._blocks_known
                self._blocks_known = (np.concatenate([keys, blocks.numpy()[new].astype(np.int32)]),
                                      np.concatenate([known, slots.numpy()[new].astype(np.int32)]), capacity)

    def _check_growth(self, size: int, capacity: int, count: int) -> None:
        """Before Open3D's hash map grows (when ``size + count`` exceeds its ``capacity``, to at least twice it,
        the old buffers held while the blocks are copied), refuse in one line if the new buffers would not fit
        (:func:`mapping.validation.check_growth`): Open3D does not survive a failed allocation. The bound holds
        for any voxel size, depth range or sequence length, since every growth passes here first."""
        if size + count <= capacity:
            return
        from mapping.validation import check_growth

        grown = max(2 * capacity, size + count)
        per_block = self.block_resolution ** 3 * COLOUR_STORAGE[self.colour_storage] + 64   # + key, hash entry
        check_growth(grown * per_block, what=f"the map ({size:,} blocks of {self.block_resolution}^3 voxels of "
                                             f"{self.voxel_size * 1000:.3g} mm, {count:,} in view) growing to "
                                             f"{grown:,} blocks")

    def _refine(self, table, K: np.ndarray, pose: np.ndarray, depth: np.ndarray, vertex: np.ndarray) -> int:
        """Move each rendered point to the zero crossing of the trilinear TSDF along its ray (the block table of
        :meth:`_surface_colour`)."""
        if table is None:
            return 0
        index, lo = table
        tsdf = self.grid.attribute("tsdf").numpy().reshape(-1)
        weight = self.grid.attribute("weight").numpy().reshape(-1)
        K = np.asarray(K, dtype=np.float64)
        return _kernels().refine(depth, vertex, K[0, 0], K[1, 1], K[0, 2], K[1, 2],
                                 np.ascontiguousarray(pose[:3, :3]), pose[:3, 3].copy(), tsdf, weight, index, lo,
                                 int(self.block_resolution).bit_length() - 1, self.voxel_size)

    def _empty_view(self, height: int, width: int, pose: np.ndarray | None = None) -> ModelView:
        return ModelView(depth=np.zeros((height, width), np.float32), colour=np.zeros((height, width, 3), np.float32),
                         vertex=np.zeros((height, width, 3), np.float32),
                         normal=np.zeros((height, width, 3), np.float32),
                         pose=None if pose is None else np.array(pose, dtype=np.float64))

    def render(self, pose: np.ndarray, K: np.ndarray, height: int, width: int) -> ModelView:
        """The map seen from ``pose``, ray cast within the blocks of the last fused frame (all zero if empty)."""
        if self.frames_integrated == 0 or self._last_blocks is None:
            return self._empty_view(height, width, pose)
        return self._ray_cast(self._last_blocks, K, pose, height, width)

    def _prepare(self, depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> _Prepared:
        """The voxel blocks ``depth`` touches at ``pose``, and the Open3D inputs integration needs."""
        extrinsic = np.linalg.inv(np.asarray(pose, dtype=np.float64))
        extrinsic_t = o3d.core.Tensor(extrinsic)
        depth_image = o3d.t.geometry.Image(_tensor(depth))
        Kt = o3d.core.Tensor(np.asarray(K, dtype=np.float64))
        blocks = self.grid.compute_unique_block_coordinates(depth_image, Kt, extrinsic_t, 1.0, self.depth_max,
                                                            self.trunc_voxel_multiplier)
        return _Prepared(blocks, depth_image, extrinsic, extrinsic_t, depth)

    def render_for_frame(self, depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> ModelView:
        """The map seen from ``pose`` within the blocks ``depth`` touches there; the view carries the block list
        (:attr:`ModelView.prepared`) for :meth:`integrate` of the same frame."""
        depth = np.asarray(depth)
        height, width = depth.shape
        prepared = self._prepare(depth, K, pose)
        if self.frames_integrated == 0:
            view = self._empty_view(height, width, pose)
        else:
            view = self._ray_cast(prepared.blocks, K, pose, height, width, extrinsic=prepared.extrinsic)
        view.prepared = prepared
        return view

    # ---------------------------------------------------------------- fusion
    def colour_pairs(self, depth: np.ndarray, colour: np.ndarray, view: ModelView) -> ColourPairs:
        """Pixels where the rendered map and the measured depth agree: (map colour, incoming colour)."""
        n_pix = depth.size
        out_map = np.empty((n_pix, 3), np.float32)
        out_sample = np.empty((n_pix, 3), np.float32)
        f32 = np.float32
        n = _kernels().colour_pairs(np.ascontiguousarray(view.depth, f32), np.ascontiguousarray(depth, f32),
                                    np.ascontiguousarray(view.colour, f32), np.ascontiguousarray(colour, f32),
                                    f32(self.agreement_voxels * self.voxel_size), f32(self.agreement_relative),
                                    f32(self.depth_min), f32(self.depth_max), out_map, out_sample)
        return ColourPairs(map_colour=out_map[:n], sample_colour=out_sample[:n])

    def integrate(self, depth: np.ndarray, colour: np.ndarray, K: np.ndarray, pose: np.ndarray, *,
                  view: ModelView | None = None, valid: np.ndarray | None = None,
                  frame_index: int = 0) -> ColourPairs | None:
        """Fuse one frame (depth float32 metres, colour (H, W, 3) float32 map units) at ``pose``, without the
        pixels ``valid`` marks False; returns the colour pairs compared against ``view`` (:meth:`render_for_frame`'s
        view of this frame, whose block list is reused when no pixel is masked; rendered here when not given)."""
        depth = np.asarray(depth)
        if depth.dtype != np.float32 or depth.ndim != 2:
            raise ValueError(f"depth must be float32 (H, W) metres, got {depth.dtype} {depth.shape}")
        colour = np.asarray(colour)
        if colour.shape != depth.shape + (3,):
            raise ValueError(f"colour must be (H, W, 3) matching depth {depth.shape}, got {colour.shape}")
        prepared = view.prepared if view is not None and valid is None else None
        if not (isinstance(prepared, _Prepared) and prepared.depth is depth
                and np.array_equal(view.pose, pose)):  # not render_for_frame's view of this frame: search again
            depth = masked_depth(depth, valid)
            prepared = self._prepare(depth, K, pose)
        pairs = None
        if self.frames_integrated:
            if view is None:
                view = self._ray_cast(prepared.blocks, K, pose, depth.shape[0], depth.shape[1],
                                      extrinsic=prepared.extrinsic)
            pairs = self.colour_pairs(depth, colour, view)
        if self.colour_storage == "uint16":
            self._integrate_u16(prepared, colour, K)
        else:
            self._activate(prepared.blocks)   # Open3D's integrate finds them all present
            hashmap = self.grid.hashmap()     # ... but grows if size + keys asked exceeds the capacity: bound it too
            self._check_growth(int(hashmap.size()), int(hashmap.capacity()), int(prepared.blocks.shape[0]))
            colour_image = o3d.t.geometry.Image(_tensor(colour))
            Kt = o3d.core.Tensor(self._integration_intrinsics(K))
            self.grid.integrate(prepared.blocks, prepared.depth_image, colour_image, Kt, prepared.extrinsic_t, 1.0,
                                self.depth_max, self.trunc_voxel_multiplier)
        self._last_blocks = prepared.blocks
        self.frames_integrated += 1
        return pairs

    def _integrate_u16(self, prepared: _Prepared, colour: np.ndarray, K: np.ndarray) -> None:
        """Fuse a frame into the 16-bit grid with our kernel (module doc): Open3D's integration, voxel for voxel,
        but with the colour rounded, not truncated."""
        f32 = np.float32
        colour = np.ascontiguousarray(colour, f32)
        if self.colour_scale is None:
            self.colour_scale = first_colour_scale(colour)
        self._activate(prepared.blocks)       # as Open3D's integrate: new blocks (zeroed), then every block's slot
        slots, found = self.grid.hashmap().find(prepared.blocks)
        found = found.numpy()
        keys = np.ascontiguousarray(prepared.blocks.numpy()[found], np.int32)
        slots = np.ascontiguousarray(slots.numpy()[found], np.int64)
        Ki = self._integration_intrinsics(K)
        clipped = np.zeros(len(slots), np.int64)
        _kernels().integrate_u16(np.ascontiguousarray(prepared.depth, f32), colour, f32(Ki[0, 0]), f32(Ki[1, 1]),
                                 f32(Ki[0, 2]), f32(Ki[1, 2]), np.ascontiguousarray(prepared.extrinsic[:3], f32),
                                 keys, slots, self.block_resolution, f32(self.voxel_size),
                                 f32(f32(self.trunc_voxel_multiplier) * f32(self.voxel_size)), f32(self.depth_max),
                                 self.colour_scale, self.grid.attribute("tsdf").numpy().reshape(-1),
                                 self.grid.attribute("weight").numpy().reshape(-1),
                                 self.grid.attribute("color").numpy().reshape(-1), clipped)
        n = int(clipped.sum())
        if n and not self.colour_clipped:
            log.warning("colour outside the 16-bit grid's range [0, %.6g] map units was clamped (%d values in frame "
                        "%d; stats()['colour_clipped'] counts them all); pass a smaller colour_scale or "
                        "colour_storage='float32'", 65535.0 / self.colour_scale, n, self.frames_integrated)
        self.colour_clipped += n

    # ---------------------------------------------------------------- output
    def extract_mesh(self, weight_threshold: float | None = None) -> MeshData:
        """Marching cubes over the grid (voxels with at least ``weight_threshold`` observations)."""
        w = self.weight_threshold if weight_threshold is None else float(weight_threshold)
        w = min(w, float(max(self.frames_integrated, 1)))
        w -= 0.5  # Open3D keeps voxels with weight > threshold; weights are whole observation counts
        if self.frames_integrated == 0:
            return MeshData(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32),
                            np.zeros((0, 3), np.float32))
        with _quiet():
            mesh = self.grid.extract_triangle_mesh(w)
        n = mesh.vertex.positions.shape[0] if "positions" in mesh.vertex else 0
        if n == 0:
            return MeshData(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32),
                            np.zeros((0, 3), np.float32))
        colours = mesh.vertex.colors.numpy().copy()   # Open3D divides the stored colour by 255
        if self.colour_storage == "uint16":
            colours *= np.float32(255.0 / self.colour_scale)
        return MeshData(vertices=mesh.vertex.positions.numpy().copy(),
                        triangles=mesh.triangle.indices.numpy().astype(np.int32),
                        colours=colours,
                        normals=mesh.vertex.normals.numpy().copy() if "normals" in mesh.vertex
                        else np.zeros((n, 3), np.float32))

    def export(self, folder: Path, to_display: Callable[[np.ndarray], np.ndarray], *,
               formats: tuple[str, ...] = ("ply",)) -> dict[str, Path]:
        """Write ``mesh.<fmt>`` for each of ``formats`` (display colours; ``npz``: ``mesh_colours.npz``, vertices,
        triangles and map-unit colours, for evaluation): :func:`mapping.export.write_mesh`."""
        from mapping.export import write_mesh

        mesh = self.extract_mesh()
        return write_mesh(Path(folder), mesh.vertices, mesh.triangles, mesh.colours, to_display,
                          normals=mesh.normals, formats=formats)

    def stats(self) -> dict:
        hashmap = self.grid.hashmap()
        blocks = int(hashmap.size())
        capacity = int(hashmap.capacity())
        voxels_per_block = self.block_resolution ** 3
        per_voxel = COLOUR_STORAGE[self.colour_storage]
        return {"backend": self.name, "voxel_size": self.voxel_size, "block_resolution": self.block_resolution,
                "truncation_m": self.truncation, "blocks": blocks, "block_capacity": capacity,
                "voxels": blocks * voxels_per_block,
                "colour_storage": self.colour_storage, "colour_scale": self.colour_scale,
                "colour_clipped": self.colour_clipped,
                "allocated_mb": capacity * voxels_per_block * per_voxel / 2 ** 20,
                "used_mb": blocks * voxels_per_block * per_voxel / 2 ** 20,
                "frames_integrated": self.frames_integrated, "ray_casts": self.ray_casts}
