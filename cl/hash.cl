/* hash.cl: multiresolution hash encoding (L levels of F features, T table rows per level),
 * forward and backward, and the SH encoding of view directions for the hash model's colour MLP.
 *
 * Normalised position. For a point x [3] in a box [lo, lo + 1/inv_ext] (host arguments):
 *   u = clamp((x - lo) * inv_ext, 0, 1)            (float32, one rounding per operation)
 * Points outside the box are CLAMPED to its surface: they read (and train) the features of the
 * nearest boundary point. The model never feeds them (samples outside the box are empty space in
 * the occupancy grid); clamping keeps the kernel total for any finite input (NaN -> 0).
 *
 * Level l (l = 0..L-1) has resolution N_l = floor(N_min b^l), b = exp((ln N_max - ln N_min)/(L-1))
 * (host: clrf.hash.encoding.level_resolutions, float64; passed as res [L]). Its grid has N_l
 * cells and N_l + 1 vertices per axis:
 *   p = u N_l (float32),  i = min(floor(p), N_l - 1) (per axis),  w = p - i in [0, 1] (exact)
 * so u = 1 lands on the last cell with w = 1. Vertex v = i + c (c in {0,1}^3) has table row
 *   dense  ((N_l + 1)^3 <= T):  v_x + (N_l + 1) (v_y + (N_l + 1) v_z)
 *   hashed (otherwise):         (v_x * 1  ^  v_y * 2654435761  ^  v_z * 805459861) mod T
 *                               (uint32 arithmetic, wrapping; T a power of two)
 * Feature f of level l: enc[l F + f] = sum_c prod_a (c_a ? w_a : 1 - w_a) table[l, row_c, f]
 * (trilinear; the 8 weights sum to 1).
 *
 * Memory layout: x [n, 3]; table and grad [L, T, F] row-major (level, row, feature);
 * enc and dL/denc [n, L F] row-major (the MLP's input rows).
 *
 * Backward: dL/dtable[l, row_c, f] += weight_c dL/denc[l F + f], ADDED to grad (collisions and
 * shared vertices sum). Two accumulation paths, chosen like the grid's (clrf/tuning.py
 * grad_slots: 0 on GPUs, > 0 on CPUs):
 *   HASH_GRAD_OWNED 0 (GPUs): one work-item per (point, level), float atomics (atomic_add_f);
 *   HASH_GRAD_OWNED 1 (CPUs): one work-item per level, which owns that level's table and adds
 *     every point into it with plain adds. Levels never share entries, so this is conflict-free
 *     by construction: no atomics and, unlike the grid's per-compute-unit copies, no scratch
 *     copy of the tables and no reduction pass (16 levels keep up to 16 cores busy).
 *
 * Spatial derivative (hash_dx, for pose refinement): dL/dx [n, 3] of each point from dL/denc,
 * OVERWRITTEN (one work-item per point, summing its levels). In the cell of level l the
 * encoding is multilinear in w, so with s_c = sum_f dL/denc[l F + f] table[l, row_c, f]:
 *   dL/dw_a = sum_c (c_a ? 1 : -1) prod_{b != a} (c_b ? w_b : 1 - w_b) s_c,
 *   dL/dx_a = inside_a inv_ext_a sum_l N_l dL/dw_a(l),
 * inside_a = 1 where 0 <= (x_a - lo_a) inv_ext_a <= 1, else 0 (the clamp; NaN -> 0). The
 * derivative is that of the cell the forward reads: on an interior cell face (w_a = 0) the
 * one-sided derivative from the cell above, at u_a = 1 (w_a = 1 in the last cell) the one
 * from inside, where the encoding has a kink (it is continuous, piecewise multilinear).
 *
 * SH encoding (hash_sh_encode): the real SH basis of sh.h at degree 3 (16 coefficients,
 * "degree 4" in the 4-band count) of d / |d| (zero d -> the basis at (0, 0, 0)).
 *
 * Every kernel covers the first live_rows(n_max, count) points (common.h): n_max, or the count
 * on the device of a bounded buffer of n_max rows (null: n_max).
 *
 * Defines read: HASH_LEVELS, HASH_FEATURES, HASH_LOG2_T, HASH_GRAD_OWNED.
 * Twin: clrf/references/reference_hash.py (float64).
 */
