/* adam.h: one Adam update (Kingma & Ba, bias-corrected) of entry i from its gradient gi, for
 * the kernels that form gi themselves (cl/splat_train.cl, cl/splat_exposure.cl); cl/optim.cl's
 * adam_update is the same update with weight decay and gradient clearing:
 *   m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2 (each stored as 0 below FLT_MIN: see
 *   cl/optim.cl), p -= lr (m / bc1) / (sqrt(v / bc2) + eps). */
#ifndef CLRF_ADAM_H
#define CLRF_ADAM_H

inline void adam_apply(const size_t i, const float gi, __global float *p, __global float *m,
                       __global float *v, const float lr, const float b1, const float b2,
                       const float eps, const float bc1, const float bc2) {
    float mi = b1 * m[i] + (1.0f - b1) * gi;
    float vi = b2 * v[i] + (1.0f - b2) * gi * gi;
    mi = fabs(mi) < FLT_MIN ? 0.0f : mi;
    vi = vi < FLT_MIN ? 0.0f : vi;
    m[i] = mi;
    v[i] = vi;
    p[i] -= lr * (mi / bc1) / (sqrt(vi / bc2) + eps);
}

#endif
