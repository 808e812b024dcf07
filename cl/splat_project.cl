/* splat_project.cl: projection of anisotropic 3D Gaussians to screen-space splats (forward) and
 * its backward, one work-item per Gaussian. Conventions and camera layout: splat.h.
 *
 * Inputs (float32, row-major, Gaussian i):
 *   means [N, 3] m_i, log_scales [N, 3], quats [N, 4] (w, x, y, z; normalised here),
 *   opacity_logits [N], sh [N, SH_BASIS, 3] (basis b, channel c at (i SH_BASIS + b) 3 + c),
 *   cam [CAM_FLOATS] (splat.h), width, height in pixels, ntx x nty tiles.
 *
 * Forward (splat_project):
 *   t = R m + t_cam,  q^ = q / |q|,  S = diag(exp(log_scales)),  M = Rot(q^) S,
 *   Sigma3 = M M^T,  Sigma2 = T Sigma3 T^T + COV_DILATION I,  T = J R   (EWA; splat.h
 *     splat_project_one has J and the frustum clamp of x/z, y/z),
 *   xy = (fx t_x / t_z + cx, fy t_y / t_z + cy),  conic = Sigma2^-1 as (A, B, C),
 *   radius = SIGMA_RADIUS sqrt(lambda_max(Sigma2)),  depth = t_z,
 *   colour_c = max(0, 0.5 + sum_b Y_b(v) sh[b, c]),  v = (m - campos) / |m - campos|
 *     (sh.h's real SH basis, which has the signs and order of the original 3DGS code),
 *   opacity = sigmoid(logit),
 *   rect = tiles [x0, x1) x [y0, y1) overlapping the square xy +- radius:
 *     x0 = clamp(floor((xy_x - radius) / TILE), 0, ntx), x1 = clamp(floor((xy_x + radius) / TILE)
 *     + 1, 0, ntx) (float32, then int), y likewise with nty.
 * Outputs: xy [N, 2], conic [N, 3], radius [N], depth [N], color [N, 3], opacity [N],
 * rect [N, 4] int (x0, y0, x1, y1). Culled Gaussians (t_z <= near, q = 0, det Sigma2 <= 0 after
 * scaling, or a Sigma2 beyond float32) get zeros everywhere, so radius 0 and an empty rect.
 *
 * Backward (splat_project_backward): given dL/dxy, dL/dconic (w.r.t. the three stored values),
 * dL/dcolor, dL/dopacity per Gaussian, writes dL/dmeans, dL/dlog_scales, dL/dquats,
 * dL/dopacity_logits, dL/dsh (overwritten, not added; zeros for culled Gaussians). With symmetric
 * matrix gradients G (dL = tr(G dX)):
 *   G_Q = [[gA, gB/2], [gB/2, gC]],  G_S2 = -Q G_Q Q,  G_S3 = T^T G_S2 T,  dL/dT = 2 G_S2 T Sigma3,
 *   dL/dJ = dL/dT R^T;  J depends on t through z and, where the clamp is inactive, through x/z,
 *   y/z (a clamped ratio is a constant: dJ02/dt_z = fx rx / z^2 there, not the unclamped
 *   2 fx t_x / z^3 of the original code, whose derivative ignores the clamp);
 *   dL/dt += (gx fx / z, gy fy / z, -(gx fx t_x + gy fy t_y) / z^2)   (the mean in pixels);
 *   dL/dM = 2 G_S3 M,  dL/dlog_s_k = s_k sum_j dL/dM_jk Rot_jk,  dL/dRot_jk = s_k dL/dM_jk,
 *   dL/dq^ from Rot(q^) (quadratic in q^), dL/dq = (dL/dq^ - q^ (q^ . dL/dq^)) / |q|;
 *   colour: dL/dsh[b, c] = Y_b gc_c with gc_c = dL/dcolor_c where the unclamped colour >= 0
 *   (else 0); the view direction's dependence on the mean IS included (as in the original 3DGS
 *   code): dL/dv = sum_b (sum_c gc_c sh[b, c]) dY_b/dv, dL/dm += (dL/dv - v (v . dL/dv)) / |m -
 *   campos|;  dL/dlogit = dL/dopacity o (1 - o);  dL/dm += R^T dL/dt.
 *
 * The camera's gradient (POSE_GRAD=1, splat.pose_opt: clrf/splat/pose.py): the backward also
 * writes each Gaussian's share of dL/dR and dL/dt of the world-to-camera transform (R, t),
 * d_cam [12, N] component-major (d_cam[k N + i]: k = 3 r + c for dL/dR[r, c], 9 + r for
 * dL/dt[r]; the host sums over i). R enters through t_c = R m + t, through T = J R and through
 * the camera centre campos = -R^T t of the view direction (dL/dcampos = -g_dir, g_dir the view
 * direction's pull on the mean above):
 *   dL/dR = g_t m^T + J^T dL/dT + t g_dir^T,   dL/dt = g_t + R g_dir,
 * g_t = dL/dt_c with every term above (the mean in pixels and J's dependence on t_c).
 *
 * Anti-aliasing (ANTIALIASED=1, splat.antialiased; Mip-Splatting, Yu et al. 2024): both
 * kernels take one more input, filter3d [N], each Gaussian's 3D filter variance f2 (the
 * training views' sampling limit, splat_filter3d below), which widens it and scales
 * its opacity so that its integral is kept, and the screen-space dilation is compensated alike:
 *   se_k = sqrt(s_k^2 + f2)  (Sigma3 = Rot diag(se^2) Rot^T),  c3 = prod_k s_k / se_k,
 *   c2 = sqrt(max(0, det(Sigma2 - COV_DILATION I) / det(Sigma2))),  opacity = sigmoid(logit) c3 c2.
 * Here the host sets COV_DILATION to the 2D filter, splat.aa_filter2d (Mip-Splatting's 0.1 px^2:
 * with the 3D filter's 0.2 of a training pixel it makes up the plain projection's 0.3).
 * Backward: dL/dc = dL/dopacity sigmoid(logit); c2 adds to G_S2 through the two
 * determinants (d c2 = c2 / 2 (d det0 / det0 - d det1 / det1)); c3 adds
 * dL/dc3 c3 f2 / se_k^2 to dL/dlog_s_k, and the covariance's share of dL/dlog_s_k is
 * dL/dse_k s_k^2 / se_k. Without ANTIALIASED the outputs are bit for bit those without it.
 *
 * splat_filter3d: f2 [N] of each Gaussian from the training cameras cams [V, CAM_FLOATS]
 * (each of width x height pixels): over the cameras that see its mean (t_z > near and the
 * projection within FILTER3D_MARGIN of the image on every side), the finest sampling interval
 * in world units, min t_z / fx; f2 = FILTER3D_VAR (that interval)^2 (Mip-Splatting's 3D
 * filter). A Gaussian no camera sees gets -1 (the host gives it the largest f2 of the others).
 *
 * Defines read: SH_DEGREE (sh.h), TILE, POSE_GRAD (0 or 1, default 0), ANTIALIASED (0 or 1,
 * default 0) and the constants of splat.h.
 * Twin: clrf/references/reference_splat.py project / project_backward / camera_backward
 * (float64).
 */
