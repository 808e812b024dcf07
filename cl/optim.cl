/* optim.cl: the optimisers, one per OPT_MODE: RMSProp and SGD over the parameter rows touched
 * in this step (grid), Adam over a flat parameter buffer (NeRF's MLPs).
 *
 * update_rows (OPT_MODE 0, 1): param, grad, state are float [n_rows, D] (row-major); touched
 * uchar [n_rows].
 * For each touched row k and column j (i = k*D + j), with g = clamp(grad[i], +-GRAD_CLAMP):
 *   RMSProp (OPT_MODE 0, svox2's variant): s = state[i] == 0 ? g^2 : beta s + (1 - beta) g^2,
 *                                          param[i] -= lr g / (sqrt(s) + eps)
 *     (on a first touch sqrt(s) is |g| itself, so the step is lr g / (|g| + eps) even where g^2
 *     underflows float32, |g| < ~1e-19; a state that underflowed stays 0, so the next touch is
 *     again a first touch - the float64 twin would keep s ~ g^2 there)
 *   SGD     (OPT_MODE 1):                  param[i] -= lr g
 * then grad[i] = 0, so gradient buffers stay zero outside the rows touched by the next step
 * (no dense zero-fill per step). With clear_touched = 1 the row's flag is reset too.
 * Only the columns j with j % group < live step (group = live = D: all of them); the others'
 * gradient is consumed and their parameter and state left as they are (the grid's SH rows,
 * channel-major: group = SH_BASIS, live = 1 trains band 0 alone, grid.sh_diffuse_until).
 * A zero or NaN gradient leaves param and state unchanged (state stays 0 until the first real
 * touch); +-inf is clamped like any huge gradient.
 *
 *
 * adam_step (OPT_MODE 2; Kingma & Ba, with bias correction): p, g, m, v are float [n], one
 * work-item per parameter i0 <= i < n (no loops: PoCL vectorises across the group; a span
 * [i0, n) skips entries that never get a gradient, such as a hash table's unused rows;
 * adam_multi takes the spans of one or several buffers in one launch (GPUs)):
 *   g' = g + wd p (L2 weight decay, wd a host argument; 0 for plain Adam); with clear_grad
 *   the gradient entry is set to 0 once read (for gradients that backward passes add into),
 *   m = b1 m + (1 - b1) g',  v = b2 v + (1 - b2) g'^2  (each set to 0 when below FLT_MIN),
 *   p -= lr (m / bc1) / (sqrt(v / bc2) + eps),  bc1 = 1 - b1^t, bc2 = 1 - b2^t (host, float64).
 * A zero gradient on a zero moment leaves p unchanged (0 / (0 + eps) = 0), which keeps the
 * MLP's zero padding at zero. Non-finite gradients are skipped (p, m, v unchanged) so one bad
 * sample cannot poison the moments.
 *
 * Defines read: OPT_MODE. Mirrored by reference.rmsprop_rows / sgd_rows and the Adam formula in
 * tests/test_nerf_model.py.
 */
#include "common.h"
#include "adam.h"

#ifndef OPT_MODE
#define OPT_MODE 0  /* 0: RMSProp, 1: SGD, 2: Adam */
#endif
#if OPT_MODE < 0 || OPT_MODE > 2
#error "OPT_MODE must be 0 (RMSProp), 1 (SGD) or 2 (Adam)"
#endif
/* |g| above this is clamped, so g*g stays finite in float32 (1e18^2 = 1e36 < 3.4e38). */
#define GRAD_CLAMP 1e18f

