/* The inner loop of the matching cost (_window_cost.pxd) for several windows at once, one
 * window per vector lane: the weighted sums of the bilinear samples of each window warped by one
 * homography into one source image (sum w s, sum w s^2, sum w s v).
 *
 * Every lane computes exactly what the scalar loop of _ncc_cost computes for its window, in
 * the same order and with the same IEEE single-precision operations (no fused multiply-add, no
 * reassociation), so the sums are the same bit for bit whatever the path. The scalar path is
 * portable C; the AVX2 and AVX-512 paths are compiled with per-function target attributes and
 * chosen at run time (dvpmvs_simd_select), so that one build runs on every x86-64 CPU. Texels
 * are read with scalar pair loads (two adjacent floats as one 64-bit load) and transposed into
 * lanes: on the CPUs measured, hardware gathers were slower.
 *
 * The caller guarantees that every sample of an active lane, and its 2x2 neighbourhood, lies
 * inside the image (the fast path of _ncc_cost); inactive lanes read the image's first texels.
 */
#ifndef DVPMVS_WINDOW_COST_SIMD_H
#define DVPMVS_WINDOW_COST_SIMD_H

#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define DVPMVS_LANES 8
#define DVPMVS_LANE_SAMPLES 256

/* Up to DVPMVS_LANES windows' samples, transposed: sample k of lane l at [k][l]. A window with
 * fewer samples than ``n`` is padded with weight 0, value 0 and its last sample's position:
 * w s = 0 adds nothing to any sum (the images are finite). */
typedef struct {
    int n;
    float x[DVPMVS_LANE_SAMPLES][DVPMVS_LANES];
    float y[DVPMVS_LANE_SAMPLES][DVPMVS_LANES];
    float w[DVPMVS_LANE_SAMPLES][DVPMVS_LANES];
    float v[DVPMVS_LANE_SAMPLES][DVPMVS_LANES];
} dvpmvs_lanes;

enum { DVPMVS_SIMD_SCALAR = 0, DVPMVS_SIMD_AVX2 = 1, DVPMVS_SIMD_AVX512 = 2 };

static int dvpmvs_simd_level = DVPMVS_SIMD_SCALAR;

static void dvpmvs_window_sums_scalar(const float *img, int stride, const float *H, const dvpmvs_lanes *L,
                                      uint32_t active, float *sws, float *swss, float *swrs)
{
    int l, k;
    for (l = 0; l < DVPMVS_LANES; l++) {
        float a = 0, b = 0, c = 0;
        if ((active >> l) & 1) {
            for (k = 0; k < L->n; k++) {
                float x = L->x[k][l], y = L->y[k][l];
                float hz = 1.0f / (H[6] * x + H[7] * y + H[8]);
                float hx = (H[0] * x + H[1] * y + H[2]) * hz;
                float hy = (H[3] * x + H[4] * y + H[5]) * hz;
                int xi = (int)hx, yi = (int)hy;
                float fx = hx - (float)xi, fy = hy - (float)yi;
                const float *r0 = img + (ptrdiff_t)yi * stride + xi;
                float top = r0[0] + fx * (r0[1] - r0[0]);
                float bottom = r0[stride] + fx * (r0[stride + 1] - r0[stride]);
                float s = top + fy * (bottom - top);
                float ws = L->w[k][l] * s;
                a = a + ws;
                b = b + ws * s;
                c = c + ws * L->v[k][l];
            }
        }
        sws[l] = a;
        swss[l] = b;
        swrs[l] = c;
    }
}

#if (defined(__x86_64__) || defined(_M_X64)) && (defined(__GNUC__) || defined(__clang__))
#define DVPMVS_HAVE_X86_SIMD 1
#include <immintrin.h>

/* The four texels of eight lanes: two 64-bit loads per lane (top and bottom pairs), transposed. */
__attribute__((target("avx2"))) static inline void
dvpmvs_texels_avx2(const float *img, int stride, __m256i idx, __m256 *t00, __m256 *t01, __m256 *t10, __m256 *t11)
{
    int32_t at[8] __attribute__((aligned(32)));
    const float *p[8];
    int l;
    __m128 t[4], b[4];
    _mm256_store_si256((__m256i *)at, idx);
    for (l = 0; l < 8; l++)
        p[l] = img + at[l];
    for (l = 0; l < 4; l++) {
        t[l] = _mm_loadh_pi(_mm_castpd_ps(_mm_load_sd((const double *)p[2 * l])), (const __m64 *)p[2 * l + 1]);
        b[l] = _mm_loadh_pi(_mm_castpd_ps(_mm_load_sd((const double *)(p[2 * l] + stride))),
                            (const __m64 *)(p[2 * l + 1] + stride));
    }
    /* t[0] = (l0 pair, l1 pair), t[1] = (l2, l3), ...: lanes 0,1,4,5 | 2,3,6,7 before the shuffles */
    __m256 g0 = _mm256_insertf128_ps(_mm256_castps128_ps256(t[0]), t[2], 1);
    __m256 g1 = _mm256_insertf128_ps(_mm256_castps128_ps256(t[1]), t[3], 1);
    __m256 g2 = _mm256_insertf128_ps(_mm256_castps128_ps256(b[0]), b[2], 1);
    __m256 g3 = _mm256_insertf128_ps(_mm256_castps128_ps256(b[1]), b[3], 1);
    *t00 = _mm256_shuffle_ps(g0, g1, 0x88);
    *t01 = _mm256_shuffle_ps(g0, g1, 0xDD);
    *t10 = _mm256_shuffle_ps(g2, g3, 0x88);
    *t11 = _mm256_shuffle_ps(g2, g3, 0xDD);
}

