/* background.cl: multi-sphere-image (MSI) background for unbounded scenes, forward and backward.
 *
 * Model. BG_LAYERS concentric spheres around `center` with radii r_l, l = 0 .. L-1, spaced
 * uniformly in inverse radius between the foreground's bounding sphere (radius r_inner) and
 * infinity:  u_l = 1/r_l = (1 - (l + 0.5)/L) / r_inner,  so r_0 = r_inner / (1 - 0.5/L) is just
 * outside the foreground and r_{L-1} = 2 L r_inner is far but finite. Each layer is an
 * equirectangular image of BG_H rows (latitude) x BG_W = 2 BG_H columns (longitude).
 *
 * Memory layout (float, C order)
 *   density [L, H, W]     density[(l*H + i)*W + j], raw (ReLU applied after interpolation)
 *   color   [L, H, W, 3]  color[((l*H + i)*W + j)*3 + ch], raw (activation after interpolation)
 *   origins, dirs [n, 3]  world space; dirs need not be unit length
 *   t_start [n]           world distance along the unit direction where the foreground ends
 *   out_rgb [n, 3], out_T [n]
 *
 * Angles (z is up): v = (x - center)/|x - center|, lon = atan2(v.y, v.x) in [-pi, pi],
 * lat = atan2(v.z, hypot(v.x, v.y)) in [-pi/2, pi/2]. Texel (i, j) sits at the centre
 * lon_j = -pi + 2 pi (j + 0.5)/W, lat_i = -pi/2 + pi (i + 0.5)/H. Column coordinate
 * X = (lon + pi) W / (2 pi) - 0.5 wraps (columns j0 = floor(X) mod W and j0 + 1 mod W); row
 * coordinate Y = (lat + pi/2) H / pi - 0.5 is clamped to [0, H - 1] (constant over the last half
 * row at each pole), like the grid's lerp_axis.
 *
 * Field. Trilinear in (lon, lat, layer coordinate s), s = L (1 - r_inner/|x - center|) - 0.5,
 * i.e. linear in inverse radius between consecutive layers (s = l exactly on sphere l):
 *   raw(x) = (1 - f) bilerp_l(lon, lat) + f bilerp_{l+1}(lon, lat),  f = s - l in [0, 1].
 *   sigma = max(raw_density, 0),  c = max(raw_color + 0.5, 0)  (the grid's colour activation).
 *
 * Quadrature. The ray o + t d (unit d) crosses sphere l outwards at the far intersection
 *   t_l = -b + sqrt(max(r_l^2 - h^2, 0)),  b = (o - center).d,  h = |(o - center) - b d|,
 * which grows with l (a ray that misses sphere l uses its point of closest approach, -b, which
 * keeps t_l continuous; cameras inside the inner sphere always hit every sphere). Segment k,
 * k = 0 .. L-2, is [a_k, t_{k+1}] with a_k = max(t_k, t_start, 0); it is skipped when empty.
 * Its one sample sits at the midpoint m_k = (a_k + t_{k+1})/2, whose radius lies between r_k and
 * r_{k+1}, so it interpolates layers k and k+1 with f_k = (u_k - 1/|x(m_k) - center|) L r_inner.
 * Midpoint quadrature, as the grid: tau_k = sigma_k delta_k with delta_k = t_{k+1} - a_k in world
 * units. Only the outgoing crossings count (a camera outside a sphere sees it from inside only).
 *
 * Compositing (front to back, log-space transmittance with a Kahan sum, as the grid):
 *   alpha_k = 1 - exp(-tau_k) = -expm1(-tau_k),  T_k = exp(-sum_{j<k} tau_j),  w_k = T_k alpha_k
 *   out_rgb = sum_k w_k c_k + T_end * bg,  out_T = T_end = exp(-sum_k tau_k).
 * There is no early termination at T_STOP (a ray has at most L - 1 samples); the march stops
 * only when log T < BG_LOGT_DEAD, where exp(log T) is exactly 0 in float32, so every later
 * weight would be 0: the result is the same as a full march.
 *
 * Backward, given g = dL/d out_rgb (the caller passes T_fg * dL/dpixel):
 *   dL/dsigma_k = delta_k (T_{k+1} (g.c_k) - R_k),   R_k = sum_{j>k} w_j (g.c_j) + T_end (g.bg)
 *   dL/dc_k     = w_k g                 (times [raw_color + 0.5 > 0] per channel)
 * R_k is the remaining radiance g.out_rgb minus the Kahan prefix sum, so the ray is marched twice
 * (once for g.out_rgb, once for the gradients): O(1) work per sample. The gradients of the raw
 * interpolated values ([raw_density > 0] for the ReLU) are scattered to the 8 texels with their
 * trilinear weights by atomic_add_f (many rays share texels), ADDED to grad_density/grad_color.
 * dL/d out_T is not propagated (out_T is an output for diagnostics and losses on opacity).
 *
 * Defines read: BG_LAYERS (L >= 2), BG_H (>= 1), CLRF_HAS_FP64 (ray.h: per-ray set-up in double),
 * CLRF_NATIVE_FLOAT_ATOMICS (common.h).
 */
