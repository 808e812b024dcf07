"""The OpenCL implementations present on this machine, one device each, for the tests.

An implementation is a driver family (PoCL, Intel's CPU runtime, Mesa's rusticl, Oclgrind,
a GPU vendor's driver), named from the platform. Two platforms of one family (pip's PoCL
beside the distribution's) count once: the one whose probe figure is higher. Oclgrind is
left out of ``present()``: it simulates every work-item and is run by its own test.
"""
from __future__ import annotations

import functools

from ..runtime.device import Device, list_devices
from ..runtime.device_probe import probe
from ..runtime.tuning import implementation

SIMULATORS = ("oclgrind",)


@functools.lru_cache(maxsize=None)
def present() -> dict:
    """{implementation: "P:D"} for every working implementation here, simulators excepted."""
    best = {}
    for pi, di, d in list_devices():
        name = implementation(d.platform.name)
        if name in SIMULATORS:
            continue
        pr = probe(d)
        if pr is None or not pr.ok:
            continue
        if name not in best or pr.gflops > best[name][1]:
            best[name] = (f"{pi}:{di}", pr.gflops)
    return {k: v[0] for k, v in best.items()}


@functools.lru_cache(maxsize=None)
def is_slow(name: str) -> bool:
    """Whether implementation ``name`` is a slow driver for this machine (clrf.runtime.device_probe
    slow_reasons: under a twelfth of the CPU's estimated peak, a generic target, or a sibling
    driver three times faster), e.g. rusticl's llvmpipe software device."""
    from ..runtime.device_probe import cpu_flags, slow_reasons
    from ..runtime.device import _candidate
    devs = {f"{pi}:{di}": (pi, di, d) for pi, di, d in list_devices()}
    cands = [_candidate(*v, probe(v[2])) for v in devs.values()]
    spec = present()[name]
    me = next(c for c in cands if c.spec == spec)
    return bool(slow_reasons(me, cands, cpu_flags()))


@functools.lru_cache(maxsize=None)
def default_device() -> Device:
    """The session's device: what ``clrf train`` picks for the grid (CLRF_DEVICE honoured;
    among equal probe figures the faster grid workload, clrf/runtime/workload.py)."""
    from ..grid.workload import WORKLOAD
    from ..runtime.workload import device_for
    return device_for(WORKLOAD)


@functools.lru_cache(maxsize=None)
def default_implementation() -> str:
    return implementation(default_device().cl_device.platform.name)


def others(spec: str = "all") -> list:
    """Implementations present other than the session device's, narrowed by ``spec``: "all",
    "default" (none) or a comma list of names."""
    spec = (spec or "all").strip().lower()
    if spec == "default":
        return []
    names = [n for n in sorted(present()) if n != default_implementation()]
    if spec != "all":
        wanted = {s.strip() for s in spec.split(",") if s.strip()}
        names = [n for n in names if n in wanted]
    return names


@functools.lru_cache(maxsize=None)
def device_of(name: str) -> Device:
    """A Device of implementation ``name`` (one per process)."""
    return Device(present()[name])