#include "common.h"
#include "sh.h"
#include "splat.h"

#ifndef POSE_GRAD
#define POSE_GRAD 0
#endif
#ifndef ANTIALIASED
#define ANTIALIASED 0
#endif
/* Gaussian i's 3D filter variance: the kernels' filter3d input, or none */
#if ANTIALIASED
#define SPLAT_F2(i) filter3d[i]
#else
#define SPLAT_F2(i) 0.0f
#endif
#ifndef FILTER3D_VAR
#define FILTER3D_VAR 0.2f       /* the 3D filter's variance in sampling intervals squared */
#endif
#ifndef FILTER3D_MARGIN
#define FILTER3D_MARGIN 0.15f   /* a camera sees a mean within this share of the image outside */
#endif

/* Loads and stores of 2, 3, 4 floats as scalar accesses, the loops unrolled, no hypot and no
 * early exit for culled Gaussians (their outputs are selected to zero): on 2 vCPUs of a Xeon
 * with PoCL 3.1 that took the forward from 15.3 to 10 ms and the backward from 22 to 14 ms over
 * 176k Gaussians. PoCL still runs both a work-item at a time: its loop vectoriser refuses a loop
 * with any instruction of a vector type, and a rewrite in scalars alone did not help (the
 * front end's SLP pass pairs scalars into <2 x float> operations before PoCL vectorises, and
 * PoCL takes no option to stop it). Running Gaussians in explicit float8 / float16 lanes, as the
 * rasteriser's rows shape does, is what would. */
