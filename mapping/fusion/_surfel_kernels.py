"""Numba kernels of the surfel backend (:mod:`mapping.fusion.surfel`); the pass over the whole map
(``cull``, the unstable rule) lives with the map's block summaries in :mod:`mapping.fusion.surfel_map`.

Each kernel is a loop NumPy cannot express without materialising far larger arrays than the answer:

- :func:`frame_samples`: the per-pixel sample preparation (validity, normal from central differences,
  radius, confidence) in one pass instead of ~60 NumPy temporaries (measured more than 10x faster at
  640x480).
- :func:`build_index` / :func:`clear_index`: the z-buffer of the clean-up's image-resolution index map, a
  per-texel minimum with write conflicts that also keeps the winner's id, and resets only the texels
  written (``np.minimum.at`` plus a winner pass and a fresh map per frame: 8.5x slower, measured at 100k
  surfels).
- :func:`bin_pixels` / :func:`mark_winners` / :func:`candidates` / :func:`match`: the association's index
  map ``scale`` times finer than the image, kept as per-pixel lists of the surfels that project into each
  pixel (the texel's winner is the nearest surfel of the list with that texel): 1.2 MB that stay in the CPU
  cache instead of a dense 4x z-buffer and id map (39 MB at 640x480, each surfel a cache miss); then the
  search for the surfels near each pixel's ray in its index-map window (depth and normal gates), sample by
  sample in image order through the lists of the window's pixels, then the pixel -> surfel choice (nearest
  ray, conflicts to the closest ray) and the surfels' own nearest pixel: scatter-minima with write
  conflicts.
- :func:`merge` / :func:`append_new`: the confidence-weighted update, a scatter into the map by surfel id that
  also records the colour pairs before averaging, and the new surfels written straight into the map (the
  samples taken to the world frame on the way: no per-frame world-frame copies, masks or gathers).
- :func:`occupants` / :func:`clean`: ElasticFusion's free-space / duplicate test, a window search per
  surfel among the stable surfels in view (gathered in one pass).
- :func:`splat`: surfel-disc rendering with a per-pixel z-buffer (ray / disc intersection per pixel of each
  surfel's footprint).

All kernels are serial (``@njit(cache=True)``, no ``parallel=True``): the backend must reach its frame
rate on one core, and serial loops keep every result deterministic.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# index-map ids are int32 "visible-surfel" indices into the per-frame culled arrays; -1 = empty texel


@njit(cache=True, nogil=True)
def transform_subset(ids, m, pos, nrm, rot, trans, fx, fy, cx, cy, width, height, max_depth,
                     out_keep, out_pc, out_nc, out_px):
    """Like :func:`cull` for the listed surfel ids only (after a merge moved them); returns the count
    kept and writes the kept ids to ``out_keep``."""
    v = 0
    for k in range(m):
        i = ids[k]
        x = np.float64(pos[i, 0])
        y = np.float64(pos[i, 1])
        z = np.float64(pos[i, 2])
        zc = rot[2, 0] * x + rot[2, 1] * y + rot[2, 2] * z + trans[2]
        if zc <= 1e-6 or zc > max_depth:
            continue
        xc = rot[0, 0] * x + rot[0, 1] * y + rot[0, 2] * z + trans[0]
        yc = rot[1, 0] * x + rot[1, 1] * y + rot[1, 2] * z + trans[1]
        u = fx * xc / zc + cx
        w = fy * yc / zc + cy
        if u < -0.5 or u >= width - 0.5 or w < -0.5 or w >= height - 0.5:
            continue
        nx = np.float64(nrm[i, 0])
        ny = np.float64(nrm[i, 1])
        nz = np.float64(nrm[i, 2])
        out_keep[v] = i
        out_pc[v, 0] = xc
        out_pc[v, 1] = yc
        out_pc[v, 2] = zc
        out_nc[v, 0] = rot[0, 0] * nx + rot[0, 1] * ny + rot[0, 2] * nz
        out_nc[v, 1] = rot[1, 0] * nx + rot[1, 1] * ny + rot[1, 2] * nz
        out_nc[v, 2] = rot[2, 0] * nx + rot[2, 1] * ny + rot[2, 2] * nz
        out_px[v, 0] = u
        out_px[v, 1] = w
        v += 1
    return v


@njit(cache=True, inline="always")
def _texel(x, y, scale, ws, hs):  # pragma: no cover
    """The (row, col) texel of continuous pixel coordinates ``(x, y)`` in a map ``scale`` times finer than the
    image (``floor((u + 0.5) * scale)``), clamped to the ``hs`` x ``ws`` map."""
    col = int(math.floor((x + 0.5) * scale))
    row = int(math.floor((y + 0.5) * scale))
    if col < 0:
        col = 0
    elif col >= ws:
        col = ws - 1
    if row < 0:
        row = 0
    elif row >= hs:
        row = hs - 1
    return row, col


@njit(cache=True, nogil=True)
def build_index(px, pc, v, scale, ws, hs, zbuf, idxmap, tex):
    """Point-render visible surfels ``0..v-1`` into an index map ``scale`` times finer than the image.

    Texel of continuous pixel coordinate ``u`` is ``floor((u + 0.5) * scale)`` (so pixel ``u`` owns texels
    ``scale*u .. scale*u + scale - 1``). Per texel the nearest surfel (smallest camera z) wins; ties keep
    the lower id. ``tex[j]`` receives surfel j's texel so that :func:`clear_index` can reset only those.
    """
    for j in range(v):
        row, col = _texel(px[j, 0], px[j, 1], scale, ws, hs)
        t = row * ws + col
        tex[j] = t
        z = pc[j, 2]
        if z < zbuf[t]:
            zbuf[t] = z
            idxmap[t] = j


@njit(cache=True, nogil=True)
def clear_index(tex, v, zbuf, idxmap):
    """Reset the texels written by :func:`build_index` (O(visible), not O(texels))."""
    for j in range(v):
        t = tex[j]
        zbuf[t] = np.inf
        idxmap[t] = -1


@njit(cache=True, nogil=True)
def bin_pixels(px, v, scale, width, height, head, nxt, tex):
    """The association's index map (``scale`` times finer than the image) as per-pixel lists.

    Texel of continuous pixel coordinate ``u`` is ``floor((u + 0.5) * scale)`` (so pixel ``u`` owns texels
    ``scale*u .. scale*u + scale - 1``), clamped to the map. ``tex[j]`` receives surfel j's texel; ``head``
    (one entry per image pixel, all -1 on entry) and ``nxt`` chain the surfels of each pixel. The texel's
    entry in a dense z-buffer would be the nearest surfel of that texel (smallest camera z, ties: lower id):
    :func:`candidates` finds it in the pixel's list.
    """
    ws = width * scale
    hs = height * scale
    for j in range(v):
        row, col = _texel(px[j, 0], px[j, 1], scale, ws, hs)
        tex[j] = row * ws + col
        p = (row // scale) * width + col // scale
        nxt[j] = head[p]
        head[p] = j


@njit(cache=True, nogil=True)
def mark_winners(tex, pc, v, scale, width, head, nxt, winner):
    """``winner[j]``: surfel j is its texel's entry in the index map (no surfel of its pixel's list in the same
    texel is nearer, or as near with a lower id: the dense z-buffer's rule, see :func:`bin_pixels`). Returns
    the length of the longest pixel list."""
    ws = width * scale
    longest = 0
    for j in range(v):
        t = tex[j]
        row = t // ws
        qz = pc[j, 2]
        i = head[(row // scale) * width + (t - row * ws) // scale]
        win = True
        length = 0
        while i >= 0:
            if i != j and tex[i] == t and (pc[i, 2] < qz or (pc[i, 2] == qz and i < j)):
                win = False
            i = nxt[i]
            length += 1
        winner[j] = win
        longest = max(longest, length)
    return longest


@njit(cache=True, nogil=True)
def candidates(pc, nc, tex, winner, head, nxt, width, height, scale, win, lo0, su, sv, m, sray, svert, snorm,
               depth_gate, cos_normal_gate, grazing_nz, found_j, found_d, cand_j, cand_d, ncand):
    """Association candidates (Keller et al. 2013 Sec. 4.2; ElasticFusion ``data.vert``).

    Sample ``k`` (pixel ``(su[k], sv[k])``; ray ``sray[k] = (x/z, y/z, |ray|^2)``, camera-frame vertex
    ``svert`` and unit normal ``snorm``) looks at the index-map texels of a window ``win`` texels square,
    ``win = (stride + 1) * scale``, starting at texel ``scale * u + lo0`` on each axis: with stride 2 the 3x3
    pixels ElasticFusion's shader reaches (+-1 pixel sampled at half-pixel steps), with stride 1 2x2
    pixels. Windows of neighbouring samples overlap by one pixel, so a surfel whose projection jitters
    across a cell boundary is still found. The texels' surfels are found in the per-pixel lists of the
    pixels the window covers (``head``/``nxt``, :func:`bin_pixels`), and only texel winners count
    (``winner``, :func:`mark_winners`): the samples run in image order, so the lists they read stay in cache.

    A candidate must lie within ``depth_gate`` of the sample along the ray and, unless seen at a grazing
    angle (``|n_z| < grazing_nz``), have a normal within the gate (``cos > cos_normal_gate``). Each sample
    keeps its ``cand_j.shape[1]`` candidates nearest its ray (``cand_d``: squared distance to the ray),
    taken in ascending surfel order (a later one replaces the farthest kept one only when strictly nearer).
    ``found_j``/``found_d`` hold one sample's candidates before that choice: room for all surfels of the
    window's pixels (``(stride + 2)^2`` times the longest pixel list, :func:`mark_winners`).
    """
    ws = width * scale
    cap = cand_j.shape[1]
    gate2 = depth_gate * depth_gate
    for k in range(m):
        c0 = scale * su[k] + lo0
        r0 = scale * sv[k] + lo0
        c1 = c0 + win
        r1 = r0 + win
        pc0 = max(c0, 0) // scale
        pc1 = min(c1 - 1, ws - 1) // scale
        pr0 = max(r0, 0) // scale
        pr1 = min(r1 - 1, height * scale - 1) // scale
        rx = sray[k, 0]
        ry = sray[k, 1]
        lam2 = sray[k, 2]
        sz = svert[k, 2]
        snx = snorm[k, 0]
        sny = snorm[k, 1]
        snz = snorm[k, 2]
        n = 0
        for prow in range(pr0, pr1 + 1):
            for pcol in range(pc0, pc1 + 1):
                j = head[prow * width + pcol]
                while j >= 0:
                    nj = nxt[j]
                    if winner[j]:
                        t = tex[j]
                        row = t // ws
                        col = t - row * ws
                        if row >= r0 and row < r1 and col >= c0 and col < c1:
                            qx = pc[j, 0]
                            qy = pc[j, 1]
                            qz = pc[j, 2]
                            dzk = qz - sz
                            mnz = nc[j, 2]
                            if dzk * dzk * lam2 < gate2 and (
                                    abs(mnz) < grazing_nz
                                    or nc[j, 0] * snx + nc[j, 1] * sny + mnz * snz > cos_normal_gate):
                                ax = ry * qz - qy
                                ay = qx - rx * qz
                                az = rx * qy - ry * qx
                                found_j[n] = j
                                found_d[n] = (ax * ax + ay * ay + az * az) / lam2
                                n += 1
                    j = nj
        for a in range(1, n):  # ascending surfel order, as a scatter over the surfels would offer them
            jj = found_j[a]
            dd = found_d[a]
            b = a - 1
            while b >= 0 and found_j[b] > jj:
                found_j[b + 1] = found_j[b]
                found_d[b + 1] = found_d[b]
                b -= 1
            found_j[b + 1] = jj
            found_d[b + 1] = dd
        kept = 0
        for a in range(n):
            d = found_d[a]
            if kept < cap:
                cand_j[k, kept] = found_j[a]
                cand_d[k, kept] = d
                kept += 1
            else:  # keep the nearest: replace the farthest if this one is nearer
                worst = 0
                for q in range(1, cap):
                    if cand_d[k, q] > cand_d[k, worst]:
                        worst = q
                if d < cand_d[k, worst]:
                    cand_j[k, worst] = found_j[a]
                    cand_d[k, worst] = d
        ncand[k] = kept


@njit(cache=True, nogil=True)
def match(cand_j, cand_d, ncand, m, conf, vis_idx, v, taken):
    """Which sample refines which surfel: ``taken[j]`` = sample merged into visible surfel j, or -1.

    1. ElasticFusion's rule: each sample picks its candidate nearest its ray (ties: higher confidence); among
       samples picking the same surfel the one whose ray passes closest wins (ties: lower sample index;
       ElasticFusion leaves this to a GPU write race).
    2. Every surfel still unrefined that is a candidate of some sample takes its nearest such sample (a
       sample may then refine a second surfel). Without this step a camera at rest, whose sample lattice
       falls exactly between the surfels, leaves about one surfel in five unrefined in every frame.

    So each surfel in view is refined at most once per frame and none with a sample in range is skipped.
    """
    best_d = np.full(max(v, 1), np.inf)
    for k in range(m):  # 1: nearest candidate per sample, closest ray per surfel
        bj = -1
        bd = np.inf
        for q in range(ncand[k]):
            j = cand_j[k, q]
            d = cand_d[k, q]
            if d < bd or (d == bd and conf[vis_idx[j]] > conf[vis_idx[bj]]):  # confidences only on a tie
                bj = j
                bd = d
        if bj >= 0 and bd < best_d[bj]:
            best_d[bj] = bd
            taken[bj] = k
    near_k = np.full(max(v, 1), -1, np.int64)
    near_d = np.full(max(v, 1), np.inf)
    for k in range(m):  # 2: nearest sample per unrefined surfel
        for q in range(ncand[k]):
            j = cand_j[k, q]
            if taken[j] >= 0:
                continue
            d = cand_d[k, q]
            if d < near_d[j]:
                near_d[j] = d
                near_k[j] = k
    for j in range(v):
        if taken[j] < 0 and near_k[j] >= 0:
            taken[j] = near_k[j]


@njit(cache=True, nogil=True)
def merge(taken, v, vis_idx, svert, snorm, rot, trans, prad, palpha, pcol, pos, nrm, rad, conf, col, t_upd, tick,
          radius_ratio, block_lo, block_hi, shift, pair_map, pair_sample):
    """Confidence-weighted averaging (ElasticFusion ``update.vert``); returns the number of colour pairs.

    For each visible surfel ``j`` refined by sample ``k = taken[j]`` (map row ``s = vis_idx[j]``; the sample's
    camera-frame vertex ``svert[k]`` and normal ``snorm[k]`` go to the world frame with ``rot``/``trans``):
    when the sample's radius is below ``radius_ratio`` times the surfel's, position, normal (renormalised),
    radius and colour become ``(c * old + a * new) / (c + a)`` (computed as ``c / (c + a) * old + a / (c + a)
    * new``: one division) and the pair (surfel colour before, sample colour) is recorded; otherwise only
    the confidence and the time are updated (the sample is too coarse to refine a surfel seen from closer
    before). In both cases ``conf += a`` and ``t_upd = tick``. A moved surfel widens its block's bounding
    box (rows ``1 << shift`` per block).
    """
    npairs = 0
    pw = np.empty(3)
    nw = np.empty(3)
    for j in range(v):
        k = taken[j]
        if k < 0:
            continue
        s = vis_idx[j]
        c = np.float64(conf[s])
        a = np.float64(palpha[k])
        if prad[k] < radius_ratio * rad[s]:
            for ch in range(3):
                pair_map[npairs, ch] = col[s, ch]
                pair_sample[npairs, ch] = pcol[k, ch]
            npairs += 1
            _to_world(svert, snorm, k, rot, trans, pw, nw)
            inv = 1.0 / (c + a)  # one division: the weights are shared by every field
            wc = c * inv
            wa = a * inv
            blk = s >> shift
            for ch in range(3):
                pos[s, ch] = wc * pos[s, ch] + wa * pw[ch]
                col[s, ch] = wc * col[s, ch] + wa * pcol[k, ch]
                block_lo[blk, ch] = min(block_lo[blk, ch], pos[s, ch])
                block_hi[blk, ch] = max(block_hi[blk, ch], pos[s, ch])
            nx = wc * nrm[s, 0] + wa * nw[0]
            ny = wc * nrm[s, 1] + wa * nw[1]
            nz = wc * nrm[s, 2] + wa * nw[2]
            nn = math.sqrt(nx * nx + ny * ny + nz * nz)
            if nn > 1e-12:
                inv_n = 1.0 / nn
                nrm[s, 0] = nx * inv_n
                nrm[s, 1] = ny * inv_n
                nrm[s, 2] = nz * inv_n
            rad[s] = wc * rad[s] + wa * prad[k]
        conf[s] = c + a
        t_upd[s] = tick
    return npairs


@njit(cache=True, nogil=True)
def append_new(ncand, m, svert, snorm, rot, trans, prad, palpha, pcol, first, tick, pos, nrm, rad, conf, col,
               t_created, t_upd):
    """New surfels from the samples without any candidate (``ncand[k] == 0``), written from map row ``first``
    on (room made by the caller): world position and normal, radius, ``conf = alpha``, colour, ``created =
    updated = tick``. Returns how many."""
    pw = np.empty(3)
    nw = np.empty(3)
    r = first
    for k in range(m):
        if ncand[k] != 0:
            continue
        _to_world(svert, snorm, k, rot, trans, pw, nw)
        for ch in range(3):
            pos[r, ch] = pw[ch]
            nrm[r, ch] = nw[ch]
            col[r, ch] = pcol[k, ch]
        rad[r] = prad[k]
        conf[r] = palpha[k]
        t_created[r] = tick
        t_upd[r] = tick
        r += 1
    return r - first


@njit(cache=True, nogil=True, inline="always")
def _to_world(svert, snorm, k, rot, trans, pw, nw):
    """Sample k's vertex and normal in the world frame (``rot @ x + trans``, ``rot @ n``), float64."""
    x = svert[k, 0]
    y = svert[k, 1]
    z = svert[k, 2]
    a = snorm[k, 0]
    b = snorm[k, 1]
    c = snorm[k, 2]
    for i in range(3):
        pw[i] = rot[i, 0] * x + rot[i, 1] * y + rot[i, 2] * z + trans[i]
        nw[i] = rot[i, 0] * a + rot[i, 1] * b + rot[i, 2] * c + 0.0


