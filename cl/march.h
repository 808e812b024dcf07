/* march.h: the ray march over a sparse SH grid shared by every kernel that walks rays
 * (render forward/backward, pruning weights). Conventions are documented in grid_render.cl.
 *
 * Defines read: SH_DEGREE (sh.h), T_STOP, CLRF_HAS_FP64 (ray.h).
 */
#ifndef CLRF_MARCH_H
#define CLRF_MARCH_H
#include "common.h"
#include "sh.h"
#include "ray.h"

#ifndef T_STOP
#define T_STOP 1e-4f  /* early termination: stop once transmittance < T_STOP (error <= T_STOP) */
#endif
#define COLOR_OFFSET 0.5f /* SH colour is offset so that all-zero coefficients give grey */

typedef struct {
    float3 p0;   /* entry point, box units */
    float3 dg;   /* unit world direction in box units per world unit */
    float3 dir;  /* unit world direction (for SH) */
    float t0;    /* world distance from the origin to the entry */
    float len;   /* world length inside the box */
    float dt;    /* world length of one step */
    int nsteps;  /* number of segments, the last one clipped to len */
} march_t;

typedef struct {
    int idx[8];   /* rows of the 8 corners (< 0: empty); corner c = (cx << 2) | (cy << 1) | cz */
    float w[8];   /* trilinear weights */
    int cell;     /* linear index of the lower corner: identifies the cell */
    int3 lo;      /* lower corner */
} lerp_t;

/* Set up the march of ray (o, d); returns 0 when the ray misses the box. */
inline int march_setup(float3 o, float3 d, int4 reso, float4 bmin, float4 scale, float step,
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
    return m->nsteps > 0;
}

/* Segment k: midpoint distance from the entry and length. */
inline void march_segment(const march_t *m, int k, float *mid, float *delta) {
    float s0 = (float)k * m->dt;
    float s1 = fmin((float)(k + 1) * m->dt, m->len);
    *mid = 0.5f * (s0 + s1);
    *delta = s1 - s0;
}

/* One axis of the interpolation set-up: position in box units -> lower index, fraction. */
inline void lerp_axis(float p, int r, int *i0, int *i1, float *f) {
    float u = clamp(p - 0.5f, 0.0f, (float)(r - 1));
    int i = min((int)u, max(r - 2, 0));
    *i0 = i;
    *i1 = min(i + 1, r - 1);
    *f = u - (float)i;
}

/* Find the 8 corners and weights of point p (box units). Returns 1 if any corner is allocated. */
inline int lerp_setup(float3 p, int4 reso, __global const int *links, lerp_t *L) {
    int x0, x1, y0, y1, z0, z1;
    float fx, fy, fz;
    lerp_axis(p.x, reso.x, &x0, &x1, &fx);
    lerp_axis(p.y, reso.y, &y0, &y1, &fy);
    lerp_axis(p.z, reso.z, &z0, &z1, &fz);
    L->lo = (int3)(x0, y0, z0);
    L->cell = (x0 * reso.y + y0) * reso.z + z0;
    const int xs[2] = {x0, x1}, ys[2] = {y0, y1}, zs[2] = {z0, z1};
    const float wx[2] = {1.0f - fx, fx}, wy[2] = {1.0f - fy, fy}, wz[2] = {1.0f - fz, fz};
    int any = 0;
    for (int c = 0; c < 8; ++c) {
        int cx = c >> 2, cy = (c >> 1) & 1, cz = c & 1;
        int k = links[(xs[cx] * reso.y + ys[cy]) * reso.z + zs[cz]];
        L->idx[c] = k;
        L->w[c] = wx[cx] * wy[cy] * wz[cz];
        any |= (k >= 0);
    }
    return any;
}

/* Distance (from the entry) at which the ray leaves the region of points that interpolate
 * from the cell with lower corner lo. Unbounded sides (the clamped outer half voxels) are
 * +-inf, so the region is convex and contains the current point. */
