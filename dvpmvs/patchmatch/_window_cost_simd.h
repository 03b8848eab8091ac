/* The inner loop of the matching cost (_window_cost.pxd), many windows at once: for a batch of
 * (window, source) pairs, one per vector lane, the weighted sums of the window's bilinear samples
 * warped into the source image by the lane's homography (sum w s, sum w s^2, sum w s v).
 *
 * Every lane computes exactly what the scalar loop of _ncc_cost computes for its window, in the
 * same order and with the same IEEE single-precision operations (no fused multiply-add, no
 * reassociation: compile with -ffp-contract=off), so the sums are the same bit for bit whatever
 * the path. The scalar path is portable C; the AVX2 and AVX-512 paths are compiled with
 * per-function target attributes and chosen at run time (dvpmvs_simd_select), so that one build
 * runs on every x86-64 CPU. Texels are read with scalar pair loads (two adjacent floats as one
 * 64-bit load) and transposed into lanes: on the CPUs measured, hardware gathers were slower.
 *
 * The caller guarantees that every sample of a lane, and its 2x2 neighbourhood, lies inside the
 * lane's image (the fast path of _ncc_cost), and that the stack of images holds fewer than
 * 2^31 - 2 floats (indices are 32-bit in the vector paths).
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
 * image that starts at ``offset[l]`` floats into the stack, through the homography H[.][l]. */
