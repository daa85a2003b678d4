/* The ray cast's march and surface colour with AVX-512 (mapping/_ckernels.c includes this file after rc_march_band,
 * the scalar march; docs/performance.md, "The ray cast's march with AVX-512").
 *
 * 16 rays per vector, one step of Open3D's march for all 16 at a time, branch-free: the lanes' block, voxel and
 * TSDF look-ups are gathers, the choices are masks. A lane whose ray ends takes the band's next pixel (scalar
 * start, the same pixel order as the scalar march), so every thread does the same work as before. Every float32
 * operation is the scalar march's, in the same order (vmulps, vaddps, vdivps, vroundscaleps towards -inf, vcvttps2dq
 * round as mulss, addss, divss, floorf and the (int) cast; the build has -ffp-contract=off and no FMA is written),
 * so the depth and the step counts are the same bit for bit. Two vectors (32 rays) are in flight, so that one's
 * chain of dependent operations (three divisions, floors, three gathers per step) overlaps the other's.
 *
 * Integer work is 32-bit: rc_simd_setup refuses (scalar march) tables or offsets that do not fit; a lane whose
 * voxel index might not fit (a slot beyond 2^30 / res^3 voxels or voxel coordinates far outside the block, which a
 * float rounding of a far coordinate could give) and the last element of a uint16 weight buffer (a 32-bit gather
 * would read past its end) are looked up in scalar code instead, as the scalar march does.
 *
 * The surface colour (colour_pixel: the trilinear colour of the 8 voxels around each hit) runs 16 pixels of a row
 * at a time the same way (rc_colour16), where rc_colour_setup finds the buffers small enough for 32-bit indices. */
#ifndef RADIOMAP_CKERNELS_RAYCAST_SIMD_H
#define RADIOMAP_CKERNELS_RAYCAST_SIMD_H

#include "../radiometry/_simd_cpu.h"

#if RM_X86_SIMD
#define RC_HAVE_SIMD 1
#define RC_TARGET __attribute__((target("avx512f")))

/* whether this CPU runs the code below: AVX-512 F (CPUID.7 ebx bit 16) */
RM_CPU_CHECK(rc_simd_supported, 1u << 16, 0)

/* the march's constants in 32-bit form (rc_simd_setup) */
typedef struct {
    int32_t lo[3], n[3], kb[6], res, res2, res3, slot_cap, v_cap, n32, w_last;
    int colour;        /* whether the colour pass runs in vectors too (rc_colour_setup) */
    int32_t col_slots; /* slots from which on a corner's voxel lies past the colour buffers (ceil(n / res^3)) */
} RcSimd;

static int rc_fits(int64_t x, int64_t lim)
{
    return x > -lim && x < lim;
}

/* whether the 32-bit arithmetic of the vector march gives the scalar march's results for this table (else the
 * scalar march runs): block coordinates are below 2^30 in magnitude (in_range), so lo within 2^30 keeps b - lo in
 * int32, and a table below 2^31 entries keeps its index in int32 */
static int rc_simd_setup(const RcCtx *c, RcSimd *s)
{
    const BlockTable *t = c->table;
    for (int i = 0; i < 3; i++)
        if (!rc_fits(t->lo[i], (int64_t)1 << 30))
            return 0;
    if (t->nx < 0 || t->ny < 0 || t->nz < 0 || (t->nx && t->ny && t->nz && t->nx * t->ny > INT32_MAX / t->nz))
        return 0;
    for (int i = 0; i < 3; i++)
        s->lo[i] = (int32_t)t->lo[i];
    s->n[0] = (int32_t)t->nx, s->n[1] = (int32_t)t->ny, s->n[2] = (int32_t)t->nz;
    for (int i = 0; i < 6; i++) /* bx >= kb[i] and bx <= kb[i] give the same answers clamped: |bx| < 2^30 */
        s->kb[i] = (int32_t)(c->kb[i] < -((int64_t)1 << 31) ? -((int64_t)1 << 31)
                             : c->kb[i] > INT32_MAX ? INT32_MAX : c->kb[i]);
    s->res = (int32_t)c->res, s->res2 = (int32_t)c->res2, s->res3 = (int32_t)c->res3;
    /* li = slot res^3 + zv res^2 + yv res + xv in int32 where slot <= 2^30 / res^3 and |xv|, |yv|, |zv| <= v_cap */
    s->slot_cap = (int32_t)(((int64_t)1 << 30) / c->res3);
    s->v_cap = (int32_t)(((int64_t)1 << 29) / (c->res2 + c->res + 1));
    s->n32 = (int32_t)(c->n_voxels < INT32_MAX ? c->n_voxels : INT32_MAX);
    s->w_last = c->weight->u16 && c->weight->n - 1 <= INT32_MAX ? (int32_t)(c->weight->n - 1) : -1;
    s->colour = 0;
    return 1;
}

