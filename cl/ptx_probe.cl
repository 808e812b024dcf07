/* ptx_probe.cl: whether float atomic adds can go through inline PTX (NVIDIA's OpenCL, which has
 * no float atomics): 2^16 work-items add 0.5 into 8 floats with red.global.add.f32, the
 * reduction CUDA's atomicAdd compiles to. The host (clrf/runtime/programs.py ptx_atomics)
 * builds this only on NVIDIA devices and checks every float came out n / 16 exactly; then
 * atomic_add_f (common.h) uses the same instruction (CLRF_PTX_ATOMICS). */
__kernel void ptx_probe(__global float *out, const int n) {
    const int i = get_global_id(0);
    if (i >= n) return;
    volatile __global float *p = out + (i & 7);
    asm volatile("red.global.add.f32 [%0], %1;" : : "l"((ulong)p), "f"(0.5f) : "memory");
}