@njit(cache=True, nogil=True)
def occupants(keep, pc, px, n_old, conf, created, updated, c_stable, occ_ids, occ_pc, occ_px, occ_created,
              occ_updated):
    """The clean-up's occupants: of the first ``n_old`` transformed surfels (``keep``/``pc``/``px``), those
    with confidence above ``c_stable``, gathered with their creation and update times; returns how many."""
    n = 0
    for k in range(n_old):
        i = keep[k]
        if conf[i] > c_stable:
            occ_ids[n] = i
            for a in range(3):
                occ_pc[n, a] = pc[k, a]
            occ_px[n, 0] = px[k, 0]
            occ_px[n, 1] = px[k, 1]
            occ_created[n] = created[i]
            occ_updated[n] = updated[i]
            n += 1
    return n


@njit(cache=True, nogil=True)
def clean(test_ids, test_pc, test_nc, test_px, nt, rad, t_created, idxmap, occ_ids, occ_pc, occ_created, occ_updated,
          ws, hs, window_px, tick, dup_gap, lateral_factor, dup_min, fs_gap, facing_nz, fs_min, remove):
    """ElasticFusion's clean-up of the surfels in view (``copy_unstable.vert``).

    ``idxmap`` is an image-resolution index map of the *stable* surfels in view after fusion ("occupants",
    compact arrays ``occ_*``: id, camera-frame position, creation and update time). For test surfel ``i``
    (camera-frame ``test_pc``/``test_nc``, pixel ``test_px``) the window is ``2 * window_px`` pixels square
    around its projection; among the occupants in it, count

    - duplicates: created before ``i``, lying behind ``i`` by less than ``dup_gap`` and within
      ``lateral_factor * radius_i`` laterally: ``i`` is a redundant newer layer;
    - free-space evidence: updated in this frame and lying behind ``i`` by more than ``fs_gap`` while ``i``
      faces the camera (``|n_z| > facing_nz``): the sensor just saw through ``i``.

    ``remove[k]`` is set when duplicates >= ``dup_min`` or free-space evidence >= ``fs_min``.
    """
    n_side = 2 * window_px
    for k in range(nt):
        i = test_ids[k]
        zi = test_pc[k, 2]
        xi = test_pc[k, 0]
        yi = test_pc[k, 1]
        ri = rad[i] * lateral_factor
        ri2 = ri * ri
        ci = t_created[i]
        facing = abs(test_nc[k, 2]) > facing_nz
        c0 = int(math.floor(test_px[k, 0] + 0.5)) - window_px
        r0 = int(math.floor(test_px[k, 1] + 0.5)) - window_px
        c1 = min(c0 + n_side, ws)
        r1 = min(r0 + n_side, hs)
        if c0 < 0:
            c0 = 0
        if r0 < 0:
            r0 = 0
        dup = 0
        fs = 0
        for row in range(r0, r1):
            base = row * ws
            for col in range(c0, c1):
                j = idxmap[base + col]
                if j < 0:
                    continue
                dz = occ_pc[j, 2] - zi
                if dz <= 0.0 or occ_ids[j] == i:
                    continue
                if dz < dup_gap:
                    if occ_created[j] < ci:
                        dx = occ_pc[j, 0] - xi
                        dy = occ_pc[j, 1] - yi
                        if dx * dx + dy * dy < ri2:
                            dup += 1
                if facing and dz > fs_gap and occ_updated[j] == tick:
                    fs += 1
        remove[k] = dup >= dup_min or fs >= fs_min


