/* The per-pixel kernels of the TSDF backend, the display look-ups and the depth pyramid, compiled at install.
 *
 * Each function is the C twin of a Numba kernel (mapping/fusion/_tsdf_kernels.py, mapping/_colour_kernels.py,
 * mapping/tracking.py's pyrdown), with the same arguments and the same arithmetic: every operation in the type
 * Numba infers for it (float32 where both operands are float32; float64 where Numba promotes, e.g. float32 times
 * uint16, an integer plus a float32, or a variable assigned values of both widths), so both give the same bits
 * (tests/test_native_kernels.py compares them). Why C: Numba's runtime costs ~111 MB of memory in every process
 * that calls a kernel (LLVM loaded for the on-disk cache too), more than radiomap's memory budget against
 * Open3D's own loop (issue 17). Built without FMA contraction (-ffp-contract=off) so float32 products round as
 * in Numba. The parallel kernels use OpenMP when the compiler has it; each output is written by one thread in a
 * fixed order, so the results do not depend on the number of threads.
 */
#include "../radiometry/_buffers.h"
#include <math.h>

typedef float f32;
typedef double f64;

static inline int64_t pymod(int64_t a, int64_t b) /* Python's a % b for b > 0 */
{
    int64_t r = a % b;
    return r < 0 ? r + b : r;
}

static inline int in_range(f32 q) /* a block coordinate that fits (|q| < 2^30; False for NaN, inf) */
{
    return fabsf(q) < 1073741824.0f;
}

/* ---------------------------------------------------------------------------------------------- colour_pairs */
static PyObject *colour_pairs(PyObject *self, PyObject *args)
{
    PyObject *o[6];
    double abs_tol_d, rel_tol_d, dmin_d, dmax_d;
    Py_buffer v[6] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOOddddOO", &o[0], &o[1], &o[2], &o[3], &abs_tol_d, &rel_tol_d, &dmin_d,
                          &dmax_d, &o[4], &o[5]))
        return NULL;
    const char *names[6] = {"map_depth", "depth", "map_colour", "colour", "out_map", "out_sample"};
    const int ndims[6] = {2, 2, 3, 3, 2, 2};
    for (int i = 0; i < 6; i++)
        if (rm_get(o[i], &v[i], 'f', 4, ndims[i], i >= 4, names[i]) < 0)
            goto fail;
    Py_ssize_t rows = v[1].shape[0], cols = v[1].shape[1], n_pix = rows * cols;
    if (rm_dim(&v[0], 0, rows, "map_depth") || rm_dim(&v[0], 1, cols, "map_depth")
        || rm_dim(&v[2], 0, rows, "map_colour") || rm_dim(&v[2], 1, cols, "map_colour")
        || rm_dim(&v[2], 2, 3, "map_colour") || rm_dim(&v[3], 0, rows, "colour") || rm_dim(&v[3], 1, cols, "colour")
        || rm_dim(&v[3], 2, 3, "colour") || rm_dim(&v[4], 1, 3, "out_map") || rm_dim(&v[5], 1, 3, "out_sample"))
        goto fail;
    if (v[4].shape[0] < n_pix || v[5].shape[0] < n_pix) {
        PyErr_SetString(PyExc_ValueError, "out_map, out_sample: need a row per pixel");
        goto fail;
    }
    const f32 *map_depth = v[0].buf, *depth = v[1].buf, *map_colour = v[2].buf, *colour = v[3].buf;
    f32 *out_map = v[4].buf, *out_sample = v[5].buf;
    const f32 abs_tol = (f32)abs_tol_d, rel_tol = (f32)rel_tol_d, dmin = (f32)dmin_d, dmax = (f32)dmax_d;
    Py_ssize_t n = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < n_pix; p++) {
        f32 m = map_depth[p], d = depth[p];
        if (m > 0 && d > dmin && d <= dmax) {
            f32 tol = rel_tol * d;
            if (tol < abs_tol)
                tol = abs_tol;
            if (fabsf(m - d) <= tol) {
                for (int c = 0; c < 3; c++) {
                    out_map[3 * n + c] = map_colour[3 * p + c];
                    out_sample[3 * n + c] = colour[3 * p + c];
                }
                n++;
            }
        }
    }
    Py_END_ALLOW_THREADS
    rm_release(v, 6);
    return PyLong_FromSsize_t(n);
fail:
    rm_release(v, 6);
    return NULL;
}

/* ----------------------------------------------------------------------------------------------- finish_view */
static PyObject *finish_view(PyObject *self, PyObject *args)
{
    PyObject *ov, *on, *od, *oc;
    double half_d;
    int debias;
    Py_buffer v[4] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOOdp", &ov, &on, &od, &oc, &half_d, &debias))
        return NULL;
    if (rm_get(ov, &v[0], 'f', 4, 3, 1, "vertex") || rm_get(on, &v[1], 'f', 4, 3, 1, "normal")
        || rm_get(od, &v[2], 'f', 4, 2, 1, "depth") || rm_get(oc, &v[3], 'f', 4, 1, 0, "c"))
        goto fail;
    Py_ssize_t rows = v[2].shape[0], cols = v[2].shape[1];
    for (int i = 0; i < 2; i++)
        if (rm_dim(&v[i], 0, rows, i ? "normal" : "vertex") || rm_dim(&v[i], 1, cols, i ? "normal" : "vertex")
            || rm_dim(&v[i], 2, 3, i ? "normal" : "vertex"))
            goto fail;
    if (rm_dim(&v[3], 0, 3, "c"))
        goto fail;
    f32 *vertex = v[0].buf, *normal = v[1].buf, *depth = v[2].buf;
    const f32 *c = v[3].buf;
    const f32 half_voxel = (f32)half_d;
    const f64 limit = 2.0 * (f64)half_voxel;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t p = 0; p < rows * cols; p++) {
        f32 z = depth[p];
        f32 *vx = vertex + 3 * p, *nx = normal + 3 * p;
        if (!(z > 0)) {
            vx[0] = vx[1] = vx[2] = 0.0f;
            nx[0] = nx[1] = nx[2] = 0.0f;
            continue;
        }
        f32 n0 = nx[0], n1 = nx[1], n2 = nx[2];
        if (!(n0 == n0 && n1 == n1 && n2 == n2)) {
            nx[0] = nx[1] = nx[2] = 0.0f;
            continue;
        }
        f32 nv = n0 * vx[0] + n1 * vx[1] + n2 * vx[2];
        if (nv > 0) {
            nx[0] = -n0;
            nx[1] = -n1;
            nx[2] = -n2;
        }
        if (!debias || fabs((f64)nv) < 1e-6)
            continue;
        f64 lam = (f64)(half_voxel * (n0 * c[0] + n1 * c[1] + n2 * c[2]) * z / nv); /* float32, then float64 */
        if (lam > limit)
            lam = limit;
        else if (lam < -limit)
            lam = -limit;
        f64 s = 1.0 - lam / (f64)z;
        vx[0] = (f32)((f64)vx[0] * s);
        vx[1] = (f32)((f64)vx[1] * s);
        vx[2] = (f32)((f64)vx[2] * s);
        depth[p] = (f32)((f64)z * s);
    }
    Py_END_ALLOW_THREADS
    rm_release(v, 4);
    Py_INCREF(od);
    return od;
fail:
    rm_release(v, 4);
    return NULL;
}

/* ---------------------------------------------------------------------------------- dense block table look-ups */
typedef struct {
    const int32_t *index; /* (X, Y, Z) buffer slots, -1 = absent */
    int64_t nx, ny, nz;
    int64_t lo[3];
} BlockTable;

static int block_table(Py_buffer *index, Py_buffer *lo, BlockTable *t)
{
    if (rm_dim(lo, 0, 3, "lo"))
        return -1;
    t->index = index->buf;
    t->nx = index->shape[0];
    t->ny = index->shape[1];
    t->nz = index->shape[2];
    memcpy(t->lo, lo->buf, sizeof t->lo);
    return 0;
}

static inline int64_t block_slot(const BlockTable *t, int64_t bx, int64_t by, int64_t bz)
{
    int64_t jx = bx - t->lo[0], jy = by - t->lo[1], jz = bz - t->lo[2];
    if (jx < 0 || jy < 0 || jz < 0 || jx >= t->nx || jy >= t->ny || jz >= t->nz)
        return -1;
    return t->index[(jx * t->ny + jy) * t->nz + jz];
}

/* A grid attribute of either storage: float32 or uint16 (``u16``). */
typedef struct {
    const void *data;
    int u16;
    Py_ssize_t n;
} Attr;

static int attr(PyObject *obj, Py_buffer *view, const char *name, Attr *a)
{
    if (rm_get_of(obj, view, 'f', 4, 'u', 2, -1, 0, name) < 0)
        return -1;
    a->data = view->buf;
    a->u16 = view->itemsize == 2;
    a->n = rm_items(view);
    return 0;
}

/* ---------------------------------------------------------------------------------------------------- refine */
static inline int64_t voxel_index(int64_t vx, int64_t vy, int64_t vz, int shift, int64_t mask, int64_t res,
                                  const BlockTable *t)
{
    int64_t slot = block_slot(t, vx >> shift, vy >> shift, vz >> shift);
    if (slot < 0)
        return -1;
    return ((slot * res + (vz & mask)) * res + (vy & mask)) * res + (vx & mask);
}

