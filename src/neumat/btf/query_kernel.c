/* Triple Plane BTF queries (neumat.btf.neural.TriplePlane), fused: for a tile of T queries,
 * the half/difference frame, the three bilinear plane fetches and the whole MLP, with the tile's
 * activations in L1 cache and the planes in L2/L3 (see neumat/btf/query.py, which compiles and
 * loads this file via neumat.cbuild). torch's path runs each of these as a separate pass over
 * memory and the fetches as gathers + batched gemv; tests/test_btf_query.py checks this file
 * against it.
 *
 *   u (N, 2), wi, wo (N, 3)     texture coordinates in [0, 1)^2 (wrap) and unit directions
 *   feat_u (N, Cu) or NULL      positional features to use in place of the f_U fetch (the hook
 *                               texture synthesis uses: its own features for each query)
 *   fu (Hu, Wu, Cu), fh (R, R, C), fd (R, R, C)   the planes, row-major, channels last
 *   L layers, dims (L + 1): widths in -> ... -> 3; params: W (out x in, row-major) and b of
 *   each layer in turn (nn.Linear layout), ReLU between layers
 *   out (N, 3): max(expm1(y), 0), or y itself (log(1 + RGB)) when raw
 *
 * btf_triple_plane_hpb: the same query with f_U synthesised by histogram-preserving blending
 * inside the tile loop (struct hpb below; float64 u, unbounded; its Gaussianised plane in
 * float16, which holds HPB's values exactly: neumat.btf.synthesis.hpb.gaussianise rounds them);
 * hpb_features: those features
 * alone (neumat.btf.synthesis.kernel). Both run the same tile code: the same decorrelated q.
 * btf_triple_plane_hex: f_U synthesised by hex-tiling (neumat.btf.synthesis.hextile) on the
 * same grid, hash and taps (struct hpb with `hex` set; its features in float16 as HPB's plane,
 * which hextile._rounded rounds them to), each vertex's luminance linear in its bilinear
 * features (`lumw`), blended in hex_fill8 (8 channels) or hex_fill_c.
 *
 * Vector width and register blocking follow the target ISA as in fit_step.c: accumulators of
 * an AJ x AS block plus its inputs fit the register file (32 or 16 vector registers).
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#include <string.h>
#if defined(__AVX__)
#include <immintrin.h>
#endif

#if defined(__AVX512F__)
#define VL 16
#define NREG 32
#elif defined(__AVX__)
#define VL 8
#define NREG 16
#elif defined(__aarch64__)
#define VL 4
#define NREG 32
#else
#define VL 4
#define NREG 16
#endif
#if NREG >= 32
enum { AJ = 7, AS = 2 };
#else
enum { AJ = 6, AS = 2 };
#endif
#define LUT_REG 128  /* the LUT size hpb_fill_c looks up in registers (AVX-512) */
#define T 64        /* queries per tile: a multiple of AS * VL for every VL */
#define MAXW 128    /* widest layer the scratch holds */

typedef float vf __attribute__((vector_size(4 * VL), aligned(4), may_alias));  /* may_alias: it reads and writes float arrays */
typedef int vi __attribute__((vector_size(4 * VL), aligned(4), may_alias));
typedef uint64_t pair_t __attribute__((may_alias));  /* two floats read as one 64-bit word */

static inline vf vload(const float *p) { return *(const vf *)p; }
static inline void st(float *p, vf v) { *(vf *)p = v; }
static inline vf splat(float a) { return (vf){0} + a; }
static inline vf relu(vf z) { return (vf)((vi)z & (z > 0)); }  /* mask: all ones where z > 0 */

/* Y (J x T) = A X + b, ReLU'd if `act`; A (J x K) row-major, X (K x T). JB rows x AS
 * vectors of queries per block; JB and act are constants after inlining. */
static inline __attribute__((always_inline)) void
layer_block(int JB, int j0, int K, const float *A, const float *b, const float *X, float *Y,
            int act)
{
    for (int s = 0; s < T; s += AS * VL) {
        vf acc[AJ][AS];
        for (int j = 0; j < JB; j++)
            for (int q = 0; q < AS; q++)
                acc[j][q] = splat(b[j0 + j]);
        for (int k = 0; k < K; k++) {
            vf x[AS];
            for (int q = 0; q < AS; q++)
                x[q] = vload(X + k * T + s + q * VL);
            for (int j = 0; j < JB; j++) {
                float a = A[(j0 + j) * K + k];
                for (int q = 0; q < AS; q++)
                    acc[j][q] += a * x[q];
            }
        }
        for (int j = 0; j < JB; j++)
            for (int q = 0; q < AS; q++)
                st(Y + (j0 + j) * T + s + q * VL, act ? relu(acc[j][q]) : acc[j][q]);
    }
}

static void layer(int J, int K, const float *A, const float *b, const float *X, float *Y,
                  int act)
{
    int j0 = 0;
    for (; j0 + AJ <= J; j0 += AJ)
        if (act)
            layer_block(AJ, j0, K, A, b, X, Y, 1);
        else
            layer_block(AJ, j0, K, A, b, X, Y, 0);
    switch (J - j0) {  /* the rest, a constant block size per case */
#define REST(r) case r: { if (act) layer_block(r, j0, K, A, b, X, Y, 1); \
                          else layer_block(r, j0, K, A, b, X, Y, 0); } break;
    REST(1) REST(2) REST(3) REST(4) REST(5) REST(6)
#undef REST
    }
}

/* A tile's bilinear taps: element offsets of each query's 4 texels and their weights. */
struct taps4 {
    int32_t off[4][T];
    float w[4][T];
};

/* Bilinear taps of a plane (H, W, C) at the tile's T points (px, py) in [0, 1]^2, texel
 * centres at (i + .5) / W, lane by lane (plain loops GCC vectorises); wrap (a constant after
 * inlining) tiles the plane, else coordinates clamp to the border (as neumat.btf.neural.fetch).
 * Offsets in int32: `query.supported` leaves planes of 2^31 elements or more to torch. */
static inline __attribute__((always_inline)) void
tile_taps(int H, int W, int C, const float *px, const float *py, const int wrap, struct taps4 *t)
{
    for (int q = 0; q < T; q++) {
        float x = px[q] * W - 0.5f, y = py[q] * H - 0.5f;
        if (!wrap) {
            x = x < 0 ? 0 : x > W - 1 ? W - 1 : x;
            y = y < 0 ? 0 : y > H - 1 ? H - 1 : y;
        }
        float fx0 = floorf(x), fy0 = floorf(y), fx = x - fx0, fy = y - fy0;
        int32_t x0, y0, x1, y1;
        if (wrap) {  /* floor(x) modulo W in double: exact while |x| < 2^53 / W, the
                        division's rounding (off by one at most) mended by the two compares */
            double kx = floor((double)fx0 / W), ky = floor((double)fy0 / H);
            x0 = (int32_t)((double)fx0 - kx * W), y0 = (int32_t)((double)fy0 - ky * H);
            x0 += x0 < 0 ? W : 0, y0 += y0 < 0 ? H : 0;
            x0 -= x0 >= W ? W : 0, y0 -= y0 >= H ? H : 0;
            x1 = x0 + 1 == W ? 0 : x0 + 1, y1 = y0 + 1 == H ? 0 : y0 + 1;
        } else {
            x0 = (int32_t)fx0, y0 = (int32_t)fy0;
            x1 = x0 + 1 < W ? x0 + 1 : W - 1, y1 = y0 + 1 < H ? y0 + 1 : H - 1;
        }
        t->off[0][q] = (y0 * W + x0) * C, t->off[1][q] = (y0 * W + x1) * C;
        t->off[2][q] = (y1 * W + x0) * C, t->off[3][q] = (y1 * W + x1) * C;
        t->w[0][q] = (1 - fx) * (1 - fy), t->w[1][q] = fx * (1 - fy);
        t->w[2][q] = (1 - fx) * fy, t->w[3][q] = fx * fy;
    }
}

/* Rows c of X at column q = the bilinear interpolation of plane's taps t of query q. */
static inline void interp(const float *plane, int C, const struct taps4 *t, int q, float *X)
{
    const float *p0 = plane + t->off[0][q], *p1 = plane + t->off[1][q],
                *p2 = plane + t->off[2][q], *p3 = plane + t->off[3][q];
    const float w0 = t->w[0][q], w1 = t->w[1][q], w2 = t->w[2][q], w3 = t->w[3][q];
    for (int c = 0; c < C; c++)
        X[c * T + q] = (w0 * p0[c] + w1 * p1[c]) + (w2 * p2[c] + w3 * p3[c]);
}

/* The f_U taps of the tile of queries t0 ... t0 + T - 1 (a short tile repeats its last query);
 * run() prefetches them (prefetch_taps) while the tile before runs. */
