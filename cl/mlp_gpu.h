/* mlp_gpu.h: the GPU tiling of the fused MLP, included by mlp.cl with MLP_GPU=1 (after
 * mlp_net.h). The network, the parameter buffer and its transposed copy, the scratch rows A and
 * G, the partial weight gradients, mlp_reduce, mlp_transpose and mlp_layout are mlp.cl's; the
 * kernels here have the CPU tiles' names and arguments (mlp_weight_grad takes one more, the
 * chunk), only the work split differs.
 *
 * Forward, density and backward: a work-group of GPU_WG work-items owns a block of GPU_BM
 * consecutive samples (scratch rows r0 .. r0 + BM - 1) and runs it through every layer in one
 * launch. The block's current layer input stays in local memory, transposed:
 *   Xt[k * BM + s]   k: input column, s: sample of the block; GPU_XW columns, the widest layer
 *                    input or output gradient the block holds
 * and the product of a layer
 *   forward   Y[s, j] = b_j + sum_{k < kin} Xt[k, s] Wt[k, j]       Wt = params_t [nin, nout]
 *   backward  Y[s, k] = sum_{live j} Gt[j, s] W[j, k]                W = params [nout, nin]
 * runs in passes of GPU_NC output columns. In a pass, work-item lid = tr * CT + tc (CT = NC / TN
 * work-items across the columns) holds a register tile of GPU_TM samples (tr * TM ..) x GPU_TN
 * columns (tc * TN ..). With NC >= 128 the 32 work-items of an NVIDIA warp share tr, so their
 * reads of Xt are broadcasts, and they read consecutive columns of the staged weights. The
 * weights pass through local memory in K-slices Ws [GPU_BK rows x NC columns], loaded by the
 * whole group between two barriers (each weight read from global memory once per block). Every
 * pass's tile stays in registers until the layer's last pass; then, after a barrier, the
 * outputs (activated) overwrite Xt in place as the next layer's input and go to A (which the
 * backward reads): local memory holds the widest layer once, not twice. Where the next layer's
 * input is more than this layer's output, the rest is loaded beside it: x after h_SKIP (the
 * skip connection), the encoded direction after the feature.
 * The backward runs the same way from the rgb layer down: Gt holds the block's gradients of the
 * current layer's outputs; the input gradients (times the activation derivative, read from A)
 * go to G and overwrite Gt as the gradients of the layer below.
 *
 * Weight gradient (mlp_weight_grad): dW[j, k] = sum_s G[s, out_off + j] A[s, in_off + k] is a
 * product whose sum runs over samples. A work-group owns one GPU_DW_BJ x GPU_DW_BKW tile of one
 * layer's dW (and, for the tiles at k = 0, the bias gradient sum_s G[s, out_off + j]) over one
 * chunk of `chunk` scratch rows, a kernel argument: the host picks the number of chunks P so
 * that the groups fill the device. It stages GPU_DW_BS rows of G and of A at a time in local
 * memory; each work-item sums a GPU_DW_TJ x GPU_DW_TK register tile over the chunk and writes it
 * to the chunk's partial gradient (partial [P, NPARAM], as with the CPU tiles); mlp_reduce sums
 * the P partials in chunk order. No atomics: the sum is deterministic for a given P, nothing is
 * zeroed first, and P x NPARAM floats of partials stay small because P is a few groups per
 * compute unit divided by the tiles of a chunk (float atomic adds, emulated by compare-and-swap
 * on NVIDIA's driver without inline PTX and on PoCL, would add one atomic per parameter per
 * group and make every gradient depend on the order of arrival).
 *
 * Local memory per group: forward / backward 4 * (XW * BM + BK * NC + BM) bytes (Xt, Ws, the
 * block's density gradients); weight gradient 4 * BS * (BJ + BKW). GPU_TM and then GPU_BK,
 * when not given, are the largest that fit in GPU_LOCAL_MAX (the host passes the device's local
 * memory size); NVIDIA's 48 KiB give 8 x 256 (XW 320) 8 samples x 4 columns per work-item,
 * blocks of 32 samples and K-slices of 4 rows, and 64-wide MLPs blocks of 64 or 128 samples.
 *
 * Defines read: GPU_WG, GPU_LOCAL_MAX, GPU_TN, GPU_NC, GPU_TM, GPU_BK, GPU_DW_TJ, GPU_DW_TK,
 * GPU_DW_BJ, GPU_DW_BS.
 */

