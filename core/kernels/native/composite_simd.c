/* Tile compositing, 16 pixels of a tile row at a time (SIMD): forward and backward.
 *
 * Built at first use by core/native_build.py with the system C compiler (GCC or
 * Clang vector extensions) and called through ctypes by core/raster/cpu_simd.py.
 * Same semantics as the numba kernels of core/raster/cpu_backend.py, float32 only:
 *
 *   front to back over each tile's depth-sorted list, alpha = min(0.99, o exp(power)),
 *   skipped when power > 0 or alpha < 1/255 (NaN included), a pixel stops before T
 *   would fall below 1e-4; the backward walks back to front, 3DGS-style, with its
 *   running state in float32 (numba's is float64; gradients agree to float32 rounding).
 *
 * Why it is fast: a tile row is one or a few vectors. Per list entry and row, every
 * lane is evaluated branch-free; lanes outside the Gaussian's ellipse get
 * alpha < 1/255 and change nothing. exp() is a vector polynomial (2^f fitted on
 * [-0.5, 0.5], about 2 float32 ulps); lanes near a decision (alpha at 1/255, o exp
 * at the 0.99 clamp) take libm's expf, and the power is computed operation for
 * operation as numba does (the build fuses no multiply-add), so every decision is
 * numba's. Rows whose pixels are all done drop out of a 16-bit mask.
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

/* How many list entries ahead a pass prefetches a Gaussian's data (its box, centre,
 * conic, opacity, features and, backward, its gradient row). A tile's list is in depth
 * order, so these reads land anywhere in arrays of megabytes; on a trained model's
 * small splats, waiting for them was about a third of both passes. */
#define PREFETCH_AHEAD 4

static inline void prefetch_gaussian(int64_t g, int64_t n_ch, const int32_t *box,
                                     const float *means2d, const float *conics,
                                     const float *opac, const float *floors,
                                     const float *feats) {
    __builtin_prefetch(box + 4 * g);
    __builtin_prefetch(means2d + 2 * g);
    __builtin_prefetch(conics + 3 * g);
    __builtin_prefetch(opac + g);
    __builtin_prefetch(floors + g);
    __builtin_prefetch(feats + g * n_ch);
}

static inline vf sel(vi m, vf a, vf b) { return (vf)((m & (vi)a) | (~m & (vi)b)); }

/* a * b + c, fused (one rounding) where the target has the instruction. The build
 * forbids the compiler to fuse on its own, so that the power (whose sign and size
 * decide which pixels a Gaussian reaches) is numba's operation for operation; the
 * exp polynomial and the sums, which decide nothing, fuse here explicitly. */
static inline vf fmadd(vf a, vf b, vf c) {
#if defined(__AVX512F__)
    return (vf)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c);
#elif defined(__FMA__) && defined(__AVX__)
    return (vf)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
#elif defined(__FMA__)
    return (vf)_mm_fmadd_ps((__m128)a, (__m128)b, (__m128)c);
#elif defined(__aarch64__)
    return (vf)vfmaq_f32((float32x4_t)c, (float32x4_t)a, (float32x4_t)b);
#else
    return a * b + c;
#endif
}

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
    y = fmadd(y, f, zero + 1.3394701e-3f);
    y = fmadd(y, f, zero + 9.6184910e-3f);
    y = fmadd(y, f, zero + 5.5503423e-2f);
    y = fmadd(y, f, zero + 2.4022647e-1f);
    y = fmadd(y, f, zero + 6.9314720e-1f);
    y = fmadd(y, f, zero + 1.0f);
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

/* Alphas of a row vector from its powers: min(a_max, o exp(power)), NaN where the
 * power is positive or NaN (the pixel is skipped). *G_out gets exp(power) and
 * *clamped the lanes where o exp(power) > a_max (no gradient to o or the footprint).
 * p_floor: see exp_floor (NaN: libm throughout). */
