/* Times two layouts of the matching kernel on one core: the house's batches (one window per
 * AVX2 lane, 8 windows of a pixel's hypotheses and sources at once, dvpmvs_batch_sums of
 * dvpmvs/patchmatch/_window_cost_simd.h, lane set-up included) against one window at a time with
 * 8 of its samples per lane and the homography broadcast, in one pass or in two (positions, then
 * texels, as the batch kernel does). Synthetic data: 7 sources of 800x600, windows of n samples
 * around pixels swept along rows, homographies near the identity.
 *
 *   gcc -O2 -ffp-contract=off -o /tmp/kernel_layouts scripts/kernel_layouts.c -lm
 *   /tmp/kernel_layouts 36   # the plain and anchor windows (11x11 sampled every 2 pixels)
 *   /tmp/kernel_layouts 9    # a deformed pixel's centre window (every 5 pixels)
 *
 * Prints ns per window matched for each layout, best of 3 rounds, and each layout's sum of
 * every window's sums (equal but for float rounding: the layouts add the samples in different
 * orders). Needs AVX2 and FMA (exit status 2 without them). */
#include "../dvpmvs/patchmatch/_window_cost_simd.h"
#include <stdio.h>
#include <stdlib.h>
#include <time.h>

#define WIDTH 800
#define HEIGHT 600
#define SOURCES 7
#define PIXELS 20000

static double now(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec + 1e-9 * t.tv_nsec;
}

/* A window's positions: 8 samples per lane, the homography broadcast; the texel indices and
 * bilinear fractions of samples k..k+7 into at, fx, fy. */
#define POSITIONS(k)                                                                                                   \
    do {                                                                                                               \
        __m256 xx = _mm256_loadu_ps(x + (k)), yy = _mm256_loadu_ps(y + (k));                                           \
        __m256 hz = _mm256_fmadd_ps(h[6], xx, _mm256_fmadd_ps(h[7], yy, h[8]));                                       \
        __m256 nx = _mm256_fmadd_ps(h[0], xx, _mm256_fmadd_ps(h[1], yy, h[2]));                                       \
        __m256 ny = _mm256_fmadd_ps(h[3], xx, _mm256_fmadd_ps(h[4], yy, h[5]));                                       \
        __m256 r = _mm256_div_ps(one, hz);                                                                             \
        __m256 hx = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(nx, r), zero), right);                                   \
        __m256 hy = _mm256_min_ps(_mm256_max_ps(_mm256_mul_ps(ny, r), zero), bottom);                                  \
        __m256i x0 = _mm256_min_epi32(_mm256_cvttps_epi32(hx), last_x);                                                \
        __m256i y0 = _mm256_min_epi32(_mm256_cvttps_epi32(hy), last_y);                                                \
        _mm256_store_ps(fx + (k), _mm256_sub_ps(hx, _mm256_cvtepi32_ps(x0)));                                          \
        _mm256_store_ps(fy + (k), _mm256_sub_ps(hy, _mm256_cvtepi32_ps(y0)));                                          \
        _mm256_store_si256((__m256i *)(at + (k)), _mm256_add_epi32(_mm256_mullo_epi32(y0, vstride), x0));             \
    } while (0)