typedef struct {
    int count;
    int32_t slot[DVPMVS_BATCH];
    int32_t offset[DVPMVS_BATCH];
    int32_t width[DVPMVS_BATCH];  /* the source image's size (read by the clamped sums only) */
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

static void dvpmvs_batch_sums_scalar(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                                     float *sws, float *swss, float *swrs)
{
    int l, k, i;
    for (l = 0; l < B->count; l++) {
        const float *img = stack + B->offset[l];
        int m = B->slot[l];
        float H[9];
        float a = 0, b = 0, c = 0;
        for (i = 0; i < 9; i++)
            H[i] = B->H[i][l];
        for (k = 0; k < T->n; k++) {
            float x = T->x[k][m], y = T->y[k][m];
            float hz = 1.0f / (H[6] * x + H[7] * y + H[8]);
            float hx = (H[0] * x + H[1] * y + H[2]) * hz;
            float hy = (H[3] * x + H[4] * y + H[5]) * hz;
            int xi = (int)hx, yi = (int)hy;
            float fx = hx - (float)xi, fy = hy - (float)yi;
            const float *r0 = img + (ptrdiff_t)yi * stride + xi;
            float top = r0[0] + fx * (r0[1] - r0[0]);
            float bottom = r0[stride] + fx * (r0[stride + 1] - r0[stride]);
            float s = top + fy * (bottom - top);
            float ws = T->w[k][m] * s;
            a = a + ws;
            b = b + ws * s;
            c = c + ws * T->v[k][m];
        }
        sws[l] = a;
        swss[l] = b;
        swrs[l] = c;
    }
}

/* The sums of windows whose warp may leave the source image (_ncc_cost_clamped): samples clamped
 * to the border and interpolated in double precision as bilinear_clamped does; bit l of the
 * result set when a sample of lane l falls behind the source camera (its cost is MAX_COST). */
static uint32_t dvpmvs_batch_sums_clamped_scalar(const float *stack, int stride, const dvpmvs_windows *T,
                                                 const dvpmvs_batch *B, float *sws, float *swss, float *swrs)
{
    uint32_t behind = 0;
    int l, k, i;
    for (l = 0; l < B->count; l++) {
        const float *img = stack + B->offset[l];
        int m = B->slot[l], width = B->width[l], height = B->height[l];
        float H[9];
        float a = 0, b = 0, c = 0;
        for (i = 0; i < 9; i++)
            H[i] = B->H[i][l];
        for (k = 0; k < T->n; k++) {
            float x = T->x[k][m], y = T->y[k][m];
            float hz = H[6] * x + H[7] * y + H[8];
            float hx = (H[0] * x + H[1] * y + H[2]) / hz;
            float hy = (H[3] * x + H[4] * y + H[5]) / hz;
            int x0, y0, x1, y1;
            float ax, ay, s, ws;
            if ((double)hz <= 1e-8)
                behind |= 1u << l;
            if (!(hx >= 0.0))
                hx = 0.0f;
            else if (hx > width - 1)
                hx = (float)(width - 1);
            if (!(hy >= 0.0))
                hy = 0.0f;
            else if (hy > height - 1)
                hy = (float)(height - 1);
            x0 = (int)hx;
            y0 = (int)hy;
            x1 = x0 + 1 < width ? x0 + 1 : x0;
            y1 = y0 + 1 < height ? y0 + 1 : y0;
            ax = hx - x0;
            ay = hy - y0;
            s = (float)((1.0 - ay) * ((1.0 - ax) * img[y0 * stride + x0] + ax * img[y0 * stride + x1])
                        + ay * ((1.0 - ax) * img[y1 * stride + x0] + ax * img[y1 * stride + x1]));
            ws = T->w[k][m] * s;
            a = a + ws;
            b = b + ws * s;
            c = c + ws * T->v[k][m];
        }
        sws[l] = a;
        swss[l] = b;
        swrs[l] = c;
    }
    return behind;
}

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

/* The corners of up to 8 windows' bounding boxes: window a's (x_min, y_min), (x_min, y_max),
 * (x_max, y_min), (x_max, y_max) at 4a .. 4a + 3 (_window_inside's order). */
typedef struct {
    float x[32];
    float y[32];
} dvpmvs_corners;

/* Bit a set when window a's corners, warped by H, lie in front of the source camera and strictly
 * inside its image (_window_inside of _window_cost.pxd, the same operations). */
static uint32_t dvpmvs_windows_inside_scalar(const float *H, const dvpmvs_corners *C, int n, int width, int height)
{
    uint32_t mask = 0;
    int a, k;
    for (a = 0; a < n; a++) {
        int inside = 1;
        for (k = 4 * a; k < 4 * a + 4; k++) {
            float hz = H[6] * C->x[k] + H[7] * C->y[k] + H[8];
            float hx = (H[0] * C->x[k] + H[1] * C->y[k] + H[2]) / hz;
            float hy = (H[3] * C->x[k] + H[4] * C->y[k] + H[5]) / hz;
            inside &= !((double)hz <= 1e-8) & (hx >= 0) & (hy >= 0) & (hx < width - 1) & (hy < height - 1);
        }
        mask |= (uint32_t)inside << a;
    }
    return mask;
}


/* The portable counterparts of the vector paths below (same results; the kernels take the
 * scalar loops of _window_cost.pxd instead where no vector path runs). */
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

/* Lanes l0..l0+7 of a batch, in two passes as the scalar loop: the warped positions of all
 * samples first (no memory lookups: many samples in flight), then the lookups and sums. */
__attribute__((target("avx2"))) static void
dvpmvs_batch_sums_avx2_8(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B, int l0,
                         float *sws, float *swss, float *swrs)
{
    int k, l, count = B->count - l0 < 8 ? B->count - l0 : 8;
    int32_t slot[8] __attribute__((aligned(32)));
    int32_t offset[8] __attribute__((aligned(32)));
    int32_t at[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    float fxs[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    float fys[DVPMVS_SLOT_SAMPLES][8] __attribute__((aligned(32)));
    float out[3][8] __attribute__((aligned(32)));
    for (l = 0; l < 8; l++) {
        int from = l < count ? l0 + l : l0;  /* spare lanes repeat the first one */
        slot[l] = B->slot[from];
        offset[l] = B->offset[from];
    }
    const __m256i vslot = _mm256_load_si256((const __m256i *)slot);
    const __m256i voffset = _mm256_load_si256((const __m256i *)offset);
    __m256 h[9];
    for (k = 0; k < 9; k++) {
        float hk[8] __attribute__((aligned(32)));
        for (l = 0; l < 8; l++)
            hk[l] = B->H[k][l < count ? l0 + l : l0];
        h[k] = _mm256_load_ps(hk);
    }
    const __m256 one = _mm256_set1_ps(1.0f);
    const __m256i vstride = _mm256_set1_epi32(stride);
    for (k = 0; k < T->n; k++) {
        __m256 x = _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->x[k]), vslot);
        __m256 y = _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->y[k]), vslot);
        __m256 hz = _mm256_div_ps(one, _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h[6], x), _mm256_mul_ps(h[7], y)), h[8]));
        __m256 hx = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h[0], x), _mm256_mul_ps(h[1], y)), h[2]), hz);
        __m256 hy = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h[3], x), _mm256_mul_ps(h[4], y)), h[5]), hz);
        __m256i xi = _mm256_cvttps_epi32(hx), yi = _mm256_cvttps_epi32(hy);
        _mm256_store_ps(fxs[k], _mm256_sub_ps(hx, _mm256_cvtepi32_ps(xi)));
        _mm256_store_ps(fys[k], _mm256_sub_ps(hy, _mm256_cvtepi32_ps(yi)));
        _mm256_store_si256((__m256i *)at[k], _mm256_add_epi32(_mm256_add_epi32(voffset, _mm256_mullo_epi32(yi, vstride)), xi));
    }
    __m256 a = _mm256_setzero_ps(), b = _mm256_setzero_ps(), c = _mm256_setzero_ps();
    for (k = 0; k < T->n; k++) {
        const int32_t *q = at[k];
        const float *p0 = stack + q[0], *p1 = stack + q[1], *p2 = stack + q[2], *p3 = stack + q[3];
        const float *p4 = stack + q[4], *p5 = stack + q[5], *p6 = stack + q[6], *p7 = stack + q[7];
        /* lanes (0,1,4,5 | 2,3,6,7) in the 128-bit halves, then even and odd floats apart */
        __m256 g0 = _mm256_insertf128_ps(_mm256_castps128_ps256(DVPMVS_PAIRS(p0, p1)), DVPMVS_PAIRS(p4, p5), 1);
        __m256 g1 = _mm256_insertf128_ps(_mm256_castps128_ps256(DVPMVS_PAIRS(p2, p3)), DVPMVS_PAIRS(p6, p7), 1);
        __m256 g2 = _mm256_insertf128_ps(_mm256_castps128_ps256(DVPMVS_PAIRS(p0 + stride, p1 + stride)),
                                         DVPMVS_PAIRS(p4 + stride, p5 + stride), 1);
        __m256 g3 = _mm256_insertf128_ps(_mm256_castps128_ps256(DVPMVS_PAIRS(p2 + stride, p3 + stride)),
                                         DVPMVS_PAIRS(p6 + stride, p7 + stride), 1);
        __m256 t00 = _mm256_shuffle_ps(g0, g1, 0x88), t01 = _mm256_shuffle_ps(g0, g1, 0xDD);
        __m256 t10 = _mm256_shuffle_ps(g2, g3, 0x88), t11 = _mm256_shuffle_ps(g2, g3, 0xDD);
        __m256 fx = _mm256_load_ps(fxs[k]), fy = _mm256_load_ps(fys[k]);
        __m256 top = _mm256_add_ps(t00, _mm256_mul_ps(fx, _mm256_sub_ps(t01, t00)));
        __m256 bottom = _mm256_add_ps(t10, _mm256_mul_ps(fx, _mm256_sub_ps(t11, t10)));
        __m256 s = _mm256_add_ps(top, _mm256_mul_ps(fy, _mm256_sub_ps(bottom, top)));
        __m256 ws = _mm256_mul_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(T->w[k]), vslot), s);
        a = _mm256_add_ps(a, ws);
        b = _mm256_add_ps(b, _mm256_mul_ps(ws, s));
        c = _mm256_add_ps(c, _mm256_mul_ps(ws, _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->v[k]), vslot)));
    }
    _mm256_store_ps(out[0], a);
    _mm256_store_ps(out[1], b);
    _mm256_store_ps(out[2], c);
    for (l = 0; l < count; l++) {
        sws[l0 + l] = out[0][l];
        swss[l0 + l] = out[1][l];
        swrs[l0 + l] = out[2][l];
    }
}

