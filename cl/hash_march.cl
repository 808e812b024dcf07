/* hash_march.cl: the hash model's samples (stratified, kept only in occupied cells, packed per
 * ray) and their compositing, forward (resumable, with early ray termination) and backward.
 *
 * Samples. Ray i (origin o, direction d, unit direction dh = d / |d|) has S bins over
 * [near, far]; bin k holds the sample at s_k = (k + u_k) / S, u_k = uniform01(key, i S + k) with
 * jitter, else 1/2 (cl/sample.cl's stratified rule):
 *   HASH_CONTRACT 0 (a bounded box): equal bins, t_k = near + (far - near) s_k,
 *                   dt_k = (far - near) / S;
 *   HASH_CONTRACT 1 (unbounded scenes): bins equal in log t, t_k = near exp(s_k ln(far/near)),
 *                   dt_k = the bin's length near r^(k/S) (r^(1/S) - 1), r = far / near, so a
 *                   sample's spacing grows with its distance as the contracted space shrinks;
 * at x_k = o + t_k dh. The point the encoding and the occupancy grid see is x_k itself
 * (HASH_CONTRACT 0) or its scene contraction (HASH_CONTRACT 1, after mip-NeRF 360, with the
 * max-norm so that the contracted space is a cube): with y = (x_k - centre) / half the inner
 * box's normalised coordinate and n = max_i |y_i|,
 *   contract(y) = y if n <= 1, else (2 - 1/n) y / n,   which maps all of space into [-2, 2]^3.
 * The sample is LIVE when that point lies inside the occupancy box in an occupied cell
 * (hash_occ.h), and then stands for its whole bin: its segment length is dt_k whatever its
 * neighbours are, so dropping the empty bins changes nothing else.
 * A window k0 <= k < k1 of bins is marched at a time (the render's early termination; training
 * takes all S at once), only for rays with alive[i] != 0 (null: every ray).
 *
 * Packed layout: march_live marks each (ray, bin) live or not, march_count sums each ray's
 * marks, the host turns the counts into offsets [n + 1] (exclusive prefix sum), march_compact
 * writes ray i's live samples in bin order at rows offsets[i] .. offsets[i+1]-1 of t [M],
 * dt [M], xyz [M, 3] (the encoding's point: contracted under HASH_CONTRACT), vdir [M, 3].
 * A bounded packing (buffers of a fixed capacity C, sizes kept on the device) caps the offsets
 * at C: a ray that crosses C keeps its first C - offsets[i] live samples, later rays none.
 *
 * Compositing over a ray's live samples (volrend.h), tau_k = sigma_k dt_k (sigma not > 0, NaN
 * included, counts as 0):
 *   w_k = T_k alpha(tau_k), T_k = exp(-sum_{j<k} tau_j) (Kahan-summed log),
 *   rgb = sum w_k c_k + T_end bg,  acc = sum w_k,  depth = sum w_k t_k.
 * packed_forward continues a per-ray state [n, 8] = (rgb, acc, depth, logT, logT compensation,
 * unused) across windows and clears alive[i] once T < HASH_T_STOP (the rest of the ray can
 * change rgb by less than T_STOP); the host adds T_end bg at the end.
 * packed_backward (training: one window, no termination): L = loss_scale sum |rgb - target|^2,
 *   g = 2 loss_scale (rgb - target), dL/dc_k = w_k g,
 *   dL/dsigma_k = dt_k (T_{k+1} (g.c_k) - R_k),  R_k = g.rgb - sum_{j<=k} w_j (g.c_j),
 * and sq_err [n] = |rgb - target|^2.
 * Training-time termination (the step differentiates only what is in front of an opaque
 * point): packed_keep counts each ray's leading samples whose transmittance in front,
 * T_k = exp(-sum_{j<k} tau_j), is >= t_stop (the first sample always); packed_gather copies
 * those prefixes (rows of `width` floats) into the packing of the kept counts. A dropped
 * sample's dL/dsigma and dL/dc are bounded by T_k |g| (|c| + 1) dt resp. T_k |g|, so below
 * t_stop times the largest kept one's scale.
 *
 * Camera gradient (HASH_POSE_GRAD 1, pose refinement; the kernels above are unchanged):
 * packed_ray_grad gives each ray's dL/d(origin, direction) [n, 6] from its samples' dL/dp
 * (p the encoding's point; cl/hash.cl hash_dx) and dL/dY (the direction's SH basis; the MLP's
 * input gradient, or none). The sample x_k = o + t_k dh (t_k does not depend on the ray), so
 *   dL/dx_k = dL/dp_k (HASH_CONTRACT 0), or J_c(x_k)^T dL/dp_k with the contraction's Jacobian
 *     (n > 1, m the axis of the largest |y_a|, s(n) = (2 - 1/n) / n, s' = 2 (1 - n) / n^3):
 *     dL/dy = s dL/dp + s' (y . dL/dp) sign(y_m) e_m,  dL/dx = dL/dy / half;
 *   dL/do = sum_k dL/dx_k,   dL/ddh = sum_k (t_k dL/dx_k + sum_b dL/dY_b,k dY_b/dv),
 *   dL/dd = (dL/ddh - dh (dh . dL/ddh)) / |d|   (dh = d / |d|; the SH reads v / |v| at v = dh,
 *     whose Jacobian (I - dh dh^T) the final projection already contains).
 *
 * Defines read: HASH_T_STOP, HASH_CONTRACT, HASH_POSE_GRAD. Twin:
 * clrf/references/reference_hash.py (march_samples, packed_forward, packed_backward,
 * packed_keep, ray_grad).
 */