CLRF_INLINE float2 ld2(__global const float *a, const size_t i) {
    return (float2)(a[2 * i], a[2 * i + 1]);
}
CLRF_INLINE float4 ld4(__global const float *a, const size_t i) {
    return (float4)(a[4 * i], a[4 * i + 1], a[4 * i + 2], a[4 * i + 3]);
}
CLRF_INLINE void st2(const float2 v, __global float *a, const size_t i) {
    a[2 * i] = v.x;
    a[2 * i + 1] = v.y;
}
CLRF_INLINE void st3(const float3 v, __global float *a, const size_t i) {
    a[3 * i] = v.x;
    a[3 * i + 1] = v.y;
    a[3 * i + 2] = v.z;
}
CLRF_INLINE void st4(const float4 v, __global float *a, const size_t i) {
    a[4 * i] = v.x;
    a[4 * i + 1] = v.y;
    a[4 * i + 2] = v.z;
    a[4 * i + 3] = v.w;
}

/* Everything the projection of one Gaussian computes; the backward reads the intermediates. */
typedef struct {
    int visible;       /* 0: culled (see the header); the outputs are then zeros */
    float3 tc;         /* camera-space mean */
    float4 qn;         /* unit quaternion (w, x, y, z) */
    float qlen;        /* |q| before normalising */
    float s[3];        /* scales exp(log_scale) */
    float se[3];       /* the scales Sigma3 is built from: s, or sqrt(s^2 + f2) (ANTIALIASED) */
    float c3, c2;      /* opacity factors of the 3D and 2D filters (1 without ANTIALIASED) */
    float det0n, detn; /* det of Sigma2 without and with the dilation, over sc^2 */
    float sc;          /* max(a, c): the scale the conic is formed at */
    float Rq[9];       /* rotation of qn, row-major */
    float S3[9];       /* Sigma3 = Rq diag(s^2) Rq^T, row-major (symmetric) */
    float rx, ry;      /* x/z, y/z clamped to +-FRUSTUM_GUARD tan(half fov) */
    int clamp_x, clamp_y;   /* 1 where the clamp is active (|x/z| > the limit) */
    float Tm[6];       /* T = J R (2 x 3, row-major), J the perspective Jacobian at (rx, ry) */
    float V[6];        /* T Sigma3 (2 x 3, row-major) */
    float a, b, c;     /* Sigma2 = T Sigma3 T^T + COV_DILATION I, [[a, b], [b, c]] */
    float3 conic;      /* (A, B, C) = Sigma2^-1 */
    float2 xy;         /* mean in pixels */
    float radius;      /* SIGMA_RADIUS sqrt(largest eigenvalue of Sigma2) */
} splat_proj_t;

/* The projection of Gaussian (m, ls, q) into *out, shared by the forward and the backward so
 * that both cull the same Gaussians. The frustum tangents are width / (2 fx), height / (2 fy)
 * (a centred principal point, as 3DGS). The conic is formed from Sigma2 / max(a, c) so that
 * its determinant cannot overflow. An out-pointer, not a returned struct: a struct return is
 * inlined with an llvm.experimental.noalias.scope.decl, which Oclgrind 21.10 cannot run. */
