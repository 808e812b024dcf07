/* splat_raster.cl: tile binning and tile-based rasterisation of projected Gaussians (the
 * outputs of splat_project.cl), forward and backward. Conventions: splat.h.
 *
 * Binning (host order: count, exclusive scan, emit, sort, ranges; clrf/splat/raster.py):
 *   splat_count   counts[i] = (x1 - x0)(y1 - y0) tiles of Gaussian i's rect [N, 4] (0: culled)
 *   (scan)        offsets[i] = sum_{j < i} counts[j] (int64, on the device), P = the total
 *   splat_emit    for tile (tx, ty) of rect i, in row-major order from offsets[i]:
 *                   keys[k] = tile << 32 | bits(depth_i),  ids[k] = i
 *                 depth_i > near > 0, so its IEEE bits order like the depths as unsigned ints
 *   (sort)        keys and ids by key: per tile, front to back; equal depths keep the emit order
 *                 (ascending id), the sort being stable
 *   splat_ranges  ranges [ntiles, 2]: tile t's pairs are sorted entries [ranges[2t], ranges[2t+1])
 *                 (the buffer is zeroed first: empty tiles read [0, 0))
 *
 * Forward (splat_raster_forward): one work-group of TILE x TILE work-items per tile, one pixel
 * each (pixels outside the image take part in the loads only). The tile's list is walked front
 * to back in batches of TILE_PIXELS Gaussians, which the work-group loads cooperatively into
 * local memory (one Gaussian per work-item; barriers around each batch). Per pixel, with
 * alpha_k from splat.h (skipped entries leave T unchanged):
 *   T_0 = 1, C = sum_k T_k alpha_k c_k + T_end bg,  T_{k+1} = T_k (1 - alpha_k),
 * stopping before the entry that would bring T below T_MIN (that entry is not composited).
 * The work-group stops early once every pixel has stopped (a local counter).
 * Outputs: rgb [H, W, 3], T [H, W] (= T_end), n_contrib [H, W]: 1 + the list position (from the
 * tile's start) of the last composited entry, 0 if none; the backward walks [0, n_contrib).
 *
 * Backward (splat_raster_backward): the same work-groups walk each list back to front from the
 * largest n_contrib of the tile (a local atomic max), batches loaded in reverse. Per pixel, with
 * g = dL/drgb and the colour behind entry k, S_k = sum_{j > k} (T_j / T_{k+1}) alpha_j c_j +
 * (T_end / T_{k+1}) bg, kept by S_{k-1} = alpha_k c_k + (1 - alpha_k) S_k from S = bg, and
 * T_k = T_{k+1} / (1 - alpha_k) recovered from T_end:
 *   dL/dc_k = T_k alpha_k g,  dL/dalpha_k = T_k g . (c_k - S_k),
 *   where alpha_k = o G < ALPHA_MAX (G = exp(power)): dL/do = G dL/dalpha, dL/dpower = o G
 *   dL/dalpha, dL/dxy = dL/dpower (-(A d_x + B d_y), -(B d_x + C d_y)),
 *   dL/d(A, B, C) = dL/dpower (-d_x^2 / 2, -d_x d_y, -d_y^2 / 2);
 *   where the clamp is active (alpha_k = ALPHA_MAX) alpha_k does not depend on o, xy, conic.
 * These per-(pixel, Gaussian) terms are ADDED into g_xy [N, 2], g_conic [N, 3], g_opacity [N],
 * g_color [N, 3] with float atomics (common.h atomic_add_f); the caller zeroes them first.
 * The stopping rule and the skip threshold are treated as constants (piecewise derivative).
 *
 * Local memory per work-group: TILE_PIXELS x (float2 xy + float4 (A, B, C, o) + float4 colour)
 * = 40 TILE_PIXELS bytes (10 KiB for TILE 16), + int ids in the backward.
 * Defines read: TILE and the constants of splat.h.
 * Twin: clrf/testing/reference_splat.py bin_gaussians / rasterize / rasterize_backward.
 */
#include "common.h"
#include "splat.h"

__kernel void splat_count(const int n, __global const int *rect, __global int *counts) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int4 r = vload4(i, rect);
    counts[i] = (r.z - r.x) * (r.w - r.y);
}

