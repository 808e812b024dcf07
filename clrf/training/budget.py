"""Memory guard: will a configured run fit the device and the host? Checked before anything is
allocated.

``check_training_fits(caps, is_cpu, cfg, n_rays, tuning, n_pixels, host)`` estimates, for every
phase of a run, the device bytes it holds at its peak, the host bytes beside them and the
largest single buffer, and raises MemoryBudgetError (a ConfigError: the CLI prints it and exits
2) naming the phase and the settings to lower when

- on a CPU device (whose buffers live in host memory): the run's predicted resident peak less
  what the process already holds exceeds the host's budget (clrf.runtime.hostmem: MemAvailable, the
  cgroup limit, ``ulimit -v``); only where that budget is unknown, the device bytes against
  ``global_mem_size`` (PoCL reports a fraction of the host there, 5.2 GiB of 24, and does not
  cap the sum of its buffers at it);
- on a GPU: the device bytes exceed ``global_mem_size``, or the host bytes the host's budget;
- anywhere: a buffer exceeds ``max_alloc_size``.

Plenoxels stage k at resolution R_k (V_k = prod(R_k) voxels, C = 3 (degree + 1)^2 SH
coefficients, r = 4 (1 + C) bytes a row) with n_k rows (stage 0: the voxels inside the inscribed
ellipsoid when ``sphere_bound``, else V_0; later stages: the previous stage's occupied fraction
over the grid grown by one previous-stage voxel on each side, at most V_k: the worst case,
pruning that keeps every row):

    grid       4 V_k + r n_k                        links, density + SH rows
    optimiser  2 r n_k + n_k                        gradient + RMSProp state, touched flags
    scratch    S n_k (r + 1)                        scratch gradient copies (Tuning.scratch_copies:
                                                    CPU with block locks S = 1; dropped when
                                                    they exceed global_mem_size / 4)
    rays       36 N + 44 B (device)                 ray store (o, d, rgb) + batch buffers (+ 4 N:
                                                    alpha, for random backgrounds, hash model);
                                                    pruning reads a strided subset back
    checkpoint 4 V_k + 2 r n_k (host)               state_dict's copies while a checkpoint is
                                                    written (every stage may write one)
    upsample   stage k-1's grid, optimiser and scratch, its max weights and keep masks
               (6 n_{k-1}), the new links and resample flags (8 V_k) and rows (r n_k)
    building   36 N (device) + 36 min(N, RAY_PART)  the device store, filled a part at a time
    rays       (host)                               from the host (o, d, rgb float32 of about
                                                    4 M rays), beside stage 0's grid
    background 49 T + 32 B, T = 2 L H^2 MSI texels (grid.background_layers L > 0, H =
               background_height): density + colour with gradients and RMSProp states, flags

NeRF (P parameters per network, s samples per ray, B rays per step, nslot activation slots
per sample): 5 P per network (params, transposed copy, gradient, Adam m and v), activations
and their gradients 2 * 4 B s nslot, per-sample encodings and gradients, plus the ray store.

On the host, beside those: what the process holds when the guard runs (the interpreter, the
OpenCL runtime, the loaded images: 3 bytes a pixel for 8-bit files at their own size, 4 for
RGBA, 12 when averaged down, clrf/data/images.py), and RUNTIME_GROWTH for the kernels compiled
later and the runtime's own buffers; the peak so far (VmHWM) is a floor. docs/memory.md has the measured peaks this model was fitted to.
"""
from __future__ import annotations

from .. import registry
from ..runtime.memory import (  # noqa: F401 - GiB, MiB, RUNTIME_GROWTH re-exported
    GiB, MiB, RUNTIME_GROWTH, MemoryPlan, MemoryPlanError, StageEstimate, check_plan, plan_peak)
from .config import ConfigError


class MemoryBudgetError(MemoryPlanError, ConfigError):
    """A configured run would not fit the device's or the host's memory; names the phase and
    the settings to lower (a ConfigError: the CLI prints it and exits 2)."""


def plan_training(caps, is_cpu: bool, cfg, n_rays: int, tuning=None, host=None) -> MemoryPlan:
    """The MemoryPlan of the run configured by ``cfg`` (a Config) on ``n_rays`` training rays,
    on the device described by ``caps`` (DeviceCaps; ``tuning`` its Tuning, None for the
    defaults), for a process whose host budget is ``host`` (clrf.runtime.hostmem.HostBudget; None:
    the host is not counted). The peak is the process's resident set now + RUNTIME_GROWTH +
    the largest phase (device + host bytes on CPU devices, host bytes elsewhere), at least
    the peak so far."""
    return _plan(caps, is_cpu, cfg, n_rays, tuning, host)[0]


def _plan(caps, is_cpu, cfg, n_rays, tuning, host):
    """(MemoryPlan, the settings to lower) from the kind's one memory estimate."""
    stages, fix = registry.get(cfg.train.model).memory(cfg, n_rays, caps, tuning, is_cpu)
    return plan_peak(stages, is_cpu, host), fix


def check_training_fits(caps, is_cpu: bool, cfg, n_rays: int, tuning=None,
                        host=None) -> MemoryPlan:
    """Raise MemoryBudgetError when a phase of the run configured by ``cfg`` on ``n_rays``
    training rays exceeds the device described by ``caps`` (its global memory or largest
    allocation) or, with ``host`` (clrf.runtime.hostmem.HostBudget), the host's budget; returns the
    MemoryPlan otherwise."""
    plan, fix = _plan(caps, is_cpu, cfg, n_rays, tuning, host)
    return check_plan(plan, caps, is_cpu, fix, MemoryBudgetError)