CLRF_INLINE void splat_project_one(const float3 m, const float3 ls, const float4 q,
                                   const float f2, __global const float *cam, const int width,
                                   const int height, splat_proj_t *out) {
    splat_proj_t P;
    const float fx = cam[CAM_FX], fy = cam[CAM_FY];
    P.tc = (float3)(cam[CAM_R + 0] * m.x + cam[CAM_R + 1] * m.y + cam[CAM_R + 2] * m.z
                        + cam[CAM_T],
                    cam[CAM_R + 3] * m.x + cam[CAM_R + 4] * m.y + cam[CAM_R + 5] * m.z
                        + cam[CAM_T + 1],
                    cam[CAM_R + 6] * m.x + cam[CAM_R + 7] * m.y + cam[CAM_R + 8] * m.z
                        + cam[CAM_T + 2]);
    const float qq = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w;
    P.visible = P.tc.z > cam[CAM_NEAR] && qq > 0.0f;
    P.qlen = sqrt(qq);
    P.qn = P.visible ? q / P.qlen : (float4)(1.0f, 0.0f, 0.0f, 0.0f);
    P.s[0] = exp(ls.x);
    P.s[1] = exp(ls.y);
    P.s[2] = exp(ls.z);
#if ANTIALIASED
    P.c3 = 1.0f;
#pragma unroll
    for (int k = 0; k < 3; ++k) {
        P.se[k] = sqrt(P.s[k] * P.s[k] + f2);
        P.c3 *= P.s[k] / P.se[k];
    }
#else
    P.se[0] = P.s[0];
    P.se[1] = P.s[1];
    P.se[2] = P.s[2];
    P.c3 = 1.0f;
#endif
    splat_quat_rot(P.qn, P.Rq);
#pragma unroll
    for (int i = 0; i < 3; ++i)
#pragma unroll
        for (int j = 0; j < 3; ++j) {
            float acc = 0.0f;
#pragma unroll
            for (int k = 0; k < 3; ++k)
                acc += P.Rq[3 * i + k] * (P.se[k] * P.se[k]) * P.Rq[3 * j + k];
            P.S3[3 * i + j] = acc;
        }
    const float z = P.visible ? P.tc.z : 1.0f;
    const float lim_x = FRUSTUM_GUARD * 0.5f * (float)width / fx;
    const float lim_y = FRUSTUM_GUARD * 0.5f * (float)height / fy;
    const float ux = P.tc.x / z, uy = P.tc.y / z;
    P.clamp_x = fabs(ux) > lim_x;
    P.clamp_y = fabs(uy) > lim_y;
    P.rx = clamp(ux, -lim_x, lim_x);
    P.ry = clamp(uy, -lim_y, lim_y);
    const float J00 = fx / z, J02 = -fx * P.rx / z, J11 = fy / z, J12 = -fy * P.ry / z;
#pragma unroll
    for (int k = 0; k < 3; ++k) {
        P.Tm[k] = J00 * cam[CAM_R + k] + J02 * cam[CAM_R + 6 + k];
        P.Tm[3 + k] = J11 * cam[CAM_R + 3 + k] + J12 * cam[CAM_R + 6 + k];
    }
#pragma unroll
    for (int i = 0; i < 2; ++i)
#pragma unroll
        for (int j = 0; j < 3; ++j)
            P.V[3 * i + j] = P.Tm[3 * i] * P.S3[j] + P.Tm[3 * i + 1] * P.S3[3 + j]
                             + P.Tm[3 * i + 2] * P.S3[6 + j];
    P.a = P.V[0] * P.Tm[0] + P.V[1] * P.Tm[1] + P.V[2] * P.Tm[2] + COV_DILATION;
    P.b = P.V[0] * P.Tm[3] + P.V[1] * P.Tm[4] + P.V[2] * P.Tm[5];
    P.c = P.V[3] * P.Tm[3] + P.V[4] * P.Tm[4] + P.V[5] * P.Tm[5] + COV_DILATION;
    const float sc = fmax(P.a, P.c);
    const float an = P.a / sc, bn = P.b / sc, cn = P.c / sc;
    const float detn = an * cn - bn * bn;
    P.sc = sc;
    P.detn = detn;
#if ANTIALIASED
    {
        const float dn = COV_DILATION / sc;
        P.det0n = (an - dn) * (cn - dn) - bn * bn;
        P.c2 = P.det0n > 0.0f && detn > 0.0f ? sqrt(P.det0n / detn) : 0.0f;
    }
#else
    P.det0n = detn;
    P.c2 = 1.0f;
#endif
    P.visible = P.visible && isfinite(P.a) && isfinite(P.b) && isfinite(P.c) && detn > 0.0f;
    const float inv = P.visible ? 1.0f / (detn * sc) : 0.0f;
    P.conic = (float3)(cn * inv, -bn * inv, an * inv);
    P.visible = P.visible && isfinite(P.conic.x) && isfinite(P.conic.y) && isfinite(P.conic.z);
    P.xy = (float2)(fx * P.tc.x / z + cam[CAM_CX], fy * P.tc.y / z + cam[CAM_CY]);
    /* hypot(u, v) without overflow, as the max times the root of the ratios' squares */
    const float hu = fabs(0.5f * (P.a - P.c)), hv = fabs(P.b), hm = fmax(hu, hv);
    const float hr = fmin(hu, hv) / fmax(hm, FLT_MIN);
    const float lam = 0.5f * (P.a + P.c) + hm * sqrt(1.0f + hr * hr);
    P.radius = P.visible ? SIGMA_RADIUS * sqrt(lam) : 0.0f;
    *out = P;
}

