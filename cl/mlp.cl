/* mlp.cl: the fused NeRF MLP, forward and backward, for tiles of MLP_ROWS samples (CPU
 * devices) or, with MLP_GPU=1, for work-groups of samples in local memory (mlp_gpu.h).
 *
 * Network (NeRF's, with the sizes as defines):
 *   h_0 = act(W_0 x + b_0), h_l = act(W_l h_{l-1} + b_l) for l = 1..D-1, where the input of
 *   layer MLP_SKIP+1 is [h_SKIP, x] (NeRF's skip connection; MLP_SKIP = -1: none);
 *   head: [sigma_raw, feature] = W_D h_{D-1} + b_D;  sigma = SIGMA_ACT(sigma_raw);
 *   c_0 = act(W_{D+1} [feature, d] + b_{D+1}),  c_j = act(W_{D+1+j} c_{j-1} + b_{D+1+j}) for
 *   j = 1..CD-1 (CD = MLP_COLOR_DEPTH colour hidden layers; NeRF: 1);
 *   rgb = sigmoid(W_{D+1+CD} c_{CD-1} + b_{D+1+CD}).
 *   x: encoded position [MLP_IN], d: encoded view direction [MLP_DIR_IN], act = HIDDEN_ACT,
 *   feature: MLP_FEAT wide (NeRF: W; the hash model's density MLP: 16).
 *
 * Padding. Every vector is padded to a multiple of LPAD = 16 floats, so each block of 16
 * columns is one float16: inputs MLP_IN -> IN_P, MLP_DIR_IN -> DIN_P; the head has 16 + FEAT
 * outputs (sigma, 15 zero rows, feature) and the rgb layer 16 outputs (r, g, b, 13 zero rows).
 * Padded weights are zero and stay zero: their inputs are 0 and their output gradients are
 * set to 0, so their weight gradients are exactly 0. The products skip what padding they can
 * without breaking the float16 blocks: the forward sums over the live inputs only (layer_t.kin),
 * the backward over the live outputs (kout1, ko2, kout2: sigma and the feature of the head,
 * r, g, b of the rgb layer), and it computes the input gradients of layer 0 and of the encoded
 * direction only when they are asked for (want_input).
 *
 * Parameters: ONE contiguous float buffer. Layer l (l = 0..NLAYER-1, NLAYER = D + 2 + CD) holds
 *   W_l [nout_l, nin_l] row-major at w_off_l, then b_l [nout_l] at b_off_l = w_off_l + nout*nin,
 * and layer l+1 starts right after b_l. layer_desc(l) (mlp_net.h, shared by both tilings) is
 * the single definition of the offsets; the host reads them with the mlp_layout kernel. The
 * forward reads a transposed copy (params_t: each W_l stored [nin_l, nout_l] at the same
 * offsets, biases copied) made by mlp_transpose after every parameter update, so both passes
 * stream contiguous weight rows.
 *
 * Scratch. Per sample one row of NSLOT floats in A (activations, after activation functions)
 * and G (dL/d pre-activation, or dL/d input for input slots). Row layout (slot offsets):
 *   SL_X  encoded position [IN_P] | h_0 [W] ... h_SKIP [W] | SL_XS copy of x [IN_P] | ... h_{D-1}
 *   SL_HD head [16 + FEAT] = sigma, pad, feature (SL_FEAT) | SL_DV encoded direction [DIN_P]
 *   SL_C colour hidden c_0 [WC] ... c_{CD-1} [WC] | SL_RGB rgb [16]
 * so that the input of every layer is one contiguous slot range (the copy of x sits right after
 * h_SKIP, the encoded direction right after the feature). Rows n..n_rows-1 of a batch are
 * padding: their output gradients are 0, so they add nothing to the weight gradients.
 *
 * Vectorisation. Every matrix product goes through gemm_tile: a ROWS x (16*CJ) register block
 * of float16 accumulators, each float16 weight row loaded once per ROWS samples and each
 * scalar activation broadcast into CJ FMAs (PoCL does not vectorise loops across work-items).
 * The tile shape is per device (defines below): the accumulators must fit the register file,
 * e.g. AVX-512 (32 zmm) takes 8 rows x 32 columns (16 float16 = 16 zmm), AVX2 (16 ymm, one
 * float16 = 2 ymm) 6 rows x 16 columns (12 ymm + the weight row + one broadcast).
 *   forward      A_out[s, j]  = act(b_j + sum_k A_in[s, k] Wt[k, j])     (rows = samples)
 *   backward     G_in[s, k]   = act'(A_in[s, k]) sum_j G_out[s, j] W[j, k] (rows = samples)
 *   weight grad  dW[j, k]     = sum_s G_out[s, j] A_in[s, k]              (rows = outputs j)
 * Weight gradients are reduced without races: mlp_weight_grad writes one partial gradient
 * (weights and biases) per chunk of DW_CHUNK rows (partial [P, NPARAM]), mlp_reduce sums them.
 *
 * GPU tiling (MLP_GPU=1, mlp_gpu.h): the same network, parameter buffer, scratch rows and
 * partial gradients, and the same kernels (mlp_weight_grad takes the chunk as an argument);
 * a work-group runs a block of samples through every layer with the block's activations in
 * local memory and small register tiles per work-item. The CPU tiles' defines are then unused.
 *
 * Sizes on the device: every kernel but mlp_reduce takes (n_max, count) for its rows, and covers
 * live_rows(n_max, count) samples (common.h; mlp_weight_grad those rows rounded up to whole
 * tiles): a step launched over a bounded buffer's capacity n_max reads its live rows from the
 * device (null count: n_max). Chunks of the weight gradient past them write zero partials.
 *
 * Defines read: MLP_WIDTH, MLP_DEPTH, MLP_SKIP, MLP_COLOR_WIDTH, MLP_COLOR_DEPTH, MLP_FEAT,
 * MLP_IN, MLP_DIR_IN, HIDDEN_ACT,
 * SIGMA_ACT, MLP_ROWS, MLP_COLS, DW_ROWS, DW_COLS, DW_CHUNK, MLP_PREFETCH, DW_PREFETCH_AHEAD,
 * MLP_GPU (and with it those of mlp_gpu.h).
 */
