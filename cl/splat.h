/* splat.h: what the Gaussian-splatting kernels share (cl/splat_project.cl, cl/splat_raster.cl):
 * the conventions, the knobs, the camera buffer's layout and the per-pixel opacity of a
 * projected Gaussian.
 *
 * Conventions (those of the 3D Gaussian Splatting paper, Kerbl et al. 2023):
 *   camera space: x right, y down, z forward (OpenCV); world-to-camera p_c = R p + t;
 *   pixels: u = fx x_c / z_c + cx, v = fy y_c / z_c + cy; pixel (px, py) covers [px, px + 1) x
 *     [py, py + 1) and is evaluated at its centre (px + 0.5, py + 0.5);
 *   tiles: TILE x TILE pixels, tile (tx, ty) has id ty * ntx + tx, ntx = ceil(width / TILE).
 *
 * Camera buffer cam [CAM_FLOATS] (float32, written by clrf/splat/raster.py SplatCamera.buffer):
 *   CAM_R   .. +8   R, world-to-camera rotation, row-major
 *   CAM_T   .. +2   t
 *   CAM_POS .. +2   camera centre in world space, -R^T t (the SH view directions start there)
 *   CAM_FX, CAM_FY, CAM_CX, CAM_CY   intrinsics in pixels
 *   CAM_NEAR        near plane (> 0): Gaussians with z_c <= near are culled
 *
 * Per-pixel opacity of a projected Gaussian (mean m [2] in pixels, conic Q = Sigma2^-1 stored
 * (A, B, C) for [[A, B], [B, C]], opacity o) at pixel centre p, d = m - p:
 *   power = -0.5 (A d_x^2 + C d_y^2) - B d_x d_y,   alpha = min(ALPHA_MAX, o exp(power))
 * skipped (no contribution, transmittance unchanged) where power > 0 (rounding only) or
 * alpha < ALPHA_MIN.
 *
 * Defines read: TILE, SH_DEGREE (sh.h, projection only) and the constants below; the host
 * passes every one of them (clrf/splat/raster.py DEFINES), the float64 twin
 * (clrf/references/reference_splat.py) uses the same values.
 */
#ifndef CLRF_SPLAT_H
#define CLRF_SPLAT_H

#include "common.h"

/* Every kernel of the family computes in IEEE float32 without contracting a * b + c into fma:
 * the rasteriser's backward recomputes each alpha and must skip exactly what the forward
 * skipped, and the projection's backward must cull exactly what its forward culled. */
#pragma OPENCL FP_CONTRACT OFF

#ifndef TILE
#define TILE 16                /* tile side in pixels; a rasteriser work-group is TILE x TILE */
#endif
#if TILE < 1 || TILE > 32
#error "TILE must be in 1..32"
#endif
#define TILE_PIXELS (TILE * TILE)   /* work-items per tile, and Gaussians per local batch */

#ifndef ALPHA_MAX
#define ALPHA_MAX 0.99f        /* opacity clamp of one Gaussian at one pixel (3DGS) */
#endif
#ifndef ALPHA_MIN
#define ALPHA_MIN 0.00392156862745098f   /* 1/255: weaker contributions are skipped (3DGS) */
#endif
#ifndef T_MIN
#define T_MIN 1e-4f            /* a pixel stops before its transmittance would fall below this */
#endif
#ifndef COV_DILATION
#define COV_DILATION 0.3f      /* low-pass filter: added to the 2D covariance's diagonal, px^2 */
#endif
#ifndef FRUSTUM_GUARD
#define FRUSTUM_GUARD 1.3f     /* x/z, y/z clamped to this times the half-frustum's tangent */
#endif
#ifndef SIGMA_RADIUS
#define SIGMA_RADIUS 3.0f      /* screen radius in standard deviations of the major axis */
#endif

#define CAM_R 0
#define CAM_T 9
#define CAM_POS 12
#define CAM_FX 15
#define CAM_FY 16
#define CAM_CX 17
#define CAM_CY 18
#define CAM_NEAR 19
#define CAM_FLOATS 20

/* The Gaussian's power at offset d = mean - pixel centre (see the header). */
CLRF_INLINE float splat_power(const float2 d, const float4 conic_op) {
    return -0.5f * (conic_op.x * d.x * d.x + conic_op.z * d.y * d.y) - conic_op.y * d.x * d.y;
}

/* Its opacity at that pixel before the clamp, o exp(power); callers clamp to ALPHA_MAX and skip
 * power > 0 or alpha < ALPHA_MIN. conic_op = (A, B, C, o). */
CLRF_INLINE float splat_raw_alpha(const float power, const float4 conic_op) {
    return conic_op.w * exp(power);
}

/* Rotation matrix (row-major) of the unit quaternion q = (w, x, y, z). */
CLRF_INLINE void splat_quat_rot(const float4 q, float *Rq) {
    const float w = q.x, x = q.y, y = q.z, z = q.w;
    Rq[0] = 1.0f - 2.0f * (y * y + z * z);
    Rq[1] = 2.0f * (x * y - w * z);
    Rq[2] = 2.0f * (x * z + w * y);
    Rq[3] = 2.0f * (x * y + w * z);
    Rq[4] = 1.0f - 2.0f * (x * x + z * z);
    Rq[5] = 2.0f * (y * z - w * x);
    Rq[6] = 2.0f * (x * z - w * y);
    Rq[7] = 2.0f * (y * z + w * x);
    Rq[8] = 1.0f - 2.0f * (x * x + y * y);
}

#endif /* CLRF_SPLAT_H */
