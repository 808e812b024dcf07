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
    rays       36 N + 44 B (device) + 24 N (host)   ray store (o, d, rgb) + batch buffers; the
                                                    host keeps o, d for pruning (+ 4 N: alpha,
                                                    for random backgrounds, hash model)
    checkpoint 4 V_k + 2 r n_k (host)               state_dict's copies while a checkpoint is
                                                    written (every stage may write one)
    upsample   stage k-1's grid, optimiser and scratch, its max weights and keep masks
               (6 n_{k-1}), the new links and resample flags (8 V_k) and rows (r n_k)
    building   72 N (host)                          pixel rays in float64, their float32 copies
    rays                                            and the colours, beside stage 0's grid
    background 49 T + 32 B, T = 2 L H^2 MSI texels (grid.background_layers L > 0, H =
               background_height): density + colour with gradients and RMSProp states, flags

NeRF (P parameters per network, s samples per ray, B rays per step, nslot activation slots
per sample): 5 P per network (params, transposed copy, gradient, Adam m and v), activations
and their gradients 2 * 4 B s nslot, per-sample encodings and gradients, plus the ray store.

On the host, beside those: what the process holds when the guard runs (the interpreter, the
OpenCL runtime, the loaded images, 12 bytes a pixel), and RUNTIME_GROWTH for the kernels
compiled later and the runtime's own buffers; the peak so far (VmHWM: loading the images) is a
floor. docs/memory.md has the measured peaks this model was fitted to.
"""
from __future__ import annotations

import numpy as np

from ..runtime.memory import (  # noqa: F401 - GiB, MiB, RUNTIME_GROWTH re-exported
    GiB, MiB, RUNTIME_GROWTH, MemoryPlan, MemoryPlanError, StageEstimate, check_plan, plan_peak)
from .config import ConfigError
RAY_HOST_BYTES = 24          # host o, d float32 kept by the ray store for pruning
RAY_DEVICE_BYTES = 36        # device o, d, rgb float32
RAY_BUILD_BYTES = 72         # host, while building: float64 o, d + their float32 copies


class MemoryBudgetError(MemoryPlanError, ConfigError):
    """A configured run would not fit the device's or the host's memory; names the phase and
    the settings to lower (a ConfigError: the CLI prints it and exits 2)."""


def sphere_rows(reso) -> int:
    """Voxel centres of a reso grid inside the box's inscribed ellipsoid (as initial_grid)."""
    rx, ry, rz = (int(r) for r in reso)
    cx = ((np.arange(rx) + 0.5) / rx * 2 - 1) ** 2
    cy = ((np.arange(ry) + 0.5) / ry * 2 - 1) ** 2
    cz = np.sort(((np.arange(rz) + 0.5) / rz * 2 - 1) ** 2)
    rest = 1.0 - (cx[:, None] + cy[None, :])                 # [rx, ry] budget left for z^2
    return int(np.searchsorted(cz, rest.ravel(), side="right").sum())


def ray_store_bytes(n_rays: int, batch: int) -> int:
    """Device bytes of the ray store and its batch buffers."""
    return RAY_DEVICE_BYTES * int(n_rays) + 44 * int(batch)


def background_bytes(g) -> tuple:
    """(total, colour buffer) bytes of the MSI background of GridConfig g (0, 0 when off)."""
    if g.background_layers <= 0:
        return 0, 0
    T = 2 * int(g.background_layers) * int(g.background_height) ** 2
    return 49 * T + 32 * int(g.batch_size), 12 * T


