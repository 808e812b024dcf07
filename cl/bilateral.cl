/* bilateral.cl: the bilateral grid of Wang et al. 2024 (gsplat's use_bilateral_grid), a per-view
 * colour correction of the splat model's render before the loss (splat.bilateral_grid,
 * clrf/corrections/bilateral.py); float64 twin: clrf/references/reference_bilateral.py.
 *
 * Layout: grids [V, L, GY, GX, 12] floats, view v's grid at v * L GY GX 12; cell (z, y, x) at
 * ((z GY + y) GX + x) 12, its 12 entries a 3 x 4 affine colour transform row-major (entry
 * k = 4 i + j: A_ij for j < 3, b_i for j = 3; the identity 1 0 0 0 0 1 0 0 0 0 1 0). Renders,
 * their gradients: [H, W, 3], pixel p = py W + px; T [H, W].
 *
 * Slice (trilinear, gsplat's grid sample with aligned corners and the border clamp): pixel
 * (px, py) of colour rgb sits at u = (px + 1/2) / W (GX - 1), w = (py + 1/2) / H (GY - 1),
 * z = clamp(lum (L - 1), 0, L - 1), lum = 0.299 r + 0.587 g + 0.114 b (BT.601 grey); on an
 * axis of n cells, i0 = min(floor(t), n - 2), i1 = i0 + 1, f = t - i0 (n = 1: one cell,
 * f = 0); M = sum of the 8 corners' w_c G_c, w_c = product of (1 - f) or f per axis.
 *   out = A rgb + b                              masked = 0 (a capture without alpha)
 *   out = A (rgb - T bg) + (1 - T) b + T bg      masked = 1: the scene's light transformed,
 *                                                its background (bg) kept
 *
 * bilateral_apply     out, one work-item per pixel.
 * bilateral_backward_rgb  dL/drgb from g = dL/dout, one work-item per pixel (T held fixed):
 *                     with x = rgb (- T bg), y = 1 (- T): dL/dM = (g_i x_j, g_i y);
 *                     dL/drgb_j = sum_i A_ij g_i + [0 < lum (L - 1) < L - 1] (L - 1) GREY_j
 *                     sum_k dL/dM_k dM_k/dz, dM/dz = sum_c (+-1 along z) wx wy G_c (the
 *                     guidance's share; none where z is clamped, as the border clamp).
 * bilateral_backward_grid  dL/dG of view v's grid [L, GY, GX, 12], one work-item per column
 *                     (x, y) that gathers sum_p w_c dL/dM_p over the pixels of its footprint
 *                     (u within 1 of x, w within 1 of y) in pixel order: deterministic, no
 *                     atomics. Float32 sums: a cell of an 800 x 800 render at 16 x 16 sums
 *                     ~11,000 terms of one sign pattern, ~1e-7 sqrt(n) relative error.
 * bilateral_tv_grad   the gradient a grid takes in a step of view v: weight times the
 *                     gradient of gsplat's total variation of each grid, TV(G) = sum over
 *                     the axes d of sum (G[i+1] - G[i])^2 / n_d (n_d: the differences along
 *                     d times 12), d TV / dG[i] = 2 / n_d ((G[i] - G[i-1]) - (G[i+1] - G[i]))
 *                     (the neighbours that exist), plus view v's data gradient (v < 0: none);
 *                     one work-item per entry of grids first .. first + count - 1 (every grid
 *                     in gsplat's dense step; view v's alone with splat.bilateral_grid_sparse).
 *                     clrf/runtime/optim.py's Adam (cl/optim.cl, cl/adam.h) then steps them.
 *
 * Defines read:
 *   BILATERAL_L  the grid's luminance bins (splat.bilateral_grid_shape[2]): the size of
 *                bilateral_backward_grid's private accumulators.
 */

#include "common.h"

#ifndef BILATERAL_L
#define BILATERAL_L 8   /* luminance bins (gsplat's default) */
#endif
#if BILATERAL_L < 1
#error "BILATERAL_L must be at least 1"
#endif

#define BILATERAL_CH 12   /* a 3 x 4 affine transform per cell */
#define GREY_R 0.299f     /* BT.601 luma weights (gsplat's rgb2gray) */
#define GREY_G 0.587f
#define GREY_B 0.114f
#define PIXEL_CENTRE 0.5f /* pixel px covers [px, px + 1): its centre */

/* where a pixel sits in the grid: the two cells and the upper one's weight on each axis, and
 * whether its guidance z is inside (0, L - 1) (unclamped: the luminance path passes) */
typedef struct {
    int x0, x1, y0, y1, z0, z1, free_z;
    float fx, fy, fz;
} bilateral_pos;

/* (i0, i1, f) of coordinate t on an axis of n cells */
CLRF_INLINE void bilateral_axis(const float t, const int n, int *i0, int *i1, float *f) {
    if (n == 1) {
        *i0 = 0; *i1 = 0; *f = 0.0f;
        return;
    }
    const int a = min((int)floor(t), n - 2);
    *i0 = a; *i1 = a + 1; *f = t - (float)a;
}