/* Unit view direction from the camera centre to m, and the distance. */
CLRF_INLINE float3 splat_view_dir(const float3 m, __global const float *cam, float *dist) {
    const float3 v = m - (float3)(cam[CAM_POS], cam[CAM_POS + 1], cam[CAM_POS + 2]);
    *dist = sqrt(v.x * v.x + v.y * v.y + v.z * v.z);
    return v / *dist;
}

/* Tile index range [lo, hi) covering [centre - radius, centre + radius] along one axis. */
CLRF_INLINE int2 splat_tile_span(const float centre, const float radius, const int ntiles) {
    const float lo = clamp(floor((centre - radius) / (float)TILE), 0.0f, (float)ntiles);
    const float hi = clamp(floor((centre + radius) / (float)TILE) + 1.0f, 0.0f, (float)ntiles);
    return (int2)((int)lo, (int)hi);
}

__kernel void splat_project(const int n, __global const float *means,
                            __global const float *log_scales, __global const float *quats,
                            __global const float *opacity_logits, __global const float *sh,
                            __global const float *cam, const int width, const int height,
                            const int ntx, const int nty, __global float *xy,
                            __global float *conic, __global float *radius, __global float *depth,
                            __global float *color, __global float *opacity,
                            __global int *rect
#if ANTIALIASED
                            , __global const float *filter3d
#endif
                            ) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float3 m = load3(means, i);
    splat_proj_t P;
    const float f2 = SPLAT_F2(i);
    splat_project_one(m, load3(log_scales, i), ld4(quats, i), f2, cam, width, height, &P);
    /* culled Gaussians compute the same and store zeros (an early exit kept this scalar) */
    const int v = P.visible;
    float dist;
    const float3 dir = splat_view_dir(m, cam, &dist);
    float Y[SH_BASIS];
    sh_basis(dir, Y);
    float3 col = (float3)(0.5f);
#pragma unroll
    for (int b = 0; b < SH_BASIS; ++b) col += Y[b] * load3(sh, (size_t)i * SH_BASIS + b);
    st2(v ? P.xy : (float2)(0.0f), xy, i);
    st3(v ? P.conic : (float3)(0.0f), conic, i);
    radius[i] = v ? P.radius : 0.0f;
    depth[i] = v ? P.tc.z : 0.0f;
    st3(v ? (float3)(fmax(col.x, 0.0f), fmax(col.y, 0.0f), fmax(col.z, 0.0f)) : (float3)(0.0f),
        color, i);
#if ANTIALIASED
    opacity[i] = v ? safe_sigmoid(opacity_logits[i]) * (P.c3 * P.c2) : 0.0f;
#else
    opacity[i] = v ? safe_sigmoid(opacity_logits[i]) : 0.0f;
#endif
    const int2 sx = splat_tile_span(P.xy.x, P.radius, ntx);
    const int2 sy = splat_tile_span(P.xy.y, P.radius, nty);
    rect[4 * i] = v ? sx.x : 0;
    rect[4 * i + 1] = v ? sy.x : 0;
    rect[4 * i + 2] = v ? sx.y : 0;
    rect[4 * i + 3] = v ? sy.y : 0;
}