#if OPT_MODE < 2
__kernel void update_rows(const int n_rows, const int D, __global float *param,
                          __global float *grad, __global float *state,
                          __global uchar *touched, const float lr, const float beta,
                          const float eps, const int clear_touched, const int group,
                          const int live) {
    const int k = get_global_id(0);
    if (k >= n_rows || !touched[k]) return;
    for (int j = 0; j < D; ++j) {
        const size_t i = (size_t)k * D + j;
        const float g0 = grad[i];
        grad[i] = 0.0f;
        if (j % group >= live) continue;
        /* NaN is skipped like 0: clamp(NaN) is fmin(fmax(NaN, -C), C) = -C on conformant
         * devices, which stepped the parameter by +lr and set the state to 1e36 */
        if (g0 == 0.0f || isnan(g0)) continue;
        const float g = clamp(g0, -GRAD_CLAMP, GRAD_CLAMP);
#if OPT_MODE == 0
        const float s0 = state[i];
        const float s = s0 == 0.0f ? g * g : beta * s0 + (1.0f - beta) * g * g;
        state[i] = s;
        /* first touch: sqrt(g^2) = |g| taken exactly (g^2 underflows to 0 for |g| < ~1e-19;
         * with eps = 0 that was g / 0 = inf), and g / den before lr so that step is +-lr */
        const float den = (s0 == 0.0f ? fabs(g) : sqrt(s)) + eps;
        param[i] -= lr * (g / den);
#else
        param[i] -= lr * g;
#endif
    }
    if (clear_touched) touched[k] = 0;
}
#else
/* The update of entry i (the formula above), shared by adam_step and adam_multi. */
CLRF_INLINE void adam_update(const int i, __global float *p, __global float *g, __global float *m,
                        __global float *v, const float lr, const float b1, const float b2,
                        const float eps, const float bc1, const float bc2, const float wd,
                        const int clear_grad) {
    const float g0 = g[i];
    if (clear_grad) g[i] = 0.0f;         /* the next backward adds into a zero gradient */
    if (!isfinite(g0)) return;
    const float gi = g0 + wd * p[i];     /* L2 weight decay (0: plain Adam) */
    adam_apply(i, gi, p, m, v, lr, b1, b2, eps, bc1, bc2);
}

__kernel void adam_step(const int i0, const int n, __global float *p, __global float *g,
                        __global float *m, __global float *v, const float lr, const float b1,
                        const float b2, const float eps, const float bc1, const float bc2,
                        const float wd, const int clear_grad) {
    const int i = i0 + (int)get_global_id(0);
    if (i >= n) return;
    adam_update(i, p, g, m, v, lr, b1, b2, eps, bc1, bc2, wd, clear_grad);
}

/* adam_multi (the GPU shape): Adam over spans of up to four buffers (p_b, g_b, m_b, v_b; the
 * same b1, b2, eps and step count) in one launch, each buffer with its own learning rate lr_b,
 * weight decay wd_b and clear_grad (bit b of clear_mask). Work-group k updates entries
 * groups[k].y + local id below groups[k].z of buffer groups[k].x (the host cuts each span into
 * work-group-sized pieces: clrf/runtime/optim.py AdamSet); unused buffers are null. On PoCL
 * a launch per span (adam_step) is faster (1.4 against 2.2 ms over a hash table's 5 spans, 1.7M
 * entries, measured with a one-buffer kernel of the same loop), so CPUs keep that. */
__kernel void adam_multi(__global const int4 *groups,
                         __global float *p0, __global float *g0, __global float *m0,
                         __global float *v0, __global float *p1, __global float *g1,
                         __global float *m1, __global float *v1, __global float *p2,
                         __global float *g2, __global float *m2, __global float *v2,
                         __global float *p3, __global float *g3, __global float *m3,
                         __global float *v3, const float4 lr, const float4 wd,
                         const int clear_mask, const float b1, const float b2, const float eps,
                         const float bc1, const float bc2) {
    const int4 r = groups[get_group_id(0)];
    const int i = r.y + (int)get_local_id(0);
    if (i >= r.z) return;
    const int b = r.x, clear = (clear_mask >> b) & 1;
    if (b == 0) adam_update(i, p0, g0, m0, v0, lr.s0, b1, b2, eps, bc1, bc2, wd.s0, clear);
    else if (b == 1) adam_update(i, p1, g1, m1, v1, lr.s1, b1, b2, eps, bc1, bc2, wd.s1, clear);
    else if (b == 2) adam_update(i, p2, g2, m2, v2, lr.s2, b1, b2, eps, bc1, bc2, wd.s2, clear);
    else adam_update(i, p3, g3, m3, v3, lr.s3, b1, b2, eps, bc1, bc2, wd.s3, clear);
}
#endif