#ifndef GPU_WG
#define GPU_WG 256          /* work-items per group, a power of two; the host clamps it to the
                               device's and the kernels' maximum work-group size */
#endif
#ifndef GPU_LOCAL_MAX
#define GPU_LOCAL_MAX 32768 /* local memory bytes a group may use (the host: the device's) */
#endif
#ifndef GPU_TN
#define GPU_TN 4            /* output columns per work-item in a pass (a float4 of weights) */
#endif
#ifndef GPU_NC              /* columns per pass: the trunk width's largest power of two <= 256 */
#if MLP_WIDTH >= 256 && GPU_WG * GPU_TN >= 256
#define GPU_NC 256
#elif MLP_WIDTH >= 128 && GPU_WG * GPU_TN >= 128
#define GPU_NC 128
#elif MLP_WIDTH >= 64 && GPU_WG * GPU_TN >= 64
#define GPU_NC 64
#elif MLP_WIDTH >= 32 && GPU_WG * GPU_TN >= 32
#define GPU_NC 32
#else
#define GPU_NC 16
#endif
#endif
#define GPU_CT (GPU_NC / GPU_TN)   /* work-items across a pass's columns */
#define GPU_RT (GPU_WG / GPU_CT)   /* work-items across the block's samples */

#define GPU_MAX2(a, b) ((a) > (b) ? (a) : (b))
/* Local columns: the widest layer input (x; [h_SKIP, x]; h; [feature, d]; c) or block of output
 * gradients (head: 16 + FEAT; rgb: 16). */
#define GPU_XW GPU_MAX2(GPU_MAX2(GPU_MAX2(IN_P, MW + (MLP_SKIP >= 0 ? IN_P : 0)),              \
                                 GPU_MAX2(HEAD_PAD + MLP_FEAT, MLP_FEAT + DIN_P)),             \
                        GPU_MAX2(MLP_COLOR_WIDTH, RGB_P))
/* Forward / backward local bytes with tm samples per work-item and K-slices of bk rows. */
#define GPU_LOCAL_BYTES(tm, bk) (4 * (GPU_XW * GPU_RT * (tm) + (bk) * GPU_NC + GPU_RT * (tm)))

#ifndef GPU_TM              /* samples per work-item: the most of 8, 4, 2, 1 that fit */
#if GPU_LOCAL_BYTES(8, 1) <= GPU_LOCAL_MAX
#define GPU_TM 8
#elif GPU_LOCAL_BYTES(4, 1) <= GPU_LOCAL_MAX
#define GPU_TM 4
#elif GPU_LOCAL_BYTES(2, 1) <= GPU_LOCAL_MAX
#define GPU_TM 2
#else
#define GPU_TM 1
#endif
#endif
#ifndef GPU_BK              /* weight rows per staged K-slice: the most of 16 .. 1 that fit */
#if GPU_LOCAL_BYTES(GPU_TM, 16) <= GPU_LOCAL_MAX
#define GPU_BK 16
#elif GPU_LOCAL_BYTES(GPU_TM, 8) <= GPU_LOCAL_MAX
#define GPU_BK 8
#elif GPU_LOCAL_BYTES(GPU_TM, 4) <= GPU_LOCAL_MAX
#define GPU_BK 4
#elif GPU_LOCAL_BYTES(GPU_TM, 2) <= GPU_LOCAL_MAX
#define GPU_BK 2
#else
#define GPU_BK 1
#endif
#endif
#define GPU_BM (GPU_RT * GPU_TM)                       /* samples per work-group */
#define GPU_TILE (GPU_TM * GPU_TN)                     /* accumulators of one pass */
#define GPU_MAXP ((GPU_XW + GPU_NC - 1) / GPU_NC)      /* passes of the widest product */

#ifndef GPU_DW_TJ
#define GPU_DW_TJ 4         /* weight gradient: output neurons per work-item */
#endif
#ifndef GPU_DW_TK
#define GPU_DW_TK 4         /* weight gradient: input columns per work-item */
#endif
#ifndef GPU_DW_BJ
#define GPU_DW_BJ (GPU_WG >= 16 ? 64 : GPU_WG * GPU_DW_TJ)  /* output neurons per group tile */
#endif
#ifndef GPU_DW_BS
#define GPU_DW_BS 16        /* scratch rows of G and A staged per step */
#endif
#define GPU_DW_JT (GPU_DW_BJ / GPU_DW_TJ)    /* work-items across the tile's outputs */
#define GPU_DW_KT (GPU_WG / GPU_DW_JT)       /* work-items across its inputs */
#define GPU_DW_BKW (GPU_DW_KT * GPU_DW_TK)   /* input columns per group tile */
#define GPU_DW_LOCAL_BYTES (4 * GPU_DW_BS * (GPU_DW_BJ + GPU_DW_BKW))

