/* grid_render.cl: forward and backward volume rendering of a sparse SH voxel grid.
 *
 * Memory layout
 *   links   int32 [RX, RY, RZ], C order: links[(x*RY + y)*RZ + z] = row k >= 0, or < 0 = empty
 *   density float [N]                 raw density of row k (ReLU applied after interpolation)
 *   sh      float [N, SH_DIM]         sh[k*SH_DIM + ch*SH_BASIS + b], channel-major
 *   origins, dirs  float [n_rays, 3]  world space; dirs need not be unit length
 *
 * Geometry. The grid fills the world box [bmin, bmin + reso/scale]. In "box units" p = (x -
 * bmin)*scale the box is [0, reso] and voxel i's value sits at its centre i + 0.5. Trilinear
 * interpolation clamps to the outermost centres (constant extension over the last half voxel),
 * so a 1x1x1 grid is a constant and a homogeneous grid is homogeneous up to the box faces.
 *
 * Marching. A ray o + t*d/|d| enters the box at t0 and leaves at t1 (length len = t1 - t0).
 * Step `step` is in box units (voxels) along the ray, i.e. dt = step/|d*scale| in world units.
 * Segment k covers s in [k dt, min((k+1) dt, len)] measured from the entry, so the segments
 * add up to len exactly; its sample sits at the segment midpoint (midpoint quadrature).
 *
 * Compositing, with sigma_k = max(trilerp(density), 0), tau_k = sigma_k delta_k:
 *   alpha_k = 1 - exp(-tau_k) = -expm1(-tau_k),  T_k = exp(-sum_{j<k} tau_j)  (log space)
 *   (alpha_of_tau in common.h: series up to tau = 0.7, 1 - exp(-tau) above; within 2 ulp)
 *   w_k = T_k alpha_k,  rgb = sum_k w_k c_k + T_end * bg,  acc = sum_k w_k,
 *   depth = sum_k w_k t_k (t_k the world distance of sample k; not divided by acc),
 *   c_k = max(0, sum_b sh_{ch,b}(x_k) Y_b(d) + 0.5)  (svox2's colour activation).
 * The march stops after the sample at which T falls below T_STOP; what is left is T_end.
 *
 * Backward (dL/drgb = g given, or g = 2 (rgb - target) * loss_scale for GRAD_MODE 1):
 *   dL/dsigma_k = delta_k (T_{k+1} (g.c_k) - R_k),   R_k = sum_{j>k} w_j (g.c_j) + T_end (g.bg)
 *   dL/dsh_{ch,b}(x_k) = w_k g_ch [pre_ch > 0] Y_b
 * R_k is the remaining radiance: g.rgb minus the (Kahan-summed) prefix, so the ray is marched
 * twice (forward for rgb, then backward). A work-item holding a gradient slot (GRAD_SLOTS,
 * with SAMPLE_RECORD) records each sample's (sigma, w, T_{k+1}, pre-activation colour) in the
 * slot's private buffer during the forward march and reads them back in the backward march
 * (the same values bit for bit); otherwise it recomputes them. Corner gradients of
 * consecutive samples in the same cell are merged in registers and scattered when the march
 * leaves the cell: one atomic add per corner value, or plain vector adds into a private copy
 * or, under the block locks, into the caller's buffers (GRAD_SLOTS, GRAD_LOCKS). GRAD_MERGE 0
 * (atomics only) adds each sample's corner gradients as it is evaluated: no sums are held
 * across the march (Intel's Xe-LP compiler spilled them), at about twice the atomics.
 *
 * Empty space: when all 8 corners of the current cell are empty the march jumps to the last
 * sample before the cell's exit; with BLOCK > 0 (the host uses 8) it first checks a table of
 * BLOCK^3-cell blocks (block_occupancy) and jumps over a whole empty block, then, with
 * BLOCK_FINE > 0 (the host uses 2), a table of BLOCK_FINE^3-cell blocks. The tables are read
 * on entering a new cell only. Those samples have sigma = 0, so the result is unchanged.
 *
 * Prefetch (CLRF_PREFETCH, PoCL CPU): PREFETCH_LINKS_AHEAD samples ahead the links of the
 * cell there are prefetched, PREFETCH_AHEAD samples ahead its rows (and, in the backward
 * march, its gradient rows), so the gathers do not wait for DRAM.
 *
 * Gradient accumulation: atomics (GRAD_SLOTS 0, any device) or, on CPU devices (GRAD_SLOTS >
 * 0; see render_backward), either private copies per running work-item without atomics, added
 * into the caller's buffers by grad_slots_reduce, or (GRAD_LOCKS) plain vector adds into the
 * caller's buffers under try-locks of voxel blocks, a cell whose lock is taken going with
 * atomics into one scratch copy. All add the same values; only the order of the float
 * additions differs.
 *
 * Vectorisation: SH rows are loaded and accumulated as float16/float8/float4/float3 vectors
 * (shv_t in march.h); consecutive samples in the same cell reuse the 8 corner rows' links.
 *
 * GPU shape (SH_PER_CORNER 1, the host sets it from tuning.gpu_kernels): a GPU gives every
 * float of a work-item a register of its own, and the vectors above (an interpolated row, the
 * 4 rows of per-ray SH factors, 8 gradient rows per cell) do not fit. Interpolation and the SH
 * sum are both linear, so c_k = sum_c w_c (sum_b sh_c,b Y_b) + 0.5 (color_pre_corners: 3 sums),
 * and corner c's merged gradient is Y_b times sum_k w_c dL/dpre_k,ch (cgrad_t: 3 floats),
 * multiplied out only as it is added. The same values up to the order of float additions.
 *
 * Per-ray background (BG_PER_RAY 1, unbounded scenes with a background model such as
 * background.cl's MSI): the constant `bg` argument is replaced by bg_rays float [n_rays, 3],
 * and everything above holds with bg -> bg_rays[i] per ray (pixel = C_fg + T_end bg_i, and
 * R_k's last term T_end (g.bg_i)). The backward also writes
 *   grad_bg [n_rays, 3] = dL/d bg_i = T_end g   (g = dL/dpixel, as above, in both GRAD_MODEs)
 * which is what the background model's own backward takes. ray_exit gives the background's
 * starting distance: t_exit[i] = world distance along the unit direction at which the ray
 * leaves the grid box (0 for a ray that misses it).
 *
 * Bricks (BRICK 1; march.h, clrf/grid/bricks.py): the grid is split into bricks, one per
 * process, and each kernel marches only the samples its brick owns, with the whole grid's
 * geometry (reso, bmin, scale) and the brick's links (voxels blo .. blo + lreso - 1). The
 * march starts with T = 1 at the brick's first sample, so render_forward returns a partial:
 *   out_rgb = sum_k T_k' w_k' c_k (premultiplied, no background), out_logT = -sum_k tau_k,
 *   out_acc = sum_k w_k', out_depth = sum_k w_k' t_k,  out_key = first segment evaluated (-1:
 *   none, the partial is the identity),
 * with T_k' the transmittance from the brick's entry. Sorted by key along the ray, the partials
 * compose with the over operator into the single-grid result: rgb = sum_b T_b rgb_b + T_end bg,
 * T_b = exp(sum_{b'<b} logT_b'). For the backward pass ray_in holds per ray the float4
 * (T_b g, R_b), R_b = g.(everything behind the brick, background included) (+ T_end dL/dT_end):
 * with total = (T_b g).rgb_b + R_b, the remaining-radiance recursion above gives each sample
 * of the brick exactly the single-grid gradient (T_k = T_b T_k', w_k = T_b w_k'). No early
 * termination: the host builds with T_STOP 0 (a brick cannot know T_b in the forward pass).
 * render_max_weight multiplies by ray_T = T_b.
 *
 * Ray order (RAY_ORDER 1, CPU devices, batches of many rays): work-item g renders ray
 * ray_order[g], a permutation of 0..n_rays-1 that the host makes by sorting ray_order_keys:
 * the Morton code of the block that holds the midpoint of each ray's path through the box. A
 * compute unit runs its work-items one after another, so consecutive rays that cross
 * neighbouring cells find the rows of the previous ray still in cache. Every output stays at
 * its ray's own index, so the results are those of the given order (gradients up to the
 * order of float additions). The host uses it on dense grids only (clrf/grid/render.py).
 *
 * Camera gradient (GRID_POSE_GRAD 1, pose refinement, clrf/corrections/ray_pose.py; without
 * the define no line of it is compiled): the kernel render_ray_grad gives each ray's
 *   ray_grad [n, 6] = (dL/do, dL/dd)
 * of the loss render_backward takes (the same arguments), marching the ray as it does. What
 * is held constant: each sample's world distance t_k = t0 + mid_k along the unit direction
 * dh = d / |d| and its segment length delta_k (the march's entry t0, step dt and segment ends
 * are not differentiated: moving the ray moves its samples, it does not re-place them, as
 * the hash model's packed_ray_grad does). Sample k sits at x_k = o + t_k dh,
 * in box units p_k = (x_k - bmin) scale, so dp/dx = diag(scale). With the corner weights
 * w_c(p) = prod_a (1 - f_a or f_a), f_a the fraction lerp_axis gives (df_a/dp_a = 1 where
 * 0 < p_a - 1/2 < reso_a - 1 and reso_a >= 2, else 0: the clamped outer half voxels and a
 * 1-voxel axis are constant), and q_c,ch = sum_b sh_c,ch,b Y_b(dh) corner c's colour:
 *   dsigma_k/dp = sum_c density_c dw_c/dp   (sigma_k > 0: the ReLU passes; else no term)
 *   dpre_k,ch/dp = sum_c q_c,ch dw_c/dp
 *   dL/dx_k = scale * (dL/dsigma_k dsigma_k/dp + sum_ch dL/dpre_k,ch dpre_k,ch/dp)
 * with dL/dsigma_k and dL/dpre_k,ch = w_k g_ch [pre > 0] the backward's values (below; empty
 * corners count as zero, as in the forward). Then, over the ray's samples,
 *   dL/do = sum_k dL/dx_k,
 *   dL/ddh = sum_k t_k dL/dx_k + sum_b dL/dY_b dY_b/dv,  dL/dY_b = sum_k sum_ch dL/dpre_k,ch
 *            sh_ch,b(x_k) (the interpolated coefficients; sh.h sh_dir_grad),
 *   dL/dd = (dL/ddh - dh (dh . dL/ddh)) / |d|
 * and a ray that misses the box gets zeros. A per-ray background's own dependence on the ray
 * (BG_PER_RAY: the MSI) is not in it. Not with BRICK (the distributed grid refuses pose
 * refinement). Twin: clrf/references/reference.py ray_grad.
 *
 * Per-image colour transform in the loss (RAY_EXPOSURE 1 or 2, GRAD_MODE 1, not BRICK;
 * grid.exposure, clrf/corrections/exposure.py RayExposure; without the define no line of it
 * is compiled): ray i belongs to training image v = exp_index[i] / exp_pixels, whose row
 * exp_rows[v] = (A row-major, b) maps the ray's whole pixel to out = A rgb + b, and the loss
 * term is |out - target|^2 (RAY_EXPOSURE 2: |clamp(out, 0, 1) - target|^2, a channel with
 * out outside [0, 1] passing no gradient, as cl/splat_exposure.cl exposure_rays with clip).
 * Then g = 2 loss_scale A^T r with r = out - target (0 in such a channel), ray_out[i] the
 * loss term, and the kernel writes what the rows' gradient (exposure_rays_grad) reads: the
 * state exp_state [n, 8] = (rgb, 1, ...) (the whole pixel, opacity 1) and r to exp_resid
 * [n, 3]. The same values as rendering the pixel first and handing this backward the target
 * rgb - A^T r (what the host did before), in one march instead of two.
 *
 * Defines read: SH_DEGREE (sh.h), T_STOP, GRAD_MODE, GRAD_SLOTS, GRAD_LOCKS, GRAD_MERGE,
 * SAMPLE_RECORD, TRACK_TOUCHED, BG_PER_RAY, BRICK, RAY_ORDER, GRID_POSE_GRAD, RAY_EXPOSURE,
 * BLOCK, BLOCK_FINE, COMPENSATED_SUMS, SH_PER_CORNER, CLRF_PREFETCH, PREFETCH_AHEAD,
 * PREFETCH_LINKS_AHEAD (march.h), CLRF_HAS_FP64 (ray.h), CLRF_INLINE (common.h). Arguments
 * that a define leaves unused are not in the signature: ray_out / loss_scale / beta_scale
 * only with GRAD_MODE 1 (then exp_index / exp_pixels / exp_rows / exp_state / exp_resid with
 * RAY_EXPOSURE), touched with TRACK_TOUCHED, the slot buffers with GRAD_SLOTS > 0,
 * grad_locks with GRAD_LOCKS, slot_rec / rec_max with SAMPLE_RECORD; with BG_PER_RAY, bg_rays
 * takes the place of bg and grad_bg follows grad_sh; with RAY_ORDER, render_forward and
 * render_backward end with ray_order.
 */