__attribute__((target("avx2"))) static void
dvpmvs_batch_sums_avx2(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                       float *sws, float *swss, float *swrs)
{
    int l0;
    for (l0 = 0; l0 < B->count; l0 += 8)
        dvpmvs_batch_sums_avx2_8(stack, stride, T, B, l0, sws, swss, swrs);
}

__attribute__((target("avx512f,avx512dq,avx512vl"))) static void
dvpmvs_batch_sums_avx512(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                         float *sws, float *swss, float *swrs)
{
    int k, l, count = B->count;
    int32_t slot[16] __attribute__((aligned(64)));
    int32_t offset[16] __attribute__((aligned(64)));
    int32_t at[DVPMVS_SLOT_SAMPLES][16] __attribute__((aligned(64)));
    float fxs[DVPMVS_SLOT_SAMPLES][16] __attribute__((aligned(64)));
    float fys[DVPMVS_SLOT_SAMPLES][16] __attribute__((aligned(64)));
    float out[3][16] __attribute__((aligned(64)));
    __m128 top_pairs[8], bottom_pairs[8];
    for (l = 0; l < 16; l++) {
        int from = l < count ? l : 0;  /* spare lanes repeat the first one */
        slot[l] = B->slot[from];
        offset[l] = B->offset[from];
    }
    const __m512i vslot = _mm512_load_si512(slot);
    const __m512i voffset = _mm512_load_si512(offset);
    __m512 h[9];
    for (k = 0; k < 9; k++) {
        float hk[16] __attribute__((aligned(64)));
        for (l = 0; l < 16; l++)
            hk[l] = B->H[k][l < count ? l : 0];
        h[k] = _mm512_load_ps(hk);
    }
    const __m512 one = _mm512_set1_ps(1.0f);
    const __m512i vstride = _mm512_set1_epi32(stride);
    const __m512i even = _mm512_setr_epi32(0, 2, 4, 6, 8, 10, 12, 14, 16, 18, 20, 22, 24, 26, 28, 30);
    const __m512i odd = _mm512_setr_epi32(1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 21, 23, 25, 27, 29, 31);
    for (k = 0; k < T->n; k++) {
        __m512 x = _mm512_permutexvar_ps(vslot, _mm512_castps256_ps512(_mm256_loadu_ps(T->x[k])));
        __m512 y = _mm512_permutexvar_ps(vslot, _mm512_castps256_ps512(_mm256_loadu_ps(T->y[k])));
        __m512 hz = _mm512_div_ps(one, _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(h[6], x), _mm512_mul_ps(h[7], y)), h[8]));
        __m512 hx = _mm512_mul_ps(_mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(h[0], x), _mm512_mul_ps(h[1], y)), h[2]), hz);
        __m512 hy = _mm512_mul_ps(_mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(h[3], x), _mm512_mul_ps(h[4], y)), h[5]), hz);
        __m512i xi = _mm512_cvttps_epi32(hx), yi = _mm512_cvttps_epi32(hy);
        _mm512_store_ps(fxs[k], _mm512_sub_ps(hx, _mm512_cvtepi32_ps(xi)));
        _mm512_store_ps(fys[k], _mm512_sub_ps(hy, _mm512_cvtepi32_ps(yi)));
        _mm512_store_si512(at[k], _mm512_add_epi32(_mm512_add_epi32(voffset, _mm512_mullo_epi32(yi, vstride)), xi));
    }
    __m512 a = _mm512_setzero_ps(), b = _mm512_setzero_ps(), c = _mm512_setzero_ps();
    for (k = 0; k < T->n; k++) {
        const int32_t *q = at[k];
        for (l = 0; l < 8; l++) {
            top_pairs[l] = DVPMVS_PAIRS(stack + q[2 * l], stack + q[2 * l + 1]);
            bottom_pairs[l] = DVPMVS_PAIRS(stack + q[2 * l] + stride, stack + q[2 * l + 1] + stride);
        }
        /* lanes 0..7 and 8..15 as (texel, next texel) pairs, then even and odd floats apart */
        __m512 g0 = _mm512_insertf32x4(_mm512_insertf32x4(_mm512_insertf32x4(
            _mm512_castps128_ps512(top_pairs[0]), top_pairs[1], 1), top_pairs[2], 2), top_pairs[3], 3);
        __m512 g1 = _mm512_insertf32x4(_mm512_insertf32x4(_mm512_insertf32x4(
            _mm512_castps128_ps512(top_pairs[4]), top_pairs[5], 1), top_pairs[6], 2), top_pairs[7], 3);
        __m512 g2 = _mm512_insertf32x4(_mm512_insertf32x4(_mm512_insertf32x4(
            _mm512_castps128_ps512(bottom_pairs[0]), bottom_pairs[1], 1), bottom_pairs[2], 2), bottom_pairs[3], 3);
        __m512 g3 = _mm512_insertf32x4(_mm512_insertf32x4(_mm512_insertf32x4(
            _mm512_castps128_ps512(bottom_pairs[4]), bottom_pairs[5], 1), bottom_pairs[6], 2), bottom_pairs[7], 3);
        __m512 t00 = _mm512_permutex2var_ps(g0, even, g1), t01 = _mm512_permutex2var_ps(g0, odd, g1);
        __m512 t10 = _mm512_permutex2var_ps(g2, even, g3), t11 = _mm512_permutex2var_ps(g2, odd, g3);
        __m512 fx = _mm512_load_ps(fxs[k]), fy = _mm512_load_ps(fys[k]);
        __m512 top = _mm512_add_ps(t00, _mm512_mul_ps(fx, _mm512_sub_ps(t01, t00)));
        __m512 bottom = _mm512_add_ps(t10, _mm512_mul_ps(fx, _mm512_sub_ps(t11, t10)));
        __m512 s = _mm512_add_ps(top, _mm512_mul_ps(fy, _mm512_sub_ps(bottom, top)));
        __m512 ws = _mm512_mul_ps(_mm512_permutexvar_ps(vslot, _mm512_castps256_ps512(_mm256_loadu_ps(T->w[k]))), s);
        a = _mm512_add_ps(a, ws);
        b = _mm512_add_ps(b, _mm512_mul_ps(ws, s));
        c = _mm512_add_ps(c, _mm512_mul_ps(ws, _mm512_permutexvar_ps(vslot, _mm512_castps256_ps512(_mm256_loadu_ps(T->v[k])))));
    }
    _mm512_store_ps(out[0], a);
    _mm512_store_ps(out[1], b);
    _mm512_store_ps(out[2], c);
    for (l = 0; l < count; l++) {
        sws[l] = out[0][l];
        swss[l] = out[1][l];
        swrs[l] = out[2][l];
    }
}

