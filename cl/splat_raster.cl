/* splat_raster.cl: tile binning and tile-based rasterisation of projected Gaussians (the
 * outputs of splat_project.cl), forward and backward. Conventions: splat.h.
 *
 * Binning (host order: count, exclusive scan, emit, sort, ranges; clrf/splat/raster.py):
 *   splat_count   counts[i] = (x1 - x0)(y1 - y0) tiles of Gaussian i's rect [N, 4] (0: culled)
 *   (scan)        offsets[i] = sum_{j < i} counts[j] (int32 [N + 1], on the device; the total P
 *                 is summed in 64 bits and refused past int32: clrf/runtime/scan.py)
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
 * Built with -D RENDER_DEPTH=1 (a render that asks for depth: clrf render, the viewer's depth
 * view) the forwards take each splat's camera depth z [N] and also write out_depth [H, W] =
 * sum_k T_k alpha_k z_k in the same pass (the host divides by 1 - T_end for the mean depth).
 * Built with -D ABSGRAD=1 (splat.absgrad) the backwards also add |dL/dxy| per pixel into
 * g_xy_abs [N, 2] (each pixel's term's absolute value, per component: the densification test
 * on absolute screen gradients, where opposite pixels' terms cannot cancel).
 *
 * Local memory per work-group: TILE_PIXELS x (float2 xy + float4 (A, B, C, o) + float4 colour)
 * = 40 TILE_PIXELS bytes (10 KiB for TILE 16), + int ids in the backward.
 * Defines read: TILE and the constants of splat.h.
 * Twin: clrf/references/reference_splat.py bin_gaussians / rasterize / rasterize_backward.
 */
#include "common.h"
#include "splat.h"

#ifndef RENDER_DEPTH
#define RENDER_DEPTH 0
#endif
#ifndef ABSGRAD
#define ABSGRAD 0
#endif

__kernel void splat_count(const int n, __global const int *rect, __global int *counts) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int4 r = vload4(i, rect);
    counts[i] = (r.z - r.x) * (r.w - r.y);
}

__kernel void splat_emit(const int n, __global const int *rect, __global const float *depth,
                         __global const int *offsets, const int ntx, __global ulong *keys,
                         __global int *ids) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int4 r = vload4(i, rect);
    const ulong dbits = (ulong)as_uint(depth[i]);
    int k = offsets[i];
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

/* Chunk binning (the CPU shape's binning, clrf/splat/raster.py): the same per-tile lists as
 * count / scan / emit / sort / ranges above, without sorting the pairs. The host sorts the
 * Gaussians by depth (a stable radix sort of their depth bits, cl/sort.cl: n items, not
 * n_pairs) and cuts that order into nchunks contiguous chunks of `chunk` Gaussians, one
 * work-item a chunk. Tile binning is then one stable counting sort with the tiles as buckets:
 *   splat_chunk_count    cc[c][t] = Gaussians of chunk c that cover tile t (each work-item
 *                        writes only its own row of cc: no atomics, no shared cache lines
 *                        but at the rows' ends)
 *   splat_chunk_totals   counts[t] = sum over c of cc[c][t]
 *   (scan)               tile offsets [ntiles + 1] (int32, exclusive), the pair total
 *   splat_chunk_cursors  cc[c][t] = offsets[t] + sum over c' < c of cc[c'][t] (in place), and
 *                        ranges [ntiles, 2] ([0, 0) for an empty tile)
 *   splat_chunk_fill     chunk c appends its Gaussians, in order, at cc[c][t]++ of each tile t
 *                        of their rects (row-major)
 * A tile's list is then front to back, equal depths in ascending id, as the pair sort leaves
 * it. The work is O(n + pairs), not O(tile rows x n). */
__kernel void splat_chunk_count(const int n, const int chunk, const int nchunks,
                                __global const int *order, __global const int *rect,
                                const int ntx, const int ntiles, __global int *cc) {
    const int c = get_global_id(0);
    if (c >= nchunks) return;
    __global int *h = cc + (size_t)c * ntiles;
    for (int t = 0; t < ntiles; ++t) h[t] = 0;
    const int lo = min(n, c * chunk), hi = min(n, lo + chunk);
    for (int j = lo; j < hi; ++j) {
        const int4 r = vload4(order[j], rect);
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) h[ty * ntx + tx] += 1;
    }
}

