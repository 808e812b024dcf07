/* splat_train.cl: the Gaussian-splatting model's per-step helpers (clrf/splat/model.py), one
 * work-item per entry.
 *
 * splat_adam_sh: Adam (Kingma & Ba, bias-corrected) over the SH coefficients sh [n, B, 3]
 *   (flat index i = (g B + b) 3 + c) with two learning rates, lr_dc for basis 0 and lr_rest
 *   for the others, and only the active bands b < active_basis updated: entries of inactive
 *   bands keep their value and moments (their gradient is ignored). Otherwise the update of
 *   cl/optim.cl adam_step with no weight decay: m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2,
 *   p -= lr (m / bc1) / (sqrt(v / bc2) + eps); a non-finite gradient leaves p, m, v unchanged.
 *
 * splat_densify_stats: the default strategy's statistics of one step (clrf/splat/strategies/
 *   default.py; float64 twin: clrf/references/reference_strategy.py densify_stats), for
 *   Gaussians seen in it (radius > 0): accum += |(gx sx, gy sy)| (the screen-space gradient of
 *   the mean, scaled from pixels to NDC units by sx = W / 2, sy = H / 2; a non-finite norm adds
 *   nothing), count += 1 (likewise), max_radius = max(max_radius, radius).
 *
 * splat_grad_sum: total = (total + g) scale, entry by entry in float32: a batch's gradients
 *   summed view by view and the last sum scaled to the mean (clrf/splat/distributed.py; the
 *   same two roundings as numpy's float32 (total + g) * scale).
 */

#include "adam.h"
#include "splat.h"

__kernel void splat_adam_sh(const int n, __global float *p, __global const float *g,
                            __global float *m, __global float *v, const float lr_dc,
                            const float lr_rest, const float b1, const float b2, const float eps,
                            const float bc1, const float bc2, const int n_basis,
                            const int active_basis) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int b = (i / 3) % n_basis;
    if (b >= active_basis) return;
    const float gi = g[i];
    if (!isfinite(gi)) return;
    adam_apply(i, gi, p, m, v, b == 0 ? lr_dc : lr_rest, b1, b2, eps, bc1, bc2);
}

__kernel void splat_densify_stats(const int n, __global const float *grad_xy,
                                  __global const float *radius, const float sx, const float sy,
                                  __global float *accum, __global float *count,
                                  __global float *max_radius) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float r = radius[i];
    if (!(r > 0.0f)) return;
    const float gx = grad_xy[2 * i] * sx, gy = grad_xy[2 * i + 1] * sy;
    const float norm = sqrt(gx * gx + gy * gy);
    if (isfinite(norm)) {
        accum[i] += norm;
        count[i] += 1.0f;
    }
    max_radius[i] = fmax(max_radius[i], r);
}

/* ---- the MCMC strategy (clrf/splat/strategies/mcmc.py; Kheradmand et al. 2024, 3DGS as MCMC)
 *
 * splat_mcmc_reg: the regularisers' gradients added to the step's: opacity_reg mean(o) and
 *   scale_reg mean(s) (o = sigmoid(opacity logit), s = exp(log scale), means over the n
 *   opacities and the 3 n scales): g_opacity += ko o (1 - o), g_log_scales += ks s, with
 *   ko = opacity_reg / n, ks = scale_reg / (3 n).
 *
 * splat_mcmc_noise: after the Adam step, each mean moves by k Sigma z, Sigma = R S^2 R^T its
 *   covariance (normalised quaternion, S = diag(exp(log scales))), z three standard normals
 *   and k = scale / (1 + exp(100 (o - 0.005))): transparent Gaussians wander, opaque ones stay
 *   (scale: the noise rate times the means' learning rate). z comes from a counter-based hash
 *   of (seed, step, 4 i + c) and Box-Muller, so the float64 twin (clrf/references/
 *   reference_strategy.py) draws the same numbers.
 */

uint mcmc_hash(uint x) {   /* a 32-bit integer mix (xorshift-multiply, "lowbias32") */
    x ^= x >> 16;
    x *= 0x7feb352dU;
    x ^= x >> 15;
    x *= 0x846ca68bU;
    x ^= x >> 16;
    return x;
}

float mcmc_uniform(uint key, uint c) {   /* in (0, 1): 24 bits, centred in their interval */
    return ((float)(mcmc_hash(key ^ c) >> 8) + 0.5f) * (1.0f / 16777216.0f);
}

__kernel void splat_mcmc_reg(const int n, __global const float *opacity_logits,
                             __global const float *log_scales, __global float *g_opacity,
                             __global float *g_log_scales, const float ko, const float ks) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float o = 1.0f / (1.0f + exp(-opacity_logits[i]));
    g_opacity[i] += ko * o * (1.0f - o);
    for (int c = 0; c < 3; c++) g_log_scales[3 * i + c] += ks * exp(log_scales[3 * i + c]);
}

__kernel void splat_mcmc_noise(const int n, __global float *means,
                               __global const float *log_scales, __global const float *quats,
                               __global const float *opacity_logits, const float scale,
                               const uint seed, const uint step) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float o = 1.0f / (1.0f + exp(-opacity_logits[i]));
    const float k = scale / (1.0f + exp(100.0f * (o - 0.005f)));
    if (!(k > 0.0f)) return;
    const uint key = mcmc_hash(mcmc_hash(seed) ^ mcmc_hash(step + 0x9e3779b9U) ^
                               mcmc_hash((uint)i * 0x85ebca6bU));
    const float u1 = mcmc_uniform(key, 0x1U), u2 = mcmc_uniform(key, 0x2U);
    const float u3 = mcmc_uniform(key, 0x3U), u4 = mcmc_uniform(key, 0x4U);
    const float r1 = sqrt(-2.0f * log(u1)), r2 = sqrt(-2.0f * log(u3));
    const float3 z = (float3)(r1 * cospi(2.0f * u2), r1 * sinpi(2.0f * u2),
                              r2 * cospi(2.0f * u4));
    float4 q = vload4(i, quats);
    q *= rsqrt(fmax(dot(q, q), 1e-24f));   /* a zero quaternion: R = I */
    float R[9];
    splat_quat_rot(q, R);
    const float3 s = exp(vload3(i, log_scales));
    /* Sigma z = R (S^2 (R^T z)) */
    const float3 a = (float3)(R[0] * z.x + R[3] * z.y + R[6] * z.z,
                              R[1] * z.x + R[4] * z.y + R[7] * z.z,
                              R[2] * z.x + R[5] * z.y + R[8] * z.z) * s * s;
    const float3 d = (float3)(R[0] * a.x + R[1] * a.y + R[2] * a.z,
                              R[3] * a.x + R[4] * a.y + R[5] * a.z,
                              R[6] * a.x + R[7] * a.y + R[8] * a.z);
    if (all(isfinite(d))) vstore3(vload3(i, means) + k * d, i, means);
}

__kernel void splat_grad_sum(const int n, __global float *total, __global const float *g,
                             const float scale) {
    const int i = get_global_id(0);
    if (i >= n) return;
    total[i] = (total[i] + g[i]) * scale;
}