static void prepare_u(const float *u, long t0, long N, int Hu, int Wu, int Cu, struct taps4 *t)
{
    float px[T], py[T];
    for (int q = 0; q < T; q++) {
        long i = t0 + q < N ? t0 + q : N - 1;
        px[q] = u[2 * i], py[q] = u[2 * i + 1];
    }
    tile_taps(Hu, Wu, Cu, px, py, 1, t);
}

/* neumat.btf.directions.half_diff, h = normalize(wi + wo), d = R_b(-theta_h) R_n(-phi_h) wi,
 * for the tile's T queries lane by lane: the plane coordinates (h.xy + 1) / 2 and
 * (d.xy + 1) / 2 in (px, py)[0] and [1]. No unsafe-math: vectorised under it, -ffast-math
 * forms the divisions and square roots from reciprocal estimates and a Newton step, whose error, grown
 * by 1 / sin(theta_h) near the normal, put a query outside the torch path's tolerance
 * (tests/test_btf_query.py); this optimize attribute is the switch that stops it (the IEEE one
 * and target("no-recip") do not). */
static __attribute__((noinline, optimize("no-unsafe-math-optimizations"))) void
half_diff(const float *wi, const float *wo, float (*restrict px)[T], float (*restrict py)[T])
{
    for (int q = 0; q < T; q++) {
        const float *a = wi + 3 * q, *b = wo + 3 * q;
        float sx = a[0] + b[0], sy = a[1] + b[1], sz = a[2] + b[2];
        float nrm = sqrtf(sx * sx + sy * sy + sz * sz);
        nrm = nrm > 1e-12f ? nrm : 1e-12f;
        float hx = sx / nrm, hy = sy / nrm, hz = sz / nrm;
        float ct = hz < -1 ? -1 : hz > 1 ? 1 : hz, sn = sqrtf(hx * hx + hy * hy);
        int rot = sn > 1e-8f;
        float sd = rot ? sn : 1;
        float cp = rot ? hx / sd : 1, sp = rot ? hy / sd : 0;
        float x = cp * a[0] + sp * a[1], y = -sp * a[0] + cp * a[1], z = a[2];
        px[0][q] = (hx + 1) / 2, py[0][q] = (hy + 1) / 2;
        px[1][q] = (ct * x - sn * z + 1) / 2, py[1][q] = (y + 1) / 2;
    }
}

/* half_diff and the taps (clamped) of the half and difference planes, d[0] and d[1], for
 * the tile's T queries: plain loops GCC vectorises. Per query one at a time, as scalar code,
 * this was 38 % of the plain query's time (47.8 CPU-ms of 125.4 a frame, measured by taking it
 * out; AMD EPYC Zen 5, AVX-512 build, 2026-12-03). */
static __attribute__((noinline)) void
dir_prepare(const float *wi, const float *wo, int R, int C, struct taps4 d[2])
{
    float px[2][T], py[2][T];
    half_diff(wi, wo, px, py);
    tile_taps(R, R, C, px[0], py[0], 0, &d[0]);
    tile_taps(R, R, C, px[1], py[1], 0, &d[1]);
}

/* Histogram-preserving blending of f_U (neumat.btf.synthesis.hpb; the maths of its torch path
 * `HPB.torch_features`), in place of the plane fetch: per query the triangle grid in double,
 * the integer vertex hash (so u = 1e5 keeps its precision), fetch coordinates formed in double
 * from frac(u) then rounded to float, three bilinear wrap fetches of the Gaussianised plane,
 * the variance-preserving blend and the inverse LUT. The result is the decorrelated q; the
 * inverse PCA (mean + basis q) is folded into the first layer's f_U columns by the caller
 * (neumat/btf/query.py), or applied by hpb_features. A pure function of (u, seed): each query
 * is one vector lane of a fixed-size tile, whatever the tile or the thread. */
struct hpb {
    const double *u;        /* (N, 2) */
    int H, W;
    const float *lut;       /* (C, L, 2) inverse LUT (HPB only) as (value, slope) pairs: entry
                               k = (lut[k], lut[k + 1] - lut[k]), built by neumat.btf.query.
                               lut_pairs; hpb_fill_c reads a pair with one 64-bit load */
    int L;
    uint32_t seed;
    int hex;                /* hex-tiling: rotated taps and hextile's blend (settings below) */
    int prefetch;           /* run() prefetches the next tile's taps (prefetch_taps;
                               neumat.btf.query.tap_prefetch) */
    float rotation, contrast, exponent, gain;  /* the angle is formed in float (sincos_polyf) */
    const float *planar;    /* HPB, L = LUT_REG: (C, 2, L) values then slopes, for the register
                               lookup (hpb_fill_c); else NULL */
    const uint16_t *gauss16;  /* HPB: (H + 1, W + 1, C) Gaussianised decorrelated plane in
                               float16, wrapped by one row and column (neumat.btf.query.
                               hpb_plane). Half the bytes of float32: the 2 x 2 footprints of
                               the three vertices are read from L2/L3 at random; HPB's overhead
                               over the plain query, float32 -> float16 (one thread, CPU time,
                               best of 15; AMD EPYC): +12.5 -> +11.6 % (AVX-512 build), +24.3
                               -> +20.3 % (AVX2 build). Hex-tiling: its features f_U, the
                               same way (hextile._rounded rounds them to float16), which took
                               hex-tiling's overhead from +25.4, +24.9 to +21.2, +19.9 %
                               (AVX-512 build) and from +33.6, +34.3 to +31.5, +31.7 % (AVX2
                               build; btf_synthesis.py --methods hpb hextile --no-torch
                               --repeat 9, one thread, two alternating rounds; AMD EPYC,
                               2026-11-26) */
    const float *lumw;      /* hex-tiling: C + 1 coefficients (a, b) of its luminance
                               a . c + b of the bilinear features c, clamped to [0, 1]
                               (hextile.HexTile.luminance_of). Formed from the features the
                               taps fetch anyway (hex_fill8): no luminance taps, texels of 16
                               bytes, as HPB's. Hex-tiling's overhead over the plain query,
                               AVX-512 build, against each texel's luminance stored and tapped
                               after its features: +17.9 -> +14.7 % (-7.3 CPU-ms a frame; the
                               control build, the same code as the former, +18.4 %); with
                               texels of 20 bytes kept, +15.6 %: the taps, not the texel
                               size (benchmarks/btf_kernel_ab.py --control --processes 5
                               --repeat 5 --methods hextile, medians of 5 processes; Intel
                               Xeon, 2026-11-30) */
};

/* A float16 value (IEEE binary16 bits) as float, exactly: F16C where the target has it, else
 * from the bits (not _Float16, which x86 GCC before 12, e.g. Ubuntu 22.04's, lacks). */
static inline float h2f(uint16_t h)
{
#if defined(__F16C__)
    return _cvtsh_ss(h);
#else
    uint32_t sign = (uint32_t)(h & 0x8000u) << 16, e = (h >> 10) & 0x1fu, m = h & 0x3ffu, bits;
    if (e == 0) {  /* zero or subnormal: m 2^-24 */
        float f = (float)m * 5.9604644775390625e-08f;
        return sign ? -f : f;
    }
    bits = sign | (e == 31 ? 0x7f800000u : (e + 112) << 23) | m << 13;  /* rebias 15 -> 127 */
    float f;
    memcpy(&f, &bits, 4);
    return f;
#endif
}

struct hpb_taps {           /* one tile's prepared fetches: 3 vertices x 4 texels */
    int32_t off[3][T];      /* off[v]: the first element of vertex v's 2 x 2 texels (the
                               planes are wrapped by one row and column: the others are 1,
                               W + 1 and W + 2 texels on) */
    float tw[12][T];        /* bilinear weights; HPB: times the vertex's blend weight */
    float w[3][T];          /* blend weights */
    float inv[T];           /* 1 / sqrt(sum of their squares) */
    float bias[T];          /* HPB: 0.5 - 0.5 (sum of w) inv, G = acc inv + bias (hpb_fill_c) */
};

/* The grid, hash and taps without -ffast-math's reassociation: with it GCC formed the bilinear
 * weights from differently rounded copies of the texel position (their sum off by ~10 ulp). */
#define IEEE __attribute__((optimize("no-associative-math", "no-reciprocal-math")))

static inline IEEE uint32_t mix(uint32_t x)  /* neumat.btf.synthesis.grid._mix */
{
    x ^= x >> 16;
    x *= 0x7FEB352Du;
    x ^= x >> 15;
    x *= 0x2C1B3C6Du;
    return x ^ (x >> 16);
}