__kernel void splat_project_backward(const int n, __global const float *means,
                                     __global const float *log_scales,
                                     __global const float *quats,
                                     __global const float *opacity_logits,
                                     __global const float *sh, __global const float *cam,
                                     const int width, const int height,
                                     __global const float *g_xy, __global const float *g_conic,
                                     __global const float *g_color,
                                     __global const float *g_opacity, __global float *d_means,
                                     __global float *d_log_scales, __global float *d_quats,
                                     __global float *d_logits, __global float *d_sh
#if ANTIALIASED
                                     , __global const float *filter3d
#endif
#if POSE_GRAD
                                     , __global float *d_cam
#endif
                                     ) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float3 m = load3(means, i);
    splat_proj_t P;
    const float f2 = SPLAT_F2(i);
    splat_project_one(m, load3(log_scales, i), ld4(quats, i), f2, cam, width, height, &P);
    /* culled Gaussians compute the same and store zeros (no early exit, as the forward) */
    const int v = P.visible;
    const float fx = cam[CAM_FX], fy = cam[CAM_FY];
    const float z = P.tc.z;

    /* colour: clamp mask, SH coefficients, and the view direction's pull on the mean */
    float dist;
    const float3 dir = splat_view_dir(m, cam, &dist);
    float Y[SH_BASIS];
    sh_basis(dir, Y);
    float3 col = (float3)(0.5f);
#pragma unroll
    for (int b = 0; b < SH_BASIS; ++b) col += Y[b] * load3(sh, (size_t)i * SH_BASIS + b);
    float3 gc = load3(g_color, i);
    gc = (float3)(col.x < 0.0f ? 0.0f : gc.x, col.y < 0.0f ? 0.0f : gc.y,
                  col.z < 0.0f ? 0.0f : gc.z);
    float w[SH_BASIS];
#pragma unroll
    for (int b = 0; b < SH_BASIS; ++b) {
        const float3 shb = load3(sh, (size_t)i * SH_BASIS + b);
        st3(v ? Y[b] * gc : (float3)(0.0f), d_sh, (size_t)i * SH_BASIS + b);
        w[b] = gc.x * shb.x + gc.y * shb.y + gc.z * shb.z;
    }
    const float3 gdir = sh_dir_grad(dir, w);
    float3 gm = (gdir - dir * (dir.x * gdir.x + dir.y * gdir.y + dir.z * gdir.z)) / dist;
#if POSE_GRAD
    const float3 g_dir = gm;   /* the view direction's pull on the mean (-dL/dcampos) */
#endif

    /* opacity */
    const float o = safe_sigmoid(opacity_logits[i]);
#if ANTIALIASED
    d_logits[i] = v ? g_opacity[i] * (P.c3 * P.c2) * o * (1.0f - o) : 0.0f;
    const float g_c = g_opacity[i] * o;   /* dL/d(c3 c2) */
#else
    d_logits[i] = v ? g_opacity[i] * o * (1.0f - o) : 0.0f;
#endif

    /* the mean in pixels */
    const float2 gxy = ld2(g_xy, i);
    float3 gt = (float3)(gxy.x * fx / z, gxy.y * fy / z,
                         -(gxy.x * fx * P.tc.x + gxy.y * fy * P.tc.y) / (z * z));

    /* conic -> Sigma2: G_S2 = -Q G_Q Q */
    const float A = P.conic.x, B = P.conic.y, C = P.conic.z;
    const float3 gq = load3(g_conic, i);
    const float hB = 0.5f * gq.y;
    const float p00 = A * gq.x + B * hB, p01 = A * hB + B * gq.z;
    const float p10 = B * gq.x + C * hB, p11 = B * hB + C * gq.z;
    const float s00 = -(p00 * A + p01 * B), s11 = -(p10 * B + p11 * C);
    const float s01 = -0.5f * ((p00 * B + p01 * C) + (p10 * A + p11 * B));
#if ANTIALIASED
    /* c2 = sqrt(det0 / det1): d c2 / d(a, c, b) over the normalised determinants */
    float t00 = 0.0f, t01 = 0.0f, t11 = 0.0f;
    if (P.c2 > 0.0f) {
        const float g2 = g_c * P.c3 * 0.5f * P.c2 / P.sc;
        const float an = P.a / P.sc, bn = P.b / P.sc, cn = P.c / P.sc;
        const float dn = COV_DILATION / P.sc;
        t00 = g2 * ((cn - dn) / P.det0n - cn / P.detn);
        t11 = g2 * ((an - dn) / P.det0n - an / P.detn);
        t01 = g2 * (-bn / P.det0n + bn / P.detn);   /* half of d/db: b sits twice in Sigma2 */
    }
    const float GS[4] = {s00 + t00, s01 + t01, s01 + t01, s11 + t11};
#else
    const float GS[4] = {s00, s01, s01, s11};