static inline int weight_positive(const Attr *w, int64_t i)
{
    return w->u16 ? ((const uint16_t *)w->data)[i] > 0 : ((const f32 *)w->data)[i] > 0;
}

static inline int weight_nonpositive(const Attr *w, int64_t i)
{
    return w->u16 ? ((const uint16_t *)w->data)[i] <= 0 : ((const f32 *)w->data)[i] <= 0;
}

static f64 tsdf_at(f64 px, f64 py, f64 pz, f64 inv_vs, int shift, const f32 *tsdf, const Attr *weight,
                   Py_ssize_t n_voxels, const BlockTable *t)
{
    int64_t res = (int64_t)1 << shift, mask = res - 1;
    f64 gx = px * inv_vs, gy = py * inv_vs, gz = pz * inv_vs;
    if (!(fabs(gx) < 4e18 && fabs(gy) < 4e18 && fabs(gz) < 4e18)) /* inf or NaN: no voxel */
        return NAN;
    f64 fx0 = floor(gx), fy0 = floor(gy), fz0 = floor(gz);
    int64_t ix = (int64_t)fx0, iy = (int64_t)fy0, iz = (int64_t)fz0;
    f64 fx = gx - fx0, fy = gy - fy0, fz = gz - fz0;
    int64_t base = voxel_index(ix, iy, iz, shift, mask, res, t);
    if (base < 0)
        return NAN;
    int inside = (ix & mask) < mask && (iy & mask) < mask && (iz & mask) < mask;
    f64 acc = 0.0;
    for (int k = 0; k < 8; k++) {
        int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;
        int64_t li;
        if (inside)
            li = base + dx + dy * res + dz * res * res;
        else {
            li = voxel_index(ix + dx, iy + dy, iz + dz, shift, mask, res, t);
            if (li < 0)
                return NAN;
        }
        if (li >= n_voxels || weight_nonpositive(weight, li))
            return NAN;
        acc += (dx ? fx : 1.0 - fx) * (dy ? fy : 1.0 - fy) * (dz ? fz : 1.0 - fz) * (f64)tsdf[li];
    }
    return acc;
}

static PyObject *refine(PyObject *self, PyObject *args)
{
    PyObject *od, *ov, *oR, *oo, *ot, *ow, *oi, *ol;
    double fx, fy, cx, cy, vs;
    int shift;
    Py_buffer v[8] = {{0}};
    Attr weight;
    BlockTable table;
    if (!PyArg_ParseTuple(args, "OOddddOOOOOOid", &od, &ov, &fx, &fy, &cx, &cy, &oR, &oo, &ot, &ow, &oi, &ol,
                          &shift, &vs))
        return NULL;
    if (rm_get(od, &v[0], 'f', 4, 2, 1, "depth") || rm_get(ov, &v[1], 'f', 4, 3, 1, "vertex")
        || rm_get(oR, &v[2], 'f', 8, 2, 0, "R") || rm_get(oo, &v[3], 'f', 8, 1, 0, "o")
        || rm_get(ot, &v[4], 'f', 4, -1, 0, "tsdf") || attr(ow, &v[5], "weight", &weight)
        || rm_get(oi, &v[6], 'i', 4, 3, 0, "index") || rm_get(ol, &v[7], 'i', 8, 1, 0, "lo"))
        goto fail;
    Py_ssize_t rows = v[0].shape[0], cols = v[0].shape[1];
    if (rm_dim(&v[1], 0, rows, "vertex") || rm_dim(&v[1], 1, cols, "vertex") || rm_dim(&v[1], 2, 3, "vertex")
        || rm_dim(&v[2], 0, 3, "R") || rm_dim(&v[2], 1, 3, "R") || rm_dim(&v[3], 0, 3, "o")
        || block_table(&v[6], &v[7], &table))
        goto fail;
    if (shift < 0 || shift > 10) {
        PyErr_Format(PyExc_ValueError, "shift: must be in 0..10, got %d", shift);
        goto fail;
    }
    Py_ssize_t n_voxels = rm_items(&v[4]) < weight.n ? rm_items(&v[4]) : weight.n;
    f32 *depth = v[0].buf, *vertex = v[1].buf;
    const f64 *R = v[2].buf, *o = v[3].buf;
    const f32 *tsdf = v[4].buf;
    const f64 inv_vs = 1.0 / vs;
    Py_ssize_t n = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t y = 0; y < rows; y++) {
        f64 yc = ((f64)y - cy) / fy;
        for (Py_ssize_t x = 0; x < cols; x++) {
            f32 t0 = depth[y * cols + x];
            if (!(t0 > 0))
                continue;
            f64 xc = ((f64)x - cx) / fx;
            f64 wx = R[0] * xc + R[1] * yc + R[2];
            f64 wy = R[3] * xc + R[4] * yc + R[5];
            f64 wz = R[6] * xc + R[7] * yc + R[8];
            f64 a = (f64)t0 - vs, b = (f64)t0 + vs;
            f64 fa = tsdf_at(o[0] + a * wx, o[1] + a * wy, o[2] + a * wz, inv_vs, shift, tsdf, &weight, n_voxels,
                             &table);
            if (!(fa > 0))
                continue;
            f64 fb = tsdf_at(o[0] + b * wx, o[1] + b * wy, o[2] + b * wz, inv_vs, shift, tsdf, &weight, n_voxels,
                             &table);
            if (!(fb < 0))
                continue;
            f64 t = a - fa * (b - a) / (fb - fa);
            f64 ft = tsdf_at(o[0] + t * wx, o[1] + t * wy, o[2] + t * wz, inv_vs, shift, tsdf, &weight, n_voxels,
                             &table);
            if (ft == ft) {
                if (ft > 0) {
                    a = t;
                    fa = ft;
                } else {
                    b = t;
                    fb = ft;
                }
                t = a - fa * (b - a) / (fb - fa);
            }
            depth[y * cols + x] = (f32)t;
            f32 *vx = vertex + 3 * (y * cols + x);
            vx[0] = (f32)(t * xc);
            vx[1] = (f32)(t * yc);
            vx[2] = (f32)t;
            n++;
        }
    }
    Py_END_ALLOW_THREADS
    rm_release(v, 8);
    return PyLong_FromSsize_t(n);
fail:
    rm_release(v, 8);
    return NULL;
}

/* The pixels a block covers at 1/down resolution and its camera depth range (Open3D 0.20's pass 0 of its ray
 * cast): the block's 8 corners projected, clamped to the image; returns whether the footprint is not empty.
 * Shared by range_fragments and raycast_depth (same float operations, -ffp-contract=off: the same bits). */
static inline int block_footprint(const int32_t *block, Py_ssize_t res, f32 voxel_size, const f32 *R, const f32 *t,
                                  f32 fx, f32 fy, f32 cx, f32 cy, f32 down, int64_t w_down, int64_t h_down,
                                  f32 depth_min, f32 depth_max, int64_t box[4], f32 z[2])
{
    int64_t u_min = w_down - 1, v_min = h_down - 1, u_max = 0, v_max = 0;
    f32 z_min = depth_max, z_max = depth_min;
    for (int i = 0; i < 8; i++) {
        f32 xw = (f32)(((int64_t)block[0] + (i & 1)) * res) * voxel_size;
        f32 yw = (f32)(((int64_t)block[1] + ((i >> 1) & 1)) * res) * voxel_size;
        f32 zw = (f32)(((int64_t)block[2] + ((i >> 2) & 1)) * res) * voxel_size;
        f32 zc = R[6] * xw + R[7] * yw + R[8] * zw + t[2];
        if (zc <= 0)
            continue;
        f32 xc = R[0] * xw + R[1] * yw + R[2] * zw + t[0];
        f32 yc = R[3] * xw + R[4] * yw + R[5] * zw + t[1];
        f32 inv_z = 1.0f / zc;
        f32 u = (xc * fx * inv_z + cx) / down;
        f32 vv = (yc * fy * inv_z + cy) / down;
        /* min(max(floor, -1.0), w_down) in float64, then int */
        f64 fu_lo = fmin(fmax((f64)floorf(u), -1.0), (f64)w_down), fu_hi = fmin(fmax((f64)ceilf(u), -1.0), (f64)w_down);
        f64 fv_lo = fmin(fmax((f64)floorf(vv), -1.0), (f64)h_down), fv_hi = fmin(fmax((f64)ceilf(vv), -1.0), (f64)h_down);
        int64_t u_lo = (int64_t)fu_lo, u_hi = (int64_t)fu_hi, v_lo = (int64_t)fv_lo, v_hi = (int64_t)fv_hi;
        if (u_lo < u_min) u_min = u_lo;
        if (u_hi > u_max) u_max = u_hi;
        if (v_lo < v_min) v_min = v_lo;
        if (v_hi > v_max) v_max = v_hi;
        if (zc < z_min) z_min = zc;
        if (zc > z_max) z_max = zc;
    }
    box[0] = u_min < 0 ? 0 : u_min;
    box[1] = v_min < 0 ? 0 : v_min;
    box[2] = u_max > w_down - 1 ? w_down - 1 : u_max;
    box[3] = v_max > h_down - 1 ? h_down - 1 : v_max;
    z[0] = z_min;
    z[1] = z_max;
    return box[1] < box[3] && box[0] < box[2] && z_min < z_max;
}