/* whether the colour pass of ``cc`` can run in vectors with 32-bit indices (else colour_pixel runs): 3 (n + res^3)
 * below 2^31 (the colour index of any corner of a slot below col_slots), res >= 2 (a corner's coordinate wraps by at
 * most one block), two weights at least (a uint16 weight is read as 32 bits ending at it) */
static void rc_colour_setup(const ColourCtx *cc, RcSimd *s)
{
    const int64_t n = cc->n_voxels, res3 = cc->res3;
    s->colour = cc->res >= 2 && n >= 2 && 3 * (n + res3) < INT32_MAX;
    s->col_slots = s->colour ? (int32_t)((n + res3 - 1) / res3) : 0;
}

/* 16 rays in flight: their state as vectors, their pixels */
typedef struct {
    __m512 xd, yd, zd, t, t_max, t_prev, tsdf_prev, tsdf;
    __mmask16 active;
    Py_ssize_t pixel[16];
} RcRays;

/* lanes ``m`` take new pixels (the others keep theirs); lanes that find none go idle */
RC_TARGET static inline void rc_refill(const RcCtx *c, RcRays *s, __mmask16 m, Py_ssize_t *next, Py_ssize_t end,
                                       int64_t *rays)
{
    __attribute__((aligned(64))) f32 init[5][16];
    __mmask16 started = 0;
    for (unsigned int bits = m; bits; bits &= bits - 1) {
        int l = __builtin_ctz(bits);
        f32 d[3], r[2];
        if (rc_start(c, next, end, &s->pixel[l], d, r, rays)) {
            init[0][l] = d[0], init[1][l] = d[1], init[2][l] = d[2], init[3][l] = r[0], init[4][l] = r[1];
            started |= (__mmask16)(1u << l);
        }
    }
    s->active = (__mmask16)((s->active & ~m) | started);
    s->xd = _mm512_mask_load_ps(s->xd, started, init[0]);
    s->yd = _mm512_mask_load_ps(s->yd, started, init[1]);
    s->zd = _mm512_mask_load_ps(s->zd, started, init[2]);
    s->t = _mm512_mask_load_ps(s->t, started, init[3]);
    s->t_prev = _mm512_mask_load_ps(s->t_prev, started, init[3]);
    s->t_max = _mm512_mask_load_ps(s->t_max, started, init[4]);
    s->tsdf_prev = _mm512_mask_mov_ps(s->tsdf_prev, started, _mm512_set1_ps(-1.0f));
    s->tsdf = _mm512_mask_mov_ps(s->tsdf, started, _mm512_set1_ps(1.0f));
}

/* the scalar look-up of lanes ``m`` (rare: see the header): bad lanes (Open3D would read outside the buffer) into
 * *bad, the others' TSDF and weight into tsdf_v / w */
