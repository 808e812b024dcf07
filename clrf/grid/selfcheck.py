"""The grid's gradient self-check: does this device and driver compute the grid backward
correctly?

A driver can compile clrf's kernels and still compute wrong gradients (a miscompile, or a
scheduling assumption that its implementation breaks), and training on such gradients runs
for minutes without an error. So once per device, driver and kernel source, clrf renders a
small grid forward and backward with the gradient path the device's tuning chose and checks
the result:

- a closed form: a grid of uniform density sigma and one constant colour c (SH degree 0) seen
  along rays that cross the whole box: the quadrature telescopes, so the ray's colour is
  c (1 - exp(-sigma L)) + bg exp(-sigma L) exactly for the path length L in the box, and the
  sums over all voxels of the gradients are d/dsigma = L exp(-sigma L) (c - bg) . g and
  d/dc = (1 - exp(-sigma L)) g (the trilinear weights of every sample sum to one);
- the float64 reference (clrf/references/reference.py) on a random grid with many rays that share
  cells, so that the concurrent gradient adds (locks, scratch copies, atomics) are exercised.

A path that fails is replaced by the float-atomic path when that one passes (with a warning);
a device on which both fail is never chosen by default, and training on it stops with a
message that names the driver. The check is registered with the runtime's verdict cache
(clrf/runtime/selfcheck.py) when clrf.grid is imported: results are cached next to the probe
figures (``$XDG_CACHE_HOME/clrf/selfcheck.json``), keyed by the probe's device key, the
tuning's gradient path and a hash of the kernel sources, and the device choice reads them.
"""
from __future__ import annotations

import numpy as np

from ..runtime import selfcheck as verdicts
from ..runtime.selfcheck import CheckResult, path_name  # noqa: F401 - re-exported

CHECK_VERSION = 1
SOURCES = ("grid_render.cl", "march.h", "volrend.h", "common.h", "sh.h", "ray.h", "reduce.h")
RTOL, ATOL = 2e-3, 2e-5      # float32 sums over a few hundred samples against float64
COLOR_OFFSET = 0.5           # the kernels' colour: SH sum + 0.5 (clrf/references/reference.py)


def _closed_form(device) -> str:
    """'' when the uniform-grid gradients match the closed form (module doc), else why not."""
    from .grid import SparseGrid
    from .render import render_rays, render_rays_backward
    sigma, c0, bg = 0.8, 0.7, 0.2
    reso = (6, 5, 4)
    bbox = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    y00 = 0.28209479177387814      # SH degree-0 basis: colour = y00 * coef + COLOR_OFFSET
    dens = np.full(reso, sigma, np.float32)
    sh = np.full(reso + (3,), (c0 - COLOR_OFFSET) / y00, np.float32)
    grid = SparseGrid.from_dense(device, dens, sh, bbox)
    # rays along x through voxel centres' interior, from outside the box to beyond it
    ys, zs = np.meshgrid(np.linspace(-0.6, 0.6, 8), np.linspace(-0.5, 0.5, 8))
    n = ys.size
    o = np.stack([np.full(n, -3.0), ys.ravel(), zs.ravel()], 1).astype(np.float32)
    d = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (n, 1))
    out = render_rays(grid, o, d, step=0.25, background=(bg, bg, bg))
    T = 1.0 - out["acc"]
    # the path length the kernel integrated, from its own transmittance (uniform density)
    L = -np.log(np.clip(T.astype(np.float64), 1e-30, 1.0)) / sigma
    if not (np.all(np.isfinite(L)) and np.ptp(L) < 1e-3 * max(L.mean(), 1e-9) and L.mean() > 0):
        return f"uniform grid: path lengths differ between parallel rays ({L.min():.4g}..{L.max():.4g})"
    want_rgb = c0 * (1 - T) + bg * T
    if not np.allclose(out["rgb"], want_rgb[:, None], rtol=RTOL, atol=ATOL):
        return "uniform grid: forward colour differs from c (1 - T) + bg T"
    rng = np.random.default_rng(7)
    g = rng.normal(size=(n, 3)).astype(np.float32)
    grads = render_rays_backward(grid, o, d, g, step=0.25, background=(bg, bg, bg))
    Lm = float(L.mean())
    Te = np.exp(-sigma * Lm)
    want_dsigma = float(np.sum(Lm * Te * (c0 - bg) * g.astype(np.float64)))
    want_dc = (1 - Te) * g.astype(np.float64).sum(axis=0) * y00       # per channel
    got_dsigma = float(grads["density"].astype(np.float64).sum())
    got_dc = grads["sh"].astype(np.float64).reshape(-1, 3).sum(axis=0)
    if not np.isclose(got_dsigma, want_dsigma, rtol=RTOL, atol=ATOL * n):
        return (f"uniform grid: sum of density gradients {got_dsigma:.6g}, closed form "
                f"{want_dsigma:.6g}")
    if not np.allclose(got_dc, want_dc, rtol=RTOL, atol=ATOL * n):
        return f"uniform grid: sum of colour gradients {got_dc}, closed form {want_dc}"
    return ""


