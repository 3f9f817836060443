/* K Adam steps of M independent NBRDF fits (6 -> 21 -> 21 -> 3) on shared minibatches.
 *
 * The CPU fast path of neumat.fit (see neumat/fit_kernel.py, which compiles and loads this
 * file). It computes what neumat.fit.loss_and_grad + adam_step compute (equal to float32
 * rounding; -ffast-math may reorder sums), material by material: one material's activations (21 x n floats per layer) stay in L1/L2 cache, and the
 * small matmuls are register-blocked over vectors of the target's native width (GCC vector
 * extensions), chosen at compile time from what -march gives (see "Vector width and register
 * blocking" below): 16 floats on AVX-512, 8 on AVX2, 4 on SSE or NEON. A block's
 * accumulators must fit the register file: 16-float vectors blocked for 32 zmm registers spill
 * on every FMA when compiled for AVX2's 16 ymm registers. torch's batched
 * matmuls spend most of a step on per-matrix overhead at these sizes;
 * tests/test_fit_kernel.py checks every variant that builds against them.
 *
 * Layouts (float32 unless said, row-major):
 *   xc_all     (B, 7)   all bins' inputs [h, d] and cos(theta_i)
 *   target_all (B, ldt) log(1 + f cos); material i's channel c in column 3 i + c
 *   idx (K, n) int64    bins of each step's minibatch; sign (K, n) -1 where d is mirrored
 *   lr (K)              learning rate of each step (no Adam update where <= 0)
 *   w, m, v (M, 675)    weights in neumat.nbrdf's flatten order, Adam moments (updated)
 *   grad (M, 675), loss (M,)  gradient and eq. 2 loss of the last step (written)
 *   work                (73 + 3 M) (n + 16) floats of scratch
 * n must be a multiple of 16 (any vector width divides it). step0 = Adam steps already taken (bias correction).
 * nbrdf_loss_sums (at the end) evaluates the loss of fitted fields on any set of bins.
 */
#include <math.h>
#include <stddef.h>
#include <stdint.h>
#ifdef __SSE__
#include <xmmintrin.h>
#endif

/* Vector width and register blocking, from the target ISA.
 *   VL       floats per vector
 *   AJ, AS   affine: blocks of AJ output rows x AS vectors of samples: AJ AS accumulators,
 *            AS inputs and one broadcast weight live at once
 *   OJ, OK   outer: OJ x OK accumulators + OJ rows of D + one row of X
 * 32 registers (AVX-512, aarch64): 7 x 2 (17 live) and 3 x 7 (25 live).
 * 16 registers (AVX2, SSE): 6 x 2 (15 live) and 3 x 4 (16 live). */
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
enum { AJ = 7, AS = 2, OJ = 3, OK = 7 };
#else
enum { AJ = 6, AS = 2, OJ = 3, OK = 4 };
#endif
#define PAD 16  /* scratch rows are n + PAD floats apart, whatever VL */

typedef float vf __attribute__((vector_size(4 * VL), aligned(4)));  /* any alignment */
typedef int vi __attribute__((vector_size(4 * VL), aligned(4)));
#define H 21
enum { OW1 = 0, OB1 = 126, OW2 = 147, OB2 = 588, OW3 = 609, OB3 = 672, NP = 675 };

static inline vf vload(const float *p) { return *(const vf *)p; }
static inline void st(float *p, vf v) { *(vf *)p = v; }
static inline vf splat(float a) { return (vf){0} + a; }
/* where mask: a, else b (C has no vector ?:) */
static inline vf sel(vi mask, vf a, vf b) { return (vf)(((vi)a & mask) | ((vi)b & ~mask)); }
static inline vf act(vf z, float slope) { return sel(z > 0, z, z * slope); }

/* Scratch arrays are J x n with rows `ld` = n + 16 floats apart: rows exactly 2 KiB apart
 * (n = 512) would all fall in the same few L1 cache sets and evict each other. */

enum { RAW, ACT, GATE };  /* what affine does to A X + b: nothing, act(.), . * act'(G) */

static inline vf finish(vf z, int mode, const float *g, float slope)
{
    if (mode == ACT)
        return act(z, slope);
    if (mode == GATE)  /* G = act(z') > 0 exactly where z' > 0 */
        return sel(vload(g) > 0, z, z * slope);
    return z;
}

