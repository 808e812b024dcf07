/* reduce.h: the terms and the merge of an accurate sum of squared differences
 * sum_i (x_i - y_i)^2 over float32 arrays, for pyopencl's ReductionKernel (clrf/metrics.py
 * sum_squares: map_expr sq_diff(x[i], y[i]), reduce_expr acc_add(a, b), neutral ACC_ZERO).
 * A float32 running sum loses ~log2(n) bits over millions of rays. Two accumulators, chosen at
 * build time:
 *
 *   REDUCE_FP64 1  each difference is formed in double (exact for two floats), squared and
 *                  summed in double. Relative error ~ n * 1.1e-16.
 *   REDUCE_FP64 0  compensated float32: a partial sum is an unevaluated pair (hi, lo) of floats
 *                  worth hi + lo. A term enters as the exact difference (TwoSum) squared, with
 *                  the square's rounding error from fma; pairs merge with Knuth's TwoSum on the
 *                  heads, so only the small tails are rounded (a double-float sum).
 *
 * Requires IEEE round-to-nearest: never build with -cl-fast-relaxed-math (TwoSum would fold).
 *
 * Defines read: REDUCE_FP64 (0/1).
 */
#ifndef CLRF_REDUCE_H
#define CLRF_REDUCE_H

#ifndef REDUCE_FP64
#define REDUCE_FP64 0   /* 1: double accumulation (needs cl_khr_fp64); 0: compensated float32 */
#endif
#if REDUCE_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double acc_t;
#define ACC_ZERO 0.0
inline acc_t acc_add(acc_t a, acc_t b) { return a + b; }
/* (a - b)^2: the difference of two floats is exact in double. */
inline acc_t sq_diff(float a, float b) { double d = (double)a - (double)b; return d * d; }
#else
typedef float2 acc_t;
#define ACC_ZERO ((float2)(0.0f, 0.0f))
/* Knuth's TwoSum: s + e == a + b exactly (round to nearest). */
inline float2 two_sum(float a, float b) {
    float s = a + b;
    float bp = s - a;
    float e = (a - (s - bp)) + (b - bp);
    return (float2)(s, e);
}
/* Sum of two pairs: heads with TwoSum, tails (small) added in float. */
inline acc_t acc_add(acc_t a, acc_t b) {
    float2 h = two_sum(a.x, b.x);
    return (float2)(h.x, h.y + (a.y + b.y));
}
/* (a - b)^2 as a pair: exact difference d = (dh, dl), exact square of dh via fma, plus the
 * cross term 2 dh dl (dl^2 is below the float32 resolution of the result). */
inline acc_t sq_diff(float a, float b) {
    float2 d = two_sum(a, -b);
    float p = d.x * d.x;
    return (float2)(p, fma(d.x, d.x, -p) + 2.0f * d.x * d.y);
}
#endif

#endif /* CLRF_REDUCE_H */
