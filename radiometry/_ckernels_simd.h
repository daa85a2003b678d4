/* The uint8 correction without per-value memory look-ups, on CPUs with AVX-512 VBMI and GFNI (radiometry/_ckernels.c
 * includes this file; docs/performance.md, "Correction (item 4)").
 *
 * The scalar kernel computes out = table[q + k[c, I]] with two dependent loads per value. Here, per channel c and
 * relative to that channel's part of ``table``, j = q + k_c[I] is a 16-bit integer and the part is non-decreasing
 * in j (radiometry.correction checks it), so ``out = #{m in 1..255 : t_c[m] <= j}`` with t_c[m] the first j whose
 * output reaches m (0xFFFF: never). Both look-ups become register permutes, 64 values at a time:
 *
 * - k_c[I] (16 bits) is two 256-entry byte tables (low, high byte), each two vpermi2b and a blend on bit 7 of I;
 *   the bytes are interleaved into words (vpunpck[lh]bw) and q is added (q was stored once, per Corrector, in
 *   that interleaved order: ``qplan``);
 * - the count is an 8-step binary search of the 255 thresholds, built least-significant bit first: step d
 *   compares j with the threshold of the node reached so far, which is a look-up in a table of 2^d words indexed
 *   by the d bits found (vpermw for d <= 5, vpermi2w for d = 6, two vpermi2w and a blend for d = 7), and sets bit
 *   d. The 8 bits are the count with its bits reversed: packed back to bytes (vpackuswb, the inverse of the
 *   unpack) and reversed with one GF(2) affine transform (vgf2p8affineqb).
 *
 * An RGB block of 64 pixels (192 bytes) is split into three 64-byte planes by vpermi2b and put back the same way.
 * AVX-512 gathers are not used: they were slower than scalar loads on the AMD EPYC this was measured on. The plan
 * per channel (``RM_PLAN_BYTES``) is: k low bytes [256], k high bytes [256], then the thresholds as words: level
 * 0 (1 word, padded to 32), levels 1..5 (32 words each), level 6 (64), level 7 (128). */
#ifndef RADIOMAP_CKERNELS_SIMD_H
#define RADIOMAP_CKERNELS_SIMD_H

#define RM_PLAN_BYTES 1792

#include "_simd_cpu.h"
#if RM_X86_SIMD
#define RM_HAVE_SIMD 1

#define RM_TARGET __attribute__((target("avx512f,avx512bw,avx512vl,avx512vbmi,gfni")))

/* whether this CPU runs the kernel below: AVX-512 F, BW, VL (CPUID.7 ebx bits 16, 30, 31), VBMI and GFNI (ecx 1, 8) */
RM_CPU_CHECK(rm_simd_supported, (1u << 16) | (1u << 30) | (1u << 31), (1u << 1) | (1u << 8))

/* searches side by side (RM_WAY / 2 planes of 64 values): one step's permute-compare-add chain takes ~11 cycles
 * on the EPYC measured, so 8 independent chains keep the vector units busy */
#ifndef RM_WAY
#define RM_WAY 8
#endif
/* one channel's tables, held in registers across a run of blocks */
typedef struct {
    __m512i k[8], t0, t[5], t6[2], t7[4], k2[8];
} rm_tables;

RM_TARGET static inline void rm_load(rm_tables *tb, const uint8_t *plan, int clamp)
{
    const __m512i *p = (const __m512i *)plan;
    for (int i = 0; i < 8; i++) {
        tb->k[i] = _mm512_loadu_si512(p + i);
        tb->k2[i] = clamp ? _mm512_loadu_si512(p + 20 + i) : _mm512_setzero_si512();
    }
    tb->t0 = _mm512_set1_epi16((short)((const uint16_t *)(plan + 512))[0]);
    for (int i = 0; i < 5; i++)
        tb->t[i] = _mm512_loadu_si512(p + 9 + i);
    tb->t6[0] = _mm512_loadu_si512(p + 14);
    tb->t6[1] = _mm512_loadu_si512(p + 15);
    for (int i = 0; i < 4; i++)
        tb->t7[i] = _mm512_loadu_si512(p + 16 + i);
}

