/* export.cl: fields of a sparse grid at arbitrary points, for mesh and point-cloud export.
 *
 * Layout and interpolation as in grid_render.cl: links int32 [RX,RY,RZ] (C order) into rows of
 * density [N] and sh [N, SH_DIM] (channel-major: R block, G block, B block of SH_BASIS each).
 * A point p (world) goes to box units u = (p - bmin) * scale; per axis the lower corner is
 * i0 = min(floor(clamp(u - 0.5, 0, R - 1)), max(R - 2, 0)), i1 = min(i0 + 1, R - 1), with
 * fraction f = clamp(u - 0.5, 0, R - 1) - i0 (values at voxel centres, clamped at the edges).
 * An unallocated corner counts as zero.
 *
 * sample_fields: for point n,
 *   sigma[n]  = sum_c w_c density_c     (raw: the renderer's density is max(sigma, 0), whose
 *                                        level sets for a level > 0 are the same; keeping the
 *                                        sign makes marching cubes' linear interpolation exact
 *                                        where the raw field is linear)
 *   rgb0[n,c] = max(SH_C0 * sum_c w_c sh_c[c * SH_BASIS] + 0.5, 0)   (the degree-0 band: the
 *               view-independent colour, i.e. the colour averaged over all directions)
 *
 * Defines read: SH_DEGREE (0..3). Interpolation (lerp_setup, lerp_density), SH_C0 and
 * COLOR_OFFSET are the renderer's own (march.h, sh.h), so export and rendering cannot disagree.
 * Mirrored by clrf.references.reference_export.sample_fields.
 */
#include "march.h"

__kernel void sample_fields(const int n, __global const float *points, const int4 reso,
                            const float4 bmin, const float4 scale,
                            __global const int *links, __global const float *density,
                            __global const float *sh, __global float *sigma_out,
                            __global float *rgb_out) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float3 p = (vload3(i, points) - bmin.xyz) * scale.xyz;   /* box units */
    lerp_t L;
    float s = 0.0f, r = 0.0f, g = 0.0f, b = 0.0f;
    if (lerp_setup(p, reso, links, &L)) {
        s = lerp_density(&L, density);
        for (int c = 0; c < 8; ++c) {
            if (L.idx[c] < 0) continue;
            const __global float *row = sh + (size_t)L.idx[c] * SH_DIM;
            r += L.w[c] * row[0];
            g += L.w[c] * row[SH_BASIS];
            b += L.w[c] * row[2 * SH_BASIS];
        }
    }
    vstore3(fmax(SH_C0 * (float3)(r, g, b) + COLOR_OFFSET, 0.0f), i, rgb_out);
    sigma_out[i] = s;
}
