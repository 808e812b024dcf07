/* grid_ops.cl: regularisers and structure changes of a sparse grid.
 *
 * Layout as in grid_render.cl: links int32 [RX,RY,RZ] (C order, cell = (x*RY + y)*RZ + z) into
 * rows; a parameter buffer of width D is float [N, D] (density: D = 1, SH: D = SH_DIM).
 *
 * tv_grad: total variation over a window of n_cells consecutive cells starting at `start`
 *   (wrapping around), svox2-style. For an allocated cell with value v and +x/+y/+z neighbour
 *   values v_a, d_a = v_a - v, per column j:  TV = sqrt(TV_EPS + dx^2 + dy^2 + dz^2)
 *   (evaluated with power-of-two rescaling above |d| = 2^60; a d that overflows float32 is
 *   clamped to +-FLT_MAX).
 *   A neighbour outside the grid counts as v (no gradient); an unallocated one as 0 if
 *   empty_is_zero (density: pulls surfaces' outsides down) else as v (SH). Gradients times
 *   `scale` are added atomically to the cell and its allocated neighbours, which are marked
 *   touched. With lambda_sparsity > 0 (density only) the Cauchy prior
 *   lambda * log(1 + 2 sigma^2) adds lambda * 4 sigma / (1 + 2 sigma^2) to each window cell.
 * threshold_keep / dilate_keep: pruning masks (keep rows whose max rendering weight or density
 *   reaches a threshold, then also every allocated row within one voxel of a kept one).
 * resample_flags / resample_fill: a new grid of another (or the same) resolution over the same
 *   box; each new voxel takes the trilinear interpolation (march.h conventions) of the kept
 *   old rows at its centre, and is allocated iff a kept old row has weight > 0 there.
 *   With the same resolution this is exactly pruning.
 *
 * tv_grad with BRICK 1 (one brick of a distributed grid, clrf/grid/bricks.py): links is the
 *   brick's array (its voxels from blo plus the one-voxel halo, shape reso); the work-items
 *   cover the brick's own voxels (bown per axis) and keep those whose whole-grid cell index
 *   (greso) lies in the window, so the bricks together do exactly the single grid's window;
 *   gradients for halo neighbours go to the halo rows (summed over holders by the host).
 *
 * Defines read: SH_DEGREE (march.h, unused here), TV_EPS, BRICK. Mirrored by reference.tv_grad,
 * reference.prune_keep, reference.resample.
 */
#include "march.h"

#ifndef TV_EPS
#define TV_EPS 1e-9f  /* inside the TV square root: keeps the gradient finite on flat regions */
#endif