/* the counts of thresholds <= j[i] for RM_WAY x 32 words, bits reversed (see the header) */
RM_TARGET static inline void rm_searchn(__m512i j[RM_WAY], const rm_tables *tb)
{
    __mmask32 m[RM_WAY];
    __m512i idx[RM_WAY];
    for (int i = 0; i < RM_WAY; i++) {
        m[i] = _mm512_cmpge_epu16_mask(j[i], tb->t0);
        idx[i] = _mm512_maskz_mov_epi16(m[i], _mm512_set1_epi16(1));
    }
#define RM_STEP(D, THR)                                                                                            \
    for (int i = 0; i < RM_WAY; i++) {                                                                             \
        m[i] = _mm512_cmpge_epu16_mask(j[i], (THR));                                                               \
        idx[i] = _mm512_mask_add_epi16(idx[i], m[i], idx[i], _mm512_set1_epi16(1 << (D)));                         \
    }
    RM_STEP(1, _mm512_permutexvar_epi16(idx[i], tb->t[0]));
    RM_STEP(2, _mm512_permutexvar_epi16(idx[i], tb->t[1]));
    RM_STEP(3, _mm512_permutexvar_epi16(idx[i], tb->t[2]));
    RM_STEP(4, _mm512_permutexvar_epi16(idx[i], tb->t[3]));
    RM_STEP(5, _mm512_permutexvar_epi16(idx[i], tb->t[4]));
    RM_STEP(6, _mm512_permutex2var_epi16(tb->t6[0], idx[i], tb->t6[1]));
    /* level 7: 128 words, two vpermi2w chosen by bit 6 of idx, which is the mask of step 6 */
    RM_STEP(7, _mm512_mask_blend_epi16(m[i], _mm512_permutex2var_epi16(tb->t7[0], idx[i], tb->t7[1]),
                                       _mm512_permutex2var_epi16(tb->t7[2], idx[i], tb->t7[3])));
#undef RM_STEP
    for (int i = 0; i < RM_WAY; i++)
        j[i] = idx[i];
}

/* a 256-entry table of 16-bit values (low bytes in t[0..3], high bytes in t[4..7]) at the 64 bytes x, as the
 * bytes' two halves interleaved (vpunpck[lh]bw order) */
RM_TARGET static inline void rm_lookup16(__m512i x, __mmask64 top, const __m512i *t, __m512i *lo, __m512i *hi)
{
    __m512i l = _mm512_mask_blend_epi8(top, _mm512_permutex2var_epi8(t[0], x, t[1]),
                                       _mm512_permutex2var_epi8(t[2], x, t[3]));
    __m512i h = _mm512_mask_blend_epi8(top, _mm512_permutex2var_epi8(t[4], x, t[5]),
                                       _mm512_permutex2var_epi8(t[6], x, t[7]));
    *lo = _mm512_unpacklo_epi8(l, h);
    *hi = _mm512_unpackhi_epi8(l, h);
}

/* j for 64 values of one channel, in two words vectors (unpack order): q + k1[x], or with ``clamp``
 * min((q + k1[x]) -sat k2[x], 65534) with unsigned saturation (the plan's second form, see the header) */
