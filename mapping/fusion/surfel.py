"""Surfel fusion in the style of ElasticFusion (Whelan et al., RSS 2015), after Keller et al., "Real-time 3D
reconstruction in dynamic scenes using point-based fusion" (3DV 2013).

The map is a set of surfels (position, normal, radius, confidence, colour in map units, creation and
last-update times) in struct-of-arrays NumPy storage (:class:`SurfelMap`: capacity doubling, lazy compaction).
Each :meth:`SurfelBackend.integrate` call runs ElasticFusion's fusion step on the CPU:

1. **Samples.** Depth pixels of one lattice: with ``pixel_stride=2`` (default, ElasticFusion's ``data.vert``)
   the pixels with ``x % 2 == y % 2 == t % 2`` (``t`` counts integrated frames), with ``pixel_stride=1``
   every pixel (Keller et al.). A pixel needs a depth in ``(0, depth_max]`` and its four neighbours valid
   (ElasticFusion's ``checkNeighbours``); additionally (not in ElasticFusion) no neighbour may differ by
   more than ``max_depth_jump`` (5 %) of the depth, so that no surfel is made across a depth discontinuity
   with a meaningless normal. Positions come from the raw depth; normals and radii from a bilateral-filtered
   depth (5x5, sigma 4.5 px and 3 cm): normal = cross product of central differences of the back-projected
   vertex map at +-``normal_baseline`` (3) pixels, facing the camera. ElasticFusion filters 13x13 and
   differences at +-1 pixel; a 13x13 bilateral filter costs 32 ms per frame on one CPU core, and the wider
   baseline gives the same noise reduction for free (with Kinect-like noise the normals at +-1 pixel after a
   5x5 filter fail the normal gate so often that the benchmark room's map grows 1.8x with duplicates, at +-3
   pixels 1.1x the noise-free map). Radius ``r = sqrt(2) z / f / |n_z|`` clamped to ``2 sqrt(2) z / f``
   (``getRadius``, f = mean focal). Per-sample confidence ``alpha = exp(-rho^2 / (2 * 0.6^2))``, ``rho`` = distance to the principal
   point over the half diagonal of the image (``confidence()``; 400 px at 640x480 in ElasticFusion): 1 at the
   centre, 0.25 in a corner. ElasticFusion's motion-dependent factor (``weighting``) is 1 here.
2. **Index map.** All live surfels (stable and unstable) are transformed to the camera frame (the one O(N)
   pass, see "Cost") and point-rendered with a z-buffer into an index map ``index_scale`` = 4 times finer
   than the image (Keller et al.'s 4x4 supersampling); a texel keeps its nearest surfel.
3. **Association.** Each sample looks at the index-map texels within a window of ``pixel_stride + 1`` pixels
   square around it: for stride 2 the 3x3 pixels ElasticFusion's shader reaches (+-1 pixel at half-pixel
   steps), for stride 1 2x2 pixels; neighbouring windows overlap by a pixel, so a surfel whose projection
   falls on a cell boundary is still found. Candidates must lie within ``depth_gate`` = 5 cm along the ray
   and, unless the surfel is seen at a grazing angle (``|n_z| < 0.75``), within ``normal_gate_deg`` = 28.6
   deg (0.5 rad, ElasticFusion's code; the paper says 20 deg) of the sample normal. Each sample takes the
   candidate closest to its ray (ties: higher confidence); when several samples take one surfel, the one
   whose ray passes closest refines it (ElasticFusion: a GPU write race). Then every surfel left unrefined
   that is some sample's candidate is refined by its nearest such sample: without this step a camera at rest,
   whose lattice falls exactly between the surfels of the previous frame, leaves one surfel in five
   unrefined in every frame (measured). A sample with candidates never creates a surfel.
4. **Merge** (``update.vert``). If the sample radius is below ``radius_ratio`` (1.5) times the surfel's,
   position, normal, radius and colour become confidence-weighted averages ``(c*old + a*new)/(c + a)``;
   otherwise only confidence and time change (ElasticFusion's rule: colour is not averaged then). Always
   ``conf += alpha`` and ``updated = now``. A surfel is refined at most once per frame.
5. **Colour pairs.** For every sample whose colour is averaged into a surfel, the pair (surfel colour
   *before* averaging, sample colour) is returned: the measurement of Alexandrov et al. (IROS 2016), who
   recorded it inside ElasticFusion's update for every merge, stable or not. Pairs are in map units.
6. **New surfels** for samples without any candidate: ``conf = alpha``, ``created = updated = now``.
7. **Clean-up** (``copy_unstable.vert``) on an image-resolution index map of the stable surfels in view
   after the merge (only stable surfels count as evidence in ElasticFusion's tests): a surfel in view is
   removed when it lies in front of >= 2 stable surfels updated in this frame by more than
   ``free_space_gap`` = 1 cm while facing the camera (``|n_z| > 0.85``) - a free-space violation, the sensor
   just saw through it - or when it lies less than 1 cm in front of >= 3 older stable surfels within 1.4 of
   its radius laterally - a redundant newer layer. ElasticFusion samples its +-1 pixel window four times per
   texel and thresholds at > 4 and > 8 samples: the same counts in distinct surfels. The window here is
   ``2 * pixel_stride`` pixels square so that it holds about four surfels of a surface at the map's density.
   Every surfel (in view or not) with confidence below ``confidence_threshold`` not updated for more than
   ``unstable_window`` = 20 frames is removed (``time - lastUpdate > 20 && conf < threshold``); the rule is
   evaluated in the next pass over the map (the next frame's cull, :meth:`~SurfelBackend.render`,
   :meth:`~SurfelBackend.stats`, :meth:`~SurfelBackend.surfels`, :meth:`~SurfelBackend.export`), which
   removes exactly the same surfels without a second pass over the map per frame.

Stable surfels have ``confidence >= confidence_threshold`` (10, ElasticFusion's default): about ten
observations near the image centre, up to forty near the corners. :meth:`~SurfelBackend.render` splats
stable surfels as discs (ray / disc intersection, nearest hit per pixel) and fills pixels no stable surfel
covers with unstable ones (``fill_unstable``; ElasticFusion fills such holes from the live frame), so that
tracking works from the second frame on. :meth:`~SurfelBackend.export` writes only stable surfels.

Not carried over from ElasticFusion: the deformation graph and loop closures, ferns, the active/inactive time
window (without loop closure every surfel stays active) and RGB tracking. ``view`` passed to
:meth:`~SurfelBackend.integrate` is not used (the index map holds all surfels, which a rendered view does
not).

Cost: per frame one pass over the map (:func:`~mapping.fusion._surfel_kernels.cull`: the unstable rule, the
transform and frustum test of the live surfels), block by block: blocks of 1024 rows whose bounding box lies
outside the view and that hold no surfel due for the unstable rule are skipped whole (``SurfelMap`` keeps the
block summaries), so a large map costs little more than the part of it in view (at 1M surfels of which 0.1M
in view: 1.2 ms instead of 3.3 ms per frame on one core). Everything else is proportional to the surfels in
view and the pixels sampled. Numba does the per-pixel and per-surfel loops: the sample preparation, the
index map (per-pixel surfel lists that stand for the 4x z-buffer and stay in the CPU cache), the window
searches sample by sample in image order and the matching (scatter-minima with conflicts), the update
scattered by surfel id and the new surfels written in place, the clean-up windows and the disc splatting
(see :mod:`mapping.fusion._surfel_kernels`). ``scripts/bench_surfel.py`` measures it.
"""

