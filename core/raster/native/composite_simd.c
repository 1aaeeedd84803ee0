/* Gradient-free tile compositing, 16 pixels of a tile row at a time (SIMD).
 *
 * Built at first use by core/raster/native_build.py with the system C compiler
 * (GCC or Clang vector extensions; no intrinsics, so any target works) and called
 * through ctypes by core/raster/cpu_simd.py. Same semantics as the numba forward of
 * core/raster/cpu_backend.py, float32 only:
 *
 *   front to back over each tile's depth-sorted list, alpha = min(0.99, o exp(power)),
 *   skipped when power > 0 or alpha < 1/255 (NaN included), a pixel stops before T
 *   would fall below 1e-4.
 *
 * Why it is fast: a tile row is one 16-lane vector. Per list entry and row, every
 * lane is evaluated branch-free; lanes outside the Gaussian's ellipse get
 * alpha < 1/255 and change nothing. exp() is a vector polynomial (2^f fitted on
 * [-0.5, 0.5], relative error about 2 float32 ulps), the only difference from the exact kernel.
 * Rows whose pixels are all done are dropped from a 16-bit mask, so saturated rows
 * cost nothing.
 */
#include <math.h>
#include <stdint.h>
#if defined(__AVX__) || defined(__SSE4_1__)
#include <immintrin.h>
#elif defined(__aarch64__)
#include <arm_neon.h>
#endif
#include <stdlib.h>
#include <string.h>

#define TS 16 /* tile side in pixels: a tile row is TS lanes */

/* Native vector width, so that no target splits vectors through memory: 16 lanes
 * with AVX-512, 8 with AVX, 4 elsewhere (SSE, NEON). A tile row is NV vectors. */
#if defined(__AVX512F__)
#define VW 16
#elif defined(__AVX__)
#define VW 8
#else
#define VW 4
#endif
#define NV (TS / VW)

typedef float vf __attribute__((vector_size(VW * 4)));
typedef int32_t vi __attribute__((vector_size(VW * 4)));
typedef uint32_t vu __attribute__((vector_size(VW * 4)));

/* How many list entries pass between checks for rows whose pixels are all done. */
#define ROW_CHECK_EVERY 16

static inline vf sel(vi m, vf a, vf b) { return (vf)((m & (vi)a) | (~m & (vi)b)); }

/* min(a, b) written as "b if a > b else a": a NaN stays NaN (as in the reference). */
static inline vf min_keep_nan(vf a, vf b) { return sel(a > b, b, a); }

/* exp(p) for p <= 0, with p raised to floor (>= -86, where o exp(floor) < 1/255 so
 * that the raise changes no decision); NaN gives a finite value the caller masks
 * out. 2^n * 2^f with f in [-0.5, 0.5]. */
static inline vf exp_nonpos(vf p, float floor) {
    const vf zero = (vf){0};
    p = sel(p > floor, p, zero + floor);
    vf x = p * 1.44269504088896341f;
    vf r = x + 0.5f;                     /* n = floor(r), r in [-124, 0.5] */
    vi n = __builtin_convertvector(r, vi);  /* truncates toward zero */
    vf nf = __builtin_convertvector(n, vf);
    n += (vi)(nf > r);                   /* mask is -1: one less where truncation rounded up */
    nf = __builtin_convertvector(n, vf);
    vf f = x - nf;
    vf y = zero + 1.5332508e-4f;
    y = y * f + 1.3394701e-3f;
    y = y * f + 9.6184910e-3f;
    y = y * f + 5.5503423e-2f;
    y = y * f + 2.4022647e-1f;
    y = y * f + 6.9314720e-1f;
    y = y * f + 1.0f;
    vu bits = ((vu)(n + 127)) << 23;
    return y * (vf)bits;
}

/* Any lane set? One test instruction where the target has one. */
static inline int any_lane(vi m) {
#if defined(__AVX512F__)
    return _mm512_test_epi32_mask((__m512i)m, (__m512i)m) != 0;
#elif defined(__AVX__)
    return !_mm256_testz_si256((__m256i)m, (__m256i)m);
#elif defined(__SSE4_1__)
    return !_mm_testz_si128((__m128i)m, (__m128i)m);
#elif defined(__aarch64__)
    return vmaxvq_u32((uint32x4_t)m) != 0;
#else
    int32_t acc = 0;
    for (int l = 0; l < VW; l++) acc |= m[l];
    return acc != 0;
#endif
}

/* Alpha of one lane with libm's expf, as the numba kernel computes it. */
static inline float exact_alpha(float power, float o, float a_max) {
    const float alpha = o * expf(power);
    return alpha > a_max ? a_max : alpha;
}