#include "hash_occ.h"
#include "volrend.h"

#ifndef HASH_CONTRACT
#define HASH_CONTRACT 0
#endif

#ifndef HASH_POSE_GRAD
#define HASH_POSE_GRAD 0   /* 1: also packed_ray_grad (pose refinement) */
#endif

#ifndef HASH_T_STOP
#define HASH_T_STOP 1e-4f   /* render: a ray stops once its transmittance is below this */
#endif

CLRF_INLINE float3 unit_dir(__global const float *dirs, const int i) {
    float3 d = load3(dirs, i);
    const float mx = fmax(fabs(d.x), fmax(fabs(d.y), fabs(d.z)));
    d = mx > 0.0f ? d / mx : (float3)(0.0f);      /* scale first: |d|^2 may under/overflow */
    return d * safe_div(1.0f, length(d));
}

/* Sample t of bin k of ray i; *dt: the bin's length. */
CLRF_INLINE float bin_t(const int i, const int k, const int S, const float near, const float far,
                        const int jitter, const uint key, float *dt) {
    const float u = jitter ? uniform01(key, (uint)(i * S + k)) : 0.5f;
    const float s = ((float)k + u) / (float)S;
#if HASH_CONTRACT
    const float lr = log(far / near);
    *dt = near * exp(lr * ((float)k / (float)S)) * expm1(lr / (float)S);
    return near * exp(lr * s);
#else
    *dt = (far - near) / (float)S;
    return near + (far - near) * s;
#endif
}

/* The point the encoding sees: x, or its contraction about the inner box (centre c, 1/half ih). */
CLRF_INLINE float3 enc_point(const float3 x, const float4 c, const float4 ih) {
#if HASH_CONTRACT
    const float3 y = (x - c.xyz) * ih.xyz;
    const float n = fmax(fabs(y.x), fmax(fabs(y.y), fabs(y.z)));
    return n <= 1.0f ? y : y * ((2.0f - 1.0f / n) / n);
#else
    return x;
#endif
}

/* contract_points: xyz [m, 3] (world) -> the encoding's points (clrf export, the viewer). */
__kernel void contract_points(const int m, const float4 c, const float4 ih,
                              __global const float *xyz, __global float *out) {
    const int j = get_global_id(0);
    if (j >= m) return;
    const float3 p = enc_point(load3(xyz, j), c, ih);
    out[3 * j] = p.x; out[3 * j + 1] = p.y; out[3 * j + 2] = p.z;
}