def grid_stages(cfg, n_rays: int, slots: int, global_mem: int, rows=None) -> list:
    """StageEstimates of cfg.grid's run (see the module docstring for the terms): building the
    rays, then per resolution its upsample (k > 0) and its training. ``rows``: the row count of
    each stage when known (a finished run's, to check the model), else the worst case."""
    g = cfg.grid
    C = 3 * (g.sh_degree + 1) ** 2
    row = 4 * (1 + C)
    bg, bg_color = background_bytes(g)
    rays = ray_store_bytes(n_rays, g.batch_size) + bg
    rays_host = RAY_HOST_BYTES * int(n_rays)
    out, prev, prev_n, prev_drop, frac = [], 0, 0, 0, 1.0
    for k, reso in enumerate(g.reso):
        V = int(np.prod([int(r) for r in reso]))
        if k == 0:
            n = sphere_rows(reso) if g.sphere_bound else V
            frac = n / V
        else:
            grown = np.prod([r + 2.0 * r / p for r, p in zip(reso, g.reso[k - 1])])
            n = min(V, int(np.ceil(frac * grown)))
            frac = n / V   # each upsample grows the occupied part again
        if rows is not None:
            n = int(rows[k])
        grid = 4 * V + row * n
        opt = 2 * row * n + n
        s = slots if slots * n * (row + 1) <= global_mem // 4 else 0
        scratch = s * n * (row + 1)
        label = "x".join(str(int(r)) for r in reso)
        what = f"grid stage {k} ({label}, SH degree {g.sh_degree})"
        buffers = [(4 * n * C, "SH values"), (4 * V, "voxel links"),
                   (s * n * 4 * C, "scratch SH gradient copies"),
                   (bg_color, "MSI background colour")]
        big, big_what = max(buffers)
        if k == 0:
            out.append(StageEstimate(f"building the training rays ({what})", grid + opt,
                                     big, big_what, RAY_BUILD_BYTES * int(n_rays)))
        else:
            # resample: the old stage whole + max weights, keep masks + flags, links, rows;
            # then the new optimiser once the old links and scratch copies are gone
            up = prev + 6 * prev_n + 4 * V + row * n + max(4 * V, 2 * row * n + n - prev_drop)
            out.append(StageEstimate(f"the upsample to {what}", up + rays, big, big_what,
                                     rays_host))
        ckpt = 4 * V + 2 * row * n + (32 * (bg - 32 * g.batch_size) // 49 if bg else 0)
        out.append(StageEstimate(what, grid + opt + scratch + rays, big, big_what,
                                 rays_host + ckpt))
        prev, prev_n, prev_drop = grid + opt + scratch, n, 4 * V + scratch
    return out


def nerf_stage(nc, n_rays: int, caps) -> StageEstimate:
    """StageEstimate of a NeRF run with NerfConfig ``nc`` on a device described by ``caps``
    (its default register tile sets the weight-gradient chunk when the config leaves it open)."""
    from ..nerf.tiling import CHUNK_TILES, device_default
    spec = nc.mlp_spec()
    dw_chunk = spec.dw_chunk or (CHUNK_TILES * spec.rows if spec.rows
                                 else device_default(caps, spec).dw_chunk)
    W, D, WC = spec.width, spec.depth, spec.color_width
    pad = lambda x: -(-x // 16) * 16                           # noqa: E731 - kernel padding
    params = (pad(spec.in_dim) * W + (D - 1) * W * W + (pad(spec.in_dim) * W if spec.skip >= 0
                                                          else 0)
              + W * (W + 16) + (W + pad(spec.dir_dim)) * WC + WC * 16 + (D + 4) * (W + 16))
    nslot = pad(spec.in_dim) + pad(spec.dir_dim) + (D + 1) * W + 16 + WC + 16
    B = nc.batch_rays
    nets = [nc.n_coarse, nc.n_coarse + nc.n_fine] if nc.n_fine else [nc.n_coarse]
    if nc.shared_net:
        nets = [max(nets)]
    act = sum(2 * 4 * pad(B * s) * nslot + 4 * (-(-B * s // dw_chunk)) * params
              for s in nets)
    samples = B * (nc.n_coarse + nc.n_fine)
    per_sample = 4 * samples * (2 * (spec.in_dim + spec.dir_dim) + 16)
    total = 5 * 4 * params * len(nets) + act + per_sample + ray_store_bytes(n_rays, B)
    big = 4 * pad(B * max(nets)) * nslot
    return StageEstimate(f"NeRF training ({B} rays x {max(nets)} samples, width {W})", total,
                         big, "MLP activations")


def hash_stage(hc, n_rays: int) -> StageEstimate:
    """StageEstimate of a hash-grid run with HashConfig ``hc``: tables with gradient and Adam
    moments (the backward needs no scratch copy on either path), the MLP's activations for
    every sample of a batch (all live: the occupancy grid starts full), per-sample buffers, the
    occupancy grid and the ray store (with the images' alpha for random backgrounds)."""
    pad = lambda x: -(-x // 16) * 16                           # noqa: E731 - kernel padding
    table = 4 * hc.levels * (1 << hc.log2_table) * hc.features
    tables = 4 * table
    W, WC, din = hc.width, hc.color_width, pad(hc.levels * hc.features)
    nslot = din + W + 16 + hc.geo_features + 16 + hc.color_depth * WC + 16
    # an adapted batch (hash.batch_samples) aims at batch_samples live samples; twice that
    # covers a step whose rays hold more than the last step's
    samples = 2 * hc.batch_samples if hc.batch_samples else hc.batch_rays * hc.samples
    act = 2 * 4 * pad(samples) * nslot
    per_sample = 4 * samples * (2 * (din + 16) + 20)
    occ = 5 * hc.occ_res ** 3
    from ..hash.model import BATCH_RAYS_RANGE
    rays = BATCH_RAYS_RANGE[1] if hc.batch_samples else hc.batch_rays
    alpha = 4 * int(n_rays) if hc.random_background else 0
    total = tables + act + per_sample + occ + ray_store_bytes(n_rays, rays) + alpha
    what = (f"{hc.batch_samples} live samples" if hc.batch_samples else
            f"{hc.batch_rays} rays x {hc.samples} samples")
    return StageEstimate(f"hash training ({what}, "
                         f"T 2^{hc.log2_table})", total, max(table, 4 * pad(samples) * nslot),
                         "hash table or MLP activations")


def scratch_copies(is_cpu: bool, tuning=None) -> int:
    """Scratch gradient copies the grid backward holds on a device with Tuning ``tuning``
    (Tuning.scratch_copies of its slots); None means the defaults: one on CPU devices (block
    locks), none elsewhere (atomics)."""
    if tuning is None:
        return 1 if is_cpu else 0
    return tuning.scratch_copies(tuning.grad_slots)


GRID_FIX = ("lower grid.reso (e.g. --set 'grid.reso=[[128,128,128]]' --set "
            "'grid.upsample_at=[]'), grid.sh_degree or grid.batch_size, or load fewer rays with "
            "train.downscale / train.max_train_images")
NERF_FIX = ("lower nerf.batch_rays, nerf.n_coarse / nerf.n_fine or nerf.width, or load fewer "
            "rays with train.downscale / train.max_train_images")
HASH_FIX = ("lower hash.log2_table, hash.batch_samples (or hash.batch_rays) or hash.samples, or "
            "load fewer rays with "
            "train.downscale / train.max_train_images")


def plan_training(caps, is_cpu: bool, cfg, n_rays: int, tuning=None, host=None) -> MemoryPlan:
    """The MemoryPlan of the run configured by ``cfg`` (a Config) on ``n_rays`` training rays,
    on the device described by ``caps`` (DeviceCaps; ``tuning`` its Tuning, None for the
    defaults), for a process whose host budget is ``host`` (clrf.runtime.hostmem.HostBudget; None:
    the host is not counted). The peak is the process's resident set now + RUNTIME_GROWTH +
    the largest phase (device + host bytes on CPU devices, host bytes elsewhere), at least
    the peak so far."""
    if cfg.train.model in ("nerf", "hash"):
        st = (nerf_stage(cfg.nerf, n_rays, caps) if cfg.train.model == "nerf"
              else hash_stage(cfg.hash, n_rays))
        stages = [StageEstimate(f"building the training rays ({st.name})", 0, 0, "",
                                RAY_BUILD_BYTES * int(n_rays)),
                  StageEstimate(st.name, st.total, st.largest, st.largest_what,
                                RAY_HOST_BYTES * int(n_rays))]
    else:
        stages = grid_stages(cfg, n_rays, scratch_copies(is_cpu, tuning),
                             int(caps.global_mem_size))
    return plan_peak(stages, is_cpu, host)


def check_training_fits(caps, is_cpu: bool, cfg, n_rays: int, tuning=None,
                        host=None) -> MemoryPlan:
    """Raise MemoryBudgetError when a phase of the run configured by ``cfg`` on ``n_rays``
    training rays exceeds the device described by ``caps`` (its global memory or largest
    allocation) or, with ``host`` (clrf.runtime.hostmem.HostBudget), the host's budget; returns the
    MemoryPlan otherwise."""
    plan = plan_training(caps, is_cpu, cfg, n_rays, tuning, host)
    fix = {"nerf": NERF_FIX, "hash": HASH_FIX}.get(cfg.train.model, GRID_FIX)
    return check_plan(plan, caps, is_cpu, fix, MemoryBudgetError)