__kernel void splat_chunk_totals(const int ntiles, const int nchunks, __global const int *cc,
                                 __global int *counts) {
    const int t = get_global_id(0);
    if (t >= ntiles) return;
    int s = 0;
    for (int c = 0; c < nchunks; ++c) s += cc[(size_t)c * ntiles + t];
    counts[t] = s;
}

__kernel void splat_chunk_cursors(const int ntiles, const int nchunks, __global int *cc,
                                  __global const int *offsets, __global int *ranges) {
    const int t = get_global_id(0);
    if (t >= ntiles) return;
    const int start = offsets[t], end = offsets[t + 1];
    int run = start;
    for (int c = 0; c < nchunks; ++c) {
        const int k = cc[(size_t)c * ntiles + t];
        cc[(size_t)c * ntiles + t] = run;
        run += k;
    }
    ranges[2 * t] = end > start ? start : 0;
    ranges[2 * t + 1] = end > start ? end : 0;
}

__kernel void splat_chunk_fill(const int n, const int chunk, const int nchunks,
                               __global const int *order, __global const int *rect,
                               const int ntx, const int ntiles, __global int *cc,
                               __global int *ids) {
    const int c = get_global_id(0);
    if (c >= nchunks) return;
    __global int *cur = cc + (size_t)c * ntiles;
    const int lo = min(n, c * chunk), hi = min(n, lo + chunk);
    for (int j = lo; j < hi; ++j) {
        const int g = order[j];
        const int4 r = vload4(g, rect);
        for (int ty = r.y; ty < r.w; ++ty)
            for (int tx = r.x; tx < r.z; ++tx) ids[cur[ty * ntx + tx]++] = g;
    }
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
                          __global int *out_n
#if RENDER_DEPTH
                          , __global const float *depth, __global float *out_depth
#endif
                          ) {
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
    float T = 1.0f, D = 0.0f;
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
#if RENDER_DEPTH
            l_col[lid] = (float4)(vload3(g, color), depth[g]);
#else
            l_col[lid] = (float4)(vload3(g, color), 0.0f);
#endif
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
            D += l_col[j].w * (alpha * T);
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
#if RENDER_DEPTH
    out_depth[p] = D;
#else
    (void)D;
#endif
}

__kernel __attribute__((reqd_work_group_size(TILE, TILE, 1)))
void splat_raster_backward(const int width, const int height, const int ntx,
                           __global const int *ranges, __global const int *ids,
                           __global const float *xy, __global const float *conic,
                           __global const float *opacity, __global const float *color,
                           const float4 bg, __global const float *out_T,
                           __global const int *out_n, __global const float *grad_rgb,
                           __global float *g_xy, __global float *g_conic,
                           __global float *g_opacity, __global float *g_color
#if ABSGRAD
                           , __global float *g_xy_abs
#endif
                           ) {
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
            const float gx = -dpow * (cop.x * d.x + cop.y * d.y);
            const float gy = -dpow * (cop.y * d.x + cop.z * d.y);
            atomic_add_f(&g_xy[2 * gi], gx);
            atomic_add_f(&g_xy[2 * gi + 1], gy);
#if ABSGRAD
            atomic_add_f(&g_xy_abs[2 * gi], fabs(gx));
            atomic_add_f(&g_xy_abs[2 * gi + 1], fabs(gy));
#endif
            atomic_add_f(&g_conic[3 * gi], -0.5f * dpow * d.x * d.x);
            atomic_add_f(&g_conic[3 * gi + 1], -dpow * d.x * d.y);
            atomic_add_f(&g_conic[3 * gi + 2], -0.5f * dpow * d.y * d.y);
        }
    }
}

