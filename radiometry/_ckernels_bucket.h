/* The uint8 correction's bucket kernel: fewer vector operations than the binary search of _ckernels_simd.h, for
 * the tables whose thresholds are spread out (radiometry/_ckernels.c includes this file after _ckernels_simd.h;
 * radiometry.correction._build_bucket_plan builds its data and decides where it applies; docs/performance.md,
 * "Correction (item 4)").
 *
 * As in _ckernels_simd.h the output of channel c is ``#{m in 1..255 : t_c[m] <= j}`` with j = q + k_c[I], but the
 * index is moved and scaled first, ``j' = (j - S) << s`` (per channel: S and s chosen by the plan, so that the
 * thresholds that matter fall in 0..65535, as far apart as 16 bits allow and with few per bucket), and computed as
 * two byte planes, 64 values per register: lo = ql + kl, hi = qh + kh + carry (q stored as ``q << s`` in two byte
 * planes, k as ``(k - S) << s`` in two 256-entry byte tables, each looked up with two vpermi2b and a blend). The
 * count is then
 *
 *     base[hi] + #{i : lo > L_i[hi]}
 *
 * with base[b] the thresholds at or below 256 b and L_i[b] the i-th threshold inside bucket b (256 b, 256 b + 256)
 * minus 256 b + 1 (255: none; a threshold at a multiple of 256 belongs to base). base and L_1 are 256-entry byte
 * tables; L_2..L_n, which are 255 except in the buckets holding two or more thresholds, are 128-entry tables over
 * the window of buckets w0..w0+127 that holds those (one vpermi2b, the compare masked off outside the window;
 * w0 = 128 needs no extra mask: the window is hi's top bit). n, the most thresholds in one bucket, is at most
 * RM_BK_NMAX; the plan falls back to _ckernels_simd.h's search otherwise. Per 64 values of a channel: 17 + 2 (n - 1)
 * shuffles and compares with the RGB split and join (the search: ~45), no 16-bit lanes, no bit reversal.
 *
 * The clamped form (``clamp``, when j' leaves 0..65535: long tables) computes the carry out of the 16-bit sum too:
 * levels below ``neg`` have k below S (stored + 65536) and a sum without carry is below 0 (count ``under``); the
 * others overflow with a carry (count ``over``, every reachable threshold). k is non-decreasing in I (checked by
 * the plan), so the levels below S are those below ``neg``.
 *
 * Three channels: each channel's pass over a run of RM_RUN blocks splits its plane out of the interleaved pixels
 * itself (two vpermi2b); channels 0 and 1 leave their outputs in two plane buffers, channel 2 interleaves them with
 * its own into the output (one store per output register). The loop is software-pipelined: the index (hi, lo) of
 * block b + 1 is computed beside the count of block b, two dependency chains in flight (9 % faster than one).
 *
 * Plan per channel (RM_BK_PLAN_BYTES): k low bytes [256], k high bytes [256], base [256], L_1 [256], L_2..L_NMAX
 * [128 each], then n, w0, clamp, neg, under, over. */
#ifndef RADIOMAP_CKERNELS_BUCKET_H
#define RADIOMAP_CKERNELS_BUCKET_H

#define RM_BK_NMAX 12
#define RM_BK_PARAMS (1024 + 128 * (RM_BK_NMAX - 1))
#define RM_BK_PLAN_BYTES (RM_BK_PARAMS + 64)

#if RM_HAVE_SIMD

/* where one channel's pass reads and writes */
typedef struct {
    const uint8_t *img;       /* the run's pixels: interleaved (channel >= 0) or one plane (-1) */
    uint8_t *out;             /* the run's output: interleaved (channel 2), else a plane */
    const uint8_t *ys0, *ys1; /* channel 2: the planes of channels 0 and 1 */
    int channel;              /* -1: one channel; else 0, 1, 2 of three */
} rm_io;

/* one channel over ``blocks`` blocks of 64 pixels; q of block b at q + b * qstride: 64 low bytes then 64 high
 * bytes. N (thresholds per bucket), CLAMP and the channel's role are constants of each instance. */
