"""Device choice per model kind by a timed run of its kernels (clrf/runtime/workload.py, the
runs in clrf/grid/workload.py and clrf/nerf/workload.py)."""
import dataclasses

import pytest

import clrf
from clrf.runtime import workload
from clrf import registry

WORKLOADS = {k.name: k.workload for k in registry.kinds() if k.workload is not None}


@pytest.fixture
def own_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    return tmp_path


def test_pick_keeps_the_probe_order_among_equals():
    assert workload.pick([100.0, 95.0]) == 0          # within 10 %: the first by probe
    assert workload.pick([100.0, 120.0]) == 1         # clearly faster
    assert workload.pick([0.0, 5.0, 5.2]) == 1


@pytest.mark.parametrize("kind", sorted(WORKLOADS))
def test_workloads_run_and_are_cached(device, own_cache, kind):
    work = WORKLOADS[kind]
    r = workload.rate(device, work)
    assert r > 0
    cached = dataclasses.replace(work, rate=lambda d: pytest.fail("not cached"))
    assert workload.rate(device, cached) == r
    assert workload.rate(device, cached, measure=False) == r


def test_a_failing_workload_scores_zero(device, own_cache):
    def broken(d):
        raise RuntimeError("driver fault")
    work = dataclasses.replace(WORKLOADS["grid"], rate=broken)
    assert workload.rate(device, work, refresh=True) == 0.0


def test_a_named_device_is_used_as_named(device, own_cache):
    spec = f"{device.platform_index}:{device.device_index}"
    dev = workload.device_for(WORKLOADS["grid"], spec)
    assert (dev.platform_index, dev.device_index) == (device.platform_index, device.device_index)
    assert not getattr(dev, "choice", None)


def test_the_fastest_contender_wins(device, own_cache, monkeypatch):
    """Two contenders (the same device twice, as far as the ranking knows): the one whose
    workload is clearly faster is chosen and the reason says so."""
    from clrf.runtime import device as devmod
    real = devmod.choose_device

    def two(spec=None, refresh=False):
        c = real(spec, refresh)
        return devmod.Choice(c.platform_index, c.device_index, c.cl_device, c.candidate,
                             c.reason, c.candidates, (c.candidate, c.candidate))
    monkeypatch.setattr(devmod, "choose_device", two)
    figures = iter([1000.0, 5000.0])
    monkeypatch.setattr(workload, "rate", lambda d, work, measure=True: next(figures))
    dev = workload.device_for(WORKLOADS["grid"], "auto")
    assert "fastest grid workload" in dev.choice and "5,000" in dev.choice