/* ------------------------------------------------------------------------------------------- range_fragments */
static PyObject *range_fragments(PyObject *self, PyObject *args)
{
    PyObject *ob, *oR, *ot, *oout;
    double fx_d, fy_d, cx_d, cy_d, down_d, vs_d, dmin_d, dmax_d;
    Py_ssize_t res, h_down, w_down;
    Py_buffer v[4] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOdddddndnnddO", &ob, &oR, &ot, &fx_d, &fy_d, &cx_d, &cy_d, &down_d, &res, &vs_d,
                          &h_down, &w_down, &dmin_d, &dmax_d, &oout))
        return NULL;
    if (rm_get(ob, &v[0], 'i', 4, 2, 0, "blocks") || rm_get(oR, &v[1], 'f', 4, 2, 0, "R")
        || rm_get(ot, &v[2], 'f', 4, 1, 0, "t") || rm_get(oout, &v[3], 'i', 8, 1, 1, "out"))
        goto fail;
    Py_ssize_t nb = v[0].shape[0];
    if (rm_dim(&v[0], 1, 3, "blocks") || rm_dim(&v[1], 0, 3, "R") || rm_dim(&v[1], 1, 3, "R")
        || rm_dim(&v[2], 0, 3, "t") || rm_dim(&v[3], 0, nb, "out"))
        goto fail;
    const int32_t *blocks = v[0].buf;
    const f32 *R = v[1].buf, *t = v[2].buf;
    int64_t *out = v[3].buf;
    const f32 fx = (f32)fx_d, fy = (f32)fy_d, cx = (f32)cx_d, cy = (f32)cy_d, down = (f32)down_d;
    const f32 voxel_size = (f32)vs_d, depth_min = (f32)dmin_d, depth_max = (f32)dmax_d;
    int64_t total = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < nb; k++) {
        int64_t box[4];
        f32 z[2];
        int64_t n = 0;
        if (block_footprint(blocks + 3 * k, res, voxel_size, R, t, fx, fy, cx, cy, down, w_down, h_down, depth_min,
                            depth_max, box, z))
            n = ((box[3] - box[1] + 16) / 16) * ((box[2] - box[0] + 16) / 16);
        out[k] = n;
        total += n;
    }
    Py_END_ALLOW_THREADS
    rm_release(v, 4);
    return PyLong_FromLongLong(total);
fail:
    rm_release(v, 4);
    return NULL;
}

/* ------------------------------------------------------------------------------------------------ hit_bounds */
static PyObject *hit_bounds(PyObject *self, PyObject *args)
{
    PyObject *od, *oR, *oo, *olo, *ohi;
    double fx_d, fy_d, cx_d, cy_d, bs_d;
    Py_buffer v[5] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOdddddOO", &od, &oR, &oo, &fx_d, &fy_d, &cx_d, &cy_d, &bs_d, &olo, &ohi))
        return NULL;
    if (rm_get(od, &v[0], 'f', 4, 2, 0, "depth") || rm_get(oR, &v[1], 'f', 4, 2, 0, "Rc")
        || rm_get(oo, &v[2], 'f', 4, 1, 0, "o") || rm_get(olo, &v[3], 'i', 8, 1, 1, "lo")
        || rm_get(ohi, &v[4], 'i', 8, 1, 1, "hi"))
        goto fail;
    if (rm_dim(&v[1], 0, 3, "Rc") || rm_dim(&v[1], 1, 3, "Rc") || rm_dim(&v[2], 0, 3, "o")
        || rm_dim(&v[3], 0, 3, "lo") || rm_dim(&v[4], 0, 3, "hi"))
        goto fail;
    Py_ssize_t rows = v[0].shape[0], cols = v[0].shape[1];
    const f32 *depth = v[0].buf, *Rc = v[1].buf, *o = v[2].buf;
    int64_t *lo = v[3].buf, *hi = v[4].buf;
    const f32 fx = (f32)fx_d, fy = (f32)fy_d, cx = (f32)cx_d, cy = (f32)cy_d, block_size = (f32)bs_d;
    Py_BEGIN_ALLOW_THREADS
    for (int a = 0; a < 3; a++) {
        lo[a] = (int64_t)1 << 30;
        hi[a] = -((int64_t)1 << 30);
    }
    for (Py_ssize_t y = 0; y < rows; y++) {
        f32 dy = ((f32)y - cy) / fy;
        for (Py_ssize_t x = 0; x < cols; x++) {
            f32 t = depth[y * cols + x];
            if (!(t > 0))
                continue;
            f32 dx = ((f32)x - cx) / fx;
            f32 q[3];
            for (int a = 0; a < 3; a++)
                q[a] = (o[a] + t * (Rc[3 * a] * dx + Rc[3 * a + 1] * dy + Rc[3 * a + 2])) / block_size;
            if (!(in_range(q[0]) && in_range(q[1]) && in_range(q[2])))
                continue; /* no block (inf, or beyond 2^30 blocks) */
            for (int a = 0; a < 3; a++) {
                int64_t b = (int64_t)floorf(q[a]);
                if (b - 1 < lo[a])
                    lo[a] = b - 1;
                if (b + 1 > hi[a])
                    hi[a] = b + 1;
            }
        }
    }
    Py_END_ALLOW_THREADS
    rm_release(v, 5);
    Py_RETURN_NONE;
fail:
    rm_release(v, 5);
    return NULL;
}

/* -------------------------------------------------------------------------------------------- surface_colour */
/* One pixel; ``ACC`` is float32 for a float32 colour buffer and float64 for uint16 (Numba's promotion). */
#define SURFACE_COLOUR_PIXEL(ACC, COLOUR)                                                                          \
    do {                                                                                                           \
        f32 r_sum = 0.0f;                                                                                          \
        ACC c0 = 0, c1 = 0, c2 = 0;                                                                                \
        for (int k = 0; k < 8; k++) {                                                                              \
            int dx = k & 1, dy = (k >> 1) & 1, dz = (k >> 2) & 1;                                                  \
            int64_t nx = ix + dx, ny = iy + dy, nz = iz + dz, li;                                                  \
            if (0 <= nx && nx < res && 0 <= ny && ny < res && 0 <= nz && nz < res)                                 \
                li = slot * res3 + nz * res2 + ny * res + nx;                                                      \
            else {                                                                                                 \
                int64_t nslot = block_slot(&table, bx + (nx >= res) - (nx < 0), by + (ny >= res) - (ny < 0),       \
                                           bz + (nz >= res) - (nz < 0));                                           \
                if (nslot < 0)                                                                                     \
                    continue;                                                                                      \
                li = nslot * res3 + pymod(nz, res) * res2 + pymod(ny, res) * res + pymod(nx, res);                 \
            }                                                                                                      \
            if (li >= n_voxels || !weight_positive(&weight, li))                                                   \
                continue;                                                                                          \
            f32 r = (dx ? rx : 1.0f - rx) * (dy ? ry : 1.0f - ry) * (dz ? rz : 1.0f - rz);                         \
            c0 += (ACC)r * (ACC)COLOUR[3 * li];                                                                    \
            c1 += (ACC)r * (ACC)COLOUR[3 * li + 1];                                                                \
            c2 += (ACC)r * (ACC)COLOUR[3 * li + 2];                                                                \
            r_sum += r;                                                                                            \
        }                                                                                                          \
        if (r_sum > 0) {                                                                                           \
            r_sum *= scale;                                                                                        \
            px[0] = (f32)(c0 / (ACC)r_sum);                                                                        \
            px[1] = (f32)(c1 / (ACC)r_sum);                                                                        \
            px[2] = (f32)(c2 / (ACC)r_sum);                                                                        \
        }                                                                                                          \
    } while (0)

/* What surface_colour computes for pixel (x, y) of depth t, into px[0..2] (zero where no voxel is observed). */
typedef struct {
    const f32 *Rc, *o;
    f32 fx, fy, cx, cy, vs, scale, block_size;
    int64_t res, res2, res3;
    Py_ssize_t n_voxels;
    const Attr *colour, *weight;
    const BlockTable *table;
} ColourCtx;