RM_TARGET static inline __attribute__((always_inline)) void rm_index(__m512i x, const uint16_t *q, const rm_tables *tb,
                                                                    __m512i *j, const int clamp)
{
    __mmask64 top = _mm512_movepi8_mask(x);
    __m512i a, b;
    rm_lookup16(x, top, tb->k, &a, &b);
    if (!clamp) {
        j[0] = _mm512_add_epi16(a, _mm512_loadu_si512(q));
        j[1] = _mm512_add_epi16(b, _mm512_loadu_si512(q + 32));
        return;
    }
    __m512i c, d, cap = _mm512_set1_epi16((short)65534);
    rm_lookup16(x, top, tb->k2, &c, &d);
    j[0] = _mm512_min_epu16(_mm512_subs_epu16(_mm512_adds_epu16(a, _mm512_loadu_si512(q)), c), cap);
    j[1] = _mm512_min_epu16(_mm512_subs_epu16(_mm512_adds_epu16(b, _mm512_loadu_si512(q + 32)), d), cap);
}

/* the count (two words vectors, bits reversed) -> 64 corrected levels */
RM_TARGET static inline __m512i rm_level(const __m512i *idx)
{
    return _mm512_gf2p8affine_epi64_epi8(_mm512_packus_epi16(idx[0], idx[1]),
                                         _mm512_set1_epi64(0x8040201008040201LL), 0); /* reverse the bits */
}

/* one channel's plane function: ``blocks`` x 64 values x (levels) -> y (corrected); the q of block b at
 * q + b * qstride (bytes) */
typedef void (*rm_plane_fn)(const uint8_t *, const uint8_t *, Py_ssize_t, const uint8_t *, uint8_t *, Py_ssize_t);

/* the search's plane functions (q: 64 uint16 per block). RM_WAY / 2 planes at a time; past the last plane, the
 * last run repeats its first plane (written first, then rewritten last). */
#define RM_CHANNEL(NAME, CLAMP)                                                                                    \
    RM_TARGET static void NAME(const uint8_t *x, const uint8_t *q, Py_ssize_t qstride, const uint8_t *plan,         \
                               uint8_t *y, Py_ssize_t blocks)                                                       \
    {                                                                                                              \
        rm_tables tb;                                                                                              \
        rm_load(&tb, plan, CLAMP);                                                                                 \
        for (Py_ssize_t b = 0; b < blocks; b += RM_WAY / 2) {                                                      \
            Py_ssize_t bs[RM_WAY / 2];                                                                             \
            __m512i j[RM_WAY];                                                                                     \
            for (int i = 0; i < RM_WAY / 2; i++) {                                                                 \
                bs[i] = b + i < blocks ? b + i : b;                                                                \
                rm_index(_mm512_loadu_si512(x + 64 * bs[i]), (const uint16_t *)(q + qstride * bs[i]), &tb, j + 2 * i, \
                         CLAMP);                                                                                   \
            }                                                                                                      \
            rm_searchn(j, &tb);                                                                                    \
            for (int i = RM_WAY / 2 - 1; i >= 0; i--)                                                              \
                _mm512_storeu_si512(y + 64 * bs[i], rm_level(j + 2 * i));                                          \
        }                                                                                                          \
    }
RM_CHANNEL(rm_channel_add, 0)
RM_CHANNEL(rm_channel_clamp, 1)

/* byte indices that split 192 interleaved RGB bytes into planes and back (built once) */
static uint8_t rm_split_idx[3][64], rm_split_sel[3][64], rm_join_idx[3][64];
static uint64_t rm_split_mask[3], rm_join_mask[3];

static void rm_simd_init(void)
{
    for (int c = 0; c < 3; c++) {
        rm_split_mask[c] = rm_join_mask[c] = 0;
        for (int i = 0; i < 64; i++) {
            int s = 3 * i + c; /* plane c, lane i <- byte s of the block */
            rm_split_idx[c][i] = (uint8_t)(s & 127);
            rm_split_sel[c][i] = (uint8_t)(s - 128 > 0 ? (s - 128) & 63 : 0);
            if (s >= 128)
                rm_split_mask[c] |= 1ULL << i;
            int b = 64 * c + i, ch = b % 3, p = b / 3; /* output register c, byte i <- plane ch, lane p */
            rm_join_idx[c][i] = (uint8_t)((ch == 1 ? 64 : 0) + p);
            if (ch == 2)
                rm_join_mask[c] |= 1ULL << i;
        }
    }
}

