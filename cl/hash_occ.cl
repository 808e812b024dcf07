/* hash_occ.cl: the hash model's occupancy grid and the sample compaction that uses it.
 *
 * Occupancy grid: R^3 cells over the scene box [lo, lo + 1/inv_ext] (cell c = cx + R (cy + R cz),
 * cell of a point: floor(u R) with u the point's box coordinate). Per cell a float `ema`:
 *   ema < 0  : never measured (the initial state): OCCUPIED, so training starts with every cell
 *              in play and an empty grid cannot stall it;
 *   ema >= 0 : a running max-decay estimate of the density, updated every few steps by
 *              occ_decay (ema *= decay for measured cells) and occ_max (ema = max(ema, sigma)
 *              at freshly measured cells: a random point in each of a random set of cells).
 * occ_threshold turns it into the byte grid the sampler reads: occ = ema < 0 || ema > thr.
 *
 * Compaction: the stratified samples of a batch (rows i K + k of xyz [n K, 3]) that lie inside
 * the box in an occupied cell are listed in ray order: occ_count counts them per ray, the host
 * turns the counts into offsets (an exclusive prefix sum) and occ_compact writes the global
 * sample indices idx [M]. Only those M samples go through the encoding and the MLPs; the
 * others have sigma = 0 (they add nothing to the composite) and get no gradient.
 *
 * Defines read: none.
 */
#include "common.h"

/* Cell index of point xyz, or -1 outside the closed box (or NaN). */
CLRF_INLINE int occ_cell(const float3 xyz, const float4 lo, const float4 inv_ext, const int R) {
    const float3 u = (xyz - lo.xyz) * inv_ext.xyz;
    if (!(u.x >= 0.0f && u.y >= 0.0f && u.z >= 0.0f && u.x <= 1.0f && u.y <= 1.0f
          && u.z <= 1.0f))
        return -1;
    const int3 c = min(convert_int3(u * (float)R), (int3)(R - 1));
    return c.x + R * (c.y + R * c.z);
}

CLRF_INLINE int occ_live(__global const float *xyz, const size_t s, const float4 lo,
                         const float4 inv_ext, const int R, __global const uchar *occ) {
    const int c = occ_cell(load3(xyz, s), lo, inv_ext, R);
    return c >= 0 && occ[c];
}

/* counts [n]: live samples of each ray (one work-item per ray). */
__kernel void occ_count(const int n, const int K, __global const float *xyz, const float4 lo,
                        const float4 inv_ext, const int R, __global const uchar *occ,
                        __global int *counts) {
    const int i = get_global_id(0);
    if (i >= n) return;
    int m = 0;
    for (int k = 0; k < K; ++k) m += occ_live(xyz, (size_t)i * K + k, lo, inv_ext, R, occ);
    counts[i] = m;
}

/* idx [M]: the live samples' global indices, ray i's from offsets[i] on, in sample order. */
__kernel void occ_compact(const int n, const int K, __global const float *xyz, const float4 lo,
                          const float4 inv_ext, const int R, __global const uchar *occ,
                          __global const int *offsets, __global int *idx) {
    const int i = get_global_id(0);
    if (i >= n) return;
    int o = offsets[i];
    for (int k = 0; k < K; ++k) {
        const size_t s = (size_t)i * K + k;
        if (occ_live(xyz, s, lo, inv_ext, R, occ)) idx[o++] = (int)s;
    }
}

/* dst[j, :] = src[idx[j], :] for rows of D floats (gather of the live samples). */
__kernel void gather_rows(const int m, const int D, __global const int *idx,
                          __global const float *src, __global float *dst) {
    const int j = get_global_id(0);
    if (j >= m) return;
    for (int c = 0; c < D; ++c) dst[(size_t)j * D + c] = src[(size_t)idx[j] * D + c];
}

/* dst[idx[j], :] = src[j, :] (scatter back; dst was cleared by the host). */
__kernel void scatter_rows(const int m, const int D, __global const int *idx,
                           __global const float *src, __global float *dst) {
    const int j = get_global_id(0);
    if (j >= m) return;
    for (int c = 0; c < D; ++c) dst[(size_t)idx[j] * D + c] = src[(size_t)j * D + c];
}

/* m random cells (uniform01 of key) and a uniformly jittered point in each: cells [m],
 * xyz [m, 3] (world). */
__kernel void occ_points(const int m, const uint key, const int R, const float4 lo,
                         const float4 ext, __global int *cells, __global float *xyz) {
    const int j = get_global_id(0);
    if (j >= m) return;
    const uint R3 = (uint)R * R * R;
    const uint c = min((uint)(uniform01(key, 4u * j) * (float)R3), R3 - 1u);
    const float3 ijk = (float3)(c % R, (c / R) % R, c / (R * R));
    const float3 jit = (float3)(uniform01(key, 4u * j + 1u), uniform01(key, 4u * j + 2u),
                                uniform01(key, 4u * j + 3u));
    const float3 p = lo.xyz + (ijk + jit) / (float)R * ext.xyz;
    cells[j] = (int)c;
    xyz[3 * j] = p.x;
    xyz[3 * j + 1] = p.y;
    xyz[3 * j + 2] = p.z;
}

/* ema *= decay where measured (ema >= 0). */
__kernel void occ_decay(const int nc, const float decay, __global float *ema) {
    const int c = get_global_id(0);
    if (c >= nc) return;
    const float e = ema[c];
    if (e >= 0.0f) ema[c] = e * decay;
}

/* ema[cells[j]] = max(ema, sigma[j]) (a never-measured cell takes sigma; NaN / negative
 * sigma count as 0). atomic_max on the bit pattern: two points may share a cell. */
__kernel void occ_max(const int m, __global const int *cells, __global const float *sigma,
                      __global float *ema) {
    const int j = get_global_id(0);
    if (j >= m) return;
    const float s = sigma[j];
    atomic_max_nonneg_f(ema + cells[j], isnan(s) ? 0.0f : s);
}

/* occ[c] = ema[c] < 0 || ema[c] > thr. */
__kernel void occ_threshold(const int nc, const float thr, __global const float *ema,
                            __global uchar *occ) {
    const int c = get_global_id(0);
    if (c >= nc) return;
    const float e = ema[c];
    occ[c] = (e < 0.0f || e > thr) ? 1 : 0;
}

/* sigma[j] = 0 where xyz[j] is outside the box (export: the field as the renderer sees it). */
__kernel void zero_outside(const int m, __global const float *xyz, const float4 lo,
                           const float4 inv_ext, __global float *sigma) {
    const int j = get_global_id(0);
    if (j >= m) return;
    if (occ_cell(load3(xyz, j), lo, inv_ext, 1) < 0) sigma[j] = 0.0f;
}
