#!/usr/bin/env python
"""Stress radiomap's own ray cast against Open3D's (issue 33): the same depth bit for bit on varied inputs.

``TSDFBackend`` casts the map with its kernel (``mapping._ckernels.raycast_depth``: Open3D 0.20's range map and
march, reading the grid's buffers through a dense block table) instead of ``VoxelBlockGrid.ray_cast``. It reads
Open3D's internals (the buffers, the block slots), so every case here builds a map and casts it both ways at
several poses, comparing depth bit for bit and colour value for value (Open3D's cast plus
:meth:`TSDFBackend._surface_colour`, the path used before):

- scenes drawn per case: a box room (walls, floor, ceiling) of random size with up to 8 spheres, rendered
  analytically from random camera poses, depth with random holes and noise, random colour;
- random voxel size (4 mm - 5 cm), block resolution (8 or 16), truncation (2-10 voxels), depth range
  (min 0-0.5 m, max 1-6 m), weight threshold (1-3), colour storage (uint16 or float32);
- image sizes 64x48, 160x120, 212x160 (not multiples of 8), 320x240 and 640x480; intrinsics with random
  focal length and principal point;
- fused: 3-7 frames of a short sweep about one viewpoint; cast poses: the fused ones, ones moved away, turned toward empty space, outside the room, inside a sphere.

Each cast is also made by the kernel's scalar march (``RADIOMAP_SIMD=0``) where the AVX-512 march runs
(``mapping/_ckernels_raycast_simd.h``): depth, colour and the step and ray counts must agree too.

A case passes when every cast agrees. Prints a line per failing case and a summary; exits 1 on any failure.
Usage::

    python scripts/stress_raycast.py --runs 300          # ~1-2 s per case on 2 cores
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np


def _look(origin, target, up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Camera-to-world pose (x right, y down, z forward) at ``origin`` looking at ``target``."""
    z = np.asarray(target, float) - origin
    z /= np.linalg.norm(z)
    x = np.cross(z, -np.asarray(up, float))
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, [1.0, 0, 0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    pose = np.eye(4)
    pose[:3, :3] = np.column_stack([x, y, z])
    pose[:3, 3] = origin
    return pose


def _render(room, spheres, pose, K, h, w) -> np.ndarray:
    """Depth (metres along z) of the box room ``room`` (lo, hi corners) and ``spheres`` (centre, radius)."""
    u, v = np.meshgrid(np.arange(w, dtype=float), np.arange(h, dtype=float))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    d = d_cam @ pose[:3, :3].T
    o = pose[:3, 3]
    t = np.full((h, w), np.inf)
    lo, hi = room
    with np.errstate(divide="ignore", invalid="ignore"):
        for a in range(3):
            for wall in (lo[a], hi[a]):
                s = (wall - o[a]) / d[..., a]
                t = np.where((s > 1e-6) & (s < t), s, t)
    for c, r in spheres:
        oc = o - c
        b = d @ oc
        cc = oc @ oc - r * r
        a2 = np.einsum("...i,...i", d, d)
        disc = b * b - a2 * cc
        ok = disc >= 0
        s = np.where(ok, (-b - np.sqrt(np.where(ok, disc, 0))) / a2, np.inf)
        s = np.where(s > 1e-6, s, np.where(ok, (-b + np.sqrt(np.where(ok, disc, 0))) / a2, np.inf))
        t = np.where((s > 1e-6) & (s < t), s, t)
    return np.where(np.isfinite(t), t, 0).astype(np.float32)   # t is depth: d_cam has z = 1


def build_case(seed: int):
    """One case's map and casts: (backend, K, h, w, cast poses, a description, the depth renderer), or None
    when nothing could be fused."""
    from mapping.fusion.tsdf import TSDFBackend

    rng = np.random.default_rng(seed)
    w, h = [(64, 48), (160, 120), (212, 160), (320, 240), (640, 480)][rng.integers(0, 5)]
    f = rng.uniform(0.7, 1.3) * w * 0.9
    K = np.array([[f, 0, w / 2 - 0.5 + rng.uniform(-8, 8)], [0, f * rng.uniform(0.97, 1.03), h / 2 - 0.5 +
                  rng.uniform(-6, 6)], [0, 0, 1]])
    size = rng.uniform(1.5, 6.0, 3)
    lo = -size / 2 + rng.uniform(-20, 20, 3) * (rng.random() < 0.3)
    room = (lo, lo + size)
    centre = lo + size / 2
    spheres = [(lo + rng.uniform(0.2, 0.8, 3) * size, rng.uniform(0.05, 0.5)) for _ in range(rng.integers(0, 9))]
    voxel = float(np.exp(rng.uniform(np.log(0.004), np.log(0.05))))
    res = int(rng.choice([8, 16]))
    settings = dict(voxel_size=voxel, block_resolution=res, trunc_voxel_multiplier=float(rng.uniform(2, 10)),
                    depth_min=float(rng.uniform(0, 0.5)), depth_max=float(rng.uniform(1.0, 6.0)),
                    weight_threshold=float(rng.integers(1, 4)),
                    colour_storage=str(rng.choice(["uint16", "float32"])), block_count=int(rng.integers(16, 2000)))
    if voxel < 0.008 and w * h > 160 * 120:      # keep the case's map small
        w, h = 160, 120
        K[:2] *= 0.25
    backend = TSDFBackend(**settings)
    poses = []   # a short hand-held sweep: small moves about one viewpoint, so that voxels gather weight
    base, aim = centre + rng.uniform(-0.35, 0.35, 3) * size, centre + rng.uniform(-0.5, 0.5, 3) * size
    for _ in range(int(rng.integers(3, 8))):
        poses.append(_look(base + rng.normal(0, 0.03, 3) * size, aim + rng.normal(0, 0.05, 3) * size))
    for pose in poses:
        depth = _render(room, spheres, pose, K, h, w)
        depth = depth * (1 + rng.normal(0, 0.002, depth.shape)).astype(np.float32)
        depth[rng.random(depth.shape) < rng.uniform(0, 0.3)] = 0
        colour = rng.uniform(0, 1.2, (h, w, 3)).astype(np.float32)
        try:
            backend.integrate(depth, colour, K, pose)
        except RuntimeError as e:      # Open3D aborts a frame whose depth touches no block (all out of range)
            if "No block is touched" not in str(e):
                raise
    if backend.frames_integrated == 0:
        return None
    casts = list(poses)
    casts.append(_look(centre + rng.uniform(-0.4, 0.4, 3) * size, centre + rng.uniform(-3, 3, 3) * size))
    casts.append(_look(centre + size * rng.choice([-1.5, 1.5], 3), centre))     # outside the room
    if spheres:
        casts.append(_look(spheres[0][0], spheres[0][0] + rng.normal(size=3)))  # inside a sphere
    casts.append(poses[0] @ np.diag([1.0, 1, 1, 1]) @ _shift(rng.uniform(-0.3, 0.3, 3)))
    desc = (f"seed {seed}: {w}x{h}, voxel {voxel * 1000:.1f} mm, res {res}, "
            f"trunc {settings['trunc_voxel_multiplier']:.1f}, depth {settings['depth_min']:.2f}-"
            f"{settings['depth_max']:.2f}, weight {settings['weight_threshold']:.0f}, {settings['colour_storage']}, "
            f"{len(poses)} fused, {len(casts)} casts")
    return backend, K, h, w, casts, desc, lambda pose: _render(room, spheres, pose, K, h, w)


def own_casts(backend, blocks, K, pose, h, w):
    """The kernel's cast with its default march and with the scalar one forced: ((view, steps, rays, SIMD ran)
    per march)."""
    backend.ray_caster = "radiomap"
    out = []
    saved = os.environ.get("RADIOMAP_SIMD")
    try:
        for value in ("1", "0"):
            os.environ["RADIOMAP_SIMD"] = value
            view = backend._ray_cast(blocks, K, pose, h, w)
            out.append((view, backend.cast_steps, backend.cast_rays, backend.cast_simd))
    finally:
        if saved is None:
            os.environ.pop("RADIOMAP_SIMD", None)
        else:
            os.environ["RADIOMAP_SIMD"] = saved
    return out


def _differ(a, b) -> np.ndarray:
    return (a.depth.view(np.uint32) != b.depth.view(np.uint32)) | np.any(a.colour != b.colour, axis=2)


def run_case(seed: int) -> tuple[int, int, int, str, int]:
    """One case: (casts, pixels compared, pixels differing in depth or colour between Open3D's cast and the
    kernel's or between the kernel's two marches (a cast whose marches' counts differ counts all its pixels), a
    description, pixels that found a surface)."""
    case = build_case(seed)
    if case is None:
        return 0, 0, 0, f"seed {seed}: nothing to fuse", 0
    backend, K, h, w, casts, desc, render = case
    n = bad = hits = simd = 0
    for pose in casts:
        depth = render(pose)
        try:   # the blocks this view's depth touches, as render_for_frame casts them
            blocks = backend._prepare(depth, K, pose).blocks
        except RuntimeError:   # it touches none (all beyond the range): the last fused frame's, as render() casts
            blocks = backend._last_blocks
        backend.ray_caster = "open3d"
        a = backend._ray_cast(blocks, K, pose, h, w)
        (b, steps, rays, used), (c, steps_s, rays_s, _) = own_casts(backend, blocks, K, pose, h, w)
        differ = _differ(a, b) | _differ(b, c)
        if (steps, rays) != (steps_s, rays_s):
            differ[:] = True
        n += a.depth.size
        bad += int(np.count_nonzero(differ))
        hits += int(np.count_nonzero(b.depth))
        simd += used
    backend.ray_caster = "radiomap"
    return len(casts), n, bad, desc + (f", {simd} with AVX-512" if simd else ""), hits


def _shift(t) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = t
    return m


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=300)
    p.add_argument("--seed", type=int, default=0, help="first case's seed")
    args = p.parse_args(argv)
    start = time.perf_counter()
    from radiometry._native import compiled

    simd = getattr(compiled("mapping._ckernels"), "raycast_simd", 0)
    print(f"the kernel's march: {'AVX-512 (compared with its scalar march)' if simd else 'scalar'}", flush=True)
    casts = pixels = failed = surface = 0
    for seed in range(args.seed, args.seed + args.runs):
        c, n, bad, desc, hits = run_case(seed)
        casts, pixels, surface = casts + c, pixels + n, surface + hits
        if bad:
            failed += 1
            print(f"DIFFER {desc}: {bad} of {n} pixels", flush=True)
    print(f"{args.runs} cases, {casts} casts, {pixels:,} pixels compared ({surface:,} on a surface): {failed} cases differ "
          f"({time.perf_counter() - start:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