CLRF_INLINE bilateral_pos bilateral_locate(const int px, const int py, const int W, const int H,
                                           const int GX, const int GY, const float3 c) {
    bilateral_pos s;
    const float u = ((float)px + PIXEL_CENTRE) / (float)W * (float)(GX - 1);
    const float w = ((float)py + PIXEL_CENTRE) / (float)H * (float)(GY - 1);
    const float zr = (GREY_R * c.x + GREY_G * c.y + GREY_B * c.z) * (float)(BILATERAL_L - 1);
    const float z = clamp(zr, 0.0f, (float)(BILATERAL_L - 1));
    s.free_z = zr > 0.0f && zr < (float)(BILATERAL_L - 1);
    bilateral_axis(u, GX, &s.x0, &s.x1, &s.fx);
    bilateral_axis(w, GY, &s.y0, &s.y1, &s.fy);
    bilateral_axis(z, BILATERAL_L, &s.z0, &s.z1, &s.fz);
    return s;
}

/* M [12] and dM/dz [12] of one grid G at s */
CLRF_INLINE void bilateral_slice(__global const float *G, const int GX, const int GY,
                                 const bilateral_pos s, float *M, float *dMdz) {
    for (int k = 0; k < BILATERAL_CH; ++k) {
        M[k] = 0.0f;
        dMdz[k] = 0.0f;
    }
    for (int c = 0; c < 8; ++c) {
        const int xc = (c & 1) ? s.x1 : s.x0, yc = (c & 2) ? s.y1 : s.y0;
        const int zc = (c & 4) ? s.z1 : s.z0;
        const float wxy = ((c & 1) ? s.fx : 1.0f - s.fx) * ((c & 2) ? s.fy : 1.0f - s.fy);
        const float wc = wxy * ((c & 4) ? s.fz : 1.0f - s.fz);
        const float dz = (c & 4) ? wxy : -wxy;
        __global const float *cell = G + ((size_t)(zc * GY + yc) * GX + xc) * BILATERAL_CH;
        for (int k = 0; k < BILATERAL_CH; ++k) {
            M[k] += wc * cell[k];
            dMdz[k] += dz * cell[k];
        }
    }
}

/* (x, y) of a pixel: out = A x + y b (+ T bg masked) */
CLRF_INLINE float4 bilateral_terms(const float3 c, const int masked, __global const float *T,
                                   const int p, const float4 bg) {
    const float t = masked ? T[p] : 0.0f;
    return (float4)(c - t * bg.xyz, 1.0f - t);
}

__kernel void bilateral_apply(const int H, const int W, const int GX, const int GY,
                              __global const float *rgb, const int masked,
                              __global const float *T, const float4 bg,
                              __global const float *grids, const int v, __global float *out) {
    const int p = get_global_id(0);
    if (p >= H * W) return;
    const float3 c = load3(rgb, p);
    const bilateral_pos s = bilateral_locate(p % W, p / W, W, H, GX, GY, c);
    float M[BILATERAL_CH], dMdz[BILATERAL_CH];
    bilateral_slice(grids + (size_t)v * BILATERAL_L * GY * GX * BILATERAL_CH, GX, GY, s, M,
                    dMdz);
    const float4 x = bilateral_terms(c, masked, T, p, bg);
    const float t = masked ? T[p] : 0.0f;
    for (int i = 0; i < 3; ++i)
        out[3 * p + i] = M[4 * i] * x.x + M[4 * i + 1] * x.y + M[4 * i + 2] * x.z
                         + M[4 * i + 3] * x.w + t * (i == 0 ? bg.x : i == 1 ? bg.y : bg.z);
}

__kernel void bilateral_backward_rgb(const int H, const int W, const int GX, const int GY,
                                     __global const float *rgb, const int masked,
                                     __global const float *T, const float4 bg,
                                     __global const float *grad_out,
                                     __global const float *grids, const int v,
                                     __global float *grad_rgb) {
    const int p = get_global_id(0);
    if (p >= H * W) return;
    const float3 c = load3(rgb, p);
    const bilateral_pos s = bilateral_locate(p % W, p / W, W, H, GX, GY, c);
    float M[BILATERAL_CH], dMdz[BILATERAL_CH];
    bilateral_slice(grids + (size_t)v * BILATERAL_L * GY * GX * BILATERAL_CH, GX, GY, s, M,
                    dMdz);
    const float4 x = bilateral_terms(c, masked, T, p, bg);
    const float g[3] = {grad_out[3 * p], grad_out[3 * p + 1], grad_out[3 * p + 2]};
    float dz = 0.0f;   /* dL/dz = sum_k dL/dM_k dM_k/dz */
    for (int i = 0; i < 3; ++i)
        dz += g[i] * (dMdz[4 * i] * x.x + dMdz[4 * i + 1] * x.y + dMdz[4 * i + 2] * x.z
                      + dMdz[4 * i + 3] * x.w);
    const float lum = s.free_z ? dz * (float)(BILATERAL_L - 1) : 0.0f;
    grad_rgb[3 * p] = M[0] * g[0] + M[4] * g[1] + M[8] * g[2] + lum * GREY_R;
    grad_rgb[3 * p + 1] = M[1] * g[0] + M[5] * g[1] + M[9] * g[2] + lum * GREY_G;
    grad_rgb[3 * p + 2] = M[2] * g[0] + M[6] * g[1] + M[10] * g[2] + lum * GREY_B;
}

