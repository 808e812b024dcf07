/* ray.h: ray / axis-aligned box intersection.
 *
 * Slab method written so that direction components of exactly 0 or of any tiny magnitude
 * (1e-30) give the right answer with no NaN: a zero component makes the slab either the whole
 * line (origin inside it) or empty; a non-zero one divides a finite numerator, so the
 * parameters are finite or +-inf but never NaN. Mirrored by reference.ray_box.
 */
#ifndef CLRF_RAY_H
#define CLRF_RAY_H

#ifndef CLRF_HAS_FP64
#define CLRF_HAS_FP64 0  /* 1: per-ray set-up (box entry, step count) in double precision */
#endif
/* Type of the once-per-ray set-up arithmetic: double where the device has it, so that an
 * origin 1e4 units outside the box still enters it at the right point. */
#if CLRF_HAS_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
typedef double real_t;
typedef double3 real3;
#define REAL3(v) convert_double3(v)
#else
typedef float real_t;
typedef float3 real3;
#define REAL3(v) (v)
#endif

/* One slab [lo, hi] on one axis; narrows [*t0, *t1]. */
CLRF_INLINE void ray_slab(real_t o, real_t d, real_t lo, real_t hi, real_t *t0, real_t *t1) {
    if (d == 0.0f) {
        if (o < lo || o > hi) { *t0 = INFINITY; *t1 = -INFINITY; }
        return;
    }
    real_t a = (lo - o) / d, b = (hi - o) / d;
    *t0 = fmax(*t0, fmin(a, b));
    *t1 = fmin(*t1, fmax(a, b));
}

/* Intersect o + t d, t >= 0, with the box [lo, hi]. Returns 1 and [t0, t1] on a hit of
 * positive length, else 0. */
CLRF_INLINE int ray_box(real3 o, real3 d, real3 lo, real3 hi, real_t *t0, real_t *t1) {
    *t0 = 0.0f;
    *t1 = INFINITY;
    ray_slab(o.x, d.x, lo.x, hi.x, t0, t1);
    ray_slab(o.y, d.y, lo.y, hi.y, t0, t1);
    ray_slab(o.z, d.z, lo.z, hi.z, t0, t1);
    return *t1 > *t0;
}

#endif /* CLRF_RAY_H */
