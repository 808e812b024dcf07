/* optim_adam.cl: Adam update of a flat parameter buffer (Kingma & Ba, with bias correction).
 *
 *   m = b1 m + (1 - b1) g,  v = b2 v + (1 - b2) g^2,
 *   p -= lr (m / bc1) / (sqrt(v / bc2) + eps),  bc1 = 1 - b1^t, bc2 = 1 - b2^t (host, float64).
 * A zero gradient on a zero moment leaves p unchanged (0 / (0 + eps) = 0), which keeps the
 * MLP's zero padding at zero. Non-finite gradients are skipped (p, m, v unchanged) so one bad
 * sample cannot poison the moments.
 *
 * Layout: p, g, m, v are float [n]. One work-item per parameter (no loops: PoCL vectorises).
 */
__kernel void adam_step(const int n, __global float *p, __global const float *g,
                        __global float *m, __global float *v, const float lr, const float b1,
                        const float b2, const float eps, const float bc1, const float bc2) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float gi = g[i];
    if (!isfinite(gi)) return;
    const float mi = b1 * m[i] + (1.0f - b1) * gi;
    const float vi = b2 * v[i] + (1.0f - b2) * gi * gi;
    m[i] = mi;
    v[i] = vi;
    p[i] -= lr * (mi / bc1) / (sqrt(vi / bc2) + eps);
}