RC_TARGET static void rc_lookup_scalar(const RcCtx *c, __mmask16 m, __m512i slot, __m512i xv, __m512i yv,
                                       __m512i zv, __m512 *tsdf_v, __m512 *w, __mmask16 *bad)
{
    __attribute__((aligned(64))) int32_t sl[16], x[16], y[16], z[16];
    __attribute__((aligned(64))) f32 tv[16], wv[16];
    _mm512_store_si512(sl, slot);
    _mm512_store_si512(x, xv);
    _mm512_store_si512(y, yv);
    _mm512_store_si512(z, zv);
    __mmask16 ok = 0;
    for (unsigned int bits = m; bits; bits &= bits - 1) {
        int l = __builtin_ctz(bits);
        int64_t li = (int64_t)sl[l] * c->res3 + (int64_t)z[l] * c->res2 + (int64_t)y[l] * c->res + x[l];
        if (li < 0 || li >= c->n_voxels) {
            *bad |= (__mmask16)(1u << l);
            continue;
        }
        tv[l] = c->tsdf[li];
        wv[l] = c->weight->u16 ? (f32)((const uint16_t *)c->weight->data)[li] : ((const f32 *)c->weight->data)[li];
        ok |= (__mmask16)(1u << l);
    }
    *tsdf_v = _mm512_mask_load_ps(*tsdf_v, ok, tv);
    *w = _mm512_mask_load_ps(*w, ok, wv);
}

/* the slots of blocks (bx, by, bz) in the lanes ``m`` by a table look-up (block_slot); -1 elsewhere; *in: the lanes
 * inside the table */
RC_TARGET static inline __m512i rc_slot(const BlockTable *t, const RcSimd *k, __mmask16 m, __m512i bx, __m512i by,
                                        __m512i bz, __mmask16 *in)
{
    const __m512i jx = _mm512_sub_epi32(bx, _mm512_set1_epi32(k->lo[0]));
    const __m512i jy = _mm512_sub_epi32(by, _mm512_set1_epi32(k->lo[1]));
    const __m512i jz = _mm512_sub_epi32(bz, _mm512_set1_epi32(k->lo[2]));
    m = _mm512_mask_cmplt_epu32_mask(m, jx, _mm512_set1_epi32(k->n[0]));
    m = _mm512_mask_cmplt_epu32_mask(m, jy, _mm512_set1_epi32(k->n[1]));
    m = _mm512_mask_cmplt_epu32_mask(m, jz, _mm512_set1_epi32(k->n[2]));
    const __m512i i = _mm512_add_epi32(
        _mm512_mullo_epi32(_mm512_add_epi32(_mm512_mullo_epi32(jx, _mm512_set1_epi32(k->n[1])), jy),
                           _mm512_set1_epi32(k->n[2])),
        jz);
    *in = m;
    return _mm512_mask_i32gather_epi32(_mm512_set1_epi32(-1), m, i, t->index, 4);
}

/* one step of Open3D's march for the active lanes of ``s`` (rc_march_band's step, lane by lane); the lanes whose
 * ray ends write their depth (if found) and take the next pixel */
