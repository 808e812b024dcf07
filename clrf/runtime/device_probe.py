"""Device choice by measurement: a one-time probe of every OpenCL device, cached on disk.

The probe (``cl/probe.cl``) builds and runs a one-line kernel, then measures fp32 throughput with
8 independent float8 FMA chains per work-item: the iteration count is calibrated so that one run
takes 20-50 ms, and the figure is the best of 3 such runs, in GFLOP/s. On a CPU device a run's
time is the smaller of its wall time and its process CPU time over the compute units, so other
load on the host at probe time does not lower the (cached) figure. Cold, it costs the build
plus about 0.2 s per device; the result is cached in ``$XDG_CACHE_HOME/clrf/devices.json``
(``~/.cache/clrf`` when unset) keyed by host, platform name and version, device name and driver
version, so later processes read it for free. A change to ``probe.cl`` or to this module's
method (``PROBE_METHOD``) invalidates every entry.

Ranking rule (``rank``): usable devices by measured GFLOP/s, highest first, whatever their type:
a GPU comes first only when it measures faster than the CPUs, because the probe is what the
kernels will see and a slow integrated GPU or an emulating driver exists. Figures within
``TIE`` (10%) of the best count as equal (the spread of the probe on a shared host) and among
equals the first in ICD order wins, so the choice does not flip on noise.

A slow driver is flagged (``slow_reasons``) when the device is a PoCL CPU device compiling for a
generic target (its name carries no LLVM CPU: ``pthread-AMD EPYC`` rather than
``pthread-haswell-AMD EPYC``), when it measures under ``SLOW_VS_PEAK`` of the CPU's estimated
peak, or when another driver on the same CPU measures ``SLOW_VS_SIBLING`` times faster.
"""
from __future__ import annotations

import functools
import hashlib
import json
import math
import os
import re
import socket
import sys
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pyopencl as cl

from .jsonfile import write_dict

PROBE_METHOD = 3            # bump when the measurement changes meaning (invalidates the cache)
PROBE_CHAINS = 8            # independent FMA chains per work-item (cl/probe.cl)
PROBE_WIDTH = 8             # float8 lanes per chain (cl/probe.cl)
PROBE_MIN_S = 0.020         # a calibrated run lasts at least this long ...
PROBE_TARGET_S = 0.030      # ... aiming at this
PROBE_MAX_ITERS = 1 << 24   # cap on the chain length (int32 kernel argument, slow devices)
PROBE_REPEATS = 3           # best of this many calibrated runs
# Lane l of every chain iterates x <- m_l x + a_l, which converges to a_l / (1 - m_l); the
# m_l and a_l differ per lane, the starts per chain and per work-item (cl/probe.cl), all exact
# in float32 and all read from a buffer.
PROBE_M = 0.999 - 0.0001 * np.arange(8)             # m_l, lanes 0..7
PROBE_ADD = 1e-3 * (1.0 + 0.125 * np.arange(8))     # a_l
PROBE_X0, PROBE_DX = 0.5, 0.25      # chain c starts at x0 + c dx ...
PROBE_DI = 1.0 / 64                 # ... plus (i & 63) / 64 for work-item i
# float32 rounding of each step (~6e-8 relative) is damped by m per step, so the chains carry at
# most ~6e-8 / (1 - m) = 6e-5 relative error; 1e-3 only rejects a driver that computes wrongly.
PROBE_RTOL = 1e-3
TIE = 0.10                  # figures within 10% of the best are equal; ICD order decides
SLOW_VS_SIBLING = 3.0       # another driver on the same CPU this many times faster: flag
SLOW_VS_PEAK = 1.0 / 12     # under this fraction of the estimated CPU peak: flag
SIMULATOR_GFLOPS = 1e-3     # the figure a simulator gets: ranks below any real device
OVER_PEAK = 1.5             # a figure above this multiple of the physical peak is impossible
#                             (turbo clocks over the reported base clock stay well under it)
INSTALL_HINT = ("install the distribution's PoCL (Debian/Ubuntu: "
                "`apt-get install pocl-opencl-icd`)")


@dataclass(frozen=True)
class Probe:
    """What the probe found on one device."""

    error: str | None       # why the device cannot build or run kernels; None when it works
    gflops: float = 0.0     # fp32 FMA throughput of clrf_probe_fma, GFLOP/s (best of 3)
    seconds: float = 0.0    # wall time the probe took (build included)
    when: str = ""          # UTC time of the measurement, ISO 8601
    cached: bool = False    # read from the cache file rather than measured by this process

    @property
    def ok(self) -> bool:
        return self.error is None


