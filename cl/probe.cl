/* probe.cl: the kernels clrf/device_probe.py runs once on every candidate device (results are
 * cached per device and driver version).
 *
 *   clrf_probe      the smallest kernel that proves a device can compile and run OpenCL C:
 *                   a[i] += 1.
 *   clrf_probe_fma  fp32 throughput. Each work-item runs PROBE_CHAINS independent floatPROBE_WIDTH
 *                   chains x <- fma(x, m, a) for iters = trip[0] steps, lane l of every chain
 *                   with its own m_l = coef[l] and a_l = coef[8 + l], chain c of work-item i
 *                   starting at x0 = coef[16 + c] + (i & 63) * coef[24], and writes the sum of
 *                   all lanes of all chains:
 *                     out[i] = sum_c sum_l (p_l + (x0 - p_l) m_l^iters),  p_l = a_l / (1 - m_l)
 *                   flop = 2 * PROBE_WIDTH * PROBE_CHAINS * iters per work-item.
 *                   Everything the chains compute comes from buffers and differs per lane and
 *                   per work-item: a compiler that vectorises across work-items (Intel's) can
 *                   no longer run one uniform chain for a whole group, which with kernel
 *                   arguments as coefficients let it report ten times the CPU's peak; the host
 *                   checks every out[i] against the closed form.
 *                   Written with explicit vectors because PoCL vectorises only what is written
 *                   as vectors; float8 is one AVX register (a float16 argument to fma() is split
 *                   into a call on AVX2); the independent chains cover the FMA latency. A driver
 *                   that compiles for a generic x86-64 target (SSE2, no hardware FMA) runs it
 *                   about ten times slower than one that targets the CPU: that is what the
 *                   device ranking has to see.
 *
 * Defines read: PROBE_CHAINS, PROBE_WIDTH (the host passes both and counts flops with them).
 */
#ifndef PROBE_CHAINS
#define PROBE_CHAINS 8  /* independent FMA chains per work-item */
#endif
#ifndef PROBE_WIDTH
#define PROBE_WIDTH 8   /* lanes per chain (float8) */
#endif
#if PROBE_CHAINS != 8 || PROBE_WIDTH != 8
#error "clrf_probe_fma is written out for 8 chains of float8"
#endif

__kernel void clrf_probe(__global float *a) { a[get_global_id(0)] += 1.0f; }

__kernel void clrf_probe_fma(__global const int *trip, __global const float *coef,
                             __global float *out) {
    const size_t i = get_global_id(0);
    const int iters = trip[0];
    const float8 mv = vload8(0, coef), av = vload8(1, coef);
    const float base = (float)(i & 63) * coef[24];
    float8 c0 = (float8)(coef[16] + base), c1 = (float8)(coef[17] + base);
    float8 c2 = (float8)(coef[18] + base), c3 = (float8)(coef[19] + base);
    float8 c4 = (float8)(coef[20] + base), c5 = (float8)(coef[21] + base);
    float8 c6 = (float8)(coef[22] + base), c7 = (float8)(coef[23] + base);
    for (int k = 0; k < iters; ++k) {
        c0 = fma(c0, mv, av); c1 = fma(c1, mv, av); c2 = fma(c2, mv, av); c3 = fma(c3, mv, av);
        c4 = fma(c4, mv, av); c5 = fma(c5, mv, av); c6 = fma(c6, mv, av); c7 = fma(c7, mv, av);
    }
    const float8 s = ((c0 + c1) + (c2 + c3)) + ((c4 + c5) + (c6 + c7));
    out[i] = ((s.s0 + s.s1) + (s.s2 + s.s3)) + ((s.s4 + s.s5) + (s.s6 + s.s7));
}