static inline double clamp_d(double v, double lo, double hi) {
    return v < lo ? lo : (v > hi ? hi : v);
}

/* Pixels [*i0, *i1) of [0, n) whose centres (i + 0.5) lie within centre +- half.
 * The numba kernel clamps the same interval to each tile; clamping to the image first
 * and to the tile later gives the same pixels. */
static inline void span(double centre, double half, int64_t n, int32_t *i0, int32_t *i1) {
    const double eps = 1e-3;
    double a = ceil(clamp_d(centre - half - 0.5 - eps, -1.0, n + 1.0));
    double b = floor(clamp_d(centre + half - 0.5 + eps, -2.0, (double)n));
    *i0 = (int32_t)clamp_d(a, 0.0, (double)n);
    *i1 = (int32_t)clamp_d(b, -1.0, (double)(n - 1)) + 1;
}

/* Smallest power the vector exp must reach: below log(a_min / o) - 1, o exp(power) is
 * under 1/255 / e, so raising it there changes no decision. Opacities over about
 * 1e35 (infinity included) get NaN: their alphas take libm's expf, as the
 * reference's, since o exp(power) then depends on where exp underflows. */
static inline float exp_floor(float o, float a_min) {
    float f = logf(a_min / o) - 1.0f;
    f = f < -30.0f ? f : -30.0f;
    return f >= -86.0f ? f : NAN;
}

/* Pixel boxes [x0, x1) x [y0, y1) outside which Gaussians [lo, hi) cannot reach
 * alpha >= 1/255 (mode 1: the culling ellipse's extents in geo; mode 2: the image;
 * mode 0: empty), into box (N, 4), and their exp floors into floors (N). The
 * per-tile test is then four integer compares. */
void culling_boxes(int64_t lo, int64_t hi, const float *means2d, const float *opac,
                   const int8_t *mode, const double *geo, float a_min, int64_t width,
                   int64_t height, int32_t *box, float *floors) {
    for (int64_t g = lo; g < hi; g++) {
        int32_t *bx = box + 4 * g;
        floors[g] = mode[g] == 0 ? -30.0f : exp_floor(opac[g], a_min);
        if (mode[g] == 1) {
            span((double)means2d[2 * g], geo[5 * g], width, &bx[0], &bx[1]);
            span((double)means2d[2 * g + 1], geo[5 * g + 1], height, &bx[2], &bx[3]);
        } else if (mode[g] == 2) {
            bx[0] = 0, bx[1] = (int32_t)width, bx[2] = 0, bx[3] = (int32_t)height;
        } else {
            bx[0] = bx[1] = bx[2] = bx[3] = 0;
        }
    }
}

/* Composite tiles w, w + n_workers, ... into out_feat (H, W, C) and out_T (H, W).
 * means2d (N, 2), conics (N, 3), opac (N), feats (N, C) float32; ids/offsets the
 * tile lists; box (N, 4) and floors (N) from culling_boxes; consts = (0.5, 1, ALPHA_MIN, ALPHA_MAX, T_MIN). Returns 0, or -1 when out of memory. */