/* Lanes l0..l0+7 of dvpmvs_batch_sums_clamped_scalar. */
__attribute__((target("avx2"))) static uint32_t
dvpmvs_batch_sums_clamped_avx2_8(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                                 int l0, float *sws, float *swss, float *swrs)
{
    int k, l, count = B->count - l0 < 8 ? B->count - l0 : 8;
    int32_t slot[8] __attribute__((aligned(32))), offset[8] __attribute__((aligned(32)));
    int32_t width[8] __attribute__((aligned(32))), height[8] __attribute__((aligned(32)));
    float hk[9][8] __attribute__((aligned(32)));
    float out[3][8] __attribute__((aligned(32)));
    __m256 h[9];
    for (l = 0; l < 8; l++) {
        int from = l < count ? l0 + l : l0;  /* spare lanes repeat the first one */
        slot[l] = B->slot[from];
        offset[l] = B->offset[from];
        width[l] = B->width[from];
        height[l] = B->height[from];
        for (k = 0; k < 9; k++)
            hk[k][l] = B->H[k][from];
    }
    for (k = 0; k < 9; k++)
        h[k] = _mm256_load_ps(hk[k]);
    const __m256i vslot = _mm256_load_si256((const __m256i *)slot);
    const __m256i voffset = _mm256_load_si256((const __m256i *)offset);
    const __m256i one_i = _mm256_set1_epi32(1), vstride = _mm256_set1_epi32(stride);
    const __m256i right_i = _mm256_sub_epi32(_mm256_load_si256((const __m256i *)width), one_i);
    const __m256i bottom_i = _mm256_sub_epi32(_mm256_load_si256((const __m256i *)height), one_i);
    const __m256 right = _mm256_cvtepi32_ps(right_i), bottom = _mm256_cvtepi32_ps(bottom_i);
    const __m256 zero = _mm256_setzero_ps(), front = _mm256_set1_ps(dvpmvs_front_max);
    const __m256d one_d = _mm256_set1_pd(1.0);
    __m256 a = _mm256_setzero_ps(), b = _mm256_setzero_ps(), c = _mm256_setzero_ps(), behind = zero;
    for (k = 0; k < T->n; k++) {
        __m256 x = _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->x[k]), vslot);
        __m256 y = _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->y[k]), vslot);
        __m256 hz = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h[6], x), _mm256_mul_ps(h[7], y)), h[8]);
        __m256 hx = _mm256_div_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h[0], x), _mm256_mul_ps(h[1], y)), h[2]), hz);
        __m256 hy = _mm256_div_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h[3], x), _mm256_mul_ps(h[4], y)), h[5]), hz);
        behind = _mm256_or_ps(behind, _mm256_cmp_ps(hz, front, _CMP_LE_OQ));
        /* NaN and negative positions read column / row 0, those past the last one the last */
        hx = _mm256_and_ps(hx, _mm256_cmp_ps(hx, zero, _CMP_GE_OQ));
        hx = _mm256_blendv_ps(hx, right, _mm256_cmp_ps(hx, right, _CMP_GT_OQ));
        hy = _mm256_and_ps(hy, _mm256_cmp_ps(hy, zero, _CMP_GE_OQ));
        hy = _mm256_blendv_ps(hy, bottom, _mm256_cmp_ps(hy, bottom, _CMP_GT_OQ));
        __m256i x0 = _mm256_cvttps_epi32(hx), y0 = _mm256_cvttps_epi32(hy);
        __m256i x1 = _mm256_min_epi32(_mm256_add_epi32(x0, one_i), right_i);
        __m256i y1 = _mm256_min_epi32(_mm256_add_epi32(y0, one_i), bottom_i);
        __m256 ax = _mm256_sub_ps(hx, _mm256_cvtepi32_ps(x0)), ay = _mm256_sub_ps(hy, _mm256_cvtepi32_ps(y0));
        __m256i r0 = _mm256_add_epi32(voffset, _mm256_mullo_epi32(y0, vstride));
        __m256i r1 = _mm256_add_epi32(voffset, _mm256_mullo_epi32(y1, vstride));
        __m256 t00 = _mm256_i32gather_ps(stack, _mm256_add_epi32(r0, x0), 4);
        __m256 t01 = _mm256_mul_ps(ax, _mm256_i32gather_ps(stack, _mm256_add_epi32(r0, x1), 4));
        __m256 t10 = _mm256_i32gather_ps(stack, _mm256_add_epi32(r1, x0), 4);
        __m256 t11 = _mm256_mul_ps(ax, _mm256_i32gather_ps(stack, _mm256_add_epi32(r1, x1), 4));
        __m128 half[2];
        int part;
        for (part = 0; part < 2; part++) {
#define DVPMVS_HALF(v) _mm256_cvtps_pd(part ? _mm256_extractf128_ps(v, 1) : _mm256_castps256_ps128(v))
            __m256d axd = DVPMVS_HALF(ax), ayd = DVPMVS_HALF(ay);
            __m256d top = _mm256_add_pd(_mm256_mul_pd(_mm256_sub_pd(one_d, axd), DVPMVS_HALF(t00)), DVPMVS_HALF(t01));
            __m256d bot = _mm256_add_pd(_mm256_mul_pd(_mm256_sub_pd(one_d, axd), DVPMVS_HALF(t10)), DVPMVS_HALF(t11));
            half[part] = _mm256_cvtpd_ps(_mm256_add_pd(_mm256_mul_pd(_mm256_sub_pd(one_d, ayd), top), _mm256_mul_pd(ayd, bot)));
#undef DVPMVS_HALF
        }
        __m256 s = _mm256_insertf128_ps(_mm256_castps128_ps256(half[0]), half[1], 1);
        __m256 ws = _mm256_mul_ps(_mm256_permutevar8x32_ps(_mm256_loadu_ps(T->w[k]), vslot), s);
        a = _mm256_add_ps(a, ws);
        b = _mm256_add_ps(b, _mm256_mul_ps(ws, s));
        c = _mm256_add_ps(c, _mm256_mul_ps(ws, _mm256_permutevar8x32_ps(_mm256_loadu_ps(T->v[k]), vslot)));
    }
    _mm256_store_ps(out[0], a);
    _mm256_store_ps(out[1], b);
    _mm256_store_ps(out[2], c);
    for (l = 0; l < count; l++) {
        sws[l0 + l] = out[0][l];
        swss[l0 + l] = out[1][l];
        swrs[l0 + l] = out[2][l];
    }
    return ((uint32_t)_mm256_movemask_ps(behind) & ((1u << count) - 1)) << l0;
}