/* ---- CPU shape: one work-item per tile, a tile row as one float vector ----------------------
 *
 * splat_raster_forward_rows / splat_raster_backward_rows compute what splat_raster_forward /
 * splat_raster_backward compute (the same alpha, skip, stop and n_contrib rules), shaped for a
 * CPU: PoCL vectorises only what the kernel vectorises itself, and a work-group per tile with a
 * data-dependent loop per pixel runs scalar there. Here one work-item owns a whole tile; a row
 * of TILE pixels is one floatTILE vector (TILE 4, 8 or 16: 16 is one AVX-512 register), and the
 * tile's list is walked once, each entry visiting only the rows where it can reach ALPHA_MIN:
 *
 *   for fixed d_y the power's largest value over d_x is -d_y^2 (AC - B^2) / (2A) (the conic is
 *   positive definite), so a row with -d_y^2 det / (2A) < log(ALPHA_MIN / o) - ROW_MARGIN has
 *   no pixel with alpha >= ALPHA_MIN: every pixel would skip the entry, and so does the row.
 *   The rows kept are the range |d_y| <= dmax that this gives (reached_rows); ROW_MARGIN
 *   (absolute, plus a relative part, on the power and on dmax) keeps float rounding on the
 *   safe side: a row is skipped only where the per-pixel test would skip every pixel.
 *   The same bound along x (-d_x^2 det / (2C)) gives the columns the splat can reach: an entry
 *   whose columns miss the tile's (its tile came from the square xy +- radius, wider than
 *   the ellipse where alpha reaches ALPHA_MIN) is skipped whole. And a row whose power stays
 *   below log(ALPHA_MIN / o), less the margin, in every lane is skipped before its exp.
 *   These bounds are computed once a splat (splat_pack_rows), not once a list entry: an entry
 *   loads one 64-byte record (position, conic, opacity, colour, bounds).
 *
 * The backward sums each entry's per-pixel terms over the tile in vector registers and adds
 * them once per gradient component and (tile, entry) instead of once per pixel, with no
 * atomics: into a copy of the gradients that only its work-item writes, the copies summed by
 * a second kernel (splat_raster_backward_rows below). The sums run in another order than the
 * work-group kernel's atomics: results agree to float32 rounding. Private state: 5 vectors a
 * row (T, C or S, and the pixel's list position).
 */
#if TILE == 4 || TILE == 8 || TILE == 16
#define SPLAT_ROWS 1
#define VF CONCAT(float, TILE)
#define VI CONCAT(int, TILE)
#define CONCAT(a, b) CONCAT_(a, b)
#define CONCAT_(a, b) a##b
#define VLOAD CONCAT(vload, TILE)
#define VLOADI CONCAT(vload, TILE)
#define VSTORE CONCAT(vstore, TILE)
#define VSTOREI CONCAT(vstore, TILE)
#define ZERO ((VF)(0.0f))
#define ROW_MARGIN 1e-3f
#define NGRAD (9 + 2 * ABSGRAD)   /* gradient floats a Gaussian in the backward's copies */

/* The lanes' x offsets 0.5, 1.5, ... as a vector. */
CLRF_INLINE VF lane_centres(void) {
#if TILE == 4
    return (VF)(0.5f, 1.5f, 2.5f, 3.5f);
#elif TILE == 8
    return (VF)(0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f);
#else
    return (VF)(0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f, 8.5f, 9.5f, 10.5f, 11.5f,
                12.5f, 13.5f, 14.5f, 15.5f);
#endif
}

CLRF_INLINE float hsum(VF v) {
#if TILE == 16
    float8 a = v.lo + v.hi;
    float4 b = a.lo + a.hi;
#elif TILE == 8
    float4 b = v.lo + v.hi;
#else
    float4 b = v;
#endif
    float2 c = b.lo + b.hi;
    return c.x + c.y;
}

/* any() / all() of a lane mask without branches: the builtins compile (PoCL 3.1, LLVM 15) to a
 * chain of one test and branch per lane pair, data-dependent branches that mispredict in the
 * inner loop; an OR / AND tree over the halves is a few shuffles and one test. */
CLRF_INLINE int any_lane(const VI v) {
#if TILE == 16
    const int8 a = v.lo | v.hi;
    const int4 b = a.lo | a.hi;
#elif TILE == 8
    const int4 b = v.lo | v.hi;
#else
    const int4 b = v;
#endif
    const int2 c = b.lo | b.hi;
    return (c.x | c.y) < 0;
}

CLRF_INLINE int all_lane(const VI v) {
#if TILE == 16
    const int8 a = v.lo & v.hi;
    const int4 b = a.lo & a.hi;
#elif TILE == 8
    const int4 b = v.lo & v.hi;
#else
    const int4 b = v;
#endif
    const int2 c = b.lo & b.hi;
    return (c.x & c.y) < 0;
}

