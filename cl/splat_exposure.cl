/* splat_exposure.cl: a learned colour transform per training image (exposure and white
 * balance of phone captures), applied to the splat model's render before the loss
 * (clrf/splat/exposure.py), and to the hash model's rays (clrf/hash/exposure.py); float64
 * twin: clrf/references/reference_exposure.py.
 *
 * Layout: P [V, 12] floats, row v = image v: A (3 x 3, row-major) then b (3). A pixel of
 * premultiplied colour c (the sum of the splats' weighted colours), opacity alpha = 1 - T and
 * background bg is shown as
 *     out = A (c + T bg) + b          a capture without alpha: the background stands for
 *                                     scene light, which the exposure changes too;
 *     out = A c + alpha b + T bg      a masked capture (RGBA, composited on bg when loaded):
 *                                     its background is not the camera's and stays bg.
 * For the second the splat model renders on bg' = A^-1 (bg - b) (clrf/splat/exposure.py), so
 * that its render rgb' = c + T bg' gives out = A rgb' + b in both cases, and the rasteriser's
 * backward from dL/drgb' = A^T dL/dout is exact, the background's share included (the first
 * renders on bg' = bg). The identity (A = I, b = 0, bg' = bg) leaves the render unchanged;
 * test views are scored under it.
 *
 * With clip set, out is clamped to [0, 1] as a camera clips a pixel it over- or under-exposes
 * (splat.exposure_clip): an image brightened past white holds no more of the scene there, and
 * its clipped channels pass no gradient (to the scene or the row) instead of pulling the
 * transform down to keep the unclipped value near 1. With clip = 2 (splat.exposure_clip_inward)
 * a clipped channel still passes a gradient that would bring it back inside [0, 1] (a render
 * past white where the capture was not white is pulled down; one that the capture clipped
 * too, target 1, passes nothing): a surrogate, not the clamp's derivative.
 *
 * exposure_apply     out = A rgb' + b (clamped with clip), one work-item per pixel.
 * exposure_backward  from g = dL/dout (a channel's g taken as 0 with clip where A rgb' + b
 *                    lies outside [0, 1], exposure_clip_grad): dL/drgb'_p = A^T g_p (one
 *                    work-item per CHUNK pixels, in order), and the work-item's partial sums
 *                    of dL/dA_ij = sum_p g_p,i x_p,j and dL/db_i = sum_p g_p,i y_p, 12 floats
 *                    per work-item in partials [items, 12]: x = rgb', y = 1 without alpha
 *                    (masked = 0); x = rgb' - T bg' = c, y = 1 - T for a masked capture.
 * exposure_adam      one work-item per entry k < 12 of row v: the partials summed in item order
 *                    (deterministic), plus the pull toward the identity, d/dP of
 *                    reg (|A - I|^2 + |b|^2) = 2 reg (P - I); then Adam (cl/optim.cl's update,
 *                    bias-corrected with the row's own step count through bc1, bc2); a
 *                    non-finite gradient leaves P, m, v unchanged. matrix (exposure_trained)
 *                    1 or 2: the entries it does not train keep their value (A's
 *                    off-diagonal entries, with 2 b too, at 0: a gain and an offset per
 *                    channel, or a gain only).
 *
 * Ray batches (the hash model: a batch holds rays of many images; ray i belongs to row
 * index[i] / pixels, index being its place in the concatenated training images). Each ray's
 * composite state [n, 8] (cl/hash_march.cl packed_forward: premultiplied colour c, then
 * opacity a; T = 1 - a) on the step's background bg gives out as above (masked or not), and:
 * exposure_rays      the residual r = out - target [n, 3], sq [n] = |r|^2, the target
 *                    eff = c - A^T r for the marcher's backward run on a black background
 *                    (its 2 s (c - eff) is then dL/dc = 2 s A^T r: the colour's gradient
 *                    through the transform), and bgt [n] = T r.(dout/dT): the background's
 *                    share, T r.(A bg), or T r.(bg - b) masked. With clip (hash.exposure_clip,
 *                    ...) the loss sees out clamped to [0, 1] as above: sq = |clamp(out) -
 *                    target|^2, and r (hence eff, bgt and the row's gradient) is 0 in a
 *                    channel where out lies outside [0, 1];
 * exposure_rays_bg   adds that share to dL/dsigma of each live sample j of ray i,
 *                    -2 s dt_j bgt_i (dT/dsigma_j = -dt_j T), which the black background left
 *                    out;
 * exposure_rays_grad one work-group (EXPOSURE_LS items) per row v, in a fixed order: dL/dP_v of
 *                    L = s sum_i |r_i|^2 (dL/dA = 2 s sum r x^T, dL/db = 2 s sum y r over the
 *                    rays of row v; x = c + T bg, y = 1, or masked x = c, y = a), plus the pull
 *                    2 reg (P_v - I) weighted by the row's share of the batch (its rays / n), so
 *                    that a row's pull against its data is that of the splat model's
 *                    whole-image step; grad [V, 12] (written, or added to with
 *                    accumulate: a renderer whose loss has several passes over the same rays,
 *                    NeRF's coarse and fine, each passes its own scale and reg = 0 but the
 *                    last). matrix 1 or 2 (hash.exposure_matrix): the entries it does not train
 *                    get 0, so that Adam leaves them at 0.
 *
 * exposure_rays_behind  for a masked capture on a renderer that composites the background
 *                    itself (the grid): each ray's background bg'_i = A_v^-1 (bg - b_v) of its
 *                    row v (the adjugate over the determinant), so that its whole pixel
 *                    rgb' = c + T bg' gives A rgb' + b = A c + (1 - T) b + T bg, the masked out
 *                    above, and the transform of whole pixels (state (rgb', opacity 1)) is the
 *                    masked one exactly; a row with a non-finite entry, whose A is singular
 *                    (|det| <= 1e-12) or whose result is not finite gives bg (never near the identity rows are pulled
 *                    to; clrf/corrections/exposure.py Exposure.background does the same).
 *
 * Defines read: none.
 */