#include "common.h"
#include "mlp_net.h"

#ifndef MLP_GPU
#define MLP_GPU 0           /* 1: the GPU tiling (mlp_gpu.h) instead of the CPU tiles below */
#endif

#if MLP_GPU
#include "mlp_gpu.h"
#else  /* the CPU tiles */

#ifndef MLP_ROWS
#define MLP_ROWS 8          /* samples per work-item in mlp_forward / mlp_backward */
#endif
#ifndef MLP_COLS
#define MLP_COLS 32         /* columns per tile there: 32 (two float16) or 16 (one) */
#endif
#ifndef DW_ROWS
#define DW_ROWS 8           /* output neurons per work-item in mlp_weight_grad; divides 16 */
#endif
#ifndef DW_COLS
#define DW_COLS 32          /* input columns per work-item there: 32 or 16 */
#endif
#ifndef DW_CHUNK
#define DW_CHUNK 512        /* scratch rows per partial weight gradient; multiple of MLP_ROWS */
#endif

#if MLP_ROWS != 1 && MLP_ROWS != 2 && MLP_ROWS != 3 && MLP_ROWS != 4 && MLP_ROWS != 5 && \
    MLP_ROWS != 6 && MLP_ROWS != 8 && MLP_ROWS != 12 && MLP_ROWS != 16
#error "MLP_ROWS must be 1, 2, 3, 4, 5, 6, 8, 12 or 16"
#endif
#if MLP_COLS != 16 && MLP_COLS != 32
#error "MLP_COLS must be 16 or 32"
#endif
#if DW_ROWS != 1 && DW_ROWS != 2 && DW_ROWS != 4 && DW_ROWS != 8 && DW_ROWS != 16
#error "DW_ROWS must divide 16"
#endif
#if DW_COLS != 16 && DW_COLS != 32
#error "DW_COLS must be 16 or 32"
#endif
#if DW_CHUNK < MLP_ROWS || DW_CHUNK % MLP_ROWS != 0
#error "DW_CHUNK must be a positive multiple of MLP_ROWS"
#endif

#ifndef MLP_PREFETCH
#define MLP_PREFETCH 0      /* 1: software prefetch (__builtin_prefetch; clang CPU compilers, PoCL)
                               of what the backward and weight gradient read from DRAM */
#endif
#ifndef DW_PREFETCH_AHEAD
#define DW_PREFETCH_AHEAD 16 /* rows ahead in the weight gradient's sum over samples */
#endif
/* SPIR targets (Mesa rusticl, Intel's CPU runtime, Oclgrind define __SPIR__ or __SPIR64__)
   get no software prefetch: SPIR-V has no counterpart of llvm.prefetch, and rusticl 22.3's SPIR-V
   translator ends the host process on llvm.prefetch instead of failing the build. The host sets
   CLRF_BUILTIN_PREFETCH for PoCL only: NVIDIA's compiler rejects __builtin_prefetch of a __global
   pointer (an address-space change), and gets OpenCL C's prefetch() too. */