#include "common.h"

#ifndef HASH_LEVELS
#define HASH_LEVELS 16    /* L: resolution levels (published: 16) */
#endif
#ifndef HASH_FEATURES
#define HASH_FEATURES 2   /* F: features per level, 1, 2 or 4 (published: 2; 2 -> float2 loads) */
#endif
#ifndef HASH_LOG2_T
#define HASH_LOG2_T 19    /* log2 of T, the table rows per level (published: 19) */
#endif
#ifndef HASH_GRAD_OWNED
#define HASH_GRAD_OWNED 0 /* 0: float atomics (GPUs); 1: one work-item owns each level (CPUs) */
#endif
#if HASH_LEVELS < 1 || HASH_LEVELS > 64
#error "HASH_LEVELS must be in 1..64"
#endif
#if HASH_FEATURES != 1 && HASH_FEATURES != 2 && HASH_FEATURES != 4
#error "HASH_FEATURES must be 1, 2 or 4"
#endif
#if HASH_LOG2_T < 1 || HASH_LOG2_T > 24
#error "HASH_LOG2_T must be in 1..24"
#endif

#define HASH_T (1u << HASH_LOG2_T)
#define HASH_DIM (HASH_LEVELS * HASH_FEATURES)
#define HASH_PRIME_Y 2654435761u
#define HASH_PRIME_Z 805459861u

#if HASH_FEATURES == 1
typedef float feat_t;
#define FEAT_LOAD(tab, row) ((tab)[row])
#elif HASH_FEATURES == 2
typedef float2 feat_t;
#define FEAT_LOAD(tab, row) vload2((row), (tab))
#else
typedef float4 feat_t;
#define FEAT_LOAD(tab, row) vload4((row), (tab))
#endif

/* The cell of level resolution N holding u, its 8 table rows and trilinear weights. */
typedef struct {
    uint row[8];
    float wt[8];
} cell_t;

CLRF_INLINE cell_t hash_cell(const float3 u, const int N) {
    const float3 p = u * (float)N;
    const float3 fl = fmin(floor(p), (float3)((float)(N - 1)));
    const float3 w = p - fl;
    const uint3 i = convert_uint3(fl);
    const uint R = (uint)N + 1u;
    const bool dense = (ulong)R * R * R <= (ulong)HASH_T;
    cell_t c;
    for (int k = 0; k < 8; ++k) {
        const uint vx = i.x + (k & 1), vy = i.y + ((k >> 1) & 1), vz = i.z + ((k >> 2) & 1);
        c.row[k] = dense ? vx + R * (vy + R * vz)
                         : (vx ^ (vy * HASH_PRIME_Y) ^ (vz * HASH_PRIME_Z)) & (HASH_T - 1u);
        c.wt[k] = ((k & 1) ? w.x : 1.0f - w.x) * (((k >> 1) & 1) ? w.y : 1.0f - w.y)
                  * (((k >> 2) & 1) ? w.z : 1.0f - w.z);
    }
    return c;
}

/* u of point i: (x - lo) * inv_ext clamped to [0, 1]; NaN -> 0 (fmax/fmin drop a NaN). */
CLRF_INLINE float3 hash_unit(__global const float *x, const size_t i, const float4 lo,
                             const float4 inv_ext) {
    const float3 u = (load3(x, i) - lo.xyz) * inv_ext.xyz;
    return fmin(fmax(u, (float3)(0.0f)), (float3)(1.0f));
}

/* enc [n, L F]: one work-item per (point, level) of a 2-D range, i = get_global_id(0) (rounded
 * up past n), l = get_global_id(1), so neighbouring items read the same level's table (and no
 * item divides: a 64-bit division per item cost about a quarter of this kernel on a CPU). */
