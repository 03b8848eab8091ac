/* The inner loop of the matching cost (_window_cost.pxd), many windows at once: for a batch of
 * (window, source) pairs, one per vector lane, the weighted sums of the window's bilinear samples
 * warped into the source image by the lane's homography (sum w s, sum w s^2, sum w s v).
 *
 * One kernel for every window, inside its source or across its border: each sample's position is
 * clamped to the image (positions past the border read the border's texels, NaN reads texel 0),
 * which leaves a window inside the image unchanged, so no inside test is needed before matching;
 * a lane whose sample falls behind the source camera is flagged (its cost is MAX_COST).
 *
 * Every path computes each sample with the same IEEE single-precision operations in the same
 * order, multiply-adds fused explicitly (fmaf in the scalar path, FMA instructions in the vector
 * paths; -ffp-contract=off keeps the compiler from fusing any other), so the sums are the same bit
 * for bit on every path and every machine: fmaf and the FMA instructions round once, as IEEE 754
 * defines. The AVX2 and AVX-512 paths are compiled with per-function target attributes and chosen
 * at run time (dvpmvs_simd_select), so that one build runs on every x86-64 CPU. Texels are read as
 * pairs of adjacent floats: by scalar 64-bit loads and transposes in the AVX2 path (on the AMD
 * EPYC measured, hardware gathers of single floats took 1.6-2x as long), by 64-bit gathers in the
 * AVX-512 path.
 * dvpmvs_window_sums is the scalar path of one window, which the kernels of _window_cost.pxd call.
 *
 * The caller guarantees that the stack of images holds fewer than 2^31 - 2 floats (indices are
 * 32-bit in the vector paths).
 */
#ifndef DVPMVS_WINDOW_COST_SIMD_H
#define DVPMVS_WINDOW_COST_SIMD_H

#include <math.h>
#include <stddef.h>
#include <stdint.h>

#define DVPMVS_SLOTS 8          /* windows of a table */
#define DVPMVS_SLOT_SAMPLES 256 /* samples of a window, at most */
#define DVPMVS_BATCH 16         /* lanes of a batch */

/* Up to DVPMVS_SLOTS windows' samples, transposed: sample k of window (slot) l at [k][l]. A
 * window with fewer samples than ``n`` is padded with weight 0, value 0 and its last sample's
 * position: w s = 0 adds nothing to any sum (the images are finite). */
typedef struct {
    int n;
    float x[DVPMVS_SLOT_SAMPLES][DVPMVS_SLOTS];
    float y[DVPMVS_SLOT_SAMPLES][DVPMVS_SLOTS];
    float w[DVPMVS_SLOT_SAMPLES][DVPMVS_SLOTS];
    float v[DVPMVS_SLOT_SAMPLES][DVPMVS_SLOTS];
} dvpmvs_windows;

/* A batch of (window, source) pairs: lane l matches window ``slot[l]`` of a table in the source
 * image of ``width[l]`` x ``height[l]`` that starts at ``offset[l]`` floats into the stack,
 * through the homography H[.][l]. */
typedef struct {
    int count;
    int32_t slot[DVPMVS_BATCH];
    int32_t offset[DVPMVS_BATCH];
    int32_t width[DVPMVS_BATCH];
    int32_t height[DVPMVS_BATCH];
    float H[9][DVPMVS_BATCH];
} dvpmvs_batch;

/* Up to 16 windows' weighted sums and reference statistics, for the NCC of _ncc_from_sums. */
typedef struct {
    int count;
    float sum_w[16], mean[16], var[16];
    float sws[16], swss[16], swrs[16];
} dvpmvs_sums;

enum { DVPMVS_SIMD_SCALAR = 0, DVPMVS_SIMD_AVX2 = 1, DVPMVS_SIMD_AVX512 = 2 };

static int dvpmvs_simd_level = DVPMVS_SIMD_SCALAR;