#include "common.h"
#include "ray.h"
#include "volrend.h"

#ifndef BG_LAYERS
#define BG_LAYERS 16  /* number of spheres L; samples per ray = L - 1 */
#endif
#ifndef BG_H
#define BG_H 64       /* rows (latitude) of each equirectangular layer; columns = 2 BG_H */
#endif
#if BG_LAYERS < 2
#error "BG_LAYERS must be >= 2 (samples lie between consecutive spheres)"
#endif
#if BG_H < 1
#error "BG_H must be >= 1"
#endif
#define BG_W (2 * BG_H)
#define BG_COLOR_OFFSET 0.5f    /* same offset as the grid: all-zero colour parameters give grey */
#define BG_LOGT_DEAD (-110.0f)  /* exp(-110) < 2^-149: transmittance is exactly 0 in float32 */
#define BG_PI 3.14159265358979323846f

/* Per-ray set-up: origin relative to the centre, unit direction, b and h^2 (see header). */
typedef struct {
    real3 oc, d;
    real_t b, h2, start;
} bg_ray_t;

/* One sample: the 8 texel indices (layer k or k+1, two rows, two columns) and weights. */
typedef struct {
    int idx[8];
    float w[8];
} bg_lerp_t;

inline int bg_setup(float3 o, float3 d, float4 center, float t_start, bg_ray_t *R) {
    real3 dd = REAL3(d);
    real_t mx = fmax(fabs(dd.x), fmax(fabs(dd.y), fabs(dd.z)));
    if (!(mx > 0) || !isfinite(mx)) return 0;
    dd /= mx;                     /* scale first: |d| may under/overflow when squared */
    dd /= sqrt(dot(dd, dd));
    R->d = dd;
    R->oc = REAL3(o) - (real3)(center.x, center.y, center.z);
    R->b = dot(R->oc, dd);
    const real3 perp = R->oc - R->b * dd;
    R->h2 = dot(perp, perp);
    R->start = fmax((real_t)t_start, (real_t)0);
    return 1;
}

/* Inverse radius of layer l. */
inline real_t bg_inv_radius(int l, float r_inner) {
    return (1 - ((real_t)l + (real_t)0.5) / (real_t)BG_LAYERS) / (real_t)r_inner;
}

/* Far crossing t_l of sphere l (closest approach -b when the ray misses it). */
inline real_t bg_crossing(const bg_ray_t *R, int l, float r_inner) {
    const real_t r = 1 / bg_inv_radius(l, r_inner);
    return -R->b + sqrt(fmax(r * r - R->h2, (real_t)0));
}

/* Segment k: length and the sample's texels and weights; returns 0 when the segment is empty. */
inline int bg_segment(const bg_ray_t *R, int k, float r_inner, float *delta, bg_lerp_t *S) {
    const real_t t1 = bg_crossing(R, k + 1, r_inner);
    const real_t a = fmax(bg_crossing(R, k, r_inner), R->start);
    if (!(t1 > a)) return 0;
    *delta = (float)(t1 - a);
    const real3 p = R->oc + (real_t)0.5 * (a + t1) * R->d;
    const real_t rho = sqrt(dot(p, p));
    float f = (float)((bg_inv_radius(k, r_inner) - 1 / rho) * (real_t)BG_LAYERS * r_inner);
    f = clamp(f, 0.0f, 1.0f);
    const float lon = atan2((float)p.y, (float)p.x);
    const float lat = atan2((float)p.z, (float)sqrt(p.x * p.x + p.y * p.y));
    const float X = (lon + BG_PI) * ((float)BG_W / (2.0f * BG_PI)) - 0.5f;
    const float Y = clamp((lat + 0.5f * BG_PI) * ((float)BG_H / BG_PI) - 0.5f, 0.0f,
                          (float)(BG_H - 1));
    const float Xf = floor(X);
    const float fx = X - Xf;
    int j0 = (int)Xf % BG_W;
    if (j0 < 0) j0 += BG_W;
    const int j1 = j0 + 1 == BG_W ? 0 : j0 + 1;
    const int i0 = min((int)Y, max(BG_H - 2, 0));
    const int i1 = min(i0 + 1, BG_H - 1);
    const float fy = Y - (float)i0;
    const int js[2] = {j0, j1}, is[2] = {i0, i1};
    const float wx[2] = {1.0f - fx, fx}, wy[2] = {1.0f - fy, fy}, wl[2] = {1.0f - f, f};
    for (int c = 0; c < 8; ++c) {
        const int cz = c >> 2, cy = (c >> 1) & 1, cx = c & 1;
        S->idx[c] = ((k + cz) * BG_H + is[cy]) * BG_W + js[cx];
        S->w[c] = wl[cz] * wy[cy] * wx[cx];
    }
    return 1;
}

