/* march.h: the ray march over a sparse SH grid shared by every kernel that walks rays
 * (render forward/backward, pruning weights). Conventions are documented in grid_render.cl.
 *
 * Bricks (BRICK 1, distributed rendering, clrf/grid/bricks.py): the kernel holds one brick of
 * the grid. The march is set up on the whole grid (global reso, bmin, scale), so the segments
 * and sample positions are those of the single-grid march bit for bit; a sample is evaluated
 * only when the brick owns it: when the lower corner of its cell (cell_locate) lies in
 * [blo, bhi) on every axis. Cells are convex and the corner index is monotone along a ray, so
 * a brick owns one contiguous run of segments, and every sample has exactly one owner. The
 * links array holds the brick's voxels plus a one-voxel halo on its high sides: voxels blo ..
 * blo + lreso - 1 (lreso = min(bhi + 1, reso) - blo), all the corners its cells touch.
 * march_setup narrows the loop to the segments [k0, nsteps) around the brick (with a slack,
 * the ownership test being the exact one).
 *
 * Defines read: SH_DEGREE (sh.h), T_STOP, BRICK, SH_PER_CORNER, CLRF_HAS_FP64 (ray.h).
 */
#ifndef CLRF_MARCH_H
#define CLRF_MARCH_H
#include "common.h"
#include "volrend.h"
#include "sh.h"
#include "ray.h"

#ifndef T_STOP
#define T_STOP 1e-4f  /* early termination: stop once transmittance < T_STOP (error <= T_STOP) */
#endif
#define COLOR_OFFSET 0.5f /* SH colour is offset so that all-zero coefficients give grey */
#ifndef CLRF_PREFETCH
#define CLRF_PREFETCH 0  /* 1: software-prefetch the rows of the cell PREFETCH_AHEAD samples
                            ahead with __builtin_prefetch (clang-based CPU compilers: PoCL) */
#endif
#ifndef PREFETCH_AHEAD
#define PREFETCH_AHEAD 3 /* samples ahead (~1.5 voxels at step 0.5): covers a DRAM latency */
#endif
#ifndef PREFETCH_LINKS_AHEAD
#define PREFETCH_LINKS_AHEAD (2 * PREFETCH_AHEAD) /* samples ahead for the links of a cell */
#endif
#ifndef BRICK
#define BRICK 0      /* 1: march one brick of a distributed grid (see above) */
#endif
#ifndef SH_PER_CORNER
#define SH_PER_CORNER 0  /* 1 (GPU shape): colours per corner, colour gradients merged as 3 floats
                            per corner (color_pre_corners; grid_render.cl render_backward) */
#endif
/* SPIR targets (Mesa rusticl, Intel's CPU runtime, Oclgrind define __SPIR__ or __SPIR64__)
   get no software prefetch: SPIR-V has no counterpart of llvm.prefetch, and rusticl 22.3's SPIR-V
   translator ends the host process on llvm.prefetch instead of failing the build. The host sets
   CLRF_BUILTIN_PREFETCH for PoCL only: NVIDIA's compiler rejects __builtin_prefetch of a __global
   pointer (an address-space change), and gets OpenCL C's prefetch() too. */
#if CLRF_PREFETCH && CLRF_BUILTIN_PREFETCH && !defined(__SPIR__) && !defined(__SPIR64__)
#define CLRF_PREFETCH_LINE(p) __builtin_prefetch((p), 0, 3)
#elif CLRF_PREFETCH
#define CLRF_PREFETCH_LINE(p) prefetch((p), 1)  /* OpenCL C's own: a real prefetch on Intel */
#else
#define CLRF_PREFETCH_LINE(p)
#endif

typedef struct {
    float3 p0;   /* entry point, box units */
    float3 dg;   /* unit world direction in box units per world unit */
    float3 dir;  /* unit world direction (for SH) */
    float t0;    /* world distance from the origin to the entry */
    float len;   /* world length inside the box */
    float dt;    /* world length of one step */
    int nsteps;  /* number of segments, the last one clipped to len */
    __global const uchar *occ; /* BLOCK > 0: occupancy of BLOCK^3 blocks of cells, then (BLOCK_FINE
                                  > 0) of BLOCK_FINE^3 blocks from entry oreso.w on */
    int4 oreso;  /* BLOCK blocks per axis; .w: where the BLOCK_FINE table starts */
    float3 idg;  /* 1 / dg per axis (inf where dg is 0): region_exit's divisions */
#if BRICK
    int k0;      /* first segment that may lie in the brick (the loop starts there) */
    int4 blo, bhi;  /* the brick owns the cells with lower corner in [blo, bhi) per axis */
    int4 lreso;  /* the links array: voxels blo .. blo + lreso - 1 */
#endif
} march_t;