#include "march.h"

#ifndef BETA_EPS
#define BETA_EPS 1e-3f  /* guard inside the beta prior's logs (svox2/Neural Volumes: 1e-3) */
#endif
#ifndef GRAD_MODE
#define GRAD_MODE 0   /* 0: ray_in holds dL/drgb; 1: ray_in holds target rgb, loss = MSE */
#endif
#ifndef RAY_EXPOSURE
#define RAY_EXPOSURE 0   /* 1, 2 (clamped): the per-image colour transform in the loss */
#endif
#if RAY_EXPOSURE && (GRAD_MODE != 1 || BRICK)
#error "RAY_EXPOSURE needs GRAD_MODE 1 and no BRICK"
#endif
#ifndef GRAD_SLOTS
#define GRAD_SLOTS 0     /* > 0: private gradient copies per running work-item (CPU devices),
                            reduced by grad_slots_reduce; 0: float atomics into the buffers */
#endif
#ifndef SAMPLE_RECORD
#define SAMPLE_RECORD 0  /* 1 (needs GRAD_SLOTS > 0): a slot's forward march records every sample
                            and the backward reads the record instead of recomputing */
#endif
#ifndef GRAD_LOCKS
#define GRAD_LOCKS 0     /* > 0 (needs GRAD_SLOTS > 0): every work-item adds into the caller's
                            buffers under try-locks of 2^GRAD_LOCKS-voxel blocks (see
                            render_backward); 0: private copies per slot */