__kernel void hash_forward(const int n_max, __global const int *count,
                           __global const float *x, const float4 lo,
                           const float4 inv_ext, __global const int *res,
                           __global const float *table, __global float *enc) {
    const int n = live_rows(n_max, count);
    const size_t i = get_global_id(0);
    const int l = get_global_id(1);
    if (i >= (size_t)n || l >= HASH_LEVELS) return;
    const cell_t c = hash_cell(hash_unit(x, i, lo, inv_ext), res[l]);
    __global const float *tab = table + (size_t)l * HASH_T * HASH_FEATURES;
    feat_t acc = (feat_t)(0.0f);
    for (int k = 0; k < 8; ++k) acc += c.wt[k] * FEAT_LOAD(tab, c.row[k]);
    __global float *o = enc + i * HASH_DIM + l * HASH_FEATURES;
#if HASH_FEATURES == 1
    o[0] = acc;
#elif HASH_FEATURES == 2
    vstore2(acc, 0, o);
#else
    vstore4(acc, 0, o);
#endif
}

/* Add point i's level-l gradient into the table gradient g (atomic or private). */
CLRF_INLINE void hash_scatter(__global float *g, const float3 u, const int N,
                              __global const float *genc, const int atomic) {
    feat_t d;
#if HASH_FEATURES == 1
    d = genc[0];
    if (d == 0.0f) return;
#elif HASH_FEATURES == 2
    d = vload2(0, genc);
    if (d.x == 0.0f && d.y == 0.0f) return;
#else
    d = vload4(0, genc);
    if (all(d == (feat_t)(0.0f))) return;
#endif
    const cell_t c = hash_cell(u, N);
    for (int k = 0; k < 8; ++k) {
        const feat_t v = c.wt[k] * d;
        __global float *p = g + (size_t)c.row[k] * HASH_FEATURES;
        if (atomic) {
#if HASH_FEATURES == 1
            atomic_add_f(p, v);
#else
            for (int f = 0; f < HASH_FEATURES; ++f) atomic_add_f(p + f, ((float *)&v)[f]);
#endif
        } else {
#if HASH_FEATURES == 1
            p[0] += v;
#elif HASH_FEATURES == 2
            vstore2(vload2(0, p) + v, 0, p);
#else
            vstore4(vload4(0, p) + v, 0, p);
#endif
        }
    }
}

#if HASH_GRAD_OWNED == 0
/* grad [L, T, F] += dL/dtable of genc [n, L F]; one work-item per (point, level), the 2-D range
 * of hash_forward. `scratch` is unused on this path. */
__kernel void hash_backward(const int n_max, __global const int *count,
                            __global const float *x, const float4 lo,
                            const float4 inv_ext, __global const int *res,
                            __global const float *genc, __global float *grad,
                            __global float *scratch) {
    const int n = live_rows(n_max, count);
    const size_t i = get_global_id(0);
    const int l = get_global_id(1);
    if (i >= (size_t)n || l >= HASH_LEVELS) return;
    hash_scatter(grad + (size_t)l * HASH_T * HASH_FEATURES, hash_unit(x, i, lo, inv_ext), res[l],
                 genc + i * HASH_DIM + l * HASH_FEATURES, 1);
}
#else
/* The CPU path: HASH_LEVELS work-items (launch exactly that many, one per work-group); item l
 * owns level l's table and adds every point's level-l gradient into it with plain adds, in
 * point order. No two items write the same entry, so there are no atomics, no scratch copies
 * and no reduction, and the result is deterministic. `scratch` is unused. */
__kernel void hash_backward(const int n_max, __global const int *count,
                            __global const float *x, const float4 lo,
                            const float4 inv_ext, __global const int *res,
                            __global const float *genc, __global float *grad,
                            __global float *scratch) {
    const int n = live_rows(n_max, count);
    const int l = get_global_id(0);
    if (l >= HASH_LEVELS) return;
    __global float *g = grad + (size_t)l * HASH_T * HASH_FEATURES;
    const int N = res[l];
    for (size_t i = 0; i < (size_t)n; ++i)
        hash_scatter(g, hash_unit(x, i, lo, inv_ext), N, genc + i * HASH_DIM + l * HASH_FEATURES,
                     0);
}
#endif