/* First segment of the march loop: 0, or the brick's k0. */
#if BRICK
#define MARCH_K0(m) ((m)->k0)
#else
#define MARCH_K0(m) 0
#endif

typedef struct {
    int idx[8];   /* rows of the 8 corners (< 0: empty); corner c = (cx << 2) | (cy << 1) | cz */
    float w[8];   /* trilinear weights */
    int cell;     /* linear index of the lower corner: identifies the cell */
    int3 lo;      /* lower corner */
} lerp_t;

/* Segment k: midpoint distance from the entry and length. */
CLRF_INLINE void march_segment(const march_t *m, int k, float *mid, float *delta) {
    float s0 = (float)k * m->dt;
    float s1 = fmin((float)(k + 1) * m->dt, m->len);
    *mid = 0.5f * (s0 + s1);
    *delta = s1 - s0;
}

/* One axis of the interpolation set-up: position in box units -> lower index, fraction. */
CLRF_INLINE void lerp_axis(float p, int r, int *i0, int *i1, float *f) {
    float u = clamp(p - 0.5f, 0.0f, (float)(r - 1));
    int i = min((int)u, max(r - 2, 0));
    *i0 = i;
    *i1 = min(i + 1, r - 1);
    *f = u - (float)i;
}

/* Linear index of cell / voxel (x, y, z) in a C-order [RX, RY, RZ] array (links). */
CLRF_INLINE int cell_of(int x, int y, int z, int4 r) { return (x * r.y + y) * r.z + z; }

/* The cell around point p (box units): corners x0..x1, y0..y1, z0..z1 (clamped at the grid
 * edges) and fractions fx, fy, fz along each axis; lerp_axis on the three axes. */
typedef struct { int x0, x1, y0, y1, z0, z1; float fx, fy, fz; } cellpos_t;
CLRF_INLINE void cell_locate(float3 p, int4 reso, cellpos_t *q) {
    lerp_axis(p.x, reso.x, &q->x0, &q->x1, &q->fx);
    lerp_axis(p.y, reso.y, &q->y0, &q->y1, &q->fy);
    lerp_axis(p.z, reso.z, &q->z0, &q->z1, &q->fz);
}

/* Index into the links array of voxel (x, y, z) (global voxel indices): the whole grid's
 * array, or the brick's (voxels from blo, lreso per axis). */
#if BRICK
#define LINK_AT(m_, ix, iy, iz, reso_) \
    cell_of((ix) - (m_)->blo.x, (iy) - (m_)->blo.y, (iz) - (m_)->blo.z, (m_)->lreso)
#else
#define LINK_AT(m_, ix, iy, iz, reso_) cell_of((ix), (iy), (iz), (reso_))
#endif

#if BRICK
/* Narrow [k0, nsteps) to the segments whose midpoints can lie in the brick: the brick's cells
 * are the points p (box units) with p - 0.5 in [blo, bhi) per axis (unbounded below blo = 0 and
 * above bhi >= reso - 1, where lerp_axis clamps). The slab bounds are widened by BRICK_SLACK
 * box units, more than the float rounding of p = p0 + mid dg, and by one segment, so no owned
 * sample is left out; march_visit's ownership test is the exact one. An axis the ray does not
 * move along (dg = 0) is owned for all samples or none, decided at p0 as march_visit would. */
#define BRICK_SLACK(reso) (1e-5f * (1.0f + (float)max((reso).x, max((reso).y, (reso).z))))
CLRF_INLINE void brick_range(march_t *m, int4 reso) {
    const float p[3] = {m->p0.x, m->p0.y, m->p0.z}, d[3] = {m->dg.x, m->dg.y, m->dg.z};
    const int lo[3] = {m->blo.x, m->blo.y, m->blo.z}, hi[3] = {m->bhi.x, m->bhi.y, m->bhi.z};
    const int r[3] = {reso.x, reso.y, reso.z};
    const float slack = BRICK_SLACK(reso);
    float s0 = -INFINITY, s1 = INFINITY;
    for (int a = 0; a < 3; ++a) {
        const float b0 = lo[a] == 0 ? -INFINITY : (float)lo[a] + 0.5f - slack;
        const float b1 = hi[a] >= r[a] - 1 ? INFINITY : (float)hi[a] + 0.5f + slack;
        if (d[a] == 0.0f) {
            int i0, i1;
            float f;
            lerp_axis(p[a], r[a], &i0, &i1, &f);
            if (i0 < lo[a] || i0 >= hi[a]) s1 = -INFINITY;
            continue;
        }
        const float ta = (b0 - p[a]) / d[a], tb = (b1 - p[a]) / d[a];
        s0 = fmax(s0, fmin(ta, tb));
        s1 = fmin(s1, fmax(ta, tb));
    }
    const float n = (float)m->nsteps;
    if (!(s1 >= s0)) { m->k0 = m->nsteps; return; }
    m->k0 = (int)clamp(floor(s0 / m->dt - 0.5f) - 1.0f, 0.0f, n);
    m->nsteps = (int)clamp(floor(s1 / m->dt - 0.5f) + 2.0f, 0.0f, n);
}