/* The float thresholds that compare as the kernels' double constants do: (double)x < 1e-7 is
 * x < dvpmvs_var_min, (double)x <= 1e-8 is x <= dvpmvs_front_max. */
static float dvpmvs_var_min;
static float dvpmvs_front_max;

static void dvpmvs_thresholds(void)
{
    float t = (float)1e-7;
    if ((double)t < 1e-7)
        t = nextafterf(t, 1.0f);
    dvpmvs_var_min = t;
    t = (float)1e-8;
    if ((double)t > 1e-8)
        t = nextafterf(t, 0.0f);
    dvpmvs_front_max = t;
}

/* The bilinear sample at (x, y) warped by H, clamped to the image (the vector paths' operations:
 * max(a, b) is a > b ? a : b, min(a, b) a < b ? a : b, as the instructions define them, NaN
 * included); *behind set when the point is behind the source camera. The 2x2 texels read are
 * those at (x0, y0) to (x0 + 1, y0 + 1) with x0 at most width - 2 (then the weight of the last
 * column is 1), so every read stays inside the image (at least 2x2). */
static inline float dvpmvs_sample(const float *img, int stride, int width, int height, const float *H, float x,
                                  float y, int *behind)
{
    float hz = fmaf(H[6], x, fmaf(H[7], y, H[8]));
    float nx = fmaf(H[0], x, fmaf(H[1], y, H[2]));
    float ny = fmaf(H[3], x, fmaf(H[4], y, H[5]));
    float r = 1.0f / hz, right = (float)(width - 1), bottom = (float)(height - 1);
    float hx = nx * r, hy = ny * r;
    int x0, y0;
    float ax, ay, t00, t01, t10, t11, top, low;
    const float *row;
    *behind |= hz <= dvpmvs_front_max;
    hx = hx > 0.0f ? hx : 0.0f;
    hx = hx < right ? hx : right;
    hy = hy > 0.0f ? hy : 0.0f;
    hy = hy < bottom ? hy : bottom;
    x0 = (int)hx < width - 2 ? (int)hx : width - 2;
    y0 = (int)hy < height - 2 ? (int)hy : height - 2;
    ax = hx - (float)x0;
    ay = hy - (float)y0;
    row = img + (ptrdiff_t)y0 * stride + x0;
    t00 = row[0];
    t01 = row[1];
    t10 = row[stride];
    t11 = row[stride + 1];
    top = fmaf(ax, t01 - t00, t00);
    low = fmaf(ax, t11 - t10, t10);
    return fmaf(ay, low - top, top);
}

/* The sums of one window of n samples (x, y, weight w, reference value v, each ``step`` floats
 * apart) warped by H into an image; returns 1 when a sample falls behind the source camera. */
static inline int dvpmvs_window_sums(const float *img, int stride, int width, int height, const float *H,
                                     const float *x, const float *y, const float *w, const float *v, int n, int step,
                                     float *sws, float *swss, float *swrs)
{
    float a = 0, b = 0, c = 0;
    int k, behind = 0;
    for (k = 0; k < n; k++) {
        float s = dvpmvs_sample(img, stride, width, height, H, x[k * step], y[k * step], &behind);
        float ws = w[k * step] * s;
        a = a + ws;
        b = fmaf(ws, s, b);
        c = fmaf(ws, v[k * step], c);
    }
    *sws = a;
    *swss = b;
    *swrs = c;
    return behind;
}

/* Bit l of the result set when a sample of lane l falls behind its source camera. */
static uint32_t dvpmvs_batch_sums_scalar(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                                         float *sws, float *swss, float *swrs)
{
    uint32_t behind = 0;
    int l, i;
    for (l = 0; l < B->count; l++) {
        float H[9];
        int m = B->slot[l];
        for (i = 0; i < 9; i++)
            H[i] = B->H[i][l];
        behind |= (uint32_t)dvpmvs_window_sums(stack + B->offset[l], stride, B->width[l], B->height[l], H, &T->x[0][m],
                                               &T->y[0][m], &T->w[0][m], &T->v[0][m], T->n, DVPMVS_SLOTS, &sws[l],
                                               &swss[l], &swrs[l]) << l;
    }
    return behind;
}