/* The texels of samples k..k+7, read as pairs, and their weighted sums added to a, b, c. */
#define TEXELS(k)                                                                                                      \
    do {                                                                                                               \
        const int32_t *q = at + (k);                                                                                   \
        __m128 a01 = DVPMVS_PAIRS(img + q[0], img + q[1]), b01 = DVPMVS_PAIRS(below + q[0], below + q[1]);           \
        __m128 a45 = DVPMVS_PAIRS(img + q[4], img + q[5]), b45 = DVPMVS_PAIRS(below + q[4], below + q[5]);           \
        __m128 a23 = DVPMVS_PAIRS(img + q[2], img + q[3]), b23 = DVPMVS_PAIRS(below + q[2], below + q[3]);           \
        __m128 a67 = DVPMVS_PAIRS(img + q[6], img + q[7]), b67 = DVPMVS_PAIRS(below + q[6], below + q[7]);           \
        __m256 g0 = _mm256_insertf128_ps(_mm256_castps128_ps256(a01), a45, 1);                                         \
        __m256 g1 = _mm256_insertf128_ps(_mm256_castps128_ps256(a23), a67, 1);                                         \
        __m256 g2 = _mm256_insertf128_ps(_mm256_castps128_ps256(b01), b45, 1);                                         \
        __m256 g3 = _mm256_insertf128_ps(_mm256_castps128_ps256(b23), b67, 1);                                         \
        __m256 t00 = _mm256_shuffle_ps(g0, g1, 0x88), t01 = _mm256_shuffle_ps(g0, g1, 0xDD);                          \
        __m256 t10 = _mm256_shuffle_ps(g2, g3, 0x88), t11 = _mm256_shuffle_ps(g2, g3, 0xDD);                          \
        __m256 ax = _mm256_load_ps(fx + (k)), ay = _mm256_load_ps(fy + (k));                                           \
        __m256 top = _mm256_fmadd_ps(ax, _mm256_sub_ps(t01, t00), t00);                                                \
        __m256 low = _mm256_fmadd_ps(ax, _mm256_sub_ps(t11, t10), t10);                                                \
        __m256 s = _mm256_fmadd_ps(ay, _mm256_sub_ps(low, top), top);                                                  \
        __m256 ws = _mm256_mul_ps(_mm256_loadu_ps(w + (k)), s);                                                        \
        a = _mm256_add_ps(a, ws);                                                                                      \
        b = _mm256_fmadd_ps(ws, s, b);                                                                                 \
        c = _mm256_fmadd_ps(ws, _mm256_loadu_ps(v + (k)), c);                                                          \
    } while (0)

/* The sums of one window of n samples (n a multiple of 8, padded with weight 0) into out[0..2]:
 * each 8 samples' positions and texels in turn, or (two_pass) every position first. */
__attribute__((target("avx2,fma"))) static void window_by_samples(const float *img, int stride, int width, int height,
                                                                  const float *Hm, const float *x, const float *y,
                                                                  const float *w, const float *v, int n, int two_pass,
                                                                  float *out)
{
    __m256 h[9];
    int k;
    for (k = 0; k < 9; k++)
        h[k] = _mm256_set1_ps(Hm[k]);
    const __m256 right = _mm256_set1_ps((float)(width - 1)), bottom = _mm256_set1_ps((float)(height - 1));
    const __m256i last_x = _mm256_set1_epi32(width - 2), last_y = _mm256_set1_epi32(height - 2);
    const __m256i vstride = _mm256_set1_epi32(stride);
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
    const float *below = img + stride;
    int32_t at[DVPMVS_SLOT_SAMPLES] __attribute__((aligned(32)));
    float fx[DVPMVS_SLOT_SAMPLES] __attribute__((aligned(32))), fy[DVPMVS_SLOT_SAMPLES] __attribute__((aligned(32)));
    __m256 a = zero, b = zero, c = zero;
    if (two_pass) {
        for (k = 0; k < n; k += 8)
            POSITIONS(k);
        for (k = 0; k < n; k += 8)
            TEXELS(k);
    } else {
        for (k = 0; k < n; k += 8) {
            POSITIONS(k);
            TEXELS(k);
        }
    }
    __m256 abc = _mm256_hadd_ps(_mm256_hadd_ps(a, b), _mm256_hadd_ps(c, c));
    _mm_storeu_ps(out, _mm_add_ps(_mm256_castps256_ps128(abc), _mm256_extractf128_ps(abc, 1)));
}