/* Y (J x n) = f(A X + b), A (J x K) with element (j, k) at A[j * sj + k * sk], X (K x n),
 * f by `mode` (G: J x n, for GATE). Blocks of JB rows x AS vectors of samples; JB and mode
 * are constants after inlining. */
static inline __attribute__((always_inline)) void
affine_block(int JB, int j0, int K, int n, int ld, const float *A, int sj, int sk,
             const float *b, const float *X, float *Y, int mode, const float *G, float slope)
{
    for (int s = 0; s < n; s += AS * VL) {
        int nv = (n - s) / VL < AS ? (n - s) / VL : AS;  /* vectors in this block */
        vf acc[AJ][AS];
        for (int j = 0; j < JB; j++)
            for (int q = 0; q < AS; q++)
                acc[j][q] = splat(b ? b[j0 + j] : 0.f);
        for (int k = 0; k < K; k++) {
            vf x[AS];
            x[0] = vload(X + (size_t)k * ld + s);
            for (int q = 1; q < AS; q++)  /* a short last block repeats its first vector */
                x[q] = q < nv ? vload(X + (size_t)k * ld + s + q * VL) : x[0];
            for (int j = 0; j < JB; j++) {
                float a = A[(j0 + j) * sj + k * sk];
                for (int q = 0; q < AS; q++)
                    acc[j][q] += a * x[q];
            }
        }
        for (int j = 0; j < JB; j++) {
            size_t o = (size_t)(j0 + j) * ld + s;
            for (int q = 0; q < nv; q++)
                st(Y + o + q * VL, finish(acc[j][q], mode, G + o + q * VL, slope));
        }
    }
}

static inline __attribute__((always_inline)) void
affine(int J, int K, int n, int ld, const float *A, int sj, int sk, const float *b,
       const float *X, float *Y, int mode, const float *G, float slope)
{
    int j0 = 0;
    for (; j0 + AJ <= J; j0 += AJ)
        affine_block(AJ, j0, K, n, ld, A, sj, sk, b, X, Y, mode, G, slope);
    if (J - j0 >= 3) {  /* J = 21 with AJ = 6, and J = 3 */
        affine_block(3, j0, K, n, ld, A, sj, sk, b, X, Y, mode, G, slope);
        j0 += 3;
    }
    for (; j0 < J; j0++)
        affine_block(1, j0, K, n, ld, A, sj, sk, b, X, Y, mode, G, slope);
}

static inline float hsum(vf v)
{
    float s = 0;
    for (int i = 0; i < VL; i++)
        s += v[i];
    return s;
}

/* G (J x K) = D X^T, D (J x n), X (K x n); gb (J) = row sums of D (if not NULL).
 * Blocks of OJ = 3 rows of D x KB rows of X, accumulated over all samples. */
static inline __attribute__((always_inline)) void
outer_block(int j0, int KB, int k0, int K, int n, int ld, const float *D, const float *X,
            float *G)
{
    vf acc[OJ][7] = {{{0}}};  /* KB <= 7 columns used; the others are optimised away */
    for (int s = 0; s < n; s += VL) {
        vf d0 = vload(D + (size_t)j0 * ld + s), d1 = vload(D + (size_t)(j0 + 1) * ld + s),
           d2 = vload(D + (size_t)(j0 + 2) * ld + s);
        for (int k = 0; k < KB; k++) {
            vf x = vload(X + (size_t)(k0 + k) * ld + s);
            acc[0][k] += d0 * x;
            acc[1][k] += d1 * x;
            acc[2][k] += d2 * x;
        }
    }
    for (int j = 0; j < 3; j++)
        for (int k = 0; k < KB; k++)
            G[(j0 + j) * K + k0 + k] = hsum(acc[j][k]);
}

static void outer(int J, int K, int n, int ld, const float *D, const float *X, float *G,
                  float *gb)
{
    for (int j0 = 0; j0 < J; j0 += 3) {  /* J is 21 or 3 */
        int k0 = 0;
        for (; k0 + OK <= K; k0 += OK)
            outer_block(j0, OK, k0, K, n, ld, D, X, G);
        switch (K - k0) {  /* the rest (K is 21 or 6; < OK), a constant block size per case */
        case 1: outer_block(j0, 1, k0, K, n, ld, D, X, G); break;
        case 2: outer_block(j0, 2, k0, K, n, ld, D, X, G); break;
        case 3: outer_block(j0, 3, k0, K, n, ld, D, X, G); break;
        case 4: outer_block(j0, 4, k0, K, n, ld, D, X, G); break;
        case 5: outer_block(j0, 5, k0, K, n, ld, D, X, G); break;
        case 6: outer_block(j0, 6, k0, K, n, ld, D, X, G); break;
        }
    }
    if (gb)
        for (int j = 0; j < J; j++) {
            vf a = {0};
            for (int s = 0; s < n; s += VL)
                a += vload(D + (size_t)j * ld + s);
            gb[j] = hsum(a);
        }
}