static inline void colour_pixel(const ColourCtx *cc, f32 t, Py_ssize_t x, Py_ssize_t y, f32 *px)
{
    const f32 *Rc = cc->Rc, *o = cc->o;
    const f32 vs = cc->vs, scale = cc->scale, block_size = cc->block_size;
    const int64_t res = cc->res, res2 = cc->res2, res3 = cc->res3;
    const Py_ssize_t n_voxels = cc->n_voxels;
    const Attr weight = *cc->weight;
    const BlockTable table = *cc->table;
    px[0] = px[1] = px[2] = 0.0f;
    if (!(t > 0))
        return;
    f32 dyc = ((f32)y - cc->cy) / cc->fy;
    f32 dxc = ((f32)x - cc->cx) / cc->fx;
    f32 xg = o[0] + t * (Rc[0] * dxc + Rc[1] * dyc + Rc[2]);
    f32 yg = o[1] + t * (Rc[3] * dxc + Rc[4] * dyc + Rc[5]);
    f32 zg = o[2] + t * (Rc[6] * dxc + Rc[7] * dyc + Rc[8]);
    f32 qx = xg / block_size, qy = yg / block_size, qz = zg / block_size;
    if (!(in_range(qx) && in_range(qy) && in_range(qz)))
        return;
    int64_t bx = (int64_t)floorf(qx), by = (int64_t)floorf(qy), bz = (int64_t)floorf(qz);
    int64_t slot = block_slot(&table, bx, by, bz);
    if (slot < 0)
        return;
    f32 gx = (xg - (f32)bx * block_size) / vs;
    f32 gy = (yg - (f32)by * block_size) / vs;
    f32 gz = (zg - (f32)bz * block_size) / vs;
    f32 fx0 = floorf(gx), fy0 = floorf(gy), fz0 = floorf(gz);
    int64_t ix = (int64_t)fx0, iy = (int64_t)fy0, iz = (int64_t)fz0;
    f32 rx = gx - fx0, ry = gy - fy0, rz = gz - fz0;
    if (cc->colour->u16) {
        const uint16_t *colour_u = cc->colour->data;
        SURFACE_COLOUR_PIXEL(f64, colour_u);
    } else {
        const f32 *colour_f = cc->colour->data;
        SURFACE_COLOUR_PIXEL(f32, colour_f);
    }
}

static PyObject *surface_colour(PyObject *self, PyObject *args)
{
    PyObject *od, *oR, *oo, *oc, *ow, *oi, *ol, *oout;
    double fx_d, fy_d, cx_d, cy_d, vs_d, scale_d;
    Py_ssize_t res;
    Py_buffer v[8] = {{0}};
    Attr colour, weight;
    BlockTable table;
    if (!PyArg_ParseTuple(args, "OOOddddOOOOnddO", &od, &oR, &oo, &fx_d, &fy_d, &cx_d, &cy_d, &oc, &ow, &oi, &ol,
                          &res, &vs_d, &scale_d, &oout))
        return NULL;
    if (rm_get(od, &v[0], 'f', 4, 2, 0, "depth") || rm_get(oR, &v[1], 'f', 4, 2, 0, "Rc")
        || rm_get(oo, &v[2], 'f', 4, 1, 0, "o") || attr(oc, &v[3], "colour", &colour)
        || attr(ow, &v[4], "weight", &weight) || rm_get(oi, &v[5], 'i', 4, 3, 0, "index")
        || rm_get(ol, &v[6], 'i', 8, 1, 0, "lo") || rm_get(oout, &v[7], 'f', 4, 3, 1, "out"))
        goto fail;
    Py_ssize_t rows = v[0].shape[0], cols = v[0].shape[1];
    if (rm_dim(&v[1], 0, 3, "Rc") || rm_dim(&v[1], 1, 3, "Rc") || rm_dim(&v[2], 0, 3, "o")
        || rm_dim(&v[7], 0, rows, "out") || rm_dim(&v[7], 1, cols, "out") || rm_dim(&v[7], 2, 3, "out")
        || block_table(&v[5], &v[6], &table))
        goto fail;
    if (res < 1 || res > 1024) {
        PyErr_Format(PyExc_ValueError, "res: must be in 1..1024, got %zd", res);
        goto fail;
    }
    const Py_ssize_t n_voxels = colour.n / 3 < weight.n ? colour.n / 3 : weight.n;
    const f32 *depth = v[0].buf, *Rc = v[1].buf, *o = v[2].buf;
    f32 *out = v[7].buf;
    const f32 fx = (f32)fx_d, fy = (f32)fy_d, cx = (f32)cx_d, cy = (f32)cy_d;
    const f32 vs = (f32)vs_d, scale = (f32)scale_d, block_size = vs * (f32)res;
    const int64_t res2 = res * res, res3 = res2 * res;
    const ColourCtx cc = {Rc, o, fx, fy, cx, cy, vs, scale, block_size, res, res2, res3, n_voxels, &colour, &weight,
                          &table};
    Py_BEGIN_ALLOW_THREADS
#ifdef _OPENMP
#pragma omp parallel for schedule(static)
#endif
    for (Py_ssize_t y = 0; y < rows; y++)
        for (Py_ssize_t x = 0; x < cols; x++)
            colour_pixel(&cc, depth[y * cols + x], x, y, out + 3 * (y * cols + x));
    Py_END_ALLOW_THREADS
    rm_release(v, 8);
    Py_RETURN_NONE;
fail:
    rm_release(v, 8);
    return NULL;
}

/* ------------------------------------------------------------------------------------------ fill_block_table */
static PyObject *fill_block_table(PyObject *self, PyObject *args)
{
    PyObject *ok, *os, *ol, *oi;
    Py_buffer v[4] = {{0}};
    if (!PyArg_ParseTuple(args, "OOOO", &ok, &os, &ol, &oi))
        return NULL;
    if (rm_get(ok, &v[0], 'i', 4, 2, 0, "keys") || rm_get(os, &v[1], 'i', 4, 1, 0, "slots")
        || rm_get(ol, &v[2], 'i', 8, 1, 0, "lo") || rm_get(oi, &v[3], 'i', 4, 3, 1, "index"))
        goto fail;
    Py_ssize_t n = v[0].shape[0];
    if (rm_dim(&v[0], 1, 3, "keys") || rm_dim(&v[1], 0, n, "slots") || rm_dim(&v[2], 0, 3, "lo"))
        goto fail;
    const int32_t *keys = v[0].buf, *slots = v[1].buf;
    const int64_t *lo = v[2].buf;
    int32_t *index = v[3].buf;
    int64_t X = v[3].shape[0], Y = v[3].shape[1], Z = v[3].shape[2];
    for (Py_ssize_t i = 0; i < n; i++) {
        int64_t jx = keys[3 * i] - lo[0], jy = keys[3 * i + 1] - lo[1], jz = keys[3 * i + 2] - lo[2];
        if (0 <= jx && jx < X && 0 <= jy && jy < Y && 0 <= jz && jz < Z)
            index[(jx * Y + jy) * Z + jz] = slots[i];
    }
    rm_release(v, 4);
    Py_RETURN_NONE;
fail:
    rm_release(v, 4);
    return NULL;
}