#endif
#if GRAD_LOCKS && GRAD_SLOTS == 0
#error "GRAD_LOCKS needs GRAD_SLOTS > 0 (the CPU path)"
#endif
#ifndef GRAD_MERGE
#define GRAD_MERGE 1     /* 1: a cell's corner gradients are summed over its samples in registers
                            and scattered once, when the march leaves the cell; 0 (needs
                            GRAD_SLOTS 0): each sample's are added with atomics as it is
                            evaluated (the host's choice on Intel GPUs, clrf/runtime/tuning.py:
                            the sums held across the march spill there) */
#endif
#if !GRAD_MERGE && GRAD_SLOTS > 0
#error "GRAD_MERGE 0 is the float-atomic path: build it with GRAD_SLOTS 0"
#endif
#ifndef TRACK_TOUCHED
#define TRACK_TOUCHED 0  /* 1: set touched[k] = 1 for every row that receives a gradient */
#endif
#ifndef BG_PER_RAY
#define BG_PER_RAY 0     /* 1: a background colour per ray (bg_rays [n, 3]) instead of the constant
                            bg, the backward writes dL/d bg_rays, and ray_exit is built */
#endif

#ifndef GRID_POSE_GRAD
#define GRID_POSE_GRAD 0 /* 1: build render_ray_grad, ray_grad [n, 6] = dL/d(origin,
                            direction) of each ray (pose refinement; see the header) */
#endif
#if GRID_POSE_GRAD && BRICK
#error "GRID_POSE_GRAD with BRICK: the distributed grid has no pose refinement"
#endif

/* The background argument of render_forward / render_backward and its value for ray i. */
#if BG_PER_RAY
#define BG_ARG __global const float *bg_rays
#define BG_OF(i) load3(bg_rays, (i))
#else
#define BG_ARG const float4 bg
#define BG_OF(i) (bg.xyz)
#endif
#if BRICK && GRAD_MODE != 0
#error "BRICK: the loss is taken on the composed rays (host); build with GRAD_MODE 0"
#endif

/* BRICK: the brick's place in the grid (march.h), the last arguments of every march kernel;
 * BRICK_SETUP copies them into the march state. */
#if BRICK
#define BRICK_ARGS , const int4 blo, const int4 bhi, const int4 lreso
#define BRICK_SETUP(m) do { (m).blo = blo; (m).bhi = bhi; (m).lreso = lreso; } while (0)
#else
#define BRICK_ARGS
#define BRICK_SETUP(m) do { } while (0)
#endif
#if BRICK && BG_PER_RAY
#error "BRICK with BG_PER_RAY: the distributed grid has no background model"
#endif

#ifndef RAY_ORDER
#define RAY_ORDER 0      /* 1: work-item g renders ray ray_order[g] (see the header) */
#endif
#if RAY_ORDER && BRICK
#error "RAY_ORDER with BRICK: bricks march their rays in the given order"
#endif
#if RAY_ORDER
#define RAY_ORDER_ARG , __global const int *ray_order
#define RAY_OF(g) ray_order[g]
#else
#define RAY_ORDER_ARG
#define RAY_OF(g) (g)
#endif

__kernel void render_forward(const int n_rays, __global const float *origins,
                             __global const float *dirs, __global const int *links,
                             __global const float *density, __global const float *sh,
                             const int4 reso, const float4 bmin, const float4 scale,
                             const float step, BG_ARG, __global float *out_rgb,
                             __global float *out_depth, __global float *out_acc,
#if BRICK
                             __global float *out_logT, __global int *out_key,
#endif
                             __global const uchar *occ, const int4 oreso BRICK_ARGS
                             RAY_ORDER_ARG) {
    const int gid = get_global_id(0);
    if (gid >= n_rays) return;
    const int i = RAY_OF(gid);
    march_t m;
    m.occ = occ;
    m.oreso = oreso;
    BRICK_SETUP(m);
    fwd_t f = {(float3)(0.0f), 0.0f, 0.0f, 0.0f};
    float t0 = 0.0f;
    int kfirst = -1;
    if (march_setup(load3(origins, i), load3(dirs, i), reso, bmin, scale, step, &m)) {
        float Y[SH_BASIS];
        sh_basis(m.dir, Y);
        march_forward(&m, reso, links, density, sh, Y, &kfirst, &f);
        t0 = m.t0;
    }
#if BRICK
    const float3 rgb = f.rgb;
    out_logT[i] = f.logT;
    out_key[i] = kfirst;
#else
    const float3 rgb = f.rgb + exp(f.logT) * BG_OF(i);
#endif
    out_rgb[3 * i] = rgb.x;
    out_rgb[3 * i + 1] = rgb.y;
    out_rgb[3 * i + 2] = rgb.z;
    out_depth[i] = t0 * f.acc + f.depth;
    out_acc[i] = f.acc;
}

/* A corner's merged colour gradient over the samples of one cell: the gradient of its SH row
 * (shv_t), or with SH_PER_CORNER the 3 sums sum_k w_c dL/dpre_k, whose product with the ray's
 * SH factors Y_b is that row (the factors are the same for every sample of a ray). */
#if SH_PER_CORNER
typedef float3 cgrad_t;
#define CGRAD_ZERO() ((float3)(0.0f))
#else
typedef shv_t cgrad_t;
#define CGRAD_ZERO() shv_zero()
#endif

/* The SH row gradient of corner gradient g (Y: the ray's SH factors, unused without
 * SH_PER_CORNER). */
CLRF_INLINE shv_t cgrad_row(cgrad_t g, const float *Y) {
#if SH_PER_CORNER
    float v[SH_DIM];
    const float gc[3] = {g.x, g.y, g.z};
#pragma unroll
    for (int ch = 0; ch < 3; ++ch)
#pragma unroll
        for (int b = 0; b < SH_BASIS; ++b) v[ch * SH_BASIS + b] = gc[ch] * Y[b];
    return shv_load_private(v);
#else
    return g;
#endif
}

/* Scatter the merged corner gradients of one cell into buffers shared with other work-items:
 * one float atomic add per non-zero value (with SH_PER_CORNER: per non-zero density value and
 * per SH value, zero or not); mark[k] = 1 if do_mark. */