/* the first and last pixel (clamped to [0, n - 1]) whose coordinate on an axis of G cells over
 * n pixels lies within 1 of cell i, with a pixel's margin for rounding (the weights decide) */
CLRF_INLINE int2 bilateral_footprint(const int i, const int G, const int n) {
    if (G == 1) return (int2)(0, n - 1);
    const float scale = (float)n / (float)(G - 1);
    const int lo = (int)floor((float)(i - 1) * scale - PIXEL_CENTRE) - 1;
    const int hi = (int)ceil((float)(i + 1) * scale - PIXEL_CENTRE) + 1;
    return (int2)(max(lo, 0), min(hi, n - 1));
}

__kernel void bilateral_backward_grid(const int H, const int W, const int GX, const int GY,
                                      __global const float *rgb, const int masked,
                                      __global const float *T, const float4 bg,
                                      __global const float *grad_out,
                                      __global float *grad_grid) {
    const int col = get_global_id(0);
    if (col >= GX * GY) return;
    const int gx = col % GX, gy = col / GX;
    float acc[BILATERAL_L * BILATERAL_CH];
    for (int k = 0; k < BILATERAL_L * BILATERAL_CH; ++k) acc[k] = 0.0f;
    const int2 xs = bilateral_footprint(gx, GX, W), ys = bilateral_footprint(gy, GY, H);
    for (int py = ys.x; py <= ys.y; ++py) {
        for (int px = xs.x; px <= xs.y; ++px) {
            const int p = py * W + px;
            const float3 c = load3(rgb, p);
            const bilateral_pos s = bilateral_locate(px, py, W, H, GX, GY, c);
            const float wx = (s.x0 == gx ? 1.0f - s.fx : 0.0f) + (s.x1 == gx ? s.fx : 0.0f);
            const float wy = (s.y0 == gy ? 1.0f - s.fy : 0.0f) + (s.y1 == gy ? s.fy : 0.0f);
            const float wxy = wx * wy;
            if (wxy == 0.0f) continue;
            const float4 x = bilateral_terms(c, masked, T, p, bg);
            const float xv[4] = {x.x, x.y, x.z, x.w};
            const float w0 = wxy * (1.0f - s.fz), w1 = wxy * s.fz;
            for (int i = 0; i < 3; ++i) {
                const float gi = grad_out[3 * p + i];
                for (int j = 0; j < 4; ++j) {
                    const float d = gi * xv[j];
                    acc[s.z0 * BILATERAL_CH + 4 * i + j] += w0 * d;
                    acc[s.z1 * BILATERAL_CH + 4 * i + j] += w1 * d;
                }
            }
        }
    }
    for (int z = 0; z < BILATERAL_L; ++z)
        for (int k = 0; k < BILATERAL_CH; ++k)
            grad_grid[((size_t)(z * GY + gy) * GX + gx) * BILATERAL_CH + k] =
                acc[z * BILATERAL_CH + k];
}

/* weight * 2 / n_d times (G[i] - G[i - stride]) - (G[i + stride] - G[i]) along one axis of n
 * cells (position a on it), n_d its differences times 12; 0 on an axis of one cell */
CLRF_INLINE float bilateral_tv_axis(__global const float *G, const size_t i, const int a,
                                    const int n, const size_t stride, const float pairs) {
    if (n == 1) return 0.0f;
    float d = 0.0f;
    if (a > 0) d += G[i] - G[i - stride];
    if (a < n - 1) d -= G[i + stride] - G[i];
    return 2.0f / pairs * d;
}

__kernel void bilateral_tv_grad(const int first, const int count, const int GX, const int GY,
                                __global const float *grids, const int v,
                                __global const float *data_grad, const float weight,
                                __global float *grad) {
    const size_t per = (size_t)BILATERAL_L * GY * GX * BILATERAL_CH;
    const size_t gid = get_global_id(0);
    if (gid >= (size_t)count * per) return;
    const size_t i = (size_t)first * per + gid;
    const size_t e = i % per;
    const int cell = (int)(e / BILATERAL_CH);
    const int x = cell % GX, y = (cell / GX) % GY, z = cell / (GX * GY);
    const float cells = (float)(BILATERAL_L * GY * GX);   /* differences: cells / n (n - 1) */
    float t = bilateral_tv_axis(grids, i, x, GX, BILATERAL_CH,
                                BILATERAL_CH * cells / GX * (GX - 1));
    t += bilateral_tv_axis(grids, i, y, GY, (size_t)GX * BILATERAL_CH,
                           BILATERAL_CH * cells / GY * (GY - 1));
    t += bilateral_tv_axis(grids, i, z, BILATERAL_L, (size_t)GY * GX * BILATERAL_CH,
                           BILATERAL_CH * cells / BILATERAL_L * (BILATERAL_L - 1));
    grad[i] = weight * t + ((int)(i / per) == v ? data_grad[e] : 0.0f);
}