/* --------------------------------------------------------------------------------------------- integrate_u16 */
static PyObject *integrate_u16(PyObject *self, PyObject *args)
{
    PyObject *od, *oc, *oE, *ok, *os, *ot, *ow, *ocb, *ocl;
    double fx_d, fy_d, cx_d, cy_d, vs_d, trunc_d, dmax_d, scale;
    Py_ssize_t res;
    Py_buffer v[9] = {{0}};
    if (!PyArg_ParseTuple(args, "OOddddOOOndddd" "OOOO", &od, &oc, &fx_d, &fy_d, &cx_d, &cy_d, &oE, &ok, &os, &res,
                          &vs_d, &trunc_d, &dmax_d, &scale, &ot, &ow, &ocb, &ocl))
        return NULL;
    if (rm_get(od, &v[0], 'f', 4, 2, 0, "depth") || rm_get(oc, &v[1], 'f', 4, 3, 0, "colour")
        || rm_get(oE, &v[2], 'f', 4, 2, 0, "E") || rm_get(ok, &v[3], 'i', 4, 2, 0, "keys")
        || rm_get(os, &v[4], 'i', 8, 1, 0, "slots") || rm_get(ot, &v[5], 'f', 4, -1, 1, "tsdf")
        || rm_get(ow, &v[6], 'u', 2, -1, 1, "weight") || rm_get(ocb, &v[7], 'u', 2, -1, 1, "colour_buf")
        || rm_get(ocl, &v[8], 'i', 8, 1, 1, "clipped"))
        goto fail;
    Py_ssize_t rows = v[0].shape[0], cols = v[0].shape[1], nb = v[4].shape[0];
    if (rm_dim(&v[1], 0, rows, "colour") || rm_dim(&v[1], 1, cols, "colour") || rm_dim(&v[1], 2, 3, "colour")
        || rm_dim(&v[2], 0, 3, "E") || rm_dim(&v[2], 1, 4, "E") || rm_dim(&v[3], 0, nb, "keys")
        || rm_dim(&v[3], 1, 3, "keys") || rm_dim(&v[8], 0, nb, "clipped"))
        goto fail;
    if (res < 1 || res > 1024) {
        PyErr_Format(PyExc_ValueError, "res: must be in 1..1024, got %zd", res);
        goto fail;
    }
    const int64_t res2 = res * res, res3 = res2 * res;
    Py_ssize_t n_voxels = rm_items(&v[5]);
    if (rm_items(&v[6]) < n_voxels)
        n_voxels = rm_items(&v[6]);
    if (rm_items(&v[7]) / 3 < n_voxels)
        n_voxels = rm_items(&v[7]) / 3;
    const int64_t *slots = v[4].buf;
    for (Py_ssize_t b = 0; b < nb; b++)
        if (slots[b] < 0 || slots[b] >= n_voxels / res3) {
            PyErr_Format(PyExc_ValueError, "slots: slot %lld is outside the grid's buffers",
                         (long long)slots[b]);
            goto fail;
        }
    const f32 *depth = v[0].buf, *colour = v[1].buf, *E = v[2].buf;
    const int32_t *keys = v[3].buf;
    f32 *tsdf = v[5].buf;
    uint16_t *weight = v[6].buf, *colour_buf = v[7].buf;
    int64_t *clipped = v[8].buf;
    const f32 fx = (f32)fx_d, fy = (f32)fy_d, cx = (f32)cx_d, cy = (f32)cy_d, voxel_size = (f32)vs_d;
    const f32 sdf_trunc = (f32)trunc_d, depth_max = (f32)dmax_d;
    Py_BEGIN_ALLOW_THREADS
#ifdef _OPENMP
#pragma omp parallel for schedule(static)
#endif
    for (Py_ssize_t b = 0; b < nb; b++) {
        int64_t base = slots[b] * res3;
        int64_t xb = (int64_t)keys[3 * b] * res, yb = (int64_t)keys[3 * b + 1] * res,
                zb = (int64_t)keys[3 * b + 2] * res;
        int64_t n_clipped = 0;
        for (int64_t iz = 0; iz < res; iz++) {
            f32 zs = (f32)(zb + iz) * voxel_size;
            f32 z0 = zs * E[2], z1 = zs * E[6], z2 = zs * E[10];
            for (int64_t iy = 0; iy < res; iy++) {
                f32 ys = (f32)(yb + iy) * voxel_size;
                f32 y0 = ys * E[1], y1 = ys * E[5], y2 = ys * E[9];
                int64_t li = base + iz * res2 + iy * res - 1;
                for (int64_t ix = 0; ix < res; ix++) {
                    li++;
                    f32 xs = (f32)(xb + ix) * voxel_size;
                    f32 xc = xs * E[0] + y0 + z0 + E[3];
                    f32 yc = xs * E[4] + y1 + z1 + E[7];
                    f32 zc = xs * E[8] + y2 + z2 + E[11];
                    f32 inv_z = 1.0f / zc;
                    f32 u = fx * xc * inv_z + cx;
                    f32 vv = fy * yc * inv_z + cy;
                    if (!(vv >= 0 && u >= 0 && vv <= (f32)(rows - 1) && u <= (f32)(cols - 1)))
                        continue;
                    Py_ssize_t ui = (Py_ssize_t)u, vi = (Py_ssize_t)vv;
                    f32 d = depth[vi * cols + ui];
                    f32 sdf = d - zc;
                    if (d <= 0 || d > depth_max || zc <= 0 || sdf < -sdf_trunc)
                        continue;
                    if (!(sdf < sdf_trunc))
                        sdf = sdf_trunc;
                    sdf /= sdf_trunc;
                    f32 w = (f32)weight[li];
                    f32 inv_wsum = 1.0f / (w + 1.0f);
                    tsdf[li] = (w * tsdf[li] + sdf) * inv_wsum;
                    f64 w64 = (f64)w, inv64 = 1.0 / (w64 + 1.0);
                    for (int c = 0; c < 3; c++) {
                        f64 x = (f64)colour[3 * (vi * cols + ui) + c] * scale;
                        if (x != x)
                            x = 0.0;
                        else if (x < 0.0 || x > 65535.0) {
                            x = x < 0.0 ? 0.0 : 65535.0;
                            n_clipped++;
                        }
                        colour_buf[3 * li + c] = (uint16_t)((w64 * colour_buf[3 * li + c] + x) * inv64 + 0.5);
                    }
                    if (w < 65535.0f)
                        weight[li] = (uint16_t)(w + 1.0f);
                }
            }
        }
        clipped[b] = n_clipped;
    }
    Py_END_ALLOW_THREADS
    rm_release(v, 9);
    Py_RETURN_NONE;
fail:
    rm_release(v, 9);
    return NULL;
}

/* ------------------------------------------------------------------------------- display look-ups (FastForward) */
typedef struct {
    const f32 *tables, *inv_slope, *lo, *inv_width;
    const int32_t *starts;
    Py_ssize_t nb; /* buckets: starts has nb + 1 rows */
} Forward;

static int forward_tables(PyObject *const *o, Py_buffer *v, Forward *f)
{
    if (rm_get(o[0], &v[0], 'f', 4, 2, 0, "tables") || rm_get(o[1], &v[1], 'f', 4, 2, 0, "inv_slope")
        || rm_get(o[2], &v[2], 'i', 4, 2, 0, "starts") || rm_get(o[3], &v[3], 'f', 4, 1, 0, "lo")
        || rm_get(o[4], &v[4], 'f', 4, 1, 0, "inv_width"))
        return -1;
    if (v[2].shape[0] < 1) {
        PyErr_SetString(PyExc_ValueError, "starts: needs at least one bucket");
        return -1;
    }
    if (rm_dim(&v[0], 0, 256, "tables") || rm_dim(&v[0], 1, 3, "tables") || rm_dim(&v[1], 0, 255, "inv_slope")
        || rm_dim(&v[1], 1, 3, "inv_slope") || rm_dim(&v[2], 1, 3, "starts") || rm_dim(&v[3], 0, 3, "lo")
        || rm_dim(&v[4], 0, 3, "inv_width"))
        return -1;
    f->tables = v[0].buf;
    f->inv_slope = v[1].buf;
    f->starts = v[2].buf;
    f->lo = v[3].buf;
    f->inv_width = v[4].buf;
    f->nb = v[2].shape[0] - 1;
    const int32_t *s = f->starts;
    for (Py_ssize_t i = 0; i < 3 * (f->nb + 1); i++)
        if (s[i] < 0 || s[i] > 254) {
            PyErr_SetString(PyExc_ValueError, "starts: table indices must be in 0..254");
            return -1;
        }
    return 0;
}

/* The display level of irradiance ``e`` in channel ``c`` (float64, as Numba's ``j + float32 term``). */
static inline f64 level(const Forward *f, f32 e, int c)
{
    const f32 t0 = f->tables[c], tmax = f->tables[255 * 3 + c];
    if (e > t0 && e < tmax) {
        f32 q = (e - f->lo[c]) * f->inv_width[c];
        int64_t b = !(q >= 0) ? 0 : (f64)q > (f64)f->nb ? f->nb : (int64_t)q; /* a bucket of the table, always */
        int64_t j = f->starts[b * 3 + c];
        while (f->tables[(j + 1) * 3 + c] <= e)
            j++;
        return (f64)j + (f64)((e - f->tables[j * 3 + c]) * f->inv_slope[j * 3 + c]);
    }
    return e >= tmax ? 255.0 : 0.0;
}