__attribute__((target("avx2"))) static uint32_t
dvpmvs_batch_sums_clamped_avx2(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                               float *sws, float *swss, float *swrs)
{
    uint32_t behind = 0;
    int l0;
    for (l0 = 0; l0 < B->count; l0 += 8)
        behind |= dvpmvs_batch_sums_clamped_avx2_8(stack, stride, T, B, l0, sws, swss, swrs);
    return behind;
}

/* Bit a of the result: window a's four corners inside (the corner masks, 4 bits per window). */
static inline uint32_t dvpmvs_whole_windows(uint32_t corners, int n)
{
    uint32_t mask = 0;
    int a;
    for (a = 0; a < n; a++)
        mask |= (uint32_t)(((corners >> (4 * a)) & 0xF) == 0xF) << a;
    return mask;
}

__attribute__((target("avx2"))) static uint32_t
dvpmvs_windows_inside_avx2(const float *H, const dvpmvs_corners *C, int n, int width, int height)
{
    const __m256 h0 = _mm256_set1_ps(H[0]), h1 = _mm256_set1_ps(H[1]), h2 = _mm256_set1_ps(H[2]);
    const __m256 h3 = _mm256_set1_ps(H[3]), h4 = _mm256_set1_ps(H[4]), h5 = _mm256_set1_ps(H[5]);
    const __m256 h6 = _mm256_set1_ps(H[6]), h7 = _mm256_set1_ps(H[7]), h8 = _mm256_set1_ps(H[8]);
    const __m256 zero = _mm256_setzero_ps(), front = _mm256_set1_ps(dvpmvs_front_max);
    const __m256 right = _mm256_set1_ps((float)(width - 1)), bottom = _mm256_set1_ps((float)(height - 1));
    uint32_t corners = 0;
    int k;
    for (k = 0; k < 4 * n; k += 8) {
        __m256 x = _mm256_loadu_ps(C->x + k), y = _mm256_loadu_ps(C->y + k);
        __m256 hz = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h6, x), _mm256_mul_ps(h7, y)), h8);
        __m256 hx = _mm256_div_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h0, x), _mm256_mul_ps(h1, y)), h2), hz);
        __m256 hy = _mm256_div_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h3, x), _mm256_mul_ps(h4, y)), h5), hz);
        __m256 in = _mm256_and_ps(_mm256_cmp_ps(hz, front, _CMP_NLE_UQ), _mm256_cmp_ps(hx, zero, _CMP_GE_OQ));
        in = _mm256_and_ps(in, _mm256_cmp_ps(hy, zero, _CMP_GE_OQ));
        in = _mm256_and_ps(in, _mm256_cmp_ps(hx, right, _CMP_LT_OQ));
        in = _mm256_and_ps(in, _mm256_cmp_ps(hy, bottom, _CMP_LT_OQ));
        corners |= (uint32_t)_mm256_movemask_ps(in) << k;
    }
    return dvpmvs_whole_windows(corners, n);
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
    if (requested >= DVPMVS_SIMD_AVX2 && __builtin_cpu_supports("avx2"))
        level = DVPMVS_SIMD_AVX2;
    if (requested >= DVPMVS_SIMD_AVX512 && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512dq")
        && __builtin_cpu_supports("avx512vl"))
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

