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
 * defines. The AVX2 path is compiled with per-function target attributes and chosen at run time
 * (dvpmvs_simd_select), so that one build runs on every x86-64 CPU. A batch is one AVX2 vector of
 * 8 lanes, which the callers fill across hypotheses and sources. Texels are read as pairs of
 * adjacent floats, by scalar 64-bit loads and transposes: hardware gathers of single floats took
 * longer on both CPUs measured (an AMD EPYC, Zen 3, and an Intel Xeon with AVX-512), and
 * a 16-lane AVX-512 path with 64-bit gathers of texel pairs took longer per lane than two AVX2
 * batches on the Intel Xeon (docs/benchmarks.md, "The vector kernels"). Lanes go across windows
 * rather than across one window's samples: 8 samples per lane with the homography broadcast was
 * no faster on 36-sample windows and slower on the 9-sample centres of deformed pixels, which
 * fill a vector only partly (scripts/kernel_layouts.c).
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
#define DVPMVS_BATCH 8          /* lanes of a batch: one AVX2 vector */

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

/* Up to 8 windows' weighted sums and reference statistics, for the NCC of _ncc_from_sums. */
typedef struct {
    int count;
    float sum_w[DVPMVS_BATCH], mean[DVPMVS_BATCH], var[DVPMVS_BATCH];
    float sws[DVPMVS_BATCH], swss[DVPMVS_BATCH], swrs[DVPMVS_BATCH];
} dvpmvs_sums;

enum { DVPMVS_SIMD_SCALAR = 0, DVPMVS_SIMD_AVX2 = 1 };

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

/* The 8 lanes of a batch, dvpmvs_window_sums's operations lane by lane, in two passes: the
 * clamped positions of all samples first (no memory lookups: many samples in flight), then the
 * texels, read as pairs of adjacent floats, and the sums. */
__attribute__((target("avx2,fma"))) static uint32_t
dvpmvs_batch_sums_avx2(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B, float *sws,
                       float *swss, float *swrs)
{
    /* every lane is filled (dvpmvs_batch_pad), and sws, swss and swrs hold them all */
    int k;
    int32_t at[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    float fxs[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    float fys[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    __m256 h[9];
    for (k = 0; k < 9; k++)
        h[k] = _mm256_loadu_ps(&B->H[k][0]);
    const __m256i vslot = _mm256_loadu_si256((const __m256i *)&B->slot[0]);
    const __m256i voffset = _mm256_loadu_si256((const __m256i *)&B->offset[0]);
    const __m256i vwidth = _mm256_loadu_si256((const __m256i *)&B->width[0]);
    const __m256i vheight = _mm256_loadu_si256((const __m256i *)&B->height[0]);
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
    _mm256_storeu_ps(sws, a);
    _mm256_storeu_ps(swss, b);
    _mm256_storeu_ps(swrs, c);
    return (uint32_t)_mm256_movemask_ps(behind) & ((1u << B->count) - 1);
}

/* 1 - NCC of each lane (_ncc_from_sums) into out. In float: the kernels' double steps (sqrt of
 * a float, 1.0 - a float) round to the same float (double rounding is innocuous for these when
 * the wider format has at least twice the precision plus two bits). */
__attribute__((target("avx2"))) static void dvpmvs_ncc_avx2(const dvpmvs_sums *S, float *out)
{
    /* the 8 lanes, spare ones included: the caller fills them (with lane 0's values) */
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), max_cost = _mm256_set1_ps(2.0f);
    const __m256 var_min = _mm256_set1_ps(dvpmvs_var_min);
    __m256 sum_w = _mm256_loadu_ps(S->sum_w), mean = _mm256_loadu_ps(S->mean), var = _mm256_loadu_ps(S->var);
    __m256 mean_s = _mm256_div_ps(_mm256_loadu_ps(S->sws), sum_w);
    __m256 var_s = _mm256_sub_ps(_mm256_div_ps(_mm256_loadu_ps(S->swss), sum_w), _mm256_mul_ps(mean_s, mean_s));
    __m256 cov = _mm256_sub_ps(_mm256_div_ps(_mm256_loadu_ps(S->swrs), sum_w), _mm256_mul_ps(mean, mean_s));
    __m256 denom = _mm256_sqrt_ps(_mm256_mul_ps(var, var_s));
    __m256 s = _mm256_sub_ps(one, _mm256_div_ps(cov, denom));
    s = _mm256_blendv_ps(s, zero, _mm256_cmp_ps(s, zero, _CMP_LT_OQ));
    s = _mm256_blendv_ps(s, max_cost, _mm256_cmp_ps(s, max_cost, _CMP_GT_OQ));
    __m256 flat = _mm256_or_ps(_mm256_cmp_ps(var, var_min, _CMP_LT_OQ), _mm256_cmp_ps(var_s, var_min, _CMP_LT_OQ));
    _mm256_storeu_ps(out, _mm256_blendv_ps(s, max_cost, flat));
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

/* Lanes count.. as copies of lane 0, so that the AVX2 path loads the 8 lanes' parameters at
 * once (spare lanes' sums are computed and not used). */
static inline void dvpmvs_batch_pad(dvpmvs_batch *B)
{
    int l, k;
    for (l = B->count; l < DVPMVS_BATCH; l++) {
        B->slot[l] = B->slot[0];
        B->offset[l] = B->offset[0];
        B->width[l] = B->width[0];
        B->height[l] = B->height[0];
        for (k = 0; k < 9; k++)
            B->H[k][l] = B->H[k][0];
    }
}

/* The sums of every lane of a batch (spare lanes may be written: sws, swss and swrs hold
 * DVPMVS_BATCH floats); bit l of the result set when a sample of lane l falls
 * behind its source camera (that lane's cost is MAX_COST). */
static inline uint32_t dvpmvs_batch_sums(const float *stack, int stride, const dvpmvs_windows *T,
                                         dvpmvs_batch *B, float *sws, float *swss, float *swrs)
{
#ifdef DVPMVS_HAVE_X86_SIMD
    if (dvpmvs_simd_level >= DVPMVS_SIMD_AVX2) {
        dvpmvs_batch_pad(B);
        return dvpmvs_batch_sums_avx2(stack, stride, T, B, sws, swss, swrs);
    }
#endif
    return dvpmvs_batch_sums_scalar(stack, stride, T, B, sws, swss, swrs);
}

#endif