@dataclass(frozen=True)
class Candidate:
    """One OpenCL device as the ranking sees it (tests build these with fake probes)."""

    platform_index: int
    device_index: int
    type: str               # "cpu", "gpu" or "accelerator"
    name: str               # device name, e.g. "pthread-haswell-AMD EPYC"
    platform: str           # platform name, e.g. "Portable Computing Language"
    platform_version: str   # names the driver, e.g. "OpenCL 3.0 PoCL 3.1+debian ..."
    vendor: str             # device vendor, e.g. "AuthenticAMD"
    compute_units: int
    clock_mhz: int          # CL_DEVICE_MAX_CLOCK_FREQUENCY
    probe: Probe

    @property
    def spec(self) -> str:
        return f"{self.platform_index}:{self.device_index}"

    def short(self) -> str:
        """``1:0 'pthread-AMD EPYC' (PoCL 3.0-rc2)``: index, name and driver."""
        m = re.search(r"PoCL \S+", self.platform_version)
        drv = m.group(0) if m else self.platform_version.split("  ")[0]
        return f"{self.spec} '{self.name}' ({drv})"


# ---- the measurement ---------------------------------------------------------------------------

def _source_path() -> Path:
    from .programs import cl_dir
    return cl_dir() / "probe.cl"


@functools.lru_cache(maxsize=None)
def probe_version() -> str:
    """Hash of ``probe.cl`` and ``PROBE_METHOD``: cache entries with another value are stale."""
    h = hashlib.sha256(_source_path().read_bytes())
    h.update(str(PROBE_METHOD).encode())
    return h.hexdigest()[:16]


def _error_text(e: Exception) -> str:
    lines = [m.strip() for m in str(e).splitlines() if m.strip()]
    errors = [m for m in lines if m.lower().startswith("error")]
    return (errors[0] if errors else " ".join(lines)[-200:]) or type(e).__name__


def probe_coefficients() -> np.ndarray:
    """The float32 buffer clrf_probe_fma reads: m_l [8], a_l [8], chain starts [8], the
    per-work-item step (cl/probe.cl)."""
    starts = PROBE_X0 + PROBE_DX * np.arange(PROBE_CHAINS)
    return np.concatenate([PROBE_M, PROBE_ADD, starts, [PROBE_DI]]).astype(np.float32)


def fma_reference(iters: int, n: int = 1) -> np.ndarray:
    """float64 values of ``out[0..n-1]`` of clrf_probe_fma after ``iters`` steps (closed form,
    see probe.cl), from the float32 coefficients the kernel reads."""
    c = probe_coefficients().astype(np.float64)
    m, a, starts, di = c[:8], c[8:16], c[16:24], c[24]
    p = a / (1.0 - m)
    base = np.float32(di) * (np.arange(n) & 63).astype(np.float32)          # float32 as in C
    x0 = (starts[None, :].astype(np.float32) + base[:, None]).astype(np.float64)   # [n, c]
    mk = m ** iters
    return np.sum(p[None, None, :] + (x0[:, :, None] - p[None, None, :]) * mk[None, None, :],
                  axis=(1, 2))


PROBE_TIMEOUT_S = 300       # a probe child that runs longer is taken as hung


def locate(dev: "cl.Device") -> tuple:
    """``(platform index, device index)`` of ``dev`` in ICD order, as ``clrf devices`` lists."""
    for pi, p in enumerate(cl.get_platforms()):
        if p.int_ptr != dev.platform.int_ptr:
            continue
        for di, d in enumerate(p.get_devices()):
            if d.int_ptr == dev.int_ptr:
                return pi, di
    raise LookupError(f"device {dev.name!r} is not in the platform listing")