__kernel void splat_emit(const int n, __global const int *rect, __global const float *depth,
                         __global const long *offsets, const int ntx, __global ulong *keys,
                         __global int *ids) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int4 r = vload4(i, rect);
    const ulong dbits = (ulong)as_uint(depth[i]);
    long k = offsets[i];
    for (int ty = r.y; ty < r.w; ++ty)
        for (int tx = r.x; tx < r.z; ++tx, ++k) {
            keys[k] = ((ulong)(ty * ntx + tx) << 32) | dbits;
            ids[k] = i;
        }
}

__kernel void splat_ranges(const int npairs, __global const ulong *keys, __global int *ranges) {
    const int k = get_global_id(0);
    if (k >= npairs) return;
    const int tile = (int)(keys[k] >> 32);
    if (k == 0 || (int)(keys[k - 1] >> 32) != tile) ranges[2 * tile] = k;
    if (k == npairs - 1 || (int)(keys[k + 1] >> 32) != tile) ranges[2 * tile + 1] = k + 1;
}

/* alpha of the Gaussian in local slot j at pixel centre pix; 0 where it is skipped. *raw_out:
 * o exp(power) before the clamp, *g_out: exp(power). The forward and the backward both call
 * this, so they skip the same entries. */
CLRF_INLINE float splat_alpha(const float2 mean, const float4 conic_op, const float2 pix,
                              float2 *d_out, float *g_out, float *raw_out) {
    const float2 d = mean - pix;
    const float power = splat_power(d, conic_op);
    const float G = exp(power);
    const float raw = conic_op.w * G;
    *d_out = d;
    *g_out = G;
    *raw_out = raw;
    const float alpha = fmin(ALPHA_MAX, raw);
    return (power > 0.0f || alpha < ALPHA_MIN) ? 0.0f : alpha;
}