#if GPU_WG < 1 || (GPU_WG & (GPU_WG - 1)) != 0
#error "GPU_WG must be a power of two"
#endif
#if GPU_TN != 1 && GPU_TN != 2 && GPU_TN != 4 && GPU_TN != 8
#error "GPU_TN must be 1, 2, 4 or 8"
#endif
#if GPU_TM != 1 && GPU_TM != 2 && GPU_TM != 4 && GPU_TM != 8
#error "GPU_TM must be 1, 2, 4 or 8"
#endif
#if GPU_NC < GPU_TN || GPU_NC % GPU_TN != 0 || GPU_CT > GPU_WG || GPU_WG % GPU_CT != 0
#error "GPU_NC must be a multiple of GPU_TN, with GPU_NC / GPU_TN dividing GPU_WG"
#endif
#if GPU_BK < 1 || GPU_BK > 64
#error "GPU_BK must be in 1..64"
#endif
#if GPU_LOCAL_BYTES(GPU_TM, GPU_BK) > GPU_LOCAL_MAX
#error "GPU_TM, GPU_BK: the forward and backward need more local memory than GPU_LOCAL_MAX"
#endif
#if GPU_DW_TJ != 1 && GPU_DW_TJ != 2 && GPU_DW_TJ != 4 && GPU_DW_TJ != 8
#error "GPU_DW_TJ must be 1, 2, 4 or 8"
#endif
#if GPU_DW_TK != 1 && GPU_DW_TK != 2 && GPU_DW_TK != 4 && GPU_DW_TK != 8
#error "GPU_DW_TK must be 1, 2, 4 or 8"
#endif
#if GPU_DW_BJ < GPU_DW_TJ || GPU_DW_BJ % GPU_DW_TJ != 0 || GPU_DW_JT > GPU_WG || \
    GPU_WG % GPU_DW_JT != 0
#error "GPU_DW_BJ must be a multiple of GPU_DW_TJ, with GPU_DW_BJ / GPU_DW_TJ dividing GPU_WG"
#endif
#if GPU_DW_BS < 1
#error "GPU_DW_BS must be >= 1"
#endif
#if GPU_DW_LOCAL_BYTES > GPU_LOCAL_MAX
#error "GPU_DW_BJ, GPU_DW_BS: the weight gradient needs more local memory than GPU_LOCAL_MAX"
#endif

/* float4-typed local arrays, so that a work-item's TM samples / TN columns (4-aligned when TM,
 * TN are multiples of 4) load as one 16-byte vector. */
#define GPU_F4(n) (((n) + 3) / 4)
#define GPU_WG_ATTR __attribute__((reqd_work_group_size(GPU_WG, 1, 1)))

/* dst[0 .. N-1] = src[0 .. N-1] from local memory (src 16-byte aligned when N % 4 == 0). */
#define GPU_LOAD_LOCAL(dst, src, N)                                                         \
    if ((N) % 4 == 0) {                                                                     \
        for (int q = 0; q < (N) / 4; ++q) {                                                 \
            const float4 v = ((__local const float4 *)(src))[q];                            \
            dst[4 * q] = v.x; dst[4 * q + 1] = v.y; dst[4 * q + 2] = v.z; dst[4 * q + 3] = v.w; \
        }                                                                                   \
    } else {                                                                                \
        for (int q = 0; q < (N); ++q) dst[q] = (src)[q];                                    \
    }

/* One k of a pass: acc[i * TN + c] += x[i] w[c] for the work-item's TM samples x TN columns. */
CLRF_INLINE void gpu_fma_step(__local const float *x, __local const float *w, float *acc) {
    float a[GPU_TM], b[GPU_TN];
    GPU_LOAD_LOCAL(a, x, GPU_TM)
    GPU_LOAD_LOCAL(b, w, GPU_TN)
#pragma unroll
    for (int i = 0; i < GPU_TM; ++i)
#pragma unroll
        for (int c = 0; c < GPU_TN; ++c) acc[i * GPU_TN + c] = fma(a[i], b[c], acc[i * GPU_TN + c]);
}