CLRF_INLINE void flush_cell_atomic(const int *idx, const float *gsig, const cgrad_t *gsh,
                                   const float *Y, __global float *gdens,
                                   __global float *gsh_rows, __global uchar *mark,
                                   const int do_mark) {
    /* SH_PER_CORNER: unrolled, so the corners' sums stay in registers (a GPU keeps private
     * arrays indexed in a loop in memory) */
#if SH_PER_CORNER
#pragma unroll
#endif
    for (int c = 0; c < 8; ++c) {
        const int k = idx[c];
        if (k < 0) continue;
        if (gsig[c] != 0.0f) atomic_add_f(gdens + k, gsig[c]);
        __global float *row = gsh_rows + (size_t)k * SH_DIM;
#if SH_PER_CORNER
        /* each value as it is added, no row of SH_DIM floats held, and no test for zeros
         * (a channel's sum is 0 only where its colour was clamped at every sample): on a
         * device without float atomics each add is a compare-and-swap loop, and with a
         * branch around each one Intel's compiler spilled half as much again (tgllp) */
        const float gc[3] = {gsh[c].x, gsh[c].y, gsh[c].z};
#pragma unroll
        for (int ch = 0; ch < 3; ++ch)
#pragma unroll
            for (int b = 0; b < SH_BASIS; ++b) atomic_add_f(row + ch * SH_BASIS + b, gc[ch] * Y[b]);
#else
        float v[SH_DIM];
        shv_store_private(gsh[c], v);
        for (int j = 0; j < SH_DIM; ++j)
            if (v[j] != 0.0f) atomic_add_f(row + j, v[j]);
#endif
        if (do_mark) mark[k] = 1;
    }
}

/* Scatter into a gradient copy that this work-item holds alone (GRAD_SLOTS): plain vector
 * read-modify-write; mark[k] = 1 if do_mark. */
CLRF_INLINE void flush_cell_private(const int *idx, const float *gsig, const cgrad_t *gsh,
                                    const float *Y, __global float *gdens,
                                    __global float *gsh_rows, __global uchar *mark,
                                    const int do_mark) {
    for (int c = 0; c < 8; ++c) {
        const int k = idx[c];
        if (k < 0) continue;
        gdens[k] += gsig[c];
        __global float *row = gsh_rows + (size_t)k * SH_DIM;
        shv_store(shv_add(shv_load(row), cgrad_row(gsh[c], Y)), row);
        if (do_mark) mark[k] = 1;
    }
}

#if GRAD_LOCKS
#define LOCK_STRIDE 16   /* ints between two locks: one lock per 64-byte cache line */
/* The lock of voxel block (x, y, z) (blocks of 2^GRAD_LOCKS voxels per axis, (reso >>
 * GRAD_LOCKS) + 1 of them per axis) in grad_locks. */
CLRF_INLINE int lock_of(int x, int y, int z, int4 reso) {
    const int ny = (reso.y >> GRAD_LOCKS) + 1, nz = (reso.z >> GRAD_LOCKS) + 1;
    return ((x * ny + y) * nz + z) * LOCK_STRIDE;
}

/* Scatter one cell's merged corner gradients into the caller's buffers (gdens, gsh_rows,
 * mark) under the locks of every voxel block that holds one of its corners (lo .. lo + 1 per
 * axis: 1, 2, 4 or 8 blocks), taken in increasing order with compare-and-swap and never waited
 * for. If another work-item holds one of them, the values go with float atomics into the
 * scratch copy (sdens, ssh, smark: no plain stores ever touch it), which grad_slots_reduce adds
 * in afterwards. Either way each value is added exactly once. */
CLRF_INLINE void flush_cell_locked(int3 lo, int4 reso, __global volatile int *locks,
                                   const int *idx, const float *gsig, const cgrad_t *gsh,
                                   const float *Y, __global float *gdens, __global float *gsh_rows,
                                   __global uchar *mark, const int do_mark, __global float *sdens,
                                   __global float *ssh, __global uchar *smark) {
    const int3 a = lo >> GRAD_LOCKS, b = (lo + 1) >> GRAD_LOCKS;
    int held[8];
    int n = 0, ok = 1;
    for (int x = a.x; x <= b.x && ok; ++x)
        for (int y = a.y; y <= b.y && ok; ++y)
            for (int z = a.z; z <= b.z; ++z) {
                const int id = lock_of(x, y, z, reso);
                if (!lock_try(locks + id)) { ok = 0; break; }
                held[n++] = id;
            }
    if (ok) flush_cell_private(idx, gsig, gsh, Y, gdens, gsh_rows, mark, do_mark);
    for (int j = n - 1; j >= 0; --j) lock_release(locks + held[j]);
    if (!ok) flush_cell_atomic(idx, gsig, gsh, Y, sdens, ssh, smark, 1);
}
#endif

#if GRID_POSE_GRAD
/* d f / d p of lerp_axis along one axis: 1 where the fraction follows the point, 0 where it is
 * clamped (the outer half voxels) or the axis has one voxel. */
CLRF_INLINE float lerp_axis_slope(float p, int r) {
    const float u = p - 0.5f;
    return (r >= 2 && u > 0.0f && u < (float)(r - 1)) ? 1.0f : 0.0f;
}

/* One sample's share of its ray's camera gradient (header, GRID_POSE_GRAD): adds dL/dp_k (box
 * units) to *gp and the SH direction term sum_b dL/dY_b,k dY_b/dv (dL/dY_b,k = sum_ch
 * dL/dpre_ch sh_ch,b(p_k)) to *gdir. p: the sample (box units), L: its corners (set up at p),
 * dsig = dL/dsigma_k, dpre = dL/dpre_k (zero where the colour is clamped), Y the ray's SH
 * factors, dir the unit direction. Per corner c, with u_b = sum_ch dpre_ch sh_c,ch,b:
 * dL/dw_c = dsig density_c + sum_b Y_b u_b, and dL/dY_b gets w_c u_b. Reads the corner rows
 * again (an opt-in variant); the SH term is taken per sample so that the loop carries 6
 * floats, not SH_BASIS + 6, and every loop is unrolled so that the private arrays are indexed
 * by constants: Intel's Xe-LP (GRAD_MERGE 0, SH_PER_CORNER) spilled otherwise. */
CLRF_INLINE void pose_grad_sample(float3 p, int4 reso, const lerp_t *L,
                                  __global const float *density, __global const float *sh,
                                  const float *Y, const float3 dir, float dsig, float3 dpre,
                                  float3 *gp, float3 *gdir) {
    cellpos_t q;
    cell_locate(p, reso, &q);
    const float sx = lerp_axis_slope(p.x, reso.x), sy = lerp_axis_slope(p.y, reso.y),
                sz = lerp_axis_slope(p.z, reso.z);
    float3 acc = (float3)(0.0f);
    float dY[SH_BASIS];
#pragma unroll
    for (int b = 0; b < SH_BASIS; ++b) dY[b] = 0.0f;
#pragma unroll
    for (int c = 0; c < 8; ++c) {
        const int k = L->idx[c];
        if (k < 0) continue;
        /* corner c's weight is ax ay az; its slope along x is (c's x bit ? sx : -sx) ay az */
        const float ax = (c & 4) ? q.fx : 1.0f - q.fx, ay = (c & 2) ? q.fy : 1.0f - q.fy,
                    az = (c & 1) ? q.fz : 1.0f - q.fz;
        const float3 dw = (float3)(((c & 4) ? sx : -sx) * ay * az,
                                   ax * ((c & 2) ? sy : -sy) * az,
                                   ax * ay * ((c & 1) ? sz : -sz));
        __global const float *row = sh + (size_t)k * SH_DIM;
        const float wc = L->w[c];
        float s = dsig * density[k];   /* dL/dw_c */
#pragma unroll
        for (int b = 0; b < SH_BASIS; ++b) {
            const float u = dpre.x * row[b] + dpre.y * row[SH_BASIS + b]
                            + dpre.z * row[2 * SH_BASIS + b];
            s += Y[b] * u;
            dY[b] += wc * u;
        }
        acc += s * dw;
    }
    *gp += acc;
    *gdir += sh_dir_grad(dir, dY);
}
#endif