RM_TARGET static inline __attribute__((always_inline)) void rm_bk_pass(const rm_io *io, const uint8_t *q,
                                                                     Py_ssize_t qstride, const uint8_t *plan,
                                                                     Py_ssize_t blocks, const int N,
                                                                     const int CLAMP, const int CH)
{
#define RM_T(i) _mm512_loadu_si512(plan + 64 * (i))
    const uint8_t *par = plan + RM_BK_PARAMS;
    const __m512i one = _mm512_set1_epi8(1), top = _mm512_set1_epi8((char)0x80);
    const __m512i w0 = _mm512_set1_epi8((char)par[1]), neg = _mm512_set1_epi8((char)par[3]);
    const __m512i under = _mm512_set1_epi8((char)par[4]), over = _mm512_set1_epi8((char)par[5]);
    const int top_window = par[1] == 128;
    __m512i si = _mm512_setzero_si512(), ss = si, jx[3] = {si, si, si};
    __mmask64 sm = 0, jm[3] = {0, 0, 0};
    if (CH >= 0) {
        si = _mm512_loadu_si512(rm_split_idx[CH]);
        ss = _mm512_loadu_si512(rm_split_sel[CH]);
        sm = rm_split_mask[CH];
    }
    if (CH == 2)
        for (int r = 0; r < 3; r++) {
            jx[r] = _mm512_loadu_si512(rm_join_idx[r]);
            jm[r] = rm_join_mask[r];
        }
    __m512i t[16]; /* k, base and L_1 stay in registers; L_2.. are read as memory operands */
    for (int i = 0; i < 16; i++)
        t[i] = RM_T(i);
#define RM_FRONT(B, LO, HI, HT, LOW, HIGH)                                                                         \
    do {                                                                                                           \
        __m512i xv;                                                                                                \
        if (CH < 0)                                                                                                \
            xv = _mm512_loadu_si512(io->img + 64 * (B));                                                           \
        else {                                                                                                     \
            const uint8_t *src = io->img + 192 * (B);                                                              \
            xv = _mm512_permutex2var_epi8(_mm512_loadu_si512(src), si, _mm512_loadu_si512(src + 64));               \
            xv = _mm512_mask_permutexvar_epi8(xv, sm, ss, _mm512_loadu_si512(src + 128));                          \
        }                                                                                                          \
        __m512i ql = _mm512_loadu_si512(q + qstride * (B)), qh = _mm512_loadu_si512(q + qstride * (B) + 64);      \
        __mmask64 xt = _mm512_movepi8_mask(xv);                                                                    \
        __m512i kl = _mm512_mask_blend_epi8(xt, _mm512_permutex2var_epi8(t[0], xv, t[1]),                          \
                                            _mm512_permutex2var_epi8(t[2], xv, t[3]));                             \
        __m512i kh = _mm512_mask_blend_epi8(xt, _mm512_permutex2var_epi8(t[4], xv, t[5]),                          \
                                            _mm512_permutex2var_epi8(t[6], xv, t[7]));                             \
        LO = _mm512_add_epi8(ql, kl);                                                                              \
        __mmask64 c1 = _mm512_cmplt_epu8_mask(LO, ql);                                                             \
        __m512i hs = _mm512_add_epi8(qh, kh);                                                                      \
        HI = _mm512_mask_add_epi8(hs, c1, hs, one);                                                                \
        if (CLAMP) {                                                                                               \
            __mmask64 carry = _mm512_cmplt_epu8_mask(hs, qh)                                                       \
                              | _mm512_mask_cmpeq_epi8_mask(c1, HI, _mm512_setzero_si512());                       \
            __mmask64 below = _mm512_cmplt_epu8_mask(xv, neg);                                                     \
            LOW = below & ~carry;                                                                                  \
            HIGH = carry & ~below;                                                                                 \
        }                                                                                                          \
        HT = _mm512_movepi8_mask(HI);                                                                              \
    } while (0)
    __m512i lo = _mm512_setzero_si512(), hi = lo;
    __mmask64 ht = 0, low = 0, high = 0;
    if (blocks > 0)
        RM_FRONT(0, lo, hi, ht, low, high);
    for (Py_ssize_t b = 0; b < blocks; b++) {
        const uint8_t *pw = plan + 1024;
        __asm__("" : "+r"(pw)); /* keeps L_2.. out of registers (spilling the others costs more) */
        __m512i lo_n = lo, hi_n = hi;
        __mmask64 ht_n = ht, low_n = low, high_n = high;
        if (b + 1 < blocks) /* the next block's index, beside this block's count: two chains in flight */
            RM_FRONT(b + 1, lo_n, hi_n, ht_n, low_n, high_n);
        __m512i c = _mm512_mask_blend_epi8(ht, _mm512_permutex2var_epi8(t[8], hi, t[9]),
                                           _mm512_permutex2var_epi8(t[10], hi, t[11]));
        if (N >= 1) {
            __m512i l1 = _mm512_mask_blend_epi8(ht, _mm512_permutex2var_epi8(t[12], hi, t[13]),
                                                _mm512_permutex2var_epi8(t[14], hi, t[15]));
            c = _mm512_mask_add_epi8(c, _mm512_cmpgt_epu8_mask(lo, l1), c, one);
        }
        if (N >= 2) {
            __m512i idx = top_window ? hi : _mm512_sub_epi8(hi, w0);
            __mmask64 in = top_window ? ht : _mm512_testn_epi8_mask(idx, top); /* bucket in the window */
#pragma GCC unroll 12
            for (int i = 0; i < N - 1; i++) {
                __m512i li = _mm512_permutex2var_epi8(_mm512_loadu_si512(pw + 128 * i), idx,
                                                      _mm512_loadu_si512(pw + 128 * i + 64));
                c = _mm512_mask_add_epi8(c, _mm512_mask_cmpgt_epu8_mask(in, lo, li), c, one);
            }
        }
        if (CLAMP) {
            c = _mm512_mask_mov_epi8(c, low, under);
            c = _mm512_mask_mov_epi8(c, high, over);
        }
        if (CH < 2)
            _mm512_storeu_si512(io->out + 64 * b, c);
        else {
            __m512i p0 = _mm512_loadu_si512(io->ys0 + 64 * b), p1 = _mm512_loadu_si512(io->ys1 + 64 * b);
            for (int r = 0; r < 3; r++)
                _mm512_storeu_si512(io->out + 192 * b + 64 * r,
                                    _mm512_mask_permutexvar_epi8(_mm512_permutex2var_epi8(p0, jx[r], p1), jm[r],
                                                                 jx[r], c));
        }
        lo = lo_n, hi = hi_n, ht = ht_n, low = low_n, high = high_n;
    }
#undef RM_FRONT
#undef RM_T
}