@njit(cache=True, nogil=True)
def splat(vis_idx, pc, nc, v, rad, conf, col, fx, fy, cx, cy, width, height, c_stable, fill_unstable, max_half,
          depth, colour, vertex, normal):
    """Render surfel discs with a per-pixel z-buffer (ElasticFusion ``splat.vert`` + ``combo_splat.frag``).

    Each surfel is a disc (centre, normal, radius). For every pixel of its projected bounding box the pixel
    ray is intersected with the disc plane and kept when the hit lies within the radius; the nearest hit
    wins. Stable surfels (``conf >= c_stable``) always win over unstable ones; unstable ones only fill
    pixels no stable surfel covers, and only when ``fill_unstable``. Outputs are written in place
    (``depth`` zero where empty); returns the number of pixels covered.
    """
    key = np.full((height, width), np.inf, dtype=np.float64)
    owner = np.full((height, width), -1, dtype=np.int32)
    big = 1e6
    for j in range(v):
        s = vis_idx[j]
        c = conf[s]
        unstable = c < c_stable
        if unstable and not fill_unstable:
            continue
        px = pc[j, 0]
        py = pc[j, 1]
        pz = pc[j, 2]
        nx = nc[j, 0]
        ny = nc[j, 1]
        nz = nc[j, 2]
        r = rad[s]
        r2 = r * r * 1.0002  # closed disc: pixels exactly on the rim (lattice diagonals) count
        # image bounding box of the disc's 3D bounding box (exact extents r * sqrt(1 - n_axis^2))
        ex = r * math.sqrt(max(0.0, 1.0 - nx * nx))
        ey = r * math.sqrt(max(0.0, 1.0 - ny * ny))
        ez = r * math.sqrt(max(0.0, 1.0 - nz * nz))
        z0 = pz - ez
        if z0 < 1e-3:
            z0 = 1e-3
        z1 = pz + ez
        xa = px - ex
        xb = px + ex
        ya = py - ey
        yb = py + ey
        ulo = fx * min(xa / z0, xa / z1) + cx
        uhi = fx * max(xb / z0, xb / z1) + cx
        vlo = fy * min(ya / z0, ya / z1) + cy
        vhi = fy * max(yb / z0, yb / z1) + cy
        uc = fx * px / pz + cx
        vc = fy * py / pz + cy
        ulo = max(ulo, uc - max_half)
        uhi = min(uhi, uc + max_half)
        vlo = max(vlo, vc - max_half)
        vhi = min(vhi, vc + max_half)
        u0 = max(int(math.ceil(ulo)), 0)
        u1 = min(int(math.floor(uhi)), width - 1)
        v0 = max(int(math.ceil(vlo)), 0)
        v1 = min(int(math.floor(vhi)), height - 1)
        nd_p = nx * px + ny * py + nz * pz
        for row in range(v0, v1 + 1):
            ry = (row - cy) / fy
            for cl in range(u0, u1 + 1):
                rx = (cl - cx) / fx
                den = nx * rx + ny * ry + nz
                if abs(den) < 1e-6:
                    continue
                # hit q = t * ray with t = nd_p / den; test |q - p|^2 <= r^2 multiplied by den^2 (no division)
                dx = nd_p * rx - den * px
                dy = nd_p * ry - den * py
                dz = nd_p - den * pz
                if dx * dx + dy * dy + dz * dz > r2 * den * den:
                    continue
                t = nd_p / den
                if t <= 1e-3:
                    continue
                kk = t + big if unstable else t
                if kk < key[row, cl]:
                    key[row, cl] = kk
                    owner[row, cl] = j
    covered = 0
    for row in range(height):
        ry = (row - cy) / fy
        for cl in range(width):
            j = owner[row, cl]
            if j < 0:
                continue
            t = key[row, cl]
            if t >= big:
                t -= big
            rx = (cl - cx) / fx
            s = vis_idx[j]
            depth[row, cl] = t
            vertex[row, cl, 0] = t * rx
            vertex[row, cl, 1] = t * ry
            vertex[row, cl, 2] = t
            nx = nc[j, 0]
            ny = nc[j, 1]
            nz = nc[j, 2]
            if nx * rx + ny * ry + nz > 0.0:  # face the camera
                nx = -nx
                ny = -ny
                nz = -nz
            normal[row, cl, 0] = nx
            normal[row, cl, 1] = ny
            normal[row, cl, 2] = nz
            for ch in range(3):
                colour[row, cl, ch] = col[s, ch]
            covered += 1
    return covered


