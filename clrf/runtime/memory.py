"""Memory planning: the bytes each phase of a run holds on the device and on the host beside
it, and the check of a plan against a device (its global memory, its largest allocation) and
the host's budget (clrf/runtime/hostmem.py). What a phase holds is estimated by the layer that
knows the run (each model kind's budget.py; clrf/training/budget.py puts them together); docs/memory.md has the model and
the measured peaks it was fitted to.
"""
from __future__ import annotations

from dataclasses import dataclass

GiB = float(1 << 30)
MiB = float(1 << 20)

# Host bytes a CPU run grows by beyond what the model counts: the kernels PoCL compiles after the
# guard has run (LLVM's working memory, the compiled code) and the runtime's own per-buffer and
# per-thread allocations. With it the three peaks of tools/results/memory/ are predicted within
# -2 .. +8 % (docs/memory.md).
RUNTIME_GROWTH = 200 * (1 << 20)

RAY_DEVICE_BYTES = 36        # device o, d, rgb float32
RAY_BUILD_BYTES = 36         # while building, per ray of one part: host o, d, rgb float32
RAY_PART = 1 << 22           # rays built and uploaded at a time (clrf/training/trainer.py)


class MemoryPlanError(ValueError):
    """A planned run would not fit the device's or the host's memory; names the phase and the
    settings to lower."""


@dataclass
class StageEstimate:
    """Bytes one phase of a run holds at its peak: on the device (``total``) and on the host
    beside it (``host``, not counting what the process holds before training), and its largest
    device buffer."""
    name: str
    total: int
    largest: int
    largest_what: str
    host: int = 0


@dataclass
class MemoryPlan:
    """The guard's verdict: the phases, the predicted resident peak of the process (``peak``;
    on GPUs the host part only), the host budget it was checked against and what the process
    held when checked."""
    stages: list
    peak: int
    budget: object = None     # clrf.runtime.hostmem.HostBudget, None when the host was not checked
    rss: int = 0

    def describe(self) -> str:
        b = self.budget
        avail = (f" of {(b.available + self.rss) / GiB:.2f} GiB ({b.source}, plus the "
                 f"{self.rss / GiB:.2f} GiB held now)" if b is not None and b.available >= 0
                 else "")
        worst = max(self.stages, key=lambda s: s.total + s.host)
        return f"predicted peak {self.peak / GiB:.3f} GiB{avail}, at {worst.name}"


def plan_peak(stages: list, is_cpu: bool, host=None) -> MemoryPlan:
    """The MemoryPlan of ``stages`` for a process whose host budget is ``host``
    (clrf.runtime.hostmem.HostBudget; None: the host is not counted). The peak is the process's
    resident set now + RUNTIME_GROWTH + the largest phase (device + host bytes on CPU devices,
    host bytes elsewhere), at least the peak so far."""
    rss = host.rss if host is not None else 0
    grow = max((st.host + (st.total if is_cpu else 0)) for st in stages)
    peak = max(rss + RUNTIME_GROWTH + grow, host.peak if host is not None else 0)
    return MemoryPlan(stages, peak, host, rss)


def check_plan(plan: MemoryPlan, caps, is_cpu: bool, fix: str, error=MemoryPlanError):
    """Raise ``error`` (a MemoryPlanError) naming the phase and ``fix`` (the settings to lower)
    when a phase of ``plan`` exceeds the device described by ``caps`` (its global memory or
    largest allocation) or the host budget the plan was made with."""
    host = plan.budget
    glob, alloc = int(caps.global_mem_size), int(caps.max_alloc_size)
    # a CPU device's buffers are host memory: with the host's budget known, that is the limit
    # (PoCL reports a fraction of the host as global_mem_size but does not cap the sum of its
    # buffers at it; each buffer stays capped at max_alloc_size)
    host_known = host is not None and host.available >= 0
    for st in plan.stages:
        if st.total > glob and not (is_cpu and host_known):
            raise error(
                f"{st.name} needs about {st.total / GiB:.2f} GiB of device memory, more than "
                f"the {glob / GiB:.2f} GiB of {caps.name}; {fix}")
        if host_known:
            need = RUNTIME_GROWTH + st.host + (st.total if is_cpu else 0)
            if need > host.available:
                where = "device and host" if is_cpu else "host"
                raise error(
                    f"{st.name} needs about {need / GiB:.2f} GiB more {where} memory than "
                    f"this process holds now ({host.rss / GiB:.2f} GiB), but only "
                    f"{host.available / GiB:.2f} GiB is available ({host.source}); {fix}")
    for st in plan.stages:
        if st.largest > alloc:
            raise error(
                f"{st.name}: its {st.largest_what} buffer needs {st.largest / GiB:.2f} GiB, "
                f"more than the largest single allocation of {caps.name} "
                f"({alloc / GiB:.2f} GiB); {fix}")
    return plan


def ray_build_host(n_rays: int) -> int:
    """Host bytes while the training rays are built: one part of them."""
    return RAY_BUILD_BYTES * min(int(n_rays), RAY_PART)


def ray_store_bytes(n_rays: int, batch: int) -> int:
    """Device bytes of the ray store and its batch buffers."""
    return RAY_DEVICE_BYTES * int(n_rays) + 44 * int(batch)


def training_stages(st: StageEstimate, n_rays: int) -> list:
    """A one-phase run's stages: building its ``n_rays`` training rays (the device store, and
    one part of them at a time on the host), then the phase ``st`` (the MLP models; the ray
    store keeps no host copy of its rays)."""
    return [StageEstimate(f"building the training rays ({st.name})",
                          RAY_DEVICE_BYTES * int(n_rays), 0, "", ray_build_host(n_rays)),
            StageEstimate(st.name, st.total, st.largest, st.largest_what, 0)]