/* Backward pass. GRAD_MODE 0: ray_in = dL/drgb [n,3]. GRAD_MODE 1: ray_in = target rgb [n,3],
 * g = 2 (rgb - target) * loss_scale, and ray_out[i] = |rgb - target|^2 (summed over channels).
 * Gradients are added into grad_density [N] and grad_sh [N, SH_DIM].
 *
 * GRAD_SLOTS = S > 0 (CPU devices): S gradient copies that a work-item can hold alone; copy 0
 * is the caller's grad_density / grad_sh, copies 1..S-1 are scratch slot_density
 * [S, n_rows] / slot_sh [S, n_rows, SH_DIM] entries 0..S-2. Each work-item first tries to
 * take a copy (slot_lock[s] 0 -> 1 by compare-and-swap) and, holding it, adds with plain
 * vector stores. A work-item that finds every copy taken adds with float atomics into scratch
 * entry S-1. Scratch rows that received anything are marked in slot_touched [S, n_rows];
 * grad_slots_reduce then adds them into grad_density / grad_sh and zeroes them. With
 * SAMPLE_RECORD a slot also owns slot_rec [S, rec_max, 8]: the forward march records each
 * sample there (march.h, march_forward_rec) and the backward march reads it instead of
 * re-gathering the rows. PoCL runs one work-item at a time per compute unit, so with
 * S = compute units no atomics are used in practice, and the result is correct under any
 * scheduling.
 *
 * GRAD_LOCKS = L > 0 (with GRAD_SLOTS > 0; the slots then only hand out the records): no
 * private copies. Every work-item adds each cell's merged gradients straight into
 * grad_density / grad_sh, holding the locks grad_locks of the 2^L-voxel blocks that contain
 * the cell's corners (flush_cell_locked, compare-and-swap, never waited for). When one of them
 * is held by another work-item, that cell's values go with float atomics into the single
 * scratch entry 0 (slot_density [n_rows], slot_sh, marked in slot_touched), which
 * grad_slots_reduce adds in. Nothing is reduced for the cells that got their locks: on the
 * Zen 4 (2 compute units, 16^3-voxel blocks) 8 of 1.67 M rows went through the scratch. */
__kernel void render_backward(const int n_rays, __global const float *origins,
                              __global const float *dirs, __global const int *links,
                              __global const float *density, __global const float *sh,
                              const int4 reso, const float4 bmin, const float4 scale,
                              const float step, BG_ARG, __global const float *ray_in,
#if GRAD_MODE == 1
                              __global float *ray_out, const float loss_scale,
                              const float beta_scale,
#if RAY_EXPOSURE
                              __global const int *exp_index, const int exp_pixels,
                              __global const float *exp_rows, __global float *exp_state,
                              __global float *exp_resid,
#endif
#endif
                              __global float *grad_density, __global float *grad_sh,
#if BG_PER_RAY
                              __global float *grad_bg,
#endif
#if TRACK_TOUCHED
                              __global uchar *touched,
#endif
#if GRAD_SLOTS > 0
                              const int n_rows, __global float *slot_density,
                              __global float *slot_sh, __global uchar *slot_touched,
                              __global volatile int *slot_lock,
#if GRAD_LOCKS
                              __global volatile int *grad_locks,
#endif
#if SAMPLE_RECORD
                              __global float *slot_rec, const int rec_max,
#endif
#endif
                              __global const uchar *occ, const int4 oreso BRICK_ARGS
                              RAY_ORDER_ARG) {
    const int gid = get_global_id(0);
    if (gid >= n_rays) return;
    const int i = RAY_OF(gid);
    march_t m;
    m.occ = occ;
    m.oreso = oreso;
    BRICK_SETUP(m);
    const int hit = march_setup(load3(origins, i), load3(dirs, i), reso, bmin, scale, step, &m);

    /* where this work-item's gradients go; a slot also brings a private sample record */
    __global float *dst_d = grad_density;
    __global float *dst_s = grad_sh;
#if TRACK_TOUCHED
    __global uchar *mark = touched;
#else
    __global uchar *mark = 0;
#endif
    __global float *rec = 0;
    int rec_len = 0;
    int do_mark = TRACK_TOUCHED;
    int slot = -1;
#if GRAD_SLOTS > 0
    if (hit) {
        for (int s = 0; s < GRAD_SLOTS && slot < 0; ++s)
            if (lock_try(slot_lock + s)) slot = s;
    }
#if SAMPLE_RECORD
    if (slot >= 0) {
        rec = slot_rec + (size_t)slot * rec_max * 8;
        rec_len = rec_max;
    }
#endif
#if !GRAD_LOCKS   /* with GRAD_LOCKS every work-item adds into the caller's buffers */
    if (slot != 0) {   /* a scratch entry: its own (slot - 1), or the shared atomic one */
        const size_t e = slot > 0 ? (size_t)(slot - 1) : (size_t)(GRAD_SLOTS - 1);
        dst_d = slot_density + e * n_rows;
        dst_s = slot_sh + e * n_rows * SH_DIM;
        mark = slot_touched + e * n_rows;
        do_mark = 1;
    }
#endif
#endif

    float Y[SH_BASIS];
    fwd_t f = {(float3)(0.0f), 0.0f, 0.0f, 0.0f};
    int n_rec = -1, kfirst = -1;
    if (hit) {
        sh_basis(m.dir, Y);
        march_forward_rec(&m, reso, links, density, sh, Y, rec, rec_len, &n_rec, &kfirst, &f);
    }
#if BRICK   /* (T_b g, R_b): see the header */
    const float4 gin = vload4(i, ray_in);
    const float3 g = gin.xyz;
    const float total = dot(g, f.rgb) + gin.w;
#else
    const float Tend = exp(f.logT);
    const float3 rgb = f.rgb + Tend * BG_OF(i);
#if GRAD_MODE == 1
#if RAY_EXPOSURE   /* out = A rgb + b of the ray's image (see the header) */
    __global const float *ea = exp_rows + (size_t)(exp_index[i] / exp_pixels) * 12;
    const float3 eo = (float3)(ea[0] * rgb.x + ea[1] * rgb.y + ea[2] * rgb.z + ea[9],
                               ea[3] * rgb.x + ea[4] * rgb.y + ea[5] * rgb.z + ea[10],
                               ea[6] * rgb.x + ea[7] * rgb.y + ea[8] * rgb.z + ea[11]);
    const float3 etg = load3(ray_in, i);
#if RAY_EXPOSURE == 2   /* the loss sees clamp(out, 0, 1); a clipped channel passes nothing */
    const float3 es = clamp(eo, 0.0f, 1.0f) - etg;
    const float3 er = select(eo - etg, (float3)(0.0f),
                             isless(eo, (float3)(0.0f)) | isgreater(eo, (float3)(1.0f)));
#else
    const float3 es = eo - etg, er = es;
#endif
    ray_out[i] = dot(es, es);
    vstore3(er, i, exp_resid);
    vstore4((float4)(rgb, 1.0f), 2 * i, exp_state);   /* (whole pixel, opacity 1) */
    const float3 diff = (float3)(ea[0] * er.x + ea[3] * er.y + ea[6] * er.z,   /* A^T r */
                                 ea[1] * er.x + ea[4] * er.y + ea[7] * er.z,
                                 ea[2] * er.x + ea[5] * er.y + ea[8] * er.z);
#else
    const float3 diff = rgb - load3(ray_in, i);
    ray_out[i] = dot(diff, diff);
#endif
    const float3 g = 2.0f * loss_scale * diff;
    /* Beta prior (Neural Volumes) on the ray's final transmittance T:
     * beta_scale * [log(T + BETA_EPS) + log(1 - T + BETA_EPS)], pushing rays to be clear or
     * opaque. dT/dsigma_k = -delta_k T, so dL/dT enters the remaining radiance exactly like a
     * background channel: total += T * dL/dT. */
    const float gT = beta_scale != 0.0f
        ? beta_scale * (1.0f / (Tend + BETA_EPS) - 1.0f / (1.0f - Tend + BETA_EPS)) : 0.0f;
#else
    const float3 g = load3(ray_in, i);
    const float gT = 0.0f;
#endif
#if BG_PER_RAY
    vstore3(Tend * g, i, grad_bg);   /* dL/d bg_i: the pixel is C_fg + T_end bg_i */
#endif
    const float total = dot(g, rgb) + Tend * gT;
#endif
    if (!hit) return;
    const int use_rec = rec != 0 && n_rec >= 0;
#if SH_PER_CORNER
    const int S = 0;   /* (SAMPLE_PRE takes no vectors) */
#else
    shy_t S;
    shy_setup(Y, &S);
#endif

    float gsig[8];
    cgrad_t gsh[8];
    for (int c = 0; c < 8; ++c) { gsig[c] = 0.0f; gsh[c] = CGRAD_ZERO(); }
#if COMPENSATED_SUMS
    float gsig_c[8];   /* Kahan carries of the per-cell registers (long rays only) */
    cgrad_t gsh_c[8];
    for (int c = 0; c < 8; ++c) { gsig_c[c] = 0.0f; gsh_c[c] = CGRAD_ZERO(); }
#endif
    int cur_idx[8];
    int cur_cell = -1;
    int3 cur_lo = (int3)(0);
#if GRAD_LOCKS
#define FLUSH_CELL() flush_cell_locked(cur_lo, reso, grad_locks, cur_idx, gsig, gsh, Y, \
                                       dst_d, dst_s, mark, do_mark, slot_density, slot_sh, \
                                       slot_touched)
