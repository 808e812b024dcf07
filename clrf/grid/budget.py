"""Memory estimate of a Plenoxels run (the terms: clrf/training/budget.py's docstring and
docs/memory.md): every stage of the coarse-to-fine schedule, its upsample and the rays."""
from __future__ import annotations

import numpy as np

from ..runtime.memory import (RAY_DEVICE_BYTES, StageEstimate, ray_build_host,
                              ray_store_bytes)


def sphere_rows(reso) -> int:
    """Voxel centres of a reso grid inside the box's inscribed ellipsoid (as initial_grid)."""
    rx, ry, rz = (int(r) for r in reso)
    cx = ((np.arange(rx) + 0.5) / rx * 2 - 1) ** 2
    cy = ((np.arange(ry) + 0.5) / ry * 2 - 1) ** 2
    cz = np.sort(((np.arange(rz) + 0.5) / rz * 2 - 1) ** 2)
    rest = 1.0 - (cx[:, None] + cy[None, :])                 # [rx, ry] budget left for z^2
    return int(np.searchsorted(cz, rest.ravel(), side="right").sum())


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
            out.append(StageEstimate(f"building the training rays ({what})",
                                     grid + opt + RAY_DEVICE_BYTES * int(n_rays), big, big_what,
                                     ray_build_host(n_rays)))
        else:
            # resample: the old stage whole + max weights, keep masks + flags, links, rows;
            # then the new optimiser once the old links and scratch copies are gone
            up = prev + 6 * prev_n + 4 * V + row * n + max(4 * V, 2 * row * n + n - prev_drop)
            out.append(StageEstimate(f"the upsample to {what}", up + rays, big, big_what, 0))
        ckpt = 4 * V + 2 * row * n + (32 * (bg - 32 * g.batch_size) // 49 if bg else 0)
        out.append(StageEstimate(what, grid + opt + scratch + rays, big, big_what,
                                 ckpt))
        prev, prev_n, prev_drop = grid + opt + scratch, n, 4 * V + scratch
    return out


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


def memory(cfg, n_rays: int, caps, tuning=None, is_cpu: bool = True):
    """(stages, fix) of cfg.grid's run on ``n_rays`` rays on the device ``caps`` / ``tuning``."""
    return (grid_stages(cfg, n_rays, scratch_copies(is_cpu, tuning), int(caps.global_mem_size)),
            GRID_FIX)