typedef void (*rm_bk_fn)(const rm_io *, const uint8_t *, Py_ssize_t, const uint8_t *, Py_ssize_t);

/* the instances: N = 0..RM_BK_NMAX, CLAMP 0/1, and the role (one channel; channel 0 or 1 of three; channel 2) */
#define RM_BK_FN(N, CLAMP, ROLE, CH)                                                                               \
    RM_TARGET static void rm_bk_##N##_##CLAMP##_##ROLE(const rm_io *io, const uint8_t *q, Py_ssize_t qs,           \
                                                       const uint8_t *pl, Py_ssize_t blocks)                       \
    {                                                                                                              \
        rm_bk_pass(io, q, qs, pl, blocks, N, CLAMP, CH);                                  \
    }
#define RM_BK_ROLES(N, CLAMP) RM_BK_FN(N, CLAMP, 0, -1) RM_BK_FN(N, CLAMP, 1, 0) RM_BK_FN(N, CLAMP, 2, 1)            \
    RM_BK_FN(N, CLAMP, 3, 2)
#define RM_BK_FNS(N) RM_BK_ROLES(N, 0) RM_BK_ROLES(N, 1)
RM_BK_FNS(0) RM_BK_FNS(1) RM_BK_FNS(2) RM_BK_FNS(3) RM_BK_FNS(4) RM_BK_FNS(5) RM_BK_FNS(6) RM_BK_FNS(7) RM_BK_FNS(8)
RM_BK_FNS(9) RM_BK_FNS(10) RM_BK_FNS(11) RM_BK_FNS(12)
#define RM_BK_SET(N, CLAMP) {rm_bk_##N##_##CLAMP##_0, rm_bk_##N##_##CLAMP##_1, rm_bk_##N##_##CLAMP##_2,                \
                             rm_bk_##N##_##CLAMP##_3}
#define RM_BK_PAIR(N) {RM_BK_SET(N, 0), RM_BK_SET(N, 1)}
static const rm_bk_fn rm_bk_fns[RM_BK_NMAX + 1][2][4] = {
    RM_BK_PAIR(0),  RM_BK_PAIR(1),  RM_BK_PAIR(2),  RM_BK_PAIR(3),  RM_BK_PAIR(4),  RM_BK_PAIR(5),
    RM_BK_PAIR(6),  RM_BK_PAIR(7),  RM_BK_PAIR(8),  RM_BK_PAIR(9),  RM_BK_PAIR(10), RM_BK_PAIR(11),
    RM_BK_PAIR(12)};

/* Corrects the first ``blocks`` * 64 pixels: img/out interleaved (``channels`` 1 or 3), qplan (blocks, channels,
 * 128) uint8, plan (channels, RM_BK_PLAN_BYTES), each channel's n at most RM_BK_NMAX (checked by the caller). */
RM_TARGET static void rm_bk_correct(const uint8_t *img, const uint8_t *qplan, const uint8_t *plan, uint8_t *out,
                                    Py_ssize_t blocks, int channels)
{
    const uint8_t *par = plan + RM_BK_PARAMS;
    if (channels == 1) {
        rm_io io = {img, out, NULL, NULL, -1};
        rm_bk_fns[par[0]][par[2] ? 1 : 0][0](&io, qplan, 128, plan, blocks);
        return;
    }
    uint8_t ys[2][RM_RUN * 64];
    for (Py_ssize_t b0 = 0; b0 < blocks; b0 += RM_RUN) {
        Py_ssize_t run = blocks - b0 < RM_RUN ? blocks - b0 : RM_RUN;
        for (int c = 0; c < 3; c++) {
            const uint8_t *pc = par + c * RM_BK_PLAN_BYTES;
            rm_io io = {img + 192 * b0, c < 2 ? ys[c] : out + 192 * b0, ys[0], ys[1], c};
            rm_bk_fns[pc[0]][pc[2] ? 1 : 0][c + 1](&io, qplan + (3 * b0 + c) * 128, 384,
                                                   plan + RM_BK_PLAN_BYTES * c, run);
        }
    }
}
#endif

#endif
