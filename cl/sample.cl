/* sample.cl: sample distances along rays (NeRF path): stratified, importance (inverse CDF),
 * merge of two sorted lists, and the points/directions fed to the encoders.
 *
 * Memory layout: per-ray lists are row-major [n_rays, K]; points and unit directions
 * [n_rays * K, 3] (sample k of ray i at row i*K + k). Distances t are along the UNIT ray
 * direction (world units), so a segment's length is a difference of t.
 *
 * Stratified (K samples in [near, far]):
 *   t_k = near + (far - near) (k + u_k) / K,  u_k = uniform01(key, i*K + k) with jitter, else 1/2.
 * Importance (Nf samples from coarse distances t_c [Kc] and weights w [Kc]):
 *   bins: edges e_0 = near, e_k = (t_{k-1} + t_k)/2 (k = 1..Kc-1), e_Kc = far; bin k has mass
 *   p_k = max(w_k, 0) + PDF_PAD (NaN counts as 0), so all-zero weights give the uniform pdf and
 *   a one-hot weight puts all but Kc*PDF_PAD of the mass in its bin;
 *   u_j = (j + v_j) / Nf, v_j uniform01 with jitter, else 1/2 (sorted), and
 *   t_j = e_b + (e_{b+1} - e_b) (u_j P - C_b) / p_b where C_b <= u_j P < C_b + p_b,
 *   C_b = sum_{k<b} p_k, P = sum_k p_k (piecewise-constant pdf inverted exactly).
 * Every output is in [near, far] and non-decreasing along the ray; near == far gives t = near.
 *
 * Random numbers: uniform01 (common.h) of a host key and the sample's counter, so a kernel
 * and its float64 reference draw the same numbers.
 *
 * Camera gradient (nerf.pose_opt; ray_points_backward): sample k of ray i is
 * x_k = o + t_k dh, seen along v_k = dh (dh = d / |d|), with t_k held constant (the
 * stratified distances do not depend on the ray, and the importance samples' distances,
 * drawn from the coarse weights, are taken as given: no gradient flows through where they
 * fall). From the samples' dL/dx_k and dL/dv_k (cl/encode.cl encode_backward of the MLP's
 * input gradient):
 *   dL/do = sum_k dL/dx_k,   dL/ddh = sum_k (t_k dL/dx_k + dL/dv_k),
 *   dL/dd = (dL/ddh - dh (dh . dL/ddh)) / |d|     (the Jacobian of d / |d|),
 * summed over the passes that saw the ray (coarse and fine: ``accumulate``). A zero d gives
 * dL/dd = 0 (its unit direction is 0, as ray_points makes it).
 *
 * Defines read: PDF_PAD.
 */
#include "common.h"

#ifndef PDF_PAD
#define PDF_PAD 1e-5f  /* mass added to every coarse weight (NeRF's "prevent nans" padding) */
#endif

/* One work-item per sample (n*K items). */
__kernel void sample_stratified(const int n, const int K, const float near, const float far,
                                const int jitter, const uint key, __global float *t) {
    const int i = get_global_id(0);
    if (i >= n * K) return;
    const int k = i % K;
    const float u = jitter ? uniform01(key, (uint)i) : 0.5f;
    t[i] = near + (far - near) * (((float)k + u) / (float)K);
}

/* One work-item per ray. */
__kernel void sample_importance(const int n, const int Kc, const int Nf, const float near,
                                const float far, __global const float *t_c,
                                __global const float *w, const int jitter, const uint key,
                                __global float *t_f) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const float *tc = t_c + (size_t)i * Kc;
    __global const float *wc = w + (size_t)i * Kc;
    __global float *out = t_f + (size_t)i * Nf;
    float total = 0.0f;
    for (int k = 0; k < Kc; ++k) total += fmax(wc[k], 0.0f) + PDF_PAD;
    int b = 0;
    float cum = 0.0f;                       /* C_b */
    float pb = fmax(wc[0], 0.0f) + PDF_PAD; /* p_b */
    for (int j = 0; j < Nf; ++j) {
        const float v = jitter ? uniform01(key, (uint)(i * Nf + j)) : 0.5f;
        const float target = (((float)j + v) / (float)Nf) * total;
        while (b < Kc - 1 && cum + pb <= target) {
            cum += pb;
            ++b;
            pb = fmax(wc[b], 0.0f) + PDF_PAD;
        }
        const float e0 = b == 0 ? near : 0.5f * (tc[b - 1] + tc[b]);
        const float e1 = b == Kc - 1 ? far : 0.5f * (tc[b] + tc[b + 1]);
        const float frac = clamp((target - cum) / pb, 0.0f, 1.0f);
        out[j] = clamp(e0 + (e1 - e0) * frac, near, far);
    }
}

