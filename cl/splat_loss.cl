/* splat_loss.cl: the Gaussian-splatting training loss L = (1 - lam) L1 + lam (1 - SSIM) of a
 * render x against its target y and dL/dx, on the device (host: clrf/splat/loss.py; float64
 * twin: clrf/references/reference_ssim.py; the host float32 original: clrf/splat/model.py
 * ssim_and_grad).
 *
 * Layout: every image and plane is float32 [H, W, 3] C-contiguous, element i = (r W + c) 3 + ch,
 * n = 3 H W elements (n < 2^31); row r is the 3 W contiguous floats from r * 3 W (row_len).
 * Channels never mix. Planes of scratch follow each other n floats apart.
 *
 * The window: G is the separable Gaussian blur, 11 taps per axis, sigma 1.5, the taps
 * w_k = exp(-k^2 / (2 sigma^2)) / sum_{j=-5..5} exp(-j^2 / (2 sigma^2)), k = -5..5 (symmetric:
 * -D SSIM_W0 .. SSIM_W5 from the host), ZERO padding: (G a)[r, c] = sum_{i, j} w_i w_j
 * a[r + i, c + j] over the taps inside the image. This is scipy.ndimage.gaussian_filter(sigma
 * 1.5, truncate 5 / 1.5, mode "constant", cval 0) per channel. With zero padding G is
 * self-adjoint (G^T = G), so the backward blurs again.
 *
 * SSIM: per element, mx = G x, my = G y, sxx = G(x^2) - mx^2, syy = G(y^2) - my^2,
 * sxy = G(x y) - mx my, a1 = 2 mx my + C1, a2 = 2 sxy + C2, b1 = mx^2 + my^2 + C1,
 * b2 = sxx + syy + C2 (C1 = 0.01^2, C2 = 0.03^2: -D SSIM_C1, SSIM_C2),
 *   s = a1 a2 / (b1 b2),   SSIM = (1 / n) sum_i s_i  (every pixel and channel).
 * Its gradient, with the partials of s
 *   ds/dmx = 2 my a2 / (b1 b2) - s 2 mx / b1,  ds/dsxx = -s / b2,  ds/dsxy = 2 a1 / (b1 b2)
 * and the chain through mx in sxx and sxy (dsxx/dx = G^T(2 x .) - 2 mx dmx, dsxy/dx =
 * G^T(y .) - my dmx):
 *   A = ds/dmx - 2 mx ds/dsxx - my ds/dsxy,  Dxx = ds/dsxx,  Dxy = ds/dsxy,
 *   dSSIM/dx = (1 / n) (G A + 2 x G Dxx + y G Dxy).
 * The loss's gradient:  dL/dx = (1 - lam) sign(x - y) / n - lam dSSIM/dx  (sign(0) = 0).
 *
 * Work split (the four SSIM kernels): work-item g takes the elements [j0, j1) of one row,
 * j0 = (g % chunks) span, j1 = min(j0 + span, row_len), row = g / chunks, chunks =
 * ceil(row_len / span); the host launches height * chunks items. CPUs: span = row_len, one
 * work-item loops over a whole row of contiguous floats, which the compiler vectorises (the
 * horizontal passes split the loop into the two borders and a test-free interior; the vertical
 * passes zero the weights of taps outside the image, so their loop has no tests either).
 * GPUs: span = 1, neighbouring work-items take neighbouring floats.
 *
 * Kernels:
 *   ssim_blur_h5     P[k] = Gh(x, y, x^2, y^2, x y)[k], k = 0..4: the horizontal pass into five
 *                    planes P [5, n] (Gh: the taps along a row, 3 floats apart)
 *   ssim_terms       the vertical pass of P (Gv, row_len floats apart) gives mx, my, G(x^2),
 *                    G(y^2), G(x y); writes s_map [n] = s and Q [3, n] = scale (A, Dxx, Dxy),
 *                    where the caller passes scale = -lam / n
 *   ssim_blur_h3     R[k] = Gh(Q[k]), k = 0..2
 *   ssim_loss_grad   grad = l1_scale sign(x - y) + Gv(R[0]) + 2 x Gv(R[1]) + y Gv(R[2]),
 *                    l1_scale = (1 - lam) / n: the loss's gradient
 *   l1_loss_grad     grad = l1_scale sign(x - y): the loss's gradient when lam = 0 (no SSIM);
 *                    one work-item per element
 *   loss_stats       one work-item: stats [4] = (loss, L1, SSIM, MSE) from the sums of the
 *                    host's reduction (pyopencl ReductionKernel, clrf/splat/loss.py), a float8
 *                    of float pairs (hi, lo) of sum |x - y|, sum s (or 0), sum (x - y)^2 in
 *                    lanes (0, 1), (2, 3), (4, 5); loss = (1 - lam) L1 + lam (1 - SSIM);
 *                    has_ssim 0: SSIM = 1 (not computed), as in clrf/splat/model.py
 *                    loss_and_grad
 *   loss_stats_f64   the same from a double4 of the three sums (devices with fp64)
 *
 * Rounding: sxx = G(x^2) - mx^2 cancels in float32 as in the host's version (an absolute error
 * of a few ulp of G(x^2) <= ~1), then is divided by b2 >= C2: flat regions carry relative errors
 * of ~1e-4 in s and its partials (the tolerances in tests/test_splat_loss.py).
 *
 * Defines read: SSIM_W0 .. SSIM_W5 (taps at offsets 0..5), SSIM_C1, SSIM_C2; CLRF_HAS_FP64
 * (programs.build_options: loss_stats_f64 is built where it is 1).
 */
