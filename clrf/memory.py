"""Memory guard: will a configured run fit the device? Checked before anything is allocated.

``check_training_fits(caps, is_cpu, cfg, n_rays)`` estimates, for every stage of a run, the
device bytes it holds at its peak and the largest single buffer, and raises MemoryBudgetError
(a ConfigError: the CLI prints it and exits 2) naming the stage and the options that would make
it fit when either exceeds the device's ``global_mem_size`` or ``max_alloc_size``.

Plenoxels stage k at resolution R_k (V_k = prod(R_k) voxels, C = 3 (degree + 1)^2 SH
coefficients) with n_k rows (stage 0: the voxels inside the inscribed ellipsoid when
``sphere_bound``, else V_0; later stages: pruning keeps every row, so the occupied fraction of
stage 0 over the grid grown by one previous-stage voxel on each side, at most V_k):

    grid       4 V_k (links) + 4 n_k (1 + C)            values
    optimiser  2 * 4 n_k (1 + C) + n_k                 gradient + RMSProp state + touched flags
    slots      S n_k (4 (1 + C) + 1)                   scratch gradient copies (CPU: S = 1 with
                                                       the block locks, else compute units;
                                                       dropped when > global / 4)
    upsample   the previous stage's grid + optimiser, + 8 V_k (flags, links) + 4 n_k (1 + C)
    rays       36 N + 44 B                             ray store (o, d, rgb) + batch buffers
    background 49 T + 32 B   (grid.background_layers L > 0: T = 2 L H^2 MSI texels, H =
                             background_height) density + colour (4 floats a texel) with their
                             gradients and RMSProp states, a touched flag per texel; per batch
                             ray t_start, bg colour, bg transmittance, dL/d bg colour

NeRF (P parameters per network, s samples per ray, B rays per step, nslot activation slots
per sample): 5 P per network (params, transposed copy, gradient, Adam m and v), activations
and their gradients 2 * 4 B s nslot, per-sample encodings and gradients, plus the ray store.
The figures estimate what clrf itself allocates; the OpenCL runtime's own overhead is not counted.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .config import ConfigError

GiB = float(1 << 30)


class MemoryBudgetError(ConfigError):
    """A configured run would not fit the device's memory; names the stage and the fix."""


@dataclass
class StageEstimate:
    """Device bytes one stage holds at its peak (``total``) and its largest buffer."""
    name: str
    total: int
    largest: int
    largest_what: str


def sphere_rows(reso) -> int:
    """Voxel centres of a reso grid inside the box's inscribed ellipsoid (as initial_grid)."""
    rx, ry, rz = (int(r) for r in reso)
    cx = ((np.arange(rx) + 0.5) / rx * 2 - 1) ** 2
    cy = ((np.arange(ry) + 0.5) / ry * 2 - 1) ** 2
    cz = np.sort(((np.arange(rz) + 0.5) / rz * 2 - 1) ** 2)
    rest = 1.0 - (cx[:, None] + cy[None, :])                 # [rx, ry] budget left for z^2
    return int(np.searchsorted(cz, rest.ravel(), side="right").sum())


def ray_store_bytes(n_rays: int, batch: int) -> int:
    return 36 * int(n_rays) + 44 * int(batch)


def background_bytes(g) -> tuple:
    """(total, colour buffer) bytes of the MSI background of GridConfig g (0, 0 when off)."""
    if g.background_layers <= 0:
        return 0, 0
    T = 2 * int(g.background_layers) * int(g.background_height) ** 2
    return 49 * T + 32 * int(g.batch_size), 12 * T


def grid_stages(cfg, n_rays: int, slots: int, global_mem: int) -> list:
    """StageEstimate per resolution of cfg.grid (see the module docstring for the terms)."""
    g = cfg.grid
    C = 3 * (g.sh_degree + 1) ** 2
    row = 4 * (1 + C)
    bg, bg_color = background_bytes(g)
    rays = ray_store_bytes(n_rays, g.batch_size) + bg
    out, prev, frac = [], 0, 1.0
    for k, reso in enumerate(g.reso):
        V = int(np.prod([int(r) for r in reso]))
        if k == 0:
            n = sphere_rows(reso) if g.sphere_bound else V
            frac = n / V
        else:
            grown = np.prod([r + 2.0 * r / p for r, p in zip(reso, g.reso[k - 1])])
            n = min(V, int(np.ceil(frac * grown)))
        grid = 4 * V + row * n
        opt = 2 * row * n + n
        s = slots if slots * n * (row + 1) <= global_mem // 4 else 0
        train = grid + opt + s * n * (row + 1) + rays
        upsample = prev + 8 * V + row * n + rays if k > 0 else 0
        buffers = [(4 * n * C, "SH values"), (4 * V, "voxel links"),
                   (s * n * 4 * C, "scratch SH gradient copies"),
                   (bg_color, "MSI background colour")]
        big, what = max(buffers)
        label = "x".join(str(int(r)) for r in reso)
        out.append(StageEstimate(f"grid stage {k} ({label}, SH degree {g.sh_degree})",
                                 max(train, upsample), big, what))
        prev = grid + opt
    return out


