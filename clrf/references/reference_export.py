"""Float64 twin of cl/export.cl (grid fields at points), for the tests."""
from __future__ import annotations

import numpy as np

from .reference import COLOR_OFFSET, SH_C0, trilerp_corners


def sample_fields(density, sh, bbox, points):
    """(sigma [n], rgb [n, 3]) at world points [n, 3] of dense arrays density [X,Y,Z] and
    sh [X,Y,Z,3B]: sigma = sum_c w_c density_c (raw, no ReLU), rgb = max(SH_C0 * sum_c w_c
    band0_c + COLOR_OFFSET, 0) with band0 the degree-0 coefficient of each channel."""
    density = np.asarray(density, np.float64)
    sh = np.asarray(sh, np.float64)
    bbox = np.asarray(bbox, np.float64)
    reso = np.array(density.shape)
    u = (np.asarray(points, np.float64) - bbox[0]) * reso / (bbox[1] - bbox[0])
    idx, w = trilerp_corners(u, reso)
    i, j, k = idx[..., 0], idx[..., 1], idx[..., 2]
    sigma = np.sum(w * density[i, j, k], 1)
    B = sh.shape[-1] // 3
    band0 = sh[..., [0, B, 2 * B]]                                  # [X, Y, Z, 3]
    rgb = np.maximum(SH_C0 * np.einsum("nc,ncj->nj", w, band0[i, j, k]) + COLOR_OFFSET, 0.0)
    return sigma, rgb