/* Merge two per-ray sorted lists a [n, Ka], b [n, Kb] into out [n, Ka + Kb] (sorted, stable:
 * ties take a first). One work-item per ray. */
__kernel void merge_sorted(const int n, const int Ka, const int Kb, __global const float *a,
                           __global const float *b, __global float *out) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const float *pa = a + (size_t)i * Ka;
    __global const float *pb = b + (size_t)i * Kb;
    __global float *o = out + (size_t)i * (Ka + Kb);
    int ia = 0, ib = 0;
    for (int k = 0; k < Ka + Kb; ++k) {
        const int take_a = ib >= Kb || (ia < Ka && pa[ia] <= pb[ib]);
        o[k] = take_a ? pa[ia++] : pb[ib++];
    }
}

/* Points x = o + t d/|d| and unit directions for every sample: one work-item per sample. */
__kernel void ray_points(const int n, const int K, __global const float *origins,
                         __global const float *dirs, __global const float *t,
                         __global float *xyz, __global float *vdir) {
    const int i = get_global_id(0);
    if (i >= n * K) return;
    const int r = i / K;
    const float3 o = (float3)(origins[3 * r], origins[3 * r + 1], origins[3 * r + 2]);
    float3 d = (float3)(dirs[3 * r], dirs[3 * r + 1], dirs[3 * r + 2]);
    const float mx = fmax(fabs(d.x), fmax(fabs(d.y), fabs(d.z)));
    d = mx > 0.0f ? d / mx : (float3)(0.0f);  /* scale first: |d|^2 may under/overflow */
    d = d * safe_div(1.0f, length(d));
    const float3 x = o + t[i] * d;
    xyz[3 * i] = x.x; xyz[3 * i + 1] = x.y; xyz[3 * i + 2] = x.z;
    vdir[3 * i] = d.x; vdir[3 * i + 1] = d.y; vdir[3 * i + 2] = d.z;
}

/* dL/d(origin, direction) [n, 6] of rays whose samples x = o + t d/|d| (ray_points, with the
 * same t [n, K]) got dL/dx gx [n*K, 3] and dL/dv gv [n*K, 3] (v the unit direction the
 * samples were seen along): written, or added to ray_grad with accumulate (a second pass over
 * the same rays). One work-item per ray. */
__kernel void ray_points_backward(const int n, const int K, __global const float *dirs,
                                  __global const float *t, __global const float *gx,
                                  __global const float *gv, const int accumulate,
                                  __global float *ray_grad) {
    const int i = get_global_id(0);
    if (i >= n) return;
    float3 d = (float3)(dirs[3 * i], dirs[3 * i + 1], dirs[3 * i + 2]);
    const float mx = fmax(fabs(d.x), fmax(fabs(d.y), fabs(d.z)));
    d = mx > 0.0f ? d / mx : (float3)(0.0f);  /* as ray_points: scale first */
    const float len = length(d);              /* |d| / mx, in [1, sqrt 3] unless d = 0 */
    const float3 dh = d * safe_div(1.0f, len);
    float3 go = (float3)(0.0f), gd = (float3)(0.0f);
    for (int k = 0; k < K; ++k) {
        const size_t q = (size_t)i * K + k;
        const float3 g = load3(gx, q);
        go += g;
        gd += t[q] * g + load3(gv, q);
    }
    /* (I - dh dh^T) dL/ddh / |d|, |d| = mx len: divided by len first, then by mx, so a tiny
     * |d| overflows only where the true value does */
    gd = (gd - dh * dot(dh, gd)) * safe_div(1.0f, len);
    gd = mx > 0.0f ? gd / mx : (float3)(0.0f);
    __global float *out = ray_grad + 6 * (size_t)i;
    if (accumulate) {
        go += (float3)(out[0], out[1], out[2]);
        gd += (float3)(out[3], out[4], out[5]);
    }
    out[0] = go.x; out[1] = go.y; out[2] = go.z;
    out[3] = gd.x; out[4] = gd.y; out[5] = gd.z;
}