def measure(dev: "cl.Device") -> Probe:
    """Measure ``dev`` now (no cache) in a child process (clrf/runtime/isolate.py): a driver
    that crashes while building or running the probe gives a Probe whose error says so, and
    this process goes on. Devices the child cannot find are measured here."""
    from .isolate import run_child
    t_start = time.perf_counter()
    when = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    try:
        pi, di = locate(dev)
    except (LookupError, cl.Error):
        return measure_here(dev)
    out = run_child({"task": "probe", "platform": pi, "device": di, "name": dev.name},
                    PROBE_TIMEOUT_S)
    seconds = time.perf_counter() - t_start
    if out.crash:
        return Probe(f"the driver crashed while building or running the probe kernel "
                     f"({out.crash})", seconds=seconds, when=when)
    r = out.result
    if r is None or r.get("name") != dev.name:
        # no answer (the child could not start: a clrf problem, not the driver's), or the
        # child's listing differs from ours: measure in this process
        return measure_here(dev)
    return Probe(r["error"], float(r["gflops"]), seconds, when)


def child_probe(request: dict) -> dict:
    """The probe child's work (clrf/runtime/child.py)."""
    dev = cl.get_platforms()[request["platform"]].get_devices()[request["device"]]
    if dev.name != request["name"]:
        return {"name": dev.name}
    pr = measure_here(dev)
    return {"name": dev.name, "error": pr.error, "gflops": pr.gflops}


def measure_here(dev: "cl.Device") -> Probe:
    """Build and run the probe kernels on ``dev`` now, in this process (no cache); see the
    module doc."""
    t_start = time.perf_counter()
    when = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    try:
        ctx = cl.Context([dev])
        q = cl.CommandQueue(ctx)
        with warnings.catch_warnings():     # PoCL's build log is not the probe's business
            warnings.simplefilter("ignore")
            prg = cl.Program(ctx, _source_path().read_text()).build(
                options=[f"-DPROBE_CHAINS={PROBE_CHAINS}", f"-DPROBE_WIDTH={PROBE_WIDTH}"])
        a = np.zeros(4, np.float32)
        buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
        prg.clrf_probe(q, (4,), None, buf)
        cl.enqueue_copy(q, a, buf)
        q.finish()
        if not np.all(a == 1.0):
            return Probe("probe kernel gave wrong results", 0.0, time.perf_counter() - t_start, when)
        if is_simulator(dev):
            return Probe(None, SIMULATOR_GFLOPS, time.perf_counter() - t_start, when)
        gflops, err = _fma_gflops(ctx, q, prg, dev)
    except Exception as e:  # noqa: BLE001 - any driver failure disqualifies the device
        return Probe(_error_text(e), seconds=time.perf_counter() - t_start, when=when)
    return Probe(err, gflops if err is None else 0.0, time.perf_counter() - t_start, when)


def is_simulator(dev: "cl.Device") -> bool:
    """A device that simulates every work-item (Oclgrind): it runs the kernels to check them,
    never to be fast, so it gets no FMA figure. (Oclgrind 21.10 with --uninitialized also
    crashes on any kernel that adds two elements of one vector, e.g. ``float4 c = vload4(0, a);
    o[i] = c.s0 + c.s1;``, which the FMA probe does.)"""
    return "oclgrind" in dev.platform.name.lower()


def run_seconds(wall: float, cpu: float, compute_units: int, gpu: bool) -> float:
    """The seconds a probe run counts. A CPU device runs in this process's threads: on a busy
    host they wait for a core, which wall time counts and process CPU time does not, so the
    CPU time over the compute units is what the device does with its cores to itself (a cached
    figure must not depend on what else ran at probe time); never more than the wall time (a
    spinning host thread adds CPU time). GPUs: wall time."""
    if gpu:
        return wall
    return min(wall, max(cpu / max(1, compute_units), 1e-9))