/* splat_pack_rows: each splat's record for the row kernels, one 64-byte line [n, 16]: x, y,
 * conic A, B, C, opacity o, colour r, g, b, then what bounds its reach (so that a list entry
 * needs one load and no log, sqrt or division):
 *   s9  pthr: the power below which a lane cannot reach ALPHA_MIN, less the margin
 *       (-INFINITY: no test),
 *   sa  dmax_x and sb dmax_y: |dx| <= dmax_x, |dy| <= dmax_y hold wherever alpha can reach
 *       ALPHA_MIN (dmax_y^2 = 2 (margin - log(ALPHA_MIN / o)) A / det from the bound above,
 *       dmax_x likewise with C; INFINITY: no bound),
 *   sc  1 when the splat can reach ALPHA_MIN at all (o >= ALPHA_MIN), else 0,
 *   sd  its camera depth z (RENDER_DEPTH's forward composites it).
 * Degenerate conics get no bounds (every row and column); the margin keeps rounding on the
 * safe side. */
__kernel void splat_pack_rows(const int n, __global const float *xy,
                              __global const float *conic, __global const float *opacity,
                              __global const float *color, __global const float *depth,
                              __global float *rec) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float2 m = vload2(i, xy);
    const float3 q = vload3(i, conic);
    const float o = opacity[i];
    const float3 c = vload3(i, color);
    float pthr = -INFINITY, dmax_x = INFINITY, dmax_y = INFINITY;
    const float det = q.x * q.z - q.y * q.y;
    if (o >= ALPHA_MIN && q.x > 0.0f && q.z > 0.0f && det > 0.0f) {
        const float log_thr = log(ALPHA_MIN / o);
        const float margin = ROW_MARGIN * (1.0f + fabs(log_thr));
        pthr = log_thr - margin;
        const float reach = -log_thr + margin;   /* >= 0 */
        dmax_y = sqrt(2.0f * reach * (q.x / det)) * (1.0f + ROW_MARGIN) + ROW_MARGIN;
        dmax_x = sqrt(2.0f * reach * (q.z / det)) * (1.0f + ROW_MARGIN) + ROW_MARGIN;
    }
    vstore16((float16)(m.x, m.y, q.x, q.y, q.z, o, c.x, c.y, c.z, pthr, dmax_x, dmax_y,
                       o >= ALPHA_MIN ? 1.0f : 0.0f, depth[i], 0.0f, 0.0f), i, rec);
}

/* The rows [*r0, *r1) of the tile at (x0, y0) (rows x cols pixels) that record ``s``
 * (splat_pack_rows) can reach; 0 when none, or when its columns miss the tile's (the entry is
 * skipped whole: its tile came from the square xy +- radius, wider than the ellipse where
 * alpha reaches ALPHA_MIN), else 1. */
CLRF_INLINE int reached_rows(const float16 s, const int x0, const int y0, const int rows,
                             const int cols, int *r0, int *r1) {
    *r0 = 0;
    *r1 = rows;
    if (!(s.sc > 0.0f)) return 0;
    if (s.sa < 4.0f * TILE) {
        /* column c's centre is x0 + c + 0.5; some column must have |x - centre| <= dmax_x */
        const float lo = s.s0 - s.sa - (float)x0 - 0.5f, hi = s.s0 + s.sa - (float)x0 - 0.5f;
        if (!(hi >= 0.0f) || !(lo <= (float)(cols - 1))) return 0;
    }
    if (!(s.sb < 4.0f * TILE)) return rows > 0;   /* huge, or not finite: every row */
    /* row r's centre is y0 + r + 0.5; keep |y - centre| <= dmax_y */
    const float lo = s.s1 - s.sb - (float)y0 - 0.5f, hi = s.s1 + s.sb - (float)y0 - 0.5f;
    *r0 = clamp((int)ceil(lo), 0, rows);
    *r1 = clamp((int)floor(hi) + 1, *r0, rows);
    return *r0 < *r1;
}

/* The power of splat (mean, cop) per lane of a row: d = mean - pixel centre. */
CLRF_INLINE VF row_power(const VF dx, const float dy, const float4 cop) {
    return -0.5f * (cop.x * dx * dx + cop.z * dy * dy) - cop.y * dx * dy;
}

/* Per-lane alpha (0 where skipped) of splat cop at the lanes' powers. */
CLRF_INLINE VF row_alpha(const VF power, const float4 cop, VF *G_out, VF *raw_out) {
    const VF G = exp(power);
    const VF raw = cop.w * G;
    const VF alpha = fmin((VF)(ALPHA_MAX), raw);
    *G_out = G;
    *raw_out = raw;
    return select(alpha, (VF)(0.0f), power > 0.0f || alpha < ALPHA_MIN);
}