@njit(cache=True, nogil=True)
def frame_samples(depth, filt, colour, fx, fy, cx, cy, offset, stride, max_depth, max_jump, two_sigma2, baseline,
                  out_u, out_v, out_ray, out_vert, out_nrm, out_rad, out_alpha, out_col):
    """Sample pixels of one lattice (rows and columns ``offset + k * stride``, borders excluded).

    A sample needs a raw depth in ``(0, max_depth]``, its four neighbours valid and within
    ``max_jump * depth`` of it, a finite colour and a filtered depth at itself and its neighbours. Writes the
    pixel, the raw-depth vertex, the normal (cross product of central differences of the filtered vertex
    map, facing the camera), the radius ``sqrt(2) z / f / |n_z|`` clamped to twice ``sqrt(2) z / f``
    (filtered z, mean focal), the ray ``(x/z, y/z, 1 + (x/z)^2 + (y/z)^2)``, the confidence
    ``exp(-rho^2 / two_sigma2)`` (rho = distance to the principal
    point over the half diagonal) and the colour. Returns the number of samples. One pass; the NumPy
    equivalent (:func:`mapping.fusion.surfel.vertex_normal_maps` for the normals) builds ~60 temporaries.
    """
    h, w = depth.shape
    fmean = 0.5 * (fx + fy)
    sqrt2 = math.sqrt(2.0)
    inv_half_diag2 = 1.0 / (0.25 * (w * w + h * h))
    b = baseline
    r_start = offset
    while r_start < b:
        r_start += stride
    m = 0
    for v in range(r_start, h - b, stride):
        ys = (v - cy) / fy
        for u in range(r_start, w - b, stride):
            d = np.float64(depth[v, u])
            if not (d > 0.0 and d <= max_depth):
                continue
            jump = max_jump * d
            dl = depth[v, u - 1]
            dr = depth[v, u + 1]
            du = depth[v - 1, u]
            dd = depth[v + 1, u]
            if not (dl > 0.0 and dr > 0.0 and du > 0.0 and dd > 0.0):
                continue
            if abs(dl - d) > jump or abs(dr - d) > jump or abs(du - d) > jump or abs(dd - d) > jump:
                continue
            c0 = colour[v, u, 0]
            c1 = colour[v, u, 1]
            c2 = colour[v, u, 2]
            if not (math.isfinite(c0) and math.isfinite(c1) and math.isfinite(c2)):
                continue
            zc = np.float64(filt[v, u])
            zl = np.float64(filt[v, u - b])
            zr = np.float64(filt[v, u + b])
            zu = np.float64(filt[v - b, u])
            zd = np.float64(filt[v + b, u])
            if not (zc > 0.0 and zl > 0.0 and zr > 0.0 and zu > 0.0 and zd > 0.0):
                continue
            if b > 1:
                if abs(zl - zc) > jump or abs(zr - zc) > jump or abs(zu - zc) > jump or abs(zd - zc) > jump:
                    continue
            xs = (u - cx) / fx
            # central differences of the back-projected (filtered) vertex map, +-b pixels
            ax = ((u + b - cx) * zr - (u - b - cx) * zl) / fx
            ay = ys * (zr - zl)
            az = zr - zl
            bx = xs * (zd - zu)
            by = ((v + b - cy) * zd - (v - b - cy) * zu) / fy
            bz = zd - zu
            nx = ay * bz - az * by
            ny = az * bx - ax * bz
            nz = ax * by - ay * bx
            nn = math.sqrt(nx * nx + ny * ny + nz * nz)
            if not nn > 0.0:
                continue
            nx /= nn
            ny /= nn
            nz /= nn
            px = xs * d
            py = ys * d
            if nx * px + ny * py + nz * d > 0.0:
                nx = -nx
                ny = -ny
                nz = -nz
            base = sqrt2 * zc / fmean
            anz = abs(nz)
            r = base / anz if anz > 0.5 else 2.0 * base
            rho2 = ((u - cx) * (u - cx) + (v - cy) * (v - cy)) * inv_half_diag2
            out_u[m] = u
            out_v[m] = v
            out_ray[m, 0] = xs
            out_ray[m, 1] = ys
            out_ray[m, 2] = 1.0 + xs * xs + ys * ys
            out_vert[m, 0] = px
            out_vert[m, 1] = py
            out_vert[m, 2] = d
            out_nrm[m, 0] = nx
            out_nrm[m, 1] = ny
            out_nrm[m, 2] = nz
            out_rad[m] = r
            out_alpha[m] = math.exp(-rho2 / two_sigma2)
            out_col[m, 0] = c0
            out_col[m, 1] = c1
            out_col[m, 2] = c2
            m += 1
    return m