RC_TARGET static inline __attribute__((always_inline)) void rc_step(const RcCtx *c, const RcSimd *k, RcRays *s,
                                                                    Py_ssize_t *next, Py_ssize_t end, int64_t count[3])
{
    const __mmask16 active = s->active;
    const __m512 bs = _mm512_set1_ps(c->block_size), vs = _mm512_set1_ps(c->voxel_size);
    const __m512 lim = _mm512_set1_ps(1073741824.0f), zero = _mm512_setzero_ps();
    count[0] += __builtin_popcount(active);
    const __m512 t = s->t;
    const __m512 xg = _mm512_add_ps(_mm512_set1_ps(c->o[0]), _mm512_mul_ps(t, s->xd));
    const __m512 yg = _mm512_add_ps(_mm512_set1_ps(c->o[1]), _mm512_mul_ps(t, s->yd));
    const __m512 zg = _mm512_add_ps(_mm512_set1_ps(c->o[2]), _mm512_mul_ps(t, s->zd));
    const __m512 qx = _mm512_div_ps(xg, bs), qy = _mm512_div_ps(yg, bs), qz = _mm512_div_ps(zg, bs);
    __mmask16 inr = _mm512_mask_cmp_ps_mask(active, _mm512_abs_ps(qx), lim, _CMP_LT_OQ); /* in_range */
    inr = _mm512_mask_cmp_ps_mask(inr, _mm512_abs_ps(qy), lim, _CMP_LT_OQ);
    inr = _mm512_mask_cmp_ps_mask(inr, _mm512_abs_ps(qz), lim, _CMP_LT_OQ);
    const __m512 fqx = _mm512_roundscale_ps(qx, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    const __m512 fqy = _mm512_roundscale_ps(qy, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    const __m512 fqz = _mm512_roundscale_ps(qz, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    const __m512i bx = _mm512_cvttps_epi32(fqx), by = _mm512_cvttps_epi32(fqy), bz = _mm512_cvttps_epi32(fqz);
    __mmask16 intab;
    const __m512i slot = rc_slot(c->table, k, inr, bx, by, bz, &intab);
    __mmask16 box = (__mmask16)(inr & ~intab); /* a block the map may hold but the table does not */
    if (box) {
        box = _mm512_mask_cmpge_epi32_mask(box, bx, _mm512_set1_epi32(k->kb[0]));
        box = _mm512_mask_cmpge_epi32_mask(box, by, _mm512_set1_epi32(k->kb[1]));
        box = _mm512_mask_cmpge_epi32_mask(box, bz, _mm512_set1_epi32(k->kb[2]));
        box = _mm512_mask_cmple_epi32_mask(box, bx, _mm512_set1_epi32(k->kb[3]));
        box = _mm512_mask_cmple_epi32_mask(box, by, _mm512_set1_epi32(k->kb[4]));
        box = _mm512_mask_cmple_epi32_mask(box, bz, _mm512_set1_epi32(k->kb[5]));
        count[2] += __builtin_popcount(box);
    }
    const __mmask16 hit = _mm512_mask_cmpge_epi32_mask(intab, slot, _mm512_setzero_si512());
    /* the voxel in the block: (int)((xg - bx * block_size) / voxel_size), bx * block_size = floor(q) * block_size */
    const __m512i xv = _mm512_cvttps_epi32(_mm512_div_ps(_mm512_sub_ps(xg, _mm512_mul_ps(fqx, bs)), vs));
    const __m512i yv = _mm512_cvttps_epi32(_mm512_div_ps(_mm512_sub_ps(yg, _mm512_mul_ps(fqy, bs)), vs));
    const __m512i zv = _mm512_cvttps_epi32(_mm512_div_ps(_mm512_sub_ps(zg, _mm512_mul_ps(fqz, bs)), vs));
    const __m512i vcap = _mm512_set1_epi32(k->v_cap), vspan = _mm512_set1_epi32(2 * k->v_cap);
    __mmask16 safe = _mm512_mask_cmple_epi32_mask(hit, slot, _mm512_set1_epi32(k->slot_cap));
    safe = _mm512_mask_cmple_epu32_mask(safe, _mm512_add_epi32(xv, vcap), vspan);
    safe = _mm512_mask_cmple_epu32_mask(safe, _mm512_add_epi32(yv, vcap), vspan);
    safe = _mm512_mask_cmple_epu32_mask(safe, _mm512_add_epi32(zv, vcap), vspan);
    const __m512i li = _mm512_add_epi32(
        _mm512_add_epi32(_mm512_mullo_epi32(slot, _mm512_set1_epi32(k->res3)),
                         _mm512_mullo_epi32(zv, _mm512_set1_epi32(k->res2))),
        _mm512_add_epi32(_mm512_mullo_epi32(yv, _mm512_set1_epi32(k->res)), xv));
    __mmask16 bad = _mm512_mask_cmplt_epi32_mask(safe, li, _mm512_setzero_si512());
    bad |= _mm512_mask_cmpge_epi32_mask(safe, li, _mm512_set1_epi32(k->n32));
    __mmask16 gather = (__mmask16)(safe & ~bad), scalar = (__mmask16)(hit & ~safe);
    if (k->w_last >= 0)
        scalar |= _mm512_mask_cmpeq_epi32_mask(gather, li, _mm512_set1_epi32(k->w_last));
    gather &= (__mmask16)~scalar;
    __m512 tsdf_v = _mm512_mask_i32gather_ps(zero, gather, li, c->tsdf, 4), w;
    if (c->weight->u16)
        w = _mm512_cvtepi32_ps(_mm512_and_si512(
            _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), gather, li, c->weight->data, 2),
            _mm512_set1_epi32(0xffff)));
    else
        w = _mm512_mask_i32gather_ps(zero, gather, li, c->weight->data, 4);
    if (scalar)
        rc_lookup_scalar(c, scalar, slot, xv, yv, zv, &tsdf_v, &w, &bad);
    const __mmask16 read = (__mmask16)(hit & ~bad);
    const __m512 tsdf_prev = _mm512_mask_mov_ps(s->tsdf_prev, read, s->tsdf);
    const __m512 tsdf = _mm512_mask_mov_ps(s->tsdf, read, tsdf_v);
    __mmask16 found = _mm512_mask_cmp_ps_mask(read, tsdf_prev, zero, _CMP_GT_OQ);
    found = _mm512_mask_cmp_ps_mask(found, w, _mm512_set1_ps(c->weight_threshold), _CMP_GE_OQ);
    found = _mm512_mask_cmp_ps_mask(found, tsdf_v, zero, _CMP_LE_OQ);
    /* the lanes that go on: t_prev = t, t += block_size (no block) or max-like(tsdf sdf_trunc, voxel_size) */
    const __mmask16 miss = (__mmask16)(active & ~hit), step = (__mmask16)(read & ~found);
    const __m512 delta = _mm512_mul_ps(tsdf_v, _mm512_set1_ps(c->sdf_trunc));
    const __m512 adv = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(delta, vs, _CMP_LT_OQ), delta, vs);
    const __mmask16 moved = (__mmask16)(miss | step);
    const __m512 t_new = _mm512_add_ps(t, _mm512_mask_blend_ps(miss, adv, bs));
    s->t = _mm512_mask_mov_ps(t, moved, t_new);
    s->t_prev = _mm512_mask_mov_ps(s->t_prev, moved, t);
    s->tsdf_prev = tsdf_prev;
    s->tsdf = tsdf;
    const __mmask16 done = (__mmask16)(bad | found | _mm512_mask_cmp_ps_mask(moved, t_new, s->t_max, _CMP_NLT_UQ));
    if (found) {
        __attribute__((aligned(64))) f32 d[16];
        _mm512_store_ps(d, _mm512_div_ps(_mm512_sub_ps(_mm512_mul_ps(t, tsdf_prev), _mm512_mul_ps(s->t_prev, tsdf)),
                                         _mm512_sub_ps(tsdf_prev, tsdf)));
        for (unsigned int bits = found; bits; bits &= bits - 1) {
            int l = __builtin_ctz(bits);
            c->out[s->pixel[l]] = d[l];
        }
    }
    if (done)
        rc_refill(c, s, done, next, end, &count[1]);
}