int composite_simd(int64_t w, int64_t n_workers, const float *means2d, const float *conics,
                   const float *opac, const float *feats, int64_t n_ch, const int64_t *ids,
                   const int64_t *offsets, int64_t n_tiles, int64_t tiles_x, int64_t width,
                   int64_t height, const int32_t *box, const float *floors, const float *consts,
                   float *out_feat, float *out_T) {
    const float a_min = consts[2], a_max = consts[3], t_min = consts[4];
    const vf zero = (vf){0}, one = zero + 1.0f;
    /* alphas this close to 1/255 are recomputed exactly (the vector exp is 2 ulps off) */
    const vf near_lo = zero + a_min * (1.0f - 2e-5f), near_hi = zero + a_min * (1.0f + 2e-5f);
    const vi none = (vi){0};
    vf lane[NV];
    for (int v = 0; v < NV; v++)
        for (int l = 0; l < VW; l++) lane[v][l] = (float)(v * VW + l) + 0.5f;
    vf T[TS][NV];
    vi live[TS][NV]; /* -1 while the pixel composites */
    vf *F = NULL;    /* [row][channel][NV] */
    if (n_ch > 0 && posix_memalign((void **)&F, 64, sizeof(vf) * TS * NV * (size_t)n_ch) != 0)
        return -1;
    for (int64_t t = w; t < n_tiles; t += n_workers) {
        const int64_t lo = offsets[t], hi = offsets[t + 1];
        if (hi == lo) continue;
        const int64_t x0 = (t % tiles_x) * TS, y0 = (t / tiles_x) * TS;
        const int64_t x1 = x0 + TS < width ? x0 + TS : width;
        const int64_t y1 = y0 + TS < height ? y0 + TS : height;
        const int nx = (int)(x1 - x0), ny = (int)(y1 - y0);
        uint32_t rows_alive = 0;
        for (int r = 0; r < TS; r++) {
            for (int v = 0; v < NV; v++) {
                T[r][v] = one;
                live[r][v] = r < ny ? (lane[v] < (float)nx) : none;
            }
            if (r < ny) rows_alive |= 1u << r;
        }
        if (n_ch > 0) memset(F, 0, sizeof(vf) * TS * NV * (size_t)n_ch);
        for (int64_t i = lo; i < hi && rows_alive; i++) {
            if ((i - lo) % ROW_CHECK_EVERY == ROW_CHECK_EVERY - 1) {
                /* drop rows whose pixels are all done; a dropped row would change nothing */
                for (uint32_t rows = rows_alive; rows; rows &= rows - 1u) {
                    const int r = __builtin_ctz(rows);
                    vi any = live[r][0];
                    for (int v = 1; v < NV; v++) any |= live[r][v];
                    int alive = 0;
                    for (int l = 0; l < VW; l++) alive |= any[l];
                    if (!alive) rows_alive &= ~(1u << r);
                }
            }
            const int64_t g = ids[i];
            const int32_t *bx = box + 4 * g;
            const int64_t c0 = bx[0] > x0 ? bx[0] : x0, c1 = bx[1] < x1 ? bx[1] : x1;
            if (c0 >= c1) continue;
            const int64_t r0 = bx[2] > y0 ? bx[2] : y0, r1 = bx[3] < y1 ? bx[3] : y1;
            if (r0 >= r1) continue;
            uint32_t rows = rows_alive & (((1u << (r1 - y0)) - 1u) & ~((1u << (r0 - y0)) - 1u));
            if (!rows) continue;
            const float mx = means2d[2 * g], my = means2d[2 * g + 1];
            const float a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
            const float o = opac[g], p_floor = floors[g];
            const float *f_g = feats + g * n_ch;
            vf dx[NV], adx[NV], bdx[NV];
            for (int v = 0; v < NV; v++) {
                dx[v] = ((float)x0 + lane[v]) - mx;
                adx[v] = a * dx[v] * dx[v];
                bdx[v] = b * dx[v];
            }
            for (; rows; rows &= rows - 1u) {
                const int r = __builtin_ctz(rows);
                const float dy = ((float)(y0 + r) + 0.5f) - my;
                const float cdy = c * dy * dy;
                vf wgt[NV];
                for (int v = 0; v < NV; v++) {
                    /* operation for operation the numba kernel's power (the build
                     * fuses no multiply-add): flat Gaussians cancel large terms */
                    const vf power = -0.5f * (adx[v] + cdy) - bdx[v] * dy;
                    vf alpha;
                    if (p_floor == p_floor) {
                        alpha = o * exp_nonpos(sel(power > 0.0f, zero, power), p_floor);
                    } else { /* huge or infinite opacity: libm, lane by lane */
                        for (int l = 0; l < VW; l++) alpha[l] = o * expf(power[l]);
                    }
                    alpha = min_keep_nan(alpha, zero + a_max);
                    alpha = sel(power <= 0.0f, alpha, zero + NAN);
                    const vi near = (alpha > near_lo) & (alpha < near_hi);
                    if (any_lane(near)) {
                        for (int l = 0; l < VW; l++)
                            if (near[l]) alpha[l] = exact_alpha(power[l], o, a_max);
                    }
                    const vi ok = (alpha >= a_min) & live[r][v];
                    const vf Tv = T[r][v];
                    const vf test = Tv * (1.0f - alpha);
                    const vi fin = ok & (test < t_min);
                    const vi take = ok & ~fin;
                    wgt[v] = sel(take, alpha * Tv, zero);
                    T[r][v] = sel(take, test, Tv);
                    live[r][v] &= ~fin;
                }
                vf *F_r = F + (int64_t)r * n_ch * NV;
                for (int64_t ch = 0; ch < n_ch; ch++)
                    for (int v = 0; v < NV; v++) F_r[ch * NV + v] += f_g[ch] * wgt[v];
            }
        }
        for (int r = 0; r < ny; r++) {
            const int64_t py = y0 + r;
            for (int l = 0; l < nx; l++) {
                const int64_t px = x0 + l;
                const int v = l / VW, k = l % VW;
                out_T[py * width + px] = T[r][v][k];
                float *dst = out_feat + (py * width + px) * n_ch;
                for (int64_t ch = 0; ch < n_ch; ch++) dst[ch] = F[(r * n_ch + ch) * NV + v][k];
            }
        }
    }
    free(F);
    return 0;
}