/* live [n, W] (W = k1 - k0): 1 where bin k0 + b of ray i is live, else 0 (and for rays not
 * alive). A 2-D range: ray i = get_global_id(1), 16 bins b = 16 get_global_id(0) + 0..15 per
 * work-item in float16/int16 lanes (the same arithmetic as bin_t, enc_point and occ_cell, lane
 * by lane). PoCL runs a kernel with a per-item loop scalar; these explicit vectors cut the
 * march from 39 to 8 ms a step on lego_400 (AVX-512). */
__kernel void march_live(const int n, const int S, const int k0, const int k1, const float near,
                         const float far, const int jitter, const uint key,
                         __global const float *origins, __global const float *dirs,
                         const float4 lo, const float4 inv_ext, const int R,
                         const float4 centre, const float4 inv_half,
                         __global const uchar *occ, __global const uchar *alive,
                         __global uchar *live) {
    const int b0 = 16 * (int)get_global_id(0), i = get_global_id(1), W = k1 - k0;
    if (b0 >= W || i >= n) return;
    __global uchar *row = live + (size_t)i * W + b0;
    const int nb = min(16, W - b0);
    if (alive && !alive[i]) {
        for (int l = 0; l < nb; ++l) row[l] = 0;
        return;
    }
    const int16 k = (int16)(k0 + b0) + (int16)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14,
                                               15);
    const float16 u = jitter ? uniform01x16(key, as_uint16((int16)(i * S) + k))
                             : (float16)(0.5f);
    const float16 s = (convert_float16(k) + u) / (float)S;
#if HASH_CONTRACT
    const float16 t = near * exp(log(far / near) * s);
#else
    const float16 t = near + (far - near) * s;
#endif
    const float3 o = load3(origins, i), dh = unit_dir(dirs, i);
    float16 x = o.x + t * dh.x, y = o.y + t * dh.y, z = o.z + t * dh.z;
#if HASH_CONTRACT
    x = (x - centre.x) * inv_half.x;
    y = (y - centre.y) * inv_half.y;
    z = (z - centre.z) * inv_half.z;
    const float16 nrm = fmax(fabs(x), fmax(fabs(y), fabs(z)));
    const float16 sc = select((2.0f - 1.0f / nrm) / nrm, (float16)(1.0f), nrm <= 1.0f);
    x *= sc;
    y *= sc;
    z *= sc;
#endif
    const float16 ux = (x - lo.x) * inv_ext.x, uy = (y - lo.y) * inv_ext.y,
                  uz = (z - lo.z) * inv_ext.z;
    const int16 in = ux >= 0.0f && uy >= 0.0f && uz >= 0.0f && ux <= 1.0f && uy <= 1.0f
                     && uz <= 1.0f;
    /* min(int16, (int16)...): Oclgrind 21.10 returned garbage lanes for min(int16, int) */
    const int16 cx = min(convert_int16(ux * (float)R), (int16)(R - 1)),
                cy = min(convert_int16(uy * (float)R), (int16)(R - 1)),
                cz = min(convert_int16(uz * (float)R), (int16)(R - 1));
    const int16 cell = select((int16)(0), cx + R * (cy + R * cz), in);
#define MARCH_LANE(l, s) if (l < nb) row[l] = in.s && occ[cell.s];
    MARCH_LANE(0, s0) MARCH_LANE(1, s1) MARCH_LANE(2, s2) MARCH_LANE(3, s3)
    MARCH_LANE(4, s4) MARCH_LANE(5, s5) MARCH_LANE(6, s6) MARCH_LANE(7, s7)
    MARCH_LANE(8, s8) MARCH_LANE(9, s9) MARCH_LANE(10, sa) MARCH_LANE(11, sb)
    MARCH_LANE(12, sc) MARCH_LANE(13, sd) MARCH_LANE(14, se) MARCH_LANE(15, sf)
#undef MARCH_LANE
}

/* counts [n]: ray i's live bins (the sum of its row of live [n, W]). */
__kernel void march_count(const int n, const int W, __global const uchar *live,
                          __global int *counts) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const uchar *row = live + (size_t)i * W;
    int m = 0;
    for (int k = 0; k < W; ++k) m += row[k];
    counts[i] = m;
}

/* t [M], dt [M], xyz [M, 3], vdir [M, 3] of the live samples (live [n, W] from march_live),
 * ray i's from offsets[i] on, recomputed exactly as march_live computed them. */
