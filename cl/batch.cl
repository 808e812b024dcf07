/* batch.cl: draw a random batch of training rays on the device.
 *
 * Ray j = floor(h * n_src / 2^32) with h = pcg_hash(seed ^ pcg_hash(i)) for batch slot i, so a
 * batch depends only on (seed, i): reproducible across devices and runs, drawn with
 * replacement. Sources and outputs are float [n, 3] (origins, dirs, colours).
 * Mirrored by reference.batch_indices.
 */

/* PCG-style 32-bit integer hash (O'Neill's RXS-M-XS output on one LCG step). */
inline uint pcg_hash(uint x) {
    uint state = x * 747796405u + 2891336453u;
    uint word = ((state >> ((state >> 28u) + 4u)) ^ state) * 277803737u;
    return (word >> 22u) ^ word;
}

__kernel void gather_batch(const int n, const uint seed, const uint n_src,
                           __global const float *src_o, __global const float *src_d,
                           __global const float *src_c, __global float *out_o,
                           __global float *out_d, __global float *out_c,
                           __global int *out_idx) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const uint h = pcg_hash(seed ^ pcg_hash((uint)i));
    const uint j = (uint)(((ulong)h * (ulong)n_src) >> 32);
    for (int c = 0; c < 3; ++c) {
        out_o[3 * i + c] = src_o[3 * (size_t)j + c];
        out_d[3 * i + c] = src_d[3 * (size_t)j + c];
        out_c[3 * i + c] = src_c[3 * (size_t)j + c];
    }
    out_idx[i] = (int)j;
}

/* recomposite: a batch's colours (gathered by gather_batch, indices idx) moved from the
 * background they were composited on to another one, delta = new - old:
 *   c += (1 - alpha[idx]) delta   (c = rgb alpha + old (1 - alpha) of an RGBA capture).
 * Mirrored by reference.recomposite. */
__kernel void recomposite(const int n, __global const int *idx, __global const float *alpha,
                          const float4 delta, __global float *colours) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const float clear = 1.0f - alpha[idx[i]];
    colours[3 * i] += clear * delta.x;
    colours[3 * i + 1] += clear * delta.y;
    colours[3 * i + 2] += clear * delta.z;
}