int main(int argc, char **argv)
{
    int n = argc > 1 ? atoi(argv[1]) : 36, padded = (n + 7) & ~7, side = 1, step, i, k, l, round, layout;
    long p;
    static dvpmvs_windows table;
    static float H[PIXELS * 8][9], px[PIXELS][2];
    static int src[PIXELS * 8];
    float xs[DVPMVS_SLOT_SAMPLES], ys[DVPMVS_SLOT_SAMPLES], ws[DVPMVS_SLOT_SAMPLES], vs[DVPMVS_SLOT_SAMPLES];
    float *stack = aligned_alloc(64, sizeof(float) * SOURCES * WIDTH * HEIGHT);
    double best[3] = {1e9, 1e9, 1e9}, check[3] = {0, 0, 0};
    if (n < 1 || n > 248 || dvpmvs_simd_select(DVPMVS_SIMD_AVX2) != DVPMVS_SIMD_AVX2) {
        fprintf(stderr, "usage: kernel_layouts N (1 <= N <= 248 samples; needs AVX2 and FMA)\n");
        return 2;
    }
    while (side * side < n)
        side++;
    step = 10 / (side > 1 ? side - 1 : 1);
    for (p = 0; p < (long)SOURCES * WIDTH * HEIGHT; p++)
        stack[p] = (float)((p * 2654435761u) % 1000) / 1000.0f;
    srand(1);
    for (i = 0; i < PIXELS * 8; i++) {
        float s = 1.0f + 0.02f * ((rand() % 100) / 100.0f - 0.5f);
        float h[9] = {s, 0.01f, 5.0f * ((rand() % 100) / 100.0f - 0.5f), -0.01f, s, 3.0f, 1e-5f, 2e-5f, 1.0f};
        for (k = 0; k < 9; k++)
            H[i][k] = h[k];
        src[i] = i % SOURCES;
    }
    for (i = 0; i < PIXELS; i++) {
        px[i][0] = 100 + i % 600;
        px[i][1] = 100 + (i / 600) % 400;
    }
    for (round = 0; round < 3; round++)
        for (layout = 0; layout < 3; layout++) {
            double t0 = now();
            for (i = 0; i < PIXELS; i++) {
                /* a pixel's window, and 8 (hypothesis, source) pairs to match it in */
                float col = px[i][0], row = px[i][1];
                for (k = 0; k < padded; k++) {
                    int kk = k < n ? k : n - 1;
                    xs[k] = col + (kk % side) * step - 5;
                    ys[k] = row + (kk / side) * step - 5;
                    ws[k] = k < n ? 0.5f : 0;
                    vs[k] = k < n ? 0.3f : 0;
                }
                if (layout == 0) {
                    dvpmvs_batch batch;
                    float a[8], b[8], c[8];
                    table.n = n;
                    for (k = 0; k < n; k++) {
                        table.x[k][0] = xs[k];
                        table.y[k][0] = ys[k];
                        table.w[k][0] = ws[k];
                        table.v[k][0] = vs[k];
                    }
                    batch.count = 8;
                    for (l = 0; l < 8; l++) {
                        batch.slot[l] = 0;
                        batch.offset[l] = src[8 * i + l] * WIDTH * HEIGHT;
                        batch.width[l] = WIDTH;
                        batch.height[l] = HEIGHT;
                        for (k = 0; k < 9; k++)
                            batch.H[k][l] = H[8 * i + l][k];
                    }
                    dvpmvs_batch_sums(stack, WIDTH, &table, &batch, a, b, c);
                    for (l = 0; l < 8; l++)
                        check[layout] += (double)a[l] + b[l] + c[l];
                } else {
                    float out[4];
                    for (l = 0; l < 8; l++) {
                        window_by_samples(stack + src[8 * i + l] * WIDTH * HEIGHT, WIDTH, WIDTH, HEIGHT,
                                          H[8 * i + l], xs, ys, ws, vs, padded, layout == 2, out);
                        check[layout] += (double)out[0] + out[1] + out[2];
                    }
                }
            }
            double t = (now() - t0) / (PIXELS * 8.0);
            if (t < best[layout])
                best[layout] = t;
        }
    printf("windows of %d samples, ns per window: batches of 8 windows %.1f, 8 samples per lane %.1f (one pass), "
           "%.1f (two passes)\nsums: %.9g %.9g %.9g\n",
           n, 1e9 * best[0], 1e9 * best[1], 1e9 * best[2], check[0], check[1], check[2]);
    return 0;
}