__kernel void splat_raster_forward_rows(const int width, const int height, const int ntx,
                                        const int ntiles, __global const int *ranges,
                                        __global const int *ids, __global const float *rec,
                                        const float4 bg,
                                        __global float *out_rgb, __global float *out_T,
                                        __global int *out_n
#if RENDER_DEPTH
                                        , __global float *out_depth
#endif
                                        ) {
    const int tile = get_global_id(0);
    if (tile >= ntiles) return;
    const int x0 = (tile % ntx) * TILE, y0 = (tile / ntx) * TILE;
    const int rows = min(TILE, height - y0), cols = min(TILE, width - x0);
    const VF xs = (float)x0 + lane_centres();
    const VI lanes_in = (VI)(cols) > CONCAT(convert_int, TILE)(lane_centres());
    VF T[TILE], Cr[TILE], Cg[TILE], Cb[TILE];
#if RENDER_DEPTH
    VF Dz[TILE];
#endif
    VI last[TILE], done[TILE];
    int alive = 0;   /* rows with a pixel still compositing */
    for (int r = 0; r < TILE; ++r) {
        T[r] = (VF)(1.0f);
        Cr[r] = Cg[r] = Cb[r] = (VF)(0.0f);
#if RENDER_DEPTH
        Dz[r] = (VF)(0.0f);
#endif
        last[r] = (VI)(0);
        done[r] = r < rows ? ~lanes_in : (VI)(-1);
        alive += r < rows && cols > 0;
    }
    const int start = ranges[2 * tile], end = ranges[2 * tile + 1];
    for (int k = start; k < end && alive > 0; ++k) {
        const float16 s = vload16(ids[k], rec);
        int r0, r1;
        if (!reached_rows(s, x0, y0, rows, cols, &r0, &r1)) continue;
        const float2 m = s.s01;
        const float4 cop = s.s2345;
        const float3 c = s.s678;
        const float pthr = s.s9;
        const VF dx = m.x - xs;
        const VI pos = (VI)(k - start + 1);
        for (int r = r0; r < r1; ++r) {
            if (all_lane(done[r])) continue;
            const float dy = m.y - ((float)(y0 + r) + 0.5f);
            const VF power = row_power(dx, dy, cop);
            if (!any_lane(power >= pthr)) continue;
            VF G, raw;
            const VF alpha = row_alpha(power, cop, &G, &raw);
            const VF nT = T[r] * (1.0f - alpha);
            const VI act = ~done[r] & (alpha != 0.0f);
            const VI stop = act & (nT < T_MIN);
            done[r] |= stop;
            const VI use = act & ~stop;
            const VF w = select(ZERO, alpha * T[r], use);   /* 0: no change (c is finite) */
            Cr[r] += c.x * w;
            Cg[r] += c.y * w;
            Cb[r] += c.z * w;
#if RENDER_DEPTH
            Dz[r] += s.sd * w;
#endif
            T[r] = select(T[r], nT, use);
            last[r] = select(last[r], pos, use);
            if (any_lane(stop) && all_lane(done[r])) --alive;
        }
    }
    for (int r = 0; r < rows; ++r) {
        const int p0 = (y0 + r) * width + x0;
        float rr[TILE], gg[TILE], bb[TILE], tt[TILE];
        int nn[TILE];
        VSTORE(Cr[r] + T[r] * bg.x, 0, rr);
        VSTORE(Cg[r] + T[r] * bg.y, 0, gg);
        VSTORE(Cb[r] + T[r] * bg.z, 0, bb);
        VSTORE(T[r], 0, tt);
        VSTOREI(last[r], 0, nn);
        for (int i = 0; i < cols; ++i) {
            vstore3((float3)(rr[i], gg[i], bb[i]), p0 + i, out_rgb);
            out_T[p0 + i] = tt[i];
            out_n[p0 + i] = nn[i];
        }
#if RENDER_DEPTH
        VSTORE(Dz[r], 0, tt);
        for (int i = 0; i < cols; ++i) out_depth[p0 + i] = tt[i];
#endif
    }
}