/* An integral double b (|b| < 2^51) modulo 2^32, as (uint32_t)(int64_t)b: its low bits once
 * 1.5 2^52 is added (two's complement for negative b). Plain arithmetic and bits: AVX2 has no
 * vector double -> int64 conversion, and with one the grid loop ran scalar there. */
static inline IEEE uint32_t low32(double b)
{
    double t = b + 6755399441055744.0;
    uint64_t bits;
    memcpy(&bits, &t, 8);
    return (uint32_t)bits;
}

/* sin and cos of a (float, |a| < 2^10) as plain arithmetic the compiler vectorises (libm's
 * scalar sincos was a third of hex-tiling's cost): a = n pi/2 + r, |r| <= pi/4 (two-part
 * pi/2), Taylor series to r^9 / r^10 (truncation < 2e-9), then the quadrant. Float, not double:
 * hex-tiling's angle, formed in float from the hash's top 24 bits, has sin and cos within
 * 5.8e-7 of float64's from all 32 (2^26 random hashes), and it turns an offset of < 0.3 from
 * the vertex, so a tap moves < 2e-7 of the plane (8e-5 texel of 400): inside float32's rounding
 * of the features the query compares against (tests/test_btf_query.py). */
static inline __attribute__((always_inline)) IEEE void sincos_polyf(float a, float *sn, float *cs)
{
    float n = floorf(a * 0.63661977f + 0.5f);
    float r = (a - n * 1.5707964f) + n * 4.371139e-08f, r2 = r * r;
    float sp = r * (1 + r2 * (-1.0f / 6 + r2 * (1.0f / 120 + r2 * (-1.0f / 5040 + r2 * (1.0f / 362880)))));
    float cp = 1 + r2 * (-0.5f + r2 * (1.0f / 24 + r2 * (-1.0f / 720 + r2 * (1.0f / 40320 +
               r2 * (-1.0f / 3628800)))));
    int k = (int)(n - 4 * floorf(n * 0.25f));  /* quadrant, 0 ... 3 */
    float s0 = k & 1 ? cp : sp, c0 = k & 1 ? sp : cp;
    *sn = k & 2 ? -s0 : s0;
    *cs = (k + 1) & 2 ? -c0 : c0;
}

/* Grid, hash and bilinear taps of the tile t0 ... t0 + T - 1 (lanes of plain loops the
 * compiler vectorises); prefetch_footprints fetches their texels.
 * `hex` is a constant after inlining (hpb_prepare, hex_prepare): a run-time branch in the
 * vertex loop kept GCC from vectorising it and doubled HPB's cost. */
static inline __attribute__((always_inline)) IEEE void
grid_prepare(const struct hpb *s, int C, long t0, long N, struct hpb_taps *p, const int hex)
{
    const double S3 = 1.7320508075688772, K = 2 * 1.7320508075688772;
    const float top = 1.0f - 5.9604644775390625e-08f;  /* 1 - 2^-24: grid.wrap_fetch_coords */
    const uint32_t hs = mix(s->seed);
    double ux[T], uy[T], wd[3][T];
    float ef0[T], ef1[T];
    uint32_t fxi[T], fyi[T];
    uint32_t vx[3][T], vy[3][T];
    int upq[T];
    if (t0 + T <= N)
        for (int q = 0; q < T; q++)
            ux[q] = s->u[2 * (t0 + q)], uy[q] = s->u[2 * (t0 + q) + 1];
    else
        for (int q = 0; q < T; q++) {
            long i = t0 + q < N ? t0 + q : N - 1;
            ux[q] = s->u[2 * i], uy[q] = s->u[2 * i + 1];
        }
    for (int q = 0; q < T; q++) {  /* grid.triangle_grid */
        double sty = uy[q] * K;
        double s0 = ux[q] * K - sty / S3, s1 = 2 * sty / S3;
        double b0 = floor(s0), b1 = floor(s1);
        double f0 = s0 - b0, f1 = s1 - b1, z = 1 - f0 - f1;
        int up = z > 0;
        ef0[q] = (float)f0, ef1[q] = (float)f1, upq[q] = up;
        uint32_t i0 = low32(b0), i1 = low32(b1);
        vx[0][q] = i0 + !up, vy[0][q] = i1 + !up, wd[0][q] = up ? z : -z;
        vx[1][q] = i0 + !up, vy[1][q] = i1 + up, wd[1][q] = up ? f1 : 1 - f1;
        vx[2][q] = i0 + up, vy[2][q] = i1 + !up, wd[2][q] = up ? f0 : 1 - f0;
        /* frac(u) in 32-bit fixed point (rounded): added to the vertex's 32-bit hash modulo
           2^32 it is frac(u + offset), with no float64 add, floor or compare per vertex. A
           frac that rounds to 1 (as torch.remainder(u, 1) may) is 2^32, i.e. 0 */
        fxi[q] = low32((ux[q] - floor(ux[q])) * 4294967296.0);
        fyi[q] = low32((uy[q] - floor(uy[q])) * 4294967296.0);
    }
    /* Three loops over the vertices' lanes, not one: the hash, hex-tiling's rotation, then the
       coordinates and taps. In one loop GCC spilled vector registers to the stack (16 on AVX2);
       split, it keeps them in registers, most on AVX2 (docs/stages.md, "BTF synthesis on the
       positional plane") */
    uint32_t hxa[3][T], h0a[3][T], ha[3][T], mxa[2][T];
    for (int q = 0; q < T; q++)  /* vertices 0 and 1 share their column i0 + !up, so its mix:
                                    two column mixes a query, not three */
        mxa[0][q] = mix(vx[0][q] ^ hs), mxa[1][q] = mix(vx[2][q] ^ hs);
    for (int v = 0; v < 3; v++)
        for (int q = 0; q < T; q++) {  /* grid.vertex_hash: mix(vy ^ mix(vx ^ hs)), ... */
            uint32_t h = mix(vy[v][q] ^ mxa[v == 2][q]);
            h = mix(h ^ 0x9E3779B1u);
            hxa[v][q] = h;
            h = mix(h ^ 0x9E3779B2u);
            h0a[v][q] = h;
            if (hex)
                ha[v][q] = mix(h ^ 0x9E3779B3u);
        }
    uint32_t rxa[3][T], rya[3][T];  /* hex-tiling: R d - d in 32-bit fixed point (below) */
    for (int v = 0; v < 3 && hex; v++)
        for (int q = 0; q < T; q++) {  /* hextile.HexTile: the patch rotated about its vertex */
            float a = (6.2831855f * ((float)(ha[v][q] >> 8) * 0x1p-24f) - 3.1415927f) * s->rotation;
            int up = upq[q], o0 = v == 0 ? !up : v == 1 ? !up : up,
                o1 = v == 0 ? !up : v == 1 ? up : !up;
            float e0 = ef0[q] - o0, e1 = ef1[q] - o1;
            float dx = (e0 + 0.5f * e1) * (float)(1 / K), dy = e1 * (float)(S3 / 2 / K);
            float cs, sn;
            sincos_polyf(a, &sn, &cs);
            float zx = (cs - 1) * dx - sn * dy, zy = sn * dx + (cs - 1) * dy;
            rxa[v][q] = 2u * (uint32_t)(int32_t)(zx * 0x1p31f);
            rya[v][q] = 2u * (uint32_t)(int32_t)(zy * 0x1p31f);
        }
    for (int v = 0; v < 3; v++)
        for (int q = 0; q < T; q++) {  /* grid.wrap_fetch_coords, taps */
            const uint32_t hx = hxa[v][q], h0 = h0a[v][q];
            float x, y;
            if (!hex) {  /* grid.wrap_fetch_coords: one rounding to float of the coordinate,
                            exact to 2^-32 (vcvtudq2ps; on AVX2 GCC's two exact halves). In
                            place of a float64 add, floor and compare per vertex: HPB's
                            overhead over the plain query +11.3 -> +9.1 % (AVX-512 build),
                            +20.6 -> +18.7 % (AVX2 build; btf_synthesis.py, one thread, best
                            of 15, AMD EPYC, 2026-11-25) */
                x = (float)(hx + fxi[q]) * 0x1p-32f;
                y = (float)(h0 + fyi[q]) * 0x1p-32f;
            } else {  /* hextile.HexTile: the patch rotated about its vertex c. With d = u - c,
                         frac(c) = frac(frac(u) - d), so the fetch coordinate frac(offset + R d +
                         frac(c)) is frac(offset + frac(u) + (R d - d)): the hash and frac(u) in
                         fixed point as HPB's, and only R d - d (|.| < 0.6) in float. d comes
                         from the skewed fractions (f0, f1) less the vertex's corner, unskewed
                         (grid.vertex_uv), so no float64 is needed past the grid */
                x = (float)(hx + fxi[q] + rxa[v][q]) * 0x1p-32f;
                y = (float)(h0 + fyi[q] + rya[v][q]) * 0x1p-32f;
            }
            x = x > top ? top : x;
            y = y > top ? top : y;
            x = x * s->W - 0.5f, y = y * s->H - 0.5f;  /* in [-0.5, W - 0.5): wrap by one */
            float x0 = floorf(x), y0 = floorf(y), ax = x - x0, ay = y - y0;
            int32_t xa = (int32_t)x0, ya = (int32_t)y0;
            xa += xa < 0 ? s->W : 0, ya += ya < 0 ? s->H : 0;
            float wv = (float)wd[v][q];
            p->w[v][q] = wv;
            if (!hex) {  /* the blend weight folded into the bilinear ones */
                p->off[v][q] = (ya * (s->W + 1) + xa) * C;
                p->tw[4 * v][q] = wv * ((1 - ax) * (1 - ay));
                p->tw[4 * v + 1][q] = wv * (ax * (1 - ay));
                p->tw[4 * v + 2][q] = wv * ((1 - ax) * ay);
                p->tw[4 * v + 3][q] = wv * (ax * ay);
                continue;
            }
            p->off[v][q] = (ya * (s->W + 1) + xa) * C;
            p->tw[4 * v][q] = (1 - ax) * (1 - ay), p->tw[4 * v + 1][q] = ax * (1 - ay);
            p->tw[4 * v + 2][q] = (1 - ax) * ay, p->tw[4 * v + 3][q] = ax * ay;
        }
    for (int q = 0; q < T && !hex; q++) {  /* hpb.blend's normalisation, in double: no approximate rsqrt */
        float ww = p->w[0][q] * p->w[0][q] + p->w[1][q] * p->w[1][q] + p->w[2][q] * p->w[2][q];
        p->inv[q] = (float)(1 / sqrt((double)ww));
        p->bias[q] = 0.5f - 0.5f * ((p->w[0][q] + p->w[1][q]) + p->w[2][q]) * p->inv[q];
    }
}