#include "common.h"

#ifndef SSIM_W0
#error "splat_loss.cl needs the window taps SSIM_W0 .. SSIM_W5 (clrf/splat/loss.py defines)"
#endif
#ifndef SSIM_C1
#define SSIM_C1 1e-4f
#endif
#ifndef SSIM_C2
#define SSIM_C2 9e-4f
#endif
#define SSIM_R 5                  /* window radius: 11 taps */
#define SSIM_EDGE (3 * SSIM_R)    /* floats of a row within SSIM_R pixels of its ends */
/* tap k = 1..5 (a constant after unrolling) */
#define SSIM_W(k) ((k) == 1 ? SSIM_W1 : (k) == 2 ? SSIM_W2 : (k) == 3 ? SSIM_W3 \
                   : (k) == 4 ? SSIM_W4 : SSIM_W5)

/* This work-item's row and its elements [*j0, *j1) of that row (the work split above). */
CLRF_INLINE int row_span(const int row_len, const int span, int *j0, int *j1) {
    const int chunks = (row_len + span - 1) / span;
    const int g = get_global_id(0);
    *j0 = (g % chunks) * span;
    *j1 = min(*j0 + span, row_len);
    return g / chunks;
}

/* The split of [j0, j1) into the left border [j0, *lo), the interior [*lo, *hi) (every
 * horizontal tap inside the row) and the right border [*hi, j1). */
CLRF_INLINE void interior(const int row_len, const int j0, const int j1, int *lo, int *hi) {
    *lo = clamp(SSIM_EDGE, j0, j1);
    *hi = clamp(row_len - SSIM_EDGE, *lo, j1);
}

/* (Gh a)[j] for element j of the row a (row_len floats), the taps 3 floats apart; checked: taps
 * outside the row read zero (else all are inside). */
CLRF_INLINE float blur_h(__global const float *a, const int j, const int row_len,
                         const bool checked) {
    float acc = SSIM_W0 * a[j];
#pragma unroll
    for (int k = 1; k <= SSIM_R; k++) {
        const float lo = !checked || j - 3 * k >= 0 ? a[j - 3 * k] : 0.0f;
        const float hi = !checked || j + 3 * k < row_len ? a[j + 3 * k] : 0.0f;
        acc = fma(SSIM_W(k), lo + hi, acc);
    }
    return acc;
}

/* The vertical taps of one row: the weights of taps above (lo) and below (hi), zero where the
 * tap falls outside the image, and their offsets in floats, 0 there (a tap of weight 0 reads
 * the element itself and adds exactly 0). */
typedef struct {
    float wlo[SSIM_R + 1], whi[SSIM_R + 1];
    int olo[SSIM_R + 1], ohi[SSIM_R + 1];
} vtaps_t;

