/* adam.h: one Adam update (Kingma & Ba, bias-corrected) of entry i from its gradient gi, for
 * the kernels that form gi themselves (cl/splat_train.cl, cl/splat_exposure.cl, and cl/optim.cl's
 * adam_update after its weight decay):
 *   m = b1 m + (1 - b1) g, v = b2 v + (1 - b2) g^2, p -= lr (m / bc1) / (sqrt(v / bc2) + eps).
 * Moments below FLT_MIN are stored as 0: a moment that decays geometrically (an entry the
 * batches stopped reaching) would otherwise turn subnormal, and x86 CPUs compute on subnormals
 * ~100x slower (9 % of lego_400's table moments were subnormal after 900 s, which tripled the
 * Adam kernel's time). Their contribution, below 1e-38 / eps, is nil. */
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