#if MLP_PREFETCH && CLRF_BUILTIN_PREFETCH && !defined(__SPIR__) && !defined(__SPIR64__)
#define MLP_PREFETCH_LINE(p) __builtin_prefetch((p), 0, 3)
#elif MLP_PREFETCH
#define MLP_PREFETCH_LINE(p) prefetch((p), 1)  /* OpenCL C's own: a real prefetch on Intel */
#else
#define MLP_PREFETCH_LINE(p)
#endif

/* ---- the register-blocked product ---------------------------------------------------------
 * acc[r*CJ + c] += sum_{k<K} L[r*lr + k*lk] * M[k*ms + 16c .. 16c+15]  for r < ROWS, c < CJ.
 * PoCL's compiler neither unrolls the row loop nor keeps a private accumulator array in
 * registers, so the tile is written out with one named float16 per accumulator (REPn repeats
 * a per-row statement n times); acc is read once before and written once after the k loop. */
#define REP1(X) X(0)
#define REP2(X) REP1(X) X(1)
#define REP3(X) REP2(X) X(2)
#define REP4(X) REP3(X) X(3)
#define REP5(X) REP4(X) X(4)
#define REP6(X) REP5(X) X(5)
#define REP8(X) REP6(X) X(6) X(7)
#define REP12(X) REP8(X) X(8) X(9) X(10) X(11)
#define REP16(X) REP12(X) X(12) X(13) X(14) X(15)
#define REPN_(n) REP##n
#define REPN(n) REPN_(n)

#define T2_LOAD(r) float16 a##r##0 = acc[2 * r], a##r##1 = acc[2 * r + 1];
#define T2_FMA(r) {                                                                         \
        const float16 l = (float16)(Lp[(size_t)(r) * lr + (size_t)k * lk]);                \
        a##r##0 = fma(l, m0, a##r##0);                                                      \
        a##r##1 = fma(l, m1, a##r##1);                                                      \
    }
#define T2_STORE(r) acc[2 * r] = a##r##0; acc[2 * r + 1] = a##r##1;
#define T1_LOAD(r) float16 a##r##0 = acc[r];
#define T1_FMA(r) a##r##0 = fma((float16)(Lp[(size_t)(r) * lr + (size_t)k * lk]), m0, a##r##0);
#define T1_STORE(r) acc[r] = a##r##0;

#define DEFINE_GEMM_TILE2(NAME, ROWS)                                                       \
    inline void NAME(__global const float *restrict Lp, const int lr, const int lk,         \
                     __global const float *restrict Mp, const int ms, const int K,          \
                     float16 *acc) {                                                        \
        REPN(ROWS)(T2_LOAD)                                                                 \
        for (int k = 0; k < K; ++k) {                                                       \
            const float16 m0 = vload16(0, Mp + (size_t)k * ms);                             \
            const float16 m1 = vload16(0, Mp + (size_t)k * ms + 16);                        \
            REPN(ROWS)(T2_FMA)                                                              \
        }                                                                                   \
        REPN(ROWS)(T2_STORE)                                                                \
    }
#define DEFINE_GEMM_TILE1(NAME, ROWS)                                                       \
    inline void NAME(__global const float *restrict Lp, const int lr, const int lk,         \
                     __global const float *restrict Mp, const int ms, const int K,          \
                     float16 *acc) {                                                        \
        REPN(ROWS)(T1_LOAD)                                                                 \
        for (int k = 0; k < K; ++k) {                                                       \
            const float16 m0 = vload16(0, Mp + (size_t)k * ms);                             \
            REPN(ROWS)(T1_FMA)                                                              \
        }                                                                                   \
        REPN(ROWS)(T1_STORE)                                                                \
    }
#if MLP_COLS == 32
DEFINE_GEMM_TILE2(gemm_rows2, MLP_ROWS)
#endif
DEFINE_GEMM_TILE1(gemm_rows1, MLP_ROWS)
/* The weight gradient's tiles: the same, and (MLP_PREFETCH) DW_PREFETCH_AHEAD rows ahead the
 * lines of L and M that row k + DW_PREFETCH_AHEAD will read (rows are NSLOT floats apart, too
 * far for the hardware's stream prefetcher to run ahead of). */