def _fma_gflops(ctx, q, prg, dev) -> tuple:
    """(GFLOP/s, None) from calibrated runs of clrf_probe_fma, or (0, reason)."""
    gpu = bool(dev.type & (cl.device_type.GPU | cl.device_type.ACCELERATOR))
    n = int(dev.max_compute_units) * (2048 if gpu else 64)   # GPUs need many work-items in flight
    mf = cl.mem_flags
    out_buf = cl.Buffer(ctx, mf.WRITE_ONLY, 4 * n)
    coef = cl.Buffer(ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=probe_coefficients())
    trip = np.zeros(1, np.int32)
    trip_buf = cl.Buffer(ctx, mf.READ_ONLY, 4)
    k = prg.clrf_probe_fma
    ncu = max(1, int(dev.max_compute_units))

    def run(iters):
        trip[0] = iters
        cl.enqueue_copy(q, trip_buf, trip)
        q.finish()
        t0, c0 = time.perf_counter(), time.process_time()
        k(q, (n,), None, trip_buf, coef, out_buf)
        q.finish()
        return run_seconds(time.perf_counter() - t0, time.process_time() - c0, ncu, gpu)

    run(1)                                          # first launch carries the JIT
    iters = 64
    t = run(iters)
    while t < PROBE_MIN_S and iters < PROBE_MAX_ITERS:
        grow = PROBE_TARGET_S / max(t, 1e-6)
        iters = int(min(PROBE_MAX_ITERS, iters * min(16.0, max(2.0, grow))))
        t = run(iters)
    best = min([t] + [run(iters) for _ in range(PROBE_REPEATS - 1)])
    out = np.empty(n, np.float32)
    cl.enqueue_copy(q, out, out_buf)
    q.finish()
    if not np.allclose(out, fma_reference(iters, n), rtol=PROBE_RTOL, atol=0):
        return 0.0, "FMA probe kernel gave wrong results"
    gflops = n * iters * 2 * PROBE_WIDTH * PROBE_CHAINS / best / 1e9
    peak = physical_peak_gflops(dev)
    if peak is not None and gflops > OVER_PEAK * peak:
        return 0.0, (f"FMA probe measured {gflops:.0f} GFLOP/s, above this CPU's physical "
                     f"peak of {peak:.0f} (the compiler removed work): figure refused")
    return gflops, None


def physical_peak_gflops(dev: "cl.Device") -> float | None:
    """fp32 peak of a CPU device where it can be known: compute units x clock x the widest
    vector ISA's lanes x 2 FMA pipes x 2 flop; None for other devices or without a clock."""
    if not dev.type & cl.device_type.CPU:
        return None
    flags = cpu_flags()
    mhz = int(getattr(dev, "max_clock_frequency", 0) or 0)
    if mhz <= 0 or "sse2" not in flags:
        return None
    lanes = 16 if "avx512f" in flags else 8 if {"avx2", "fma"} <= flags else 4
    return int(dev.max_compute_units) * mhz * 1e-3 * lanes * 2 * 2


# ---- the cache ---------------------------------------------------------------------------------

