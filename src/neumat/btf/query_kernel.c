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
 * Vector width and register blocking follow the target ISA as in fit_step.c: accumulators of
 * an AJ x AS block plus its inputs fit the register file (32 or 16 vector registers).
 */
#include <math.h>
#include <stddef.h>

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
#define T 64        /* queries per tile: a multiple of AS * VL for every VL */
#define MAXW 128    /* widest layer the scratch holds */

typedef float vf __attribute__((vector_size(4 * VL), aligned(4)));
typedef int vi __attribute__((vector_size(4 * VL), aligned(4)));

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

/* Bilinear taps of a plane (H, W, C) at (x, y) in [0, 1]^2, texel centres at (i + .5) / W:
 * offsets (in floats) of the 4 texels and their weights; wrap tiles the plane, else coordinates
 * clamp to the border (as neumat.btf.neural.fetch). */
static inline void taps(int H, int W, int C, float px, float py, int wrap, long *off, float *w)
{
    float x = px * W - 0.5f, y = py * H - 0.5f;
    if (!wrap) {
        x = x < 0 ? 0 : x > W - 1 ? W - 1 : x;
        y = y < 0 ? 0 : y > H - 1 ? H - 1 : y;
    }
    float fx0 = floorf(x), fy0 = floorf(y), fx = x - fx0, fy = y - fy0;
    long x0 = (long)fx0, y0 = (long)fy0, x1, y1;
    if (wrap) {
        x0 %= W; x0 += x0 < 0 ? W : 0;
        y0 %= H; y0 += y0 < 0 ? H : 0;
        x1 = x0 + 1 == W ? 0 : x0 + 1;
        y1 = y0 + 1 == H ? 0 : y0 + 1;
    } else {
        x1 = x0 + 1 < W ? x0 + 1 : W - 1;
        y1 = y0 + 1 < H ? y0 + 1 : H - 1;
    }
    off[0] = (y0 * W + x0) * C, off[1] = (y0 * W + x1) * C;
    off[2] = (y1 * W + x0) * C, off[3] = (y1 * W + x1) * C;
    w[0] = (1 - fx) * (1 - fy), w[1] = fx * (1 - fy), w[2] = (1 - fx) * fy, w[3] = fx * fy;
}

/* Rows c of X at column q = the bilinear interpolation of plane's taps (off, w). */
static inline void interp(const float *plane, int C, const long *off, const float *w, float *X,
                          int q)
{
    const float *p0 = plane + off[0], *p1 = plane + off[1], *p2 = plane + off[2],
                *p3 = plane + off[3];
    for (int c = 0; c < C; c++)
        X[c * T + q] = w[0] * p0[c] + w[1] * p1[c] + w[2] * p2[c] + w[3] * p3[c];
}

static inline void fetch(const float *plane, int H, int W, int C, float px, float py, int wrap,
                         float *X, int q)
{
    long off[4];
    float w[4];
    taps(H, W, C, px, py, wrap, off, w);
    interp(plane, C, off, w, X, q);
}

/* The f_U taps of the tile of queries t0 ... t0 + T - 1 (a short tile repeats its last query),
 * prefetched: f_U (megabytes) is read at random texels, and a tile's 4 T fetches in flight
 * while the previous tile runs its MLP hide most of the memory latency. */
static void prepare_u(const float *u, long t0, long N, const float *fu, int Hu, int Wu, int Cu,
                      long (*off)[4], float (*w)[4])
{
    for (int q = 0; q < T; q++) {
        long i = t0 + q < N ? t0 + q : N - 1;
        taps(Hu, Wu, Cu, u[2 * i], u[2 * i + 1], 1, off[q], w[q]);
        for (int k = 0; k < 4; k++) {
            __builtin_prefetch(fu + off[q][k]);
            __builtin_prefetch(fu + off[q][k] + Cu - 1);  /* a texel may straddle two lines */
        }
    }
}

/* neumat.btf.directions.half_diff: h = normalize(wi + wo), d = R_b(-theta_h) R_n(-phi_h) wi;
 * writes the plane coordinates (h.xy + 1) / 2 and (d.xy + 1) / 2. */
static inline void half_diff(const float *wi, const float *wo, float *hxy, float *dxy)
{
    float sx = wi[0] + wo[0], sy = wi[1] + wo[1], sz = wi[2] + wo[2];
    float nrm = sqrtf(sx * sx + sy * sy + sz * sz);
    nrm = nrm > 1e-12f ? nrm : 1e-12f;
    float hx = sx / nrm, hy = sy / nrm, hz = sz / nrm;
    float ct = hz < -1 ? -1 : hz > 1 ? 1 : hz, sn = sqrtf(hx * hx + hy * hy);
    float cp = 1, sp = 0;
    if (sn > 1e-8f) {
        cp = hx / sn;
        sp = hy / sn;
    }
    float x = cp * wi[0] + sp * wi[1], y = -sp * wi[0] + cp * wi[1], z = wi[2];
    hxy[0] = (hx + 1) / 2;
    hxy[1] = (hy + 1) / 2;
    dxy[0] = (ct * x - sn * z + 1) / 2;
    dxy[1] = (y + 1) / 2;
}

void btf_triple_plane(long N, const float *u, const float *wi, const float *wo,
                      const float *feat_u, const float *fu, int Hu, int Wu, int Cu,
                      const float *fh, const float *fd, int R, int C, int L, const int *dims,
                      const float *params, float *out, int raw)
{
    float bufa[MAXW * T], bufb[MAXW * T];  /* a tile's activations, ping-pong between layers */
    float wi_[3 * T], wo_[3 * T];
    long uoff[2][T][4];  /* f_U taps of this tile and the next */
    float uw[2][T][4];
    if (!feat_u && N > 0)
        prepare_u(u, 0, N, fu, Hu, Wu, Cu, uoff[0], uw[0]);
    for (long t0 = 0, tile = 0; t0 < N; t0 += T, tile ^= 1) {
        int nt = N - t0 < T ? (int)(N - t0) : T;  /* a short last tile repeats its last query */
        if (!feat_u && t0 + T < N)
            prepare_u(u, t0 + T, N, fu, Hu, Wu, Cu, uoff[tile ^ 1], uw[tile ^ 1]);
        for (int q = 0; q < T; q++) {
            long i = t0 + (q < nt ? q : nt - 1);
            for (int k = 0; k < 3; k++)
                wi_[3 * q + k] = wi[3 * i + k], wo_[3 * q + k] = wo[3 * i + k];
            if (feat_u)
                for (int c = 0; c < Cu; c++)
                    bufa[c * T + q] = feat_u[i * Cu + c];
        }
        for (int q = 0; q < T; q++) {
            float hxy[2], dxy[2];
            half_diff(wi_ + 3 * q, wo_ + 3 * q, hxy, dxy);
            if (!feat_u)
                interp(fu, Cu, uoff[tile][q], uw[tile][q], bufa, q);
            fetch(fh, R, R, C, hxy[0], hxy[1], 0, bufa + Cu * T, q);
            fetch(fd, R, R, C, dxy[0], dxy[1], 0, bufa + (Cu + C) * T, q);
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
