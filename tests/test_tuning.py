"""Tuning: defaults from capabilities, the CLRF_* overrides (read only by Tuning.from_env), and
Device.with_tuning sharing the device while changing only the tuning."""
from types import SimpleNamespace

import pytest

from clrf.runtime.tuning import Tuning


def caps(kind, cu=4, platform="OpenCL 3.0 PoCL 3.1", acq_rel=True):
    return SimpleNamespace(type=kind, compute_units=cu, platform_version=platform,
                           acq_rel=acq_rel)


def test_defaults_follow_capabilities():
    cpu = Tuning.for_device(caps("cpu", cu=6))
    assert (cpu.grad_slots, cpu.sample_record, cpu.prefetch) == (6, True, True)
    assert cpu.grad_locks == 4
    gpu = Tuning.for_device(caps("gpu", cu=80, platform="OpenCL 3.0 CUDA"))
    assert (gpu.grad_slots, gpu.sample_record, gpu.prefetch) == (0, False, False)
    assert gpu.grad_locks == 0
    other_cpu = Tuning.for_device(caps("cpu", platform="OpenCL 2.1 Intel"))
    assert other_cpu.prefetch is False and other_cpu.fast_math is False
    # OpenCL 1.2 atomics only (rusticl, Oclgrind): the float-atomic path
    old = Tuning.for_device(caps("cpu", platform="OpenCL 3.0 rusticl", acq_rel=False))
    assert (old.grad_slots, old.sample_record, old.grad_locks) == (0, False, 0)


def test_environment_overrides():
    env = {"CLRF_GRAD_SLOTS": "0", "CLRF_SAMPLE_RECORD": "0", "CLRF_PREFETCH": "0",
           "CLRF_PREFETCH_AHEAD": "4", "CLRF_BLOCK": "16", "CLRF_FAST_MATH": "",
           "CLRF_GRAD_LOCKS": "0"}
    t = Tuning.from_env(caps("cpu"), env)
    assert (t.grad_slots, t.sample_record, t.prefetch, t.grad_locks) == (0, False, False, 0)
    assert (t.prefetch_ahead, t.prefetch_links_ahead, t.block, t.fast_math) == (4, 8, 16, False)
    assert Tuning.from_env(caps("cpu"), {}) == Tuning.for_device(caps("cpu"))
    with pytest.raises(ValueError, match="CLRF_BLOCK"):
        Tuning.from_env(caps("cpu"), {"CLRF_BLOCK": "eight"})


def test_with_tuning_shares_the_device(device):
    gpu_path = device.with_tuning(grad_slots=0, sample_record=False)
    assert gpu_path.context is device.context and gpu_path.queue is device.queue
    assert gpu_path.tuning == device.tuning.replace(grad_slots=0, sample_record=False)
    assert device.tuning.grad_slots == Tuning.from_env(device.caps).grad_slots
