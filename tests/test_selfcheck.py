"""The gradient self-check (clrf/grid/selfcheck.py): it passes on the test device's gradient paths,
it catches a backward that computes wrong gradients, training then refuses with the driver
named, and such a device is never the default again."""
import numpy as np
import pytest

import clrf
from clrf.grid import selfcheck
from clrf.runtime import selfcheck as verdicts
from clrf.runtime.device import DeviceError, choose_device
from clrf.runtime.tuning import Tuning, slots_order_memory


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    """An empty verdict cache, and checks run in this process, where the tests' fakes of a
    broken driver (monkeypatched kernels' wrappers) act; tests/test_selfcheck_isolation.py
    tests the child process."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    monkeypatch.setattr(verdicts, "ISOLATE", False)
    return tmp_path


def test_both_gradient_paths_pass(device, device_gpu_path, own_cache):
    for dev in (device, device_gpu_path):
        res = selfcheck.run_check(dev)
        assert res.ok, res.detail
    assert selfcheck.run_check(device_gpu_path).path == "atomics"


def _zero_backward(monkeypatch, factor):
    """render_rays_backward that returns its gradients scaled by ``factor`` (a broken driver)."""
    import clrf.grid.render as gr
    real = gr.render_rays_backward

    def broken(*a, **k):
        out = real(*a, **k)
        return {n: v * factor for n, v in out.items()}
    monkeypatch.setattr(gr, "render_rays_backward", broken)


@pytest.mark.parametrize("factor", [0.0, 0.9])
def test_wrong_gradients_are_caught(device, own_cache, monkeypatch, factor):
    """Zero gradients (what rusticl's block-locked path gave) and gradients 10 % off both fail
    the closed form, and the reason says which sum differs."""
    _zero_backward(monkeypatch, factor)
    res = selfcheck.run_check(device.with_tuning(grad_slots=0, sample_record=False))
    assert not res.ok
    assert "closed form" in res.detail


def test_training_refuses_a_device_with_wrong_gradients(device, own_cache, monkeypatch):
    _zero_backward(monkeypatch, 0.0)
    dev = device.with_tuning()
    with pytest.raises(DeviceError) as e:
        selfcheck.ensure_trusted(dev)
    msg = str(e.value)
    assert dev.caps.driver_version in msg and "gradient self-check" in msg and "CLRF_DEVICE" in msg
    # the cached verdict keeps it from being the default: choose_device skips it
    assert selfcheck.known_wrong(dev.cl_device) is not None
    if len(clrf.runtime.device.list_devices()) == 1:
        with pytest.raises(DeviceError):
            choose_device("auto")


def test_a_failing_path_falls_back_to_atomics(device, own_cache, monkeypatch):
    """Only the slot/lock path is broken: training goes on with the float-atomic path."""
    import clrf.grid.render as gr
    real = gr.render_rays_backward

    def broken_on_slots(grid, *a, **k):
        out = real(grid, *a, **k)
        if grid.device.tuning.grad_slots > 0:
            out = {n: v * 0 for n, v in out.items()}
        return out
    monkeypatch.setattr(gr, "render_rays_backward", broken_on_slots)
    if not slots_order_memory(device.caps):
        pytest.skip(f"{device.caps.name} refuses gradient slots (no acquire/release atomics)")
    dev = device.with_tuning(grad_slots=2, sample_record=True, grad_locks=4)
    said = []
    res = selfcheck.ensure_trusted(dev, said.append)
    assert res.ok and res.path == "atomics" and dev.tuning.grad_slots == 0
    assert "slots+locks" in said[0] and "float-atomic" in said[0]


def test_check_is_cached(device, own_cache, monkeypatch):
    first = selfcheck.gradient_check(device)
    monkeypatch.setattr(selfcheck, "run_check", lambda d: pytest.fail("not cached"))
    assert selfcheck.gradient_check(device) == first


class _Caps:
    type = "cpu"
    compute_units = 4
    platform_version = "OpenCL 3.0 PoCL 3.1"

    def __init__(self, acq_rel):
        self.acq_rel = acq_rel


def test_slots_only_with_acquire_release_atomics():
    """OpenCL 1.2 atomics order no plain memory between work-groups: without the OpenCL C 3.0
    acquire/release features a CPU device takes the float-atomic path."""
    t = Tuning.for_device(_Caps(acq_rel=False))
    assert t.grad_slots == 0 and t.grad_locks == 0 and not t.sample_record
    t = Tuning.for_device(_Caps(acq_rel=True))
    assert t.grad_slots == 4 and t.grad_locks > 0 and t.sample_record
