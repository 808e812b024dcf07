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
 * Defines read: SH_DEGREE (0..3), SH_C0, COLOR_OFFSET (the host passes clrf.export's values).
 * Mirrored by clrf.reference_export.sample_fields.
 */
#ifndef SH_DEGREE
#define SH_DEGREE 0                  /* SH degree of the grid's rows (0..3) */
#endif
#ifndef SH_C0
#define SH_C0 0.28209479f            /* Y_0^0 = 1 / (2 sqrt(pi)) (set by the host) */
#endif
#ifndef COLOR_OFFSET
#define COLOR_OFFSET 0.5f            /* as in the renderer: zero coefficients give grey */
#endif
#define SH_BASIS ((SH_DEGREE + 1) * (SH_DEGREE + 1))
#define SH_DIM (3 * SH_BASIS)

inline void axis_lerp(float u, int r, int *i0, int *i1, float *f) {
    const float c = clamp(u - 0.5f, 0.0f, (float)(r - 1));
    const int i = min((int)c, max(r - 2, 0));
    *i0 = i;
    *i1 = min(i + 1, r - 1);
    *f = c - (float)i;
}

__kernel void sample_fields(const int n, __global const float *points, const int4 reso,
                            const float4 bmin, const float4 scale,
                            __global const int *links, __global const float *density,
                            __global const float *sh, __global float *sigma_out,
                            __global float *rgb_out) {
    const int i = get_global_id(0);
    if (i >= n) return;
    int lo[3], hi[3];
    float f[3];
    axis_lerp((points[3 * i] - bmin.x) * scale.x, reso.x, &lo[0], &hi[0], &f[0]);
    axis_lerp((points[3 * i + 1] - bmin.y) * scale.y, reso.y, &lo[1], &hi[1], &f[1]);
    axis_lerp((points[3 * i + 2] - bmin.z) * scale.z, reso.z, &lo[2], &hi[2], &f[2]);
    float s = 0.0f, r = 0.0f, g = 0.0f, b = 0.0f;
    for (int c = 0; c < 8; ++c) {
        const int cx = (c >> 2) & 1, cy = (c >> 1) & 1, cz = c & 1;
        const int x = cx ? hi[0] : lo[0], y = cy ? hi[1] : lo[1], z = cz ? hi[2] : lo[2];
        const int k = links[(x * reso.y + y) * reso.z + z];
        if (k < 0) continue;
        const float w = (cx ? f[0] : 1.0f - f[0]) * (cy ? f[1] : 1.0f - f[1]) *
                        (cz ? f[2] : 1.0f - f[2]);
        const __global float *row = sh + (size_t)k * SH_DIM;
        s += w * density[k];
        r += w * row[0];
        g += w * row[SH_BASIS];
        b += w * row[2 * SH_BASIS];
    }
    sigma_out[i] = s;
    rgb_out[3 * i] = fmax(SH_C0 * r + COLOR_OFFSET, 0.0f);
    rgb_out[3 * i + 1] = fmax(SH_C0 * g + COLOR_OFFSET, 0.0f);
    rgb_out[3 * i + 2] = fmax(SH_C0 * b + COLOR_OFFSET, 0.0f);
}
