/* mlp_net.h: the fused MLP's network, shared by its CPU tiles (mlp.cl) and its GPU tiling
 * (mlp_gpu.h): the shape defines and their checks, the padding and the scratch-row slots, the
 * one definition of every layer's slot and parameter offsets (layer_desc), and the activation
 * helpers. mlp.cl's header describes the network, the padding and the layouts.
 *
 * Defines read: MLP_WIDTH, MLP_DEPTH, MLP_SKIP, MLP_COLOR_WIDTH, MLP_COLOR_DEPTH, MLP_FEAT,
 * MLP_IN, MLP_DIR_IN, HIDDEN_ACT, SIGMA_ACT, SIGMA_EXP_MAX.
 */
#ifndef CLRF_MLP_NET_H
#define CLRF_MLP_NET_H

#include "common.h"
#define ACT_NONE 0
#define ACT_RELU 1
#define ACT_SOFTPLUS 2
#define ACT_SIGMOID 3
#define ACT_TRUNC_EXP 4     /* density only: exp(min(x, SIGMA_EXP_MAX)) (see below) */

#ifndef MLP_WIDTH
#define MLP_WIDTH 64        /* trunk width W; a multiple of 16 */
#endif
#ifndef MLP_DEPTH
#define MLP_DEPTH 4         /* trunk layers D >= 1 (NeRF: 8) */
#endif
#ifndef MLP_SKIP
#define MLP_SKIP -1         /* x re-enters at the input of layer MLP_SKIP+1; -1: none (NeRF: 4) */
#endif
#ifndef MLP_COLOR_WIDTH
#define MLP_COLOR_WIDTH 32  /* view-dependent colour layer width WC, multiple of 16 (NeRF: 128) */
#endif
#ifndef MLP_COLOR_DEPTH
#define MLP_COLOR_DEPTH 1   /* colour hidden layers CD >= 1 (NeRF: 1; the hash model: 2) */
#endif
#ifndef MLP_FEAT
#define MLP_FEAT MLP_WIDTH  /* feature outputs of the head, multiple of 16 (NeRF: W) */
#endif
#ifndef MLP_IN
#define MLP_IN 51           /* encoded position dims (NeRF: 63 = 3 + 6*10) */
#endif
#ifndef MLP_DIR_IN
#define MLP_DIR_IN 27       /* encoded direction dims (NeRF: 27 = 3 + 6*4) */
#endif
#ifndef HIDDEN_ACT
#define HIDDEN_ACT ACT_RELU /* trunk and colour layers: ACT_RELU or ACT_SOFTPLUS */
#endif
#ifndef SIGMA_ACT
#define SIGMA_ACT ACT_RELU  /* density: ACT_RELU (NeRF), ACT_SOFTPLUS (stable, never dead) or
                               ACT_TRUNC_EXP (the hash model's) */
#endif
/* ACT_TRUNC_EXP: sigma = exp(min(x, SIGMA_EXP_MAX)), so sigma <= e^15 = 3.3e6 never overflows
 * however large the pre-activation; its backward is dL/dx = dL/dsigma * sigma, i.e. the
 * derivative of exp at the clamped value, which does not vanish beyond the clamp (so a
 * saturated density can still come down). */
#ifndef SIGMA_EXP_MAX
#define SIGMA_EXP_MAX 15.0f
#endif

#if MLP_WIDTH % 16 != 0 || MLP_WIDTH < 16
#error "MLP_WIDTH must be a positive multiple of 16"
#endif
#if MLP_COLOR_WIDTH % 16 != 0 || MLP_COLOR_WIDTH < 16
#error "MLP_COLOR_WIDTH must be a positive multiple of 16"
#endif
#if MLP_DEPTH < 1
#error "MLP_DEPTH must be >= 1"
#endif
#if MLP_COLOR_DEPTH < 1
#error "MLP_COLOR_DEPTH must be >= 1"
#endif
#if MLP_FEAT % 16 != 0 || MLP_FEAT < 16
#error "MLP_FEAT must be a positive multiple of 16"
#endif
#if MLP_SKIP < -1 || MLP_SKIP >= MLP_DEPTH - 1
#error "MLP_SKIP must be -1 (none) or in 0..MLP_DEPTH-2 (it feeds layer MLP_SKIP+1)"
#endif
#if MLP_IN < 1 || MLP_DIR_IN < 1
#error "MLP_IN and MLP_DIR_IN must be >= 1"
#endif
#if HIDDEN_ACT != ACT_RELU && HIDDEN_ACT != ACT_SOFTPLUS
#error "HIDDEN_ACT must be ACT_RELU (1) or ACT_SOFTPLUS (2)"
#endif
#if SIGMA_ACT != ACT_RELU && SIGMA_ACT != ACT_SOFTPLUS && SIGMA_ACT != ACT_TRUNC_EXP
#error "SIGMA_ACT must be ACT_RELU (1), ACT_SOFTPLUS (2) or ACT_TRUNC_EXP (4)"
#endif

#define LPAD 16                                   /* padding unit: one float16 */
#define PADUP(n) ((((n) + LPAD - 1) / LPAD) * LPAD)
#define MW MLP_WIDTH
#define IN_P PADUP(MLP_IN)
#define DIN_P PADUP(MLP_DIR_IN)
#define HEAD_PAD LPAD                             /* sigma + 15 zero outputs before the feature */
#define RGB_P LPAD                                /* r, g, b + 13 zero outputs */
#define NLAYER (MLP_DEPTH + 2 + MLP_COLOR_DEPTH)

/* Slot offsets in a scratch row (see the header). */
#define SL_X 0
#define SL_H(l) (IN_P + (l) * MW + ((MLP_SKIP >= 0 && (l) > MLP_SKIP) ? IN_P : 0))
#define SL_XS (IN_P + (MLP_SKIP + 1) * MW)
#define SL_HD SL_H(MLP_DEPTH)
#define SL_FEAT (SL_HD + HEAD_PAD)
#define SL_DV (SL_FEAT + MLP_FEAT)
#define SL_C (SL_DV + DIN_P)
#define SL_RGB (SL_C + MLP_COLOR_DEPTH * MLP_COLOR_WIDTH)
#define NSLOT (SL_RGB + RGB_P)

typedef struct {
    int in_off, nin;    /* input slot range */
    int out_off, nout;  /* output slot range */
    int w_off, b_off;   /* parameter offsets */
    int kin;            /* live inputs: the forward's sum runs over inputs 0 .. kin-1 only */
    int kout1, ko2, kout2;  /* live outputs 0 .. kout1-1 and ko2 .. ko2+kout2-1: the backward's
                               sum skips the padding rows (their gradients are 0) */
} layer_t;

/* The layout of layer l: the one definition of slot and parameter offsets. */
inline layer_t layer_desc(const int l) {
    layer_t L = {0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
    int w_off = 0;
    for (int i = 0; i <= l; ++i) {
        L.ko2 = 0; L.kout2 = 0;
        if (i == 0) {
            L.in_off = SL_X; L.nin = IN_P; L.out_off = SL_H(0); L.nout = MW;
            L.kin = MLP_IN; L.kout1 = MW;
        } else if (i < MLP_DEPTH) {
            L.in_off = SL_H(i - 1);
            L.nin = MW + (i == MLP_SKIP + 1 ? IN_P : 0);
            L.out_off = SL_H(i); L.nout = MW;
            L.kin = MW + (i == MLP_SKIP + 1 ? MLP_IN : 0); L.kout1 = MW;
        } else if (i == MLP_DEPTH) {
            L.in_off = SL_H(MLP_DEPTH - 1); L.nin = MW; L.out_off = SL_HD;
            L.nout = HEAD_PAD + MLP_FEAT;
            L.kin = MW; L.kout1 = 1; L.ko2 = HEAD_PAD; L.kout2 = MLP_FEAT;  /* sigma, feature */
        } else if (i == MLP_DEPTH + 1) {
            L.in_off = SL_FEAT; L.nin = MLP_FEAT + DIN_P; L.out_off = SL_C;
            L.nout = MLP_COLOR_WIDTH;
            L.kin = MLP_FEAT + MLP_DIR_IN; L.kout1 = MLP_COLOR_WIDTH;
        } else if (i < NLAYER - 1) {          /* colour hidden layer c_j, j = i - D - 1 >= 1 */
            L.in_off = SL_C + (i - MLP_DEPTH - 2) * MLP_COLOR_WIDTH; L.nin = MLP_COLOR_WIDTH;
            L.out_off = L.in_off + MLP_COLOR_WIDTH; L.nout = MLP_COLOR_WIDTH;
            L.kin = MLP_COLOR_WIDTH; L.kout1 = MLP_COLOR_WIDTH;
        } else {
            L.in_off = SL_RGB - MLP_COLOR_WIDTH; L.nin = MLP_COLOR_WIDTH; L.out_off = SL_RGB;
            L.nout = RGB_P;
            L.kin = MLP_COLOR_WIDTH; L.kout1 = 3;
        }
        L.w_off = w_off;
        L.b_off = w_off + L.nout * L.nin;
        w_off = L.b_off + L.nout;
    }
    return L;
}

inline int n_params(void) {
    const layer_t L = layer_desc(NLAYER - 1);
    return L.b_off + L.nout;
}


/* The activation of a layer's outputs, for a float16 of them (CPU tiles) or one (GPU tiles). */
#define MLP_DEFINE_ACT_FORWARD(T)                                                            \
    inline T __attribute__((overloadable)) act_forward(const T x, const int act) {           \
        if (act == ACT_RELU) return fmax(x, (T)(0.0f));                                       \
        if (act == ACT_SOFTPLUS) return safe_softplus(x);                                     \
        if (act == ACT_SIGMOID) return safe_sigmoid(x);                                       \
        return x;                                                                             \
    }
MLP_DEFINE_ACT_FORWARD(float16)
MLP_DEFINE_ACT_FORWARD(float)

/* g * (d act / d x) for the hidden activation, the derivative a function of its output y.
 * Compile-time: a runtime switch that can reach the softplus library call made the compiler
 * keep the whole backward tile in memory (~30% of the backward pass on PoCL). */
inline float16 __attribute__((overloadable)) hidden_act_grad_mul(const float16 g, const float16 y) {
#if HIDDEN_ACT == ACT_RELU
    return as_float16(as_int16(g) & isgreater(y, (float16)(0.0f)));
#else
    return g * softplus_grad_from_y(y);
#endif
}

/* The same for one float (a scalar isgreater is 1, not the all-ones mask of a vector one). */
inline float __attribute__((overloadable)) hidden_act_grad_mul(const float g, const float y) {
#if HIDDEN_ACT == ACT_RELU
    return y > 0.0f ? g : 0.0f;
#else
    return g * softplus_grad_from_y(y);
#endif
}

/* The density of its pre-activation (SIGMA_ACT). */
inline float sigma_forward(const float x) {
#if SIGMA_ACT == ACT_RELU
    return fmax(x, 0.0f);
#elif SIGMA_ACT == ACT_TRUNC_EXP
    return exp(fmin(x, SIGMA_EXP_MAX));   /* NaN stays NaN, as with the other two */
#else
    return safe_softplus(x);
#endif
}

inline float act_grad1(const float y, const int act) {
    if (act == ACT_RELU) return relu_grad_from_y(y);
    if (act == ACT_SOFTPLUS) return softplus_grad_from_y(y);
    if (act == ACT_SIGMOID) return sigmoid_grad_from_y(y);
    if (act == ACT_TRUNC_EXP) return y;
    return 1.0f;
}

#endif  /* CLRF_MLP_NET_H */
