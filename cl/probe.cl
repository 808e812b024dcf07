/* probe.cl: the smallest kernel that proves a device can compile and run OpenCL C
 * (clrf/device.py builds it on every candidate device; a[i] += 1). */
__kernel void clrf_probe(__global float *a) { a[get_global_id(0)] += 1.0f; }