/* eq. 2 on the raw outputs Y (3 x n): loss, and dY = d loss / d Y written over Y */
static float loss_backward(int n, int ld, float *Y, const float *t, const float *cos)
{
    float loss = 0, scale = 1.0f / (3 * n);
    for (int c = 0; c < 3; c++) {
        float *y = Y + (size_t)c * ld;
        const float *tc = t + (size_t)c * ld;
        for (int s = 0; s < n; s++) {  /* vectorised with libmvec's expf / log1pf */
            float e = expf(y[s]), fc = (e - 1) * cos[s], r = log1pf(fc) - tc[s];
            float sg = (r > 0) - (r < 0);
            loss += fabsf(r);
            y[s] = sg * cos[s] * e / (fc + 1) * scale;
        }
    }
    return loss * scale;
}

static void adam(float *w, const float *g, float *m, float *v, float lr, float bc1, float bc2)
{
    const float b1 = 0.9f, b2 = 0.999f, eps = 1e-8f;
    for (int i = 0; i < NP; i++) {
        m[i] += (1 - b1) * (g[i] - m[i]);
        v[i] = b2 * v[i] + (1 - b2) * g[i] * g[i];
        w[i] -= lr / bc1 * m[i] / (sqrtf(v[i] / bc2) + eps);
    }
}

/* Flush denormals to zero inside the kernel only (and restore the caller's mode): Adam's
 * second moments of near-zero gradients fall below 1e-38, where every operation takes a
 * ~100-cycle microcode assist. */
static unsigned flush_denormals(void)
{
#ifdef __SSE__
    unsigned csr = _mm_getcsr();
    _mm_setcsr(csr | 0x8040);  /* FTZ | DAZ */
    return csr;
#else
    return 0;
#endif
}

static void restore_denormals(unsigned csr)
{
#ifdef __SSE__
    _mm_setcsr(csr);
#else
    (void)csr;
#endif
}

/* Gather one step's minibatch into feature-major rows `ld` apart: inputs + cos (7 x n) and
 * the targets of materials 0..M-1, tb (M * 3 x n). The table rows are read once per step for
 * all materials (3 M contiguous floats each), 16 rows at a time so that every store fills a
 * whole vector. */
static void gather(int M, int n, int ld, const float *xc_all, const float *target_all, int ldt,
                   const int64_t *idx, const float *sign, float *xc, float *tb)
{
    for (int s0 = 0; s0 < n; s0 += VL) {
        if (s0 + VL < n)  /* the next block's rows: random rows of a table larger than L2 */
            for (int u = 0; u < VL; u++) {
                const char *p = (const char *)(target_all + idx[s0 + VL + u] * ldt);
                for (int off = 0; off < 12 * M; off += 64)
                    __builtin_prefetch(p + off);
                __builtin_prefetch(xc_all + 7 * idx[s0 + VL + u]);
            }
        const float *row[VL];
        vf sg = splat(1.f);
        if (sign)
            sg = vload(sign + s0);
        for (int u = 0; u < VL; u++)
            row[u] = xc_all + 7 * idx[s0 + u];
        for (int f = 0; f < 7; f++) {
            vf x;
            for (int u = 0; u < VL; u++)
                x[u] = row[u][f];
            st(xc + (size_t)f * ld + s0, f == 3 || f == 4 ? x * sg : x);  /* phi_d + pi */
        }
        for (int u = 0; u < VL; u++)
            row[u] = target_all + idx[s0 + u] * ldt;
        for (int j = 0; j < 3 * M; j++) {
            vf x;
            for (int u = 0; u < VL; u++)
                x[u] = row[u][j];
            st(tb + (size_t)j * ld + s0, x);
        }
    }
}

