"""Per-ray set-up shared by the peers: the march parameters in float64 (clrf computes them in
double on devices with fp64), from clrf.references.reference so every peer marches the same segments."""
from __future__ import annotations

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