#endif

    /* Sigma2 -> T (dT = 2 G_S2 T Sigma3 = 2 G_S2 V) and Sigma3 (G3 = T^T G_S2 T) */
    float dT[6], GT[6];   /* GT = G_S2 T */
#pragma unroll
    for (int r = 0; r < 2; ++r)
#pragma unroll
        for (int k = 0; k < 3; ++k) {
            dT[3 * r + k] = 2.0f * (GS[2 * r] * P.V[k] + GS[2 * r + 1] * P.V[3 + k]);
            GT[3 * r + k] = GS[2 * r] * P.Tm[k] + GS[2 * r + 1] * P.Tm[3 + k];
        }
    float G3[9];
#pragma unroll
    for (int j = 0; j < 3; ++j)
#pragma unroll
        for (int k = 0; k < 3; ++k) G3[3 * j + k] = P.Tm[j] * GT[k] + P.Tm[3 + j] * GT[3 + k];

    /* T = J R -> J (dJ = dT R^T); only J00, J02, J11, J12 depend on t */
    float dJ[6];
#pragma unroll
    for (int r = 0; r < 2; ++r)
#pragma unroll
        for (int j = 0; j < 3; ++j)
            dJ[3 * r + j] = dT[3 * r] * cam[CAM_R + 3 * j] + dT[3 * r + 1] * cam[CAM_R + 3 * j + 1]
                            + dT[3 * r + 2] * cam[CAM_R + 3 * j + 2];
    const float iz2 = 1.0f / (z * z);
    gt.z += -fx * iz2 * dJ[0] - fy * iz2 * dJ[4];
    /* J02 = -fx rx / z: through rx (unclamped only) and through 1/z */
    gt.x += P.clamp_x ? 0.0f : -fx * iz2 * dJ[2];
    gt.z += (P.clamp_x ? 1.0f : 2.0f) * fx * P.rx * iz2 * dJ[2];
    gt.y += P.clamp_y ? 0.0f : -fy * iz2 * dJ[5];
    gt.z += (P.clamp_y ? 1.0f : 2.0f) * fy * P.ry * iz2 * dJ[5];
#if POSE_GRAD
    {
        /* dL/dR = g_t m^T + J^T dT + t g_dir^T, dL/dt = g_t + R g_dir (the header) */
        const float J00 = fx / z, J02 = -fx * P.rx / z, J11 = fy / z, J12 = -fy * P.ry / z;
        const float gtv[3] = {gt.x, gt.y, gt.z};
        const float mv[3] = {m.x, m.y, m.z};
        const float gdv[3] = {g_dir.x, g_dir.y, g_dir.z};
        const float tv[3] = {cam[CAM_T], cam[CAM_T + 1], cam[CAM_T + 2]};
#pragma unroll
        for (int c = 0; c < 3; ++c) {
            const float jt0 = J00 * dT[c], jt1 = J11 * dT[3 + c];
            const float jt2 = J02 * dT[c] + J12 * dT[3 + c];
            d_cam[(size_t)c * n + i] = v ? gtv[0] * mv[c] + jt0 + tv[0] * gdv[c] : 0.0f;
            d_cam[(size_t)(3 + c) * n + i] = v ? gtv[1] * mv[c] + jt1 + tv[1] * gdv[c] : 0.0f;
            d_cam[(size_t)(6 + c) * n + i] = v ? gtv[2] * mv[c] + jt2 + tv[2] * gdv[c] : 0.0f;
        }
#pragma unroll
        for (int r = 0; r < 3; ++r)
            d_cam[(size_t)(9 + r) * n + i] =
                v ? gtv[r] + cam[CAM_R + 3 * r] * gdv[0] + cam[CAM_R + 3 * r + 1] * gdv[1]
                        + cam[CAM_R + 3 * r + 2] * gdv[2]
                  : 0.0f;
    }
#endif
    gm += (float3)(cam[CAM_R + 0] * gt.x + cam[CAM_R + 3] * gt.y + cam[CAM_R + 6] * gt.z,
                   cam[CAM_R + 1] * gt.x + cam[CAM_R + 4] * gt.y + cam[CAM_R + 7] * gt.z,
                   cam[CAM_R + 2] * gt.x + cam[CAM_R + 5] * gt.y + cam[CAM_R + 8] * gt.z);
    st3(v ? gm : (float3)(0.0f), d_means, i);

    /* Sigma3 = M M^T, M = Rot diag(s): dM = 2 G3 M */
    float dR[9], ds[3] = {0.0f, 0.0f, 0.0f};