#else
#define FLUSH_CELL() do { \
        if (slot >= 0) flush_cell_private(cur_idx, gsig, gsh, Y, dst_d, dst_s, mark, do_mark); \
        else flush_cell_atomic(cur_idx, gsig, gsh, Y, dst_d, dst_s, mark, do_mark); \
    } while (0)
#endif
    lerp_t L;
    L.cell = -1;
    int pf[2] = {-1, -1};

    ksum_t logT = {0.0f, 0.0f};
    ksum_t prefix = {0.0f, 0.0f};
    float T = 1.0f;
    /* k: the record's entries in order (use_rec), or the segments, re-marched */
    const int kend = use_rec ? n_rec : m.nsteps;
    for (int k = use_rec ? 0 : MARCH_K0(&m); k < kend; ++k) {
        float mid, delta, sigma;
        if (use_rec) {
            sigma = rec[8 * k + REC_SIGMA];
            if (!(sigma > 0.0f)) continue;
            march_segment(&m, as_int(rec[8 * k + REC_K]), &mid, &delta);
#if CLRF_PREFETCH   /* the links, then the gradient rows, of entries ahead */
            float pmid, pdelta;
            if (k + PREFETCH_LINKS_AHEAD < n_rec) {
                march_segment(&m, as_int(rec[8 * (k + PREFETCH_LINKS_AHEAD) + REC_K]), &pmid,
                              &pdelta);
                prefetch_links(&m, m.p0 + pmid * m.dg, reso, links, &pf[1]);
            }
            if (k + PREFETCH_AHEAD < n_rec) {
                march_segment(&m, as_int(rec[8 * (k + PREFETCH_AHEAD) + REC_K]), &pmid, &pdelta);
                prefetch_cell_grad(&m, m.p0 + pmid * m.dg, reso, links, 0, 0, dst_d, dst_s,
                                   &pf[0]);
            }
#endif
            lerp_setup_cached(&m, m.p0 + mid * m.dg, reso, links, &L);
        } else {
            if (!march_visit(&m, reso, links, density, sh, dst_d, dst_s, pf, &k, &mid, &delta,
                             &L))
                continue;
            sigma = lerp_density(&L, density);
        }
        if (!(sigma > 0.0f)) continue;
        if (GRAD_MERGE && L.cell != cur_cell) {
            if (cur_cell >= 0) {
                FLUSH_CELL();
                for (int c = 0; c < 8; ++c) { gsig[c] = 0.0f; gsh[c] = CGRAD_ZERO(); }
#if COMPENSATED_SUMS
                for (int c = 0; c < 8; ++c) { gsig_c[c] = 0.0f; gsh_c[c] = CGRAD_ZERO(); }
#endif
            }
            cur_cell = L.cell;
            cur_lo = L.lo;
            for (int c = 0; c < 8; ++c) cur_idx[c] = L.idx[c];
        }
        float w, Tnext;
        float3 pre;
        if (use_rec) {
            const float8 r = vload8(k, rec);   /* entry k of the record */
            w = r.s1;
            Tnext = r.s2;
            pre = (float3)(r.s3, r.s4, r.s5);
        } else {
            w = vr_step(&logT, T, sigma * delta, &Tnext);
            pre = SAMPLE_PRE(&L, sh, &S, Y);
        }
        const float3 c = fmax(pre, 0.0f);
        const float dsig = vr_dsigma(&prefix, total, w, Tnext, dot(g, c), delta);
        const float3 dpre = select((float3)(0.0f), w * g, isgreater(pre, (float3)(0.0f)));
#if !SH_PER_CORNER
        /* d(loss)/d(coefficients) of this sample: dpre_ch * Y_b at ch*SH_BASIS + b */
        shv_t dco = shv_scale(S.ych[0], dpre.x);
        shv_axpy(&dco, dpre.y, S.ych[1]);
        shv_axpy(&dco, dpre.z, S.ych[2]);
#endif
#if !GRAD_MERGE   /* this sample's corner gradients, added now (flush_cell_atomic of one sample) */
        {
            float gs[8];
            cgrad_t gc[8];
#pragma unroll
            for (int cc = 0; cc < 8; ++cc) {
                gs[cc] = L.w[cc] * dsig;
#if SH_PER_CORNER
                gc[cc] = L.w[cc] * dpre;
#else
                gc[cc] = shv_scale(dco, L.w[cc]);
#endif
            }
            flush_cell_atomic(L.idx, gs, gc, Y, dst_d, dst_s, mark, do_mark);
        }
#elif SH_PER_CORNER   /* corner c's row gradient is Y_b times the sum of w_c dpre (cgrad_t) */
#pragma unroll
        for (int cc = 0; cc < 8; ++cc) {
            const float wc = L.w[cc];
#if COMPENSATED_SUMS
            csum_add(&gsig[cc], &gsig_c[cc], wc * dsig);
            const float3 y = wc * dpre - gsh_c[cc];
            const float3 t = gsh[cc] + y;
            gsh_c[cc] = (t - gsh[cc]) - y;
            gsh[cc] = t;
#else
            gsig[cc] += wc * dsig;
            gsh[cc] += wc * dpre;
#endif
        }
#else
#pragma unroll
        for (int cc = 0; cc < 8; ++cc) {
            const float wc = L.w[cc];
#if COMPENSATED_SUMS
            csum_add(&gsig[cc], &gsig_c[cc], wc * dsig);
            const shv_t y = shv_add(shv_scale(dco, wc), shv_scale(gsh_c[cc], -1.0f));
            const shv_t t = shv_add(gsh[cc], y);
            gsh_c[cc] = shv_add(shv_add(t, shv_scale(gsh[cc], -1.0f)), shv_scale(y, -1.0f));
            gsh[cc] = t;
#else
            gsig[cc] += wc * dsig;
            shv_axpy(&gsh[cc], wc, dco);
#endif
        }
#endif
        T = Tnext;
        if (Tnext < T_STOP) break;
    }
    if (GRAD_MERGE && cur_cell >= 0) FLUSH_CELL();