/* The texels of queries q0 ... q1 - 1 of a prepared tile into L2. A 2 x 2 footprint is two
 * rows of 2C float16, each in one or two lines, so both ends of each row (a scratch build
 * prefetching only each row's first line was clearly slower; figures in issue #18's note). */
static inline __attribute__((always_inline)) void
prefetch_footprints(const struct hpb *s, int C, const struct hpb_taps *p, int q0, int q1)
{
    const long pitch = (long)C * (s->W + 1);
    for (int q = q0; q < q1; q++)
        for (int v = 0; v < 3; v++) {
            const uint16_t *a = s->gauss16 + p->off[v][q];
            __builtin_prefetch(a, 0, 1);
            __builtin_prefetch(a + 2 * C - 1, 0, 1);
            __builtin_prefetch(a + pitch, 0, 1);
            __builtin_prefetch(a + pitch + 2 * C - 1, 0, 1);
        }
}

static IEEE __attribute__((noinline)) void
hpb_prepare(const struct hpb *s, int C, long t0, long N, struct hpb_taps *p)
{
    grid_prepare(s, C, t0, N, p, 0);
}

static IEEE __attribute__((noinline)) void
hex_prepare(const struct hpb *s, int C, long t0, long N, struct hpb_taps *p)
{
    grid_prepare(s, C, t0, N, p, 1);
}

#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
static inline __attribute__((always_inline)) IEEE __m256
tap8(__m256 acc, const uint16_t *x, float w)  /* acc + w x[0:8], x float16 */
{
    __m256 v = _mm256_cvtph_ps(_mm_loadu_si128((const __m128i *)x));
    return _mm256_fmadd_ps(v, _mm256_set1_ps(w), acc);
}
#endif

#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
/* r[k]: the 8 channels of query q0 + k -> X[c * T + q0 + k] (X at column q0): 3 x 8 shuffles,
 * not 64 scalar stores. */
static inline __attribute__((always_inline)) IEEE void store8x8(const __m256 r[8], float *X)
{
    __m256 t[8], u[8];
    for (int k = 0; k < 8; k += 2)
        t[k] = _mm256_unpacklo_ps(r[k], r[k + 1]), t[k + 1] = _mm256_unpackhi_ps(r[k], r[k + 1]);
    for (int k = 0; k < 8; k += 4)
        for (int j = 0; j < 2; j++) {
            u[k + j] = _mm256_shuffle_ps(t[k + j], t[k + j + 2], 0x44);
            u[k + j + 2] = _mm256_shuffle_ps(t[k + j], t[k + j + 2], 0xEE);
        }
    /* u[0..3]: queries 0-3 x channels (0, 4) (2, 6) (1, 5) (3, 7) in 128-bit halves; u[4..7]
       the same for queries 4-7 */
    static const int ch[4] = {0, 2, 1, 3};
    for (int k = 0; k < 4; k++) {
        _mm256_storeu_ps(X + ch[k] * T, _mm256_permute2f128_ps(u[k], u[k + 4], 0x20));
        _mm256_storeu_ps(X + (ch[k] + 4) * T, _mm256_permute2f128_ps(u[k], u[k + 4], 0x31));
    }
}
#endif

#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
/* Query q's bilinear features from a plane of C = 8 float32 channels: one register. */
static inline __attribute__((always_inline)) __m256
bilerp8(const float *plane, const struct taps4 *t, int q)
{
    __m256 a = _mm256_mul_ps(_mm256_loadu_ps(plane + t->off[0][q]), _mm256_set1_ps(t->w[0][q]));
    __m256 b = _mm256_mul_ps(_mm256_loadu_ps(plane + t->off[2][q]), _mm256_set1_ps(t->w[2][q]));
    a = _mm256_fmadd_ps(_mm256_loadu_ps(plane + t->off[1][q]), _mm256_set1_ps(t->w[1][q]), a);
    b = _mm256_fmadd_ps(_mm256_loadu_ps(plane + t->off[3][q]), _mm256_set1_ps(t->w[3][q]), b);
    return _mm256_add_ps(a, b);
}
#endif

#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
/* Queries q0 ... q0 + 7's bilinear features from a plane of C = 8 float32 channels into the
 * rows of X: one register a query, transposed in registers (store8x8). */
static inline __attribute__((always_inline)) void
bilerp8x8(const float *plane, const struct taps4 *t, int q0, float *X)
{
    __m256 r[8];
    for (int j = 0; j < 8; j++)
        r[j] = bilerp8(plane, t, q0 + j);
    store8x8(r, X + q0);
}
#endif

/* Rows c < C of X: sum over the 3 vertices of the 2 x 2 footprints at element off[v] of the
 * float16 `plane` (texels of C), weighted by tw (the blend weights folded into the bilinear
 * ones), for a tile. Shared by HPB and hex-tiling; C is a constant after inlining. */
static inline __attribute__((always_inline)) IEEE void
blend_taps(int C, const uint16_t *plane, long pitch, const int32_t (*restrict off)[T],
           const float (*restrict tw)[T], float *restrict X)
{
#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
    if (C == 8) {  /* a query's 8 channels in one register; 8 queries' registers transposed
                      into 8 rows of X (3 x 8 shuffles) rather than stored lane by lane */
        for (int q0 = 0; q0 < T; q0 += 8) {
            __m256 r[8];
            for (int k = 0; k < 8; k++) {
                int q = q0 + k;
                __m256 acc0 = _mm256_setzero_ps(), acc1 = _mm256_setzero_ps();
                for (int v = 0; v < 3; v++) {  /* rows y and y + 1: two chains */
                    const uint16_t *a = plane + off[v][q], *d = a + pitch;
                    acc0 = tap8(acc0, a, tw[4 * v][q]);
                    acc1 = tap8(acc1, d, tw[4 * v + 2][q]);
                    acc0 = tap8(acc0, a + C, tw[4 * v + 1][q]);
                    acc1 = tap8(acc1, d + C, tw[4 * v + 3][q]);
                }
                r[k] = _mm256_add_ps(acc0, acc1);
            }
            store8x8(r, X + q0);
        }
        return;
    }
#endif
    for (int q = 0; q < T; q++) {  /* the taps are in L2 (run's prefetch_taps) */
        float acc[C];
        for (int c = 0; c < C; c++)
            acc[c] = 0;
        for (int v = 0; v < 3; v++) {
            long o = off[v][q];
            float t0 = tw[4 * v][q], t1 = tw[4 * v + 1][q], t2 = tw[4 * v + 2][q],
                  t3 = tw[4 * v + 3][q];
#define AT(k) h2f(plane[k])
            for (int c = 0; c < C; c++)  /* two short chains: more in flight */
                acc[c] += (t0 * AT(o + c) + t1 * AT(o + C + c)) +
                          (t2 * AT(o + pitch + c) + t3 * AT(o + pitch + C + c));
#undef AT
        }
        for (int c = 0; c < C; c++)
            X[c * T + q] = acc[c];
    }
}