/* Which of n (<= 8) windows stay inside the source under H (bit a: window a). */
static inline uint32_t dvpmvs_windows_inside(const float *H, const dvpmvs_corners *C, int n, int width, int height)
{
#ifdef DVPMVS_HAVE_X86_SIMD
    /* AVX2 on AVX-512 CPUs too: 8 windows' 32 corners are 4 vectors of 8 */
    if (dvpmvs_simd_level >= DVPMVS_SIMD_AVX2)
        return dvpmvs_windows_inside_avx2(H, C, n, width, height);
#endif
    return dvpmvs_windows_inside_scalar(H, C, n, width, height);
}

/* dvpmvs_batch_sums for windows that may leave their source image (see the scalar version). */
static inline uint32_t dvpmvs_batch_sums_clamped(const float *stack, int stride, const dvpmvs_windows *T,
                                                 const dvpmvs_batch *B, float *sws, float *swss, float *swrs)
{
#ifdef DVPMVS_HAVE_X86_SIMD
    if (dvpmvs_simd_level >= DVPMVS_SIMD_AVX2)
        return dvpmvs_batch_sums_clamped_avx2(stack, stride, T, B, sws, swss, swrs);
#endif
    return dvpmvs_batch_sums_clamped_scalar(stack, stride, T, B, sws, swss, swrs);
}

/* How many lanes a batch should fill: the width of the path taken. */
static inline int dvpmvs_batch_width(void)
{
    return dvpmvs_simd_level == DVPMVS_SIMD_AVX512 ? 16 : 8;
}

static inline void dvpmvs_batch_sums(const float *stack, int stride, const dvpmvs_windows *T, const dvpmvs_batch *B,
                                     float *sws, float *swss, float *swrs)
{
#ifdef DVPMVS_HAVE_X86_SIMD
    if (dvpmvs_simd_level == DVPMVS_SIMD_AVX512 && B->count > 8) {
        dvpmvs_batch_sums_avx512(stack, stride, T, B, sws, swss, swrs);
        return;
    }
    if (dvpmvs_simd_level >= DVPMVS_SIMD_AVX2) {
        dvpmvs_batch_sums_avx2(stack, stride, T, B, sws, swss, swrs);
        return;
    }
#endif
    dvpmvs_batch_sums_scalar(stack, stride, T, B, sws, swss, swrs);
}

#endif