def cache_path() -> Path:
    """``$XDG_CACHE_HOME/clrf/devices.json``, or ``~/.cache/clrf/devices.json``."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "clrf" / "devices.json"


def device_key(dev: "cl.Device") -> str:
    """What a figure is valid for: this host, platform name and version, device, driver."""
    p = dev.platform
    return "|".join(s.strip() for s in (socket.gethostname(), p.name, p.version, dev.name,
                                         dev.driver_version))


def _load(path: Path, version: str) -> dict:
    """Entries of the cache file that belong to ``version``; {} if missing or corrupt."""
    try:
        data = json.loads(path.read_text())
        entries = data["devices"]
        if not isinstance(entries, dict):
            return {}
    except (OSError, ValueError, KeyError, TypeError):
        return {}
    return {k: v for k, v in entries.items() if isinstance(v, dict) and v.get("probe") == version}


def _store(path: Path, version: str, key: str, probe: Probe) -> None:
    """Add one entry and write the file atomically; a cache that cannot be written is skipped."""
    entries = _load(path, version)
    entry = asdict(probe)
    entry.pop("cached")
    entry["probe"] = version
    entries[key] = entry
    write_dict(path, {"devices": entries})


def _from_entry(e: dict) -> Probe | None:
    try:
        g = float(e["gflops"])
        err = e["error"]
        if (err is not None and not isinstance(err, str)) or not math.isfinite(g):
            return None
        if err is None and g <= 0:
            return None
        return Probe(err, g, float(e.get("seconds", 0.0)), str(e.get("when", "")), cached=True)
    except (KeyError, TypeError, ValueError):
        return None


_memo: dict = {}    # device_key -> Probe, for this process


def probe(dev: "cl.Device", refresh: bool = False, measure_missing: bool = True) -> Probe | None:
    """The device's probe: from this process, else the cache file, else measured and stored.

    ``refresh`` measures again whatever is cached; ``measure_missing=False`` returns None
    instead of measuring a device that has no figure yet. A driver known to crash on this
    CPU (``known_crash``) is unusable without being run at all.
    """
    crash = known_crash(dev.platform.version, dev.name, cpu_id())
    if crash:
        return Probe(error=crash)
    key = device_key(dev)
    if not refresh and key in _memo:
        return _memo[key]
    path, version = cache_path(), probe_version()
    found = None if refresh else _from_entry(_load(path, version).get(key, {}))
    if found is None:
        if not measure_missing:
            return None
        found = measure(dev)
        _store(path, version, key, found)
    _memo[key] = found
    return found


# ---- ranking and slow-driver detection ---------------------------------------------------------

def rank(cands: list) -> list:
    """Usable candidates, best first (rule in the module doc)."""
    left = sorted((c for c in cands if c.probe.ok),
                  key=lambda c: (c.platform_index, c.device_index))
    out = []
    while left:
        top = max(c.probe.gflops for c in left)
        pick = next(c for c in left if c.probe.gflops >= top * (1 - TIE))
        out.append(pick)
        left.remove(pick)
    return out


def choice_reason(ranked: list) -> str:
    """Why ``ranked[0]`` is the default, in words, given the ranking of the wanted devices."""
    best = ranked[0]
    if len(ranked) == 1:
        return "the only working device"
    nxt = ranked[1]
    if nxt.probe.gflops >= best.probe.gflops * (1 - TIE):
        return (f"within {TIE:.0%} of {nxt.spec} ({nxt.probe.gflops:.1f} GFLOP/s) and first "
                f"in platform order")
    return (f"fastest measured, {best.probe.gflops / nxt.probe.gflops:.1f}x the next "
            f"({nxt.spec}, {nxt.probe.gflops:.1f} GFLOP/s)")


_TARGET_RE = re.compile(r"([a-z][a-z0-9_.]*(?:-[a-z0-9_.]+)*?)-(?=[A-Z])")
GENERIC_TARGETS = ("", "generic", "x86-64")


def pocl_cpu_target(name: str) -> str | None:
    """The LLVM CPU a PoCL CPU device compiles for, from its name.

    ``'pthread-haswell-AMD EPYC'`` -> ``'haswell'``; ``'cpu-znver3-AMD Ryzen 9'`` -> ``'znver3'``;
    ``'pthread-AMD EPYC'`` -> ``''`` (no CPU named: a generic target); a name that is not a
    PoCL CPU device's -> None.
    """
    m = re.match(r"(?:pthread|cpu|basic|tbb)-(.+)$", name.strip())
    if not m:
        return None
    t = _TARGET_RE.match(m.group(1))
    return t.group(1) if t else ""


def _model(c: Candidate) -> str:
    """The CPU model part of a PoCL device name (what two drivers on one CPU share)."""
    target = pocl_cpu_target(c.name)
    rest = c.name.split("-", 1)[1] if target is not None else c.name
    return rest[len(target) + 1:] if target else rest


def is_generic_target(c: Candidate) -> bool:
    return (c.type == "cpu" and "portable computing language" in c.platform.lower()
            and pocl_cpu_target(c.name) in GENERIC_TARGETS)


@functools.lru_cache(maxsize=None)
def cpu_id() -> tuple:
    """(vendor_id, family, model) of the host CPU from /proc/cpuinfo (``("AuthenticAMD", 25,
    17)``); ``("", -1, -1)`` where there is none."""
    got = {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                k, _, v = line.partition(":")
                k = k.strip()
                if k in ("vendor_id", "cpu family", "model") and k not in got:
                    got[k] = v.strip()
                if not line.strip() and got:
                    break
    except OSError:
        pass

    def num(v):
        return int(v) if v and v.isdigit() else -1
    return got.get("vendor_id", ""), num(got.get("cpu family")), num(got.get("model"))


# AMD family 25 (0x19) models of the Zen 4 cores (Genoa 0x10-0x1f, Raphael 0x60-0x6f, Phoenix
# 0x70-0x7f, Bergamo / Siena 0xa0-0xaf); the rest of family 25 is Zen 3
ZEN4_MODELS = (range(0x10, 0x20), range(0x60, 0x80), range(0xa0, 0xb0))


def is_zen4(cpu: tuple) -> bool:
    vendor, family, model = cpu
    return vendor == "AuthenticAMD" and family == 25 and any(model in r for r in ZEN4_MODELS)


# Drivers that crash the process on some CPU, each refused there with its reason: a crash
# inside a kernel is a signal, which no check in the same process survives, and a self-check in a
# child process covers only the kernels it runs. (driver test, CPU test, reason)
KNOWN_CRASHES = (
    (lambda version, name: "pocl 3.0" in version.lower() and pocl_cpu_target(name) in
     GENERIC_TARGETS,
     is_zen4,
     "pip's PoCL 3.0 (pocl-binary-distribution, LLVM 14) compiles for a generic x86-64 target on "
     "AMD Zen 4 and crashed clrf with SIGSEGV in the grid renderer there (CPU family 25 model "
     "{model}), after passing its gradient self-check; " + INSTALL_HINT + " or Intel's CPU "
     "runtime (`bash tools/setup.sh intel`)"),
)


def known_crash(platform_version: str, name: str, cpu: tuple) -> str | None:
    """Why the driver ``platform_version`` (device ``name``) is refused on ``cpu`` (``cpu_id``)
    without being run, or None."""
    for driver, on_cpu, reason in KNOWN_CRASHES:
        if driver(platform_version, name) and on_cpu(cpu):
            return "known to crash here: " + reason.format(model=cpu[2])
    return None


@functools.lru_cache(maxsize=None)
def cpu_flags() -> frozenset:
    """The host CPU's feature flags from /proc/cpuinfo (empty where there is none)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return frozenset(line.split(":", 1)[1].split())
    except OSError:
        pass
    return frozenset()


