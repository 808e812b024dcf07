"""What the peers share: the per-ray set-up (the march parameters in float64, as clrf computes
them in double on devices with fp64, from clrf.references.reference, so every peer marches the
same segments) and one Taichi initialisation for all the Taichi peers of a process."""
from __future__ import annotations

import os

import numpy as np

from clrf.references import reference

T_STOP = reference.T_STOP
COLOR_OFFSET = reference.COLOR_OFFSET


def ray_setup(origins, dirs, reso, bbox, step, degree):
    """dict of float32/int32 per-ray arrays: p0 [n,3], dg [n,3], dt, len, t0 [n], nsteps [n],
    Y [n, (d+1)^2] (SH basis at the unit direction)."""
    m = reference.march_setup(origins, dirs, reso, bbox, step)
    return {"p0": m["p0"].astype(np.float32), "dg": m["dg"].astype(np.float32),
            "dt": m["dt"].astype(np.float32), "len": m["len"].astype(np.float32),
            "t0": m["t0"].astype(np.float32),
            "nsteps": np.where(m["hit"], m["nsteps"], 0).astype(np.int32),
            "Y": reference.sh_basis(m["dir"], degree).astype(np.float32)}


_TAICHI_READY = False


def init_taichi():
    """ti.init once per process for every Taichi peer: the CPU backend on all cores, float32,
    warnings only (a second ti.init would reset the runtime and drop compiled kernels)."""
    global _TAICHI_READY
    if not _TAICHI_READY:
        import taichi as ti
        ti.init(arch=ti.cpu, cpu_max_num_threads=os.cpu_count() or 1, default_fp=ti.f32,
                log_level=ti.WARN)
        _TAICHI_READY = True