/* The portable counterpart of dvpmvs_ncc_avx2 (same results). */
static void dvpmvs_ncc_scalar(const dvpmvs_sums *S, float *out)
{
    int l;
    for (l = 0; l < S->count; l++) {
        float mean_s = S->sws[l] / S->sum_w[l];
        float var_s = S->swss[l] / S->sum_w[l] - mean_s * mean_s;
        float cov, denom, s;
        if (S->var[l] < 1e-7 || var_s < 1e-7) {
            out[l] = 2.0f;
            continue;
        }
        cov = S->swrs[l] / S->sum_w[l] - S->mean[l] * mean_s;
        denom = (float)sqrt((double)(S->var[l] * var_s));
        s = (float)(1.0 - (double)(cov / denom));
        out[l] = s < 0 ? 0.0f : (s > 2.0f ? 2.0f : s);
    }
}

#if (defined(__x86_64__) || defined(_M_X64)) && (defined(__GNUC__) || defined(__clang__))
#define DVPMVS_HAVE_X86_SIMD 1
#include <immintrin.h>

/* The texel pairs (p, p + 1) of two lanes as one 128-bit vector. */
#define DVPMVS_PAIRS(p, q) _mm_loadh_pi(_mm_castpd_ps(_mm_load_sd((const double *)(p))), (const __m64 *)(q))

/* Lanes l0..l0+7 of a batch, dvpmvs_window_sums's operations lane by lane, in two passes: the
 * clamped positions of all samples first (no memory lookups: many samples in flight), then the
 * texels, read as pairs of adjacent floats, and the sums. */