#undef FLUSH_CELL
#if GRAD_SLOTS > 0
    if (slot >= 0) lock_release(slot_lock + slot);
#endif
}

#if GRID_POSE_GRAD
/* ray_grad [n, 6] = (dL/do, dL/dd) of each ray, the loss as render_backward takes it (GRAD_MODE
 * 0: ray_in = dL/drgb; 1: ray_in = the targets, with loss_scale and the beta prior's
 * beta_scale), its sample distances held (header, GRID_POSE_GRAD); zeros for a ray that misses
 * the box. A kernel of its own, run after render_backward: it marches the ray forward (for
 * g.rgb) and back again as render_backward does, but scatters nothing, so the backward's
 * gradient state and this one's per-ray sums are never live together (in render_backward
 * they spilled on Intel's Xe-LP, where even 6 more floats carried across the march did). */
__kernel void render_ray_grad(const int n_rays, __global const float *origins,
                              __global const float *dirs, __global const int *links,
                              __global const float *density, __global const float *sh,
                              const int4 reso, const float4 bmin, const float4 scale,
                              const float step, BG_ARG, __global const float *ray_in,
#if GRAD_MODE == 1
                              const float loss_scale, const float beta_scale,
#endif
                              __global float *ray_grad, __global const uchar *occ,
                              const int4 oreso RAY_ORDER_ARG) {
    const int gid = get_global_id(0);
    if (gid >= n_rays) return;
    const int i = RAY_OF(gid);
    march_t m;
    m.occ = occ;
    m.oreso = oreso;
    const float3 d0 = load3(dirs, i);
    float3 g_o = (float3)(0.0f), g_dh = (float3)(0.0f);   /* dL/do, dL/ddh */
    if (march_setup(load3(origins, i), d0, reso, bmin, scale, step, &m)) {
        float Y[SH_BASIS];
        sh_basis(m.dir, Y);
        fwd_t f = {(float3)(0.0f), 0.0f, 0.0f, 0.0f};
        int kfirst = -1;
        march_forward(&m, reso, links, density, sh, Y, &kfirst, &f);
        const float Tend = exp(f.logT);
        const float3 rgb = f.rgb + Tend * BG_OF(i);
#if GRAD_MODE == 1   /* as render_backward: the MSE's gradient and the beta prior's dL/dT */
        const float3 g = 2.0f * loss_scale * (rgb - load3(ray_in, i));
        const float gT = beta_scale != 0.0f
            ? beta_scale * (1.0f / (Tend + BETA_EPS) - 1.0f / (1.0f - Tend + BETA_EPS)) : 0.0f;
#else
        const float3 g = load3(ray_in, i);
        const float gT = 0.0f;
#endif
        const float total = dot(g, rgb) + Tend * gT;
#if SH_PER_CORNER
        const int S = 0;   /* (SAMPLE_PRE takes no vectors) */
#else
        shy_t S;
        shy_setup(Y, &S);
#endif
        lerp_t L;
        L.cell = -1;
        ksum_t logT = {0.0f, 0.0f};
        ksum_t prefix = {0.0f, 0.0f};
        float T = 1.0f;
        for (int k = 0; k < m.nsteps; ++k) {
            float mid, delta;
            if (!march_visit(&m, reso, links, density, sh, 0, 0, 0, &k, &mid, &delta, &L))
                continue;
            const float sigma = lerp_density(&L, density);
            if (!(sigma > 0.0f)) continue;
            float Tnext;
            const float w = vr_step(&logT, T, sigma * delta, &Tnext);
            const float3 pre = SAMPLE_PRE(&L, sh, &S, Y);
            const float3 c = fmax(pre, 0.0f);
            const float dsig = vr_dsigma(&prefix, total, w, Tnext, dot(g, c), delta);
            const float3 dpre = select((float3)(0.0f), w * g, isgreater(pre, (float3)(0.0f)));
            float3 gp = (float3)(0.0f);
            pose_grad_sample(m.p0 + mid * m.dg, reso, &L, density, sh, Y, m.dir, dsig, dpre,
                             &gp, &g_dh);
            const float3 gx = gp * scale.xyz;   /* dL/dx_k: dp/dx = diag(scale) */
            g_o += gx;
            g_dh += (m.t0 + mid) * gx;
            T = Tnext;
            if (Tnext < T_STOP) break;
        }
        /* dL/dd = (I - dh dh^T) dL/ddh / |d|, |d| scaled first as march_setup does */
        const float mx = fmax(fabs(d0.x), fmax(fabs(d0.y), fabs(d0.z)));
        g_dh = (g_dh - m.dir * dot(m.dir, g_dh)) / (mx * length(d0 / mx));
    }
    vstore3(g_o, 2 * i, ray_grad);
    vstore3(g_dh, 2 * i + 1, ray_grad);
}
#endif

/* After render_backward with GRAD_SLOTS > 0: for every row k marked in a scratch copy, add the
 * copy's gradient into grad_density / grad_sh, zero it and clear the mark (so the copies are
 * zero again for the next call), and set touched[k] (TRACK_TOUCHED). One work-item per
 * REDUCE_ROWS consecutive rows, which it passes over with one vector load of their marks when
 * none is set (with GRAD_LOCKS almost all of them). */
#define REDUCE_ROWS 16
CLRF_INLINE void reduce_row(const int k, const size_t r, __global float *slot_density,
                            __global float *slot_sh, __global uchar *slot_touched,
                            __global float *grad_density, __global float *grad_sh,
                            __global uchar *touched) {
    if (!slot_touched[r]) return;
    grad_density[k] += slot_density[r];
    slot_density[r] = 0.0f;
    __global float *src = slot_sh + r * SH_DIM;
    __global float *dst = grad_sh + (size_t)k * SH_DIM;
    shv_store(shv_add(shv_load(dst), shv_load(src)), dst);
    shv_store(shv_zero(), src);
    slot_touched[r] = 0;
#if TRACK_TOUCHED
    touched[k] = 1;
#endif
}

