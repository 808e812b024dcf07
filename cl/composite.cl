/* composite.cl: volume rendering of per-sample (sigma, rgb) lists (NeRF path), forward and
 * backward, with the same stable math as grid_render.cl.
 *
 * Memory layout: t [n, K] sorted distances along the unit ray direction; sigma [n*K] (>= 0 from
 * the MLP; anything not > 0, NaN included, contributes nothing); rgb [n*K, 3]; outputs per ray.
 *
 * Segments: delta_k = t_{k+1} - t_k, and delta_{K-1} = far - t_{K-1} (the last sample covers
 * the rest of [near, far], so background shows through a transparent ray), clamped at >= 0.
 * Compositing, tau_k = sigma_k delta_k:
 *   alpha_k = alpha_of_tau(tau_k) = 1 - exp(-tau_k),  T_k = exp(-sum_{j<k} tau_j) (Kahan-summed
 *   in log space),
 *   w_k = T_k alpha_k,  rgb = sum_k w_k c_k + T_K bg,  acc = sum_k w_k,  depth = sum_k w_k t_k.
 * No early termination: every sample was evaluated by the MLP already, so all K are used.
 *
 * Backward (dL/drgb = g given, or g = 2 loss_scale (rgb - target) for GRAD_MODE 1):
 *   dL/dc_k = w_k g,
 *   dL/dsigma_k = delta_k (T_{k+1} (g.c_k) - R_k),  R_k = sum_{j>k} w_j (g.c_j) + T_K (g.bg),
 * with R_k = g.rgb - prefix_k (the remaining radiance; prefix Kahan-summed), so the ray is
 * marched twice and nothing is stored per sample. dL/dsigma_k = 0 where sigma_k is not > 0.
 * The per-sample steps are volrend.h's, the same as the grid renderer's.
 *
 * Per-ray state (composite_state, for the colour corrections of ray batches, nerf.exposure:
 * clrf/corrections/exposure.py RayExposure reads it as cl/hash_march.cl's packed_forward
 * writes it): state [n, 8] = (c, acc, depth, logT, 0, 0) with c = sum_k w_k c_k the colour on a
 * black background; and the packing those corrections read of a ray's samples, which here is
 * every sample: offsets [n + 1] = i K and dt [n*K] = delta_k (dT_K/dsigma_k = -delta_k T_K).
 *
 * Defines read: GRAD_MODE.
 */
#include "volrend.h"

#ifndef GRAD_MODE
#define GRAD_MODE 0  /* 0: ray_in holds dL/drgb; 1: ray_in holds target rgb, loss = MSE */
#endif

inline float seg_delta(__global const float *t, const int k, const int K, const float far) {
    return fmax((k + 1 < K ? t[k + 1] : far) - t[k], 0.0f);
}

/* The forward march shared by both kernels; writes weights [K] if w_out is not null. */
inline fwd_t composite_march(const int K, const float far, __global const float *t,
                             __global const float *sigma, __global const float *rgb,
                             __global float *w_out) {
    fwd_t f = {(float3)(0.0f), 0.0f, 0.0f, 0.0f};
    ksum_t logT = {0.0f, 0.0f};
    float T = 1.0f;
    for (int k = 0; k < K; ++k) {
        const float s = sigma[k];
        float w = 0.0f;
        if (s > 0.0f) {
            w = vr_step(&logT, T, s * seg_delta(t, k, K, far), &T);
            f.rgb += w * load3(rgb, k);
            f.acc += w;
            f.depth += w * t[k];
        }
        if (w_out) w_out[k] = w;
    }
    f.logT = logT.s;
    return f;
}

/* One work-item per ray. weights [n, K] is optional (null: not written). */
__kernel void composite_forward(const int n, const int K, const float far,
                                __global const float *t, __global const float *sigma,
                                __global const float *rgb, const float4 bg,
                                __global float *out_rgb, __global float *out_depth,
                                __global float *out_acc, __global float *weights) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t o = (size_t)i * K;
    const fwd_t f = composite_march(K, far, t + o, sigma + o, rgb + 3 * o,
                                     weights ? weights + o : 0);
    const float3 c = f.rgb + exp(f.logT) * bg.xyz;
    out_rgb[3 * i] = c.x;
    out_rgb[3 * i + 1] = c.y;
    out_rgb[3 * i + 2] = c.z;
    out_depth[i] = f.depth;
    out_acc[i] = f.acc;
}

/* One work-item per ray. Writes dsigma [n*K] and drgb [n*K, 3]; ray_out [n] gets the squared
 * error summed over channels (GRAD_MODE 1); weights [n, K] optional as in the forward. */
__kernel void composite_backward(const int n, const int K, const float far,
                                 __global const float *t, __global const float *sigma,
                                 __global const float *rgb, const float4 bg,
                                 __global const float *ray_in, __global float *ray_out,
                                 const float loss_scale, __global float *dsigma,
                                 __global float *drgb, __global float *weights) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t o = (size_t)i * K;
    __global const float *ti = t + o, *si = sigma + o, *ci = rgb + 3 * o;
    const fwd_t f = composite_march(K, far, ti, si, ci, weights ? weights + o : 0);
    const float3 col = f.rgb + exp(f.logT) * bg.xyz;
#if GRAD_MODE == 1
    const float3 diff = col - load3(ray_in, i);
    ray_out[i] = dot(diff, diff);
    const float3 g = 2.0f * loss_scale * diff;
#else
    const float3 g = load3(ray_in, i);
#endif
    const float total = dot(g, col);
    ksum_t logT = {0.0f, 0.0f};
    ksum_t prefix = {0.0f, 0.0f};
    float T = 1.0f;
    for (int k = 0; k < K; ++k) {
        const size_t q = o + k;
        const float s = si[k];
        if (!(s > 0.0f)) {
            dsigma[q] = 0.0f;
            drgb[3 * q] = drgb[3 * q + 1] = drgb[3 * q + 2] = 0.0f;
            continue;
        }
        const float delta = seg_delta(ti, k, K, far);
        const float w = vr_step(&logT, T, s * delta, &T);
        dsigma[q] = vr_dsigma(&prefix, total, w, T, dot(g, load3(ci, k)), delta);
        drgb[3 * q] = w * g.x;
        drgb[3 * q + 1] = w * g.y;
        drgb[3 * q + 2] = w * g.z;
    }
}

/* One work-item per ray: state [n, 8], offsets [n + 1] (int) and dt [n*K] (header). */
__kernel void composite_state(const int n, const int K, const float far,
                              __global const float *t, __global const float *sigma,
                              __global const float *rgb, __global float *state,
                              __global int *offsets, __global float *dt) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t o = (size_t)i * K;
    const fwd_t f = composite_march(K, far, t + o, sigma + o, rgb + 3 * o, 0);
    __global float *s = state + 8 * (size_t)i;
    s[0] = f.rgb.x; s[1] = f.rgb.y; s[2] = f.rgb.z;
    s[3] = f.acc; s[4] = f.depth; s[5] = f.logT; s[6] = 0.0f; s[7] = 0.0f;
    offsets[i] = i * K;
    if (i == n - 1) offsets[n] = n * K;
    for (int k = 0; k < K; ++k) dt[o + k] = seg_delta(t + o, k, K, far);
}
