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

/* sum_b w_b dY_b/dd at direction d (the components treated as independent; the caller projects
 * out the radial part). Derivatives of sh_basis's polynomials, term by term. Twin:
 * reference.sh_dir_grad. */
CLRF_INLINE float3 sh_dir_grad(const float3 d, const float *w) {
    float3 g = (float3)(0.0f);
#if SH_DEGREE >= 1
    const float x = d.x, y = d.y, z = d.z;
    g.x += -SH_C1 * w[3];
    g.y += -SH_C1 * w[1];
    g.z += SH_C1 * w[2];
#endif
#if SH_DEGREE >= 2
    const float xx = x * x, yy = y * y, zz = z * z;
    g.x += SH_C2_0 * y * w[4];
    g.y += SH_C2_0 * x * w[4];
    g.y += SH_C2_1 * z * w[5];
    g.z += SH_C2_1 * y * w[5];
    g.x += -2.0f * SH_C2_2 * x * w[6];
    g.y += -2.0f * SH_C2_2 * y * w[6];
    g.z += 4.0f * SH_C2_2 * z * w[6];
    g.x += SH_C2_3 * z * w[7];
    g.z += SH_C2_3 * x * w[7];
    g.x += 2.0f * SH_C2_4 * x * w[8];
    g.y += -2.0f * SH_C2_4 * y * w[8];
#endif
#if SH_DEGREE >= 3
    g.x += 6.0f * SH_C3_0 * x * y * w[9];
    g.y += SH_C3_0 * (3.0f * xx - 3.0f * yy) * w[9];
    g.x += SH_C3_1 * y * z * w[10];
    g.y += SH_C3_1 * x * z * w[10];
    g.z += SH_C3_1 * x * y * w[10];
    g.x += -2.0f * SH_C3_2 * x * y * w[11];
    g.y += SH_C3_2 * (4.0f * zz - xx - 3.0f * yy) * w[11];
    g.z += 8.0f * SH_C3_2 * y * z * w[11];
    g.x += -6.0f * SH_C3_3 * x * z * w[12];
    g.y += -6.0f * SH_C3_3 * y * z * w[12];
    g.z += SH_C3_3 * (6.0f * zz - 3.0f * xx - 3.0f * yy) * w[12];
    g.x += SH_C3_4 * (4.0f * zz - 3.0f * xx - yy) * w[13];
    g.y += -2.0f * SH_C3_4 * x * y * w[13];
    g.z += 8.0f * SH_C3_4 * x * z * w[13];
    g.x += 2.0f * SH_C3_5 * x * z * w[14];
    g.y += -2.0f * SH_C3_5 * y * z * w[14];
    g.z += SH_C3_5 * (xx - yy) * w[14];
    g.x += SH_C3_6 * (3.0f * xx - 3.0f * yy) * w[15];
    g.y += -6.0f * SH_C3_6 * x * y * w[15];
#endif
    return g;
}

#endif /* CLRF_SH_H */