__kernel void tv_grad(const int n_cells, const int start, const int4 reso,
                      __global const int *links, __global const float *data, const int D,
                      __global float *grad, __global uchar *touched, const float scale,
                      const int empty_is_zero, const float lambda_sparsity
#if BRICK
                      , const int4 greso, const int4 blo, const int4 bown
#endif
                      ) {
    const int i = get_global_id(0);
#if BRICK
    if (i >= bown.x * bown.y * bown.z) return;
    const int z = i % bown.z, y = (i / bown.z) % bown.y, x = i / (bown.y * bown.z);
    const long gtotal = (long)greso.x * greso.y * greso.z;
    const long gcell = ((long)(x + blo.x) * greso.y + (y + blo.y)) * greso.z + (z + blo.z);
    if ((gcell - start + gtotal) % gtotal >= n_cells) return;
    const int cell = cell_of(x, y, z, reso);
#else
    if (i >= n_cells) return;
    const int total = reso.x * reso.y * reso.z;
    const int cell = (int)(((long)start + i) % total);
    const int z = cell % reso.z, y = (cell / reso.z) % reso.y, x = cell / (reso.y * reso.z);
#endif
    const int k = links[cell];
    if (k < 0) return;
    /* neighbour rows: >= 0 allocated, -1 unallocated, -2 outside the grid */
    int kn[3];
    kn[0] = x + 1 < reso.x ? max(links[cell_of(x + 1, y, z, reso)], -1) : -2;
    kn[1] = y + 1 < reso.y ? max(links[cell_of(x, y + 1, z, reso)], -1) : -2;
    kn[2] = z + 1 < reso.z ? max(links[cell_of(x, y, z + 1, reso)], -1) : -2;
    for (int j = 0; j < D; ++j) {
        const float v = data[(size_t)k * D + j];
        float d[3];
        for (int a = 0; a < 3; ++a) {
            float va = v;
            if (kn[a] >= 0) va = data[(size_t)kn[a] * D + j];
            else if (kn[a] == -1 && empty_is_zero) va = 0.0f;
            d[a] = clamp(va - v, -FLT_MAX, FLT_MAX);   /* opposite-sign values near FLT_MAX */
        }
        /* d^2 overflows for |d| > 1.8e19 (r = inf, s = 0: the gradient vanished, or was
         * NaN = inf * 0 where d itself overflowed). Above 2^60, d and TV_EPS are scaled by
         * 2^-sc2 first (exact); d[a] * s is then the same scale * d / r. Below 2^60 sc2 = 0. */
        const float m = fmax(fabs(d[0]), fmax(fabs(d[1]), fabs(d[2])));
        const int sc2 = m > 0x1p60f ? ilogb(m) : 0;
        for (int a = 0; a < 3; ++a) d[a] = ldexp(d[a], -sc2);
        const float r = sqrt(ldexp(TV_EPS, -2 * sc2) + d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
        const float s = scale / r;
        const float gc = -(d[0] + d[1] + d[2]) * s;
        if (gc != 0.0f) atomic_add_f(grad + (size_t)k * D + j, gc);
        for (int a = 0; a < 3; ++a)
            if (kn[a] >= 0 && d[a] != 0.0f) atomic_add_f(grad + (size_t)kn[a] * D + j, d[a] * s);
    }
    if (lambda_sparsity > 0.0f && D == 1) {
        const float sg = data[k];
        const float g = lambda_sparsity * 4.0f * sg / (1.0f + 2.0f * sg * sg);
        if (g != 0.0f && isfinite(g)) atomic_add_f(grad + k, g);
    }
    touched[k] = 1;
    for (int a = 0; a < 3; ++a)
        if (kn[a] >= 0) touched[kn[a]] = 1;
}

__kernel void threshold_keep(const int n_rows, __global const float *maxw,
                             __global const float *density, const float weight_thresh,
                             const float density_thresh, __global uchar *keep) {
    const int k = get_global_id(0);
    if (k >= n_rows) return;
    keep[k] = (maxw[k] >= weight_thresh) || (density[k] >= density_thresh);
}

__kernel void dilate_keep(const int4 reso, __global const int *links,
                          __global const uchar *keep_in, __global uchar *keep_out) {
    const int cell = get_global_id(0);
    if (cell >= reso.x * reso.y * reso.z) return;
    const int k = links[cell];
    if (k < 0) return;
    const int z = cell % reso.z, y = (cell / reso.z) % reso.y, x = cell / (reso.y * reso.z);
    uchar out = 0;
    for (int dx = -1; dx <= 1 && !out; ++dx)
        for (int dy = -1; dy <= 1 && !out; ++dy)
            for (int dz = -1; dz <= 1; ++dz) {
                const int xx = x + dx, yy = y + dy, zz = z + dz;
                if (xx < 0 || yy < 0 || zz < 0 || xx >= reso.x || yy >= reso.y || zz >= reso.z)
                    continue;
                const int kn = links[cell_of(xx, yy, zz, reso)];
                if (kn >= 0 && keep_in[kn]) { out = 1; break; }
            }
    keep_out[k] = out;
}

/* Centre of new voxel `cell` in old box units, and its interpolation corners (kept rows only). */
inline int resample_corners(int cell, int4 new_reso, int4 old_reso, __global const int *links,
                            __global const uchar *keep, lerp_t *L) {
    const int z = cell % new_reso.z, y = (cell / new_reso.z) % new_reso.y;
    const int x = cell / (new_reso.y * new_reso.z);
    const float3 p = (float3)(((float)x + 0.5f) * old_reso.x / new_reso.x,
                              ((float)y + 0.5f) * old_reso.y / new_reso.y,
                              ((float)z + 0.5f) * old_reso.z / new_reso.z);
    lerp_setup(p, old_reso, links, L);
    int any = 0;
    for (int c = 0; c < 8; ++c) {
        if (L->idx[c] >= 0 && !keep[L->idx[c]]) L->idx[c] = -1;
        any |= (L->idx[c] >= 0 && L->w[c] > 0.0f);
    }
    return any;
}

__kernel void resample_flags(const int4 new_reso, const int4 old_reso,
                             __global const int *old_links, __global const uchar *keep,
                             __global int *flags) {
    const int cell = get_global_id(0);
    if (cell >= new_reso.x * new_reso.y * new_reso.z) return;
    lerp_t L;
    flags[cell] = resample_corners(cell, new_reso, old_reso, old_links, keep, &L);
}

__kernel void resample_fill(const int4 new_reso, const int4 old_reso,
                            __global const int *old_links, __global const uchar *keep,
                            __global const int *new_links, const int D,
                            __global const float *old_density, __global const float *old_sh,
                            __global float *new_density, __global float *new_sh) {
    const int cell = get_global_id(0);
    if (cell >= new_reso.x * new_reso.y * new_reso.z) return;
    const int kn = new_links[cell];
    if (kn < 0) return;
    lerp_t L;
    resample_corners(cell, new_reso, old_reso, old_links, keep, &L);
    float dens = 0.0f;
    for (int j = 0; j < D; ++j) new_sh[(size_t)kn * D + j] = 0.0f;
    for (int c = 0; c < 8; ++c) {
        const int k = L.idx[c];
        if (k < 0 || L.w[c] == 0.0f) continue;
        dens += L.w[c] * old_density[k];
        for (int j = 0; j < D; ++j)
            new_sh[(size_t)kn * D + j] += L.w[c] * old_sh[(size_t)k * D + j];
    }
    new_density[kn] = dens;
}