def nerf_stage(nc, n_rays: int, caps) -> StageEstimate:
    """StageEstimate of a NeRF run with NerfConfig ``nc`` on a device described by ``caps``
    (its default register tile sets the weight-gradient chunk when the config leaves it open)."""
    from .autotune import CHUNK_TILES, device_default
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
    occupancy grid and the ray store."""
    pad = lambda x: -(-x // 16) * 16                           # noqa: E731 - kernel padding
    table = 4 * hc.levels * (1 << hc.log2_table) * hc.features
    tables = 4 * table
    W, WC, din = hc.width, hc.color_width, pad(hc.levels * hc.features)
    nslot = din + W + 16 + hc.geo_features + 16 + hc.color_depth * WC + 16
    samples = hc.batch_rays * hc.samples
    act = 2 * 4 * pad(samples) * nslot
    per_sample = 4 * samples * (2 * (din + 16) + 20)
    occ = 5 * hc.occ_res ** 3
    total = tables + act + per_sample + occ + ray_store_bytes(n_rays, hc.batch_rays)
    return StageEstimate(f"hash training ({hc.batch_rays} rays x {hc.samples} samples, "
                         f"T 2^{hc.log2_table})", total, max(table, 4 * pad(samples) * nslot),
                         "hash table or MLP activations")


def scratch_copies(is_cpu: bool, tuning=None) -> int:
    """Scratch gradient copies the grid backward holds on a device with Tuning ``tuning``
    (Tuning.scratch_copies of its slots); None means the defaults: one on CPU devices (block
    locks), none elsewhere (atomics)."""
    if tuning is None:
        return 1 if is_cpu else 0
    return tuning.scratch_copies(tuning.grad_slots)


def check_training_fits(caps, is_cpu: bool, cfg, n_rays: int, tuning=None) -> list:
    """Raise MemoryBudgetError when a stage of the run configured by ``cfg`` (a Config) on
    ``n_rays`` training rays exceeds the device described by ``caps`` (DeviceCaps; ``tuning``
    its Tuning, None for the defaults); returns the StageEstimates otherwise."""
    if cfg.train.model == "hash":
        stages = [hash_stage(cfg.hash, n_rays)]
        fix = ("lower hash.log2_table, hash.batch_rays or hash.samples, or load fewer rays with "
               "train.downscale / train.max_train_images")
    elif cfg.train.model == "nerf":
        stages = [nerf_stage(cfg.nerf, n_rays, caps)]
        fix = ("lower nerf.batch_rays, nerf.n_coarse / nerf.n_fine or nerf.width, or load fewer "
               "rays with train.downscale / train.max_train_images")
    else:
        stages = grid_stages(cfg, n_rays, scratch_copies(is_cpu, tuning),
                             int(caps.global_mem_size))
        fix = ("lower grid.reso (e.g. --set 'grid.reso=[[128,128,128]]' "
               "--set 'grid.upsample_at=[]'), grid.sh_degree or grid.batch_size, or load fewer "
               "rays with train.downscale / train.max_train_images")
    glob, alloc = int(caps.global_mem_size), int(caps.max_alloc_size)
    for st in stages:
        if st.total > glob:
            raise MemoryBudgetError(
                f"{st.name} needs about {st.total / GiB:.2f} GiB of device memory, more than "
                f"the {glob / GiB:.2f} GiB of {caps.name}; {fix}")
        if st.largest > alloc:
            raise MemoryBudgetError(
                f"{st.name}: its {st.largest_what} buffer needs {st.largest / GiB:.2f} GiB, "
                f"more than the largest single allocation of {caps.name} "
                f"({alloc / GiB:.2f} GiB); {fix}")
    return stages
