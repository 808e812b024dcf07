/* bench.cl: reference kernels that measure the device's own peaks in the same run as the
 * benchmarks (tools/bench.py), so every figure can be given as a ratio to them.
 *
 *   bench_copy   a[i] = b[i]                 float16 per work-item; bytes = 2 * 4 * n
 *   bench_triad  a[i] = b[i] + s * c[i]      float16 per work-item; bytes = 3 * 4 * n (STREAM count)
 *   bench_fma    FMA_CHAINS independent floatFMA_VEC chains of FMA_ITERS fused multiply-adds
 *                each; flop = 2 * FMA_VEC * FMA_CHAINS * FMA_ITERS per work-item. Explicit
 *                vectors because PoCL runs a scalar loop one lane wide; FMA_VEC is the device's
 *                native float width (8 AVX2, 16 AVX-512): wider ones need two registers each
 *                and the 8 chains spill.
 *
 * n is in floats and a multiple of 16 (the host pads). Defines read: FMA_CHAINS, FMA_ITERS,
 * FMA_VEC.
 */
#include "common.h"   /* for its -Wpsabi note: float16 builtin calls */

#ifndef FMA_CHAINS
#define FMA_CHAINS 8    /* independent dependency chains: enough to cover the FMA latency */
#endif
#ifndef FMA_ITERS
#define FMA_ITERS 1024  /* FMAs per chain per work-item */
#endif
#ifndef FMA_VEC
#define FMA_VEC 16      /* float vector width of the FMA chains: 4, 8 or 16 */
#endif
#if FMA_CHAINS != 8
#error "bench_fma is written out for FMA_CHAINS == 8"
#endif
#if FMA_VEC != 4 && FMA_VEC != 8 && FMA_VEC != 16
#error "FMA_VEC must be 4, 8 or 16"
#endif
#define FMA_CAT_(a, b) a##b
#define FMA_CAT(a, b) FMA_CAT_(a, b)
#define vec_t FMA_CAT(float, FMA_VEC)

__kernel void bench_copy(__global float16 *restrict a, __global const float16 *restrict b) {
    const size_t i = get_global_id(0);
    a[i] = b[i];
}

__kernel void bench_triad(__global float16 *restrict a, __global const float16 *restrict b,
                          __global const float16 *restrict c, const float s) {
    const size_t i = get_global_id(0);
    a[i] = b[i] + s * c[i];
}

/* out[i] keeps the chains alive (the compiler cannot drop them). */
__kernel void bench_fma(__global float *out, const float m, const float add) {
    const size_t i = get_global_id(0);
    vec_t x0 = (vec_t)((float)i * 1e-7f), x1 = x0 + 0.1f, x2 = x0 + 0.2f, x3 = x0 + 0.3f;
    vec_t x4 = x0 + 0.4f, x5 = x0 + 0.5f, x6 = x0 + 0.6f, x7 = x0 + 0.7f;
    const vec_t mv = (vec_t)(m), av = (vec_t)(add);
    for (int k = 0; k < FMA_ITERS; ++k) {
        x0 = fma(x0, mv, av); x1 = fma(x1, mv, av); x2 = fma(x2, mv, av); x3 = fma(x3, mv, av);
        x4 = fma(x4, mv, av); x5 = fma(x5, mv, av); x6 = fma(x6, mv, av); x7 = fma(x7, mv, av);
    }
    float lanes[FMA_VEC];
    FMA_CAT(vstore, FMA_VEC)(((x0 + x1) + (x2 + x3)) + ((x4 + x5) + (x6 + x7)), 0, lanes);
    float s = 0.0f;
    for (int c = 0; c < FMA_VEC; ++c) s += lanes[c];
    out[i] = s;
}