static PyObject *forward(PyObject *self, PyObject *args)
{
    PyObject *o[7];
    Py_buffer v[7] = {{0}};
    Forward f;
    if (!PyArg_ParseTuple(args, "OOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6]))
        return NULL;
    if (rm_get(o[0], &v[0], 'f', 4, 2, 0, "x") || forward_tables(o + 1, v + 1, &f)
        || rm_get(o[6], &v[6], 'f', 4, 2, 1, "out"))
        goto fail;
    Py_ssize_t n = v[0].shape[0];
    if (rm_dim(&v[0], 1, 3, "x") || rm_dim(&v[6], 0, n, "out") || rm_dim(&v[6], 1, 3, "out"))
        goto fail;
    const f32 *x = v[0].buf;
    f32 *out = v[6].buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < n; i++)
        for (int c = 0; c < 3; c++)
            out[3 * i + c] = (f32)level(&f, x[3 * i + c], c);
    Py_END_ALLOW_THREADS
    rm_release(v, 7);
    Py_INCREF(o[6]);
    return o[6];
fail:
    rm_release(v, 7);
    return NULL;
}

static PyObject *l1(PyObject *self, PyObject *args)
{
    PyObject *o[8];
    Py_buffer v[8] = {{0}};
    Forward f;
    if (!PyArg_ParseTuple(args, "OOOOOOOO", &o[0], &o[1], &o[2], &o[3], &o[4], &o[5], &o[6], &o[7]))
        return NULL;
    if (rm_get(o[0], &v[0], 'f', 4, 2, 0, "a") || rm_get(o[1], &v[1], 'f', 4, 2, 0, "b")
        || forward_tables(o + 2, v + 2, &f) || rm_get(o[7], &v[7], 'f', 4, 1, 1, "out"))
        goto fail;
    Py_ssize_t n = v[0].shape[0];
    if (rm_dim(&v[0], 1, 3, "a") || rm_dim(&v[1], 0, n, "b") || rm_dim(&v[1], 1, 3, "b")
        || rm_dim(&v[7], 0, n, "out"))
        goto fail;
    const f32 *a = v[0].buf, *b = v[1].buf;
    f32 *out = v[7].buf;
    Py_BEGIN_ALLOW_THREADS
#ifdef _OPENMP
#pragma omp parallel for schedule(static)
#endif
    for (Py_ssize_t i = 0; i < n; i++) {
        f32 acc = 0.0f;
        for (int c = 0; c < 3; c++) /* out[i] += |la - lb|: float32 + float64, stored as float32 */
            acc = (f32)((f64)acc + fabs(level(&f, a[3 * i + c], c) - level(&f, b[3 * i + c], c)));
        out[i] = acc;
    }
    Py_END_ALLOW_THREADS
    rm_release(v, 8);
    Py_INCREF(o[7]);
    return o[7];
fail:
    rm_release(v, 8);
    return NULL;
}

/* ---------------------------------------------------------------------------------------------------- pyrdown */
static PyObject *pyrdown(PyObject *self, PyObject *args)
{
    PyObject *od, *oo;
    double diff_d;
    Py_buffer v[2] = {{0}};
    if (!PyArg_ParseTuple(args, "OdO", &od, &diff_d, &oo))
        return NULL;
    if (rm_get(od, &v[0], 'f', 4, 2, 0, "depth") || rm_get(oo, &v[1], 'f', 4, 2, 1, "out"))
        goto fail;
    Py_ssize_t rows = v[0].shape[0], cols = v[0].shape[1];
    if (rm_dim(&v[1], 0, (rows + 1) / 2, "out") || rm_dim(&v[1], 1, (cols + 1) / 2, "out"))
        goto fail;
    const f32 *depth = v[0].buf, diff = (f32)diff_d;
    f32 *out = v[1].buf;
    const f64 w1[5] = {1.0, 4.0, 6.0, 4.0, 1.0};
    Py_ssize_t orows = v[1].shape[0], ocols = v[1].shape[1];
    Py_BEGIN_ALLOW_THREADS
#ifdef _OPENMP
#pragma omp parallel for schedule(static)
#endif
    for (Py_ssize_t y = 0; y < orows; y++)
        for (Py_ssize_t x = 0; x < ocols; x++) {
            Py_ssize_t cy = 2 * y, cx = 2 * x;
            f32 c = depth[cy * cols + cx];
            if (!(c > 0)) {
                out[y * ocols + x] = NAN;
                continue;
            }
            f64 s = 0.0, ws = 0.0;
            for (int dy = -2; dy < 3; dy++) {
                Py_ssize_t yy = cy + dy;
                if (yy < 0 || yy >= rows)
                    continue;
                for (int dx = -2; dx < 3; dx++) {
                    Py_ssize_t xx = cx + dx;
                    if (xx < 0 || xx >= cols)
                        continue;
                    f32 d = depth[yy * cols + xx];
                    if (d > 0 && fabsf(d - c) < diff) {
                        f64 w = w1[dy + 2] * w1[dx + 2];
                        s += w * (f64)d;
                        ws += w;
                    }
                }
            }
            out[y * ocols + x] = ws > 0 ? (f32)(s / ws) : NAN; /* no neighbour within diff (diff <= 0, inf) */
        }
    Py_END_ALLOW_THREADS
    rm_release(v, 2);
    Py_INCREF(oo);
    return oo;
fail:
    rm_release(v, 2);
    return NULL;
}

/* ------------------------------------------------------------------------------------- vertex and normal maps */
/* Open3D 0.20's Image.create_vertex_map and create_normal_map (t/geometry/kernel/ImageImpl.h, CPU, one thread there)
 * with the same float32 operations in the same order, so the same bits (tests/test_surface_maps.py compares them
 * with Open3D's), on every thread. vertex_map: (x - cx) * d / fx, (y - cy) * d / fy, d; NaN depth gives NaN (as
 * Open3D's with invalid_fill NaN). normal_map: the cross product of the differences to the pixel below and to the
 * right, divided by its length but at most by 1e-5 (a tiny or zero cross product stays short: Open3D 0.20's floor,
 * found by comparing); NaN in the last row and column and wherever a neighbour is NaN. */
static PyObject *vertex_map(PyObject *self, PyObject *args)
{
    PyObject *od, *oo;
    double fx_d, fy_d, cx_d, cy_d;
    Py_buffer v[2] = {{0}};
    if (!PyArg_ParseTuple(args, "OddddO", &od, &fx_d, &fy_d, &cx_d, &cy_d, &oo))
        return NULL;
    if (rm_get(od, &v[0], 'f', 4, 2, 0, "depth") || rm_get(oo, &v[1], 'f', 4, 3, 1, "out"))
        goto fail;
    Py_ssize_t rows = v[0].shape[0], cols = v[0].shape[1];
    if (rm_dim(&v[1], 0, rows, "out") || rm_dim(&v[1], 1, cols, "out") || rm_dim(&v[1], 2, 3, "out"))
        goto fail;
    const f32 *depth = v[0].buf, fx = (f32)fx_d, fy = (f32)fy_d, cx = (f32)cx_d, cy = (f32)cy_d;
    f32 *out = v[1].buf;
    Py_BEGIN_ALLOW_THREADS
#ifdef _OPENMP
#pragma omp parallel for schedule(static)
#endif
    for (Py_ssize_t y = 0; y < rows; y++)
        for (Py_ssize_t x = 0; x < cols; x++) {
            f32 d = depth[y * cols + x], *p = out + 3 * (y * cols + x);
            p[0] = ((f32)x - cx) * d / fx;
            p[1] = ((f32)y - cy) * d / fy;
            p[2] = d;
        }
    Py_END_ALLOW_THREADS
    rm_release(v, 2);
    Py_INCREF(oo);
    return oo;
fail:
    rm_release(v, 2);
    return NULL;
}

static PyObject *normal_map(PyObject *self, PyObject *args)
{
    PyObject *ov, *oo;
    Py_buffer v[2] = {{0}};
    if (!PyArg_ParseTuple(args, "OO", &ov, &oo))
        return NULL;
    if (rm_get(ov, &v[0], 'f', 4, 3, 0, "vertex") || rm_get(oo, &v[1], 'f', 4, 3, 1, "out"))
        goto fail;
    Py_ssize_t rows = v[0].shape[0], cols = v[0].shape[1];
    if (rm_dim(&v[0], 2, 3, "vertex") || rm_dim(&v[1], 0, rows, "out") || rm_dim(&v[1], 1, cols, "out")
        || rm_dim(&v[1], 2, 3, "out"))
        goto fail;
    const f32 *vx = v[0].buf;
    f32 *out = v[1].buf;
    Py_BEGIN_ALLOW_THREADS
#ifdef _OPENMP
#pragma omp parallel for schedule(static)
#endif
    for (Py_ssize_t y = 0; y < rows; y++)
        for (Py_ssize_t x = 0; x < cols; x++) {
            f32 *n = out + 3 * (y * cols + x);
            if (y == rows - 1 || x == cols - 1) {
                n[0] = n[1] = n[2] = NAN;
                continue;
            }
            const f32 *v00 = vx + 3 * (y * cols + x), *v10 = v00 + 3, *v01 = v00 + 3 * cols;
            f32 dx0 = v01[0] - v00[0], dy0 = v01[1] - v00[1], dz0 = v01[2] - v00[2];
            f32 dx1 = v10[0] - v00[0], dy1 = v10[1] - v00[1], dz1 = v10[2] - v00[2];
            f32 a = dy0 * dz1 - dz0 * dy1, b = dz0 * dx1 - dx0 * dz1, c = dx0 * dy1 - dy0 * dx1;
            f32 norm = sqrtf(a * a + b * b + c * c);
            if (norm < 1e-5f) /* Open3D's floor: a normal shorter than 1e-5 is divided by 1e-5, not by its length */
                norm = 1e-5f;
            n[0] = a / norm;
            n[1] = b / norm;
            n[2] = c / norm;
        }
    Py_END_ALLOW_THREADS
    rm_release(v, 2);
    Py_INCREF(oo);
    return oo;
fail:
    rm_release(v, 2);
    return NULL;
}

/* ---------------------------------------------------------------------------------------------- raycast_depth */
/* Open3D 0.20's VoxelBlockGrid.ray_cast (EstimateRange, then RayCastCPU's march), depth only, with the grid's
 * blocks looked up in a dense table (BlockTable) instead of its hash map, and nothing but the depth written:
 * the same float32 operations in the same order, so the same depth bit for bit (tests/test_raycast.py compares
 * it with Open3D's cast). The range map: per 8x8 pixels the least and greatest camera depth of the listed blocks'
 * corners whose projected rectangles (Open3D's pass 0, as range_fragments) cover it; pixels march from there.
 * The table must hold every block of the grid that a ray below ``t_max`` can reach (the caller builds it over
 * the view frustum); a block outside it is taken as absent. ``steps`` (int64[9]) holds on entry, in [3:9], the
 * bounding box of the map's blocks (lo, hi) and receives in [0:3] the march steps taken, the rays marched and the
 * look-ups of a block inside that box but outside the table (then the cast may not be Open3D's: cast again).
 * The optional last argument ``simd`` (default True) lets the march use AVX-512 where the CPU has it (the same
 * bits; False forces the scalar march); returns whether it did. */

/* What the march of one band reads and writes. */
typedef struct {
    const f32 *range, *Rc, *o, *tsdf;
    f32 *out;
    Py_ssize_t cols, n_voxels;
    int64_t w_down, res, res2, res3, kb[6]; /* kb: the bounding box of the map's blocks (lo, hi) */
    f32 fx, fy, cx, cy, block_size, voxel_size, sdf_trunc, weight_threshold;
    const Attr *weight;
    const BlockTable *table;
} RcCtx;

#define RC_LANES 8
typedef struct {
    Py_ssize_t pixel; /* -1: free */
    f32 xd, yd, zd, t, t_max, t_prev, tsdf_prev, tsdf;
    int64_t cslot;
    int cbx, cby, cbz;
} RayLane;

/* Start the band's next pixel that has a range (``next`` .. ``end``; the pixels passed get depth 0): its pixel,
 * ray direction (d) and range of t (r), one more ray counted; 0 when none is left. */
static inline int rc_start(const RcCtx *c, Py_ssize_t *next, Py_ssize_t end, Py_ssize_t *pixel, f32 d[3], f32 r[2],
                           int64_t *rays)
{
    const f32 *Rc = c->Rc, *o = c->o;
    while (*next < end) {
        Py_ssize_t p = (*next)++, y = p / c->cols, x = p % c->cols;
        c->out[p] = 0.0f;
        const f32 *range = c->range + 2 * ((y / 8) * c->w_down + x / 8);
        if (range[0] >= range[1])
            continue;
        ++*rays;
        f32 xc = ((f32)x - c->cx) * 1.0f / c->fx, yc = ((f32)y - c->cy) * 1.0f / c->fy, zc = 1.0f;
        d[0] = (xc * Rc[0] + yc * Rc[1] + zc * Rc[2] + o[0]) - o[0];
        d[1] = (xc * Rc[3] + yc * Rc[4] + zc * Rc[5] + o[1]) - o[1];
        d[2] = (xc * Rc[6] + yc * Rc[7] + zc * Rc[8] + o[2]) - o[2];
        r[0] = range[0];
        r[1] = range[1];
        *pixel = p;
        return 1;
    }
    return 0;
}

/* The march of the 8 rows of ``band``, RC_LANES rays in flight, one step of each in turn, so that the long chain
 * of dependent operations of one step (divisions, floors, two loads) of one ray overlaps those of the others;
 * every ray's own arithmetic is unchanged. Adds to count[0..2] the steps, rays and look-ups outside the table. */
static void rc_march_band(const RcCtx *c, Py_ssize_t band, int64_t count[3])
{
    const f32 *o = c->o, *tsdf = c->tsdf;
    f32 *out = c->out;
    const Py_ssize_t cols = c->cols, n_voxels = c->n_voxels;
    const int64_t res = c->res, res2 = c->res2, res3 = c->res3, *kb = c->kb;
    const f32 block_size = c->block_size;
    const f32 voxel_size = c->voxel_size, sdf_trunc = c->sdf_trunc, weight_threshold = c->weight_threshold;
    const Attr weight = *c->weight;
    const BlockTable table = *c->table;
    int64_t total_steps = 0, total_rays = 0, total_outside = 0;
    RayLane lane[RC_LANES];
    int active = 0;
    Py_ssize_t next = band * 8 * cols, end = (band + 1) * 8 * cols;
    for (int l = 0; l < RC_LANES; l++)
        lane[l].pixel = -1;
    for (;;) {
        for (int l = 0; l < RC_LANES; l++) {
            RayLane *L = &lane[l];
            f32 d[3], r[2];
            if (L->pixel < 0 && rc_start(c, &next, end, &L->pixel, d, r, &total_rays)) {
                L->xd = d[0], L->yd = d[1], L->zd = d[2];
                L->t = L->t_prev = r[0];
                L->t_max = r[1];
                L->tsdf_prev = -1.0f;
                L->tsdf = 1.0f;
                L->cslot = -1;
                active++;
            }
            if (L->pixel < 0)
                continue;
            /* one step of Open3D's march */
            int done = 0, found = 0;
            total_steps++;
            f32 t = L->t;
            f32 xg = o[0] + t * L->xd, yg = o[1] + t * L->yd, zg = o[2] + t * L->zd;
            f32 qx = xg / block_size, qy = yg / block_size, qz = zg / block_size;
            int64_t slot = -1;
            int bx = 0, by = 0, bz = 0;
            if (in_range(qx) && in_range(qy) && in_range(qz)) {
                bx = (int)floorf(qx);
                by = (int)floorf(qy);
                bz = (int)floorf(qz);
                if (L->cslot >= 0 && bx == L->cbx && by == L->cby && bz == L->cbz)
                    slot = L->cslot;
                else {
                    int64_t jx = bx - table.lo[0], jy = by - table.lo[1], jz = bz - table.lo[2];
                    if ((jx < 0 || jy < 0 || jz < 0 || jx >= table.nx || jy >= table.ny || jz >= table.nz)
                        && bx >= kb[0] && by >= kb[1] && bz >= kb[2] && bx <= kb[3] && by <= kb[4] && bz <= kb[5])
                        total_outside++; /* a block the map may hold but the table does not: cast again */
                    slot = block_slot(&table, bx, by, bz);
                    if (slot >= 0) {
                        L->cbx = bx, L->cby = by, L->cbz = bz, L->cslot = slot;
                    }
                }
            }
            if (slot < 0) {
                L->t_prev = t;
                L->t = t + block_size;
            } else {
                int xv = (int)((xg - (f32)bx * block_size) / voxel_size);
                int yv = (int)((yg - (f32)by * block_size) / voxel_size);
                int zv = (int)((zg - (f32)bz * block_size) / voxel_size);
                int64_t li = slot * res3 + (int64_t)zv * res2 + (int64_t)yv * res + xv;
                if (li < 0 || li >= n_voxels) /* Open3D would read outside the buffer: stop (never seen) */
                    done = 1;
                else {
                    f32 tsdf_prev = L->tsdf, tsdf_v = tsdf[li];
                    f32 w = weight.u16 ? (f32)((const uint16_t *)weight.data)[li]
                                       : ((const f32 *)weight.data)[li];
                    L->tsdf_prev = tsdf_prev;
                    L->tsdf = tsdf_v;
                    if (tsdf_prev > 0 && w >= weight_threshold && tsdf_v <= 0)
                        done = found = 1;
                    else {
                        L->t_prev = t;
                        f32 delta = tsdf_v * sdf_trunc;
                        L->t = t + (delta < voxel_size ? voxel_size : delta);
                    }
                }
            }
            if (!done && !(L->t < L->t_max))
                done = 1;
            if (done) {
                if (found)
                    out[L->pixel] = (L->t * L->tsdf_prev - L->t_prev * L->tsdf) / (L->tsdf_prev - L->tsdf);
                L->pixel = -1;
                active--;
            }
        }
        if (active == 0 && next >= end)
            break;
    }
    count[0] += total_steps;
    count[1] += total_rays;
    count[2] += total_outside;
}

#include "_ckernels_raycast_simd.h"

static PyObject *raycast_depth(PyObject *self, PyObject *args)
{
    PyObject *ob, *oR, *ot, *oRc, *oo, *ots, *ow, *oi, *ol, *oout, *osteps, *oRp, *oop, *oc, *ooc;
    double fx_d, fy_d, cx_d, cy_d, vs_d, trunc_d, dmin_d, dmax_d, wt_d, scale_d;
    Py_ssize_t res;
    Py_buffer v[10] = {{0}}, vc[4] = {{0}};
    Attr weight, colour;
    BlockTable table;
    int simd = 1; /* optional: 0 forces the scalar march (tests; RADIOMAP_SIMD=0) */
    if (!PyArg_ParseTuple(args, "OOOOOddddndddddOOOOOOOOOdO|p", &ob, &oR, &ot, &oRc, &oo, &fx_d, &fy_d, &cx_d, &cy_d,
                          &res, &vs_d, &trunc_d, &dmin_d, &dmax_d, &wt_d, &ots, &ow, &oi, &ol, &oout, &osteps, &oRp,
                          &oop, &oc, &scale_d, &ooc, &simd))
        return NULL;
    /* the surface colour (surface_colour's, of each pixel's depth, band by band while its voxels are in the
     * caches): pose rotation and origin as surface_colour takes them, the colour buffer, out (rows, cols, 3) */
    if (rm_get(oRp, &vc[0], 'f', 4, 2, 0, "Rc_pose") || rm_get(oop, &vc[1], 'f', 4, 1, 0, "o_pose")
        || attr(oc, &vc[2], "colour", &colour) || rm_get(ooc, &vc[3], 'f', 4, 3, 1, "out_colour")) {
        rm_release(vc, 4);
        return NULL;
    }
    if (rm_dim(&vc[0], 0, 3, "Rc_pose") || rm_dim(&vc[0], 1, 3, "Rc_pose") || rm_dim(&vc[1], 0, 3, "o_pose")
        || rm_dim(&vc[3], 2, 3, "out_colour")) {
        rm_release(vc, 4);
        return NULL;
    }
    if (rm_get(ob, &v[0], 'i', 4, 2, 0, "blocks") || rm_get(oR, &v[1], 'f', 4, 2, 0, "R")
        || rm_get(ot, &v[2], 'f', 4, 1, 0, "t") || rm_get(oRc, &v[3], 'f', 4, 2, 0, "Rc")
        || rm_get(oo, &v[4], 'f', 4, 1, 0, "o") || rm_get(ots, &v[5], 'f', 4, -1, 0, "tsdf")
        || attr(ow, &v[6], "weight", &weight) || rm_get(oi, &v[7], 'i', 4, 3, 0, "index")
        || rm_get(ol, &v[8], 'i', 8, 1, 0, "lo") || rm_get(oout, &v[9], 'f', 4, 2, 1, "out"))
        goto fail;
    Py_buffer vs_buf = {0};
    if (rm_get(osteps, &vs_buf, 'i', 8, 1, 1, "steps"))
        goto fail;
    if (rm_dim(&vs_buf, 0, 9, "steps")) {
        PyBuffer_Release(&vs_buf);
        goto fail;
    }
    Py_ssize_t nb = v[0].shape[0], rows = v[9].shape[0], cols = v[9].shape[1];
    if (rm_dim(&v[0], 1, 3, "blocks") || rm_dim(&v[1], 0, 3, "R") || rm_dim(&v[1], 1, 3, "R")
        || rm_dim(&v[2], 0, 3, "t") || rm_dim(&v[3], 0, 3, "Rc") || rm_dim(&v[3], 1, 3, "Rc")
        || rm_dim(&v[4], 0, 3, "o") || block_table(&v[7], &v[8], &table)) {
        PyBuffer_Release(&vs_buf);
        goto fail;
    }
    const Py_ssize_t c_rows = vc[3].shape[0], c_cols = vc[3].shape[1]; /* colour of the first c_rows x c_cols */
    if (c_rows > rows || c_cols > cols) {
        PyErr_Format(PyExc_ValueError, "out_colour: at most %zd x %zd, got %zd x %zd", rows, cols, c_rows, c_cols);
        PyBuffer_Release(&vs_buf);
        goto fail;
    }
    if (res < 1 || res > 1024 || rows % 8 || cols % 8) {
        PyErr_Format(PyExc_ValueError, "res must be in 1..1024 and out's sides multiples of 8, got %zd, %zd x %zd",
                     res, rows, cols);
        PyBuffer_Release(&vs_buf);
        goto fail;
    }
    const int32_t *blocks = v[0].buf;
    const f32 *R = v[1].buf, *tv = v[2].buf, *Rc = v[3].buf, *o = v[4].buf, *tsdf = v[5].buf;
    f32 *out = v[9].buf;
    int64_t *steps_out = vs_buf.buf;
    int64_t kb[6]; /* the bounding box of the map's blocks (lo, hi): steps[3:9] on entry */
    memcpy(kb, steps_out + 3, sizeof kb);
    const Py_ssize_t n_voxels = rm_items(&v[5]) < weight.n ? rm_items(&v[5]) : weight.n;
    const f32 fx = (f32)fx_d, fy = (f32)fy_d, cx = (f32)cx_d, cy = (f32)cy_d, down = 8.0f;
    const f32 voxel_size = (f32)vs_d, sdf_trunc = (f32)trunc_d, depth_min = (f32)dmin_d, depth_max = (f32)dmax_d;
    const f32 weight_threshold = (f32)wt_d, block_size = voxel_size * (f32)res;
    const int64_t res2 = res * res, res3 = res2 * res;
    const int64_t h_down = rows / 8, w_down = cols / 8;
    const Py_ssize_t n_col_voxels = colour.n / 3 < weight.n ? colour.n / 3 : weight.n;
    const ColourCtx cc = {vc[0].buf, vc[1].buf, fx, fy, cx, cy, voxel_size, (f32)scale_d, block_size, res, res2, res3,
                          n_col_voxels, &colour, &weight, &table};
    f32 *out_colour = vc[3].buf;
    f32 *range = PyMem_RawMalloc(sizeof(f32) * 2 * (size_t)(h_down * w_down > 0 ? h_down * w_down : 1));
    if (range == NULL) {
        PyBuffer_Release(&vs_buf);
        rm_release(v, 10);
        rm_release(vc, 4);
        return PyErr_NoMemory();
    }
    int64_t total_steps = 0, total_rays = 0, total_outside = 0;
    RcCtx rc = {range, Rc, o, tsdf, out, cols, n_voxels, w_down, res, res2, res3,
                {kb[0], kb[1], kb[2], kb[3], kb[4], kb[5]}, fx, fy, cx, cy, block_size, voxel_size, sdf_trunc,
                weight_threshold, &weight, &table};
#if RC_HAVE_SIMD
    RcSimd rs;
    const int use_simd = simd && rc_simd_supported() && rc_simd_setup(&rc, &rs);
    if (use_simd)
        rc_colour_setup(&cc, &rs);
#else
    const int use_simd = 0;
#endif
    Py_BEGIN_ALLOW_THREADS
    for (int64_t i = 0; i < h_down * w_down; i++) {
        range[2 * i] = depth_max;
        range[2 * i + 1] = depth_min;
    }
    for (Py_ssize_t k = 0; k < nb; k++) { /* Open3D's pass 0 (as range_fragments), then its fragments' min/max */
        int64_t box[4];
        f32 z[2];
        if (!block_footprint(blocks + 3 * k, res, voxel_size, R, tv, fx, fy, cx, cy, down, w_down, h_down, depth_min,
                             depth_max, box, z))
            continue;
        for (int64_t vt = box[1]; vt <= box[3]; vt++)
            for (int64_t ut = box[0]; ut <= box[2]; ut++) {
                f32 *r = range + 2 * (vt * w_down + ut);
                if (z[0] < r[0]) r[0] = z[0];
                if (z[1] > r[1]) r[1] = z[1];
            }
    }
    /* The march: each thread takes 8 rows at a time (band), with AVX-512 where the CPU has it (16 rays a vector,
     * _ckernels_raycast_simd.h) unless ``simd`` is 0, else RC_LANES scalar rays; both give the same bits. */
#ifdef _OPENMP
#pragma omp parallel for schedule(dynamic, 1) reduction(+ : total_steps, total_rays, total_outside)
#endif
    for (Py_ssize_t band = 0; band < rows / 8; band++) {
        int64_t count[3] = {0, 0, 0};
#if RC_HAVE_SIMD
        if (use_simd)
            rc_march_band_simd(&rc, &rs, band, count);
        else
#endif
            rc_march_band(&rc, band, count);
        total_steps += count[0];
        total_rays += count[1];
        total_outside += count[2];
        for (Py_ssize_t y = band * 8; y < band * 8 + 8 && y < c_rows; y++) {
#if RC_HAVE_SIMD
            if (use_simd && rs.colour) {
                for (Py_ssize_t x0 = 0; x0 < c_cols; x0 += 16)
                    rc_colour16(&cc, &rs, out + y * cols, y, x0, c_cols, out_colour + 3 * y * c_cols);
                continue;
            }
#endif
            for (Py_ssize_t x = 0; x < c_cols; x++)
                colour_pixel(&cc, out[y * cols + x], x, y, out_colour + 3 * (y * c_cols + x));
        }
    }
    Py_END_ALLOW_THREADS
    PyMem_RawFree(range);
    steps_out[0] = total_steps;
    steps_out[1] = total_rays;
    steps_out[2] = total_outside;
    PyBuffer_Release(&vs_buf);
    rm_release(v, 10);
    rm_release(vc, 4);
    return PyBool_FromLong(use_simd);
fail:
    rm_release(v, 10);
    rm_release(vc, 4);
    return NULL;
}

static PyMethodDef methods[] = {
    {"colour_pairs", colour_pairs, METH_VARARGS, "TSDF colour pairs (mapping.fusion._tsdf_kernels.colour_pairs)."},
    {"finish_view", finish_view, METH_VARARGS, "Finish a ray-cast view (_tsdf_kernels.finish_view)."},
    {"refine", refine, METH_VARARGS, "Zero crossing of the trilinear TSDF per ray (_tsdf_kernels.refine)."},
    {"range_fragments", range_fragments, METH_VARARGS, "Open3D's range-map fragments (_tsdf_kernels)."},
    {"hit_bounds", hit_bounds, METH_VARARGS, "Block bounds of the surface points, into lo, hi (_tsdf_kernels)."},
    {"surface_colour", surface_colour, METH_VARARGS, "Trilinear surface colour (_tsdf_kernels.surface_colour)."},
    {"fill_block_table", fill_block_table, METH_VARARGS, "Dense block-slot table (_tsdf_kernels)."},
    {"raycast_depth", raycast_depth, METH_VARARGS, "Open3D's ray cast of depth over a dense block table."},
    {"integrate_u16", integrate_u16, METH_VARARGS, "Fusion into the 16-bit grid (_tsdf_kernels.integrate_u16)."},
    {"forward", forward, METH_VARARGS, "Display levels of irradiance (mapping._colour_kernels.forward)."},
    {"l1", l1, METH_VARARGS, "Display L1 of two irradiance arrays (mapping._colour_kernels.l1)."},
    {"pyrdown", pyrdown, METH_VARARGS, "Edge-preserving half-resolution depth (mapping.tracking)."},
    {"vertex_map", vertex_map, METH_VARARGS, "Open3D's create_vertex_map, bit for bit (mapping.surface_maps)."},
    {"normal_map", normal_map, METH_VARARGS, "Open3D's create_normal_map, bit for bit (mapping.surface_maps)."},
    RM_THREAD_METHODS,
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ckernels",
                                    "radiomap's compiled mapping kernels (see the C source's header).", -1, methods};

PyMODINIT_FUNC PyInit__ckernels(void)
{
    PyObject *m = PyModule_Create(&module);
    if (m != NULL && (PyModule_AddIntConstant(m, "openmp", RM_OPENMP) < 0
                      || PyModule_AddIntConstant(m, "ABI", RM_ABI) < 0
                      || PyModule_AddIntConstant(m, "raycast_simd", rc_simd_supported()) < 0)) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
