"""The OpenCL implementations present on this machine, one device each, for the tests.

An implementation is a driver family (PoCL, Intel's CPU runtime, Mesa's rusticl, Oclgrind,
a GPU vendor's driver), named from the platform. Two platforms of one family (pip's PoCL
beside the distribution's) count once: the one whose probe figure is higher. Oclgrind is
left out of ``present()``: it simulates every work-item and is run by its own test.
"""
from __future__ import annotations

import functools
import json
import os

from ..runtime.device import Device, list_devices
from ..runtime.device_probe import probe
from ..runtime.tuning import implementation

SIMULATORS = ("oclgrind",)
# What pin() resolved, as JSON: {"default": "P:D", "present": {name: "P:D"}, "slow": {name: bool}}
PINNED_VAR = "CLRF_TEST_DEVICES"


def _pinned() -> dict:
    v = os.environ.get(PINNED_VAR, "").strip()
    return json.loads(v) if v else {}


def pin(with_others: bool = True) -> dict:
    """Resolve the session's devices once and put them in the environment (PINNED_VAR), so that
    every process of a test run collects the same tests: pytest-xdist's workers inherit it from
    the controller. Each worker choosing for itself chose by workloads it measured while the
    other worker ran on the same cores, and where two implementations are within a few per cent
    (PoCL and Intel's CPU runtime on a Xeon) they chose differently, and xdist stopped ("Different
    tests were collected"). ``with_others``: also the other implementations and which are slow
    (not needed when only the session device is tested). Returns what is pinned."""
    p = _pinned()
    if "default" not in p:
        d = default_device()
        p["default"] = f"{d.platform_index}:{d.device_index}"
    if with_others and "present" not in p:
        p["present"] = present()
        p["slow"] = {n: is_slow(n) for n in p["present"]}
    os.environ[PINNED_VAR] = json.dumps(p)
    return p


@functools.lru_cache(maxsize=None)
def present() -> dict:
    """{implementation: "P:D"} for every working implementation here, simulators excepted."""
    if "present" in _pinned():
        return dict(_pinned()["present"])
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
    if name in _pinned().get("slow", {}):
        return bool(_pinned()["slow"][name])
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
    among equal probe figures the faster grid workload, clrf/runtime/workload.py; the pinned
    one when pin() has run in this process or the one that started it)."""
    if "default" in _pinned():
        return Device(_pinned()["default"])
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