__kernel void march_compact(const int n, const int S, const int k0, const int k1,
                            const float near, const float far, const int jitter, const uint key,
                            __global const float *origins, __global const float *dirs,
                            const float4 centre, const float4 inv_half,
                            __global const uchar *live, __global const int *offsets,
                            __global float *t_out, __global float *dt_out, __global float *xyz,
                            __global float *vdir) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int W = k1 - k0;
    __global const uchar *row = live + (size_t)i * W;
    int j = offsets[i];
    const int j_end = offsets[i + 1];   /* less than the live bins where capped at capacity */
    if (j == j_end) return;
    const float3 o = load3(origins, i), dh = unit_dir(dirs, i);
    for (int k = k0; k < k1 && j < j_end; ++k) {
        if (!row[k - k0]) continue;
        float dt;
        const float t = bin_t(i, k, S, near, far, jitter, key, &dt);
        const float3 x = enc_point(o + t * dh, centre, inv_half);
        t_out[j] = t;
        dt_out[j] = dt;
        xyz[3 * j] = x.x; xyz[3 * j + 1] = x.y; xyz[3 * j + 2] = x.z;
        vdir[3 * j] = dh.x; vdir[3 * j + 1] = dh.y; vdir[3 * j + 2] = dh.z;
        ++j;
    }
}

#define ST 8   /* floats of per-ray state in packed_forward */

/* Continue ray i's composite over its live samples of this window (state [n, ST]). */
__kernel void packed_forward(const int n, __global const int *offsets, __global const float *t,
                             __global const float *dt, __global const float *sigma,
                             __global const float *rgb, __global float *state,
                             __global uchar *alive) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global float *s = state + (size_t)i * ST;
    float3 col = (float3)(s[0], s[1], s[2]);
    float acc = s[3], depth = s[4];
    ksum_t logT = {s[5], s[6]};
    float T = exp(logT.s);
    for (int j = offsets[i]; j < offsets[i + 1]; ++j) {
        const float sg = sigma[j];
        if (!(sg > 0.0f)) continue;
        const float w = vr_step(&logT, T, sg * dt[j], &T);
        col += w * load3(rgb, j);
        acc += w;
        depth += w * t[j];
    }
    s[0] = col.x; s[1] = col.y; s[2] = col.z;
    s[3] = acc; s[4] = depth; s[5] = logT.s; s[6] = logT.c;
    if (alive && !(T >= HASH_T_STOP)) alive[i] = 0;
}

/* Training: loss gradients of every live sample (one window holding all bins). */
__kernel void packed_backward(const int n, __global const int *offsets, __global const float *t,
                              __global const float *dt, __global const float *sigma,
                              __global const float *rgb, const float4 bg,
                              __global const float *target, const float loss_scale,
                              __global float *sq_err, __global float *dsigma,
                              __global float *drgb) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int j0 = offsets[i], j1 = offsets[i + 1];
    float3 col = (float3)(0.0f);
    ksum_t logT = {0.0f, 0.0f};
    float T = 1.0f;
    for (int j = j0; j < j1; ++j) {
        const float sg = sigma[j];
        if (sg > 0.0f) col += vr_step(&logT, T, sg * dt[j], &T) * load3(rgb, j);
    }
    col += exp(logT.s) * bg.xyz;
    const float3 diff = col - load3(target, i);
    sq_err[i] = dot(diff, diff);
    const float3 g = 2.0f * loss_scale * diff;
    const float total = dot(g, col);
    ksum_t prefix = {0.0f, 0.0f};
    logT.s = logT.c = 0.0f;
    T = 1.0f;
    for (int j = j0; j < j1; ++j) {
        const float sg = sigma[j];
        if (!(sg > 0.0f)) {
            dsigma[j] = 0.0f;
            drgb[3 * j] = drgb[3 * j + 1] = drgb[3 * j + 2] = 0.0f;
            continue;
        }
        const float w = vr_step(&logT, T, sg * dt[j], &T);
        dsigma[j] = vr_dsigma(&prefix, total, w, T, dot(g, load3(rgb, j)), dt[j]);
        drgb[3 * j] = w * g.x;
        drgb[3 * j + 1] = w * g.y;
        drgb[3 * j + 2] = w * g.z;
    }
}