/* acc[i * TN + c] += sum_{k in [kb, ke)} Xt[k * BM + tr * TM + i] M[k * ms + c0 + tc * TN + c],
 * the rows of M staged through Ws in K-slices of GPU_BK rows x GPU_NC columns; columns of M at
 * or beyond ncol read as 0. Every work-item of the group calls it with the same arguments (it
 * holds barriers); Xt rows kb .. ke-1 must be written. */
CLRF_INLINE void gpu_gemm(__local const float *Xt, __local float *Ws,
                          __global const float *M, const int ms, const int kb,
                          const int ke, const int c0, const int ncol, float *acc) {
    const int lid = get_local_id(0);
    __local const float *x = Xt + (lid / GPU_CT) * GPU_TM;
    __local const float *w = Ws + (lid % GPU_CT) * GPU_TN;
    for (int k0 = kb; k0 < ke; k0 += GPU_BK) {
        barrier(CLK_LOCAL_MEM_FENCE);            /* every work-item is done with the last slice */
        for (int e = lid; e < GPU_BK * GPU_NC; e += GPU_WG) {
            const int k = k0 + e / GPU_NC, c = c0 + e % GPU_NC;
            Ws[e] = (k < ke && c < ncol) ? M[(size_t)k * ms + c] : 0.0f;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        const int kn = min(GPU_BK, ke - k0);
        if (kn == GPU_BK) {
#pragma unroll
            for (int kk = 0; kk < GPU_BK; ++kk)
                gpu_fma_step(x + (k0 + kk) * GPU_BM, w + kk * GPU_NC, acc);
        } else {
            for (int kk = 0; kk < kn; ++kk)
                gpu_fma_step(x + (k0 + kk) * GPU_BM, w + kk * GPU_NC, acc);
        }
    }
}

/* Cooperative copy of `dim` columns of rows r0 .. r0+BM-1 of src [n, dim] (zeros beyond dim
 * and n) into the padded slot range at `off` of A's rows and, with xcol >= 0, into Xt columns
 * xcol .. xcol+dim_p-1. */
CLRF_INLINE void gpu_load_input(const int n, const int r0, __global const float *src,
                                const int dim, const int dim_p, __global float *A, const int off,
                                __local float *Xt, const int xcol) {
    for (int e = get_local_id(0); e < GPU_BM * dim_p; e += GPU_WG) {
        const int s = e / dim_p, k = e % dim_p, row = r0 + s;
        const float v = (row < n && k < dim) ? src[(size_t)row * dim + k] : 0.0f;
        if (A) A[(size_t)row * NSLOT + off + k] = v;
        if (xcol >= 0) Xt[(xcol + k) * GPU_BM + s] = v;
    }
}

/* The forward product of layer L, every pass: acc[p * TILE ..] = b + Xt Wt over the live
 * inputs, for the output columns p * NC + tc * TN + c < nout. */
CLRF_INLINE void gpu_product_forward(const layer_t L, __global const float *Pt,
                                     __local const float *Xt, __local float *Ws, float *acc) {
    const int wo = (get_local_id(0) % GPU_CT) * GPU_TN;
#pragma unroll
    for (int p = 0; p < GPU_MAXP; ++p) {
        if (p * GPU_NC < L.nout) {
            float *a = acc + p * GPU_TILE;
#pragma unroll
            for (int c = 0; c < GPU_TN; ++c) {
                const int j = p * GPU_NC + wo + c;
                const float b = j < L.nout ? Pt[L.b_off + j] : 0.0f;
#pragma unroll
                for (int i = 0; i < GPU_TM; ++i) a[i * GPU_TN + c] = b;
            }
            gpu_gemm(Xt, Ws, Pt + L.w_off, L.nout, 0, L.kin, p * GPU_NC, L.nout, a);
        }
    }
}

/* The backward product of layer L for its first ncol inputs, every pass: acc[p * TILE ..] =
 * sum over the live outputs j (0 .. kout1-1, ko2 .. ko2+kout2-1) of Gt[j, s] W[j, k]. */
CLRF_INLINE void gpu_product_backward(const layer_t L, __global const float *P,
                                      __local const float *Gt, __local float *Ws, const int ncol,
                                      float *acc) {
#pragma unroll
    for (int p = 0; p < GPU_MAXP; ++p) {
        if (p * GPU_NC < ncol) {
            float *a = acc + p * GPU_TILE;
#pragma unroll
            for (int i = 0; i < GPU_TILE; ++i) a[i] = 0.0f;
            gpu_gemm(Gt, Ws, P + L.w_off, L.nin, 0, L.kout1, p * GPU_NC, ncol, a);
            if (L.kout2 > 0)
                gpu_gemm(Gt, Ws, P + L.w_off, L.nin, L.ko2, L.ko2 + L.kout2, p * GPU_NC, ncol, a);
        }
    }
}

/* After the forward product of layer l (every work-item done reading Xt): activate, store to
 * A (and sigma_out / rgb_out for the block's live rows), and write what the next layer reads
 * into Xt: the hidden and colour layers' outputs at their own columns, the head's feature at
 * columns 0 .. FEAT-1 (the direction goes after it), nothing of the rgb layer. */
CLRF_INLINE void gpu_store_forward(const int l, const layer_t L, const int act, const int n,
                                   const int r0, const float *acc, __local float *Xt,
                                   __global float *A, __global float *sigma_out,
                                   __global float *rgb_out) {
    const int lid = get_local_id(0);
    const int s0 = (lid / GPU_CT) * GPU_TM, wo = (lid % GPU_CT) * GPU_TN;
#pragma unroll
    for (int p = 0; p < GPU_MAXP; ++p) {
        if (p * GPU_NC < L.nout) {
#pragma unroll
            for (int i = 0; i < GPU_TM; ++i) {
                const int s = s0 + i, row = r0 + s;
                __global float *a = A + (size_t)row * NSLOT + L.out_off;
#pragma unroll
                for (int c = 0; c < GPU_TN; ++c) {
                    const int j = p * GPU_NC + wo + c;
                    if (j >= L.nout) continue;
                    float v = act_forward(acc[p * GPU_TILE + i * GPU_TN + c], act);
                    if (l == MLP_DEPTH && j == 0) {
                        v = sigma_forward(v);
                        if (row < n) sigma_out[row] = v;
                    }
                    a[j] = v;
                    if (l == NLAYER - 1) {
                        if (j < 3 && row < n) rgb_out[3 * row + j] = v;
                    } else if (l != MLP_DEPTH) {
                        Xt[j * GPU_BM + s] = v;
                    } else if (j >= HEAD_PAD) {
                        Xt[(j - HEAD_PAD) * GPU_BM + s] = v;
                    }
                }
            }
        }
    }
}

/* Forward of the block at r0: the trunk and the head, then (colour) the colour layers and rgb.
 * A receives every activation; sigma_out [n] and (colour) rgb_out [n, 3] the outputs. */
CLRF_INLINE void gpu_forward(const int n, const int r0, __global const float *x_enc,
                             __global const float *d_enc, __global const float *Pt,
                             __global float *A, __global float *sigma_out,
                             __global float *rgb_out, const int colour, __local float *Xt,
                             __local float *Ws) {
    float acc[GPU_MAXP * GPU_TILE];
    gpu_load_input(n, r0, x_enc, MLP_IN, IN_P, A, SL_X, Xt, 0);
#if MLP_SKIP >= 0
    gpu_load_input(n, r0, x_enc, MLP_IN, IN_P, A, SL_XS, Xt, -1);
#endif
    if (colour) gpu_load_input(n, r0, d_enc, MLP_DIR_IN, DIN_P, A, SL_DV, Xt, -1);
    barrier(CLK_LOCAL_MEM_FENCE);
    const int last = colour ? NLAYER - 1 : MLP_DEPTH;
    for (int l = 0; l <= last; ++l) {
        const layer_t L = layer_desc(l);
        const int act = l == MLP_DEPTH ? ACT_NONE : l == NLAYER - 1 ? ACT_SIGMOID : HIDDEN_ACT;
        gpu_product_forward(L, Pt, Xt, Ws, acc);
        barrier(CLK_LOCAL_MEM_FENCE);            /* every work-item is done reading Xt */
        gpu_store_forward(l, L, act, n, r0, acc, Xt, A, sigma_out, rgb_out);
        if (l == MLP_SKIP)                       /* the next layer's input is [h_SKIP, x] */
            gpu_load_input(n, r0, x_enc, MLP_IN, IN_P, 0, 0, Xt, MW);
        if (l == MLP_DEPTH && colour)            /* the colour layer's is [feature, d] */
            gpu_load_input(n, r0, d_enc, MLP_DIR_IN, DIN_P, 0, 0, Xt, MLP_FEAT);
        barrier(CLK_LOCAL_MEM_FENCE);
    }
}

/* mlp_density of mlp.cl: sigma [n] only, A used as scratch; one work-group per GPU_BM rows. */
__kernel GPU_WG_ATTR void mlp_density(const int n_max, __global const int *count,
                                      __global const float *x_enc,
                                      __global const float *params_t, __global float *A_all,
                                      __global float *sigma_out) {
    __local float4 xt4[GPU_F4(GPU_XW * GPU_BM)], ws4[GPU_F4(GPU_BK * GPU_NC)];
    const int n = live_rows(n_max, count);
    const int r0 = get_group_id(0) * GPU_BM;
    if (r0 >= n) return;                         /* the whole group */
    gpu_forward(n, r0, x_enc, x_enc, params_t, A_all, sigma_out, sigma_out, 0,
                (__local float *)xt4, (__local float *)ws4);
}

/* mlp_forward of mlp.cl: sigma [n], rgb [n, 3] and every activation in A_all. */
__kernel GPU_WG_ATTR void mlp_forward(const int n_max, __global const int *count,
                                      __global const float *x_enc,
                                      __global const float *d_enc,
                                      __global const float *params_t, __global float *A_all,
                                      __global float *sigma_out, __global float *rgb_out) {
    __local float4 xt4[GPU_F4(GPU_XW * GPU_BM)], ws4[GPU_F4(GPU_BK * GPU_NC)];
    const int n = live_rows(n_max, count);
    const int r0 = get_group_id(0) * GPU_BM;
    if (r0 >= n) return;                         /* the whole group */
    gpu_forward(n, r0, x_enc, d_enc, params_t, A_all, sigma_out, rgb_out, 1,
                (__local float *)xt4, (__local float *)ws4);
}

/* mlp_backward of mlp.cl: dsigma [n], drgb [n, 3] -> G_all (every slot the weight gradient
 * reads) and, with want_input, dx_enc [n, MLP_IN], dd_enc [n, MLP_DIR_IN]. The input gradients
 * of layer l overwrite Gt as the output gradients of layer l-1: h_{l-1} at its own columns, the
 * head's feature after its 16 rows of sigma and padding (those from gsig); the skip's x part
 * and the encoded direction's go to G only. */
__kernel GPU_WG_ATTR void mlp_backward(const int n_max, __global const int *count,
                                       __global const float *dsigma,
                                       __global const float *drgb, __global const float *params,
                                       __global const float *A_all, __global float *G_all,
                                       const int want_input, __global float *dx_enc,
                                       __global float *dd_enc) {
    __local float4 xt4[GPU_F4(GPU_XW * GPU_BM)], ws4[GPU_F4(GPU_BK * GPU_NC)];
    __local float gsig[GPU_BM];
    __local float *Gt = (__local float *)xt4, *Ws = (__local float *)ws4;
    const int lid = get_local_id(0);
    const int n = live_rows(n_max, count);
    const int r0 = get_group_id(0) * GPU_BM;
    if (r0 >= n) return;                         /* the whole group */
    /* the head's and the rgb layer's output gradients (their padding rows 0) */
    for (int e = lid; e < GPU_BM * LPAD; e += GPU_WG) {
        const int s = e / LPAD, c = e % LPAD, row = r0 + s;
        const size_t o = (size_t)row * NSLOT;
        float gr = 0.0f, gs = 0.0f;
        if (row < n && c < 3) gr = drgb[3 * row + c] * sigmoid_grad_from_y(A_all[o + SL_RGB + c]);
        if (row < n && c == 0) gs = dsigma[row] * act_grad1(A_all[o + SL_HD], SIGMA_ACT);
        G_all[o + SL_RGB + c] = gr;
        Gt[c * GPU_BM + s] = gr;
        G_all[o + SL_HD + c] = gs;
        if (c == 0) gsig[s] = gs;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    const int s0 = (lid / GPU_CT) * GPU_TM, wo = (lid % GPU_CT) * GPU_TN;
    float acc[GPU_MAXP * GPU_TILE];
    for (int l = NLAYER - 1; l >= 0; --l) {
        if (l == 0 && !want_input) break;
        const layer_t L = layer_desc(l);
        /* input columns wanted and how many of them carry the hidden activation */
        int ncol = L.nin, n_act = 0;
        if (l > MLP_DEPTH + 1) {                 /* rgb, colour c_1 .. */
            n_act = MLP_COLOR_WIDTH;
        } else if (l == MLP_DEPTH + 1) {         /* [feature, d]: d's only when asked for */
            ncol = want_input ? MLP_FEAT + DIN_P : MLP_FEAT;
        } else if (l >= 1) {                     /* head, trunk 1 .. D-1: [h, (x)] */
            n_act = MW;
        }
        gpu_product_backward(L, params, Gt, Ws, ncol, acc);
        barrier(CLK_LOCAL_MEM_FENCE);            /* every work-item is done reading Gt */
#pragma unroll
        for (int p = 0; p < GPU_MAXP; ++p) {
            if (p * GPU_NC < ncol) {
#pragma unroll
                for (int i = 0; i < GPU_TM; ++i) {
                    const int s = s0 + i;
                    const size_t o = (size_t)(r0 + s) * NSLOT + L.in_off;
#pragma unroll
                    for (int c = 0; c < GPU_TN; ++c) {
                        const int k = p * GPU_NC + wo + c;
                        if (k >= ncol) continue;
                        float d = acc[p * GPU_TILE + i * GPU_TN + c];
                        if (k < n_act) d = hidden_act_grad_mul(d, A_all[o + k]);
                        G_all[o + k] = d;
                        if (l == MLP_DEPTH + 1) {
                            if (k < MLP_FEAT) Gt[(HEAD_PAD + k) * GPU_BM + s] = d;
                        } else if (l > MLP_DEPTH || (l >= 1 && k < MW)) {
                            Gt[k * GPU_BM + s] = d;
                        }
                    }
                }
            }
        }
        if (l == MLP_DEPTH + 1)                  /* the head's sigma row and padding rows */
            for (int e = lid; e < GPU_BM * HEAD_PAD; e += GPU_WG) {
                const int s = e / HEAD_PAD, c = e % HEAD_PAD;
                Gt[c * GPU_BM + s] = c == 0 ? gsig[s] : 0.0f;
            }
        barrier(CLK_LOCAL_MEM_FENCE);
    }
    if (!want_input) return;                     /* the whole group */
    barrier(CLK_GLOBAL_MEM_FENCE);               /* G's input slots, written by the group */
    for (int e = lid; e < GPU_BM * MLP_IN; e += GPU_WG) {
        const int s = e / MLP_IN, k = e % MLP_IN, row = r0 + s;
        if (row >= n) continue;
        __global const float *g = G_all + (size_t)row * NSLOT;
        float v = g[SL_X + k];
#if MLP_SKIP >= 0
        v += g[SL_XS + k];
#endif
        dx_enc[(size_t)row * MLP_IN + k] = v;
    }
    for (int e = lid; e < GPU_BM * MLP_DIR_IN; e += GPU_WG) {
        const int s = e / MLP_DIR_IN, k = e % MLP_DIR_IN, row = r0 + s;
        if (row < n) dd_enc[(size_t)row * MLP_DIR_IN + k] = G_all[(size_t)row * NSLOT + SL_DV + k];
    }
}

/* Weight-gradient tiles of one layer and of one chunk (every layer). */
inline int gpu_wgrad_layer_tiles(const layer_t L) {
    return ((L.nout + GPU_DW_BJ - 1) / GPU_DW_BJ) * ((L.nin + GPU_DW_BKW - 1) / GPU_DW_BKW);
}

inline int gpu_wgrad_tiles(void) {
    int t = 0;
    for (int l = 0; l < NLAYER; ++l) t += gpu_wgrad_layer_tiles(layer_desc(l));
    return t;
}

/* Partial weight and bias gradients over chunk p of the scratch rows (rows p*chunk ..
 * min((p+1)*chunk, n_rows) - 1), as mlp.cl's mlp_weight_grad:
 *   partial[p, w_off + j*nin + k] = sum_s G[s, out_off + j] A[s, in_off + k],
 *   partial[p, b_off + j]         = sum_s G[s, out_off + j].
 * Work-group gid = p * gpu_wgrad_tiles() + e (chunk-major); e runs over the layers in order,
 * within a layer e' = kt * njt + jt: outputs jt * BJ .., inputs kt * BKW ... Work-item lid =
 * tj * KT + tk sums outputs tj * TJ .. x inputs tk * TK .. of the tile. */
__kernel GPU_WG_ATTR void mlp_weight_grad(const int n_rows_max, __global const int *count,
                                          const int chunk,
                                          __global const float *A, __global const float *G,
                                          __global float *partial) {
    const int n_rows = live_tile_rows(n_rows_max, count, GPU_BM);
    __local float4 gs4[GPU_F4(GPU_DW_BS * GPU_DW_BJ)], as4[GPU_F4(GPU_DW_BS * GPU_DW_BKW)];
    __local float *Gs = (__local float *)gs4, *As = (__local float *)as4;
    const int ipc = gpu_wgrad_tiles();
    const int grp = get_group_id(0), lid = get_local_id(0);
    const int p = grp / ipc;
    int e = grp % ipc, layer = 0;
    while (e >= gpu_wgrad_layer_tiles(layer_desc(layer)))
        e -= gpu_wgrad_layer_tiles(layer_desc(layer++));
    const layer_t L = layer_desc(layer);
    const int njt = (L.nout + GPU_DW_BJ - 1) / GPU_DW_BJ;
    const int j0 = (e % njt) * GPU_DW_BJ, k0 = (e / njt) * GPU_DW_BKW;
    const int tj = lid / GPU_DW_KT, tk = lid % GPU_DW_KT;
    const int s_end = min(n_rows, (p + 1) * chunk);
    const int bias = k0 == 0 && lid < GPU_DW_BJ;   /* this work-item sums output j0 + lid */
    float acc[GPU_DW_TJ * GPU_DW_TK], bsum = 0.0f;
#pragma unroll
    for (int i = 0; i < GPU_DW_TJ * GPU_DW_TK; ++i) acc[i] = 0.0f;
    for (int sb = p * chunk; sb < s_end; sb += GPU_DW_BS) {
        barrier(CLK_LOCAL_MEM_FENCE);            /* every work-item is done with the last rows */
        for (int i = lid; i < GPU_DW_BS * GPU_DW_BJ; i += GPU_WG) {
            const int s = sb + i / GPU_DW_BJ, j = j0 + i % GPU_DW_BJ;
            Gs[i] = (s < s_end && j < L.nout) ? G[(size_t)s * NSLOT + L.out_off + j] : 0.0f;
        }
        for (int i = lid; i < GPU_DW_BS * GPU_DW_BKW; i += GPU_WG) {
            const int s = sb + i / GPU_DW_BKW, k = k0 + i % GPU_DW_BKW;
            As[i] = (s < s_end && k < L.nin) ? A[(size_t)s * NSLOT + L.in_off + k] : 0.0f;
        }
        barrier(CLK_LOCAL_MEM_FENCE);
        if (bias)
            for (int ss = 0; ss < GPU_DW_BS; ++ss) bsum += Gs[ss * GPU_DW_BJ + lid];
        for (int ss = 0; ss < GPU_DW_BS; ++ss) {
            float g[GPU_DW_TJ], a[GPU_DW_TK];
            GPU_LOAD_LOCAL(g, Gs + ss * GPU_DW_BJ + tj * GPU_DW_TJ, GPU_DW_TJ)
            GPU_LOAD_LOCAL(a, As + ss * GPU_DW_BKW + tk * GPU_DW_TK, GPU_DW_TK)
#pragma unroll
            for (int i = 0; i < GPU_DW_TJ; ++i)
#pragma unroll
                for (int c = 0; c < GPU_DW_TK; ++c)
                    acc[i * GPU_DW_TK + c] = fma(g[i], a[c], acc[i * GPU_DW_TK + c]);
        }
    }
    __global float *out = partial + (size_t)p * n_params();
#pragma unroll
    for (int i = 0; i < GPU_DW_TJ; ++i) {
        const int j = j0 + tj * GPU_DW_TJ + i;
        if (j >= L.nout) break;
#pragma unroll
        for (int c = 0; c < GPU_DW_TK; ++c) {
            const int k = k0 + tk * GPU_DW_TK + c;
            if (k < L.nin) out[L.w_off + (size_t)j * L.nin + k] = acc[i * GPU_DW_TK + c];
        }
    }
    if (bias && j0 + lid < L.nout) out[L.b_off + j0 + lid] = bsum;
}