inline float cell_exit(const march_t *m, int3 lo, int4 reso) {
    float s = INFINITY;
    const float p[3] = {m->p0.x, m->p0.y, m->p0.z}, d[3] = {m->dg.x, m->dg.y, m->dg.z};
    const int l[3] = {lo.x, lo.y, lo.z}, r[3] = {reso.x, reso.y, reso.z};
    for (int a = 0; a < 3; ++a) {
        float bound_lo = l[a] == 0 ? -INFINITY : (float)l[a] + 0.5f;
        float bound_hi = l[a] >= r[a] - 2 ? INFINITY : (float)l[a] + 1.5f;
        if (d[a] > 0.0f) s = fmin(s, (bound_hi - p[a]) / d[a]);
        else if (d[a] < 0.0f) s = fmin(s, (bound_lo - p[a]) / d[a]);
    }
    return s;
}

/* Index of the next segment to evaluate after segment k found its cell empty: the last one
 * whose midpoint is still inside the cell (so a skipped sample is never outside it). */
inline int skip_empty(const march_t *m, int k, int3 lo, int4 reso) {
    float s = cell_exit(m, lo, reso);
    float j = fmin(ceil(s / m->dt - 0.5f) - 1.0f, (float)m->nsteps);
    return max(k + 1, (int)j);
}

inline float lerp_density(const lerp_t *L, __global const float *density) {
    float s = 0.0f;
    for (int c = 0; c < 8; ++c)
        if (L->idx[c] >= 0) s += L->w[c] * density[L->idx[c]];
    return s;
}

/* Interpolated SH coefficients -> pre-activation colour per channel. */
inline float3 lerp_color_pre(const lerp_t *L, __global const float *sh, const float *Y) {
    float co[SH_DIM];
    for (int j = 0; j < SH_DIM; ++j) co[j] = 0.0f;
    for (int c = 0; c < 8; ++c) {
        if (L->idx[c] < 0) continue;
        __global const float *row = sh + (size_t)L->idx[c] * SH_DIM;
        const float w = L->w[c];
        for (int j = 0; j < SH_DIM; ++j) co[j] += w * row[j];
    }
    float pre[3];
    for (int ch = 0; ch < 3; ++ch) {
        float v = COLOR_OFFSET;
        for (int b = 0; b < SH_BASIS; ++b) v += co[ch * SH_BASIS + b] * Y[b];
        pre[ch] = v;
    }
    return (float3)(pre[0], pre[1], pre[2]);
}

typedef struct {
    float3 rgb;  /* foreground radiance, without background */
    float acc;   /* sum of weights */
    float depth; /* sum of weights times distance from the entry */
    float logT;  /* log transmittance at the end of the march */
} fwd_t;

/* The forward march shared by every kernel. */
inline void march_forward(const march_t *m, int4 reso, __global const int *links,
                          __global const float *density, __global const float *sh,
                          const float *Y, fwd_t *out) {
    ksum_t logT = {0.0f, 0.0f};
    float3 rgb = (float3)(0.0f);
    float acc = 0.0f, depth = 0.0f;
    for (int k = 0; k < m->nsteps; ++k) {
        float mid, delta;
        march_segment(m, k, &mid, &delta);
        lerp_t L;
        if (!lerp_setup(m->p0 + mid * m->dg, reso, links, &L)) {
            k = skip_empty(m, k, L.lo, reso) - 1;
            continue;
        }
        float sigma = lerp_density(&L, density);
        if (!(sigma > 0.0f)) continue;
        float tau = sigma * delta;
        float w = exp(logT.s) * alpha_from_tau(tau);
        float3 c = fmax(lerp_color_pre(&L, sh, Y), 0.0f);
        rgb += w * c;
        acc += w;
        depth += w * mid;
        ksum_add(&logT, -tau);
        if (exp(logT.s) < T_STOP) break;
    }
    out->rgb = rgb;
    out->acc = acc;
    out->depth = depth;
    out->logT = logT.s;
}

inline float3 load3(__global const float *a, int i) {
    return (float3)(a[3 * i], a[3 * i + 1], a[3 * i + 2]);
}

#endif /* CLRF_MARCH_H */