#include "common.h"
#include "adam.h"

#define EXPOSURE_ROW 12

/* entry k of the identity row: A = I (k = 0, 4, 8), b = 0 */
inline float identity_entry(int k) { return (k == 0 || k == 4 || k == 8) ? 1.0f : 0.0f; }

/* whether entry k of a row trains, by matrix (splat.exposure_matrix): 0 "full" every one,
 * 1 "diagonal" A's diagonal and b, 2 "gain" A's diagonal only */
inline bool exposure_trained(int k, int matrix) {
    return matrix == 0 || (k < 9 ? k % 4 == 0 : matrix == 1);
}

/* A rgb + b of one pixel (row a) */
inline float3 exposure_affine(__global const float *a, const float r, const float g,
                              const float b) {
    return (float3)(a[0] * r + a[1] * g + a[2] * b + a[9], a[3] * r + a[4] * g + a[5] * b + a[10],
                    a[6] * r + a[7] * g + a[8] * b + a[11]);
}

/* dL/dout of one channel of value o (before the clamp) with clip: 0 outside [0, 1] (clip 1),
 * or there unless it points back inside (clip 2: g > 0 above 1, g < 0 below 0) */
inline float exposure_clip_grad(const float o, const float g, const int clip) {
    const int outside = o < 0.0f || o > 1.0f;
    const int inward = (o > 1.0f && g > 0.0f) || (o < 0.0f && g < 0.0f);
    return (outside && !(clip == 2 && inward)) ? 0.0f : g;
}

__kernel void exposure_apply(const int n, __global const float *rgb,
                             __global const float *P, const int v, const int clip,
                             __global float *out) {
    const int p = get_global_id(0);
    if (p >= n) return;
    __global const float *a = P + (size_t)v * EXPOSURE_ROW;
    float3 o = exposure_affine(a, rgb[3 * p], rgb[3 * p + 1], rgb[3 * p + 2]);
    if (clip) o = clamp(o, 0.0f, 1.0f);
    out[3 * p] = o.x;
    out[3 * p + 1] = o.y;
    out[3 * p + 2] = o.z;
}