#if defined(__AVX512F__)
/* Entry i of a 128-entry table held in 8 registers, per lane: a two-register permute on i's 5
 * low bits, then blends on bits 5 and 6. (always_inline and IEEE like hpb_fill_c: GCC does not
 * inline a function whose optimize attributes differ, and a call per vector cost HPB a tenth.) */
static inline __attribute__((always_inline)) IEEE __m512
lut128(const __m512 t[8], __m512i i)
{
    __mmask16 b5 = _mm512_test_epi32_mask(i, _mm512_set1_epi32(32)),
              b6 = _mm512_test_epi32_mask(i, _mm512_set1_epi32(64));
    __m512 lo = _mm512_mask_blend_ps(b5, _mm512_permutex2var_ps(t[0], i, t[1]),
                                     _mm512_permutex2var_ps(t[2], i, t[3]));
    __m512 hi = _mm512_mask_blend_ps(b5, _mm512_permutex2var_ps(t[4], i, t[5]),
                                     _mm512_permutex2var_ps(t[6], i, t[7]));
    return _mm512_mask_blend_ps(b6, lo, hi);
}
#endif

#if !defined(__AVX512F__) && !(defined(__AVX2__) && defined(__FMA__))
/* The (value, slope) pairs of a tile's LUT entries, one 64-bit scalar load each: below AVX-512
 * GCC gathered them (vpgatherdq), and the loads are faster. HPB's overhead over the plain
 * query, AVX2 build: +17.7, +18.2 -> +15.4, +16.4 % (btf_synthesis.py --methods hpb --march
 * x86-64-v3, one thread, best of 9, in turn; AMD EPYC, 2026-11-25). AVX2 builds now load the
 * pairs into registers in hpb_fill_c; this serves the builds below. noinline: the optimize
 * attribute needs its own function. */
static __attribute__((noinline, optimize("no-tree-vectorize"))) void
lut_fetch(const pair_t *restrict row, const int *restrict is, pair_t *restrict out)
{
    for (int q = 0; q < T; q++)
        out[q] = row[is[q]];
}
#endif

/* Rows c < C of X: the tile's q (hpb.blend, then hpb.inverse_lut). C is a constant after
 * inlining (one vector of channels per texel for C = 8). The blend weights are folded into the
 * bilinear ones and the -0.5 into `bias` (grid_prepare): G = sum_v w_v (bil_v - 0.5) inv + 0.5
 * = (sum of the weighted taps) inv + bias. */
static inline __attribute__((always_inline)) IEEE void
hpb_fill_c(int C, const struct hpb *s, const struct hpb_taps *p, float *restrict X)
{
    blend_taps(C, s->gauss16, (long)C * (s->W + 1), p->off, p->tw, X);
    const int L = s->L;
#if defined(__AVX512F__)
    if (s->planar) {  /* the 128-entry LUT of a channel in 16 registers (8 of values, 8 of
                         slopes): entry i0 by two-register permutes on its 5 low bits and
                         blends on bits 5 and 6, in place of a gather of 16 pairs */
        for (int c = 0; c < C; c++) {
            const float *tv = s->planar + 2L * c * LUT_REG, *ts = tv + LUT_REG;
            __m512 v[8], sl[8];
            for (int k = 0; k < 8; k++)
                v[k] = _mm512_loadu_ps(tv + 16 * k), sl[k] = _mm512_loadu_ps(ts + 16 * k);
            for (int q = 0; q < T; q += 16) {
                __m512 g = _mm512_fmadd_ps(_mm512_loadu_ps(X + c * T + q),
                                           _mm512_loadu_ps(p->inv + q), _mm512_loadu_ps(p->bias + q));
                g = _mm512_min_ps(_mm512_max_ps(g, _mm512_setzero_ps()), _mm512_set1_ps(1));
                __m512 x = _mm512_sub_ps(_mm512_mul_ps(g, _mm512_set1_ps(LUT_REG)),
                                         _mm512_set1_ps(0.5f));
                x = _mm512_min_ps(_mm512_max_ps(x, _mm512_setzero_ps()),
                                  _mm512_set1_ps(LUT_REG - 1));
                __m512i i0 = _mm512_min_epi32(_mm512_cvttps_epi32(x),
                                              _mm512_set1_epi32(LUT_REG - 2));
                __m512 a = lut128(v, i0), slope = lut128(sl, i0);
                _mm512_storeu_ps(X + c * T + q,
                                 _mm512_fmadd_ps(_mm512_sub_ps(x, _mm512_cvtepi32_ps(i0)), slope, a));
            }
        }
        return;
    }
#endif
#if !defined(__AVX512F__)
    for (int c = 0; c < C; c++) {  /* as below, the pairs fetched by scalar 64-bit loads */
        const pair_t *restrict row = (const pair_t *)(s->lut + 2L * c * L);
        float xs[T];
        int is[T];
        for (int q = 0; q < T; q++) {
            float g = X[c * T + q] * p->inv[q] + p->bias[q];
            g = g < 0 ? 0 : g > 1 ? 1 : g;
            float x = g * L - 0.5f;
            x = x < 0 ? 0 : x > L - 1 ? L - 1 : x;
            int i0 = (int)x;
            is[q] = i0 > L - 2 ? L - 2 : i0;
            xs[q] = x;
        }
#if defined(__AVX2__) && defined(__FMA__)
        /* AVX2: 8 pairs by 64-bit loads straight into two registers, split by two shuffles
           into values and slopes in query order: no pass through `ab`, whose 64-bit stores
           the 256-bit reloads could not forward from. HPB's overhead over the plain query, AVX2
           build: +13.2, +13.5 -> +12.3, +12.4 % (-1.6, -2.5 CPU-ms a frame; bit-identical;
           benchmarks/btf_kernel_ab.py --rev d7b09d6 --march x86-64-v3 --methods hpb, one
           thread, AMD EPYC AVX-512, 2026-11-28). Two vpgatherdq of 4 pairs each measured level
           with it (issue #18's note), and gathers are slow on older AMD and on
           microcode-patched Intel cores */
        const float *rowf = (const float *)row;
        for (int q = 0; q < T; q += 8) {
#define PAIR(k) _mm_loadl_epi64((const __m128i *)(rowf + 2 * is[q + (k)]))
            __m128i p01 = _mm_unpacklo_epi64(PAIR(0), PAIR(1)), p23 = _mm_unpacklo_epi64(PAIR(2), PAIR(3)),
                    p45 = _mm_unpacklo_epi64(PAIR(4), PAIR(5)), p67 = _mm_unpacklo_epi64(PAIR(6), PAIR(7));
#undef PAIR
            /* a: pairs 0 1 | 4 5, b: 2 3 | 6 7; per 128-bit half, shuffle 0x88 takes the values
               a0 a2 b0 b2 (queries 0-3 | 4-7) and 0xDD the slopes */
            __m256 a = _mm256_castsi256_ps(_mm256_inserti128_si256(_mm256_castsi128_si256(p01), p45, 1));
            __m256 b = _mm256_castsi256_ps(_mm256_inserti128_si256(_mm256_castsi128_si256(p23), p67, 1));
            __m256 val = _mm256_shuffle_ps(a, b, 0x88), slope = _mm256_shuffle_ps(a, b, 0xDD);
            __m256 fi = _mm256_cvtepi32_ps(_mm256_loadu_si256((const __m256i *)(is + q)));
            _mm256_storeu_ps(X + c * T + q,
                             _mm256_fmadd_ps(_mm256_sub_ps(_mm256_loadu_ps(xs + q), fi), slope, val));
        }
#else
        float ab[2 * T];
        lut_fetch(row, is, (pair_t *)ab);
        for (int q = 0; q < T; q++)
            X[c * T + q] = ab[2 * q] + (xs[q] - is[q]) * ab[2 * q + 1];
#endif
    }
    return;
#endif
    for (int c = 0; c < C; c++) {
        const pair_t *restrict row = (const pair_t *)(s->lut + 2L * c * L);
        for (int q = 0; q < T; q++) {  /* linear interpolation, clamped at both ends */
            float g = X[c * T + q] * p->inv[q] + p->bias[q];
            g = g < 0 ? 0 : g > 1 ? 1 : g;
            float x = g * L - 0.5f;
            x = x < 0 ? 0 : x > L - 1 ? L - 1 : x;
            int i0 = (int)x;  /* x >= 0: truncation is floor */
            i0 = i0 > L - 2 ? L - 2 : i0;
            /* value and slope in one 64-bit load: with AVX-512, GCC gathers 8 pairs per
               vpgatherdq, half the elements of two vgatherdps of 16 floats; a + t (b - a) as
               before, bit for bit */
            uint64_t v = row[i0];
            uint32_t lo = (uint32_t)v, hi = (uint32_t)(v >> 32);  /* little-endian: value low */
            float a, slope;
            memcpy(&a, &lo, 4);
            memcpy(&slope, &hi, 4);
            X[c * T + q] = a + (x - i0) * slope;
        }
    }
}