CLRF_INLINE vtaps_t vertical_taps(const int row, const int height, const int row_len) {
    vtaps_t t;
#pragma unroll
    for (int k = 1; k <= SSIM_R; k++) {
        const bool lo_in = row - k >= 0, hi_in = row + k < height;
        t.wlo[k] = lo_in ? SSIM_W(k) : 0.0f;
        t.whi[k] = hi_in ? SSIM_W(k) : 0.0f;
        t.olo[k] = lo_in ? -k * row_len : 0;
        t.ohi[k] = hi_in ? k * row_len : 0;
    }
    return t;
}

/* (Gv a)[i] with the row's taps t. */
CLRF_INLINE float blur_v(__global const float *a, const int i, const vtaps_t *t) {
    float acc = SSIM_W0 * a[i];
#pragma unroll
    for (int k = 1; k <= SSIM_R; k++)
        acc = fma(t->wlo[k], a[i + t->olo[k]], fma(t->whi[k], a[i + t->ohi[k]], acc));
    return acc;
}

/* The five horizontal moments at element j of rows x, y (checked: as in blur_h). */
CLRF_INLINE void h5_at(__global const float *x, __global const float *y, const int j,
                       const int row_len, const bool checked, __global float *P, const int n) {
    const float x0 = x[j], y0 = y[j];
    float mx = SSIM_W0 * x0, my = SSIM_W0 * y0, exx = SSIM_W0 * x0 * x0,
          eyy = SSIM_W0 * y0 * y0, exy = SSIM_W0 * x0 * y0;
#pragma unroll
    for (int k = 1; k <= SSIM_R; k++) {
        const bool lo_in = !checked || j - 3 * k >= 0, hi_in = !checked || j + 3 * k < row_len;
        const float xl = lo_in ? x[j - 3 * k] : 0.0f, yl = lo_in ? y[j - 3 * k] : 0.0f;
        const float xh = hi_in ? x[j + 3 * k] : 0.0f, yh = hi_in ? y[j + 3 * k] : 0.0f;
        const float w = SSIM_W(k);
        mx = fma(w, xl + xh, mx);
        my = fma(w, yl + yh, my);
        exx = fma(w, xl * xl + xh * xh, exx);
        eyy = fma(w, yl * yl + yh * yh, eyy);
        exy = fma(w, xl * yl + xh * yh, exy);
    }
    P[j] = mx;
    P[n + j] = my;
    P[2 * n + j] = exx;
    P[3 * n + j] = eyy;
    P[4 * n + j] = exy;
}

__kernel void ssim_blur_h5(const int width, const int height, const int span,
                           __global const float *restrict x, __global const float *restrict y,
                           __global float *restrict P) {
    const int row_len = 3 * width, n = row_len * height;
    int j0, j1, lo, hi;
    const int row = row_span(row_len, span, &j0, &j1);
    if (row >= height) return;
    interior(row_len, j0, j1, &lo, &hi);
    const int base = row * row_len;
    x += base;
    y += base;
    P += base;
    for (int j = j0; j < lo; j++) h5_at(x, y, j, row_len, true, P, n);
    for (int j = lo; j < hi; j++) h5_at(x, y, j, row_len, false, P, n);
    for (int j = hi; j < j1; j++) h5_at(x, y, j, row_len, true, P, n);
}

__kernel void ssim_terms(const int width, const int height, const int span,
                         __global const float *restrict P, const float scale,
                         __global float *restrict s_map, __global float *restrict Q) {
    const int row_len = 3 * width, n = row_len * height;
    int j0, j1;
    const int row = row_span(row_len, span, &j0, &j1);
    if (row >= height) return;
    const vtaps_t t = vertical_taps(row, height, row_len);
    for (int i = row * row_len + j0; i < row * row_len + j1; i++) {
        const float mx = blur_v(P, i, &t);
        const float my = blur_v(P + n, i, &t);
        const float exx = blur_v(P + 2 * n, i, &t);
        const float eyy = blur_v(P + 3 * n, i, &t);
        const float exy = blur_v(P + 4 * n, i, &t);
        const float sxx = fma(-mx, mx, exx), syy = fma(-my, my, eyy), sxy = fma(-mx, my, exy);
        const float a1 = 2.0f * mx * my + SSIM_C1, a2 = 2.0f * sxy + SSIM_C2;
        const float b1 = mx * mx + my * my + SSIM_C1, b2 = sxx + syy + SSIM_C2;
        const float inv_b = 1.0f / (b1 * b2);
        const float s = a1 * a2 * inv_b;
        const float d_mx = 2.0f * my * a2 * inv_b - s * 2.0f * mx / b1;
        const float d_sxx = -s / b2;
        const float d_sxy = 2.0f * a1 * inv_b;
        s_map[i] = s;
        Q[i] = scale * (d_mx - 2.0f * mx * d_sxx - my * d_sxy);
        Q[n + i] = scale * d_sxx;
        Q[2 * n + i] = scale * d_sxy;
    }
}

