/* encode.cl: NeRF positional encoding gamma, forward and backward.
 *
 * For a point x [3] and a scale s (host argument), with p = s * x (one float32 rounding):
 *   gamma(x) = [p (if ENC_INCLUDE_INPUT)] ++ for k = 0..ENC_FREQS-1:
 *                  [sin(2^k pi p_0), sin(2^k pi p_1), sin(2^k pi p_2),
 *                   cos(2^k pi p_0), cos(2^k pi p_1), cos(2^k pi p_2)]
 * (NeRF's order; s = 1/pi gives NeRF's frequencies 2^k rad per unit.)
 * Accuracy: 2^k p is exact in float32 (a power-of-two scaling) and sincospi_v (common.h, a
 * sinpi/cospi pair) reduces its argument exactly, so every entry is accurate to a few ulp for
 * any |p| and any k, where sin(2^k * pi * p) would lose all accuracy once 2^k pi p ~ 1e7.
 *
 * Memory layout: x [n, 3]; out [n, ENC_DIM] row-major, ENC_DIM = 3*ENC_INCLUDE_INPUT + 6*ENC_FREQS.
 *
 * Backward: dL/dx_c = s * (dL/dp_c [if included]
 *                    + sum_k 2^k pi (cos(2^k pi p_c) dL/dsin_kc - sin(2^k pi p_c) dL/dcos_kc)).
 *
 * Defines read: ENC_FREQS, ENC_INCLUDE_INPUT.
 */
#include "common.h"

#ifndef ENC_FREQS
#define ENC_FREQS 10          /* number of frequency bands L (k = 0..L-1) */
#endif
#ifndef ENC_INCLUDE_INPUT
#define ENC_INCLUDE_INPUT 1   /* 1: the scaled input p itself leads the encoding */
#endif
#if ENC_FREQS < 0 || ENC_FREQS > 30
#error "ENC_FREQS must be in 0..30 (2^k p must stay a float32 power-of-two scaling)"
#endif
#if ENC_INCLUDE_INPUT != 0 && ENC_INCLUDE_INPUT != 1
#error "ENC_INCLUDE_INPUT must be 0 or 1"
#endif
#define ENC_IN0 (3 * ENC_INCLUDE_INPUT)        /* index of the first sin entry */
#define ENC_DIM (ENC_IN0 + 6 * ENC_FREQS)

/* One work-item per (block of 16 points, frequency band, coordinate), vectorised explicitly
 * over the 16 points (float16): PoCL ran the per-point versions (a loop over bands, or scalar
 * code per band) one lane wide. Items of band 0 also write the scaled input. */
#define ENC_ITEMS (ENC_FREQS > 0 ? ENC_FREQS : 1)
#define ENC_BLOCK 16
__kernel void encode_forward(const int n, const float scale, __global const float *x,
                             __global float *out) {
    const int gid = get_global_id(0);
    const int nb = (n + ENC_BLOCK - 1) / ENC_BLOCK;
    if (gid >= 3 * ENC_ITEMS * nb) return;
    const int c = gid % 3, k = (gid / 3) % ENC_ITEMS, b = gid / (3 * ENC_ITEMS);
    const int i0 = b * ENC_BLOCK, m = min(ENC_BLOCK, n - i0);
    float pa[ENC_BLOCK];
    for (int j = 0; j < ENC_BLOCK; ++j) pa[j] = j < m ? scale * x[3 * (i0 + j) + c] : 0.0f;
#if ENC_INCLUDE_INPUT
    if (k == 0)
        for (int j = 0; j < m; ++j) out[(size_t)(i0 + j) * ENC_DIM + c] = pa[j];
#endif
#if ENC_FREQS > 0
    float16 s, co;
    /* 2^k p is exact: a product with a power of two (k <= 30). Written as a product, not as
     * ldexp(float16, int), which Oclgrind 21.10 computes wrongly for vectors. */
    sincospi_v(vload16(0, pa) * (float)(1u << k), &s, &co);
    float sa[ENC_BLOCK], ca[ENC_BLOCK];
    vstore16(s, 0, sa);
    vstore16(co, 0, ca);
    for (int j = 0; j < m; ++j) {
        __global float *o = out + (size_t)(i0 + j) * ENC_DIM + ENC_IN0 + 6 * k + c;
        o[0] = sa[j];
        o[3] = ca[j];
    }
#endif
}

/* dL/dx [n, 3] from dL/dgamma [n, ENC_DIM] (written, not accumulated). */
__kernel void encode_backward(const int n, const float scale, __global const float *x,
                              __global const float *grad_out, __global float *grad_x) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float3 p = scale * (float3)(x[3 * i], x[3 * i + 1], x[3 * i + 2]);
    __global const float *g = grad_out + (size_t)i * ENC_DIM;
    float3 dp = (float3)(0.0f);
#if ENC_INCLUDE_INPUT
    dp = (float3)(g[0], g[1], g[2]);
#endif
    float f = 1.0f;
    for (int k = 0; k < ENC_FREQS; ++k, f *= 2.0f) {
        const float3 a = f * p;
        float3 s, c;
    sincospi_v(a, &s, &c);
        __global const float *gk = g + ENC_IN0 + 6 * k;
        const float3 gs = (float3)(gk[0], gk[1], gk[2]), gc = (float3)(gk[3], gk[4], gk[5]);
        dp += (f * M_PI_F) * (c * gs - s * gc);
    }
    const float3 dx = scale * dp;
    grad_x[3 * i] = dx.x;
    grad_x[3 * i + 1] = dx.y;
    grad_x[3 * i + 2] = dx.z;
}
