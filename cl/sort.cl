/* sort.cl: a stable LSD radix sort of uint keys for devices that run few, long work-items well
 * (CPUs): the n items are cut into nchunks contiguous chunks of `chunk` items, one work-item a
 * chunk, and each pass of RADIX_BITS key bits (from bit `shift`) is a stable counting sort:
 *   radix_count    hist[c][d] = items of chunk c whose digit is d (private counters)
 *   radix_offsets  one work-item: hist[c][d] = sum of hist[c'][d'] over (d', c') < (d, c)
 *                  in digit-major order (the exclusive scan; nchunks x RADIX values)
 *   radix_scatter  chunk c moves its items, in order, to hist[c][d]++ (keys and values)
 * Equal keys keep their input order within a chunk, chunks go in order, and so the sort is
 * stable; the first pass's values are the items' positions (first = 1, vals unread), so the
 * values end as the stable ascending order of the keys.
 * Twin: numpy's argsort(kind="stable") (tests/test_sort.py). Host: clrf/runtime/sort.py. */
#ifndef RADIX_BITS
#define RADIX_BITS 8
#endif
#define RADIX (1 << RADIX_BITS)

__kernel void radix_count(const int n, const int chunk, const int nchunks, const int shift,
                          __global const uint *keys, __global int *hist) {
    const int c = get_global_id(0);
    if (c >= nchunks) return;
    int h[RADIX];
    for (int d = 0; d < RADIX; ++d) h[d] = 0;
    const int lo = min(n, c * chunk), hi = min(n, lo + chunk);
    for (int i = lo; i < hi; ++i) h[(keys[i] >> shift) & (RADIX - 1)] += 1;
    __global int *out = hist + c * RADIX;
    for (int d = 0; d < RADIX; ++d) out[d] = h[d];
}

__kernel void radix_offsets(const int nchunks, __global int *hist) {
    if (get_global_id(0) != 0) return;
    int run = 0;
    for (int d = 0; d < RADIX; ++d)
        for (int c = 0; c < nchunks; ++c) {
            const int k = hist[c * RADIX + d];
            hist[c * RADIX + d] = run;
            run += k;
        }
}

__kernel void radix_scatter(const int n, const int chunk, const int nchunks, const int shift,
                            const int first, __global const uint *keys,
                            __global const int *vals, __global const int *hist,
                            __global uint *keys_out, __global int *vals_out) {
    const int c = get_global_id(0);
    if (c >= nchunks) return;
    int cur[RADIX];
    for (int d = 0; d < RADIX; ++d) cur[d] = hist[c * RADIX + d];
    const int lo = min(n, c * chunk), hi = min(n, lo + chunk);
    for (int i = lo; i < hi; ++i) {
        const uint k = keys[i];
        const int p = cur[(k >> shift) & (RADIX - 1)]++;
        keys_out[p] = k;
        vals_out[p] = first ? i : vals[i];
    }
}