/* ------------------------------------------------------------------------------------------ the colour pass */
/* colour_pixel for 16 pixels of a row at a time: the same float32 (and, for a uint16 colour, float64) operations in
 * the same order, a corner skipped by a mask where colour_pixel skips it. A pixel whose voxel coordinates in its
 * block lie outside -1..res (a float rounding far from the origin) goes through colour_pixel itself. */
RC_TARGET static inline __m256 rc_high8(__m512 v) /* lanes 8..15 (AVX-512 F: no vextractf32x8) */
{
    return _mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(v), 1));
}

RC_TARGET static inline __m512 rc_join8(__m256 lo, __m256 hi)
{
    return _mm512_castpd_ps(_mm512_insertf64x4(_mm512_castps_pd(_mm512_castps256_ps512(lo)), _mm256_castps_pd(hi), 1));
}

RC_TARGET static inline __m512i rc_wrap(__m512i v, __m512i res)
{
    v = _mm512_mask_add_epi32(v, _mm512_cmplt_epi32_mask(v, _mm512_setzero_si512()), v, res);
    return _mm512_mask_sub_epi32(v, _mm512_cmpge_epi32_mask(v, res), v, res);
}

/* pixels x0 .. x0 + 15 (those below c_cols) of row y: depth from ``depth`` (the row), colour into ``px`` (the
 * row's colours, 3 per pixel) */
