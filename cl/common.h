/* common.h: shared types, named constants, safe math and the float atomic add.
 *
 * Every helper here has a float64 twin of the same name in clrf/references/reference.py.
 *
 * Defines read (all optional, each with its default):
 *   CLRF_NATIVE_FLOAT_ATOMICS  1 if the device reports cl_ext_float_atomics (set by the host)
 *   CLRF_ACQ_REL               1: try-locks with OpenCL C 3.0 acquire/release atomics (host)
 */
#ifndef CLRF_COMMON_H
#define CLRF_COMMON_H

#if defined(__clang__) && defined(__has_warning)
/* Clang on x86 without AVX-512 (PoCL's CPU target) warns that passing float16 to a builtin
 * "changes the ABI" (-Wpsabi). The builtins are compiled by the same compiler for the same
 * target as the kernels, so caller and callee agree; the warning says nothing about our code.
 * Only where the compiler knows the group: NVIDIA's clang warns of an unknown one. */
#if __has_warning("-Wpsabi")
#pragma clang diagnostic ignored "-Wpsabi"
#endif
#endif

/* The helpers of the grid march (march.h, volrend.h, sh.h, ray.h, grid_render.cl) are always
 * inlined: PoCL's LLVM kept march_visit, lerp_setup_cached_q, lerp_sh, prefetch_cell_grad and
 * march_forward_rec as calls, their state passed through memory (~45 % of the backward's
 * samples sat in them). In-process A/B on the Zen 4 (128^3 SH2 dense, 4,096 camera rays):
 * forward 11-13 % and fused forward + backward 10-11 % faster. */
#ifndef CLRF_INLINE   /* -D CLRF_INLINE=inline: the compiler's own choice, for comparison */
#define CLRF_INLINE inline __attribute__((always_inline))
#endif

#ifndef CLRF_NATIVE_FLOAT_ATOMICS
#define CLRF_NATIVE_FLOAT_ATOMICS 0  /* 1: use atomic_fetch_add on floats (OpenCL C 2.0+) */
#endif

/* a / b, 0 when b == 0 (used where the numerator is also 0 in the limit). */
CLRF_INLINE float safe_div(float a, float b) { return b != 0.0f ? a / b : 0.0f; }

/* Opacity 1 - exp(-tau) of a segment with optical depth tau >= 0, the one opacity function of
 * every renderer (grid and NeRF). As accurate as -expm1(-tau) but without its out-of-line
 * expm1 call, which cost a fifth of the forward march on PoCL:
 * tau <= ALPHA_SERIES_MAX: the series tau * sum_k (-tau)^k / (k+1)!, k = 0..10, in Horner form
 * (truncation < tau^12/12! <= 3e-11 at 0.7, far below float rounding; about 1.4 ulp of
 * rounding in all); above: 1 - exp(-tau). The split lies above ln 2, so exp(-tau) < 0.5 <
 * 1 - exp(-tau) there: an error of e ulp in exp costs at most e/2 ulp of the result, about
 * 1.5 ulp for OpenCL's 3-ulp bound on exp. (Split at 0.5 it cost twice that: NVIDIA's exp
 * gave 2.2 ulp.) */
#define ALPHA_SERIES_MAX 0.7f
CLRF_INLINE float alpha_of_tau(float tau) {
    if (tau > ALPHA_SERIES_MAX) return 1.0f - exp(-tau);
    float r = 1.0f / 39916800.0f;          /* 1/11! ... 1/1!, each step r = r * (-tau) + 1/k! */
    r = fma(r, -tau, 1.0f / 3628800.0f);
    r = fma(r, -tau, 1.0f / 362880.0f);
    r = fma(r, -tau, 1.0f / 40320.0f);
    r = fma(r, -tau, 1.0f / 5040.0f);
    r = fma(r, -tau, 1.0f / 720.0f);
    r = fma(r, -tau, 1.0f / 120.0f);
    r = fma(r, -tau, 1.0f / 24.0f);
    r = fma(r, -tau, 1.0f / 6.0f);
    r = fma(r, -tau, 0.5f);
    r = fma(r, -tau, 1.0f);
    return tau * r;
}