static inline vf row_alpha(vf power, float o, float p_floor, float a_min, float a_max,
                           vf *G_out, vi *clamped) {
    const vf zero = (vf){0};
    vf G;
    if (p_floor == p_floor) {
        G = exp_nonpos(sel(power > 0.0f, zero, power), p_floor);
    } else { /* huge or infinite opacity: libm, lane by lane */
        for (int l = 0; l < VW; l++) G[l] = expf(power[l]);
    }
    vf raw = o * G;
    /* lanes this close to a decision take libm's expf, as numba's kernel */
    const vi near = ((raw > a_min * (1.0f - 2e-5f)) & (raw < a_min * (1.0f + 2e-5f))) |
                    ((raw > a_max * (1.0f - 2e-5f)) & (raw < a_max * (1.0f + 2e-5f)));
    if (any_lane(near)) {
        for (int l = 0; l < VW; l++)
            if (near[l]) {
                G[l] = expf(power[l]);
                raw[l] = o * G[l];
            }
    }
    *G_out = G;
    *clamped = raw > a_max;
    const vf alpha = min_keep_nan(raw, zero + a_max);
    return sel(power <= 0.0f, alpha, zero + NAN);
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

/* The lanes of x summed in float64, pairwise: the upper half of the lanes converted
 * and added onto the lower half, halving until one is left. A backward entry takes
 * 6 + C of these; summed lane after lane, each was a chain of VW dependent adds, about
 * a sixth of a training backward on small splats. */
typedef double vd2 __attribute__((vector_size(16)));
typedef float vf2 __attribute__((vector_size(8)));
#if VW >= 8
typedef double vd4 __attribute__((vector_size(32)));
typedef float vf4 __attribute__((vector_size(16)));
#endif
#if VW == 16
typedef double vd8 __attribute__((vector_size(64)));
typedef float vf8 __attribute__((vector_size(32)));
#endif
#if (defined(__clang__) || __GNUC__ >= 12) && !defined(GLINT_NO_SHUFFLEVECTOR)
/* __builtin_shufflevector (GCC 12+, Clang); tests build the fallback with
 * -DGLINT_NO_SHUFFLEVECTOR */
static inline double hsum(vf x) {
#if VW == 16
    const vf8 a = __builtin_shufflevector(x, x, 0, 1, 2, 3, 4, 5, 6, 7);
    const vf8 b = __builtin_shufflevector(x, x, 8, 9, 10, 11, 12, 13, 14, 15);
    const vd8 s8 = __builtin_convertvector(a, vd8) + __builtin_convertvector(b, vd8);
    const vd4 s4 = __builtin_shufflevector(s8, s8, 0, 1, 2, 3) +
                   __builtin_shufflevector(s8, s8, 4, 5, 6, 7);
#elif VW == 8
    const vf4 a = __builtin_shufflevector(x, x, 0, 1, 2, 3);
    const vf4 b = __builtin_shufflevector(x, x, 4, 5, 6, 7);
    const vd4 s4 = __builtin_convertvector(a, vd4) + __builtin_convertvector(b, vd4);
#endif
#if VW >= 8
    const vd2 s2 = __builtin_shufflevector(s4, s4, 0, 1) + __builtin_shufflevector(s4, s4, 2, 3);
#else
    const vf2 a = __builtin_shufflevector(x, x, 0, 1);
    const vf2 b = __builtin_shufflevector(x, x, 2, 3);
    const vd2 s2 = __builtin_convertvector(a, vd2) + __builtin_convertvector(b, vd2);
#endif
    return s2[0] + s2[1];
}
#else /* older compilers: the same pairwise sums, lane by lane */
static inline double hsum(vf x) {
    double s[VW];
    for (int l = 0; l < VW; l++) s[l] = (double)x[l];
    for (int w = VW / 2; w >= 1; w /= 2)
        for (int l = 0; l < w; l++) s[l] += s[l + w];
    return s[0];
}
#endif

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

/* A tile's pixel bounds [x0, x1) x [y0, y1), clipped to the image. */
typedef struct {
    int64_t x0, y0, x1, y1;
    int nx, ny;
} Tile;

static inline Tile tile_at(int64_t t, int64_t tiles_x, int64_t width, int64_t height) {
    Tile tl;
    tl.x0 = (t % tiles_x) * TS;
    tl.y0 = (t / tiles_x) * TS;
    tl.x1 = tl.x0 + TS < width ? tl.x0 + TS : width;
    tl.y1 = tl.y0 + TS < height ? tl.y0 + TS : height;
    tl.nx = (int)(tl.x1 - tl.x0);
    tl.ny = (int)(tl.y1 - tl.y0);
    return tl;
}

/* The tile rows (bit r = row y0 + r) a Gaussian's pixel box covers; 0 when the box
 * misses the tile. */
static inline uint32_t box_rows(const int32_t *bx, Tile tl) {
    const int64_t c0 = bx[0] > tl.x0 ? bx[0] : tl.x0, c1 = bx[1] < tl.x1 ? bx[1] : tl.x1;
    const int64_t r0 = bx[2] > tl.y0 ? bx[2] : tl.y0, r1 = bx[3] < tl.y1 ? bx[3] : tl.y1;
    if (c0 >= c1 || r0 >= r1) return 0;
    return ((1u << (r1 - tl.y0)) - 1u) & ~((1u << (r0 - tl.y0)) - 1u);
}

/* Per-lane terms of a Gaussian's power that do not depend on the row: dx, a dx²,
 * b dx (the numba kernel's operation order). */
static inline void lane_terms(const vf lane[NV], int64_t x0, float mx, float a, float b,
                              vf dx[NV], vf adx[NV], vf bdx[NV]) {
    for (int v = 0; v < NV; v++) {
        dx[v] = ((float)x0 + lane[v]) - mx;
        adx[v] = a * dx[v] * dx[v];
        bdx[v] = b * dx[v];
    }
}

/* Composite tiles w, w + n_workers, ... into out_feat (H, W, C), out_T (H, W) and,
 * unless NULL, out_last (H, W): the count of list entries up to the pixel's last
 * contributing one, which the backward starts from. means2d (N, 2), conics (N, 3),
 * opac (N), feats (N, C) float32; ids/offsets the tile lists; box (N, 4) and floors
 * (N) from culling_boxes; consts = (0.5, 1, ALPHA_MIN, ALPHA_MAX, T_MIN). Returns 0,
 * or -1 when out of memory. */
int composite_simd(int64_t w, int64_t n_workers, const float *means2d, const float *conics,
                   const float *opac, const float *feats, int64_t n_ch, const int64_t *ids,
                   const int64_t *offsets, int64_t n_tiles, int64_t tiles_x, int64_t width,
                   int64_t height, const int32_t *box, const float *floors, const float *consts,
                   float *out_feat, float *out_T, int32_t *out_last) {
    const float a_min = consts[2], a_max = consts[3], t_min = consts[4];
    const vf zero = (vf){0}, one = zero + 1.0f;
    const vi none = (vi){0};
    vf lane[NV];
    for (int v = 0; v < NV; v++)
        for (int l = 0; l < VW; l++) lane[v][l] = (float)(v * VW + l) + 0.5f;
    vf T[TS][NV];
    vi live[TS][NV]; /* -1 while the pixel composites */
    vi last[TS][NV];
    vf *F = NULL;    /* [row][channel][NV] */
    if (n_ch > 0 && posix_memalign((void **)&F, 64, sizeof(vf) * TS * NV * (size_t)n_ch) != 0)
        return -1;
    for (int64_t t = w; t < n_tiles; t += n_workers) {
        const int64_t lo = offsets[t], hi = offsets[t + 1];
        if (hi == lo) continue;
        const Tile tl = tile_at(t, tiles_x, width, height);
        const int64_t x0 = tl.x0, y0 = tl.y0;
        const int nx = tl.nx, ny = tl.ny;
        uint32_t rows_alive = 0;
        for (int r = 0; r < TS; r++) {
            for (int v = 0; v < NV; v++) {
                T[r][v] = one;
                live[r][v] = r < ny ? (lane[v] < (float)nx) : none;
                last[r][v] = none;
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
            if (i + PREFETCH_AHEAD < hi)
                prefetch_gaussian(ids[i + PREFETCH_AHEAD], n_ch, box, means2d, conics, opac,
                                  floors, feats);
            uint32_t rows = rows_alive & box_rows(box + 4 * g, tl);
            if (!rows) continue;
            const float mx = means2d[2 * g], my = means2d[2 * g + 1];
            const float a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
            const float o = opac[g], p_floor = floors[g];
            const float *f_g = feats + g * n_ch;
            vf dx[NV], adx[NV], bdx[NV];
            lane_terms(lane, x0, mx, a, b, dx, adx, bdx);
            for (; rows; rows &= rows - 1u) {
                const int r = __builtin_ctz(rows);
                const float dy = ((float)(y0 + r) + 0.5f) - my;
                const float cdy = c * dy * dy;
                vf wgt[NV];
                for (int v = 0; v < NV; v++) {
                    /* operation for operation the numba kernel's power (the build
                     * fuses no multiply-add): flat Gaussians cancel large terms */
                    const vf power = -0.5f * (adx[v] + cdy) - bdx[v] * dy;
                    vf G;
                    vi clamped;
                    const vf alpha = row_alpha(power, o, p_floor, a_min, a_max, &G, &clamped);
                    const vi ok = (alpha >= a_min) & live[r][v];
                    const vf Tv = T[r][v];
                    const vf test = Tv * (1.0f - alpha);
                    const vi fin = ok & (test < t_min);
                    const vi take = ok & ~fin;
                    wgt[v] = sel(take, alpha * Tv, zero);
                    T[r][v] = sel(take, test, Tv);
                    live[r][v] &= ~fin;
                    last[r][v] = (take & (none + (int32_t)(i - lo + 1))) | (~take & last[r][v]);
                }
                vf *F_r = F + (int64_t)r * n_ch * NV;
                for (int64_t ch = 0; ch < n_ch; ch++) {
                    const vf f_ch = (vf){0} + f_g[ch];
                    for (int v = 0; v < NV; v++)
                        F_r[ch * NV + v] = fmadd(f_ch, wgt[v], F_r[ch * NV + v]);
                }
            }
        }
        for (int r = 0; r < ny; r++) {
            const int64_t py = y0 + r;
            for (int l = 0; l < nx; l++) {
                const int64_t px = x0 + l;
                const int v = l / VW, k = l % VW;
                out_T[py * width + px] = T[r][v][k];
                if (out_last) out_last[py * width + px] = last[r][v][k];
                float *dst = out_feat + (py * width + px) * n_ch;
                for (int64_t ch = 0; ch < n_ch; ch++) dst[ch] = F[(r * n_ch + ch) * NV + v][k];
            }
        }
    }
    free(F);
    return 0;
}

/* ---- backward ------------------------------------------------------------------ */

/* Gradients of tiles w, w + n_workers, ..., back to front, added into
 * gbuf[w, g, :] = (d means2d (2), d conic (3), d opacity, d features (C)), float64,
 * gbuf of shape (n_workers, N, 6 + C). final_T, last: the forward's outputs;
 * grad_feat (H, W, C), grad_alpha (H, W): the incoming gradients. With T_before =
 * T_after / (1 - alpha) and R the suffix sum of alpha_k T_k (g . f_k):
 *   dL/dalpha = T_before (g . f) - R / (1 - alpha) + g_alpha T_final / (1 - alpha).
 *
 * The running state (T, R) and each Gaussian's sums over one tile are float32 vectors,
 * a whole tile row per vector, as 3DGS's CUDA backward keeps them; each tile's sums
 * are added into gbuf in float64. (The numba kernel keeps float64 state; the two agree
 * to float32 rounding, tests/test_raster_simd.py.) Float64 state, half a row per
 * vector, cost twice the vector work in the per-channel loop.
 * Returns 0, or -1 when out of memory. */
int composite_simd_backward(int64_t w, int64_t n_workers, const float *means2d,
                            const float *conics, const float *opac, const float *feats,
                            int64_t n_ch, const int64_t *ids, const int64_t *offsets,
                            int64_t n_tiles, int64_t tiles_x, int64_t width, int64_t height,
                            const int32_t *box, const float *floors, const float *consts,
                            const float *final_T, const int32_t *last, const float *grad_feat,
                            const float *grad_alpha, int64_t n_gauss, double *gbuf) {
    const float a_min = consts[2], a_max = consts[3];
    const vf zero = (vf){0};
    const vi none = (vi){0};
    vf lane[NV];
    for (int v = 0; v < NV; v++)
        for (int l = 0; l < VW; l++) lane[v][l] = (float)(v * VW + l) + 0.5f;
    vf Tc[TS][NV], R[TS][NV], gaT[TS][NV];
    vi lastv[TS][NV];
    int32_t row_last[TS];
    vf *Gt = NULL, *acc_f = NULL; /* dL/dfeatures per pixel [row][ch][NV]; per channel */
    const size_t nc = n_ch > 0 ? (size_t)n_ch : 1;
    if (posix_memalign((void **)&Gt, 64, sizeof(vf) * TS * NV * nc) != 0 ||
        posix_memalign((void **)&acc_f, 64, sizeof(vf) * nc) != 0) {
        free(Gt);
        return -1;
    }
    double *gb = gbuf + (size_t)w * (size_t)n_gauss * (size_t)(6 + n_ch);
    for (int64_t t = w; t < n_tiles; t += n_workers) {
        const int64_t lo = offsets[t], hi = offsets[t + 1];
        if (hi == lo) continue;
        const Tile tl = tile_at(t, tiles_x, width, height);
        const int64_t x0 = tl.x0, y0 = tl.y0;
        const int nx = tl.nx, ny = tl.ny;
        int32_t n_last = 0;
        for (int r = 0; r < TS; r++) {
            row_last[r] = 0;
            for (int l = 0; l < TS; l++) {
                const int v = l / VW, k = l % VW;
                if (r < ny && l < nx) {
                    const int64_t p = (y0 + r) * width + (x0 + l);
                    const float Tf = final_T[p];
                    Tc[r][v][k] = Tf;
                    gaT[r][v][k] = grad_alpha[p] * Tf;
                    lastv[r][v][k] = last[p];
                    for (int64_t ch = 0; ch < n_ch; ch++)
                        Gt[((int64_t)r * n_ch + ch) * NV + v][k] = grad_feat[p * n_ch + ch];
                    if (last[p] > row_last[r]) row_last[r] = last[p];
                } else { /* outside the image: never contributes */
                    Tc[r][v][k] = 1.0f;
                    gaT[r][v][k] = 0.0f;
                    lastv[r][v][k] = 0;
                    for (int64_t ch = 0; ch < n_ch; ch++) Gt[((int64_t)r * n_ch + ch) * NV + v][k] = 0.0f;
                }
                R[r][v][k] = 0.0f;
            }
            if (row_last[r] > n_last) n_last = row_last[r];
        }
        if (n_last > hi - lo) n_last = (int32_t)(hi - lo); /* a corrupt count reads no further */
        for (int64_t i = lo + n_last - 1; i >= lo; i--) {
            const int32_t kk = (int32_t)(i - lo);
            const int64_t g = ids[i];
            if (i - PREFETCH_AHEAD >= lo) { /* the walk goes back to front */
                const int64_t gp = ids[i - PREFETCH_AHEAD];
                prefetch_gaussian(gp, n_ch, box, means2d, conics, opac, floors, feats);
                const double *row = gb + (size_t)gp * (size_t)(6 + n_ch);
                for (int64_t k = 0; k < 6 + n_ch; k += 8) /* 8 doubles: a 64-byte line */
                    __builtin_prefetch(row + k, 1);
            }
            uint32_t rows = box_rows(box + 4 * g, tl);
            for (uint32_t m = rows; m; m &= m - 1u) /* rows whose pixels all ended earlier */
                if (kk >= row_last[__builtin_ctz(m)]) rows &= ~(1u << __builtin_ctz(m));
            if (!rows) continue;
            const float mx = means2d[2 * g], my = means2d[2 * g + 1];
            const float a = conics[3 * g], b = conics[3 * g + 1], c = conics[3 * g + 2];
            const float o = opac[g], p_floor = floors[g];
            const float *f_g = feats + g * n_ch;
            for (int64_t ch = 0; ch < n_ch; ch++) acc_f[ch] = zero;
            vf s_mx = zero, s_my = zero, s_a = zero, s_b = zero, s_c = zero, s_o = zero;
            const vi kv = none + kk;
            vf dx[NV], adx[NV], bdx[NV];
            lane_terms(lane, x0, mx, a, b, dx, adx, bdx);
            int touched = 0;
            for (; rows; rows &= rows - 1u) {
                const int r = __builtin_ctz(rows);
                const float dy = ((float)(y0 + r) + 0.5f) - my;
                const float cdy = c * dy * dy;
                for (int v = 0; v < NV; v++) {
                    const vf power = -0.5f * (adx[v] + cdy) - bdx[v] * dy;
                    vf G;
                    vi clamped;
                    const vf alpha = row_alpha(power, o, p_floor, a_min, a_max, &G, &clamped);
                    const vi m = (alpha >= a_min) & (kv < lastv[r][v]);
                    if (!any_lane(m)) continue;
                    touched = 1;
                    const vf al = sel(m, alpha, zero);
                    const vf one_m = 1.0f - al;
                    const vf inv = 1.0f / one_m; /* one division for both uses below */
                    const vf Tb = Tc[r][v] * inv;
                    const vf wgt = al * Tb;
                    vf gf = zero;
                    const vf *Gr = Gt + (int64_t)r * n_ch * NV + v;
                    for (int64_t ch = 0; ch < n_ch; ch++) {
                        const vf gc = Gr[ch * NV];
                        gf = fmadd(gc, zero + f_g[ch], gf);
                        acc_f[ch] = fmadd(wgt, gc, acc_f[ch]);
                    }
                    const vf d_alpha = fmadd(Tb, gf, (gaT[r][v] - R[r][v]) * inv);
                    R[r][v] = fmadd(wgt, gf, R[r][v]);
                    Tc[r][v] = Tb;
                    const vi mc = m & ~clamped;
                    const vf d_pow = sel(mc, al * d_alpha, zero);
                    s_mx = fmadd(a * dx[v] + b * dy, d_pow, s_mx);
                    s_my = fmadd(c * dy + b * dx[v], d_pow, s_my);
                    s_a = fmadd(-0.5f * dx[v] * dx[v], d_pow, s_a);
                    s_b = fmadd(-dx[v] * dy, d_pow, s_b);
                    s_c = fmadd((zero - 0.5f * dy * dy), d_pow, s_c);
                    s_o += sel(mc, G * d_alpha, zero);
                }
            }
            if (touched) {
                double *out = gb + (size_t)g * (size_t)(6 + n_ch);
                out[0] += hsum(s_mx);
                out[1] += hsum(s_my);
                out[2] += hsum(s_a);
                out[3] += hsum(s_b);
                out[4] += hsum(s_c);
                out[5] += hsum(s_o);
                for (int64_t ch = 0; ch < n_ch; ch++) out[6 + ch] += hsum(acc_f[ch]);
            }
        }
    }
    free(Gt);
    free(acc_f);
    return 0;
}
