/* volrend.h: the volume-rendering core shared by the grid renderer (march.h, grid_render.cl)
 * and NeRF's compositing (composite.cl): one compositing step forward and one
 * remaining-radiance step backward. The callers own their loops (how samples are found and what
 * colour they carry); these steps are the math every one of them does per sample.
 *
 * Forward, per sample k with optical depth tau_k = sigma_k delta_k:
 *   w_k = T_k alpha(tau_k),  log T_{k+1} = log T_k - tau_k (Kahan-summed, so T stays accurate
 *   over thousands of samples).
 * Backward, with g = dL/drgb and total = g.rgb (+ T_end dL/dT_end where a loss on T exists):
 *   dL/dsigma_k = delta_k (T_{k+1} (g.c_k) - R_k),  R_k = total - sum_{j<=k} w_j (g.c_j),
 * the remaining radiance behind sample k (prefix Kahan-summed), so nothing is stored per sample.
 */
#ifndef CLRF_VOLREND_H
#define CLRF_VOLREND_H

#include "common.h"

/* Result of one forward march. */
typedef struct {
    float3 rgb;  /* foreground radiance, without background */
    float acc;   /* sum of weights */
    float depth; /* sum of weights times distance (grid: from the entry; NeRF: t) */
    float logT;  /* log transmittance at the end of the march */
} fwd_t;

/* One compositing step: the weight T alpha(tau) of a sample with optical depth tau seen
 * through transmittance T = exp(logT->s); advances logT past it and sets *Tnext = exp(logT). */
CLRF_INLINE float vr_step(ksum_t *logT, const float T, const float tau, float *Tnext) {
    const float w = T * alpha_of_tau(tau);
    ksum_add(logT, -tau);
    *Tnext = exp(logT->s);
    return w;
}

/* One remaining-radiance backward step for a sample of weight w, transmittance behind it
 * Tnext, segment length delta and gc = g.c (its colour dotted with dL/drgb): adds w gc to
 * the prefix and returns dL/dsigma = delta (Tnext gc - (total - prefix)). */
CLRF_INLINE float vr_dsigma(ksum_t *prefix, const float total, const float w, const float Tnext,
                            const float gc, const float delta) {
    ksum_add(prefix, w * gc);
    return delta * (Tnext * gc - (total - prefix->s));
}

#endif /* CLRF_VOLREND_H */