RC_TARGET static void rc_colour16(const ColourCtx *cc, const RcSimd *k, const f32 *depth, Py_ssize_t y, Py_ssize_t x0,
                                  Py_ssize_t c_cols, f32 *px)
{
    const __mmask16 m = (__mmask16)(c_cols - x0 >= 16 ? 0xffff : (1u << (c_cols - x0)) - 1);
    const __m512 zero = _mm512_setzero_ps(), bs = _mm512_set1_ps(cc->block_size), vs = _mm512_set1_ps(cc->vs);
    const __m512 lim = _mm512_set1_ps(1073741824.0f);
    const __m512i ires = _mm512_set1_epi32(k->res);
    const f32 *Rc = cc->Rc, *o = cc->o;
    const __m512 t = _mm512_maskz_loadu_ps(m, depth + x0);
    __mmask16 valid = _mm512_mask_cmp_ps_mask(m, t, zero, _CMP_GT_OQ);
    const f32 dyc = ((f32)y - cc->cy) / cc->fy;
    const __m512 xs = _mm512_cvtepi32_ps(_mm512_add_epi32(_mm512_set1_epi32((int32_t)x0),
                                                          _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12,
                                                                            13, 14, 15)));
    const __m512 dxc = _mm512_div_ps(_mm512_sub_ps(xs, _mm512_set1_ps(cc->cx)), _mm512_set1_ps(cc->fx));
    const __m512 vdyc = _mm512_set1_ps(dyc);
    __m512 g[3];
    __m512i b[3], iv[3];
    __m512 fr[3];
    for (int a = 0; a < 3; a++) {
        const __m512 dir = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(_mm512_set1_ps(Rc[3 * a]), dxc),
                                                       _mm512_mul_ps(_mm512_set1_ps(Rc[3 * a + 1]), vdyc)),
                                         _mm512_set1_ps(Rc[3 * a + 2]));
        const __m512 xg = _mm512_add_ps(_mm512_set1_ps(o[a]), _mm512_mul_ps(t, dir));
        const __m512 q = _mm512_div_ps(xg, bs);
        valid = _mm512_mask_cmp_ps_mask(valid, _mm512_abs_ps(q), lim, _CMP_LT_OQ);
        const __m512 fq = _mm512_roundscale_ps(q, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
        b[a] = _mm512_cvttps_epi32(fq);
        g[a] = _mm512_div_ps(_mm512_sub_ps(xg, _mm512_mul_ps(fq, bs)), vs);
    }
    __mmask16 in;
    const __m512i slot = rc_slot(cc->table, k, valid, b[0], b[1], b[2], &in);
    valid = _mm512_mask_cmpge_epi32_mask(valid, slot, _mm512_setzero_si512());
    __mmask16 safe = valid;
    for (int a = 0; a < 3; a++) {
        const __m512 fl = _mm512_roundscale_ps(g[a], _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
        fr[a] = _mm512_sub_ps(g[a], fl);
        /* -1 <= floor(g) <= res (compared as floats: no integer overflow) */
        safe = _mm512_mask_cmp_ps_mask(safe, fl, _mm512_set1_ps(-1.0f), _CMP_GE_OQ);
        safe = _mm512_mask_cmp_ps_mask(safe, fl, _mm512_set1_ps((f32)k->res), _CMP_LE_OQ);
        iv[a] = _mm512_cvttps_epi32(fl);
    }
    const int u16c = cc->colour->u16, u16w = cc->weight->u16;
    const __m512 one = _mm512_set1_ps(1.0f);
    const __m512 omr[3] = {_mm512_sub_ps(one, fr[0]), _mm512_sub_ps(one, fr[1]), _mm512_sub_ps(one, fr[2])};
    __m512 r_sum = zero, f0 = zero, f1 = zero, f2 = zero;                           /* float32 colour */
    __m512d d0[2] = {_mm512_setzero_pd(), _mm512_setzero_pd()}, d1[2] = {d0[0], d0[1]}, d2[2] = {d0[0], d0[1]};
    for (int c = 0; safe && c < 8; c++) {
        const int dx = c & 1, dy = (c >> 1) & 1, dz = (c >> 2) & 1;
        const __m512i nx = _mm512_add_epi32(iv[0], _mm512_set1_epi32(dx));
        const __m512i ny = _mm512_add_epi32(iv[1], _mm512_set1_epi32(dy));
        const __m512i nz = _mm512_add_epi32(iv[2], _mm512_set1_epi32(dz));
        __mmask16 in = _mm512_mask_cmplt_epu32_mask(safe, nx, ires);
        in = _mm512_mask_cmplt_epu32_mask(in, ny, ires);
        in = _mm512_mask_cmplt_epu32_mask(in, nz, ires);
        __m512i s = slot;
        const __mmask16 out = (__mmask16)(safe & ~in);
        if (out) { /* the neighbouring block: b + (n >= res) - (n < 0) */
            __m512i nb[3];
            const __m512i n3[3] = {nx, ny, nz};
            for (int a = 0; a < 3; a++) {
                nb[a] = _mm512_mask_add_epi32(b[a], _mm512_cmpge_epi32_mask(n3[a], ires), b[a], _mm512_set1_epi32(1));
                nb[a] = _mm512_mask_sub_epi32(nb[a], _mm512_cmplt_epi32_mask(n3[a], _mm512_setzero_si512()), nb[a],
                                              _mm512_set1_epi32(1));
            }
            s = _mm512_mask_mov_epi32(s, out, rc_slot(cc->table, k, out, nb[0], nb[1], nb[2], &in));
        }
        __mmask16 use = _mm512_mask_cmpge_epi32_mask(safe, s, _mm512_setzero_si512());
        use = _mm512_mask_cmplt_epi32_mask(use, s, _mm512_set1_epi32(k->col_slots)); /* else li >= n: skipped */
        const __m512i li = _mm512_add_epi32(
            _mm512_add_epi32(_mm512_mullo_epi32(s, _mm512_set1_epi32(k->res3)),
                             _mm512_mullo_epi32(rc_wrap(nz, ires), _mm512_set1_epi32(k->res2))),
            _mm512_add_epi32(_mm512_mullo_epi32(rc_wrap(ny, ires), ires), rc_wrap(nx, ires)));
        use = _mm512_mask_cmplt_epi32_mask(use, li, _mm512_set1_epi32((int32_t)cc->n_voxels));
        if (u16w) { /* 32 bits ending at weight[li] (starting at it where li = 0) */
            const __mmask16 first = _mm512_cmpeq_epi32_mask(li, _mm512_setzero_si512());
            const __m512i at = _mm512_mask_sub_epi32(li, (__mmask16)~first, li, _mm512_set1_epi32(1));
            __m512i w = _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), use, at, cc->weight->data, 2);
            w = _mm512_mask_mov_epi32(_mm512_srli_epi32(w, 16), first, _mm512_and_si512(w, _mm512_set1_epi32(0xffff)));
            use = _mm512_mask_cmpgt_epu32_mask(use, w, _mm512_setzero_si512());
        } else {
            const __m512 w = _mm512_mask_i32gather_ps(zero, use, li, cc->weight->data, 4);
            use = _mm512_mask_cmp_ps_mask(use, w, zero, _CMP_GT_OQ);
        }
        if (!use)
            continue;
        const __m512 r = _mm512_mul_ps(_mm512_mul_ps(dx ? fr[0] : omr[0], dy ? fr[1] : omr[1]), dz ? fr[2] : omr[2]);
        const __m512i l3 = _mm512_mullo_epi32(li, _mm512_set1_epi32(3));
        if (u16c) { /* colour[3 li] | colour[3 li + 1] << 16, then colour[3 li + 2] in the high half */
            const __m512i a01 = _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), use, l3, cc->colour->data, 2);
            const __m512i a12 = _mm512_mask_i32gather_epi32(_mm512_setzero_si512(), use,
                                                            _mm512_add_epi32(l3, _mm512_set1_epi32(1)),
                                                            cc->colour->data, 2);
            const __m512i ch[3] = {_mm512_and_si512(a01, _mm512_set1_epi32(0xffff)), _mm512_srli_epi32(a01, 16),
                                   _mm512_srli_epi32(a12, 16)};
            __m512d *acc[3] = {d0, d1, d2};
            for (int h = 0; h < 2; h++) {
                const __mmask8 uh = (__mmask8)(use >> (8 * h));
                const __m512d rh = _mm512_cvtps_pd(h ? rc_high8(r) : _mm512_castps512_ps256(r));
                for (int a = 0; a < 3; a++) {
                    const __m256i ci = h ? _mm512_extracti64x4_epi64(ch[a], 1) : _mm512_castsi512_si256(ch[a]);
                    acc[a][h] = _mm512_mask_add_pd(acc[a][h], uh, acc[a][h], _mm512_mul_pd(rh, _mm512_cvtepi32_pd(ci)));
                }
            }
        } else {
            const __m512 c0 = _mm512_mask_i32gather_ps(zero, use, l3, cc->colour->data, 4);
            const __m512 c1 = _mm512_mask_i32gather_ps(zero, use, _mm512_add_epi32(l3, _mm512_set1_epi32(1)),
                                                       cc->colour->data, 4);
            const __m512 c2 = _mm512_mask_i32gather_ps(zero, use, _mm512_add_epi32(l3, _mm512_set1_epi32(2)),
                                                       cc->colour->data, 4);
            f0 = _mm512_mask_add_ps(f0, use, f0, _mm512_mul_ps(r, c0));
            f1 = _mm512_mask_add_ps(f1, use, f1, _mm512_mul_ps(r, c1));
            f2 = _mm512_mask_add_ps(f2, use, f2, _mm512_mul_ps(r, c2));
        }
        r_sum = _mm512_mask_add_ps(r_sum, use, r_sum, r);
    }
    const __mmask16 seen = _mm512_mask_cmp_ps_mask(safe, r_sum, zero, _CMP_GT_OQ);
    const __m512 rs = _mm512_mul_ps(r_sum, _mm512_set1_ps(cc->scale));
    __attribute__((aligned(64))) f32 rgb[3][16];
    if (u16c) {
        __m512d *acc[3] = {d0, d1, d2};
        for (int a = 0; a < 3; a++) {
            const __m256 lo = _mm512_cvtpd_ps(_mm512_div_pd(acc[a][0], _mm512_cvtps_pd(_mm512_castps512_ps256(rs))));
            const __m256 hi = _mm512_cvtpd_ps(_mm512_div_pd(acc[a][1], _mm512_cvtps_pd(rc_high8(rs))));
            _mm512_store_ps(rgb[a], rc_join8(lo, hi));
        }
    } else {
        _mm512_store_ps(rgb[0], _mm512_div_ps(f0, rs));
        _mm512_store_ps(rgb[1], _mm512_div_ps(f1, rs));
        _mm512_store_ps(rgb[2], _mm512_div_ps(f2, rs));
    }
    for (unsigned int bits = m; bits; bits &= bits - 1) {
        const int l = __builtin_ctz(bits);
        f32 *p = px + 3 * (x0 + l);
        if (valid & ~safe & (1u << l))
            colour_pixel(cc, depth[x0 + l], x0 + l, y, p);
        else if (seen & (1u << l)) {
            p[0] = rgb[0][l];
            p[1] = rgb[1][l];
            p[2] = rgb[2][l];
        } else
            p[0] = p[1] = p[2] = 0.0f;
    }
}