__kernel void grad_slots_reduce(const int n_rows, __global float *slot_density,
                                __global float *slot_sh, __global uchar *slot_touched,
                                __global float *grad_density, __global float *grad_sh,
                                __global uchar *touched) {
    const int k0 = get_global_id(0) * REDUCE_ROWS;
    if (k0 >= n_rows) return;
#if GRAD_SLOTS > 0
    for (int s = 0; s < (GRAD_LOCKS ? 1 : GRAD_SLOTS); ++s) {
        const size_t r0 = (size_t)s * n_rows + k0;
        if (k0 + REDUCE_ROWS <= n_rows) {
            const uchar16 m = vload16(0, slot_touched + r0);
            if (!any(as_char16(m) != (char16)(0))) continue;
        }
        for (int k = k0; k < min(k0 + REDUCE_ROWS, n_rows); ++k)
            reduce_row(k, r0 + (k - k0), slot_density, slot_sh, slot_touched, grad_density,
                       grad_sh, touched);
    }
#endif
}

/* Pruning weights: maxw[k] = max over rays and samples of w_sample * w_corner for every row k
 * that is a corner of a sample (maxw must be zeroed by the caller). The same march as
 * render_forward, without colour. */
__kernel void render_max_weight(const int n_rays, __global const float *origins,
                                __global const float *dirs, __global const int *links,
                                __global const float *density, const int4 reso,
                                const float4 bmin, const float4 scale, const float step,
                                __global float *maxw, __global const uchar *occ,
                                const int4 oreso
#if BRICK
                                , __global const float *ray_T
#endif
                                BRICK_ARGS) {
    const int i = get_global_id(0);
    if (i >= n_rays) return;
    march_t m;
    m.occ = occ;
    m.oreso = oreso;
    BRICK_SETUP(m);
    if (!march_setup(load3(origins, i), load3(dirs, i), reso, bmin, scale, step, &m)) return;
    ksum_t logT = {0.0f, 0.0f};
#if BRICK
    const float Tb = ray_T[i];   /* transmittance in front of the brick */
#else
    const float Tb = 1.0f;
#endif
    float T = 1.0f;
    lerp_t L;
    L.cell = -1;
    for (int k = MARCH_K0(&m); k < m.nsteps; ++k) {
        float mid, delta;
        if (!march_visit(&m, reso, links, density, 0, 0, 0, 0, &k, &mid, &delta, &L)) continue;
        const float sigma = lerp_density(&L, density);
        if (!(sigma > 0.0f)) continue;
        float Tnext;
        const float w = Tb * vr_step(&logT, T, sigma * delta, &Tnext);
        for (int c = 0; c < 8; ++c)
            if (L.idx[c] >= 0 && L.w[c] > 0.0f) atomic_max_nonneg_f(maxw + L.idx[c], w * L.w[c]);
        T = Tnext;
        if (T < T_STOP) break;
    }
}

/* occ[off + b] = 1 if block b of nb^3 cells (cells with lower corner in [b*nb, b*nb + nb - 1]
 * per axis) has an allocated corner voxel, i.e. any links >= 0 in [b*nb, b*nb + nb] (clamped):
 * the tables skip_block reads (nb = BLOCK at offset 0, nb = BLOCK_FINE at offset oreso.w).
 * One work-item per block, blocks in C order, oreso blocks per axis. */
__kernel void block_occupancy(const int4 reso, const int4 oreso, const int nb, const int off,
                              __global const int *links, __global uchar *occ) {
    const int b = get_global_id(0);
    if (b >= oreso.x * oreso.y * oreso.z) return;
    const int bz = b % oreso.z, by = (b / oreso.z) % oreso.y, bx = b / (oreso.y * oreso.z);
    const int3 lo = (int3)(bx, by, bz) * nb;
    const int3 hi = min(lo + nb, (int3)(reso.x, reso.y, reso.z) - 1);
    uchar any = 0;
    for (int x = lo.x; x <= hi.x && !any; ++x)
        for (int y = lo.y; y <= hi.y && !any; ++y)
            for (int z = lo.z; z <= hi.z; ++z)
                if (links[cell_of(x, y, z, reso)] >= 0) { any = 1; break; }
    occ[off + b] = any;
}

#if BG_PER_RAY
/* t_exit[i] = where ray i leaves the grid box: world distance along its unit direction
 * (march_setup's t0 + len, the end of its last segment), 0 for a ray that misses the box.
 * The background model starts there. */
__kernel void ray_exit(const int n_rays, __global const float *origins,
                       __global const float *dirs, const int4 reso, const float4 bmin,
                       const float4 scale, const float step, __global float *t_exit) {
    const int i = get_global_id(0);
    if (i >= n_rays) return;
    march_t m;
    t_exit[i] = march_setup(load3(origins, i), load3(dirs, i), reso, bmin, scale, step, &m)
        ? m.t0 + m.len : 0.0f;
}
#endif

/* Sort keys for RAY_ORDER: keys[i] = the Morton code (10 bits per axis, interleaved x, y, z
 * from the top bit down) of the cell that holds the midpoint of ray i's path through the grid
 * box, its coordinates divided by 2^shift (the host quantises to 32 blocks per axis); rays
 * that miss the box get 0xffffffff and go last. */
#if !BRICK
CLRF_INLINE uint morton_spread10(uint v) {
    v &= 0x3ffu;
    v = (v | (v << 16)) & 0x030000ffu;
    v = (v | (v << 8)) & 0x0300f00fu;
    v = (v | (v << 4)) & 0x030c30c3u;
    v = (v | (v << 2)) & 0x09249249u;
    return v;
}

__kernel void ray_order_keys(const int n_rays, __global const float *origins,
                             __global const float *dirs, const int4 reso, const float4 bmin,
                             const float4 scale, const float step, const int shift,
                             __global uint *keys) {
    const int i = get_global_id(0);
    if (i >= n_rays) return;
    march_t m;
    if (!march_setup(load3(origins, i), load3(dirs, i), reso, bmin, scale, step, &m)) {
        keys[i] = 0xffffffffu;
        return;
    }
    const int3 hi = (int3)(reso.x - 1, reso.y - 1, reso.z - 1);
    const float3 mid = m.p0 + (0.5f * m.len) * m.dg;
    const int3 c = clamp(convert_int3_rtn(mid), (int3)(0), hi) >> shift;
    keys[i] = (morton_spread10((uint)c.x) << 2) | (morton_spread10((uint)c.y) << 1) |
              morton_spread10((uint)c.z);
}
#endif

/* Test hook (tests/test_march_alpha.py): out[i] = alpha_of_tau(tau[i]), the opacity every
 * kernel of this file uses. */
__kernel void march_alpha_eval(const int n, __global const float *tau, __global float *out) {
    const int i = get_global_id(0);
    if (i < n) out[i] = alpha_of_tau(tau[i]);
}
