"""Benchmark inputs shared by tools/bench.py, the peers and the smoke test: grids, rays, counts.

Everything is deterministic (seeded) so clrf and every peer see identical inputs.

- ``make_grid_rows(reso, degree, occupancy, seed)``: links [R,R,R] int32 and compact rows
  (density [N], sh [N, 3(d+1)^2]) in clrf's layout. ``occupancy=1`` is dense (every voxel
  allocated); ``occupancy<1`` keeps a spherical shell around the centre whose thickness is
  chosen so that that fraction of voxels is allocated (a pruned grid looks like a surface,
  not like salt and pepper). Densities are scaled by 128/reso so the optical depth along a ray
  does not depend on the resolution and no ray reaches T_STOP (every marched sample counts).
- ``camera_rays(side)``: a side x side pinhole view of the whole box, pixels in row-major order
  (neighbouring rays are neighbouring pixels: coherent).
- ``random_rays(n)``: origins on a sphere around the box, directions through random points in
  it, in random order (incoherent).
- ``count_samples(links, origins, dirs, bbox, step)``: (segments, samples): segments inside
  the box, and samples whose cell has at least one allocated corner (the ones the kernels
  evaluate; the others are skipped as empty space).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.append(str(Path(__file__).resolve().parent.parent))   # the checkout's clrf only where none is installed
from clrf.references import reference  # noqa: E402
from clrf.testing.benchmark import camera_rays  # noqa: E402,F401  (same view as `clrf bench`)

BBOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
DENSITY_MAX_128 = 0.05   # raw density upper bound at 128^3 (optical depth ~5 along a diagonal)
SH_STD = 0.2             # std of the SH coefficients (colours stay mostly inside [0, 1])


def shell_mask(reso: int, occupancy: float) -> np.ndarray:
    """Boolean [R,R,R]: a spherical shell of radius 0.6 (box units [-1,1]) holding ~occupancy."""
    c = (np.arange(reso) + 0.5) / reso * 2 - 1
    r = np.sqrt(c[:, None, None] ** 2 + c[None, :, None] ** 2 + c[None, None, :] ** 2)
    d = np.abs(r - 0.6).ravel()
    k = max(1, int(round(occupancy * d.size)))
    thr = np.partition(d, k - 1)[k - 1]
    return (np.abs(r - 0.6) <= thr)


def make_grid_rows(reso: int, degree: int, occupancy: float = 1.0, seed: int = 0):
    """(links, density_rows, sh_rows) for clrf.SparseGrid.from_arrays; see module doc."""
    rng = np.random.default_rng(seed)
    C = 3 * (degree + 1) ** 2
    if occupancy >= 1.0:
        links = np.arange(reso ** 3, dtype=np.int32).reshape(reso, reso, reso)
    else:
        mask = shell_mask(reso, occupancy)
        links = np.full((reso,) * 3, -1, np.int32)
        links[mask] = np.arange(int(mask.sum()), dtype=np.int32)
    n = int((links >= 0).sum())
    dmax = DENSITY_MAX_128 * 128.0 / reso
    if occupancy < 1.0:
        dmax *= 4.0   # a thin shell: denser, still far from T_STOP
    density = rng.uniform(0.0, dmax, n).astype(np.float32)
    sh = np.empty((n, C), np.float32)
    chunk = 1 << 20
    for i in range(0, n, chunk):
        sh[i:i + chunk] = rng.standard_normal((min(chunk, n - i), C), dtype=np.float32) * SH_STD
    return links, density, sh


def dense_from_rows(links, density_rows, sh_rows):
    """Dense float64-ready views (zeros where empty) for the numpy reference."""
    mask = links >= 0
    dens = np.zeros(links.shape, np.float32)
    sh = np.zeros(links.shape + (sh_rows.shape[1],), np.float32)
    dens[mask] = density_rows[links[mask]]
    sh[mask] = sh_rows[links[mask]]
    return dens, sh


def random_rays(n: int, seed: int = 1):
    """origins, dirs float32 [n, 3]: from a sphere of radius 3 through random points of the box."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o *= 3.0 / np.linalg.norm(o, axis=1, keepdims=True)
    tgt = rng.uniform(-0.9, 0.9, (n, 3))
    return o.astype(np.float32), (tgt - o).astype(np.float32)


def make_rays(kind: str, n: int):
    """kind 'camera' (n rounded to a square) or 'random'."""
    if kind == "camera":
        return camera_rays(int(round(np.sqrt(n))))
    if kind == "random":
        return random_rays(n)
    raise ValueError(f"ray kind {kind!r}: expected 'camera' or 'random'")


def count_samples(links, origins, dirs, bbox, step, chunk_points: int = 1 << 20):
    """(segments, samples) marched by the kernels (see module doc); no early termination."""
    R = links.shape
    m = reference.march_setup(origins, dirs, R, bbox, step)
    nsteps = m["nsteps"]
    segments = int(nsteps.sum())
    samples = 0
    rays = np.nonzero(nsteps)[0]
    lo = 0
    while lo < rays.size:
        # take rays until about chunk_points points
        cum = np.cumsum(nsteps[rays[lo:]])
        hi = lo + max(1, int(np.searchsorted(cum, chunk_points)))
        rr = rays[lo:hi]
        ns = nsteps[rr]
        ray_of = np.repeat(rr, ns)
        k = np.arange(ns.sum()) - np.repeat(np.cumsum(ns) - ns, ns)
        dt, ln = m["dt"][ray_of], m["len"][ray_of]
        mid = 0.5 * (k * dt + np.minimum((k + 1) * dt, ln))
        p = m["p0"][ray_of] + mid[:, None] * m["dg"][ray_of]
        idx, _ = reference.trilerp_corners(p, R)
        occ = links[idx[..., 0], idx[..., 1], idx[..., 2]] >= 0
        samples += int(occ.any(axis=1).sum())
        lo = hi
    return segments, samples


def grid_bytes_per_sample(degree, backward):
    """Bytes requested per evaluated sample with no reuse between samples:
    8 links + 8 rows of (1 + SH_DIM) floats; fwd+bwd gathers twice and reads + writes the
    8 gradient rows."""
    row = 4 * (1 + 3 * (degree + 1) ** 2)
    fwd = 8 * 4 + 8 * row
    return 2 * fwd + 2 * 8 * row if backward else fwd


def grid_flop_per_sample(degree, backward):
    """Floating-point operations per evaluated sample (a model): interpolation
    8 x (1 + SH_DIM) FMAs, SH dot and colour 2 x SH_DIM, ~70 for weights, exp and compositing;
    fwd+bwd: the forward twice plus the corner-gradient accumulation (again 8 x (1 + SH_DIM)
    FMAs), the coefficient gradient 2 x SH_DIM and ~40 for the density gradient."""
    C = 3 * (degree + 1) ** 2
    fwd = 2 * 8 * (1 + C) + 2 * C + 70
    return 2 * fwd + 2 * 8 * (1 + C) + 2 * C + 40 if backward else fwd