from __future__ import annotations

import logging
import math
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mapping.fusion import _surfel_kernels as kern
from mapping.fusion.base import ColourPairs, ModelView, masked_depth
from mapping.fusion.surfel_map import SurfelMap, cull, remove_unstable, write_surfel_ply
from radiometry.errors import OutputError
from radiometry.fileio import atomic_path, ensure_dir

log = logging.getLogger(__name__)

SIGMA = 0.6  # ElasticFusion / Keller et al.: per-sample confidence exp(-rho^2 / (2 sigma^2))
GRAZING_NZ = 0.75  # surfels with |n_z| below this skip the normal gate (ElasticFusion data.vert)
FACING_NZ = 0.85  # only surfels facing the camera can be free-space violations (copy_unstable.vert)
DUPLICATE_GAP = 0.01  # metres: a newer surfel this close in front of older stable ones is a duplicate
DUPLICATE_LATERAL = 1.4  # lateral reach of the duplicate test, in radii of the tested surfel
DUPLICATE_MIN = 3  # older stable surfels just behind that make a surfel redundant
FREE_SPACE_MIN = 2  # stable surfels seen behind a surfel in this frame that make it a violation
MAX_SPLAT_HALF = 32.0  # largest half-size in pixels of one splat in render()
MAX_CANDIDATES = 8  # association candidates kept per sample (nearest its ray)


class _Samples:
    """Valid sample pixels of one frame (camera frame, float64)."""

    __slots__ = ("u", "v", "ray", "vertex", "normal", "radius", "alpha", "colour")

    def __init__(self, u, v, ray, vertex, normal, radius, alpha, colour):
        self.u, self.v, self.ray, self.vertex, self.normal = u, v, ray, vertex, normal
        self.radius, self.alpha, self.colour = radius, alpha, colour

    def __len__(self) -> int:
        return int(self.u.shape[0])