__kernel void exposure_backward(const int n, const int chunk, __global const float *rgb,
                                const int masked, __global const float *T, const float4 bg,
                                __global const float *grad_out, __global const float *P,
                                const int v, const int clip, __global float *grad_rgb,
                                __global float *partials) {
    const int item = get_global_id(0);
    const int p0 = item * chunk;
    if (p0 >= n) return;
    const int p1 = min(n, p0 + chunk);
    __global const float *a = P + (size_t)v * EXPOSURE_ROW;
    float s[EXPOSURE_ROW];
    for (int k = 0; k < EXPOSURE_ROW; ++k) s[k] = 0.0f;
    for (int p = p0; p < p1; ++p) {
        const float t = masked ? T[p] : 0.0f;
        const float r = rgb[3 * p] - t * bg.x, g = rgb[3 * p + 1] - t * bg.y;
        const float b = rgb[3 * p + 2] - t * bg.z, op = 1.0f - t;
        float g0 = grad_out[3 * p], g1 = grad_out[3 * p + 1], g2 = grad_out[3 * p + 2];
        if (clip) {   /* a clipped channel passes nothing, or only inward (clip 2) */
            const float3 o = exposure_affine(a, rgb[3 * p], rgb[3 * p + 1], rgb[3 * p + 2]);
            g0 = exposure_clip_grad(o.x, g0, clip);
            g1 = exposure_clip_grad(o.y, g1, clip);
            g2 = exposure_clip_grad(o.z, g2, clip);
        }
        grad_rgb[3 * p] = a[0] * g0 + a[3] * g1 + a[6] * g2;
        grad_rgb[3 * p + 1] = a[1] * g0 + a[4] * g1 + a[7] * g2;
        grad_rgb[3 * p + 2] = a[2] * g0 + a[5] * g1 + a[8] * g2;
        s[0] += g0 * r; s[1] += g0 * g; s[2] += g0 * b;
        s[3] += g1 * r; s[4] += g1 * g; s[5] += g1 * b;
        s[6] += g2 * r; s[7] += g2 * g; s[8] += g2 * b;
        s[9] += g0 * op; s[10] += g1 * op; s[11] += g2 * op;
    }
    for (int k = 0; k < EXPOSURE_ROW; ++k) partials[(size_t)item * EXPOSURE_ROW + k] = s[k];
}

__kernel void exposure_adam(const int items, __global const float *partials,
                            __global float *P, __global float *m, __global float *vm,
                            const int v, const float lr, const float reg, const float b1,
                            const float b2, const float eps, const float bc1,
                            const float bc2, const int matrix) {
    const int k = get_global_id(0);
    if (k >= EXPOSURE_ROW || !exposure_trained(k, matrix)) return;
    const size_t i = (size_t)v * EXPOSURE_ROW + k;
    float gk = 0.0f;
    for (int it = 0; it < items; ++it) gk += partials[(size_t)it * EXPOSURE_ROW + k];
    gk += 2.0f * reg * (P[i] - identity_entry(k));
    if (!isfinite(gk)) return;
    adam_apply(i, gk, P, m, vm, lr, b1, b2, eps, bc1, bc2);
}

#define EXPOSURE_LS 64

__kernel void exposure_rays(const int n, const int pixels, __global const int *index,
                            __global const float *state, const int masked, const int clip,
                            const float4 bg,
                            __global const float *target, __global const float *P,
                            __global float *resid, __global float *eff, __global float *sq,
                            __global float *bgt) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const float *s = state + (size_t)i * 8;
    const float t = 1.0f - s[3];
    __global const float *a = P + (size_t)(index[i] / pixels) * EXPOSURE_ROW;
    /* x, y: what A and b multiply; d = dout/dT */
    const float3 c = (float3)(s[0], s[1], s[2]);
    const float3 Ab = (float3)(a[0] * bg.x + a[1] * bg.y + a[2] * bg.z,
                               a[3] * bg.x + a[4] * bg.y + a[5] * bg.z,
                               a[6] * bg.x + a[7] * bg.y + a[8] * bg.z);
    const float3 b = (float3)(a[9], a[10], a[11]);
    const float3 x = masked ? c : c + t * bg.xyz;
    const float y = masked ? s[3] : 1.0f;
    const float3 d = masked ? bg.xyz - b : Ab;
    const float3 o = (float3)(a[0] * x.x + a[1] * x.y + a[2] * x.z,
                              a[3] * x.x + a[4] * x.y + a[5] * x.z,
                              a[6] * x.x + a[7] * x.y + a[8] * x.z)
                     + y * b + (masked ? t * bg.xyz : (float3)(0.0f));
    const float3 tg = load3(target, i);
    /* with clip: the loss sees clamp(o, 0, 1), and a clipped channel passes no gradient */
    const float3 es = (clip ? clamp(o, 0.0f, 1.0f) : o) - tg;
    const int3 out_of = isless(o, (float3)(0.0f)) | isgreater(o, (float3)(1.0f));
    const float3 e = clip ? select(o - tg, (float3)(0.0f), out_of) : o - tg;
    resid[3 * i] = e.x; resid[3 * i + 1] = e.y; resid[3 * i + 2] = e.z;
    eff[3 * i] = c.x - (a[0] * e.x + a[3] * e.y + a[6] * e.z);
    eff[3 * i + 1] = c.y - (a[1] * e.x + a[4] * e.y + a[7] * e.z);
    eff[3 * i + 2] = c.z - (a[2] * e.x + a[5] * e.y + a[8] * e.z);
    sq[i] = dot(es, es);
    bgt[i] = t * dot(e, d);
}

