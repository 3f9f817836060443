/* Histogram-preserving blending of a C-channel plane, one query per loop iteration: the same
 * maths as hpb.py's torch path (triangle grid in double, integer vertex hash, fetch
 * coordinates formed in double from frac(u) then rounded to float, bilinear wrap fetch of the
 * Gaussianised plane, variance-preserving blend, inverse LUT, inverse PCA), fused so each
 * query touches memory once instead of once per torch op. Compiled without -ffast-math:
 * results equal the torch path up to float summation order. */
#include <math.h>
#include <stdint.h>

static inline uint32_t mix(uint32_t x) {
    x ^= x >> 16;
    x *= 0x7FEB352Du;
    x ^= x >> 15;
    x *= 0x2C1B3C6Du;
    return x ^ (x >> 16);
}

static inline int wrapi(int64_t i, int n) {
    int64_t r = i % n;
    return (int)(r < 0 ? r + n : r);
}

#define MAXC 64

int hpb_features(int64_t n, const double *u, const float *gauss, int H, int W, int C,
                 const float *lut, int L, const float *mean, const float *basis,
                 uint32_t seed, float *out) {
    if (C > MAXC) return -1;
    const double S3 = sqrt(3.0);
    const uint32_t hs = mix(seed);
    const float top = 1.0f - 5.9604644775390625e-08f;   /* 1 - 2^-24 */
    for (int64_t k = 0; k < n; k++) {
        double ux = u[2 * k], uy = u[2 * k + 1];
        double stx = ux * (2 * S3), sty = uy * (2 * S3);
        double s0 = stx - sty / S3, s1 = 2 * sty / S3;
        double b0 = floor(s0), b1 = floor(s1);
        double f0 = s0 - b0, f1 = s1 - b1, z = 1 - f0 - f1;
        int64_t v[3][2];
        double wd[3];
        int64_t ib0 = (int64_t)b0, ib1 = (int64_t)b1;
        if (z > 0) {
            v[0][0] = ib0;     v[0][1] = ib1;     wd[0] = z;
            v[1][0] = ib0;     v[1][1] = ib1 + 1; wd[1] = f1;
            v[2][0] = ib0 + 1; v[2][1] = ib1;     wd[2] = f0;
        } else {
            v[0][0] = ib0 + 1; v[0][1] = ib1 + 1; wd[0] = -z;
            v[1][0] = ib0 + 1; v[1][1] = ib1;     wd[1] = 1 - f1;
            v[2][0] = ib0;     v[2][1] = ib1 + 1; wd[2] = 1 - f0;
        }
        double fx = ux - floor(ux), fy = uy - floor(uy);
        /* torch.remainder(u, 1) can round to 1.0 for tiny negative u; keep the same value */
        if (fx >= 1.0) fx -= 1.0;
        if (fy >= 1.0) fy -= 1.0;
        float w[3], acc[MAXC], ww = 0;
        for (int c = 0; c < C; c++) acc[c] = 0;
        for (int i = 0; i < 3; i++) {
            w[i] = (float)wd[i];
            ww += w[i] * w[i];
            uint32_t h = mix((uint32_t)v[i][1] ^ mix((uint32_t)v[i][0] ^ hs));
            h = mix(h ^ 0x9E3779B1u);
            double hx = h / 4294967296.0;
            h = mix(h ^ 0x9E3779B2u);
            double hy = h / 4294967296.0;
            double px = fx + hx, py = fy + hy;
            px -= floor(px);
            py -= floor(py);
            float x = (float)px, y = (float)py;
            x = x < 0 ? 0 : (x > top ? top : x);
            y = y < 0 ? 0 : (y > top ? top : y);
            float X = x * W - 0.5f, Y = y * H - 0.5f;
            float x0 = floorf(X), y0 = floorf(Y);
            float ax = X - x0, ay = Y - y0;
            int xa = wrapi((int64_t)x0, W), xb = wrapi((int64_t)x0 + 1, W);
            int ya = wrapi((int64_t)y0, H), yb = wrapi((int64_t)y0 + 1, H);
            float t00 = (1 - ax) * (1 - ay), t01 = ax * (1 - ay), t10 = (1 - ax) * ay, t11 = ax * ay;
            const float *p00 = gauss + ((int64_t)ya * W + xa) * C, *p01 = gauss + ((int64_t)ya * W + xb) * C;
            const float *p10 = gauss + ((int64_t)yb * W + xa) * C, *p11 = gauss + ((int64_t)yb * W + xb) * C;
            for (int c = 0; c < C; c++) {
                float g = t00 * p00[c] + t01 * p01[c] + t10 * p10[c] + t11 * p11[c];
                acc[c] += (g - 0.5f) * w[i];
            }
        }
        float inv = 1.0f / sqrtf(ww);
        float q[MAXC];
        for (int c = 0; c < C; c++) {
            float g = acc[c] * inv + 0.5f;
            g = g < 0 ? 0 : (g > 1 ? 1 : g);
            float x = g * L - 0.5f;
            x = x < 0 ? 0 : (x > L - 1 ? (float)(L - 1) : x);
            int i0 = (int)floorf(x);
            if (i0 > L - 2) i0 = L - 2;
            if (i0 < 0) i0 = 0;
            float t = x - i0;
            const float *row = lut + (int64_t)c * L;
            float a = row[i0], b = row[i0 + 1 < L ? i0 + 1 : L - 1];
            q[c] = a + t * (b - a);
        }
        float *o = out + k * C;
        for (int j = 0; j < C; j++) {
            float s = mean[j];
            for (int c = 0; c < C; c++) s += q[c] * basis[j * C + c];
            o[j] = s;
        }
    }
    return 0;
}