/* One tile of the backward: its entries' per-pixel terms summed over the tile in vector
 * registers, then added to the Gaussians' rows of ``acc`` ([n, NGRAD]: dL/d(x, y), conic A, B, C,
 * opacity, colour r, g, b, then with ABSGRAD |dL/dx|, |dL/dy|), which no other work-item
 * writes (splat_raster_backward_rows). */
CLRF_INLINE void backward_rows_tile(const int tile, const int width, const int height,
                                    const int ntx, __global const int *ranges,
                                    __global const int *ids, __global const float *rec,
                                    const float4 bg, __global const float *out_T,
                                    __global const int *out_n,
                                    __global const float *grad_rgb, __global float *acc) {
    const int x0 = (tile % ntx) * TILE, y0 = (tile / ntx) * TILE;
    const int rows = min(TILE, height - y0), cols = min(TILE, width - x0);
    const VF xs = (float)x0 + lane_centres();
    VF T[TILE], Sr[TILE], Sg[TILE], Sb[TILE], gr[TILE], gg[TILE], gb[TILE];
    VI npix[TILE];
    int rtop[TILE];   /* the largest n_contrib of each row */
    int top = 0;      /* and of the tile */
    for (int r = 0; r < TILE; ++r) {
        rtop[r] = 0;
        T[r] = (VF)(1.0f);
        Sr[r] = (VF)(bg.x);
        Sg[r] = (VF)(bg.y);
        Sb[r] = (VF)(bg.z);
        gr[r] = gg[r] = gb[r] = (VF)(0.0f);
        npix[r] = (VI)(0);
        if (r >= rows) continue;
        const int p0 = (y0 + r) * width + x0;
        float tt[TILE], r3[TILE], g3[TILE], b3[TILE];
        int nn[TILE];
        for (int i = 0; i < TILE; ++i) {   /* lanes past the image: T 1, no entry, no gradient */
            const int in = i < cols;
            tt[i] = in ? out_T[p0 + i] : 1.0f;
            nn[i] = in ? out_n[p0 + i] : 0;
            r3[i] = in ? grad_rgb[3 * (p0 + i)] : 0.0f;
            g3[i] = in ? grad_rgb[3 * (p0 + i) + 1] : 0.0f;
            b3[i] = in ? grad_rgb[3 * (p0 + i) + 2] : 0.0f;
            rtop[r] = max(rtop[r], nn[i]);
        }
        top = max(top, rtop[r]);
        T[r] = VLOAD(0, tt);
        npix[r] = VLOADI(0, nn);
        gr[r] = VLOAD(0, r3);
        gg[r] = VLOAD(0, g3);
        gb[r] = VLOAD(0, b3);
    }
    const int start = ranges[2 * tile];
    for (int k = start + top - 1; k >= start; --k) {
        const int g = ids[k];
        const float16 s = vload16(g, rec);
        int r0, r1;
        if (!reached_rows(s, x0, y0, rows, cols, &r0, &r1)) continue;
        const float2 m = s.s01;
        const float4 cop = s.s2345;
        const float3 c = s.s678;
        const float pthr = s.s9;
        const VF dx = m.x - xs;
        const VI pos = (VI)(k - start);
        VF s_cr = ZERO, s_cg = ZERO, s_cb = ZERO, s_o = ZERO, s_x = ZERO, s_y = ZERO;
        VF s_a = ZERO, s_b = ZERO, s_c = ZERO;
#if ABSGRAD
        VF s_ax = ZERO, s_ay = ZERO;
#endif
        int touched = 0;
        const int kpos = k - start;
        for (int r = r0; r < r1; ++r) {
            if (kpos >= rtop[r]) continue;   /* past every pixel's last entry in this row */
            const float dy = m.y - ((float)(y0 + r) + 0.5f);
            const VF power = row_power(dx, dy, cop);
            if (!any_lane(power >= pthr)) continue;
            VF G, raw;
            const VF alpha0 = row_alpha(power, cop, &G, &raw);
            const VI act = (pos < npix[r]) & (alpha0 != 0.0f);
            if (!any_lane(act)) continue;
            touched = 1;
            /* inactive lanes get alpha 0 and dpow 0, so that they change nothing and add
             * exact zeros (every factor below is finite: the conic is bounded by the
             * dilation, dx and dy are differences of finite positions) */
            const VF alpha = select(ZERO, alpha0, act);
            const VF Tk = T[r] / (1.0f - alpha);
            T[r] = Tk;
            const VF dalpha = Tk * (gr[r] * (c.x - Sr[r]) + gg[r] * (c.y - Sg[r]) +
                                    gb[r] * (c.z - Sb[r]));
            Sr[r] += alpha * (c.x - Sr[r]);
            Sg[r] += alpha * (c.y - Sg[r]);
            Sb[r] += alpha * (c.z - Sb[r]);
            const VF w = Tk * alpha;
            s_cr += w * gr[r];
            s_cg += w * gg[r];
            s_cb += w * gb[r];
            const VI free = act & (raw < ALPHA_MAX);
            const VF dG = select(ZERO, G * dalpha, free);
            const VF dpow = cop.w * dG;
            s_o += dG;
            const VF gx = dpow * (cop.x * dx + cop.y * dy);
            const VF gy = dpow * (cop.y * dx + cop.z * dy);
            s_x -= gx;
            s_y -= gy;
#if ABSGRAD
            s_ax += fabs(gx);
            s_ay += fabs(gy);
#endif
            s_a -= 0.5f * dpow * dx * dx;
            s_b -= dpow * dx * dy;
            s_c -= 0.5f * dpow * dy * dy;
        }
        if (!touched) continue;
        __global float *a = acc + (size_t)g * NGRAD;
        a[0] += hsum(s_x);
        a[1] += hsum(s_y);
        a[2] += hsum(s_a);
        a[3] += hsum(s_b);
        a[4] += hsum(s_c);
        a[5] += hsum(s_o);
        a[6] += hsum(s_cr);
        a[7] += hsum(s_cg);
        a[8] += hsum(s_cb);
#if ABSGRAD
        a[9] += hsum(s_ax);
        a[10] += hsum(s_ay);
#endif
    }
}