/* b^k for b in [1e-30, 1] and k > 0 (hex-tiling's Gain3), as exp2(k log2 b) by plain arithmetic
 * the compiler vectorises: log2 of the mantissa in [sqrt(1/2), sqrt(2)) by a degree-8 and
 * 2^frac by a degree-6 polynomial (Chebyshev fits: 1.2e-7 each, so ~3e-7 relative for k = 1.74);
 * results below 2^-126 come out as 2^-126 (torch: 0 or subnormal, no matter beside weights of
 * order 1). In place of libmvec's expf(k logf(b)): hex-tiling's overhead over the plain query
 * +26.9, +27.0 -> +24.9, +24.9 % (btf_synthesis.py --methods hextile, one thread, best of 7,
 * in turn; AMD EPYC AVX-512, 2026-11-25), its error against the torch path unchanged. */
static inline __attribute__((always_inline)) IEEE float powk(float b, float k)
{
    uint32_t i;
    memcpy(&i, &b, 4);
    int e = (int)(i >> 23) - 127;
    uint32_t mi = (i & 0x7FFFFFu) | 0x3F800000u;
    float m;
    memcpy(&m, &mi, 4);
    int big = m > 1.41421356f;
    m = big ? m * 0.5f : m;
    e += big;
    float t = m - 1;
    float l = -0.14199515f;
    l = l * t + 0.23610973f;
    l = l * t - 0.25111422f;
    l = l * t + 0.28684822f;
    l = l * t - 0.35998312f;
    l = l * t + 0.48093262f;
    l = l * t - 0.72136116f;
    l = l * t + 1.4426948f;
    l = l * t + 4.1276955e-08f;
    float y = k * ((float)e + l);
    y = y < -126.0f ? -126.0f : y;
    float n = floorf(y + 0.5f), f = y - n;
    float p = 0.00015469732f;
    p = p * f + 0.0013400433f;
    p = p * f + 0.009618025f;
    p = p * f + 0.05550327f;
    p = p * f + 0.2402265f;
    p = p * f + 0.6931472f;
    p = p * f + 1.0f;
    uint32_t pi;
    memcpy(&pi, &p, 4);
    pi += (uint32_t)(int32_t)n << 23;
    memcpy(&p, &pi, 4);
    return p;
}

/* hex-tiling's blend weights of a tile from the bilinear luminance and the grid weights:
 * W_i = (1 + contrast (lum_i - 1)) w_i^exponent, normalised, then hextile.gain3 unless
 * gain = 0.5. Plain loops over the tile's lanes that GCC vectorises (Gain3's power by powk,
 * a non-integer exponent by libmvec's powf). IEEE: with reassociation allowed, GCC gave the
 * tile's first 16 lanes other code than the rest, which rounded differently, so a value
 * depended on its place in the batch (tests/test_btf_query.py, the pure-function test). */
static IEEE __attribute__((noinline)) void
hex_weights(const struct hpb *s, float (*restrict lum)[T], const float (*restrict w)[T],
            float (*restrict wt)[T])
{
    const float e = s->exponent, k = (float)(log(1.0 - s->gain) / log(0.5)), ct = s->contrast;
    const int ie = e == floorf(e) && e >= 0 && e <= 16 ? (int)e : -1;  /* hextile._power */
    if (ie >= 0) {  /* w^e as hextile._power: repeated products in the same order, the loop
                       over the power outside the lanes' loop so it vectorises */
        for (int v = 0; v < 3; v++)
            for (int q = 0; q < T; q++)
                wt[v][q] = 1;
        for (int i = 0; i < ie; i++)
            for (int v = 0; v < 3; v++)
                for (int q = 0; q < T; q++)
                    wt[v][q] *= w[v][q];
    } else
        for (int v = 0; v < 3; v++)
            for (int q = 0; q < T; q++)
                wt[v][q] = powf(w[v][q], e);
    for (int v = 0; v < 3; v++)
        for (int q = 0; q < T; q++)
            wt[v][q] *= 1 + ct * (lum[v][q] - 1);
    for (int q = 0; q < T; q++) {
        float sum = wt[0][q] + wt[1][q] + wt[2][q];
        sum = sum > 1e-30f ? sum : 1e-30f;
        for (int v = 0; v < 3; v++)
            wt[v][q] = wt[v][q] / sum;
    }
    if (s->gain == 0.5f)
        return;
    for (int v = 0; v < 3; v++)  /* hextile.gain3 */
        for (int q = 0; q < T; q++) {
            float x = wt[v][q], sg = x >= 0.5f ? 2.f : 0.f, m = 2 * (1 - sg), b = sg + x * m;
            b = b > 1e-30f ? b : 1e-30f;
            wt[v][q] = 0.5f * sg + 0.25f * m * powk(b, k);
        }
    for (int q = 0; q < T; q++) {
        float sum = wt[0][q] + wt[1][q] + wt[2][q];
        for (int v = 0; v < 3; v++)
            wt[v][q] = wt[v][q] / sum;
    }
}

/* Rows c < C of X: hex-tiling's features (hextile.HexTile.__call__): per vertex the luminance
 * of the bilinear features, the weights W_v (hex_weights), then sum W_v c_v with W_v folded into
 * the bilinear weights, as HPB's blend (blend_taps). */
static inline __attribute__((always_inline)) IEEE void
hex_fill_c(int C, const struct hpb *s, const struct hpb_taps *p, float *restrict X)
{
    const long pitch = (long)C * (s->W + 1);
    float lum[3][T], wt[3][T], tw[12][T];
    for (int v = 0; v < 3; v++)
        for (int q = 0; q < T; q++) {  /* the taps are in L2 (run's prefetch_taps) */
            const uint16_t *a = s->gauss16 + p->off[v][q], *d = a + pitch;
            const float t0 = p->tw[4 * v][q], t1 = p->tw[4 * v + 1][q],
                        t2 = p->tw[4 * v + 2][q], t3 = p->tw[4 * v + 3][q];
            float l = 0;
            for (int c = 0; c < C; c++)
                l += s->lumw[c] * ((t0 * h2f(a[c]) + t1 * h2f(a[C + c])) +
                                   (t2 * h2f(d[c]) + t3 * h2f(d[C + c])));
            l += s->lumw[C];
            lum[v][q] = l < 0 ? 0 : l > 1 ? 1 : l;
        }
    hex_weights(s, lum, p->w, wt);
    for (int k = 0; k < 12; k++)
        for (int q = 0; q < T; q++)
            tw[k][q] = wt[k / 4][q] * p->tw[k][q];
    blend_taps(C, s->gauss16, pitch, p->off, tw, X);
}

#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
/* hex_fill_c for C = 8 in two passes over the tile's queries: each vertex's bilinear features
 * (one register) and, by a horizontal-add tree over 8 queries, its luminance a . c + b; then,
 * with the weights, their blend (sum_v W_v c_v, in hextile's order). The luminance linear in
 * the features (hextile) needs no taps of its own and leaves texels of 16 bytes. */
