/* hash_occ.cl: the hash model's occupancy grid.
 *
 * Occupancy grid: R^3 cells over the scene box [lo, lo + 1/inv_ext] (cell c = cx + R (cy + R cz),
 * cell of a point: floor(u R) with u the point's box coordinate). Per cell a float `ema`:
 *   ema < 0  : never measured (the initial state): OCCUPIED, so training starts with every cell
 *              in play and an empty grid cannot stall it;
 *   ema >= 0 : a running max-decay estimate of the density, updated every few steps by
 *              occ_decay (ema *= decay for measured cells) and occ_max (ema = max(ema, sigma)
 *              at freshly measured cells: a random point in each of the cells measured).
 * Cells are measured in a sweep: update u measures positions start .. start + m - 1 (mod R^3)
 * of the order  c(p) = p * stride mod R^3  (stride odd and coprime with R^3, so the order is a
 * permutation that scatters neighbouring positions over the grid), so R^3 / m updates measure
 * every cell once (uniformly random cells would leave 1/e of them unmeasured after as many).
 * occ_threshold turns it into the byte grid the sampler reads: occ = ema < 0 || ema > thr.
 *
 * The sampler that reads the byte grid is cl/hash_march.cl; the cell of a point is hash_occ.h's.
 *
 * Defines read: none.
 */
#include "hash_occ.h"

/* The cells at sweep positions start .. start + m - 1 (mod R^3; see above) and a uniformly
 * jittered point in each (uniform01 of key): cells [m], xyz [m, 3] (world). */
__kernel void occ_points(const int m, const uint key, const uint start, const uint stride,
                         const int R, const float4 lo, const float4 ext, __global int *cells,
                         __global float *xyz) {
    const int j = get_global_id(0);
    if (j >= m) return;
    const uint R3 = (uint)R * R * R;
    const ulong pos = ((ulong)start + (ulong)j) % R3;
    const uint c = (uint)(pos * stride % R3);
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
