/* splat_exposure.cl: a learned colour transform per training image (exposure and white
 * balance of phone captures), applied to the splat model's render before the loss
 * (clrf/splat/exposure.py; float64 twin: clrf/references/reference_exposure.py).
 *
 * Layout: P [V, 12] floats, row v = image v: A (3 x 3, row-major) then b (3). A render rgb
 * [n, 3] (n = H W pixels, channel fastest) becomes
 *     out_p,i = sum_j A_ij rgb_p,j + b_i.
 * The identity (A = I, b = 0) leaves it unchanged; test views are scored under it.
 *
 * exposure_apply     out = A rgb + b, one work-item per pixel.
 * exposure_backward  from g = dL/dout: dL/drgb_p = A^T g_p (one work-item per CHUNK pixels,
 *                    in order), and the work-item's partial sums of dL/dA_ij = sum_p g_p,i
 *                    rgb_p,j and dL/db_i = sum_p g_p,i, 12 floats per work-item in
 *                    partials [items, 12].
 * exposure_adam      one work-item per entry k < 12 of row v: the partials summed in item order
 *                    (deterministic), plus the pull toward the identity, d/dP of
 *                    reg (|A - I|^2 + |b|^2) = 2 reg (P - I); then Adam (cl/optim.cl's update,
 *                    bias-corrected with the row's own step count through bc1, bc2); a
 *                    non-finite gradient leaves P, m, v unchanged.
 *
 * Defines read: none.
 */

#include "adam.h"

#define EXPOSURE_ROW 12

/* entry k of the identity row: A = I (k = 0, 4, 8), b = 0 */
inline float identity_entry(int k) { return (k == 0 || k == 4 || k == 8) ? 1.0f : 0.0f; }

__kernel void exposure_apply(const int n, __global const float *rgb,
                             __global const float *P, const int v, __global float *out) {
    const int p = get_global_id(0);
    if (p >= n) return;
    __global const float *a = P + (size_t)v * EXPOSURE_ROW;
    const float r = rgb[3 * p], g = rgb[3 * p + 1], b = rgb[3 * p + 2];
    out[3 * p] = a[0] * r + a[1] * g + a[2] * b + a[9];
    out[3 * p + 1] = a[3] * r + a[4] * g + a[5] * b + a[10];
    out[3 * p + 2] = a[6] * r + a[7] * g + a[8] * b + a[11];
}

__kernel void exposure_backward(const int n, const int chunk, __global const float *rgb,
                                __global const float *grad_out, __global const float *P,
                                const int v, __global float *grad_rgb,
                                __global float *partials) {
    const int item = get_global_id(0);
    const int p0 = item * chunk;
    if (p0 >= n) return;
    const int p1 = min(n, p0 + chunk);
    __global const float *a = P + (size_t)v * EXPOSURE_ROW;
    float s[EXPOSURE_ROW];
    for (int k = 0; k < EXPOSURE_ROW; ++k) s[k] = 0.0f;
    for (int p = p0; p < p1; ++p) {
        const float r = rgb[3 * p], g = rgb[3 * p + 1], b = rgb[3 * p + 2];
        const float g0 = grad_out[3 * p], g1 = grad_out[3 * p + 1], g2 = grad_out[3 * p + 2];
        grad_rgb[3 * p] = a[0] * g0 + a[3] * g1 + a[6] * g2;
        grad_rgb[3 * p + 1] = a[1] * g0 + a[4] * g1 + a[7] * g2;
        grad_rgb[3 * p + 2] = a[2] * g0 + a[5] * g1 + a[8] * g2;
        s[0] += g0 * r; s[1] += g0 * g; s[2] += g0 * b;
        s[3] += g1 * r; s[4] += g1 * g; s[5] += g1 * b;
        s[6] += g2 * r; s[7] += g2 * g; s[8] += g2 * b;
        s[9] += g0; s[10] += g1; s[11] += g2;
    }
    for (int k = 0; k < EXPOSURE_ROW; ++k) partials[(size_t)item * EXPOSURE_ROW + k] = s[k];
}

__kernel void exposure_adam(const int items, __global const float *partials,
                            __global float *P, __global float *m, __global float *vm,
                            const int v, const float lr, const float reg, const float b1,
                            const float b2, const float eps, const float bc1,
                            const float bc2) {
    const int k = get_global_id(0);
    if (k >= EXPOSURE_ROW) return;
    const size_t i = (size_t)v * EXPOSURE_ROW + k;
    float gk = 0.0f;
    for (int it = 0; it < items; ++it) gk += partials[(size_t)it * EXPOSURE_ROW + k];
    gk += 2.0f * reg * (P[i] - identity_entry(k));
    if (!isfinite(gk)) return;
    adam_apply(i, gk, P, m, vm, lr, b1, b2, eps, bc1, bc2);
}