static inline __attribute__((always_inline)) IEEE void
hex_fill8(const struct hpb *s, const struct hpb_taps *p, float *restrict X)
{
    enum { C = 8 };
    const long pitch = (long)C * (s->W + 1);
    float lum[3][T] __attribute__((aligned(32))), wt[3][T];
    float r[T][3][8] __attribute__((aligned(32)));
    const __m256 la = _mm256_loadu_ps(s->lumw), lb = _mm256_set1_ps(s->lumw[C]);
    for (int q0 = 0; q0 < T; q0 += 8)
        for (int v = 0; v < 3; v++) {
            __m256 m[8];
            for (int k = 0; k < 8; k++) {
                const int q = q0 + k;
                const uint16_t *a = s->gauss16 + p->off[v][q], *d = a + pitch;
                __m256 acc0 = tap8(_mm256_setzero_ps(), a, p->tw[4 * v][q]),
                       acc1 = tap8(_mm256_setzero_ps(), d, p->tw[4 * v + 2][q]);
                acc0 = tap8(acc0, a + C, p->tw[4 * v + 1][q]);
                acc1 = tap8(acc1, d + C, p->tw[4 * v + 3][q]);
                const __m256 c = _mm256_add_ps(acc0, acc1);
                _mm256_store_ps(r[q][v], c);
                m[k] = _mm256_mul_ps(c, la);
            }
            /* the 8 sums of m[k]'s lanes, in query order: per 128-bit half the pairs, then
               the quads (hadd), then the halves added across */
            __m256 h0 = _mm256_hadd_ps(_mm256_hadd_ps(m[0], m[1]), _mm256_hadd_ps(m[2], m[3])),
                   h1 = _mm256_hadd_ps(_mm256_hadd_ps(m[4], m[5]), _mm256_hadd_ps(m[6], m[7]));
            __m256 l = _mm256_add_ps(_mm256_add_ps(_mm256_permute2f128_ps(h0, h1, 0x20),
                                                   _mm256_permute2f128_ps(h0, h1, 0x31)), lb);
            l = _mm256_min_ps(_mm256_max_ps(l, _mm256_setzero_ps()), _mm256_set1_ps(1));
            _mm256_store_ps(lum[v] + q0, l);
        }
    hex_weights(s, lum, p->w, wt);
    for (int q0 = 0; q0 < T; q0 += 8) {
        __m256 b[8];
        for (int k = 0; k < 8; k++) {
            const int q = q0 + k;
            __m256 acc = _mm256_mul_ps(_mm256_set1_ps(wt[0][q]), _mm256_load_ps(r[q][0]));
            acc = _mm256_fmadd_ps(_mm256_set1_ps(wt[1][q]), _mm256_load_ps(r[q][1]), acc);
            b[k] = _mm256_fmadd_ps(_mm256_set1_ps(wt[2][q]), _mm256_load_ps(r[q][2]), acc);
        }
        store8x8(b, X + q0);
    }
}
#endif

static IEEE void hpb_fill(int C, const struct hpb *s, const struct hpb_taps *p, float *X)
{
    if (s->hex && C == 8)
#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
        hex_fill8(s, p, X);
#else
        hex_fill_c(8, s, p, X);
#endif
    else if (s->hex)
        hex_fill_c(C, s, p, X);
    else if (C == 8)
        hpb_fill_c(8, s, p, X);
    else
        hpb_fill_c(C, s, p, X);
}

/* The (value, slope) pairs of s->lut as (C, 2, L) in buf, for the register lookup: with
 * AVX-512 and L = LUT_REG, else NULL (the gather path). */
static const float *lut_planar(const struct hpb *s, int C, float *buf)
{
#if defined(__AVX512F__)
    if (s->L == LUT_REG) {
        for (int c = 0; c < C; c++)
            for (int k = 0; k < LUT_REG; k++) {
                buf[2 * c * LUT_REG + k] = s->lut[2 * (c * LUT_REG + k)];
                buf[(2 * c + 1) * LUT_REG + k] = s->lut[2 * (c * LUT_REG + k) + 1];
            }
        return buf;
    }
#endif
    (void)C, (void)buf;
    return NULL;
}

/* Where a tile's f_U comes from: the plane fetch at u, the caller's features, or HPB. */
struct source {
    const float *u, *feat, *fu;
    int Hu, Wu, Cu;
    const struct hpb *hpb;
};

struct prepared {           /* a tile's f_U fetches, prepared a tile ahead */
    struct taps4 fu;
    struct hpb_taps hpb;
};

/* noinline: inlined into run(), GCC 12.2 at -O3 -ffast-math lost prepare_u's stores (every
 * f_U row 0; found by tests/test_btf_query.py, gone with -fno-strict-aliasing too). A call per
 * tile of 64 queries costs nothing measurable. */
static __attribute__((noinline)) void prepare(const struct source *src, long t0, long N, struct prepared *p)
{
    if (src->hpb && src->hpb->hex)
        hex_prepare(src->hpb, src->Cu, t0, N, &p->hpb);
    else if (src->hpb)
        hpb_prepare(src->hpb, src->Cu, t0, N, &p->hpb);
    else if (!src->feat)
        prepare_u(src->u, t0, N, src->Hu, src->Wu, src->Cu, &p->fu);
}

/* Query q's f_U texels of the next tile, prepared, into the cache: run() asks for them query by
 * query between the direction fetches of the tile before (with C = 8, eight queries' before
 * each eight queries' fetches). Issued in one burst after the
 * tile's preparation (768 prefetches for HPB's 3 footprints of 64 queries, 512 for the plain
 * query's 4 texels), they queued on the few lines a core has in flight; spread over the tile,
 * they overlap its work. Per 1920 x 1080 frame against the burst, and against no tap prefetch
 * for HPB and hex-tiling (Intel's choice until then): AVX-512 build, plain query 263.2 and
 * 267.5 (its two rows) -> 254.8 CPU-ms, HPB 302.5 / 294.0 -> 279.3 (+8.1 % over the plain
 * query), hex-tiling 312.5 / 299.4 -> 278.8 (+8.8 %); AVX2 build, plain 263.4 and 266.5 ->
 * 256.5, HPB 311.7 / 298.8 -> 286.4 (+10.1 %),
 * hex-tiling 321.2 / 311.4 -> 294.8 (+14.8 %); outputs equal to the bit
 * (benchmarks/btf_kernel_ab.py --rev beb9859 --control --processes 5 --repeat 5 --tap-prefetch
 * both, and with --march x86-64-v3; medians of 5 processes; Intel Xeon, idle, 2026-11-30). A
 * scratch build spreading them over the MLP's row blocks in place gained as much on the
 * AVX-512 build, nothing on AVX2. */
static inline __attribute__((always_inline)) void
prefetch_taps(const struct source *src, const struct prepared *p, int q)
{
    if (src->hpb) {
        if (src->hpb->prefetch)
            prefetch_footprints(src->hpb, src->Cu, &p->hpb, q, q + 1);
    } else if (!src->feat)
        for (int k = 0; k < 4; k++) {  /* locality 2 (prefetcht1): the plain query took 4 %
                                          less time than with prefetcht0, which brings a
                                          tile's lines into L1 a tile early (btf_query.py,
                                          AMD EPYC AVX-512: 231.7 against 242.3 CPU-ms) */
            __builtin_prefetch(src->fu + p->fu.off[k][q], 0, 2);
            __builtin_prefetch(src->fu + p->fu.off[k][q] + src->Cu - 1, 0, 2);  /* a texel may
                                                                       straddle two lines */
        }
}

/* Rows 0 ... Cu - 1 of X for the tile at t0 (nt queries, the rest repeat the last). */
static void fill(const struct source *src, long t0, int nt, const struct prepared *p, float *X)
{
    int Cu = src->Cu;
    if (src->hpb)
        hpb_fill(Cu, src->hpb, &p->hpb, X);
    else if (src->feat)
        for (int q = 0; q < T; q++) {
            long i = t0 + (q < nt ? q : nt - 1);
            for (int c = 0; c < Cu; c++)
                X[c * T + q] = src->feat[i * Cu + c];
        }
    else {
#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
        if (Cu == 8) {
            for (int q0 = 0; q0 < T; q0 += 8)
                bilerp8x8(src->fu, &p->fu, q0, X);
            return;
        }
#endif
        for (int q = 0; q < T; q++)
            interp(src->fu, Cu, &p->fu, q, X);
    }
}

/* The lines of [p, p + bytes) into the cache (rw 1: about to be written). */
static inline __attribute__((always_inline)) void prefetch_lines(const void *p, long bytes, int rw)
{
    for (long k = 0; k < bytes; k += 64)
        if (rw)
            __builtin_prefetch((const char *)p + k, 1, 3);
        else
            __builtin_prefetch((const char *)p + k, 0, 3);
}

/* The streamed arrays of the tile at t (its u, directions, caller's features, output), which
 * run() asks for a tile before `prepare` reads its u: between two tiles' reads the random
 * plane taps and the MLP left the hardware prefetcher behind (`perf annotate`, Intel Xeon: the
 * first loads of a tile's u were 44 % of hpb_prepare's samples). Per frame, against the kernel
 * without it (benchmarks/btf_kernel_ab.py --control --processes 5 --repeat 5, medians; Intel
 * Xeon, 2026-11-30; outputs equal to the bit): AVX-512 build plain query 266.5 -> 253.4, HPB
 * 289.1 -> 280.0, hex-tiling 295.1 -> 288.4 CPU-ms; AVX2 build 295.6 -> 282.8, 331.4 -> 324.6,
 * 341.8 -> 327.7. A tile further ahead, or without the output lines: inside the noise. */
static inline __attribute__((always_inline)) void
prefetch_streams(const struct source *src, const float *wi, const float *wo, float *out, long t,
                 long N)
{
    if (t >= N)
        return;
    long n = N - t < T ? N - t : T;
    if (src->hpb)
        prefetch_lines(src->hpb->u + 2 * t, 16 * n, 0);
    else if (src->feat)
        prefetch_lines(src->feat + (long)src->Cu * t, 4L * src->Cu * n, 0);
    else
        prefetch_lines(src->u + 2 * t, 8 * n, 0);
    prefetch_lines(wi + 3 * t, 12 * n, 0);
    prefetch_lines(wo + 3 * t, 12 * n, 0);
    prefetch_lines(out + 3 * t, 12 * n, 1);
}

