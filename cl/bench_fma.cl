/* bench_fma.cl: the device's fp32 FMA throughput, the reference every kernel benchmark is
 * divided by (benchmarks on a shared host swing by 2x; ratios do not).
 *
 * Each work-item runs FMA_CHAINS independent chains of floatFMA_VEC FMAs for `iters` iterations
 * (2 * FMA_VEC * FMA_CHAINS flops per iteration) and writes their sum so nothing is optimised
 * away. Independent chains hide the FMA latency; FMA_VEC is the device's native float vector
 * width (8 AVX2, 16 AVX-512): wider vectors take two registers each and the chains spill.
 *
 * Defines read: FMA_CHAINS, FMA_VEC.
 */
#ifndef FMA_CHAINS
#define FMA_CHAINS 8  /* independent accumulators per work-item (FMA latency x throughput) */
#endif
#ifndef FMA_VEC
#define FMA_VEC 16    /* float vector width: 4, 8 or 16 */
#endif
#if FMA_CHAINS != 8
#error "FMA_CHAINS: only 8 is written out"
#endif
#if FMA_VEC != 4 && FMA_VEC != 8 && FMA_VEC != 16
#error "FMA_VEC must be 4, 8 or 16"
#endif
#define FMA_CAT_(a, b) a##b
#define FMA_CAT(a, b) FMA_CAT_(a, b)
#define vec_t FMA_CAT(float, FMA_VEC)

__kernel void fma_peak(const int iters, const float a, const float b, __global float *out) {
    const int i = get_global_id(0);
    vec_t x0 = (vec_t)(i), x1 = x0 + 1.0f, x2 = x0 + 2.0f, x3 = x0 + 3.0f;
    vec_t x4 = x0 + 4.0f, x5 = x0 + 5.0f, x6 = x0 + 6.0f, x7 = x0 + 7.0f;
    const vec_t va = (vec_t)(a), vb = (vec_t)(b);
    for (int k = 0; k < iters; ++k) {
        x0 = fma(x0, va, vb); x1 = fma(x1, va, vb); x2 = fma(x2, va, vb); x3 = fma(x3, va, vb);
        x4 = fma(x4, va, vb); x5 = fma(x5, va, vb); x6 = fma(x6, va, vb); x7 = fma(x7, va, vb);
    }
    float lanes[FMA_VEC];
    FMA_CAT(vstore, FMA_VEC)(((x0 + x1) + (x2 + x3)) + ((x4 + x5) + (x6 + x7)), 0, lanes);
    float s = 0.0f;
    for (int c = 0; c < FMA_VEC; ++c) s += lanes[c];
    out[i] = s;
}
