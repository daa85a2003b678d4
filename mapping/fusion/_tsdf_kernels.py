"""Numba kernels of the TSDF backend (one pass over an image each; compiled on first use, cached on disk)."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

import mapping._numba_threads  # noqa: F401  (the threading layer, before any parallel kernel runs)


@njit(cache=True, nogil=True)
def colour_pairs(map_depth, depth, map_colour, colour, abs_tol, rel_tol, dmin, dmax, out_map,
                 out_sample):  # pragma: no cover
    """Gather (map colour, sample colour) where the rendered and measured depths agree; returns the count."""
    f32 = np.float32  # the scalars' types here, not the caller's (the C twin's contract)
    abs_tol, rel_tol, dmin, dmax = f32(abs_tol), f32(rel_tol), f32(dmin), f32(dmax)
    n = 0
    rows, cols = depth.shape
    for y in range(rows):
        for x in range(cols):
            m = map_depth[y, x]
            d = depth[y, x]
            if m > 0 and d > dmin and d <= dmax:
                tol = rel_tol * d
                if tol < abs_tol:
                    tol = abs_tol
                if abs(m - d) <= tol:
                    for c in range(3):
                        out_map[n, c] = map_colour[y, x, c]
                        out_sample[n, c] = colour[y, x, c]
                    n += 1
    return n


@njit(cache=True, nogil=True)
def finish_view(vertex, normal, depth, c, half_voxel, debias):  # pragma: no cover
    """Per pixel of a ray-cast view: zero vertex and normal where there is no surface (0 normal also where the
    normal is undefined, next to holes), orient normals towards the camera and, with ``debias``, move the
    point along its ray by the mean displacement of Open3D's floored voxel reads,
    ``lambda = (n . h) z / (n . v)`` (``h = half_voxel * c``, ``c`` the grid diagonal in the camera frame)."""
    rows, cols = depth.shape
    half_voxel = np.float32(half_voxel)
    limit = 2.0 * half_voxel
    for y in range(rows):
        for x in range(cols):
            z = depth[y, x]
            if not z > 0:
                for k in range(3):
                    vertex[y, x, k] = 0.0
                    normal[y, x, k] = 0.0
                continue
            n0 = normal[y, x, 0]
            n1 = normal[y, x, 1]
            n2 = normal[y, x, 2]
            if not (n0 == n0 and n1 == n1 and n2 == n2):
                normal[y, x, 0] = 0.0
                normal[y, x, 1] = 0.0
                normal[y, x, 2] = 0.0
                continue
            nv = n0 * vertex[y, x, 0] + n1 * vertex[y, x, 1] + n2 * vertex[y, x, 2]
            if nv > 0:
                normal[y, x, 0] = -n0
                normal[y, x, 1] = -n1
                normal[y, x, 2] = -n2
            if not debias or abs(nv) < 1e-6:
                continue
            lam = half_voxel * (n0 * c[0] + n1 * c[1] + n2 * c[2]) * z / nv
            if lam > limit:
                lam = limit
            elif lam < -limit:
                lam = -limit
            s = 1.0 - lam / z
            vertex[y, x, 0] *= s
            vertex[y, x, 1] *= s
            vertex[y, x, 2] *= s
            depth[y, x] = z * s
    return depth


# --------------------------------------------------------------------------------------------------
# surface refinement: voxel look-ups without the hash map (a dense table of buffer indices per block)
# --------------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True, inline="always")
def _voxel(vx, vy, vz, shift, mask, res, index, lo):  # pragma: no cover
    """Linear index of voxel (vx, vy, vz) in the grid's attribute buffers, or -1 when its block is absent.
    Blocks are ``res = 2**shift`` voxels a side; ``index[bx - lo0, by - lo1, bz - lo2]`` is a block's buffer
    slot; inside a block, voxels are stored z-major (Open3D's layout ``[slot, z, y, x]``)."""
    jx = (vx >> shift) - lo[0]
    jy = (vy >> shift) - lo[1]
    jz = (vz >> shift) - lo[2]
    if jx < 0 or jy < 0 or jz < 0 or jx >= index.shape[0] or jy >= index.shape[1] or jz >= index.shape[2]:
        return -1
    slot = index[jx, jy, jz]
    if slot < 0:
        return -1
    return ((slot * res + (vz & mask)) * res + (vy & mask)) * res + (vx & mask)


@njit(cache=True, nogil=True)
def _tsdf_at(px, py, pz, inv_vs, shift, tsdf, weight, index, lo):  # pragma: no cover
    """Trilinear TSDF at a world point (voxel i sits at i * voxel_size); NaN next to unobserved voxels."""
    res = 1 << shift
    mask = res - 1
    gx, gy, gz = px * inv_vs, py * inv_vs, pz * inv_vs
    if not (abs(gx) < 4e18 and abs(gy) < 4e18 and abs(gz) < 4e18):  # inf or NaN: no voxel
        return np.nan
    fx0, fy0, fz0 = np.floor(gx), np.floor(gy), np.floor(gz)
    ix, iy, iz = int(fx0), int(fy0), int(fz0)
    fx, fy, fz = gx - fx0, gy - fy0, gz - fz0
    base = _voxel(ix, iy, iz, shift, mask, res, index, lo)
    if base < 0:
        return np.nan
    inside = (ix & mask) < mask and (iy & mask) < mask and (iz & mask) < mask  # all 8 corners in one block
    acc = 0.0
    for k in range(8):
        dx, dy, dz = k & 1, (k >> 1) & 1, (k >> 2) & 1
        if inside:
            li = base + dx + dy * res + dz * res * res
        else:
            li = _voxel(ix + dx, iy + dy, iz + dz, shift, mask, res, index, lo)
            if li < 0:
                return np.nan
        if weight[li] <= 0:
            return np.nan
        acc += (fx if dx else 1.0 - fx) * (fy if dy else 1.0 - fy) * (fz if dz else 1.0 - fz) * tsdf[li]
    return acc


@njit(cache=True, nogil=True)
def refine(depth, vertex, fx, fy, cx, cy, R, o, tsdf, weight, index, lo, shift, vs):  # pragma: no cover
    """Move each rendered point to the zero crossing of the trilinear TSDF along its ray: bracket the
    current depth by +-1 voxel, one regula-falsi step, one secant step. Pixels whose bracket does not change
    sign (or touches unobserved voxels) keep their depth. Returns the number of refined pixels."""
    rows, cols = depth.shape
    f64 = np.float64
    fx, fy, cx, cy, vs = f64(fx), f64(fy), f64(cx), f64(cy), f64(vs)
    inv_vs = 1.0 / vs
    n = 0
    for v in range(rows):
        yc = (v - cy) / fy
        for u in range(cols):
            t0 = depth[v, u]
            if not t0 > 0:
                continue
            xc = (u - cx) / fx
            wx = R[0, 0] * xc + R[0, 1] * yc + R[0, 2]
            wy = R[1, 0] * xc + R[1, 1] * yc + R[1, 2]
            wz = R[2, 0] * xc + R[2, 1] * yc + R[2, 2]
            a, b = t0 - vs, t0 + vs
            fa = _tsdf_at(o[0] + a * wx, o[1] + a * wy, o[2] + a * wz, inv_vs, shift, tsdf, weight, index, lo)
            if not fa > 0:
                continue
            fb = _tsdf_at(o[0] + b * wx, o[1] + b * wy, o[2] + b * wz, inv_vs, shift, tsdf, weight, index, lo)
            if not fb < 0:
                continue
            t = a - fa * (b - a) / (fb - fa)
            ft = _tsdf_at(o[0] + t * wx, o[1] + t * wy, o[2] + t * wz, inv_vs, shift, tsdf, weight, index, lo)
            if ft == ft:
                if ft > 0:
                    a, fa = t, ft
                else:
                    b, fb = t, ft
                t = a - fa * (b - a) / (fb - fa)
            depth[v, u] = t
            vertex[v, u, 0] = t * xc
            vertex[v, u, 1] = t * yc
            vertex[v, u, 2] = t
            n += 1
    return n


@njit(cache=True, nogil=True)
def range_fragments(blocks, R, t, fx, fy, cx, cy, down, res, voxel_size, h_down, w_down, depth_min, depth_max,
                    out):  # pragma: no cover
    """Per block: the fragments Open3D's ``EstimateRange`` (pass 0) allots it, in its float32 arithmetic: the
    eight corners in front of the camera projected into the 1/``down`` range map, their floored / ceiled
    rectangle clipped to ``h_down`` x ``w_down`` and cut into 16 x 16 fragments (0 for an empty rectangle or
    depth interval). Coordinates beyond the map are clipped before the int conversion (Open3D's overflows to
    INT_MIN and widens nothing, so the count here is never the smaller). Returns the total."""
    total = 0
    f32 = np.float32
    fx, fy, cx, cy, down, voxel_size = f32(fx), f32(fy), f32(cx), f32(cy), f32(down), f32(voxel_size)
    depth_min, depth_max = f32(depth_min), f32(depth_max)
    one = np.float32(1.0)
    for k in range(blocks.shape[0]):
        u_min, v_min, u_max, v_max = w_down - 1, h_down - 1, 0, 0
        z_min, z_max = depth_max, depth_min
        for i in range(8):
            xw = np.float32((blocks[k, 0] + (i & 1)) * res) * voxel_size
            yw = np.float32((blocks[k, 1] + ((i >> 1) & 1)) * res) * voxel_size
            zw = np.float32((blocks[k, 2] + ((i >> 2) & 1)) * res) * voxel_size
            zc = R[2, 0] * xw + R[2, 1] * yw + R[2, 2] * zw + t[2]
            if zc <= 0:
                continue
            xc = R[0, 0] * xw + R[0, 1] * yw + R[0, 2] * zw + t[0]
            yc = R[1, 0] * xw + R[1, 1] * yw + R[1, 2] * zw + t[1]
            inv_z = one / zc
            u = (xc * fx * inv_z + cx) / down
            v = (yc * fy * inv_z + cy) / down
            u_lo = int(min(max(np.floor(u), -1.0), w_down))
            u_hi = int(min(max(np.ceil(u), -1.0), w_down))
            v_lo = int(min(max(np.floor(v), -1.0), h_down))
            v_hi = int(min(max(np.ceil(v), -1.0), h_down))
            u_min, u_max = min(u_lo, u_min), max(u_hi, u_max)
            v_min, v_max = min(v_lo, v_min), max(v_hi, v_max)
            z_min, z_max = min(z_min, zc), max(z_max, zc)
        u_min, v_min = max(0, u_min), max(0, v_min)
        u_max, v_max = min(w_down - 1, u_max), min(h_down - 1, v_max)
        n = 0
        if v_min < v_max and u_min < u_max and z_min < z_max:
            n = ((v_max - v_min + 16) // 16) * ((u_max - u_min + 16) // 16)
        out[k] = n
        total += n
    return total


# --------------------------------------------------------------------------------------------------
# surface colour: the trilinear colour at each ray-cast surface point, read straight from the grid's buffers
# --------------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True)
def hit_bounds(depth, Rc, o, fx, fy, cx, cy, block_size):  # pragma: no cover
    """The block coordinates (lowest, highest) of a box holding the surface point of every pixel with depth
    (``o + depth * Rc (u - cx) / fx, (v - cy) / fy, 1)``, camera-to-world ``Rc``, origin ``o``) and the blocks
    of its eight neighbouring voxels (one block wider on each side)."""
    f32 = np.float32
    fx, fy, cx, cy, block_size = f32(fx), f32(fy), f32(cx), f32(cy), f32(block_size)
    lo = np.full(3, 2 ** 30, np.int64)
    hi = np.full(3, -2 ** 30, np.int64)
    q = np.empty(3, np.float32)
    rows, cols = depth.shape
    for y in range(rows):
        dy = (np.float32(y) - cy) / fy
        for x in range(cols):
            t = depth[y, x]
            if not t > 0:
                continue
            dx = (np.float32(x) - cx) / fx
            for a in range(3):
                q[a] = (o[a] + t * (Rc[a, 0] * dx + Rc[a, 1] * dy + Rc[a, 2])) / block_size
            if not (_in_range(q[0]) and _in_range(q[1]) and _in_range(q[2])):
                continue  # no block (inf, or beyond 2^30 blocks)
            for a in range(3):
                b = int(np.floor(q[a]))
                if b - 1 < lo[a]:
                    lo[a] = b - 1
                if b + 1 > hi[a]:
                    hi[a] = b + 1
    return lo, hi


@njit(cache=True, nogil=True, inline="always")
def _in_range(q):  # pragma: no cover
    """A block coordinate that fits (``|q| < 2^30``; False for NaN and inf)."""
    return abs(q) < np.float32(1073741824.0)


@njit(cache=True, nogil=True, parallel=True)
def surface_colour(depth, Rc, o, fx, fy, cx, cy, colour, weight, index, lo, res, voxel_size, scale,
                   out):  # pragma: no cover
    """Colour of each pixel's ray-cast surface point (``depth`` along the ray, as :func:`hit_bounds`), as
    Open3D's ``VoxelBlockGrid.ray_cast`` colours it: the trilinear interpolation of the eight voxels around the
    point, over those observed (weight > 0), 0 where the point's block is absent or no corner is observed.
    ``index``/``lo`` is a dense table of the blocks' buffer slots (-1 = absent); ``colour`` holds the stored
    colours (float32 x 255 as Open3D stores float images, or uint16 x the backend's ``colour_scale``), divided
    by ``scale`` here. Voxel
    ``(i, j, k)`` of a block sits at its corner ``+ (i, j, k) * voxel_size`` (z-major buffers)."""
    rows, cols = depth.shape
    f32 = np.float32
    fx, fy, cx, cy, scale = f32(fx), f32(fy), f32(cx), f32(cy), f32(scale)
    vs = f32(voxel_size)
    block_size = vs * f32(res)
    res2 = res * res
    res3 = res2 * res
    for y in prange(rows):
        dyc = (f32(y) - cy) / fy
        for x in range(cols):
            out[y, x, 0] = 0.0
            out[y, x, 1] = 0.0
            out[y, x, 2] = 0.0
            t = depth[y, x]
            if not t > 0:
                continue
            dxc = (f32(x) - cx) / fx
            xg = o[0] + t * (Rc[0, 0] * dxc + Rc[0, 1] * dyc + Rc[0, 2])
            yg = o[1] + t * (Rc[1, 0] * dxc + Rc[1, 1] * dyc + Rc[1, 2])
            zg = o[2] + t * (Rc[2, 0] * dxc + Rc[2, 1] * dyc + Rc[2, 2])
            qx, qy, qz = xg / block_size, yg / block_size, zg / block_size
            if not (_in_range(qx) and _in_range(qy) and _in_range(qz)):
                continue
            bx = int(np.floor(qx))
            by = int(np.floor(qy))
            bz = int(np.floor(qz))
            slot = _block_slot(bx, by, bz, index, lo)
            if slot < 0:
                continue
            gx = (xg - f32(bx) * block_size) / vs
            gy = (yg - f32(by) * block_size) / vs
            gz = (zg - f32(bz) * block_size) / vs
            fx0, fy0, fz0 = np.floor(gx), np.floor(gy), np.floor(gz)
            ix, iy, iz = int(fx0), int(fy0), int(fz0)
            rx, ry, rz = gx - fx0, gy - fy0, gz - fz0
            r_sum = f32(0.0)
            c0 = f32(0.0)
            c1 = f32(0.0)
            c2 = f32(0.0)
            for k in range(8):
                dx, dy, dz = k & 1, (k >> 1) & 1, (k >> 2) & 1
                nx, ny, nz = ix + dx, iy + dy, iz + dz
                if 0 <= nx < res and 0 <= ny < res and 0 <= nz < res:
                    li = slot * res3 + nz * res2 + ny * res + nx
                else:
                    nslot = _block_slot(bx + (nx >= res) - (nx < 0), by + (ny >= res) - (ny < 0),
                                        bz + (nz >= res) - (nz < 0), index, lo)
                    if nslot < 0:
                        continue
                    li = nslot * res3 + (nz % res) * res2 + (ny % res) * res + (nx % res)
                if not weight[li] > 0:
                    continue
                r = (rx if dx else f32(1.0) - rx) * (ry if dy else f32(1.0) - ry) * (rz if dz else f32(1.0) - rz)
                c0 += r * colour[3 * li]
                c1 += r * colour[3 * li + 1]
                c2 += r * colour[3 * li + 2]
                r_sum += r
            if r_sum > 0:
                r_sum *= scale
                out[y, x, 0] = c0 / r_sum
                out[y, x, 1] = c1 / r_sum
                out[y, x, 2] = c2 / r_sum


@njit(cache=True, nogil=True)
def fill_block_table(keys, slots, lo, index):  # pragma: no cover
    """Write the slot of each block ``keys[i]`` that lies in the dense table ``index`` over blocks ``lo ..``."""
    for i in range(keys.shape[0]):
        jx, jy, jz = keys[i, 0] - lo[0], keys[i, 1] - lo[1], keys[i, 2] - lo[2]
        if 0 <= jx < index.shape[0] and 0 <= jy < index.shape[1] and 0 <= jz < index.shape[2]:
            index[jx, jy, jz] = slots[i]


@njit(cache=True, nogil=True, inline="always")
def _block_slot(bx, by, bz, index, lo):  # pragma: no cover
    """Buffer slot of block (bx, by, bz) in a dense table over blocks ``lo ..`` (-1: absent or outside)."""
    jx, jy, jz = bx - lo[0], by - lo[1], bz - lo[2]
    if jx < 0 or jy < 0 or jz < 0 or jx >= index.shape[0] or jy >= index.shape[1] or jz >= index.shape[2]:
        return -1
    return index[jx, jy, jz]


# --------------------------------------------------------------------------------------------------
# integration into a grid of 16-bit weight and colour (Open3D's kernel truncates 16-bit colour: see tsdf.py)
# --------------------------------------------------------------------------------------------------
@njit(cache=True, nogil=True, parallel=True)
def integrate_u16(depth, colour, fx, fy, cx, cy, E, keys, slots, res, voxel_size, sdf_trunc, depth_max, scale,
                  tsdf, weight, colour_buf, clipped):  # pragma: no cover
    """Fuse one frame into the voxels of the blocks ``keys`` (block coordinates) held at buffer ``slots``,
    voxel for voxel as Open3D's ``VoxelBlockGrid.integrate`` does (its float32 arithmetic: voxel centre
    ``(block * res + i) * voxel_size``, world-to-camera ``E`` (3 x 4), pixel ``int(u)`` of ``u = fx x / z + cx``
    inside ``[0, W - 1]``, the same depth and truncation tests, the running average of the TSDF), except the
    colour: ``colour * scale`` averaged with the voxel's colour and rounded to the nearest integer (Open3D
    truncates, a bias that grows with the weight), clamped to ``[0, 65535]``; NaN stores 0. Weights stop at
    65535. ``clipped[b]`` counts the colour values of block ``b`` that were clamped."""
    rows, cols = depth.shape
    res2 = res * res
    res3 = res2 * res
    f32 = np.float32
    fx, fy, cx, cy, voxel_size = f32(fx), f32(fy), f32(cx), f32(cy), f32(voxel_size)
    sdf_trunc, depth_max, scale = f32(sdf_trunc), f32(depth_max), np.float64(scale)
    for b in prange(slots.shape[0]):
        base = slots[b] * res3
        xb, yb, zb = keys[b, 0] * res, keys[b, 1] * res, keys[b, 2] * res
        n_clipped = 0
        for iz in range(res):
            zs = f32(zb + iz) * voxel_size
            z0, z1, z2 = zs * E[0, 2], zs * E[1, 2], zs * E[2, 2]
            for iy in range(res):
                ys = f32(yb + iy) * voxel_size
                y0, y1, y2 = ys * E[0, 1], ys * E[1, 1], ys * E[2, 1]
                li = base + iz * res2 + iy * res - 1
                for ix in range(res):
                    li += 1
                    xs = f32(xb + ix) * voxel_size
                    # Open3D's order of operations (the same float32 rounding: the same voxels fused)
                    xc = xs * E[0, 0] + y0 + z0 + E[0, 3]
                    yc = xs * E[1, 0] + y1 + z1 + E[1, 3]
                    zc = xs * E[2, 0] + y2 + z2 + E[2, 3]
                    inv_z = f32(1.0) / zc
                    u = fx * xc * inv_z + cx
                    v = fy * yc * inv_z + cy
                    if not (v >= 0 and u >= 0 and v <= f32(rows - 1) and u <= f32(cols - 1)):
                        continue
                    ui, vi = int(u), int(v)
                    d = depth[vi, ui]
                    sdf = d - zc
                    if d <= 0 or d > depth_max or zc <= 0 or sdf < -sdf_trunc:
                        continue
                    if not sdf < sdf_trunc:
                        sdf = sdf_trunc
                    sdf /= sdf_trunc
                    w = f32(weight[li])
                    inv_wsum = f32(1.0) / (w + f32(1.0))
                    tsdf[li] = (w * tsdf[li] + sdf) * inv_wsum
                    w64 = np.float64(w)
                    inv64 = 1.0 / (w64 + 1.0)
                    for c in range(3):
                        x = np.float64(colour[vi, ui, c]) * scale
                        if x != x:
                            x = 0.0
                        elif x < 0.0 or x > 65535.0:
                            x = 0.0 if x < 0.0 else 65535.0
                            n_clipped += 1
                        colour_buf[3 * li + c] = np.uint16((w64 * colour_buf[3 * li + c] + x) * inv64 + 0.5)
                    if w < f32(65535.0):
                        weight[li] = np.uint16(w + f32(1.0))
        clipped[b] = n_clipped