/* 1 if the brick owns the sample whose cell is q: its lower corner is in [blo, bhi). */
CLRF_INLINE int brick_owns_q(const march_t *m, const cellpos_t *q) {
    return q->x0 >= m->blo.x && q->x0 < m->bhi.x && q->y0 >= m->blo.y && q->y0 < m->bhi.y &&
           q->z0 >= m->blo.z && q->z0 < m->bhi.z;
}
/* The same for the sample at p (box units). */
CLRF_INLINE int brick_owns(const march_t *m, float3 p, int4 reso) {
    cellpos_t q;
    cell_locate(p, reso, &q);
    return brick_owns_q(m, &q);
}
#define BRICK_OWNS(m, p, reso) brick_owns((m), (p), (reso))
#else
#define BRICK_OWNS(m, p, reso) 1
#endif

/* Set up the march of ray (o, d); returns 0 when the ray misses the box. */
CLRF_INLINE int march_setup(float3 o, float3 d, int4 reso, float4 bmin, float4 scale, float step,
                            march_t *m) {
    real3 dd = REAL3(d);
    real_t mx = fmax(fabs(dd.x), fmax(fabs(dd.y), fabs(dd.z)));
    if (!(mx > 0) || !isfinite(mx)) return 0;
    dd /= mx;                       /* scale first: |d| may under/overflow when squared */
    dd /= sqrt(dot(dd, dd));
    real3 sc = (real3)(scale.x, scale.y, scale.z);
    real3 og = (REAL3(o) - (real3)(bmin.x, bmin.y, bmin.z)) * sc;
    real3 dg = dd * sc;
    real3 hi = (real3)(reso.x, reso.y, reso.z);
    real_t t0, t1;
    if (!ray_box(og, dg, (real3)(0, 0, 0), hi, &t0, &t1)) return 0;
    real_t dt = (real_t)step / sqrt(dot(dg, dg));
    real_t len = t1 - t0;
    real3 p0 = clamp(og + t0 * dg, (real3)(0, 0, 0), hi);
    m->p0 = (float3)(p0.x, p0.y, p0.z);
    m->dg = (float3)(dg.x, dg.y, dg.z);
    m->dir = (float3)(dd.x, dd.y, dd.z);
    m->t0 = (float)t0;
    m->len = (float)len;
    m->dt = (float)dt;
    m->nsteps = (int)ceil(len / dt);
    m->idg = 1.0f / m->dg;
#if BRICK
    brick_range(m, reso);
#endif
    return m->nsteps > 0;
}


/* Find the 8 corners and weights of point p (box units). Returns 1 if any corner is allocated. */
CLRF_INLINE int lerp_setup(float3 p, int4 reso, __global const int *links, lerp_t *L) {
    cellpos_t q;
    cell_locate(p, reso, &q);
    L->lo = (int3)(q.x0, q.y0, q.z0);
    L->cell = cell_of(q.x0, q.y0, q.z0, reso);
    const int xs[2] = {q.x0, q.x1}, ys[2] = {q.y0, q.y1}, zs[2] = {q.z0, q.z1};
    const float wx[2] = {1.0f - q.fx, q.fx}, wy[2] = {1.0f - q.fy, q.fy},
                wz[2] = {1.0f - q.fz, q.fz};
    int any = 0;
    for (int c = 0; c < 8; ++c) {
        int cx = c >> 2, cy = (c >> 1) & 1, cz = c & 1;
        int k = links[cell_of(xs[cx], ys[cy], zs[cz], reso)];
        L->idx[c] = k;
        L->w[c] = wx[cx] * wy[cy] * wz[cz];
        any |= (k >= 0);
    }
    return any;
}

/* Distance (from the entry) at which the ray leaves the region of points whose cell (lower
 * corner) lies in [lo, lo + nb - 1] per axis. Unbounded sides (the clamped outer half voxels)
 * are +-inf, so the region is convex and contains the current point. */
