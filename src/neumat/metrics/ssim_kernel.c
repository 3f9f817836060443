/* SSIM of every pair of two image sets (neumat.metrics.distances.pairwise_ssim), one pass per
 * pair and channel: the 7 x 7 box of x y by sliding sums over rows (a ring of the last 7 rows'
 * horizontal sums), fused with the SSIM formula and the mean over windows. The per-image terms
 * (box means ux, and the parts of the formula that depend on one image alone) come from the
 * caller, so a pair costs ~15 vector operations per pixel in place of torch's two band-matrix
 * products (~370 FLOP per pixel) and a dozen passes over memory.
 *
 *   x (n, C, H, W), y (m, C, H, W)               float32 images
 *   sx (n, C), sy (m, C)                          shifts (the channels' means): the covariance
 *                                                 box((x - sx)(y - sy)) - (u - sx)(u' - sy)
 *                                                 cancels far less than box(x y) - u u'
 *   ux, qx, rx (n, C, H - 6, W - 6); uy, qy, ry   per-image terms: u = box mean,
 *                                                 q = u^2 (+ c1 for y), r = k var (+ c2 for y)
 *   out[i, j] = mean over C and the windows of (2 u u' + c1)(2 k (box(x y) - u u') + c2)
 *                                              / ((q + q')(r + r'))
 * Rows of `out` are taken in blocks of IB, block b by worker b % workers (the caller's threads);
 * sym: x is y and only j >= i is computed.
 * The window sums add 7 terms in a fixed order (no running add-and-subtract, whose rounding
 * drift would show in the small covariances). */
#include <stddef.h>

#define WIN 7
#define WMAX 1024   /* widest image */
#define IB 4        /* x images whose channel stays in L2 while y streams past */

static void pair_channel(int H, int W, const float *restrict x, const float *restrict y,
                         float sx, float sy, const float *restrict ux, const float *restrict qx,
                         const float *restrict rx, const float *restrict uy,
                         const float *restrict qy, const float *restrict ry,
                         float c1, float c2, float k, double *acc)
{
    const int Wv = W - WIN + 1;
    float ring[WIN][WMAX], prod[WMAX];
    const float scale = 1.0f / (WIN * WIN);
    double total = 0;
    for (int r = 0; r < H; r++) {
        const float *xr = x + (long)r * W, *yr = y + (long)r * W;
        for (int w = 0; w < W; w++)
            prod[w] = (xr[w] - sx) * (yr[w] - sy);
        float *h = ring[r % WIN];
        for (int w = 0; w < Wv; w++)
            h[w] = ((prod[w] + prod[w + 1]) + (prod[w + 2] + prod[w + 3])) +
                   ((prod[w + 4] + prod[w + 5]) + prod[w + 6]);
        if (r < WIN - 1)
            continue;
        long o = (long)(r - WIN + 1) * Wv;  /* the window row that ends at row r */
        float row = 0;
        for (int w = 0; w < Wv; w++) {
            float v = ((ring[0][w] + ring[1][w]) + (ring[2][w] + ring[3][w])) +
                      ((ring[4][w] + ring[5][w]) + ring[6][w]);
            float uu = ux[o + w] * uy[o + w], cu = (ux[o + w] - sx) * (uy[o + w] - sy);
            float num = ((v * scale - cu) * (2 * k) + c2) * (2 * uu + c1);
            float den = (qx[o + w] + qy[o + w]) * (rx[o + w] + ry[o + w]);
            row += num / den;
        }
        total += row;
    }
    *acc += total;
}

int ssim_pairs(long n, long m, int C, int H, int W, const float *x, const float *y,
               const float *sx, const float *sy, const float *ux, const float *qx, const float *rx, const float *uy,
               const float *qy, const float *ry, float c1, float c2, float k, int sym,
               int worker, int workers, double *out)
{
    if (W > WMAX || H < WIN || W < WIN)
        return 1;
    const long img = (long)H * W, win = (long)(H - WIN + 1) * (W - WIN + 1);
    for (long i0 = (long)worker * IB; i0 < n; i0 += (long)workers * IB) {
        long i1 = i0 + IB < n ? i0 + IB : n;
        for (long i = i0; i < i1; i++)
            for (long j = sym ? i : 0; j < m; j++)
                out[i * m + j] = 0;
        for (int c = 0; c < C; c++)
            for (long j = sym ? i0 : 0; j < m; j++)
                for (long i = i0; i < i1 && (!sym || i <= j); i++) {
                    long a = i * C + c, b = j * C + c;
                    pair_channel(H, W, x + a * img, y + b * img, sx[a], sy[b], ux + a * win, qx + a * win,
                                 rx + a * win, uy + b * win, qy + b * win, ry + b * win, c1,
                                 c2, k, out + i * m + j);
                }
        for (long i = i0; i < i1; i++)
            for (long j = sym ? i : 0; j < m; j++)
                out[i * m + j] /= (double)C * win;
    }
    return 0;
}
