/* bench_fma.cl: the device's fp32 FMA throughput, the reference every kernel benchmark is
 * divided by (benchmarks on a shared host swing by 2x; ratios do not).
 *
 * Each work-item runs FMA_CHAINS independent float16 FMA chains for `iters` iterations
 * (2 * 16 * FMA_CHAINS flops per iteration) and writes their sum so nothing is optimised away.
 * Independent chains hide the FMA latency; float16 is what PoCL needs to use full-width vectors.
 *
 * Defines read: FMA_CHAINS.
 */
#ifndef FMA_CHAINS
#define FMA_CHAINS 8  /* independent accumulators per work-item (FMA latency x throughput) */
#endif
#if FMA_CHAINS != 8
#error "FMA_CHAINS: only 8 is written out"
#endif

__kernel void fma_peak(const int iters, const float a, const float b, __global float *out) {
    const int i = get_global_id(0);
    float16 x0 = (float16)(i), x1 = x0 + 1.0f, x2 = x0 + 2.0f, x3 = x0 + 3.0f;
    float16 x4 = x0 + 4.0f, x5 = x0 + 5.0f, x6 = x0 + 6.0f, x7 = x0 + 7.0f;
    const float16 va = (float16)(a), vb = (float16)(b);
    for (int k = 0; k < iters; ++k) {
        x0 = fma(x0, va, vb); x1 = fma(x1, va, vb); x2 = fma(x2, va, vb); x3 = fma(x3, va, vb);
        x4 = fma(x4, va, vb); x5 = fma(x5, va, vb); x6 = fma(x6, va, vb); x7 = fma(x7, va, vb);
    }
    const float16 s = ((x0 + x1) + (x2 + x3)) + ((x4 + x5) + (x6 + x7));
    out[i] = s.s0 + s.s1 + s.s2 + s.s3 + s.s4 + s.s5 + s.s6 + s.s7 + s.s8 + s.s9 + s.sa + s.sb +
             s.sc + s.sd + s.se + s.sf;
}