/* Kahan-compensated s += x: c carries the lost low-order part (s + c is the sum). The one
 * compensated add; ksum_t bundles s and c for running sums. */
CLRF_INLINE void kahan_add(float *s, float *c, float x) {
    const float y = x - *c;
    const float t = *s + y;
    *c = (t - *s) - y;
    *s = t;
}

typedef struct { float s; float c; } ksum_t;
CLRF_INLINE void ksum_add(ksum_t *k, float x) { kahan_add(&k->s, &k->c, x); }

/* The rows a kernel covers of a buffer of n: n, or fewer where `count` (one int on the device:
 * the live rows of a bounded buffer, written by an earlier kernel of the same queue) says so;
 * null: n. A step that keeps its sizes on the device launches every kernel over the buffer's
 * capacity n and passes the count: no size crosses to the host. */
CLRF_INLINE int live_rows(const int n, __global const int *count) {
    return count ? clamp(count[0], 0, n) : n;
}

/* live_rows rounded up to whole tiles of `tile` rows (scratch rows of tiled kernels), at most
 * n_rows (itself a multiple of tile). */
CLRF_INLINE int live_tile_rows(const int n_rows, __global const int *count, const int tile) {
    return count ? min(n_rows, (clamp(count[0], 0, n_rows) + tile - 1) / tile * tile) : n_rows;
}

/* Element i of an array of float triples [n, 3]. */
CLRF_INLINE float3 load3(__global const float *a, const size_t i) {
    return (float3)(a[3 * i], a[3 * i + 1], a[3 * i + 2]);
}

/* Atomic float add on global memory. Native where the device has it (or inline PTX on NVIDIA,
 * whose OpenCL has no float atomics), else a compare-and-swap
 * loop on the bit pattern (portable to every OpenCL 1.2 device). Every access to *p is atomic:
 * the loop starts from a guess of 0.0f (the value of a freshly zeroed gradient buffer) instead
 * of a plain read, which would race with other work-items' atomics (OpenCL memory model;
 * Oclgrind --data-races reports it). A wrong guess costs one compare-and-swap, which returns
 * the current value atomically. */
#ifndef CLRF_PTX_ATOMICS
#define CLRF_PTX_ATOMICS 0   /* 1 (the host, after a probe: clrf/runtime/programs.py): NVIDIA */
#endif
CLRF_INLINE void atomic_add_f(volatile __global float *p, float v) {
#if CLRF_NATIVE_FLOAT_ATOMICS && defined(__opencl_c_ext_fp32_global_atomic_add)
    atomic_fetch_add_explicit((volatile __global atomic_float *)p, v, memory_order_relaxed,
                              memory_scope_device);
#elif CLRF_PTX_ATOMICS
    /* NVIDIA: the relaxed reduction in L2 that CUDA's atomicAdd compiles to, by inline PTX */
    asm volatile("red.global.add.f32 [%0], %1;" : : "l"((ulong)p), "f"(v) : "memory");
#else
    /* the first guess is 0, not a plain read of *p: a plain read beside other work-items'
     * atomics is a data race by the OpenCL memory model (Oclgrind reports it) */
    union { unsigned int u; float f; } old, upd;
    old.u = 0u;
    do {
        upd.f = old.f + v;
        const unsigned int seen = atomic_cmpxchg((volatile __global unsigned int *)p, old.u,
                                                 upd.u);
        if (seen == old.u) break;
        old.u = seen;
    } while (1);
#endif
}