CLRF_INLINE float region_exit(const march_t *m, int3 lo, int nb, int4 reso) {
    float s = INFINITY;
    const float p[3] = {m->p0.x, m->p0.y, m->p0.z}, d[3] = {m->dg.x, m->dg.y, m->dg.z};
    const float id[3] = {m->idg.x, m->idg.y, m->idg.z};
    const int l[3] = {lo.x, lo.y, lo.z}, r[3] = {reso.x, reso.y, reso.z};
    for (int a = 0; a < 3; ++a) {
        float bound_lo = l[a] == 0 ? -INFINITY : (float)l[a] + 0.5f;
        float bound_hi = l[a] + nb - 1 >= r[a] - 2 ? INFINITY : (float)(l[a] + nb) + 0.5f;
        if (d[a] > 0.0f) s = fmin(s, (bound_hi - p[a]) * id[a]);
        else if (d[a] < 0.0f) s = fmin(s, (bound_lo - p[a]) * id[a]);
    }
    return s;
}

/* Index of the next segment to evaluate after segment k found its region (nb^3 cells from
 * lo) empty: the first one whose midpoint lies at least SKIP_MARGIN steps before the region's
 * exit s is not skipped, so every skipped midpoint is inside the region by that margin, far
 * more than the float rounding of s and of the sample positions (~1e-5 voxels against 5e-4
 * at step 0.5). A segment just inside is visited again and skipped on its own; the last,
 * clipped segment has its midpoint earlier than (j + 0.5) dt, so it is inside too. */
#define SKIP_MARGIN 1e-3f
CLRF_INLINE int skip_region(const march_t *m, int k, int3 lo, int nb, int4 reso) {
    float s = region_exit(m, lo, nb, reso);
    float j = fmin(ceil(s / m->dt - 0.5f - SKIP_MARGIN), (float)m->nsteps);
    return max(k + 1, (int)j);
}

/* The same for one empty cell. */
CLRF_INLINE int skip_empty(const march_t *m, int k, int3 lo, int4 reso) {
    return skip_region(m, k, lo, 1, reso);
}

#ifndef BLOCK
#define BLOCK 0  /* > 0: skip BLOCK^3-cell blocks with no allocated corner (occupancy array) */
#endif
#ifndef BLOCK_FINE
#define BLOCK_FINE 0  /* > 0 (with BLOCK > 0): inside an occupied block, skip BLOCK_FINE^3-cell
                         blocks with no allocated corner (a second table) */
#endif

/* Empty-space skipping by blocks: if the block (then, with BLOCK_FINE, the fine block) of the
 * sample whose cell is q has no allocated voxel, set *k to the segment before the next one to
 * evaluate (the loop's ++k follows) and return 1. */
CLRF_INLINE int skip_block(const march_t *m, const cellpos_t *q, int4 reso, int *k) {
#if BLOCK > 0
#if BRICK   /* the tables cover the brick's links: blocks of local cells */
    const int3 org = (int3)(m->blo.x, m->blo.y, m->blo.z);
    const int4 lr = m->lreso;
#else
    const int3 org = (int3)(0);
    const int4 lr = reso;
#endif
    const int3 c = (int3)(q->x0, q->y0, q->z0) - org;
    const int3 b = c / BLOCK;
    if (!m->occ[cell_of(b.x, b.y, b.z, m->oreso)]) {
        *k = skip_region(m, *k, b * BLOCK + org, BLOCK, reso) - 1;
        return 1;
    }
#if BLOCK_FINE > 0
    const int4 fr = (lr + (BLOCK_FINE - 1)) / BLOCK_FINE;
    const int3 f = c / BLOCK_FINE;
    if (!m->occ[m->oreso.w + cell_of(f.x, f.y, f.z, fr)]) {
        *k = skip_region(m, *k, f * BLOCK_FINE + org, BLOCK_FINE, reso) - 1;
        return 1;
    }
#endif
#endif
    return 0;
}

CLRF_INLINE float lerp_density(const lerp_t *L, __global const float *density) {
    float s = 0.0f;
#pragma unroll
    for (int c = 0; c < 8; ++c)
        if (L->idx[c] >= 0) s += L->w[c] * density[L->idx[c]];
    return s;
}

/* ---- one SH row in vector registers -------------------------------------------------------
 * PoCL runs a work-item's own scalar loops one lane wide, so a row of SH_DIM
 * floats is held as explicit vectors: SH_DIM = 3 -> float3; 12 -> float8 + float4;
 * 27 -> float16 + float8 + float3; 48 -> 3 x float16. SHV_MAP(OP) applies OP(field, width,
 * offset) to each part. Rows start at any float offset: vloadn/vstoren need only float
 * alignment. */