#pragma unroll
    for (int j = 0; j < 3; ++j)
#pragma unroll
        for (int k = 0; k < 3; ++k) {
            const float dM = 2.0f * (G3[3 * j] * P.Rq[k] + G3[3 * j + 1] * P.Rq[3 + k]
                                     + G3[3 * j + 2] * P.Rq[6 + k]) * P.se[k];
            ds[k] += dM * P.Rq[3 * j + k];
            dR[3 * j + k] = dM * P.se[k];
        }
#if ANTIALIASED
    /* the covariance's share (through se) and c3's: dlog c3 / dlog s_k = f2 / se_k^2 */
    float3 dls;
    {
        float d3[3];
#pragma unroll
        for (int k = 0; k < 3; ++k)
            d3[k] = ds[k] * (P.s[k] * P.s[k] / P.se[k])
                    + g_c * P.c2 * P.c3 * f2 / (P.se[k] * P.se[k]);
        dls = (float3)(d3[0], d3[1], d3[2]);
    }
    st3(v ? dls : (float3)(0.0f), d_log_scales, i);
#else
    st3(v ? (float3)(ds[0] * P.s[0], ds[1] * P.s[1], ds[2] * P.s[2]) : (float3)(0.0f),
        d_log_scales, i);
#endif

    /* Rot(q^) -> q^ -> q */
    const float qw = P.qn.x, qx = P.qn.y, qy = P.qn.z, qz = P.qn.w;
    const float4 gqn = 2.0f * (float4)(
        -qz * dR[1] + qy * dR[2] + qz * dR[3] - qx * dR[5] - qy * dR[6] + qx * dR[7],
        qy * dR[1] + qz * dR[2] + qy * dR[3] - 2.0f * qx * dR[4] - qw * dR[5] + qz * dR[6]
            + qw * dR[7] - 2.0f * qx * dR[8],
        -2.0f * qy * dR[0] + qx * dR[1] + qw * dR[2] + qx * dR[3] + qz * dR[5] - qw * dR[6]
            + qz * dR[7] - 2.0f * qy * dR[8],
        -2.0f * qz * dR[0] - qw * dR[1] + qx * dR[2] + qw * dR[3] - 2.0f * qz * dR[4]
            + qy * dR[5] + qx * dR[6] + qy * dR[7]);
    const float along = qw * gqn.x + qx * gqn.y + qy * gqn.z + qz * gqn.w;
    st4(v ? (gqn - P.qn * along) / P.qlen : (float4)(0.0f), d_quats, i);
}

__kernel void splat_filter3d(const int n, __global const float *means, __global const float *cams,
                             const int n_cams, const int width, const int height,
                             __global float *f2) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float3 m = load3(means, i);
    const float w = (float)width, h = (float)height;
    float best = INFINITY;
    for (int k = 0; k < n_cams; ++k) {
        __global const float *cam = cams + (size_t)k * CAM_FLOATS;
        const float x = cam[CAM_R + 0] * m.x + cam[CAM_R + 1] * m.y + cam[CAM_R + 2] * m.z
                        + cam[CAM_T];
        const float y = cam[CAM_R + 3] * m.x + cam[CAM_R + 4] * m.y + cam[CAM_R + 5] * m.z
                        + cam[CAM_T + 1];
        const float z = cam[CAM_R + 6] * m.x + cam[CAM_R + 7] * m.y + cam[CAM_R + 8] * m.z
                        + cam[CAM_T + 2];
        if (!(z > cam[CAM_NEAR])) continue;
        const float u = cam[CAM_FX] * x / z + cam[CAM_CX];
        const float v = cam[CAM_FY] * y / z + cam[CAM_CY];
        if (u < -FILTER3D_MARGIN * w || u > (1.0f + FILTER3D_MARGIN) * w
            || v < -FILTER3D_MARGIN * h || v > (1.0f + FILTER3D_MARGIN) * h)
            continue;
        best = fmin(best, z / cam[CAM_FX]);
    }
    f2[i] = isfinite(best) ? FILTER3D_VAR * best * best : -1.0f;
}