/* dL/dw (w the cell weights of hash_cell) of the level whose table is tab, from its features'
 * gradient ge [F]: s_k = ge . table[row_k], then per axis the differences of s along that axis
 * weighted by the other two axes' weights (the header's formula, unrolled). */
CLRF_INLINE float3 cell_dw(__global const float *tab, __global const float *ge,
                           const cell_t *c, const float3 w) {
    const feat_t g = FEAT_LOAD(ge, 0);
    float s[8];
#pragma unroll
    for (int k = 0; k < 8; ++k) {
        const feat_t t = FEAT_LOAD(tab, c->row[k]) * g;
#if HASH_FEATURES == 1
        s[k] = t;
#elif HASH_FEATURES == 2
        s[k] = t.x + t.y;
#else
        s[k] = (t.x + t.y) + (t.z + t.w);
#endif
    }
    const float ux = 1.0f - w.x, uy = 1.0f - w.y, uz = 1.0f - w.z;
    return (float3)(uy * uz * (s[1] - s[0]) + w.y * uz * (s[3] - s[2])
                        + uy * w.z * (s[5] - s[4]) + w.y * w.z * (s[7] - s[6]),
                    ux * uz * (s[2] - s[0]) + w.x * uz * (s[3] - s[1])
                        + ux * w.z * (s[6] - s[4]) + w.x * w.z * (s[7] - s[5]),
                    ux * uy * (s[4] - s[0]) + w.x * uy * (s[5] - s[1])
                        + ux * w.y * (s[6] - s[2]) + w.x * w.y * (s[7] - s[3]));
}

/* dx [n, 3] = dL/dx of points x [n, 3] from genc [n, L F] (see the header), one work-item a
 * point; the levels are summed in float32 in level order. */
__kernel void hash_dx(const int n_max, __global const int *count, __global const float *x,
                      const float4 lo, const float4 inv_ext, __global const int *res,
                      __global const float *table, __global const float *genc,
                      __global float *dx) {
    const int n = live_rows(n_max, count);
    const size_t i = get_global_id(0);
    if (i >= (size_t)n) return;
    const float3 raw = (load3(x, i) - lo.xyz) * inv_ext.xyz;
    const float3 u = fmin(fmax(raw, (float3)(0.0f)), (float3)(1.0f));
    float3 g = (float3)(0.0f);
    for (int l = 0; l < HASH_LEVELS; ++l) {
        const int N = res[l];
        const cell_t c = hash_cell(u, N);
        const float3 p = u * (float)N;     /* the weights of hash_cell, per axis */
        const float3 w = p - fmin(floor(p), (float3)((float)(N - 1)));
        g += cell_dw(table + (size_t)l * HASH_T * HASH_FEATURES,
                     genc + i * HASH_DIM + l * HASH_FEATURES, &c, w) * (float)N;
    }
    const float3 inside = (float3)(raw.x >= 0.0f && raw.x <= 1.0f ? 1.0f : 0.0f,
                                   raw.y >= 0.0f && raw.y <= 1.0f ? 1.0f : 0.0f,
                                   raw.z >= 0.0f && raw.z <= 1.0f ? 1.0f : 0.0f);
    vstore3(g * inv_ext.xyz * inside, i, dx);
}

/* SH basis (sh.h, degree 3: 16 coefficients) of the unit direction of d [n, 3] -> out [n, 16]. */
#define SH_DEGREE 3
#include "sh.h"
__kernel void hash_sh_encode(const int n_max, __global const int *count,
                             __global const float *d, __global float *out) {
    const int n = live_rows(n_max, count);
    const size_t i = get_global_id(0);
    if (i >= (size_t)n) return;
    const float3 v = load3(d, i);
    const float len = length(v);
    float Y[SH_BASIS];
    sh_basis(len > 0.0f ? v / len : (float3)(0.0f), Y);
    for (int b = 0; b < SH_BASIS; ++b) out[i * SH_BASIS + b] = Y[b];
}