#if SH_DEGREE == 0
typedef struct { float3 a; } shv_t;
#define SHV_MAP(OP) OP(a, 3, 0)
#elif SH_DEGREE == 1
typedef struct { float8 a; float4 b; } shv_t;
#define SHV_MAP(OP) OP(a, 8, 0) OP(b, 4, 8)
#elif SH_DEGREE == 2
typedef struct { float16 a; float8 b; float3 c; } shv_t;
#define SHV_MAP(OP) OP(a, 16, 0) OP(b, 8, 16) OP(c, 3, 24)
#else
typedef struct { float16 a; float16 b; float16 c; } shv_t;
#define SHV_MAP(OP) OP(a, 16, 0) OP(b, 16, 16) OP(c, 16, 32)
#endif

#define SHV_ZERO_(f, n, o) r.f = (float##n)(0.0f);
CLRF_INLINE shv_t shv_zero(void) { shv_t r; SHV_MAP(SHV_ZERO_) return r; }
#define SHV_LOAD_(f, n, o) r.f = vload##n(0, p + (o));
CLRF_INLINE shv_t shv_load(__global const float *p) { shv_t r; SHV_MAP(SHV_LOAD_) return r; }
CLRF_INLINE shv_t shv_load_private(const float *p) { shv_t r; SHV_MAP(SHV_LOAD_) return r; }
#define SHV_STORE_(f, n, o) vstore##n(v.f, 0, p + (o));
CLRF_INLINE void shv_store(shv_t v, __global float *p) { SHV_MAP(SHV_STORE_) }
CLRF_INLINE void shv_store_private(shv_t v, float *p) { SHV_MAP(SHV_STORE_) }
/* acc += w * x */
#define SHV_AXPY_(f, n, o) acc->f += w * x.f;
CLRF_INLINE void shv_axpy(shv_t *acc, float w, shv_t x) { SHV_MAP(SHV_AXPY_) }
#define SHV_ADD_(f, n, o) r.f = x.f + y.f;
CLRF_INLINE shv_t shv_add(shv_t x, shv_t y) { shv_t r; SHV_MAP(SHV_ADD_) return r; }
#define SHV_MUL_(f, n, o) r.f = x.f * y.f;
CLRF_INLINE shv_t shv_mul(shv_t x, shv_t y) { shv_t r; SHV_MAP(SHV_MUL_) return r; }
#define SHV_SCALE_(f, n, o) r.f = s * x.f;
CLRF_INLINE shv_t shv_scale(shv_t x, float s) { shv_t r; SHV_MAP(SHV_SCALE_) return r; }

/* Per-ray SH factors: Ych[ch] holds Y_b at positions ch*SH_BASIS + b and 0 elsewhere, so
 * that dot(coefficients, Ych[ch]) is channel ch's SH value and sum_ch d_ch Ych[ch] is the
 * gradient of sum_ch d_ch * value_ch with respect to the coefficients. */
typedef struct { shv_t ych[3]; shv_t yall; } shy_t;
CLRF_INLINE void shy_setup(const float *Y, shy_t *S) {
    float tmp[SH_DIM];
    for (int ch = 0; ch < 3; ++ch) {
        for (int j = 0; j < SH_DIM; ++j) tmp[j] = 0.0f;
        for (int b = 0; b < SH_BASIS; ++b) tmp[ch * SH_BASIS + b] = Y[b];
        S->ych[ch] = shv_load_private(tmp);
    }
    for (int j = 0; j < SH_DIM; ++j) tmp[j] = Y[j % SH_BASIS];
    S->yall = shv_load_private(tmp);
}

/* Interpolated SH coefficients of the sample (8 corner rows, vector loads). */
CLRF_INLINE shv_t lerp_sh(const lerp_t *L, __global const float *sh) {
    shv_t co = shv_zero();
#pragma unroll
    for (int c = 0; c < 8; ++c)
        if (L->idx[c] >= 0) shv_axpy(&co, L->w[c], shv_load(sh + (size_t)L->idx[c] * SH_DIM));
    return co;
}

