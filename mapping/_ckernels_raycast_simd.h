/* The ray cast's march with AVX-512 (mapping/_ckernels.c includes this file after rc_march_band, the scalar march;
 * docs/performance.md, "The ray cast's march with AVX-512").
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
 * would read past its end) are looked up in scalar code instead, as the scalar march does. */
#ifndef RADIOMAP_CKERNELS_RAYCAST_SIMD_H
#define RADIOMAP_CKERNELS_RAYCAST_SIMD_H

#include "../radiometry/_simd_cpu.h"

#if RM_X86_SIMD
#define RC_HAVE_SIMD 1
#define RC_TARGET __attribute__((target("avx512f")))

/* AVX-512 F (CPUID.7 ebx bit 16), detected once; a race writes the same value */
static int rc_simd_supported(void)
{
    static int cached = -1;
    if (cached < 0)
        cached = rm_cpu_avx512(1u << 16, 0);
    return cached;
}

/* the march's constants in 32-bit form (rc_simd_setup) */
typedef struct {
    int32_t lo[3], n[3], kb[6], res, res2, res3, slot_cap, v_cap, n32, w_last;
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
    return 1;
}

/* 16 rays in flight: their state as vectors, their pixels */
typedef struct {
    __m512 xd, yd, zd, t, t_max, t_prev, tsdf_prev, tsdf;
    __mmask16 active;
    Py_ssize_t pixel[16];
} RcRays;

/* the band's next pixel that has a range, started in lane ``l`` of the start arrays (the scalar march's start);
 * 0 when the band has none left */
static inline int rc_start(const RcCtx *c, Py_ssize_t *next, Py_ssize_t end, Py_ssize_t *pixel, f32 init[5][16],
                           int l, int64_t *rays)
{
    const f32 *Rc = c->Rc, *o = c->o;
    const Py_ssize_t cols = c->cols;
    while (*next < end) {
        Py_ssize_t p = (*next)++, y = p / cols, x = p % cols;
        c->out[p] = 0.0f;
        const f32 *r = c->range + 2 * ((y / 8) * c->w_down + x / 8);
        if (r[0] >= r[1])
            continue;
        ++*rays;
        f32 xc = ((f32)x - c->cx) * 1.0f / c->fx, yc = ((f32)y - c->cy) * 1.0f / c->fy, zc = 1.0f;
        init[0][l] = (xc * Rc[0] + yc * Rc[1] + zc * Rc[2] + o[0]) - o[0];
        init[1][l] = (xc * Rc[3] + yc * Rc[4] + zc * Rc[5] + o[1]) - o[1];
        init[2][l] = (xc * Rc[6] + yc * Rc[7] + zc * Rc[8] + o[2]) - o[2];
        init[3][l] = r[0];
        init[4][l] = r[1];
        *pixel = p;
        return 1;
    }
    return 0;
}

/* lanes ``m`` take new pixels (the others keep theirs); lanes that find none go idle */
RC_TARGET static inline void rc_refill(const RcCtx *c, RcRays *s, __mmask16 m, Py_ssize_t *next, Py_ssize_t end,
                                       int64_t *rays)
{
    __attribute__((aligned(64))) f32 init[5][16];
    __mmask16 started = 0;
    for (unsigned int bits = m; bits; bits &= bits - 1) {
        int l = __builtin_ctz(bits);
        if (rc_start(c, next, end, &s->pixel[l], init, l, rays))
            started |= (__mmask16)(1u << l);
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
    const __m512i jx = _mm512_sub_epi32(bx, _mm512_set1_epi32(k->lo[0]));
    const __m512i jy = _mm512_sub_epi32(by, _mm512_set1_epi32(k->lo[1]));
    const __m512i jz = _mm512_sub_epi32(bz, _mm512_set1_epi32(k->lo[2]));
    __mmask16 intab = _mm512_mask_cmplt_epu32_mask(inr, jx, _mm512_set1_epi32(k->n[0]));
    intab = _mm512_mask_cmplt_epu32_mask(intab, jy, _mm512_set1_epi32(k->n[1]));
    intab = _mm512_mask_cmplt_epu32_mask(intab, jz, _mm512_set1_epi32(k->n[2]));
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
    const __m512i tidx = _mm512_add_epi32(
        _mm512_mullo_epi32(_mm512_add_epi32(_mm512_mullo_epi32(jx, _mm512_set1_epi32(k->n[1])), jy),
                           _mm512_set1_epi32(k->n[2])),
        jz);
    const __m512i slot = _mm512_mask_i32gather_epi32(_mm512_set1_epi32(-1), intab, tidx, c->table->index, 4);
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