def estimated_peak_gflops(c: Candidate, flags: frozenset) -> float | None:
    """Rough fp32 peak the probe could reach on an x86 CPU device, or None where unknown.

    compute units x clock x lanes x 2 FMA pipes x 2 flop, lanes = min(PROBE_WIDTH, vector
    width of the widest ISA in ``flags``: avx512f 16, avx2 with fma 8, sse2 4). Clocks under
    turbo and CPUs with one FMA pipe make it off by up to 2x, which ``SLOW_VS_PEAK`` allows for.
    """
    if c.type != "cpu" or c.clock_mhz <= 0 or "sse2" not in flags:
        return None
    lanes = 16 if "avx512f" in flags else 8 if {"avx2", "fma"} <= flags else 4
    return c.compute_units * c.clock_mhz * 1e-3 * min(lanes, PROBE_WIDTH) * 2 * 2


def slow_reasons(c: Candidate, cands: list, flags: frozenset) -> list:
    """Why ``c`` looks like a slow driver for its hardware ([] when it does not)."""
    if not c.probe.ok:
        return []
    out = []
    if is_generic_target(c):
        out.append("compiles for a generic CPU target (no LLVM CPU in the device name)")
    peak = estimated_peak_gflops(c, flags)
    if peak and c.probe.gflops < peak * SLOW_VS_PEAK:
        out.append(f"measures {c.probe.gflops:.1f} GFLOP/s, under {SLOW_VS_PEAK:.0%} of this "
                   f"CPU's estimated peak of {peak:.0f}")
    sib = faster_sibling(c, cands)
    if sib is not None:
        out.append(f"{sib.probe.gflops / c.probe.gflops:.0f}x slower than {sib.spec} "
                   f"on the same CPU")
    return out


def faster_sibling(c: Candidate, cands: list) -> Candidate | None:
    """The fastest other driver for the same CPU if it measures SLOW_VS_SIBLING times faster."""
    same = [o for o in cands if o is not c and o.probe.ok and o.type == c.type == "cpu"
            and o.vendor == c.vendor and o.compute_units == c.compute_units
            and _model(o) == _model(c)]
    best = max(same, key=lambda o: o.probe.gflops, default=None)
    if best is not None and best.probe.gflops >= SLOW_VS_SIBLING * c.probe.gflops:
        return best
    return None


def slow_warning(c: Candidate, cands: list, flags: frozenset) -> str | None:
    """The one-line warning for using ``c``, naming the fix, or None when it is not slow."""
    why = slow_reasons(c, cands, flags)
    if not why:
        return None
    sib = faster_sibling(c, cands)
    fix = f"use CLRF_DEVICE={sib.spec} or {INSTALL_HINT}" if sib else INSTALL_HINT
    return f"clrf: warning: device {c.short()} {why[0]}; {fix}"


_warned: set = set()


def warn_once(line: str | None) -> None:
    """Print ``line`` to stderr the first time this process sees it."""
    if line and line not in _warned:
        _warned.add(line)
        print(line, file=sys.stderr)
