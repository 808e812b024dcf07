/* bench.cl: reference kernels that measure the device's own peaks in the same run as the
 * benchmarks (tools/bench.py), so every figure can be given as a ratio to them.
 *
 *   bench_copy   a[i] = b[i]                 float16 per work-item; bytes = 2 * 4 * n
 *   bench_triad  a[i] = b[i] + s * c[i]      float16 per work-item; bytes = 3 * 4 * n (STREAM count)
 *   bench_fma    FMA_CHAINS independent float16 chains of FMA_ITERS fused multiply-adds each;
 *                flop = 2 * 16 * FMA_CHAINS * FMA_ITERS per work-item. Explicit float16 because
 *                PoCL runs a work-item's scalar loop one lane wide.
 *
 * n is in floats and a multiple of 16 (the host pads). Defines read: FMA_CHAINS, FMA_ITERS.
 */
#include "common.h"   /* for its -Wpsabi note: float16 builtin calls */

#ifndef FMA_CHAINS
#define FMA_CHAINS 8    /* independent dependency chains: enough to cover the FMA latency */
#endif
#ifndef FMA_ITERS
#define FMA_ITERS 1024  /* FMAs per chain per work-item */
#endif
#if FMA_CHAINS != 8
#error "bench_fma is written out for FMA_CHAINS == 8"
#endif

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
    float16 x0 = (float16)((float)i * 1e-7f), x1 = x0 + 0.1f, x2 = x0 + 0.2f, x3 = x0 + 0.3f;
    float16 x4 = x0 + 0.4f, x5 = x0 + 0.5f, x6 = x0 + 0.6f, x7 = x0 + 0.7f;
    const float16 mv = (float16)(m), av = (float16)(add);
    for (int k = 0; k < FMA_ITERS; ++k) {
        x0 = fma(x0, mv, av); x1 = fma(x1, mv, av); x2 = fma(x2, mv, av); x3 = fma(x3, mv, av);
        x4 = fma(x4, mv, av); x5 = fma(x5, mv, av); x6 = fma(x6, mv, av); x7 = fma(x7, mv, av);
    }
    const float16 s = ((x0 + x1) + (x2 + x3)) + ((x4 + x5) + (x6 + x7));
    out[i] = s.s0 + s.s1 + s.s2 + s.s3 + s.s4 + s.s5 + s.s6 + s.s7 + s.s8 + s.s9 + s.sa + s.sb +
             s.sc + s.sd + s.se + s.sf;
}