__attribute__((target("avx2,fma"))) static uint32_t
dvpmvs_batch_sums_avx2_8(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B, int l0,
                         float *sws, float *swss, float *swrs)
{
    /* lanes l0..l0+7 are filled (dvpmvs_batch_pad), and sws, swss and swrs hold them all */
    int k, count = B->count - l0 < 8 ? B->count - l0 : 8;
    int32_t at[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    float fxs[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    float fys[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    __m256 h[9];
    for (k = 0; k < 9; k++)
        h[k] = _mm256_loadu_ps(&B->H[k][l0]);
    const __m256i vslot = _mm256_loadu_si256((const __m256i *)&B->slot[l0]);
    const __m256i voffset = _mm256_loadu_si256((const __m256i *)&B->offset[l0]);
    const __m256i vwidth = _mm256_loadu_si256((const __m256i *)&B->width[l0]);
    const __m256i vheight = _mm256_loadu_si256((const __m256i *)&B->height[l0]);
    const __m256i one_i = _mm256_set1_epi32(1), two_i = _mm256_set1_epi32(2), vstride = _mm256_set1_epi32(stride);
    const __m256i last_x = _mm256_sub_epi32(vwidth, two_i), last_y = _mm256_sub_epi32(vheight, two_i);
    const __m256 right = _mm256_cvtepi32_ps(_mm256_sub_epi32(vwidth, one_i));
    const __m256 bottom = _mm256_cvtepi32_ps(_mm256_sub_epi32(vheight, one_i));
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), front = _mm256_set1_ps(dvpmvs_front_max);
    const float *below = stack + stride;
    __m256 a = zero, b = zero, c = zero, behind = zero;
    for (k = 0; k < T->n; k++) {
        __m256 x = _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->x[k]), vslot);
        __m256 y = _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->y[k]), vslot);
        __m256 hz = _mm256_fmadd_ps(h[6], x, _mm256_fmadd_ps(h[7], y, h[8]));
        __m256 nx = _mm256_fmadd_ps(h[0], x, _mm256_fmadd_ps(h[1], y, h[2]));
        __m256 ny = _mm256_fmadd_ps(h[3], x, _mm256_fmadd_ps(h[4], y, h[5]));
        __m256 r = _mm256_div_ps(one, hz);
        __m256 hx = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(nx, r), zero), right);
        __m256 hy = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(ny, r), zero), bottom);
        __m256i x0 = _mm256_min_epi32(_mm256_cvttps_epi32(hx), last_x);
        __m256i y0 = _mm256_min_epi32(_mm256_cvttps_epi32(hy), last_y);
        behind = _mm256_or_ps(behind, _mm256_cmp_ps(hz, front, _CMP_LE_OQ));
        _mm256_store_ps(fxs[k], _mm256_sub_ps(hx, _mm256_cvtepi32_ps(x0)));
        _mm256_store_ps(fys[k], _mm256_sub_ps(hy, _mm256_cvtepi32_ps(y0)));
        _mm256_store_si256((__m256i *)at[k], _mm256_add_epi32(_mm256_add_epi32(voffset, _mm256_mullo_epi32(y0, vstride)), x0));
    }
    for (k = 0; k < T->n; k++) {
        /* each pair read through base + index addressing as soon as its index is loaded, so
         * that no lane's addresses stay live across the others' (they spilled to the stack) */
        const int32_t *q = at[k];
        __m128 a01 = DVPMVS_PAIRS(stack + q[0], stack + q[1]), b01 = DVPMVS_PAIRS(below + q[0], below + q[1]);
        __m128 a45 = DVPMVS_PAIRS(stack + q[4], stack + q[5]), b45 = DVPMVS_PAIRS(below + q[4], below + q[5]);
        __m128 a23 = DVPMVS_PAIRS(stack + q[2], stack + q[3]), b23 = DVPMVS_PAIRS(below + q[2], below + q[3]);
        __m128 a67 = DVPMVS_PAIRS(stack + q[6], stack + q[7]), b67 = DVPMVS_PAIRS(below + q[6], below + q[7]);
        /* lanes (0,1,4,5 | 2,3,6,7) in the 128-bit halves, then even and odd floats apart */
        __m256 g0 = _mm256_insertf128_ps(_mm256_castps128_ps256(a01), a45, 1);
        __m256 g1 = _mm256_insertf128_ps(_mm256_castps128_ps256(a23), a67, 1);
        __m256 g2 = _mm256_insertf128_ps(_mm256_castps128_ps256(b01), b45, 1);
        __m256 g3 = _mm256_insertf128_ps(_mm256_castps128_ps256(b23), b67, 1);
        __m256 t00 = _mm256_shuffle_ps(g0, g1, 0x88), t01 = _mm256_shuffle_ps(g0, g1, 0xDD);
        __m256 t10 = _mm256_shuffle_ps(g2, g3, 0x88), t11 = _mm256_shuffle_ps(g2, g3, 0xDD);
        __m256 ax = _mm256_load_ps(fxs[k]), ay = _mm256_load_ps(fys[k]);
        __m256 top = _mm256_fmadd_ps(ax, _mm256_sub_ps(t01, t00), t00);
        __m256 low = _mm256_fmadd_ps(ax, _mm256_sub_ps(t11, t10), t10);
        __m256 s = _mm256_fmadd_ps(ay, _mm256_sub_ps(low, top), top);
        __m256 ws = _mm256_mul_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(T->w[k]), vslot), s);
        a = _mm256_add_ps(a, ws);
        b = _mm256_fmadd_ps(ws, s, b);
        c = _mm256_fmadd_ps(ws, _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->v[k]), vslot), c);
    }
    _mm256_storeu_ps(sws + l0, a);
    _mm256_storeu_ps(swss + l0, b);
    _mm256_storeu_ps(swrs + l0, c);
    return ((uint32_t)_mm256_movemask_ps(behind) & ((1u << count) - 1)) << l0;
}

