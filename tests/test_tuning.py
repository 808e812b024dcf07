"""Tuning: defaults from capabilities, the CLRF_* overrides (read only by Tuning.from_env), and
Device.with_tuning sharing the device while changing only the tuning."""
from types import SimpleNamespace

import pytest

from clrf.runtime.tuning import IMPLEMENTATIONS, Tuning, implementation


def caps(kind, cu=4, platform="OpenCL 3.0 PoCL 3.1", acq_rel=True,
         name="Portable Computing Language"):
    return SimpleNamespace(type=kind, compute_units=cu, platform_version=platform,
                           acq_rel=acq_rel, platform=name)


def test_defaults_follow_capabilities():
    cpu = Tuning.for_device(caps("cpu", cu=6))
    assert (cpu.grad_slots, cpu.sample_record, cpu.prefetch) == (6, True, True)
    assert cpu.grad_locks == 4
    gpu = Tuning.for_device(caps("gpu", cu=80, platform="OpenCL 3.0 CUDA", name="NVIDIA CUDA"))
    assert (gpu.grad_slots, gpu.sample_record, gpu.prefetch) == (0, False, False)
    assert gpu.grad_locks == 0
    assert cpu.mlp_prefetch is True and cpu.grid_local_size == 32
    other_cpu = Tuning.for_device(caps("cpu", platform="OpenCL 2.1 AMD-APP",
                                       name="AMD Accelerated Parallel Processing"))
    assert other_cpu.prefetch is False and other_cpu.mlp_prefetch is False
    assert other_cpu.fast_math is False and other_cpu.grid_local_size == 32


def test_implementation_entries():
    # Intel's CPU runtime: 8 rays per group, prefetch in the march but not in the MLP
    intel = Tuning.for_device(caps("cpu", platform="OpenCL 3.1 LINUX", name="Intel(R) OpenCL"))
    assert (intel.grid_local_size, intel.prefetch, intel.mlp_prefetch) == (8, True, False)
    assert intel.grad_slots == 4 and intel.grad_locks == 4   # the capability defaults stay
    # an Intel GPU driver is not the CPU runtime; entries apply to CPU devices only
    assert implementation("Intel(R) OpenCL HD Graphics") == "intel-gpu"
    assert implementation("Intel(R) OpenCL Graphics") == "intel-gpu"
    gpu = Tuning.for_device(caps("gpu", platform="OpenCL 3.0 NEO", name="Intel(R) OpenCL"))
    assert (gpu.grid_local_size, gpu.prefetch) == (64, False)   # GPU_GROUPS, not the entry's 8
    for name, impl in (("Portable Computing Language", "pocl"), ("Intel(R) OpenCL", "intel"),
                       ("rusticl", "rusticl"), ("Oclgrind", "oclgrind"), ("Clover", "clover"),
                       ("NVIDIA CUDA", "nvidia"), ("", "unknown")):
        assert implementation(name) == impl
    # every entry names real Tuning fields
    for entry in IMPLEMENTATIONS.values():
        Tuning().replace(**entry)


def test_gpus_get_groups_of_64():
    """Every GPU gets groups of 64 for the small-group kernels (tuning.GPU_GROUPS: a wave64,
    two warps or wave32s); CPU devices keep the defaults, whatever their name."""
    def amd(name, kind="gpu"):
        c = caps(kind, platform="OpenCL 2.1 AMD-APP", name="AMD Accelerated Parallel Processing")
        c.name = name
        return Tuning.for_device(c)
    gpus = [amd(n) for n in ("gfx90a:sramecc+:xnack-", "gfx942", "gfx908", "gfx1100", "gfx1030")]
    gpus += [Tuning.for_device(caps("gpu", name=n))
             for n in ("NVIDIA CUDA", "Intel(R) OpenCL Graphics", "rusticl")]
    for t in gpus:
        assert (t.grid_local_size, t.per_ray_local_size, t.encode_local_size) == (64, 64, 64)
        assert t.gpu_kernels and t.grad_slots == 0
    base = Tuning()
    for t in (amd("gfx90a", kind="cpu"), Tuning.for_device(caps("cpu"))):
        assert (t.grid_local_size, t.per_ray_local_size, t.encode_local_size) == (
            base.grid_local_size, base.per_ray_local_size, base.encode_local_size)


def test_intel_gpus_add_each_samples_gradients():
    """Intel GPUs build the grid backward without the per-cell merge (INTEL_GPU: the merged sums
    spill on Xe-LP); every other device keeps it, and CLRF_GRAD_MERGE switches it."""
    intel = Tuning.for_device(caps("gpu", platform="OpenCL 3.0 NEO",
                                   name="Intel(R) OpenCL Graphics"))
    assert intel.grad_merge is False and intel.grad_slots == 0
    for t in (Tuning.for_device(caps("gpu", name="NVIDIA CUDA")),
              Tuning.for_device(caps("gpu", name="AMD Accelerated Parallel Processing")),
              Tuning.for_device(caps("cpu", name="Intel(R) OpenCL")), Tuning.for_device(caps("cpu"))):
        assert t.grad_merge is True
    assert Tuning.from_env(caps("cpu"), {"CLRF_GRAD_MERGE": "0"}).grad_merge is False
    assert Tuning.from_env(caps("gpu", name="Intel(R) OpenCL Graphics"),
                           {"CLRF_GRAD_MERGE": "1"}).grad_merge is True


def test_environment_overrides():
    env = {"CLRF_GRAD_SLOTS": "0", "CLRF_SAMPLE_RECORD": "0", "CLRF_PREFETCH": "0",
           "CLRF_MLP_PREFETCH": "0",
           "CLRF_PREFETCH_AHEAD": "4", "CLRF_BLOCK": "16", "CLRF_FAST_MATH": "",
           "CLRF_GRAD_LOCKS": "0"}
    t = Tuning.from_env(caps("cpu"), env)
    assert (t.grad_slots, t.sample_record, t.prefetch, t.grad_locks) == (0, False, False, 0)
    assert t.mlp_prefetch is False
    assert (t.prefetch_ahead, t.prefetch_links_ahead, t.block, t.fast_math) == (4, 8, 16, False)
    assert Tuning.from_env(caps("cpu"), {}) == Tuning.for_device(caps("cpu"))
    with pytest.raises(ValueError, match="CLRF_BLOCK"):
        Tuning.from_env(caps("cpu"), {"CLRF_BLOCK": "eight"})


def test_with_tuning_shares_the_device(device):
    gpu_path = device.with_tuning(grad_slots=0, sample_record=False)
    assert gpu_path.context is device.context and gpu_path.queue is device.queue
    assert gpu_path.tuning == device.tuning.replace(grad_slots=0, sample_record=False)
    assert device.tuning.grad_slots == Tuning.from_env(device.caps).grad_slots