/* keep[i] = the number of ray i's leading samples with T in front >= t_stop (>= 1 if it has
 * any), compositing as packed_forward. */
__kernel void packed_keep(const int n, __global const int *offsets, __global const float *dt,
                          __global const float *sigma, const float t_stop, __global int *keep) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int j0 = offsets[i], j1 = offsets[i + 1];
    ksum_t logT = {0.0f, 0.0f};
    float T = 1.0f;
    int j = j0;
    for (; j < j1; ++j) {
        if (j > j0 && !(T >= t_stop)) break;
        const float sg = sigma[j];
        if (sg > 0.0f) vr_step(&logT, T, sg * dt[j], &T);
    }
    keep[i] = j - j0;
}

/* dst rows new_offsets[i] .. new_offsets[i+1]-1 = src rows offsets[i] .. (the kept prefix of
 * ray i), rows of `width` floats. */
__kernel void packed_gather(const int n, const int width, __global const int *offsets,
                            __global const int *new_offsets, __global const float *src,
                            __global float *dst) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const size_t a = (size_t)offsets[i] * width, b = (size_t)new_offsets[i] * width;
    const size_t len = (size_t)(new_offsets[i + 1] - new_offsets[i]) * width;
    for (size_t k = 0; k < len; ++k) dst[b + k] = src[a + k];
}

#if HASH_POSE_GRAD
#define SH_DEGREE 3
#include "sh.h"

/* dL/dx at world point x of dL/dp at the encoding's point p = enc_point(x) (see the header). */
CLRF_INLINE float3 enc_point_vjp(const float3 x, const float3 gp, const float4 c,
                                 const float4 ih) {
#if HASH_CONTRACT
    const float3 y = (x - c.xyz) * ih.xyz, a = fabs(y);
    const float n = fmax(a.x, fmax(a.y, a.z));
    if (n <= 1.0f) return gp * ih.xyz;
    const float k = dot(y, gp) * 2.0f * (1.0f - n) / (n * n * n);
    float3 gy = gp * ((2.0f - 1.0f / n) / n);
    if (a.x >= a.y && a.x >= a.z) gy.x += k * sign(y.x);   /* the first axis on ties */
    else if (a.y >= a.z) gy.y += k * sign(y.y);
    else gy.z += k * sign(y.z);
    return gy * ih.xyz;
#else
    return gp;
#endif
}

/* grad [n, 6] = (dL/do, dL/dd) of ray i (overwritten) from gp [M, 3] = dL/dp of its samples
 * and gsh [M, SH_BASIS] = dL/dY (null: no direction encoding's share); see the header. */
__kernel void packed_ray_grad(const int n, __global const int *offsets, __global const float *t,
                              __global const float *origins, __global const float *dirs,
                              const float4 centre, const float4 inv_half,
                              __global const float *gp, __global const float *gsh,
                              __global float *grad) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float3 o = load3(origins, i), dh = unit_dir(dirs, i);
    float3 go = (float3)(0.0f), gd = (float3)(0.0f);
    for (int j = offsets[i]; j < offsets[i + 1]; ++j) {
        const float3 gx = enc_point_vjp(o + t[j] * dh, load3(gp, j), centre, inv_half);
        go += gx;
        gd += t[j] * gx;
        if (gsh) {
            float w[SH_BASIS];
            for (int b = 0; b < SH_BASIS; ++b) w[b] = gsh[(size_t)j * SH_BASIS + b];
            gd += sh_dir_grad(dh, w);
        }
    }
    const float3 d = load3(dirs, i);
    const float mx = fmax(fabs(d.x), fmax(fabs(d.y), fabs(d.z)));
    const float len = mx > 0.0f ? mx * length(d / mx) : 0.0f;   /* |d| without overflow */
    gd = (gd - dh * dot(dh, gd)) * safe_div(1.0f, len);
    __global float *g = grad + (size_t)i * 6;
    g[0] = go.x; g[1] = go.y; g[2] = go.z;
    g[3] = gd.x; g[4] = gd.y; g[5] = gd.z;
}
#endif