inline float bg_lerp_density(const bg_lerp_t *S, __global const float *density) {
    float s = 0.0f;
    for (int c = 0; c < 8; ++c) s += S->w[c] * density[S->idx[c]];
    return s;
}

inline float3 bg_lerp_color_pre(const bg_lerp_t *S, __global const float *color) {
    float3 s = (float3)(0.0f);
    for (int c = 0; c < 8; ++c) s += S->w[c] * vload3(S->idx[c], color);
    return s + BG_COLOR_OFFSET;
}

/* Forward march of one ray: the premultiplied MSI colour sum_k w_k c_k, and log T_end. */
inline float3 bg_march(const bg_ray_t *R, float r_inner, __global const float *density,
                       __global const float *color, float *logT_end) {
    ksum_t logT = {0.0f, 0.0f};
    float T = 1.0f;
    float3 rgb = (float3)(0.0f);
    for (int k = 0; k < BG_LAYERS - 1; ++k) {
        float delta;
        bg_lerp_t S;
        if (!bg_segment(R, k, r_inner, &delta, &S)) continue;
        const float sigma = bg_lerp_density(&S, density);
        if (!(sigma > 0.0f)) continue;
        const float tau = sigma * delta;
        rgb += vr_step(&logT, T, tau, &T) * fmax(bg_lerp_color_pre(&S, color), 0.0f);
        if (logT.s < BG_LOGT_DEAD) break;
    }
    *logT_end = logT.s;
    return rgb;
}

__kernel void bg_forward(const int n, __global const float *origins, __global const float *dirs,
                         __global const float *t_start, __global const float *density,
                         __global const float *color, const float4 center, const float r_inner,
                         const float4 bg, __global float *out_rgb, __global float *out_T) {
    const int gid = get_global_id(0);
    if (gid >= n) return;
    bg_ray_t R;
    float3 rgb = (float3)(0.0f);
    float logT = 0.0f;
    if (bg_setup(vload3(gid, origins), vload3(gid, dirs), center, t_start[gid], &R))
        rgb = bg_march(&R, r_inner, density, color, &logT);
    const float T = exp(logT);
    vstore3(rgb + T * bg.xyz, gid, out_rgb);
    out_T[gid] = T;
}

__kernel void bg_backward(const int n, __global const float *origins, __global const float *dirs,
                          __global const float *t_start, __global const float *density,
                          __global const float *color, const float4 center, const float r_inner,
                          const float4 bg, __global const float *grad_rgb,
                          __global float *grad_density, __global float *grad_color) {
    const int gid = get_global_id(0);
    if (gid >= n) return;
    bg_ray_t R;
    if (!bg_setup(vload3(gid, origins), vload3(gid, dirs), center, t_start[gid], &R)) return;
    const float3 g = vload3(gid, grad_rgb);
    float logT_end;
    const float3 rgb = bg_march(&R, r_inner, density, color, &logT_end);
    const float total = dot(g, rgb) + exp(logT_end) * dot(g, bg.xyz);  /* g.out_rgb */
    ksum_t logT = {0.0f, 0.0f}, prefix = {0.0f, 0.0f};
    float T = 1.0f;
    for (int k = 0; k < BG_LAYERS - 1; ++k) {
        float delta;
        bg_lerp_t S;
        if (!bg_segment(&R, k, r_inner, &delta, &S)) continue;
        const float sigma = bg_lerp_density(&S, density);
        if (!(sigma > 0.0f)) continue;
        const float tau = sigma * delta;
        const float w = vr_step(&logT, T, tau, &T);   /* T is now T_{k+1} */
        const float3 pre = bg_lerp_color_pre(&S, color);
        const float gc = dot(g, fmax(pre, 0.0f));
        const float dsigma = vr_dsigma(&prefix, total, w, T, gc, delta);
        const float3 dpre = select((float3)(0.0f), w * g, isgreater(pre, (float3)(0.0f)));
        for (int c8 = 0; c8 < 8; ++c8) {
            const float wc = S.w[c8];
            if (wc == 0.0f) continue;
            const int t = S.idx[c8];
            if (dsigma != 0.0f) atomic_add_f(grad_density + t, wc * dsigma);
            if (dpre.x != 0.0f) atomic_add_f(grad_color + 3 * t, wc * dpre.x);
            if (dpre.y != 0.0f) atomic_add_f(grad_color + 3 * t + 1, wc * dpre.y);
            if (dpre.z != 0.0f) atomic_add_f(grad_color + 3 * t + 2, wc * dpre.z);
        }
        if (logT.s < BG_LOGT_DEAD) break;
    }
}