def _reference(device) -> str:
    """'' when a random grid's gradients match the float64 reference, else why not."""
    from ..references import reference as ref
    from .grid import SparseGrid
    from .render import render_rays_backward
    rng = np.random.default_rng(11)
    reso = (5, 4, 6)
    dens = rng.uniform(0.0, 2.0, reso).astype(np.float32)
    dens[rng.random(reso) < 0.2] = 0.0
    sh = rng.normal(0.0, 0.5, reso + (12,)).astype(np.float32)        # SH degree 1
    bbox = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    grid = SparseGrid.from_dense(device, dens, sh, bbox)
    n = 96                      # many rays through few cells: concurrent adds to shared rows
    o = rng.uniform(-0.3, 0.3, (n, 3)) + np.array([0.0, 0.0, -3.0])
    tgt = rng.uniform(-0.5, 0.5, (n, 3))
    d = tgt - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o, d = o.astype(np.float32), d.astype(np.float32)
    g = rng.normal(size=(n, 3)).astype(np.float32)
    bg = (0.3, 0.6, 0.1)
    got = render_rays_backward(grid, o, d, g, step=0.5, background=bg)
    want = ref.render_backward(dens, sh, bbox, o, d, g, 0.5, bg)
    for name in ("density", "sh"):
        a, b = got[name].astype(np.float64), np.asarray(want[name], np.float64)
        bad = ~np.isclose(a, b, rtol=RTOL, atol=ATOL * 10)
        if bad.any():
            i = np.flatnonzero(bad)[0]
            return (f"random grid: {bad.sum()} of {bad.size} {name} gradients differ from the "
                    f"float64 reference (first: {a.flat[i]:.6g} vs {b.flat[i]:.6g})")
    return ""


def _why_not(device) -> str:
    return _closed_form(device) or _reference(device)


CHECK = verdicts.register(verdicts.GradientCheck(SOURCES, CHECK_VERSION, _why_not,
                                                   "the grid backward"))


def run_check(device) -> CheckResult:
    """Run both checks on ``device`` with its own tuning now (no cache)."""
    return verdicts.run_check(device, CHECK)


def gradient_check(device, refresh: bool = False) -> CheckResult:
    """The cached check of ``device``'s gradient path, measured when missing."""
    return verdicts.gradient_check(device, CHECK, refresh, run=lambda d: run_check(d))


def known_wrong(cl_device) -> str | None:
    """Why ``cl_device`` is known (from the cache only; nothing is run) to compute wrong
    gradients on its float-atomic path with the current kernels, or None."""
    return verdicts.known_wrong(cl_device, [CHECK])


def ensure_trusted(device, log=None):
    """Before training: this check's verdict for ``device`` (clrf.runtime.selfcheck
    .ensure_trusted: the float-atomic path replaces a failing one, else DeviceError)."""
    from ..runtime.trust import ensure_trusted as ensure
    return ensure(device, [CHECK], log)[0]