/* Pre-activation colour from interpolated coefficients: per channel sum_b co Y + offset. */
CLRF_INLINE float3 color_pre(shv_t co, const shy_t *S) {
    float t[SH_DIM];
    shv_store_private(shv_mul(co, S->yall), t);
    float pre[3];
#pragma unroll
    for (int ch = 0; ch < 3; ++ch) {
        float v = 0.0f;
#pragma unroll
        for (int b = 0; b < SH_BASIS; ++b) v += t[ch * SH_BASIS + b];
        pre[ch] = v + COLOR_OFFSET;
    }
    return (float3)(pre[0], pre[1], pre[2]);
}

/* SH_PER_CORNER (the GPU shape, tuning.gpu_kernels): the sample's pre-activation colour as
 * the weighted sum of its corners' SH values, sum_c w_c sum_b sh_c Y_b + offset. Both sums are
 * linear, so this is the colour of the interpolated coefficients (color_pre of lerp_sh) up to
 * the order of the float additions, but a work-item holds 3 sums and the SH_BASIS factors
 * instead of an interpolated row and the 4 rows of shy_t: on a GPU, where every float of a
 * work-item is a register of its own, that is what keeps the march out of spill memory. */
CLRF_INLINE float3 color_pre_corners(const lerp_t *L, __global const float *sh, const float *Y) {
    float acc[3] = {0.0f, 0.0f, 0.0f};
#pragma unroll
    for (int c = 0; c < 8; ++c) {
        if (L->idx[c] < 0) continue;
        __global const float *row = sh + (size_t)L->idx[c] * SH_DIM;
#pragma unroll
        for (int ch = 0; ch < 3; ++ch) {
            float v = 0.0f;
#pragma unroll
            for (int b = 0; b < SH_BASIS; ++b) v += row[ch * SH_BASIS + b] * Y[b];
            acc[ch] += L->w[c] * v;
        }
    }
    return (float3)(acc[0], acc[1], acc[2]) + COLOR_OFFSET;
}

/* The sample's pre-activation colour in the build's shape (S: shy_setup of Y, unused with
 * SH_PER_CORNER). */
#if SH_PER_CORNER
#define SAMPLE_PRE(L, sh, S, Y) color_pre_corners((L), (sh), (Y))
#else
#define SAMPLE_PRE(L, sh, S, Y) color_pre(lerp_sh((L), (sh)), (S))
#endif

/* lerp_setup that reuses the previous sample's corner rows when it lies in the same cell
 * (about every other sample at step 0.5): the 8 link loads are skipped, the weights are new. */
CLRF_INLINE int lerp_setup_cached_q(const march_t *m, const cellpos_t *qp, int4 reso,
                                    __global const int *links, lerp_t *L) {
    const cellpos_t q = *qp;
    const int cell = cell_of(q.x0, q.y0, q.z0, reso);
    const float wx[2] = {1.0f - q.fx, q.fx}, wy[2] = {1.0f - q.fy, q.fy},
                wz[2] = {1.0f - q.fz, q.fz};
    int any = 0;
    if (cell != L->cell) {
        L->cell = cell;
        L->lo = (int3)(q.x0, q.y0, q.z0);
        const int xs[2] = {q.x0, q.x1}, ys[2] = {q.y0, q.y1}, zs[2] = {q.z0, q.z1};
#pragma unroll
        for (int c = 0; c < 8; ++c) {
            int cx = c >> 2, cy = (c >> 1) & 1, cz = c & 1;
            L->idx[c] = links[LINK_AT(m, xs[cx], ys[cy], zs[cz], reso)];
        }
    }
#pragma unroll
    for (int c = 0; c < 8; ++c) {
        int cx = c >> 2, cy = (c >> 1) & 1, cz = c & 1;
        L->w[c] = wx[cx] * wy[cy] * wz[cz];
        any |= (L->idx[c] >= 0);
    }
    return any;
}

CLRF_INLINE int lerp_setup_cached(const march_t *m, float3 p, int4 reso, __global const int *links,
                                  lerp_t *L) {
    cellpos_t q;
    cell_locate(p, reso, &q);
    return lerp_setup_cached_q(m, &q, reso, links, L);
}

/* Start loading the 8 links of the cell around point p (4 pairs adjacent along z) into the
 * cache, a few samples before prefetch_cell needs them to find the rows. */
CLRF_INLINE void prefetch_links(const march_t *m, float3 p, int4 reso, __global const int *links,
                                int *last) {
#if CLRF_PREFETCH
    cellpos_t q;
    cell_locate(p, reso, &q);
    const int cell = cell_of(q.x0, q.y0, q.z0, reso);
    if (cell == *last) return;
    *last = cell;
    CLRF_PREFETCH_LINE(links + LINK_AT(m, q.x0, q.y0, q.z0, reso));
    CLRF_PREFETCH_LINE(links + LINK_AT(m, q.x0, q.y1, q.z0, reso));
    CLRF_PREFETCH_LINE(links + LINK_AT(m, q.x1, q.y0, q.z0, reso));
    CLRF_PREFETCH_LINE(links + LINK_AT(m, q.x1, q.y1, q.z0, reso));
#endif
}