__attribute__((target("avx2"))) static void
dvpmvs_window_sums_avx2(const float *img, int stride, const float *H, const dvpmvs_lanes *L, uint32_t active,
                        float *sws, float *swss, float *swrs)
{
    int k;
    int32_t keep[8] __attribute__((aligned(32)));
    for (k = 0; k < 8; k++)
        keep[k] = ((active >> k) & 1) ? -1 : 0;
    const __m256i live = _mm256_load_si256((const __m256i *)keep);
    const __m256 h0 = _mm256_set1_ps(H[0]), h1 = _mm256_set1_ps(H[1]), h2 = _mm256_set1_ps(H[2]);
    const __m256 h3 = _mm256_set1_ps(H[3]), h4 = _mm256_set1_ps(H[4]), h5 = _mm256_set1_ps(H[5]);
    const __m256 h6 = _mm256_set1_ps(H[6]), h7 = _mm256_set1_ps(H[7]), h8 = _mm256_set1_ps(H[8]);
    const __m256 one = _mm256_set1_ps(1.0f);
    const __m256i vstride = _mm256_set1_epi32(stride);
    __m256 a = _mm256_setzero_ps(), b = _mm256_setzero_ps(), c = _mm256_setzero_ps();
    for (k = 0; k < L->n; k++) {
        __m256 x = _mm256_loadu_ps(L->x[k]), y = _mm256_loadu_ps(L->y[k]);
        __m256 hz = _mm256_div_ps(one, _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h6, x), _mm256_mul_ps(h7, y)), h8));
        __m256 hx = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h0, x), _mm256_mul_ps(h1, y)), h2), hz);
        __m256 hy = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(h3, x), _mm256_mul_ps(h4, y)), h5), hz);
        __m256i xi = _mm256_cvttps_epi32(hx), yi = _mm256_cvttps_epi32(hy);
        __m256 fx = _mm256_sub_ps(hx, _mm256_cvtepi32_ps(xi)), fy = _mm256_sub_ps(hy, _mm256_cvtepi32_ps(yi));
        __m256i idx = _mm256_and_si256(_mm256_add_epi32(_mm256_mullo_epi32(yi, vstride), xi), live);
        __m256 t00, t01, t10, t11;
        dvpmvs_texels_avx2(img, stride, idx, &t00, &t01, &t10, &t11);
        __m256 top = _mm256_add_ps(t00, _mm256_mul_ps(fx, _mm256_sub_ps(t01, t00)));
        __m256 bottom = _mm256_add_ps(t10, _mm256_mul_ps(fx, _mm256_sub_ps(t11, t10)));
        __m256 s = _mm256_add_ps(top, _mm256_mul_ps(fy, _mm256_sub_ps(bottom, top)));
        __m256 ws = _mm256_mul_ps(_mm256_loadu_ps(L->w[k]), s);
        a = _mm256_add_ps(a, ws);
        b = _mm256_add_ps(b, _mm256_mul_ps(ws, s));
        c = _mm256_add_ps(c, _mm256_mul_ps(ws, _mm256_loadu_ps(L->v[k])));
    }
    _mm256_storeu_ps(sws, a);
    _mm256_storeu_ps(swss, b);
    _mm256_storeu_ps(swrs, c);
}
#endif

/* The best path this CPU runs, at most ``requested`` (a DVPMVS_SIMD_* value); it becomes the one
 * dvpmvs_window_sums takes. */
static int dvpmvs_simd_select(int requested)
{
    int level = DVPMVS_SIMD_SCALAR;
#ifdef DVPMVS_HAVE_X86_SIMD
    __builtin_cpu_init();
    if (requested >= DVPMVS_SIMD_AVX2 && __builtin_cpu_supports("avx2"))
        level = DVPMVS_SIMD_AVX2;
#endif
    dvpmvs_simd_level = level;
    return level;
}

static inline void dvpmvs_window_sums(const float *img, int stride, const float *H, const dvpmvs_lanes *L,
                                      uint32_t active, float *sws, float *swss, float *swrs)
{
#ifdef DVPMVS_HAVE_X86_SIMD
    if (dvpmvs_simd_level >= DVPMVS_SIMD_AVX2) {
        dvpmvs_window_sums_avx2(img, stride, H, L, active, sws, swss, swrs);
        return;
    }
#endif
    dvpmvs_window_sums_scalar(img, stride, H, L, active, sws, swss, swrs);
}

#endif
