/* ray_pose.cl: training cameras' pose corrections for models whose batches mix rays of many
 * images (hash.pose_opt; clrf/corrections/ray_pose.py): each ray made from its image's
 * corrected camera, and the camera gradient of a batch summed per image.
 *
 * Ray i comes from training image v = index[i] / pixels. The ray store holds it as the given
 * camera made it: o0 = -R0^T t0 (the camera centre), d0 = R0^T d_cam (d_cam the pixel's
 * direction in the camera's axes), with [R0 t0] the given world-to-camera. Image v's corrected
 * camera [R t] makes the ray
 *   o = c_v = -R^T t,   d = A_v d0,  A_v = R^T R0          (ray_pose_apply; rows [V, 12] =
 *                                                            A_v row-major, then c_v)
 * and, from each ray's dL/do, dL/dd (ray_grad [n, 6]), since d_cam = R d:
 *   dL/dR = sum_i (d_cam,i dL/dd_i^T - t dL/do_i^T) = R S_d - t S_o^T,   dL/dt = -R S_o,
 *   S_d = sum_i d_i dL/dd_i^T,   S_o = sum_i dL/do_i                 (over image v's rays)
 * ray_pose_sums gives sums [V, 13] = (S_d row-major, S_o, the ray count); the host forms dL/dR,
 * dL/dt (12 numbers a touched image) and the correction's step.
 * ray_pose_sums: one work-group of RAY_POSE_LS items per image; item l sums rays l, l + LS, ...
 * of the batch that are image v's, then a fixed tree adds the items' sums (deterministic).
 *
 * Defines read: RAY_POSE_LS (the host passes its local size). Twin:
 * clrf/references/reference_ray_pose.py.
 */
#include "common.h"

#ifndef RAY_POSE_LS
#define RAY_POSE_LS 64   /* work-items per image of ray_pose_sums (a power of two) */
#endif
#if RAY_POSE_LS < 1 || (RAY_POSE_LS & (RAY_POSE_LS - 1))
#error "RAY_POSE_LS must be a power of two"
#endif
#define RAY_POSE_SUMS 13

/* o [n, 3], d [n, 3]: ray i of o0/d0 [n, 3] moved by its image's row of rows [V, 12]. */
__kernel void ray_pose_apply(const int n, const int pixels, __global const int *index,
                             __global const float *rows, __global const float *o0,
                             __global const float *d0, __global float *o, __global float *d) {
    const int i = get_global_id(0);
    if (i >= n) return;
    __global const float *r = rows + (size_t)(index[i] / pixels) * 12;
    const float3 v = load3(d0, i);
    vstore3((float3)(dot((float3)(r[0], r[1], r[2]), v), dot((float3)(r[3], r[4], r[5]), v),
                     dot((float3)(r[6], r[7], r[8]), v)), i, d);
    vstore3((float3)(r[9], r[10], r[11]), i, o);
}

/* sums [V, 13] of the batch's rays (see the header); one work-group per image. */
__kernel __attribute__((reqd_work_group_size(RAY_POSE_LS, 1, 1)))
void ray_pose_sums(const int n, const int pixels, __global const int *index,
                   __global const float *d, __global const float *ray_grad,
                   __global float *sums) {
    __local float part[RAY_POSE_LS * RAY_POSE_SUMS];
    const int v = get_group_id(0), l = get_local_id(0);
    float s[RAY_POSE_SUMS];
    for (int k = 0; k < RAY_POSE_SUMS; ++k) s[k] = 0.0f;
    for (int i = l; i < n; i += RAY_POSE_LS) {
        if (index[i] / pixels != v) continue;
        const float3 di = load3(d, i);
        __global const float *g = ray_grad + (size_t)i * 6;
        for (int a = 0; a < 3; ++a) {
            const float da = a == 0 ? di.x : (a == 1 ? di.y : di.z);
            s[3 * a] += da * g[3];
            s[3 * a + 1] += da * g[4];
            s[3 * a + 2] += da * g[5];
        }
        s[9] += g[0]; s[10] += g[1]; s[11] += g[2];
        s[12] += 1.0f;
    }
    for (int k = 0; k < RAY_POSE_SUMS; ++k) part[l * RAY_POSE_SUMS + k] = s[k];
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int h = RAY_POSE_LS / 2; h > 0; h >>= 1) {
        if (l < h)
            for (int k = 0; k < RAY_POSE_SUMS; ++k)
                part[l * RAY_POSE_SUMS + k] += part[(l + h) * RAY_POSE_SUMS + k];
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (l < RAY_POSE_SUMS) sums[(size_t)v * RAY_POSE_SUMS + l] = part[l];
}