__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void splat_raster_forward(const int width, const int height, const int ntx,
                          __global const int *ranges, __global const int *ids,
                          __global const float *xy, __global const float *conic,
                          __global const float *opacity, __global const float *color,
                          const float4 bg, __global float *out_rgb, __global float *out_T,
                          __global int *out_n) {
    __local float2 l_xy[TILE_PIXELS];
    __local float4 l_cop[TILE_PIXELS];   /* conic A, B, C and opacity */
    __local float4 l_col[TILE_PIXELS];
    __local int l_done;
    const int lx = get_local_id(0), ly = get_local_id(1), lid = ly * TILE + lx;
    const int tile = get_group_id(1) * ntx + get_group_id(0);
    const int px = get_group_id(0) * TILE + lx, py = get_group_id(1) * TILE + ly;
    const int inside = px < width && py < height;
    const float2 pix = (float2)((float)px + 0.5f, (float)py + 0.5f);
    const int start = ranges[2 * tile], end = ranges[2 * tile + 1];
    float T = 1.0f;
    float3 C = (float3)(0.0f);
    int last = 0, done = !inside;
    if (lid == 0) l_done = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (done) atomic_inc(&l_done);
    for (int base = start; base < end; base += TILE_PIXELS) {
        barrier(CLK_LOCAL_MEM_FENCE);   /* the previous batch is consumed; l_done is current */
        if (l_done == TILE_PIXELS) break;   /* every work-item reads the same value */
        if (base + lid < end) {
            const int g = ids[base + lid];
            l_xy[lid] = vload2(g, xy);
            l_cop[lid] = (float4)(vload3(g, conic), opacity[g]);
            l_col[lid] = (float4)(vload3(g, color), 0.0f);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        if (done) continue;
        const int cnt = min(TILE_PIXELS, end - base);
        for (int j = 0; j < cnt; ++j) {
            float2 d;
            float G, raw;
            const float alpha = splat_alpha(l_xy[j], l_cop[j], pix, &d, &G, &raw);
            if (alpha == 0.0f) continue;
            const float nT = T * (1.0f - alpha);
            if (nT < T_MIN) {
                done = 1;
                break;
            }
            C += l_col[j].xyz * (alpha * T);
            T = nT;
            last = base - start + j + 1;
        }
        if (done) atomic_inc(&l_done);
    }
    if (!inside) return;
    const int p = py * width + px;
    vstore3(C + T * bg.xyz, p, out_rgb);
    out_T[p] = T;
    out_n[p] = last;
}

__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void splat_raster_backward(const int width, const int height, const int ntx,
                           __global const int *ranges, __global const int *ids,
                           __global const float *xy, __global const float *conic,
                           __global const float *opacity, __global const float *color,
                           const float4 bg, __global const float *out_T,
                           __global const int *out_n, __global const float *grad_rgb,
                           __global float *g_xy, __global float *g_conic,
                           __global float *g_opacity, __global float *g_color) {
    __local int l_id[TILE_PIXELS];
    __local float2 l_xy[TILE_PIXELS];
    __local float4 l_cop[TILE_PIXELS];
    __local float4 l_col[TILE_PIXELS];
    __local int l_max;
    const int lx = get_local_id(0), ly = get_local_id(1), lid = ly * TILE + lx;
    const int tile = get_group_id(1) * ntx + get_group_id(0);
    const int px = get_group_id(0) * TILE + lx, py = get_group_id(1) * TILE + ly;
    const int inside = px < width && py < height;
    const float2 pix = (float2)((float)px + 0.5f, (float)py + 0.5f);
    const int start = ranges[2 * tile];
    const int p = inside ? py * width + px : 0;
    const int n_pix = inside ? out_n[p] : 0;
    float T = inside ? out_T[p] : 1.0f;
    const float3 g = inside ? vload3(p, grad_rgb) : (float3)(0.0f);
    float3 S = bg.xyz;
    if (lid == 0) l_max = 0;
    barrier(CLK_LOCAL_MEM_FENCE);
    atomic_max(&l_max, n_pix);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int stop = start + l_max;   /* entries [start, stop) are needed by some pixel */
    for (int top = stop; top > start; top -= TILE_PIXELS) {
        const int lo = max(start, top - TILE_PIXELS);
        barrier(CLK_LOCAL_MEM_FENCE);   /* the previous batch is consumed */
        if (top - 1 - lid >= lo) {      /* slot j holds entry top - 1 - j */
            const int gi = ids[top - 1 - lid];
            l_id[lid] = gi;
            l_xy[lid] = vload2(gi, xy);
            l_cop[lid] = (float4)(vload3(gi, conic), opacity[gi]);
            l_col[lid] = (float4)(vload3(gi, color), 0.0f);
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        const int cnt = top - lo;
        for (int j = 0; j < cnt; ++j) {
            if (top - 1 - j - start >= n_pix) continue;   /* beyond this pixel's last entry */
            float2 d;
            float G, raw;
            const float4 cop = l_cop[j];
            const float alpha = splat_alpha(l_xy[j], cop, pix, &d, &G, &raw);
            if (alpha == 0.0f) continue;
            const float3 c = l_col[j].xyz;
            T = T / (1.0f - alpha);
            const float3 dc = c - S;
            const float dalpha = T * (g.x * dc.x + g.y * dc.y + g.z * dc.z);
            S = alpha * c + (1.0f - alpha) * S;
            const int gi = l_id[j];
            const float w = T * alpha;
            atomic_add_f(&g_color[3 * gi], w * g.x);
            atomic_add_f(&g_color[3 * gi + 1], w * g.y);
            atomic_add_f(&g_color[3 * gi + 2], w * g.z);
            if (raw >= ALPHA_MAX) continue;   /* clamped: alpha is constant */
            atomic_add_f(&g_opacity[gi], G * dalpha);
            const float dpow = raw * dalpha;
            atomic_add_f(&g_xy[2 * gi], -dpow * (cop.x * d.x + cop.y * d.y));
            atomic_add_f(&g_xy[2 * gi + 1], -dpow * (cop.y * d.x + cop.z * d.y));
            atomic_add_f(&g_conic[3 * gi], -0.5f * dpow * d.x * d.x);
            atomic_add_f(&g_conic[3 * gi + 1], -dpow * d.x * d.y);
            atomic_add_f(&g_conic[3 * gi + 2], -0.5f * dpow * d.y * d.y);
        }
    }
}
