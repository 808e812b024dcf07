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
_fixed: dict = {}   # fix(): {"default": "P:D", "present": {name: "P:D"}, "slow": {name: bool}}


def choose(with_others: bool = True) -> dict:
    """This process's choice, to hand to others (fix): {"default": "P:D"} and, with
    ``with_others``, "present" (present()) and "slow" (is_slow of each)."""
    d = default_device()
    c = {"default": f"{d.platform_index}:{d.device_index}"}
    if with_others:
        c["present"] = present()
        c["slow"] = {n: is_slow(n) for n in c["present"]}
    return c


def fix(choice: dict) -> None:
    """Take the devices from ``choice`` (choose() of another process) instead of measuring:
    a test harness whose processes must agree on them (pytest-xdist's workers). Call it before
    anything of this module is asked."""
    _fixed.clear()
    _fixed.update(choice)
    for f in (present, is_slow, default_device, default_implementation):
        f.cache_clear()


@functools.lru_cache(maxsize=None)
def present() -> dict:
    """{implementation: "P:D"} for every working implementation here, simulators excepted."""
    if "present" in _fixed:
        return dict(_fixed["present"])
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
    if name in _fixed.get("slow", {}):
        return bool(_fixed["slow"][name])
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
    among equal probe figures the faster grid workload, clrf/runtime/workload.py; or the one
    fix() was given)."""
    if "default" in _fixed:
        return Device(_fixed["default"])
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