/* always_inline: each entry point gets its own copy, specialised on its source (GCC's
 * constprop clone served the plain query alone) */
static inline __attribute__((always_inline)) void run(long N, const struct source *src, const float *wi, const float *wo,
                const float *fh, const float *fd, int R, int C, int L, const int *dims,
                const float *params, float *out, int raw)
{
    float bufa[MAXW * T], bufb[MAXW * T];  /* a tile's activations, ping-pong between layers */
    float wi_[3 * T], wo_[3 * T];
    struct taps4 dt[2];  /* the direction planes' */
    /* f_U fetches prepared, and their texels prefetched, a tile ahead */
    struct prepared pre[2];
    int Cu = src->Cu;
    if (N > 0)
        prepare(src, 0, N, &pre[0]);
    for (long t0 = 0, tile = 0; t0 < N; t0 += T, tile ^= 1) {
        int nt = N - t0 < T ? (int)(N - t0) : T;  /* a short last tile repeats its last query */
        struct prepared *next = t0 + T < N ? &pre[tile ^ 1] : NULL;
        prefetch_streams(src, wi, wo, out, t0 + 2 * T, N);
        if (next)
            prepare(src, t0 + T, N, next);
        for (int q = 0; q < T; q++) {
            long i = t0 + (q < nt ? q : nt - 1);
            for (int k = 0; k < 3; k++)
                wi_[3 * q + k] = wi[3 * i + k], wo_[3 * q + k] = wo[3 * i + k];
        }
        fill(src, t0, nt, &pre[tile], bufa);
        dir_prepare(wi_, wo_, R, C, dt);
        float *Xh = bufa + Cu * T, *Xd = bufa + (Cu + C) * T;
#if defined(__AVX2__) && defined(__FMA__) && defined(__F16C__)
        if (C == 8)
            for (int q0 = 0; q0 < T; q0 += 8) {
                for (int j = 0; j < 8 && next; j++)
                    prefetch_taps(src, next, q0 + j);
                bilerp8x8(fh, &dt[0], q0, Xh);
                bilerp8x8(fd, &dt[1], q0, Xd);
            }
        else
#endif
            for (int q = 0; q < T; q++) {
                if (next)
                    prefetch_taps(src, next, q);
                interp(fh, C, &dt[0], q, Xh);
                interp(fd, C, &dt[1], q, Xd);
            }
        const float *p = params;
        float *X = bufa, *Y = bufb;
        for (int l = 0; l < L; l++) {
            int K = dims[l], J = dims[l + 1];
            layer(J, K, p, p + J * K, X, Y, l < L - 1);
            p += J * K + J;
            float *tmp = X; X = Y; Y = tmp;
        }
        float o[3 * T];  /* every tile through the same (vectorised) expm1f: a result does
                            not depend on where its tile starts, e.g. on the thread count */
        for (int c = 0; c < 3; c++)
            for (int q = 0; q < T; q++) {
                float y = X[c * T + q];
                o[3 * q + c] = raw ? y : fmaxf(expm1f(y), 0.f);
            }
        for (int k = 0; k < 3 * nt; k++)
            out[t0 * 3 + k] = o[k];
    }
}

void btf_triple_plane(long N, const float *u, const float *wi, const float *wo,
                      const float *feat_u, const float *fu, int Hu, int Wu, int Cu,
                      const float *fh, const float *fd, int R, int C, int L, const int *dims,
                      const float *params, float *out, int raw)
{
    struct source src = {u, feat_u, fu, Hu, Wu, Cu, NULL};
    run(N, &src, wi, wo, fh, fd, R, C, L, dims, params, out, raw);
}

/* The query with HPB's f_U at float64 u: params' first layer takes q in place of f_U (its
 * f_U columns times the PCA basis, its bias plus those columns times the mean). */
void btf_triple_plane_hpb(long N, const double *u, const float *wi, const float *wo,
                          const uint16_t *gauss, int H, int W, int Cu, const float *lut, int Lut,
                          uint32_t seed, const float *fh, const float *fd, int R, int C, int L,
                          const int *dims, const float *params, float *out, int raw, int prefetch)
{
    struct hpb s = {u, H, W, lut, Lut, seed};
    s.gauss16 = gauss;
    s.prefetch = prefetch;
    float planar[Lut == LUT_REG && Cu <= MAXW ? 2 * Cu * LUT_REG : 1];
    s.planar = lut_planar(&s, Cu, planar);
    struct source src = {NULL, NULL, NULL, 0, 0, Cu, &s};
    run(N, &src, wi, wo, fh, fd, R, C, L, dims, params, out, raw);
}

/* The query with hex-tiling's f_U at float64 u (plane (H + 1, W + 1, Cu) float16, wrapped:
 * neumat.btf.query.hex_plane; lumw: its luminance's Cu + 1 coefficients, struct hpb). */
void btf_triple_plane_hex(long N, const double *u, const float *wi, const float *wo,
                          const uint16_t *plane, const float *lumw, int H, int W, int Cu,
                          uint32_t seed,
                          double rotation, float contrast, float exponent, float gain,
                          const float *fh, const float *fd, int R, int C, int L,
                          const int *dims, const float *params, float *out, int raw, int prefetch)
{
    struct hpb s = {u, H, W, NULL, 0, seed, 1, 0, (float)rotation, contrast, exponent, gain};
    s.gauss16 = plane;
    s.lumw = lumw;
    s.prefetch = prefetch;
    struct source src = {NULL, NULL, NULL, 0, 0, Cu, &s};
    run(N, &src, wi, wo, fh, fd, R, C, L, dims, params, out, raw);
}

/* HPB's features alone, (N, C) = mean + basis q (neumat.btf.synthesis.kernel). */
void hpb_features(long N, const double *u, const uint16_t *gauss, int H, int W, int C,
                  const float *lut, int Lut, uint32_t seed, const float *mean,
                  const float *basis, float *out)
{
    struct hpb s = {u, H, W, lut, Lut, seed};
    s.gauss16 = gauss;
    float planar[Lut == LUT_REG && C <= MAXW ? 2 * C * LUT_REG : 1];
    s.planar = lut_planar(&s, C, planar);
    struct hpb_taps p;
    float X[MAXW * T];
    for (long t0 = 0; t0 < N; t0 += T) {
        int nt = N - t0 < T ? (int)(N - t0) : T;
        hpb_prepare(&s, C, t0, N, &p);
        prefetch_footprints(&s, C, &p, 0, T);
        hpb_fill(C, &s, &p, X);
        for (int q = 0; q < nt; q++)
            for (int j = 0; j < C; j++) {
                float f = mean[j];
                for (int c = 0; c < C; c++)
                    f += basis[j * C + c] * X[c * T + q];
                out[(t0 + q) * C + j] = f;
            }
    }
}

/* This build's fp32 vector FMA peak, for the benchmarks' bound (query.fma_peak): n rounds of
 * 12 independent chains a = a m + c on VL-lane vectors, 24 VL FLOP a round (12 chains cover an
 * FMA's latency times its ports on current x86 cores; builds without FMA count the multiply
 * and the add). m and c are arguments: as constants GCC folded the loop away. Returns the
 * chains' sum, so the work is kept. */
float fma_peak(long n, float mf, float cf)
{
    const vf m = splat(mf), c = splat(cf);
#define CHAIN(i) vf a##i = splat(1.0f + 1e-3f * i);
    CHAIN(0) CHAIN(1) CHAIN(2) CHAIN(3) CHAIN(4) CHAIN(5)
    CHAIN(6) CHAIN(7) CHAIN(8) CHAIN(9) CHAIN(10) CHAIN(11)
#undef CHAIN
    for (long k = 0; k < n; k++) {
#define CHAIN(i) a##i = a##i * m + c;
        CHAIN(0) CHAIN(1) CHAIN(2) CHAIN(3) CHAIN(4) CHAIN(5)
        CHAIN(6) CHAIN(7) CHAIN(8) CHAIN(9) CHAIN(10) CHAIN(11)
#undef CHAIN
    }
    vf t = ((a0 + a1) + (a2 + a3)) + ((a4 + a5) + (a6 + a7)) + ((a8 + a9) + (a10 + a11));
    float s = 0;
    for (int l = 0; l < VL; l++)
        s += t[l];
    return s;
}

/* The lanes of this build's vectors (VL), for fma_peak's FLOP count. */
int vector_lanes(void)
{
    return VL;
}