__attribute__((target("avx2,fma"))) static uint32_t
dvpmvs_batch_sums_avx2(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                       float *sws, float *swss, float *swrs)
{
    uint32_t behind = 0;
    int l0;
    for (l0 = 0; l0 < B->count; l0 += 8)
        behind |= dvpmvs_batch_sums_avx2_8(stack, stride, T, B, l0, sws, swss, swrs);
    return behind;
}

/* All 16 lanes at once, in one pass (dvpmvs_batch_sums_avx2_8's operations); the texel pairs of
 * 8 lanes are one gather of 64-bit elements. */
__attribute__((target("avx512f,avx512dq,avx512vl"))) static uint32_t
dvpmvs_batch_sums_avx512(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                         float *sws, float *swss, float *swrs)
{
    int k, l, count = B->count;
    int32_t slot[16] __attribute__((aligned(64))), offset[16] __attribute__((aligned(64)));
    int32_t width[16] __attribute__((aligned(64))), height[16] __attribute__((aligned(64)));
    float hk[9][16] __attribute__((aligned(64)));
    float out[3][16] __attribute__((aligned(64)));
    __m512 h[9];
    for (l = 0; l < 16; l++) {
        int from = l < count ? l : 0;  /* spare lanes repeat the first one */
        slot[l] = B->slot[from];
        offset[l] = B->offset[from];
        width[l] = B->width[from];
        height[l] = B->height[from];
        for (k = 0; k < 9; k++)
            hk[k][l] = B->H[k][from];
    }
    for (k = 0; k < 9; k++)
        h[k] = _mm512_load_ps(hk[k]);
    const __m512i vslot = _mm512_load_si512(slot);
    const __m512i voffset = _mm512_load_si512(offset);
    const __m512i vwidth = _mm512_load_si512(width), vheight = _mm512_load_si512(height);
    const __m512i one_i = _mm512_set1_epi32(1), two_i = _mm512_set1_epi32(2), vstride = _mm512_set1_epi32(stride);
    const __m512i last_x = _mm512_sub_epi32(vwidth, two_i), last_y = _mm512_sub_epi32(vheight, two_i);
    const __m512 right = _mm512_cvtepi32_ps(_mm512_sub_epi32(vwidth, one_i));
    const __m512 bottom = _mm512_cvtepi32_ps(_mm512_sub_epi32(vheight, one_i));
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f), front = _mm512_set1_ps(dvpmvs_front_max);
    const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    const __m512i odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    __m512 a = zero, b = zero, c = zero;
    __mmask16 behind = 0;
