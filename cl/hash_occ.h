/* hash_occ.h: the occupancy grid's cell of a point (hash_occ.cl, hash_march.cl).
 *
 * R^3 cells over the box [lo, lo + 1/inv_ext]; the cell of a point with box coordinate
 * u = (xyz - lo) * inv_ext is floor(u R) (clamped to R - 1), index cx + R (cy + R cz).
 */
#ifndef CLRF_HASH_OCC_H
#define CLRF_HASH_OCC_H

#include "common.h"

/* Cell index of point xyz, or -1 outside the closed box (or NaN). */
CLRF_INLINE int occ_cell(const float3 xyz, const float4 lo, const float4 inv_ext, const int R) {
    const float3 u = (xyz - lo.xyz) * inv_ext.xyz;
    if (!(u.x >= 0.0f && u.y >= 0.0f && u.z >= 0.0f && u.x <= 1.0f && u.y <= 1.0f
          && u.z <= 1.0f))
        return -1;
    const int3 c = min(convert_int3(u * (float)R), (int3)(R - 1));
    return c.x + R * (c.y + R * c.z);
}

#endif /* CLRF_HASH_OCC_H */
