/* sh.h: real spherical-harmonic basis, degree 0..3, at a unit direction (x, y, z).
 *
 * Basis index b = l*l + l + m (l = degree, m = -l..l), the ordering and signs used by
 * PlenOctrees/svox2 (their tables stop at degree 2; degree 3 follows the same convention).
 * Mirrored by reference.sh_basis.
 *
 * Defines read: SH_DEGREE (0..3, default 2).
 */
#ifndef CLRF_SH_H
#define CLRF_SH_H

#ifndef SH_DEGREE
#define SH_DEGREE 2  /* 0: diffuse colour only; 1..3: view dependence */
#endif
#if SH_DEGREE < 0 || SH_DEGREE > 3
#error "SH_DEGREE must be 0, 1, 2 or 3"
#endif
#define SH_BASIS ((SH_DEGREE + 1) * (SH_DEGREE + 1))   /* coefficients per colour channel */
#define SH_DIM (3 * SH_BASIS)                          /* floats per voxel row, channel-major */

#define SH_C0 0.28209479177387814f
#define SH_C1 0.4886025119029199f
#define SH_C2_0 1.0925484305920792f
#define SH_C2_1 -1.0925484305920792f
#define SH_C2_2 0.31539156525252005f
#define SH_C2_3 -1.0925484305920792f
#define SH_C2_4 0.5462742152960396f
#define SH_C3_0 -0.5900435899266435f
#define SH_C3_1 2.890611442640554f
#define SH_C3_2 -0.4570457994644658f
#define SH_C3_3 0.3731763325901154f
#define SH_C3_4 -0.4570457994644658f
#define SH_C3_5 1.445305721320277f
#define SH_C3_6 -0.5900435899266435f

CLRF_INLINE void sh_basis(float3 d, float *Y) {
    Y[0] = SH_C0;
#if SH_DEGREE >= 1
    const float x = d.x, y = d.y, z = d.z;
    Y[1] = -SH_C1 * y;
    Y[2] = SH_C1 * z;
    Y[3] = -SH_C1 * x;
#endif
#if SH_DEGREE >= 2
    const float xx = x * x, yy = y * y, zz = z * z;
    Y[4] = SH_C2_0 * x * y;
    Y[5] = SH_C2_1 * y * z;
    Y[6] = SH_C2_2 * (2.0f * zz - xx - yy);
    Y[7] = SH_C2_3 * x * z;
    Y[8] = SH_C2_4 * (xx - yy);
#endif
#if SH_DEGREE >= 3
    Y[9] = SH_C3_0 * y * (3.0f * xx - yy);
    Y[10] = SH_C3_1 * x * y * z;
    Y[11] = SH_C3_2 * y * (4.0f * zz - xx - yy);
    Y[12] = SH_C3_3 * z * (2.0f * zz - 3.0f * xx - 3.0f * yy);
    Y[13] = SH_C3_4 * x * (4.0f * zz - xx - yy);
    Y[14] = SH_C3_5 * z * (xx - yy);
    Y[15] = SH_C3_6 * x * (xx - 3.0f * yy);
#endif
}

#endif /* CLRF_SH_H */
