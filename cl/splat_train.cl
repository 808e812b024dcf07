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
 * splat_densify_stats: the densification statistics of one step, for Gaussians seen in it
 *   (radius > 0): accum += |(gx sx, gy sy)| (the screen-space gradient of the mean, scaled from
 *   pixels to NDC units by sx = W / 2, sy = H / 2), count += 1, max_radius = max(max_radius,
 *   radius).
 */

#include "adam.h"

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