void nbrdf_fit_steps(int M, int n, int K, int step0, const float *xc_all,
                     const float *target_all, int ldt, const int64_t *idx, const float *sign,
                     const float *lr, float *w, float *m, float *v, float *grad, float *loss,
                     float *work, float slope)
{
    unsigned csr = flush_denormals();
    int ld = n + PAD;
    float *xc = work, *a1 = xc + 7 * ld, *a2 = a1 + H * ld, *d = a2 + H * ld, *y = d + H * ld,
          *tb = y + 3 * ld;  /* y: 3 x n, tb: M * 3 x n */
    const float *cos = xc + 6 * (size_t)ld;
    for (int k = 0; k < K; k++) {
        gather(M, n, ld, xc_all, target_all, ldt, idx + (size_t)k * n, sign + (size_t)k * n, xc,
               tb);
        int step = step0 + k + 1;  /* Adam's step count, from 1 */
        float bc1 = (float)(1 - pow(0.9, step)), bc2 = (float)(1 - pow(0.999, step));
        for (int i = 0; i < M; i++) {
            float *wi = w + (size_t)i * NP, *g = grad + (size_t)i * NP;
            const float *t = tb + (size_t)i * 3 * ld;
            affine(H, 6, n, ld, wi + OW1, 6, 1, wi + OB1, xc, a1, ACT, NULL, slope);
            affine(H, H, n, ld, wi + OW2, H, 1, wi + OB2, a1, a2, ACT, NULL, slope);
            affine(3, H, n, ld, wi + OW3, H, 1, wi + OB3, a2, y, RAW, NULL, 0);
            loss[i] = loss_backward(n, ld, y, t, cos);  /* y := d loss / d y */
            outer(3, H, n, ld, y, a2, g + OW3, g + OB3);
            /* d2 = W3^T dy * act'(z2), then d1 = W2^T d2 * act'(z1) over a2 (no longer needed) */
            affine(H, 3, n, ld, wi + OW3, 1, H, NULL, y, d, GATE, a2, slope);
            outer(H, H, n, ld, d, a1, g + OW2, g + OB2);
            affine(H, H, n, ld, wi + OW2, 1, H, NULL, d, a2, GATE, a1, slope);
            outer(H, 6, n, ld, a2, xc, g + OW1, g + OB1);
            if (lr[k] > 0)
                adam(wi, g, m + (size_t)i * NP, v + (size_t)i * NP, lr[k], bc1, bc2);
        }
    }
    restore_denormals(csr);
}

/* Eq. 2 loss of the fields as evaluated (f = max(exp(y) - 1, 0), as neumat.fit.field_loss),
 * summed over the bins idx (N,) of the table, no mirroring: out (M,) = sum over bins and
 * channels of |r|, in float64. N must be a multiple of 16 (pad idx) of which the first nv
 * count; chunks of n bins. */
void nbrdf_loss_sums(int M, int n, int N, int nv, const float *xc_all, const float *target_all,
                     int ldt, const int64_t *idx, const float *w, double *out, float *work,
                     float slope)
{
    unsigned csr = flush_denormals();
    int ld = n + PAD;
    float *xc = work, *a1 = xc + 7 * ld, *a2 = a1 + H * ld, *y = a2 + 2 * H * ld,
          *tb = y + 3 * ld;
    const float *cos = xc + 6 * (size_t)ld;
    for (int i = 0; i < M; i++)
        out[i] = 0;
    for (int s0 = 0; s0 < N; s0 += n) {
        int c = N - s0 < n ? N - s0 : n, cv = nv - s0 < c ? nv - s0 : c;
        gather(M, c, ld, xc_all, target_all, ldt, idx + s0, NULL, xc, tb);
        for (int i = 0; i < M; i++) {
            const float *wi = w + (size_t)i * NP, *t = tb + (size_t)i * 3 * ld;
            affine(H, 6, c, ld, wi + OW1, 6, 1, wi + OB1, xc, a1, ACT, NULL, slope);
            affine(H, H, c, ld, wi + OW2, H, 1, wi + OB2, a1, a2, ACT, NULL, slope);
            affine(3, H, c, ld, wi + OW3, H, 1, wi + OB3, a2, y, RAW, NULL, 0);
            float sum = 0;
            for (int ch = 0; ch < 3; ch++)
                for (int s = 0; s < cv; s++) {
                    float e = expf(y[(size_t)ch * ld + s]), f = e > 1 ? e - 1 : 0;
                    sum += fabsf(log1pf(f * cos[s]) - t[(size_t)ch * ld + s]);
                }
            out[i] += sum;
        }
    }
    restore_denormals(csr);
}
