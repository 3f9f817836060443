/* Pairwise L1 distances between the rows of A (M x D) and B (N x D), float32 in, float64 out:
 * out[i, j] = sum_d |A[i, d] - B[j, d]| (neumat.metrics.distances.pairwise_l1; torch.cdist(p=1)
 * ran at ~0.5 G pair-dims/s on one core, a third of the default config's metric job).
 *
 * Cache blocking: a chunk of DC floats of IO rows of A stays in L2 while every row of B streams
 * past it once, so each float of B read from memory serves IO rows of A. Inside, an IB x JB
 * register block: IB + JB vector loads feed IB * JB sub/abs/add. Partial sums are float32 over
 * one chunk (DC / VL = 64 terms a lane) and float64 across chunks.
 *
 * Vector width and register blocking follow the target ISA (compile time), as in fit_step.c. */
#include <stddef.h>

#if defined(__AVX512F__)
#define VL 16
enum { IB = 4, JB = 4 };   /* 16 accumulators + 8 inputs of 32 registers */
#elif defined(__AVX__)
#define VL 8
enum { IB = 3, JB = 3 };   /* 9 + 6 of 16 */
#else
#define VL 4
enum { IB = 3, JB = 3 };
#endif
#define DC 1024             /* floats of a row per chunk: 4 KB */
#define IO 32               /* rows of A per outer block: 128 KB of chunks in L2 */

typedef float vf __attribute__((vector_size(4 * VL), aligned(4), may_alias));
typedef int vi __attribute__((vector_size(4 * VL), aligned(4), may_alias));

static inline vf vload(const float *p) { return *(const vf *)p; }
static inline vf vabs(vf x) { return (vf)((vi)x & 0x7fffffff); }

static inline float hsum(vf v)
{
    float s = 0;
    for (int k = 0; k < VL; k++)
        s += v[k];
    return s;
}

/* out[i, j] += the chunk's sum for rows a[0 .. ib) x b[0 .. jb); ib, jb constants after
 * inlining for the full block, run-time at the edges. */
static inline __attribute__((always_inline)) void
block(int ib, int jb, long n, const float *a, const float *b, long D, double *out, long N)
{
    vf acc[IB][JB];
    for (int x = 0; x < ib; x++)
        for (int y = 0; y < jb; y++)
            acc[x][y] = (vf){0};
    long nv = n - n % VL;
    for (long k = 0; k < nv; k += VL) {
        vf va[IB], vb[JB];
        for (int x = 0; x < ib; x++)
            va[x] = vload(a + x * D + k);
        for (int y = 0; y < jb; y++)
            vb[y] = vload(b + y * D + k);
        for (int x = 0; x < ib; x++)
            for (int y = 0; y < jb; y++)
                acc[x][y] += vabs(va[x] - vb[y]);
    }
    for (int x = 0; x < ib; x++)
        for (int y = 0; y < jb; y++) {
            float s = hsum(acc[x][y]);
            for (long k = nv; k < n; k++) {
                float d = a[x * D + k] - b[y * D + k];
                s += d < 0 ? -d : d;
            }
            out[x * N + y] += s;
        }
}

void l1_pairwise(long M, long N, long D, const float *A, const float *B, double *out)
{
    for (long i = 0; i < M * N; i++)
        out[i] = 0;
    for (long i0 = 0; i0 < M; i0 += IO) {
        long i1 = i0 + IO < M ? i0 + IO : M;
        for (long d0 = 0; d0 < D; d0 += DC) {
            long n = D - d0 < DC ? D - d0 : DC;
            for (long j = 0; j < N; j += JB) {
                int jb = N - j < JB ? (int)(N - j) : JB;
                for (long i = i0; i < i1; i += IB) {
                    int ib = i1 - i < IB ? (int)(i1 - i) : IB;
                    const float *a = A + i * D + d0, *b = B + j * D + d0;
                    double *o = out + i * N + j;
                    if (ib == IB && jb == JB)
                        block(IB, JB, n, a, b, D, o, N);
                    else
                        block(ib, jb, n, a, b, D, o, N);
                }
            }
        }
    }
}