def _positive(name: str, value, *, integer: bool = False, allow_zero: bool = False):
    ok_type = isinstance(value, (int, np.integer)) if integer else isinstance(value, (int, float, np.number))
    if isinstance(value, bool) or not ok_type:
        kind = "an integer" if integer else "a number"
        raise TypeError(f"{name} must be {kind}, got {value!r}")
    if not np.isfinite(value) or value < 0 or (value == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'} and finite, got {value!r}")
    return int(value) if integer else float(value)


class SurfelBackend:
    """ElasticFusion-style surfel map behind :class:`mapping.fusion.base.FusionBackend` (see module doc).

    Parameters (all keyword-only; defaults are ElasticFusion's unless said otherwise):
        confidence_threshold: confidence at which a surfel is stable (rendered for tracking, exported).
        unstable_window: frames without update after which an unstable surfel is removed.
        depth_max: depth cut-off in metres for fusion (ElasticFusion's ``-d``); ``depth_min`` is 0.
        index_scale: index-map supersampling per image axis (Keller et al.).
        pixel_stride: 2 = ElasticFusion's alternating half-resolution lattice; 1 = every pixel.
        depth_gate: association gate along the ray, metres.
        normal_gate_deg: association gate on the normal angle, degrees.
        radius_ratio: a sample refines a surfel only if its radius is below this times the surfel's.
        bilateral: filter depth (5x5 bilateral) before computing normals and radii.
        max_depth_jump: reject samples next to a depth step larger than this fraction of the depth (not in
            ElasticFusion).
        normal_baseline: half-width in pixels of the central differences for normals (ElasticFusion: 1 after a
            13x13 bilateral filter; here 3 after a 5x5 one, see the module doc).
        free_space_gap: how far behind a surfel stable surfels seen now must lie for a violation, metres.
        fill_unstable: render() fills pixels without stable surfels from unstable ones.
        mesh: export() also writes a Poisson mesh (Open3D) of the stable surfels.
        poisson_depth, poisson_trim: octree depth of the Poisson solve; fraction of lowest-density vertices
            removed from the mesh.
        initial_capacity: surfel rows allocated up front (grows by doubling).
    """

    name = "surfel"
    depth_min = 0.0  # a sample needs a depth in (0, depth_max]

    def __init__(self, *, confidence_threshold: float = 10.0, unstable_window: int = 20, depth_max: float = 3.0,
                 index_scale: int = 4, pixel_stride: int = 2, depth_gate: float = 0.05,
                 normal_gate_deg: float = math.degrees(0.5), radius_ratio: float = 1.5, bilateral: bool = True,
                 max_depth_jump: float = 0.05, normal_baseline: int = 3, free_space_gap: float = 0.01,
                 fill_unstable: bool = True, mesh: bool = False, poisson_depth: int = 9, poisson_trim: float = 0.05,
                 initial_capacity: int = 1 << 16) -> None:
        self.confidence_threshold = _positive("confidence_threshold", confidence_threshold)
        self.unstable_window = _positive("unstable_window", unstable_window, integer=True, allow_zero=True)
        self.depth_max = _positive("depth_max", depth_max)
        self.index_scale = _positive("index_scale", index_scale, integer=True)
        self.pixel_stride = _positive("pixel_stride", pixel_stride, integer=True)
        if self.index_scale > 8:
            raise ValueError(f"index_scale must be between 1 and 8, got {index_scale}")
        if self.pixel_stride > 4:
            raise ValueError(f"pixel_stride must be between 1 and 4 (2 is ElasticFusion's), got {pixel_stride}")
        self.depth_gate = _positive("depth_gate", depth_gate)
        self.normal_gate_deg = _positive("normal_gate_deg", normal_gate_deg)
        if self.normal_gate_deg >= 180:
            raise ValueError(f"normal_gate_deg must be below 180, got {normal_gate_deg}")
        self.radius_ratio = _positive("radius_ratio", radius_ratio)
        self.bilateral = bool(bilateral)
        self.max_depth_jump = _positive("max_depth_jump", max_depth_jump)
        self.normal_baseline = _positive("normal_baseline", normal_baseline, integer=True)
        if self.normal_baseline > 8:
            raise ValueError(f"normal_baseline must be between 1 and 8 pixels, got {normal_baseline}")
        self.free_space_gap = _positive("free_space_gap", free_space_gap)
        self.fill_unstable = bool(fill_unstable)
        self.mesh = bool(mesh)
        self.poisson_depth = _positive("poisson_depth", poisson_depth, integer=True)
        self.poisson_trim = _positive("poisson_trim", poisson_trim, allow_zero=True)
        if self.poisson_trim >= 1:
            raise ValueError(f"poisson_trim must be a fraction in [0, 1), got {poisson_trim}")
        self.map = SurfelMap(_positive("initial_capacity", initial_capacity, integer=True),
                             stable_confidence=self.confidence_threshold)
        self._tick = 0
        self._frames: list[int] = []  # frame index of each integration
        self._scratch: dict[str, np.ndarray] = {}
        self._expired = 0
        self._removed_clean = 0
        #: counts of the last integrated frame: samples, associated, refined (surfels), pairs, new, removed_unstable
        #: (by the pass at the start of the frame), removed_clean, visible (surfels in view)
        self.last_frame: dict[str, int] = {}
        #: cumulative CPU seconds (``time.process_time``) per fusion stage (samples, cull, associate, merge, clean,
        #: compact), for benchmarks on a shared machine
        self.timings: dict[str, float] = defaultdict(float)

    # ------------------------------------------------------------------------------------------------
    # FusionBackend
    # ------------------------------------------------------------------------------------------------
    def render(self, pose: np.ndarray, K: np.ndarray, height: int, width: int) -> ModelView:
        """Stable surfels splatted as discs at ``pose`` (holes filled by unstable ones, see
        ``fill_unstable``): depth, colour, camera-frame vertex and normal (facing the camera) maps."""
        pose = _check_pose(pose)
        K = _check_K(K)
        height = _positive("height", height, integer=True)
        width = _positive("width", width, integer=True)
        depth = np.zeros((height, width), np.float32)
        colour = np.zeros((height, width, 3), np.float32)
        vertex = np.zeros((height, width, 3), np.float32)
        normal = np.zeros((height, width, 3), np.float32)
        if len(self.map) == 0:
            return ModelView(depth, colour, vertex, normal, pose=pose.copy())
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        rcw, tcw = _world_to_camera(pose)
        min_conf = 0.0 if self.fill_unstable else self.confidence_threshold
        idx, pc, nc, px = self._scratch_view(self.map.size)
        v = self._cull(rcw, tcw, K, width, height, min_conf, np.inf, idx, pc, nc, px)
        kern.splat(idx, pc, nc, v, self.map.array("radius"), self.map.array("confidence"), self.map.array("colour"),
                   fx, fy, cx, cy, width, height, self.confidence_threshold, self.fill_unstable, MAX_SPLAT_HALF,
                   depth, colour, vertex, normal)
        return ModelView(depth, colour, vertex, normal, pose=pose.copy())

    def render_for_frame(self, depth: np.ndarray, K: np.ndarray, pose: np.ndarray) -> ModelView:
        """:meth:`render` at the frame's size (a surfel map prepares nothing for fusion)."""
        height, width = np.shape(depth)[:2]
        return self.render(pose, K, height, width)

    def integrate(self, depth: np.ndarray, colour: np.ndarray, K: np.ndarray, pose: np.ndarray, *,
                  view: ModelView | None = None, valid: np.ndarray | None = None,
                  frame_index: int = 0) -> ColourPairs:
        """Fuse one frame (see the module doc) without the pixels ``valid`` marks False; returns the colour pairs
        (surfel colour before averaging, sample colour) of every sample averaged into an existing surfel, in map
        units. ``view`` is unused."""
        depth, colour = _check_images(depth, colour)
        depth = masked_depth(depth, valid)
        K = _check_K(K)
        pose = _check_pose(pose)
        h, w = depth.shape
        tick = self._tick
        rot = pose[:3, :3]
        trans = pose[:3, 3]
        rcw, tcw = _world_to_camera(pose)

        timings = self.timings
        t0 = time.process_time()
        smp = self._samples(depth, colour, K, tick % self.pixel_stride)
        m = len(smp)
        smap = self.map
        t1 = time.process_time()
        timings["samples"] += t1 - t0

        # 1. surfels in view, index map, association
        idx, pc, nc, px = self._scratch_view(smap.size)
        v = self._cull(rcw, tcw, K, w, h, 0.0, self.depth_max + self.depth_gate, idx, pc, nc, px)
        removed = self._expired
        t0 = time.process_time()
        timings["cull"] += t0 - t1
        scale = self.index_scale
        taken = np.full(max(v, 1), -1, dtype=np.int64)
        ncand = np.zeros(m, np.int32)
        if v > 0 and m > 0:
            head, nxt, tex, winner = self._pixel_bins(w * h, v)
            kern.bin_pixels(px, v, scale, w, h, head, nxt, tex)
            cand_j = np.empty((m, MAX_CANDIDATES), np.int32)
            cand_d = np.empty((m, MAX_CANDIDATES), np.float32)
            try:
                longest = kern.mark_winners(tex, pc, v, scale, w, head, nxt, winner)
                room = (self.pixel_stride + 2) ** 2 * longest
                kern.candidates(pc, nc, tex, winner, head, nxt, w, h, scale, (self.pixel_stride + 1) * scale,
                                -(scale * self.pixel_stride) // 2, smp.u, smp.v, m, smp.ray, smp.vertex, smp.normal,
                                self.depth_gate, math.cos(math.radians(self.normal_gate_deg)), GRAZING_NZ,
                                np.empty(room, np.int64), np.empty(room, np.float64), cand_j, cand_d, ncand)
            finally:
                head.fill(-1)
            kern.match(cand_j, cand_d, ncand, m, smap.array("confidence"), idx, v, taken)
        visible = idx[:v].copy()
        t1 = time.process_time()
        timings["associate"] += t1 - t0

        # 2. merge, recording the colour pairs before averaging
        pair_map = np.empty((max(v, 1), 3), np.float32)  # one pair per refined surfel at most
        pair_sample = np.empty((max(v, 1), 3), np.float32)
        npairs = kern.merge(taken, v, idx, smp.vertex, smp.normal, rot, trans, smp.radius, smp.alpha, smp.colour,
                            smap.array("position"), smap.array("normal"), smap.array("radius"),
                            smap.array("confidence"), smap.array("colour"), smap.array("updated"), tick,
                            self.radius_ratio, smap.block_lo, smap.block_hi, smap.BLOCK_SHIFT, pair_map, pair_sample)

        # 3. new surfels for unassociated samples
        first_new = smap.claim(int(np.count_nonzero(ncand[:m] == 0)))
        kern.append_new(ncand, m, smp.vertex, smp.normal, rot, trans, smp.radius, smp.alpha, smp.colour, first_new,
                        tick, smap.array("position"), smap.array("normal"), smap.array("radius"),
                        smap.array("confidence"), smap.array("colour"), smap.array("created"), smap.array("updated"))
        smap.note_rows(first_new, smap.size)
        n_new = smap.size - first_new
        t0 = time.process_time()
        timings["merge"] += t0 - t1

        # 4. clean-up (the unstable rule for this frame runs in the next pass over the map: _cull / _expire)
        self._removed_clean = self._clean(visible, first_new, n_new, rcw, tcw, K, w, h, tick)
        t1 = time.process_time()
        timings["clean"] += t1 - t0
        self.last_frame = {"samples": m, "associated": int(m - n_new), "refined": int(np.count_nonzero(taken >= 0)),
                           "pairs": int(npairs), "new": n_new, "removed_unstable": int(removed),
                           "removed_clean": self._removed_clean, "visible": int(v)}
        if smap.dead * 8 > smap.size:
            smap.compact()
        timings["compact"] += time.process_time() - t1

        self._frames.append(int(frame_index))
        self._tick += 1
        return ColourPairs(pair_map[:npairs].copy(), pair_sample[:npairs].copy())

    def export(self, folder: str | Path, to_display: Callable[[np.ndarray], np.ndarray], *,
               formats: tuple[str, ...] = ("ply",)) -> dict[str, Path]:
        """Write the stable surfels as ``surfels.ply`` (position, normal, display colour, radius, confidence)
        and, with ``mesh=True``, a density-trimmed Poisson mesh ``surfels_mesh.ply`` (PLY whatever ``formats``
        says: the surfel backend's files are PLY only)."""
        folder = ensure_dir(folder)
        s = self.surfels(stable_only=True)
        n = s["position"].shape[0]
        if n == 0:   # a short run: every surfel still below the confidence that makes it part of the map
            live = int(np.count_nonzero(self.map.live_mask()))
            log.warning("no surfel became stable in %d frames (%d surfels, none at confidence %g): %s holds no "
                        "surfel; fuse more frames of the same surfaces (a surfel is kept once seen about %g times) "
                        "or use --backend tsdf", self._tick, live, self.confidence_threshold,
                        Path(folder) / "surfels.ply", self.confidence_threshold)
        rgb = np.zeros((n, 3), np.uint8)
        if n:
            disp = np.asarray(to_display(s["colour"]), dtype=np.float64)
            if disp.shape != (n, 3):
                raise ValueError(f"to_display must map ({n}, 3) colours to ({n}, 3) display levels, "
                                 f"got shape {disp.shape}")
            rgb = np.clip(np.rint(np.nan_to_num(disp, nan=0.0)), 0, 255).astype(np.uint8)
        out = {"surfels": write_surfel_ply(folder / "surfels.ply", s["position"], s["normal"], rgb, s["radius"],
                                           s["confidence"])}
        if self.mesh:
            path = self._write_mesh(folder / "surfels_mesh.ply", s["position"], s["normal"], rgb)
            if path is not None:
                out["mesh"] = path
        return out

    def stats(self) -> dict:
        """Surfel counts and memory for metrics.json."""
        self._expire()
        live = self.map.live_mask()
        conf = self.map.confidence
        stable = int(np.count_nonzero(conf >= self.confidence_threshold))
        scratch = int(sum(a.nbytes for a in self._scratch.values()))
        return {
            "backend": self.name,
            "surfels": int(np.count_nonzero(live)),
            "stable_surfels": stable,
            "capacity": self.map.capacity,
            "frames_integrated": self._tick,
            "memory_bytes": self.map.nbytes + self.map.block_nbytes + scratch,
            "map_bytes": self.map.nbytes,
        }

    # ------------------------------------------------------------------------------------------------
    # inspection
    # ------------------------------------------------------------------------------------------------
    def surfels(self, *, stable_only: bool = False) -> dict[str, np.ndarray]:
        """Copies of the live (or stable) surfels: position, normal, radius, confidence, colour (map units),
        created, updated (frame indices as passed to :meth:`integrate`)."""
        self._expire()
        conf = self.map.confidence
        keep = conf >= (self.confidence_threshold if stable_only else 0.0)
        out = {name: getattr(self.map, name)[keep].copy() for name, _, _ in SurfelMap.FIELDS}
        frames = np.asarray(self._frames, dtype=np.int64)
        for name in ("created", "updated"):
            ticks = out[name]
            out[name] = frames[np.clip(ticks, 0, frames.size - 1)] if frames.size else ticks.astype(np.int64)
        return out

    # ------------------------------------------------------------------------------------------------
    # steps
    # ------------------------------------------------------------------------------------------------
    def _samples(self, depth: np.ndarray, colour: np.ndarray, K: np.ndarray, offset: int) -> _Samples:
        """Sample pixels of this frame's lattice with vertex, normal, radius, confidence and colour."""
        h, w = depth.shape
        filt = _bilateral(depth) if self.bilateral else depth
        cap = ((h - 2) // self.pixel_stride + 1) * ((w - 2) // self.pixel_stride + 1)
        u = np.empty(cap, np.int32)
        v = np.empty(cap, np.int32)
        ray = np.empty((cap, 3), np.float64)
        vert = np.empty((cap, 3), np.float64)
        nrm = np.empty((cap, 3), np.float64)
        rad = np.empty(cap, np.float64)
        alpha = np.empty(cap, np.float64)
        col = np.empty((cap, 3), np.float32)
        m = kern.frame_samples(depth, filt, colour, K[0, 0], K[1, 1], K[0, 2], K[1, 2], offset, self.pixel_stride,
                               self.depth_max, self.max_depth_jump, 2.0 * SIGMA * SIGMA, self.normal_baseline, u, v,
                               ray, vert, nrm, rad, alpha, col)
        return _Samples(u[:m], v[:m], ray[:m], vert[:m], nrm[:m], rad[:m], alpha[:m], col[:m])

    def _clean(self, visible: np.ndarray, first_new: int, n_new: int, rcw, tcw, K, w: int, h: int, tick: int) -> int:
        """Free-space and duplicate removal among the surfels in view after the merge; returns how many."""
        ids = np.concatenate([visible.astype(np.int64), np.arange(first_new, first_new + n_new, dtype=np.int64)])
        nt = ids.size
        if nt == 0:
            return 0
        smap = self.map
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        keep = np.empty(nt, np.int64)
        pc = np.empty((nt, 3), np.float32)
        nc = np.empty((nt, 3), np.float32)
        px = np.empty((nt, 2), np.float32)
        vt = kern.transform_subset(ids, nt, smap.array("position"), smap.array("normal"), rcw, tcw, fx, fy, cx, cy,
                                   float(w), float(h), np.inf, keep, pc, nc, px)
        n_old = int(np.count_nonzero(keep[:vt] < first_new))  # old ones come first, in order
        occ_ids = np.empty(n_old, np.int64)
        occ_pc = np.empty((n_old, 3), np.float32)
        occ_px = np.empty((n_old, 2), np.float32)
        occ_created = np.empty(n_old, np.int32)
        occ_updated = np.empty(n_old, np.int32)
        n_occ = kern.occupants(keep, pc, px, n_old, smap.array("confidence"), smap.array("created"),
                               smap.array("updated"), self.confidence_threshold, occ_ids, occ_pc, occ_px, occ_created,
                               occ_updated)
        if n_occ == 0:
            return 0
        zbuf, imap, tex = self._index_buffers("coarse", w * h, n_occ)
        kern.build_index(occ_px, occ_pc, n_occ, 1, w, h, zbuf, imap, tex)
        remove = np.zeros(vt, np.bool_)
        try:
            kern.clean(keep, pc, nc, px, vt, smap.array("radius"), smap.array("created"), imap, occ_ids, occ_pc,
                       occ_created, occ_updated, w, h, self.pixel_stride, tick, DUPLICATE_GAP, DUPLICATE_LATERAL,
                       DUPLICATE_MIN, self.free_space_gap, FACING_NZ, FREE_SPACE_MIN, remove)
        finally:
            kern.clear_index(tex, n_occ, zbuf, imap)
        return smap.kill(keep[:vt][remove]) if remove.any() else 0

    def _cull(self, rcw, tcw, K, w: int, h: int, min_conf: float, max_depth: float, idx, pc, nc, px) -> int:
        """The per-frame pass over the map: unstable rule, then the surfels in view into the scratch buffers."""
        smap = self.map
        removed = np.zeros(1, np.int64)
        v = cull(smap.array("position"), smap.array("normal"), smap.array("confidence"), smap.array("updated"),
                 smap.size, smap.block_lo, smap.block_hi, smap.block_oldest, smap.BLOCK_SHIFT, rcw, tcw, K[0, 0],
                 K[1, 1], K[0, 2], K[1, 2], float(w), float(h), min_conf, max_depth, self._tick - 1,
                 self.confidence_threshold, self.unstable_window, idx, pc, nc, px, removed)
        self._expired = int(removed[0])
        smap.note_dead(self._expired)
        return v

    def _expire(self) -> None:
        """Apply the unstable rule now (it otherwise runs inside the next frame's pass over the map)."""
        smap = self.map
        self._expired = int(remove_unstable(smap.array("confidence"), smap.array("updated"), smap.size,
                                                 self._tick - 1, self.confidence_threshold, self.unstable_window))
        smap.note_dead(self._expired)

    # ------------------------------------------------------------------------------------------------
    # buffers
    # ------------------------------------------------------------------------------------------------
    def _scratch_view(self, n: int):
        """Per-surfel scratch buffers for the culled set (grown with the map, reused across frames)."""
        have = self._scratch.get("vis_idx")
        if have is None or have.shape[0] < max(n, 1):
            cap = max(n, self.map.capacity, 1)
            self._scratch["vis_idx"] = np.empty(cap, np.int64)
            self._scratch["vis_pc"] = np.empty((cap, 3), np.float32)
            self._scratch["vis_nc"] = np.empty((cap, 3), np.float32)
            self._scratch["vis_px"] = np.empty((cap, 2), np.float32)
        s = self._scratch
        return s["vis_idx"], s["vis_pc"], s["vis_nc"], s["vis_px"]

    def _pixel_bins(self, pixels: int, v: int):
        """Persistent per-pixel surfel lists of the association (``head`` all -1 between uses) and per-surfel
        buffers (next in list, texel, texel winner)."""
        head = self._scratch.get("bins_head")
        if head is None or head.shape[0] != pixels:
            self._scratch["bins_head"] = np.full(pixels, -1, np.int32)
        nxt = self._scratch.get("bins_next")
        if nxt is None or nxt.shape[0] < v:
            grown = max(v, 1024, 2 * (0 if nxt is None else nxt.shape[0]))
            self._scratch["bins_next"] = np.empty(grown, np.int32)
            self._scratch["bins_tex"] = np.empty(grown, np.int64)
            self._scratch["bins_winner"] = np.empty(grown, np.bool_)
        s = self._scratch
        return s["bins_head"], s["bins_next"], s["bins_tex"], s["bins_winner"]

    def _index_buffers(self, key: str, texels: int, v: int):
        """Persistent index map (all empty between uses: kernels reset only the texels they wrote)."""
        zb = self._scratch.get(f"{key}_z")
        if zb is None or zb.shape[0] != texels:
            self._scratch[f"{key}_z"] = np.full(texels, np.inf, np.float32)
            self._scratch[f"{key}_id"] = np.full(texels, -1, np.int32)
        tex = self._scratch.get(f"{key}_tex")
        if tex is None or tex.shape[0] < v:
            self._scratch[f"{key}_tex"] = np.empty(max(v, 1024, 2 * (0 if tex is None else tex.shape[0])), np.int64)
        return self._scratch[f"{key}_z"], self._scratch[f"{key}_id"], self._scratch[f"{key}_tex"]

    def _write_mesh(self, path: Path, pos: np.ndarray, nrm: np.ndarray, rgb: np.ndarray) -> Path | None:
        if pos.shape[0] < 100:
            log.warning("only %d stable surfels: no Poisson mesh written", pos.shape[0])
            return None
        from mapping._open3d import o3d

        pcd = o3d.geometry.PointCloud()
        pcd.points = o3d.utility.Vector3dVector(pos.astype(np.float64))
        pcd.normals = o3d.utility.Vector3dVector(nrm.astype(np.float64))
        pcd.colors = o3d.utility.Vector3dVector(rgb.astype(np.float64) / 255.0)
        mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=self.poisson_depth)
        densities = np.asarray(densities)
        if self.poisson_trim > 0 and densities.size:
            mesh.remove_vertices_by_mask(densities < np.quantile(densities, self.poisson_trim))
        with atomic_path(path) as tmp:
            if not o3d.io.write_triangle_mesh(str(tmp), mesh):
                raise OutputError(f"Open3D could not write the mesh {path}; choose another output folder")
        return Path(path)


# --------------------------------------------------------------------------------------------------
# helpers
# --------------------------------------------------------------------------------------------------
def vertex_normal_maps(depth: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame vertex and unit normal maps ``(H, W, 3)`` float32 of a depth map (vectorised NumPy).

    Normals are the cross product of central differences of the back-projected vertex map, oriented to face
    the camera (``n . v < 0``); zero where the pixel or one of its four neighbours has no depth, and on the
    border. This is the same computation :func:`~mapping.fusion._surfel_kernels.frame_samples` does per
    sample inside the fusion loop.
    """
    depth, _ = _check_images(depth, np.zeros(np.shape(depth) + (3,), np.float32))
    K = _check_K(K)
    h, w = depth.shape
    z = depth.astype(np.float64)
    u = (np.arange(w) - K[0, 2]) / K[0, 0]
    v = (np.arange(h) - K[1, 2]) / K[1, 1]
    vert = np.stack([z * u[None, :], z * v[:, None], z], axis=-1)
    normal = np.zeros_like(vert)
    dx = vert[1:-1, 2:] - vert[1:-1, :-2]
    dy = vert[2:, 1:-1] - vert[:-2, 1:-1]
    n = np.cross(dx, dy)
    ok = (z[1:-1, 1:-1] > 0) & (z[1:-1, 2:] > 0) & (z[1:-1, :-2] > 0) & (z[2:, 1:-1] > 0) & (z[:-2, 1:-1] > 0)
    norm = np.linalg.norm(n, axis=-1)
    ok &= norm > 0
    n /= np.where(ok, norm, 1.0)[..., None]
    n *= np.where(np.einsum("ijk,ijk->ij", n, vert[1:-1, 1:-1]) > 0, -1.0, 1.0)[..., None]
    normal[1:-1, 1:-1] = np.where(ok[..., None], n, 0.0)
    return vert.astype(np.float32), normal.astype(np.float32)


def _bilateral(depth: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.bilateralFilter(depth, 5, 0.03, 4.5)


def _world_to_camera(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    rot = pose[:3, :3]
    return np.ascontiguousarray(rot.T), np.ascontiguousarray(-rot.T @ pose[:3, 3])


def _check_pose(pose) -> np.ndarray:
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"pose must be a (4, 4) camera-to-world matrix, got shape {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise ValueError("pose must be finite; got NaN or inf entries (a failed tracking step?)")
    rot = pose[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > 1e-3 or np.linalg.det(rot) < 0:
        raise ValueError("pose must hold a rotation in its upper-left 3x3 block (orthonormal, det +1); "
                         "re-orthonormalise it")
    return pose


def _check_K(K) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K must be a (3, 3) intrinsics matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"K must be finite with positive focal lengths, got fx={K[0, 0]}, fy={K[1, 1]}")
    return K


def _check_images(depth, colour) -> tuple[np.ndarray, np.ndarray]:
    depth = np.asarray(depth)
    if depth.ndim != 2:
        raise ValueError(f"depth must be a (H, W) array in metres, got shape {depth.shape}")
    if depth.shape[0] < 3 or depth.shape[1] < 3:
        raise ValueError(f"depth must be at least 3x3 pixels, got shape {depth.shape}")
    if not np.issubdtype(depth.dtype, np.floating):
        raise TypeError(f"depth must be float metres (0 = invalid), got dtype {depth.dtype}; "
                        "convert with radiometry.images.read_depth")
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if not np.all(np.isfinite(depth)):
        depth = np.where(np.isfinite(depth), depth, np.float32(0))
    colour = np.asarray(colour)
    if colour.shape != depth.shape + (3,):
        raise ValueError(f"colour must have shape {depth.shape + (3,)} (the depth's size, 3 channels), "
                         f"got {colour.shape}")
    return depth, np.ascontiguousarray(colour, dtype=np.float32)