/* Try-locks (0 free, 1 held) that order the plain loads and stores made while holding them.
 * CLRF_ACQ_REL 1 (the host sets it, and builds with -cl-std=CL3.0, on devices with the
 * OpenCL C 3.0 features __opencl_c_atomic_order_acq_rel and __opencl_c_atomic_scope_device):
 * compare-and-swap with acquire and a release store, so under the OpenCL memory model what one
 * holder wrote happens-before what the next holder reads, in any work-group. CLRF_ACQ_REL 0:
 * OpenCL 1.2 atomics and fences, which order nothing between work-groups by the specification;
 * the host then does not choose the paths that take these locks (clrf/tuning.py) unless a
 * user forces them. lock_try returns 1 when the lock was taken. */
#ifndef CLRF_ACQ_REL
#define CLRF_ACQ_REL 0
#endif
#if CLRF_ACQ_REL
CLRF_INLINE int lock_try(volatile __global int *l) {
    int expected = 0;
    return atomic_compare_exchange_strong_explicit((volatile __global atomic_int *)l, &expected,
                                                   1, memory_order_acquire, memory_order_relaxed,
                                                   memory_scope_device);
}
CLRF_INLINE void lock_release(volatile __global int *l) {
    atomic_store_explicit((volatile __global atomic_int *)l, 0, memory_order_release,
                          memory_scope_device);
}
#else
CLRF_INLINE int lock_try(volatile __global int *l) {
    const int got = atomic_cmpxchg(l, 0, 1) == 0;
    mem_fence(CLK_GLOBAL_MEM_FENCE);
    return got;
}
CLRF_INLINE void lock_release(volatile __global int *l) {
    mem_fence(CLK_GLOBAL_MEM_FENCE);   /* the plain stores before the release */
    atomic_xchg(l, 0);
}
#endif

/* Atomic max for non-negative floats: their bit patterns order like signed ints. */
CLRF_INLINE void atomic_max_nonneg_f(volatile __global float *p, float v) {
    atomic_max((volatile __global int *)p, as_int(fmax(v, 0.0f)));
}


/* ---- activations (scalar and float16 overloads share one definition each) ---------------
 * softplus(x) = max(x, 0) + log1p(exp(-|x|)): never overflows, exact for large |x|.
 * sigmoid(x)  = 1 / (1 + exp(-x)) written with e = exp(-|x|) <= 1, so exp never overflows.
 * Their derivatives are written in terms of the OUTPUT y, which is what the MLP stores:
 *   relu'   = [y > 0],  softplus' = sigmoid(x) = 1 - exp(-y) = -expm1(-y),  sigmoid' = y (1 - y).
 */
#define CLRF_DEFINE_ACTIVATIONS(T)                                                            \
    inline T __attribute__((overloadable)) safe_softplus(T x) {                               \
        return fmax(x, (T)(0.0f)) + log1p(exp(-fabs(x)));                                     \
    }                                                                                         \
    inline T __attribute__((overloadable)) safe_sigmoid(T x) {                                \
        const T e = exp(-fabs(x));                                                            \
        const T r = (T)(1.0f) / ((T)(1.0f) + e);                                              \
        return select(e * r, r, x >= (T)(0.0f));                                              \
    }                                                                                         \
    inline T __attribute__((overloadable)) relu_grad_from_y(T y) {                            \
        return select((T)(0.0f), (T)(1.0f), y > (T)(0.0f));                                   \
    }                                                                                         \
    inline T __attribute__((overloadable)) softplus_grad_from_y(T y) { return -expm1(-y); }   \
    inline T __attribute__((overloadable)) sigmoid_grad_from_y(T y) {                         \
        return y * ((T)(1.0f) - y);                                                           \
    }
CLRF_DEFINE_ACTIVATIONS(float)
CLRF_DEFINE_ACTIVATIONS(float16)

/* ---- counter-based random numbers ---------------------------------------------------------
 * hash_u32 is the "lowbias32" integer hash (two multiply-xorshift rounds); its twin is
 * clrf.reference_nerf.hash_u32 (bit-exact). uniform01(key, counter) is in [0, 1) with 24 bits. */