/* The backward over every tile, without atomics: work-item w of ``copies`` zeroes its own
 * copy w of the gradients ([copies, n, NGRAD], backward_rows_tile's layout) and adds into it
 * the tiles w, w + copies, w + 2 copies, ...; splat_backward_rows_sum then adds the copies up
 * in the order 0, 1, ... Each copy is written by one work-item alone, the sum runs in a later
 * launch, and which tiles a copy holds does not depend on scheduling: the gradients are the
 * same from run to run (float atomics add in whatever order the threads reach them). */
__kernel void splat_raster_backward_rows(const int width, const int height, const int ntx,
                                         const int ntiles, __global const int *ranges,
                                         __global const int *ids, __global const float *rec,
                                         const float4 bg,
                                         __global const float *out_T, __global const int *out_n,
                                         __global const float *grad_rgb, const int n,
                                         const int copies, __global float *acc) {
    const int w = get_global_id(0);
    if (w >= copies) return;
    __global float *mine = acc + (size_t)w * (size_t)n * NGRAD;
    const size_t len = (size_t)n * NGRAD;
    for (size_t i = 0; i < len; ++i) mine[i] = 0.0f;
    for (int tile = w; tile < ntiles; tile += copies)
        backward_rows_tile(tile, width, height, ntx, ranges, ids, rec, bg, out_T, out_n,
                           grad_rgb, mine);
}

/* Gaussian i's gradients: the sum of its rows of the ``copies`` copies, in copy order. */
__kernel void splat_backward_rows_sum(const int n, const int copies,
                                      __global const float *acc,
                                      __global float *g_xy, __global float *g_conic,
                                      __global float *g_opacity, __global float *g_color
#if ABSGRAD
                                      , __global float *g_xy_abs
#endif
                                      ) {
    const int i = get_global_id(0);
    if (i >= n) return;
    float t[NGRAD];
    for (int j = 0; j < NGRAD; ++j) t[j] = 0.0f;
    for (int c = 0; c < copies; ++c) {
        __global const float *a = acc + ((size_t)c * (size_t)n + (size_t)i) * NGRAD;
        for (int j = 0; j < NGRAD; ++j) t[j] += a[j];
    }
    vstore2((float2)(t[0], t[1]), i, g_xy);
    vstore3((float3)(t[2], t[3], t[4]), i, g_conic);
    g_opacity[i] = t[5];
    vstore3((float3)(t[6], t[7], t[8]), i, g_color);
#if ABSGRAD
    vstore2((float2)(t[9], t[10]), i, g_xy_abs);
#endif
}
#endif /* TILE 4, 8 or 16 */