#define DVPMVS_TABLE16(row) _mm512_permutexvar_ps(vslot, _mm512_castps256_ps512(_mm256_loadu_ps(row)))
#define DVPMVS_PAIRS8(at) _mm512_castpd_ps(_mm512_i32gather_pd((at), (const void *)stack, 4))
    for (k = 0; k < T->n; k++) {
        __m512 x = DVPMVS_TABLE16(T->x[k]), y = DVPMVS_TABLE16(T->y[k]);
        __m512 hz = _mm512_fmadd_ps(h[6], x, _mm512_fmadd_ps(h[7], y, h[8]));
        __m512 nx = _mm512_fmadd_ps(h[0], x, _mm512_fmadd_ps(h[1], y, h[2]));
        __m512 ny = _mm512_fmadd_ps(h[3], x, _mm512_fmadd_ps(h[4], y, h[5]));
        __m512 r = _mm512_div_ps(one, hz);
        __m512 hx = _mm512_min_ps(_mm512_max_ps(_mm512_mul_ps(nx, r), zero), right);
        __m512 hy = _mm512_min_ps(_mm512_max_ps(_mm512_mul_ps(ny, r), zero), bottom);
        __m512i x0 = _mm512_min_epi32(_mm512_cvttps_epi32(hx), last_x);
        __m512i y0 = _mm512_min_epi32(_mm512_cvttps_epi32(hy), last_y);
        behind |= _mm512_cmp_ps_mask(hz, front, _CMP_LE_OQ);
        __m512 ax = _mm512_sub_ps(hx, _mm512_cvtepi32_ps(x0)), ay = _mm512_sub_ps(hy, _mm512_cvtepi32_ps(y0));
        __m512i at = _mm512_add_epi32(_mm512_add_epi32(voffset, _mm512_mullo_epi32(y0, vstride)), x0);
        __m512i below = _mm512_add_epi32(at, vstride);
        /* (texel, next texel) of lanes 0..7 and 8..15, then even and odd floats apart */
        __m512 g0 = DVPMVS_PAIRS8(_mm512_castsi512_si256(at));
        __m512 g1 = DVPMVS_PAIRS8(_mm512_extracti64x4_epi64(at, 1));
        __m512 g2 = DVPMVS_PAIRS8(_mm512_castsi512_si256(below));
        __m512 g3 = DVPMVS_PAIRS8(_mm512_extracti64x4_epi64(below, 1));
        __m512 t00 = _mm512_permutex2var_ps(g0, even, g1), t01 = _mm512_permutex2var_ps(g0, odd, g1);
        __m512 t10 = _mm512_permutex2var_ps(g2, even, g3), t11 = _mm512_permutex2var_ps(g2, odd, g3);
        __m512 top = _mm512_fmadd_ps(ax, _mm512_sub_ps(t01, t00), t00);
        __m512 low = _mm512_fmadd_ps(ax, _mm512_sub_ps(t11, t10), t10);
        __m512 s = _mm512_fmadd_ps(ay, _mm512_sub_ps(low, top), top);
        __m512 ws = _mm512_mul_ps(DVPMVS_TABLE16(T->w[k]), s);
        a = _mm512_add_ps(a, ws);
        b = _mm512_fmadd_ps(ws, s, b);
        c = _mm512_fmadd_ps(ws, DVPMVS_TABLE16(T->v[k]), c);
    }
#undef DVPMVS_PAIRS8
#undef DVPMVS_TABLE16
    _mm512_store_ps(out[0], a);
    _mm512_store_ps(out[1], b);
    _mm512_store_ps(out[2], c);
    for (l = 0; l < count; l++) {
        sws[l] = out[0][l];
        swss[l] = out[1][l];
        swrs[l] = out[2][l];
    }
    return (uint32_t)behind & ((1u << count) - 1);
}

/* 1 - NCC of each lane (_ncc_from_sums) into out. In float: the kernels' double steps (sqrt of
 * a float, 1.0 - a float) round to the same float (double rounding is innocuous for these when
 * the wider format has at least twice the precision plus two bits). */
__attribute__((target("avx2"))) static void dvpmvs_ncc_avx2(const dvpmvs_sums *S, float *out)
{
    int l0;
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), max_cost = _mm256_set1_ps(2.0f);
    const __m256 var_min = _mm256_set1_ps(dvpmvs_var_min);
    for (l0 = 0; l0 < S->count; l0 += 8) {
        __m256 sum_w = _mm256_loadu_ps(S->sum_w + l0), mean = _mm256_loadu_ps(S->mean + l0);
        __m256 var = _mm256_loadu_ps(S->var + l0);
        __m256 mean_s = _mm256_div_ps(_mm256_loadu_ps(S->sws + l0), sum_w);
        __m256 var_s = _mm256_sub_ps(_mm256_div_ps(_mm256_loadu_ps(S->swss + l0), sum_w), _mm256_mul_ps(mean_s, mean_s));
        __m256 cov = _mm256_sub_ps(_mm256_div_ps(_mm256_loadu_ps(S->swrs + l0), sum_w), _mm256_mul_ps(mean, mean_s));
        __m256 denom = _mm256_sqrt_ps(_mm256_mul_ps(var, var_s));
        __m256 s = _mm256_sub_ps(one, _mm256_div_ps(cov, denom));
        s = _mm256_blendv_ps(s, zero, _mm256_cmp_ps(s, zero, _CMP_LT_OQ));
        s = _mm256_blendv_ps(s, max_cost, _mm256_cmp_ps(s, max_cost, _CMP_GT_OQ));
        __m256 flat = _mm256_or_ps(_mm256_cmp_ps(var, var_min, _CMP_LT_OQ), _mm256_cmp_ps(var_s, var_min, _CMP_LT_OQ));
        s = _mm256_blendv_ps(s, max_cost, flat);
        _mm256_storeu_ps(out + l0, s);
    }
}
#endif