#define DEFINE_GEMM_DW(NAME, ROWS, NV, LOADS, FMA)                                         \
    inline void NAME(__global const float *restrict Lp, const int lr, const int lk,         \
                     __global const float *restrict Mp, const int ms, const int K,          \
                     float16 *acc) {                                                        \
        REPN(ROWS)(NV##_LOAD)                                                               \
        for (int k = 0; k < K; ++k) {                                                       \
            MLP_PREFETCH_LINE(Lp + (size_t)(k + DW_PREFETCH_AHEAD) * lk);                   \
            MLP_PREFETCH_LINE(Mp + (size_t)(k + DW_PREFETCH_AHEAD) * ms);                   \
            LOADS                                                                           \
            REPN(ROWS)(FMA)                                                                 \
        }                                                                                   \
        REPN(ROWS)(NV##_STORE)                                                              \
    }
#define DW_LOADS2 const float16 m0 = vload16(0, Mp + (size_t)k * ms);                       \
                  const float16 m1 = vload16(0, Mp + (size_t)k * ms + 16);
#define DW_LOADS1 const float16 m0 = vload16(0, Mp + (size_t)k * ms);
#if DW_COLS == 32
DEFINE_GEMM_DW(gemm_dw2, DW_ROWS, T2, DW_LOADS2, T2_FMA)
#endif
DEFINE_GEMM_DW(gemm_dw1, DW_ROWS, T1, DW_LOADS1, T1_FMA)


/* The helpers from here on are static inline: an inline definition alone (C99) gives no
 * external one to call where a compiler does not inline it, and clang's NVPTX build of the
 * tiles left calls to layer_forward and trunk_forward unresolved (tools/gpu_builds.py). The
 * gemm tiles above stay inline: as static functions, inlined with their restrict arguments,
 * they carry llvm.experimental.noalias.scope.decl, which Oclgrind 21.10 cannot run. */

/* Forward of one layer for the MLP_ROWS rows starting at A (row stride NSLOT): MLP_COLS-wide
 * column blocks, then 16-wide ones for the rest (nout is a multiple of 16). */
static inline void layer_forward(const layer_t L, __global const float *Pt, __global float *A,
                                 const int act) {
    int j0 = 0;
#if MLP_COLS == 32
    for (; j0 + 32 <= L.nout; j0 += 32) {
        float16 acc[MLP_ROWS * 2];
        const float16 b0 = vload16(0, Pt + L.b_off + j0), b1 = vload16(0, Pt + L.b_off + j0 + 16);
        for (int r = 0; r < MLP_ROWS; ++r) { acc[2 * r] = b0; acc[2 * r + 1] = b1; }
        gemm_rows2(A + L.in_off, NSLOT, 1, Pt + L.w_off + j0, L.nout, L.kin, acc);
        for (int r = 0; r < MLP_ROWS; ++r)
            for (int c = 0; c < 2; ++c)
                vstore16(act_forward(acc[2 * r + c], act), 0,
                         A + (size_t)r * NSLOT + L.out_off + j0 + 16 * c);
    }
#endif
    for (; j0 < L.nout; j0 += 16) {
        float16 acc[MLP_ROWS];
        const float16 b0 = vload16(0, Pt + L.b_off + j0);
        for (int r = 0; r < MLP_ROWS; ++r) acc[r] = b0;
        gemm_rows1(A + L.in_off, NSLOT, 1, Pt + L.w_off + j0, L.nout, L.kin, acc);
        for (int r = 0; r < MLP_ROWS; ++r)
            vstore16(act_forward(acc[r], act), 0, A + (size_t)r * NSLOT + L.out_off + j0);
    }
}

/* MLP_PREFETCH: the lines of columns k0 .. k1-1 (multiples of 16) of the MLP_ROWS rows of A,
 * which the backward's activation derivative reads after the next column block's product. A
 * was written by the forward long before (from DRAM), and each row's few lines per layer are
 * too short a stream for the hardware prefetcher. */
static inline void prefetch_act(__global const float *A, const int k0, const int k1) {
#if MLP_PREFETCH
    for (int r = 0; r < MLP_ROWS; ++r)
        for (int k = k0; k < k1; k += 16) MLP_PREFETCH_LINE(A + (size_t)r * NSLOT + k);
#endif
}

/* Backward through one layer's weights for MLP_ROWS rows: G[in] = (G[out] W) * act'(A[in])
 * for the first nin input columns (a multiple of 16), where the (hidden) activation derivative
 * applies to the first n_act of them only. The sum runs over the live outputs (layer_t). */
static inline void layer_backward(const layer_t L, __global const float *P, __global float *G,
                                  __global const float *A, const int n_act, const int nin) {
    int k0 = 0;
#if MLP_COLS == 32
    for (; k0 + 32 <= nin; k0 += 32) {
        prefetch_act(A + L.in_off, k0 + 32, min(k0 + 64, n_act));
        float16 acc[MLP_ROWS * 2];
        for (int r = 0; r < 2 * MLP_ROWS; ++r) acc[r] = (float16)(0.0f);
        gemm_rows2(G + L.out_off, NSLOT, 1, P + L.w_off + k0, L.nin, L.kout1, acc);
        if (L.kout2 > 0)
            gemm_rows2(G + L.out_off + L.ko2, NSLOT, 1, P + L.w_off + L.ko2 * L.nin + k0, L.nin,
                       L.kout2, acc);
        for (int r = 0; r < MLP_ROWS; ++r)
            for (int c = 0; c < 2; ++c) {
                const size_t o = (size_t)r * NSLOT + L.in_off + k0 + 16 * c;
                float16 d = acc[2 * r + c];
                if (k0 + 16 * c < n_act) d = hidden_act_grad_mul(d, vload16(0, A + o));
                vstore16(d, 0, G + o);
            }
    }
#endif
    for (; k0 < nin; k0 += 16) {
        prefetch_act(A + L.in_off, k0 + 16, min(k0 + 32, n_act));
        float16 acc[MLP_ROWS];
        for (int r = 0; r < MLP_ROWS; ++r) acc[r] = (float16)(0.0f);
        gemm_rows1(G + L.out_off, NSLOT, 1, P + L.w_off + k0, L.nin, L.kout1, acc);
        if (L.kout2 > 0)
            gemm_rows1(G + L.out_off + L.ko2, NSLOT, 1, P + L.w_off + L.ko2 * L.nin + k0, L.nin,
                       L.kout2, acc);
        for (int r = 0; r < MLP_ROWS; ++r) {
            const size_t o = (size_t)r * NSLOT + L.in_off + k0;
            float16 d = acc[r];
            if (k0 < n_act) d = hidden_act_grad_mul(d, vload16(0, A + o));
            vstore16(d, 0, G + o);
        }
    }
}

/* Copy `dim` input columns of rows r0.. into a padded slot range (zeros beyond dim and n). */
static inline void load_input(const int n, const int r0, __global const float *src, const int dim,
                              const int dim_p, __global float *A, const int off) {
    for (int r = 0; r < MLP_ROWS; ++r) {
        const int row = r0 + r;
        for (int k = 0; k < dim_p; ++k)
            A[(size_t)r * NSLOT + off + k] =
                (row < n && k < dim) ? src[(size_t)row * dim + k] : 0.0f;
    }
}

/* Forward of tiles of MLP_ROWS samples: one work-item per tile (n_tiles = ceil(n / MLP_ROWS)).
 * x_enc [n, MLP_IN], d_enc [n, MLP_DIR_IN]; A [n_tiles*MLP_ROWS, NSLOT] receives every
 * activation (kept for the backward); sigma [n], rgb [n, 3]. */
/* The encoded positions of the tile at row r0 into A, then the trunk and the head: A's slots
 * up to SL_HD, sigma activated. */
static inline void trunk_forward(const int n, const int r0, __global const float *x_enc,
                                 __global const float *params_t, __global float *A) {
    load_input(n, r0, x_enc, MLP_IN, IN_P, A, SL_X);
#if MLP_SKIP >= 0
    load_input(n, r0, x_enc, MLP_IN, IN_P, A, SL_XS);
#endif
    for (int l = 0; l < MLP_DEPTH; ++l) layer_forward(layer_desc(l), params_t, A, HIDDEN_ACT);
    layer_forward(layer_desc(MLP_DEPTH), params_t, A, ACT_NONE);
    for (int r = 0; r < MLP_ROWS; ++r) {
        __global float *s = A + (size_t)r * NSLOT + SL_HD;
        *s = sigma_forward(*s);
    }
}

/* sigma [n] only (the trunk and the head; no colour layers, no direction): A_all is scratch,
 * and its rows no longer hold a forward for a backward. */
__kernel void mlp_density(const int n_max, __global const int *count,
                          __global const float *x_enc,
                          __global const float *params_t, __global float *A_all,
                          __global float *sigma_out) {
    const int n = live_rows(n_max, count);
    const int tile = get_global_id(0);
    const int r0 = tile * MLP_ROWS;
    if (r0 >= n) return;
    __global float *A = A_all + (size_t)r0 * NSLOT;
    trunk_forward(n, r0, x_enc, params_t, A);
    for (int r = 0; r < MLP_ROWS && r0 + r < n; ++r)
        sigma_out[r0 + r] = A[(size_t)r * NSLOT + SL_HD];
}

__kernel void mlp_forward(const int n_max, __global const int *count,
                          __global const float *x_enc, __global const float *d_enc,
                          __global const float *params_t, __global float *A_all,
                          __global float *sigma_out, __global float *rgb_out) {
    const int n = live_rows(n_max, count);
    const int tile = get_global_id(0);
    const int r0 = tile * MLP_ROWS;
    if (r0 >= n) return;
    __global float *A = A_all + (size_t)r0 * NSLOT;
    load_input(n, r0, d_enc, MLP_DIR_IN, DIN_P, A, SL_DV);
    trunk_forward(n, r0, x_enc, params_t, A);
    for (int l = MLP_DEPTH + 1; l < NLAYER - 1; ++l)
        layer_forward(layer_desc(l), params_t, A, HIDDEN_ACT);
    layer_forward(layer_desc(NLAYER - 1), params_t, A, ACT_SIGMOID);
    for (int r = 0; r < MLP_ROWS; ++r) {
        const int row = r0 + r;
        if (row >= n) break;
        __global const float *a = A + (size_t)r * NSLOT;
        sigma_out[row] = a[SL_HD];
        rgb_out[3 * row] = a[SL_RGB];
        rgb_out[3 * row + 1] = a[SL_RGB + 1];
        rgb_out[3 * row + 2] = a[SL_RGB + 2];
    }
}

/* Backward of tiles: dsigma [n], drgb [n, 3] (dL/d outputs) -> G [n_tiles*MLP_ROWS, NSLOT].
 * With want_input != 0 also dx_enc [n, MLP_IN] and dd_enc [n, MLP_DIR_IN] (else unused). */
__kernel void mlp_backward(const int n_max, __global const int *count,
                           __global const float *dsigma, __global const float *drgb,
                           __global const float *params, __global const float *A_all,
                           __global float *G_all, const int want_input,
                           __global float *dx_enc, __global float *dd_enc) {
    const int n = live_rows(n_max, count);
    const int tile = get_global_id(0);
    const int r0 = tile * MLP_ROWS;
    if (r0 >= n) return;
    __global const float *A = A_all + (size_t)r0 * NSLOT;
    __global float *G = G_all + (size_t)r0 * NSLOT;
    for (int r = 0; r < MLP_ROWS; ++r) {
        const int row = r0 + r;
        const int live = row < n;
        __global const float *a = A + (size_t)r * NSLOT;
        __global float *g = G + (size_t)r * NSLOT;
        for (int k = 0; k < HEAD_PAD; ++k) g[SL_HD + k] = 0.0f;
        for (int k = 0; k < RGB_P; ++k) g[SL_RGB + k] = 0.0f;
        if (!live) continue;
        g[SL_HD] = dsigma[row] * act_grad1(a[SL_HD], SIGMA_ACT);
        for (int c = 0; c < 3; ++c)
            g[SL_RGB + c] = drgb[3 * row + c] * sigmoid_grad_from_y(a[SL_RGB + c]);
    }
    for (int l = NLAYER - 1; l > MLP_DEPTH + 1; --l)   /* rgb, then colour layers c_CD-1..c_1 */
        layer_backward(layer_desc(l), params, G, A, MLP_COLOR_WIDTH, MLP_COLOR_WIDTH);
    /* the encoded direction's columns only when asked for */
    layer_backward(layer_desc(MLP_DEPTH + 1), params, G, A, 0,
                   want_input ? MLP_FEAT + DIN_P : MLP_FEAT);
    layer_backward(layer_desc(MLP_DEPTH), params, G, A, MW, MW);
    for (int l = MLP_DEPTH - 1; l >= 1; --l)
        layer_backward(layer_desc(l), params, G, A, MW, layer_desc(l).nin);
    if (!want_input) return;
    layer_backward(layer_desc(0), params, G, A, 0, IN_P);
    for (int r = 0; r < MLP_ROWS; ++r) {
        const int row = r0 + r;
        if (row >= n) break;
        __global const float *g = G + (size_t)r * NSLOT;
        for (int k = 0; k < MLP_IN; ++k) {
            float v = g[SL_X + k];
#if MLP_SKIP >= 0
            v += g[SL_XS + k];
#endif
            dx_enc[(size_t)row * MLP_IN + k] = v;
        }
        for (int k = 0; k < MLP_DIR_IN; ++k) dd_enc[(size_t)row * MLP_DIR_IN + k] = g[SL_DV + k];
    }
}

/* Work-items of one chunk in mlp_weight_grad: per layer (nout / DW_ROWS) x ceil(nin / DW_COLS). */
static inline int wgrad_items(const layer_t L) {
    return (L.nout / DW_ROWS) * ((L.nin + DW_COLS - 1) / DW_COLS);
}

static inline int wgrad_items_per_chunk(void) {
    int n = 0;
    for (int l = 0; l < NLAYER; ++l) n += wgrad_items(layer_desc(l));
    return n;
}

/* Partial weight and bias gradients of every layer over chunk p of the scratch rows:
 *   partial[p, w_off + j*nin + k] = sum_{s in chunk p} G[s, out_off + j] A[s, in_off + k],
 *   partial[p, b_off + j]         = sum_{s in chunk p} G[s, out_off + j]  (items with kb == 0,
 *                                   while the chunk's G rows are still in cache).
 * One launch for all layers (PoCL pays a launch and a queue drain per kernel): work-item
 * gid = p * wgrad_items_per_chunk() + e, chunk-major so that a chunk's rows of A and G are
 * read by all its layers while in cache; e runs over the layers in order, within a layer
 * e' = kb * njb + jb: DW_ROWS outputs j x DW_COLS (or a last 16) inputs k, njb = nout / DW_ROWS. */
__kernel void mlp_weight_grad(const int n_rows_max, __global const int *count,
                              __global const float *A,
                              __global const float *G, __global float *partial) {
    const int n_rows = live_tile_rows(n_rows_max, count, MLP_ROWS);
    const int ipc = wgrad_items_per_chunk();
    const int n_chunks = (n_rows_max + DW_CHUNK - 1) / DW_CHUNK;   /* chunks past the count: 0 */
    const int gid = get_global_id(0);
    if (gid >= ipc * n_chunks) return;
    const int p = gid / ipc;
    int e = gid % ipc, layer = 0;
    while (e >= wgrad_items(layer_desc(layer))) e -= wgrad_items(layer_desc(layer++));
    const layer_t L = layer_desc(layer);
    const int njb = L.nout / DW_ROWS;
    const int jb = e % njb, kb = e / njb;
    const int j0 = jb * DW_ROWS, k0 = kb * DW_COLS;
    /* a block of padding outputs only (head rows 1..15, rgb rows 3..15) writes its zeros */
    const int live = j0 < L.kout1 || (j0 + DW_ROWS > L.ko2 && j0 < L.ko2 + L.kout2);
    const int s0 = p * DW_CHUNK, ns = live ? clamp(n_rows - s0, 0, DW_CHUNK) : 0;
    __global const float *Lp = G + (size_t)s0 * NSLOT + L.out_off + j0;
    __global const float *Mp = A + (size_t)s0 * NSLOT + L.in_off + k0;
    __global float *out = partial + (size_t)p * n_params();
#if DW_COLS == 32
    if (k0 + 32 <= L.nin) {
        float16 acc[DW_ROWS * 2];
        for (int r = 0; r < 2 * DW_ROWS; ++r) acc[r] = (float16)(0.0f);
        gemm_dw2(Lp, 1, NSLOT, Mp, NSLOT, ns, acc);
        for (int r = 0; r < DW_ROWS; ++r)
            for (int c = 0; c < 2; ++c)
                vstore16(acc[2 * r + c], 0, out + L.w_off + (size_t)(j0 + r) * L.nin + k0 + 16 * c);
    } else
#endif
    {
        float16 acc[DW_ROWS];
        for (int r = 0; r < DW_ROWS; ++r) acc[r] = (float16)(0.0f);
        gemm_dw1(Lp, 1, NSLOT, Mp, NSLOT, ns, acc);
        for (int r = 0; r < DW_ROWS; ++r)
            vstore16(acc[r], 0, out + L.w_off + (size_t)(j0 + r) * L.nin + k0);
    }
    if (kb == 0) {
#if DW_ROWS == 8
        float8 b = (float8)(0.0f);   /* one vector add per row instead of 8 scalar ones */
        for (int s = 0; s < ns; ++s) b += vload8(0, Lp + (size_t)s * NSLOT);
        vstore8(b, 0, out + L.b_off + j0);
#else
        float b[DW_ROWS];
        for (int r = 0; r < DW_ROWS; ++r) b[r] = 0.0f;
        for (int s = 0; s < ns; ++s)
            for (int r = 0; r < DW_ROWS; ++r) b[r] += Lp[(size_t)s * NSLOT + r];
        for (int r = 0; r < DW_ROWS; ++r) out[L.b_off + j0 + r] = b[r];
#endif
    }
}
#endif  /* MLP_GPU */

/* grad[16i .. 16i+15] (+)= sum_p partial[p, 16i ..] in chunk order (deterministic). */
__kernel void mlp_reduce(const int n_chunks, __global const float *partial, __global float *grad,
                         const int accumulate) {
    const int i = get_global_id(0);
    const int np = n_params();
    if (16 * i >= np) return;
    float16 s = accumulate ? vload16(i, grad) : (float16)(0.0f);
    for (int p = 0; p < n_chunks; ++p) s += vload16(0, partial + (size_t)p * np + 16 * i);
    vstore16(s, i, grad);
}

/* params_t = params with every W_l transposed to [nin, nout] (biases copied). One item each. */
__kernel void mlp_transpose(__global const float *params, __global float *params_t) {
    const int i = get_global_id(0);
    if (i >= n_params()) return;
    for (int l = 0; l < NLAYER; ++l) {
        const layer_t L = layer_desc(l);
        if (i >= L.b_off + L.nout) continue;
        if (i >= L.b_off) {
            params_t[i] = params[i];
        } else {
            const int e = i - L.w_off, j = e / L.nin, k = e % L.nin;
            params_t[L.w_off + k * L.nout + j] = params[i];
        }
        return;
    }
}

/* The layout for the host: out[0..7] = NLAYER, NSLOT, n_params, MLP_ROWS, DW_CHUNK, SL_X,
 * SL_XS (-1 without skip), SL_HD; out[8..11] = SL_FEAT, SL_DV, SL_C, SL_RGB;
 * out[12..15] = MLP_COLS, DW_ROWS, DW_COLS (the tile), wgrad_items_per_chunk() (the host's
 * work split of mlp_weight_grad);
 * out[16..23] = MLP_GPU, then with MLP_GPU (mlp_gpu.h) GPU_WG, GPU_TM, GPU_TN, GPU_NC, GPU_BK,
 * the forward's and backward's local memory bytes per group, GPU_DW_BS; there out[3] is GPU_BM
 * (samples per work-group), out[4] 0 (the weight gradient's chunk is a kernel argument),
 * out[12..15] = GPU_NC, GPU_DW_BJ, GPU_DW_BKW, the weight-gradient tiles per chunk;
 * then from out[LAYOUT_HEAD] 6 ints per layer: in_off, nin, out_off, nout, w_off, b_off. */
#define LAYOUT_HEAD 24
__kernel void mlp_layout(__global int *out) {
    if (get_global_id(0) != 0) return;
    out[0] = NLAYER; out[1] = NSLOT; out[2] = n_params();
    out[5] = SL_X; out[6] = MLP_SKIP >= 0 ? SL_XS : -1; out[7] = SL_HD;
    out[8] = SL_FEAT; out[9] = SL_DV; out[10] = SL_C; out[11] = SL_RGB;
#if MLP_GPU
    out[3] = GPU_BM; out[4] = 0;
    out[12] = GPU_NC; out[13] = GPU_DW_BJ; out[14] = GPU_DW_BKW; out[15] = gpu_wgrad_tiles();
    out[16] = 1; out[17] = GPU_WG; out[18] = GPU_TM; out[19] = GPU_TN; out[20] = GPU_NC;
    out[21] = GPU_BK; out[22] = GPU_LOCAL_BYTES(GPU_TM, GPU_BK); out[23] = GPU_DW_BS;
#else
    out[3] = MLP_ROWS; out[4] = DW_CHUNK;
    out[12] = MLP_COLS; out[13] = DW_ROWS; out[14] = DW_COLS; out[15] = wgrad_items_per_chunk();
    for (int i = 16; i < LAYOUT_HEAD; ++i) out[i] = 0;
#endif
    for (int l = 0; l < NLAYER; ++l) {
        const layer_t L = layer_desc(l);
        __global int *o = out + LAYOUT_HEAD + 6 * l;
        o[0] = L.in_off; o[1] = L.nin; o[2] = L.out_off; o[3] = L.nout;
        o[4] = L.w_off; o[5] = L.b_off;
    }
}