/* Start loading the corner rows of the cell around point p (box units) into the cache, so the
 * gathers of a later sample do not wait for DRAM (not when sh is 0); when grad_d is not 0,
 * also the gradient rows grad_d[k], grad_s[k * SH_DIM ...] that the backward pass will
 * read-modify-write. Only when
 * CLRF_PREFETCH; *last holds the cell prefetched last time (skip if unchanged). The links are
 * read here and again later (then from the cache). */
CLRF_INLINE void prefetch_cell_grad(const march_t *m, float3 p, int4 reso,
                                    __global const int *links, __global const float *density,
                                    __global const float *sh, __global const float *grad_d,
                                    __global const float *grad_s, int *last) {
#if CLRF_PREFETCH
    cellpos_t q;
    cell_locate(p, reso, &q);
    const int cell = cell_of(q.x0, q.y0, q.z0, reso);
    if (cell == *last) return;
    *last = cell;
    const int xs[2] = {q.x0, q.x1}, ys[2] = {q.y0, q.y1}, zs[2] = {q.z0, q.z1};
    for (int c = 0; c < 8; ++c) {
        int k = links[LINK_AT(m, xs[c >> 2], ys[(c >> 1) & 1], zs[c & 1], reso)];
        if (k < 0) continue;
        if (sh) {
            __global const float *row = sh + (size_t)k * SH_DIM;
            for (int j = 0; j < SH_DIM; j += 16) CLRF_PREFETCH_LINE(row + j);
            CLRF_PREFETCH_LINE(row + SH_DIM - 1);
            CLRF_PREFETCH_LINE(density + k);
        }
        if (grad_d) {
            __global const float *grow = grad_s + (size_t)k * SH_DIM;
            for (int j = 0; j < SH_DIM; j += 16) CLRF_PREFETCH_LINE(grow + j);
            CLRF_PREFETCH_LINE(grow + SH_DIM - 1);
            CLRF_PREFETCH_LINE(grad_d + k);
        }
    }
#endif
}

/* The march loop's visit of segment *k, shared by every grid march: the segment's midpoint
 * and length, the empty-block skips (on entering a new cell: the last one passed them), the
 * prefetch of a later sample's rows (pf != 0: pf[0] the cell, pf[1] the links last
 * prefetched; grad_d / grad_s as in prefetch_cell_grad) and the trilinear set-up with the
 * empty-cell skip. Returns 1 when segment *k has a sample to evaluate (L set up for it); 0
 * when the caller continues, *k then being the segment before the next one to visit (the
 * loop's ++k follows). Prefetching happens only where the march evaluates samples, never
 * across empty blocks. */
CLRF_INLINE int march_visit(const march_t *m, int4 reso, __global const int *links,
                            __global const float *density, __global const float *sh,
                            __global const float *grad_d, __global const float *grad_s, int *pf,
                            int *k, float *mid, float *delta, lerp_t *L) {
    march_segment(m, *k, mid, delta);
    const float3 p = m->p0 + *mid * m->dg;
    cellpos_t q;
    cell_locate(p, reso, &q);
    if (cell_of(q.x0, q.y0, q.z0, reso) != L->cell) {   /* the last cell passed both tests */
#if BRICK
        if (!brick_owns_q(m, &q)) return 0;
#endif
        if (skip_block(m, &q, reso, k)) return 0;
    }
#if CLRF_PREFETCH
    if (pf) {   /* a brick prefetches only points it owns: their corners are in its links */
        const float3 pl = m->p0 + (*mid + PREFETCH_LINKS_AHEAD * m->dt) * m->dg;
        if (*k + PREFETCH_LINKS_AHEAD < m->nsteps && BRICK_OWNS(m, pl, reso))
            prefetch_links(m, pl, reso, links, &pf[1]);
        const float3 pr = m->p0 + (*mid + PREFETCH_AHEAD * m->dt) * m->dg;
        if (*k + PREFETCH_AHEAD < m->nsteps && BRICK_OWNS(m, pr, reso))
            prefetch_cell_grad(m, pr, reso, links, density, sh, grad_d, grad_s, &pf[0]);
    }
#endif
    if (!lerp_setup_cached_q(m, &q, reso, links, L)) {
        *k = skip_empty(m, *k, L->lo, reso) - 1;
        return 0;
    }
    return 1;
}