#define CLRF_DEFINE_HASH_U32(NAME, T)                                                         \
    inline T NAME(T x) {                                                                      \
        x ^= x >> 16;                                                                         \
        x *= 0x7feb352dU;                                                                     \
        x ^= x >> 15;                                                                         \
        x *= 0x846ca68bU;                                                                     \
        x ^= x >> 16;                                                                         \
        return x;                                                                             \
    }
CLRF_DEFINE_HASH_U32(hash_u32, uint)
/* the same on 16 counters at once (explicit vectors: PoCL runs a per-item loop scalar) */
CLRF_DEFINE_HASH_U32(hash_u32x16, uint16)
#define CLRF_U24_SCALE 5.9604644775390625e-8f  /* 2^-24: maps a 24-bit integer into [0, 1) */
inline float uniform01(uint key, uint counter) {
    return (float)(hash_u32(key ^ hash_u32(counter)) >> 8) * CLRF_U24_SCALE;
}
inline float16 uniform01x16(uint key, uint16 counter) {
    return convert_float16(hash_u32x16((uint16)(key) ^ hash_u32x16(counter)) >> 8)
           * CLRF_U24_SCALE;
}


/* ---- sin(pi a), cos(pi a) with exact argument reduction ----------------------------------
 * a = n/2 + r with n = rint(2a) and |r| <= 1/4; r = a - n/2 is exact in float32 (it is a
 * multiple of ulp(a) and no larger than 1/4), and only n mod 4 matters, taken in float so any
 * finite a works. sin(pi r), cos(pi r) are Taylor polynomials to degree 11 / 12: truncation
 * < 1e-11 on |pi r| <= pi/4, so the result is accurate to a few ulp. Written on float3 with
 * selects (no branches, no library call): PoCL vectorises it across work-items, which its
 * sinpi/cospi did not. Twin: clrf.reference_nerf._sincospi (float64).
 * Caveat: scalar isequal returns 1, vector isequal -1; select tests the MSB for vectors and
 * non-zero for scalars, so both overloads select correctly. */
#define CLRF_PI_F 3.14159265358979323846f
#define CLRF_DEFINE_SINCOSPI(T, IT)                                                           \
    inline void __attribute__((overloadable)) sincospi_v(const T a, T *s_out, T *c_out) {     \
        const T nf = rint(2.0f * a);                                                          \
        const T r = a - 0.5f * nf;                                                            \
        const T q = nf - 4.0f * floor(0.25f * nf);        /* n mod 4, in {0, 1, 2, 3} */      \
        const T x = CLRF_PI_F * r, x2 = x * x;                                                \
        const T sp = x * (1.0f + x2 * (-1.0f / 6.0f + x2 * (1.0f / 120.0f                     \
                     + x2 * (-1.0f / 5040.0f + x2 * (1.0f / 362880.0f                         \
                     + x2 * (-1.0f / 39916800.0f))))));                                       \
        const T cp = 1.0f + x2 * (-0.5f + x2 * (1.0f / 24.0f + x2 * (-1.0f / 720.0f           \
                     + x2 * (1.0f / 40320.0f + x2 * (-1.0f / 3628800.0f                       \
                     + x2 * (1.0f / 479001600.0f))))));                                       \
        const IT odd = isequal(q, (T)(1.0f)) | isequal(q, (T)(3.0f));                         \
        const T s0 = select(sp, cp, odd), c0 = select(cp, sp, odd);                           \
        /* sin negated for n = 2, 3; cos negated for n = 1, 2 */                              \
        *s_out = select(s0, -s0, isgreaterequal(q, (T)(2.0f)));                               \
        *c_out = select(c0, -c0, isequal(q, (T)(1.0f)) | isequal(q, (T)(2.0f)));              \
    }
CLRF_DEFINE_SINCOSPI(float, int)
CLRF_DEFINE_SINCOSPI(float3, int3)
CLRF_DEFINE_SINCOSPI(float16, int16)

#endif /* CLRF_COMMON_H */