CLRF_INLINE void h3_at(__global const float *Q, const int j, const int row_len,
                       const bool checked, __global float *R, const int n) {
    R[j] = blur_h(Q, j, row_len, checked);
    R[n + j] = blur_h(Q + n, j, row_len, checked);
    R[2 * n + j] = blur_h(Q + 2 * n, j, row_len, checked);
}

__kernel void ssim_blur_h3(const int width, const int height, const int span,
                           __global const float *restrict Q, __global float *restrict R) {
    const int row_len = 3 * width, n = row_len * height;
    int j0, j1, lo, hi;
    const int row = row_span(row_len, span, &j0, &j1);
    if (row >= height) return;
    interior(row_len, j0, j1, &lo, &hi);
    Q += row * row_len;
    R += row * row_len;
    for (int j = j0; j < lo; j++) h3_at(Q, j, row_len, true, R, n);
    for (int j = lo; j < hi; j++) h3_at(Q, j, row_len, false, R, n);
    for (int j = hi; j < j1; j++) h3_at(Q, j, row_len, true, R, n);
}

__kernel void ssim_loss_grad(const int width, const int height, const int span,
                             __global const float *restrict x, __global const float *restrict y,
                             __global const float *restrict R, const float l1_scale,
                             __global float *restrict grad) {
    const int row_len = 3 * width, n = row_len * height;
    int j0, j1;
    const int row = row_span(row_len, span, &j0, &j1);
    if (row >= height) return;
    const vtaps_t t = vertical_taps(row, height, row_len);
    for (int i = row * row_len + j0; i < row * row_len + j1; i++) {
        const float xi = x[i], yi = y[i];
        const float ga = blur_v(R, i, &t);
        const float gxx = blur_v(R + n, i, &t);
        const float gxy = blur_v(R + 2 * n, i, &t);
        grad[i] = fma(l1_scale, sign(xi - yi), ga + 2.0f * xi * gxx + yi * gxy);
    }
}

/* The L1 term's gradient alone (lam = 0), one work-item per element i < n. */
__kernel void l1_loss_grad(const int n, __global const float *restrict x,
                           __global const float *restrict y, const float l1_scale,
                           __global float *restrict grad) {
    const int i = get_global_id(0);
    if (i >= n) return;
    grad[i] = l1_scale * sign(x[i] - y[i]);
}

/* stats = (loss, L1, SSIM, MSE) from the reduction's sums (see the header): float pairs. */
__kernel void loss_stats(__global const float8 *sums, const int n, const float lam,
                         const int has_ssim, __global float *stats) {
    if (get_global_id(0) != 0) return;
    const float8 t = sums[0];
    const float l1 = (t.s0 + t.s1) / (float)n;
    const float ssim = has_ssim ? (t.s2 + t.s3) / (float)n : 1.0f;
    const float mse = (t.s4 + t.s5) / (float)n;
    stats[0] = (1.0f - lam) * l1 + lam * (1.0f - ssim);
    stats[1] = l1;
    stats[2] = ssim;
    stats[3] = mse;
}

#if CLRF_HAS_FP64
#pragma OPENCL EXTENSION cl_khr_fp64 : enable
/* The same from double sums (lanes |x - y|, s, (x - y)^2), the loss formed in double. */
__kernel void loss_stats_f64(__global const double4 *sums, const int n, const float lam,
                             const int has_ssim, __global float *stats) {
    if (get_global_id(0) != 0) return;
    const double4 t = sums[0] / (double)n;
    const double ssim = has_ssim ? t.y : 1.0;
    stats[0] = (float)((1.0 - lam) * t.x + lam * (1.0 - ssim));
    stats[1] = (float)t.x;
    stats[2] = (float)ssim;
    stats[3] = (float)t.z;
}
#endif