#ifndef COMPENSATED_SUMS
#define COMPENSATED_SUMS 0  /* 1: Kahan-compensated rgb/acc/depth (and, in the backward, per-cell
                               gradient registers); the host sets it when a ray can have more
                               than LONG_RAY_SAMPLES samples (clrf/grid/render.py), where plain
                               float32 sums would drift like n * 6e-8 */
#endif

/* s += x, compensated when COMPENSATED_SUMS (c carries the lost low-order part). */
CLRF_INLINE void csum_add(float *s, float *c, float x) {
#if COMPENSATED_SUMS
    kahan_add(s, c, x);
#else
    *s += x;
#endif
}


/* Per-sample record written by the forward march for the backward march (rec != 0): one
 * float8 per non-empty sample j, in march order: (sigma, w, T after the sample, pre.x, pre.y,
 * pre.z, k, 0) with k the segment index (int bits), w, T and pre only where sigma > 0. The
 * backward walks the record instead of re-marching: it jumps to segment k (no empty-space
 * skipping, no density or SH gathers), recomputes the corner links and weights there and
 * reads the rest (bitwise the same values). rec_max bounds the count; a march that would
 * exceed it records nothing usable (*n_rec < 0) and the backward re-marches. */
#define REC_SIGMA 0
#define REC_W 1
#define REC_TNEXT 2
#define REC_PRE 3
#define REC_K 6

/* The forward march shared by every kernel (rec: see above; 0 for no record). With BRICK,
 * *kfirst is set to the first segment the brick evaluates (left as it was when none): it
 * orders the bricks' partial results along the ray. */
CLRF_INLINE void march_forward_rec(const march_t *m, int4 reso, __global const int *links,
                                   __global const float *density, __global const float *sh,
                                   const float *Y, __global float *rec, const int rec_max,
                                   int *n_rec, int *kfirst, fwd_t *out) {
    int j = 0;
#if SH_PER_CORNER
    const int S = 0;   /* (SAMPLE_PRE takes no vectors) */
#else
    shy_t S;
    shy_setup(Y, &S);
#endif
    ksum_t logT = {0.0f, 0.0f};
    float T = 1.0f;
    float rgb[3] = {0.0f, 0.0f, 0.0f}, crgb[3] = {0.0f, 0.0f, 0.0f};
    float acc = 0.0f, depth = 0.0f, cacc = 0.0f, cdepth = 0.0f;
    lerp_t L;
    L.cell = -1;
    int pf[2] = {-1, -1};
    for (int k = MARCH_K0(m); k < m->nsteps; ++k) {
        float mid, delta;
        if (!march_visit(m, reso, links, density, sh, 0, 0, pf, &k, &mid, &delta, &L)) continue;
#if BRICK
        if (*kfirst < 0) *kfirst = k;
#endif
        float sigma = lerp_density(&L, density);
        if (!(sigma > 0.0f)) {
            if (rec && j < rec_max) {
                rec[8 * j + REC_SIGMA] = sigma;
                rec[8 * j + REC_K] = as_float(k);
            }
            ++j;
            continue;
        }
        float tau = sigma * delta;
        float Tnext;
        float w = vr_step(&logT, T, tau, &Tnext);
        float3 pre = SAMPLE_PRE(&L, sh, &S, Y);
        float3 c = fmax(pre, 0.0f);
        csum_add(&rgb[0], &crgb[0], w * c.x);
        csum_add(&rgb[1], &crgb[1], w * c.y);
        csum_add(&rgb[2], &crgb[2], w * c.z);
        csum_add(&acc, &cacc, w);
        csum_add(&depth, &cdepth, w * mid);
        T = Tnext;
        if (rec && j < rec_max)
            vstore8((float8)(sigma, w, T, pre.x, pre.y, pre.z, as_float(k), 0.0f), j, rec);
        ++j;
        if (T < T_STOP) break;
    }
    *n_rec = j <= rec_max ? j : -1;
    out->rgb = (float3)(rgb[0], rgb[1], rgb[2]);
    out->acc = acc;
    out->depth = depth;
    out->logT = logT.s;
}

CLRF_INLINE void march_forward(const march_t *m, int4 reso, __global const int *links,
                               __global const float *density, __global const float *sh,
                               const float *Y, int *kfirst, fwd_t *out) {
    int n_rec;
    march_forward_rec(m, reso, links, density, sh, Y, 0, 0, &n_rec, kfirst, out);
}

#endif /* CLRF_MARCH_H */