#ifndef RC_GROUPS
#define RC_GROUPS 2 /* vectors of 16 rays in flight per thread */
#endif

/* rc_march_band with RC_GROUPS x 16 rays in flight (see the header) */
RC_TARGET static void rc_march_band_simd(const RcCtx *c, const RcSimd *k, Py_ssize_t band, int64_t count[3])
{
    Py_ssize_t next = band * 8 * c->cols, end = (band + 1) * 8 * c->cols;
    RcRays s[RC_GROUPS];
    __mmask16 any = 0;
    for (int g = 0; g < RC_GROUPS; g++) {
        s[g].active = 0;
        s[g].xd = s[g].yd = s[g].zd = s[g].t = s[g].t_max = s[g].t_prev = s[g].tsdf_prev = s[g].tsdf =
            _mm512_setzero_ps();
        rc_refill(c, &s[g], 0xffff, &next, end, &count[1]);
        any |= s[g].active;
    }
    while (any) {
        any = 0;
        for (int g = 0; g < RC_GROUPS; g++)
            if (s[g].active) {
                rc_step(c, k, &s[g], &next, end, count);
                any |= s[g].active;
            }
    }
}
#else
#define RC_HAVE_SIMD 0
static int rc_simd_supported(void)
{
    return 0;
}
#endif

#endif