/* The widest path this CPU runs, at most ``requested`` (a DVPMVS_SIMD_* value); it becomes the
 * one dvpmvs_batch_sums takes. */
static int dvpmvs_simd_select(int requested)
{
    int level = DVPMVS_SIMD_SCALAR;
#ifdef DVPMVS_HAVE_X86_SIMD
    __builtin_cpu_init();
    if (requested >= DVPMVS_SIMD_AVX2 && __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma"))
        level = DVPMVS_SIMD_AVX2;
    if (requested >= DVPMVS_SIMD_AVX512 && level == DVPMVS_SIMD_AVX2 && __builtin_cpu_supports("avx512f")
        && __builtin_cpu_supports("avx512dq") && __builtin_cpu_supports("avx512vl"))
        level = DVPMVS_SIMD_AVX512;
#endif
    dvpmvs_simd_level = level;
    dvpmvs_thresholds();
    return level;
}

static inline void dvpmvs_ncc(const dvpmvs_sums *S, float *out)
{
#ifdef DVPMVS_HAVE_X86_SIMD
    if (dvpmvs_simd_level >= DVPMVS_SIMD_AVX2) {
        dvpmvs_ncc_avx2(S, out);
        return;
    }
#endif
    dvpmvs_ncc_scalar(S, out);
}

/* How many lanes a batch should fill: the width of the path taken. */
static inline int dvpmvs_batch_width(void)
{
    return dvpmvs_simd_level == DVPMVS_SIMD_AVX512 ? 16 : 8;
}

/* Lanes count.. up to the next multiple of 8 as copies of lane 0, so that the AVX2 path loads
 * 8 lanes' parameters at once (spare lanes' sums are computed and not used). */
static inline void dvpmvs_batch_pad(dvpmvs_batch *B)
{
    int l, k;
    for (l = B->count; l % 8 != 0; l++) {
        B->slot[l] = B->slot[0];
        B->offset[l] = B->offset[0];
        B->width[l] = B->width[0];
        B->height[l] = B->height[0];
        for (k = 0; k < 9; k++)
            B->H[k][l] = B->H[k][0];
    }
}

/* The sums of every lane of a batch (spare lanes up to a multiple of 8 may be written: sws, swss
 * and swrs hold DVPMVS_BATCH floats); bit l of the result set when a sample of lane l falls
 * behind its source camera (that lane's cost is MAX_COST). */
static inline uint32_t dvpmvs_batch_sums(const float *stack, int stride, const dvpmvs_windows *T,
                                         dvpmvs_batch *B, float *sws, float *swss, float *swrs)
{
#ifdef DVPMVS_HAVE_X86_SIMD
    if (dvpmvs_simd_level == DVPMVS_SIMD_AVX512 && B->count > 8)
        return dvpmvs_batch_sums_avx512(stack, stride, T, B, sws, swss, swrs);
    if (dvpmvs_simd_level >= DVPMVS_SIMD_AVX2) {
        dvpmvs_batch_pad(B);
        return dvpmvs_batch_sums_avx2(stack, stride, T, B, sws, swss, swrs);
    }
#endif
    return dvpmvs_batch_sums_scalar(stack, stride, T, B, sws, swss, swrs);
}

#endif