#define RM_RUN 16 /* blocks split into planes at a time (3 KB in, 3 KB out: in L1) */

/* Corrects the first ``blocks`` * 64 pixels: img/out interleaved (``channels`` 1 or 3) through fn[c], the plane
 * function of channel c, with plan + c * plan_bytes; qplan: per block and channel, ``qbytes`` bytes. Three channels
 * go through planes a run of blocks at a time, so that each channel's tables stay in registers across the run. */
RM_TARGET static void rm_planes(const uint8_t *img, const uint8_t *qplan, Py_ssize_t qbytes, const uint8_t *plan,
                                Py_ssize_t plan_bytes, uint8_t *out, Py_ssize_t blocks, int channels,
                                const rm_plane_fn *fn)
{
    if (channels == 1) {
        fn[0](img, qplan, qbytes, plan, out, blocks);
        return;
    }
    uint8_t xs[3][RM_RUN * 64], ys[3][RM_RUN * 64];
    __m512i si[3], ss[3], ji[3];
    for (int c = 0; c < 3; c++) {
        si[c] = _mm512_loadu_si512(rm_split_idx[c]);
        ss[c] = _mm512_loadu_si512(rm_split_sel[c]);
        ji[c] = _mm512_loadu_si512(rm_join_idx[c]);
    }
    for (Py_ssize_t b0 = 0; b0 < blocks; b0 += RM_RUN) {
        Py_ssize_t run = blocks - b0 < RM_RUN ? blocks - b0 : RM_RUN;
        for (Py_ssize_t b = 0; b < run; b++) {
            const uint8_t *src = img + 192 * (b0 + b);
            __m512i a0 = _mm512_loadu_si512(src), a1 = _mm512_loadu_si512(src + 64), a2 = _mm512_loadu_si512(src + 128);
            for (int c = 0; c < 3; c++) {
                __m512i x = _mm512_permutex2var_epi8(a0, si[c], a1);
                _mm512_storeu_si512(xs[c] + 64 * b, _mm512_mask_permutexvar_epi8(x, rm_split_mask[c], ss[c], a2));
            }
        }
        for (int c = 0; c < 3; c++)
            fn[c](xs[c], qplan + (3 * b0 + c) * qbytes, 3 * qbytes, plan + plan_bytes * c, ys[c], run);
        for (Py_ssize_t b = 0; b < run; b++) {
            __m512i p0 = _mm512_loadu_si512(ys[0] + 64 * b), p1 = _mm512_loadu_si512(ys[1] + 64 * b);
            __m512i p2 = _mm512_loadu_si512(ys[2] + 64 * b);
            for (int c = 0; c < 3; c++) {
                __m512i y = _mm512_permutex2var_epi8(p0, ji[c], p1);
                y = _mm512_mask_permutexvar_epi8(y, rm_join_mask[c], ji[c], p2);
                _mm512_storeu_si512(out + 192 * (b0 + b) + 64 * c, y);
            }
        }
    }
}

/* the binary search on the first ``blocks`` * 64 pixels: qplan (blocks, channels, 64) uint16, plan (channels,
 * RM_PLAN_BYTES) */
static void rm_correct_simd(const uint8_t *img, const uint16_t *qplan, const uint8_t *plan, uint8_t *out,
                            Py_ssize_t blocks, int channels, int clamp)
{
    rm_plane_fn f = clamp ? rm_channel_clamp : rm_channel_add;
    const rm_plane_fn fn[3] = {f, f, f};
    rm_planes(img, (const uint8_t *)qplan, 128, plan, RM_PLAN_BYTES, out, blocks, channels, fn);
}
#else
#define RM_HAVE_SIMD 0
static int rm_simd_supported(void)
{
    return 0;
}
static void rm_simd_init(void)
{
}
#endif

#endif