__kernel void exposure_rays_bg(const int n, __global const int *offsets,
                               __global const float *dt, __global const float *sigma,
                               __global const float *bgt, const float scale,
                               __global float *dsigma) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float k = 2.0f * scale * bgt[i];
    for (int j = offsets[i]; j < offsets[i + 1]; ++j)
        if (sigma[j] > 0.0f) dsigma[j] -= k * dt[j];
}

__kernel __attribute__((reqd_work_group_size(EXPOSURE_LS, 1, 1)))
void exposure_rays_grad(const int n, const int pixels, __global const int *index,
                        __global const float *state, const int masked, const float4 bg,
                        __global const float *resid,
                        __global const float *P, const float scale, const float reg,
                        const int matrix, const int accumulate, __global float *grad) {
    __local float part[EXPOSURE_LS * (EXPOSURE_ROW + 1)];
    const int v = get_group_id(0), l = get_local_id(0);
    float s[EXPOSURE_ROW + 1];
    for (int k = 0; k <= EXPOSURE_ROW; ++k) s[k] = 0.0f;
    for (int i = l; i < n; i += EXPOSURE_LS) {
        if (index[i] / pixels != v) continue;
        __global const float *st = state + (size_t)i * 8;
        const float t = masked ? 0.0f : 1.0f - st[3], op = masked ? st[3] : 1.0f;
        const float x0 = st[0] + t * bg.x, x1 = st[1] + t * bg.y, x2 = st[2] + t * bg.z;
        const float e0 = resid[3 * i], e1 = resid[3 * i + 1], e2 = resid[3 * i + 2];
        s[0] += e0 * x0; s[1] += e0 * x1; s[2] += e0 * x2;
        s[3] += e1 * x0; s[4] += e1 * x1; s[5] += e1 * x2;
        s[6] += e2 * x0; s[7] += e2 * x1; s[8] += e2 * x2;
        s[9] += e0 * op; s[10] += e1 * op; s[11] += e2 * op;
        s[12] += 1.0f;
    }
    for (int k = 0; k <= EXPOSURE_ROW; ++k) part[l * (EXPOSURE_ROW + 1) + k] = s[k];
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int h = EXPOSURE_LS / 2; h > 0; h >>= 1) {      /* a fixed tree: deterministic */
        if (l < h)
            for (int k = 0; k <= EXPOSURE_ROW; ++k)
                part[l * (EXPOSURE_ROW + 1) + k] += part[(l + h) * (EXPOSURE_ROW + 1) + k];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (l < EXPOSURE_ROW) {
        const float share = part[EXPOSURE_ROW] / (float)max(n, 1);
        const size_t j = (size_t)v * EXPOSURE_ROW + l;
        grad[j] = !exposure_trained(l, matrix) ? 0.0f
                  : (accumulate ? grad[j] : 0.0f) + 2.0f * scale * part[l]
                    + 2.0f * reg * share * (P[j] - identity_entry(l));
    }
}

/* out [n, 3]: A_v^-1 (bg - b_v) of each ray's row v (see the header). */
__kernel void exposure_rays_behind(const int n, const int pixels, __global const int *index,
                                   const float4 bg, __global const float *P,
                                   __global float *out) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const float *a = P + (size_t)(index[i] / pixels) * EXPOSURE_ROW;
    const float3 r = bg.xyz - (float3)(a[9], a[10], a[11]);
    /* the cofactors of A's first row, then A^-1 = adj(A) / det, adj(A)_ij = C_ji */
    const float c00 = a[4] * a[8] - a[5] * a[7], c01 = a[5] * a[6] - a[3] * a[8],
                c02 = a[3] * a[7] - a[4] * a[6];
    const float det = a[0] * c00 + a[1] * c01 + a[2] * c02;
    const float3 x = (float3)(c00 * r.x + (a[2] * a[7] - a[1] * a[8]) * r.y
                                  + (a[1] * a[5] - a[2] * a[4]) * r.z,
                              c01 * r.x + (a[0] * a[8] - a[2] * a[6]) * r.y
                                  + (a[2] * a[3] - a[0] * a[5]) * r.z,
                              c02 * r.x + (a[1] * a[6] - a[0] * a[7]) * r.y
                                  + (a[0] * a[4] - a[1] * a[3]) * r.z) / det;
    const int ok = isfinite(det) && fabs(det) > 1e-12f && isfinite(x.x) && isfinite(x.y) && isfinite(x.z);
    vstore3(ok ? x : bg.xyz, i, out);
}
