"""Background model in Plenoxels training: the grid renderer's per-ray background (BG_PER_RAY)
against the float64 reference and finite differences, GridModel with an MSI background against
a float64 composition of the references, checkpoints, background off, and a real-scene smoke."""
import numpy as np
import pytest

import clrf
import pyopencl.array as cla
from clrf.grid.render import ray_exit_device
from clrf.testing import reference as ref
from clrf.testing.tolerances import (FD_ATOL, FD_RTOL, GRAD_ATOL, GRAD_RTOL, RENDER_ATOL,
                                     RENDER_RTOL)

from test_render import BBOX, assert_forward_matches, random_grid, random_rays


@pytest.mark.parametrize("shape,degree", [((1, 1, 1), 0), ((6, 5, 4), 2)])
def test_per_ray_forward_vs_reference(device, shape, degree):
    rng = np.random.default_rng(40 + degree)
    dens, sh = random_grid(rng, shape, degree, empty_frac=0.25 if np.prod(shape) > 8 else 0.0)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 150)
    bg = rng.uniform(0, 1, (150, 3)).astype(np.float32)
    out = clrf.render_rays(grid, o, d, step=0.37, background=bg)
    r = ref.render_forward(dens, sh, BBOX, o, d, 0.37, bg)
    assert_forward_matches(out, r)
    # rays that miss the box show their own background exactly
    miss = out["acc"] == 0
    assert miss.any() and np.array_equal(out["rgb"][miss], bg[miss])
    # a per-ray background equal to a constant one gives the constant path's bytes
    c = (0.2, 0.5, 0.9)
    same = clrf.render_rays(grid, o, d, step=0.37, background=np.tile(np.float32(c), (150, 1)))
    const = clrf.render_rays(grid, o, d, step=0.37, background=c)
    for k in const:
        assert np.array_equal(same[k], const[k]), k


def test_ray_exit_vs_reference(device):
    rng = np.random.default_rng(44)
    dens, sh = random_grid(rng, (3, 4, 5), 0)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 100)
    o[:10] = BBOX.mean(0)                      # origins inside the box: exit from inside
    q = device.queue
    t = ray_exit_device(grid, cla.to_device(q, o), cla.to_device(q, d), 0.5).get()[:100]
    r = ref.ray_exit(o, d, dens.shape, BBOX, 0.5)
    np.testing.assert_allclose(t, r, atol=RENDER_ATOL, rtol=RENDER_RTOL)
    assert np.all(t[:10] > 0) and np.any(t[10:] == 0)


@pytest.mark.parametrize("degree", [0, 2])
def test_per_ray_backward_vs_reference_and_fd(render_device, degree):
    """dL/d density, sh and the per-ray background (T_end g) on both backward code paths."""
    rng = np.random.default_rng(50 + degree)
    shape = (2, 3, 2)
    dens, sh = random_grid(rng, shape, degree, dens_hi=2.0)
    grid = clrf.SparseGrid.from_dense(render_device, dens, sh, BBOX)
    n = 24
    o, d = random_rays(rng, n, spread=2.0)
    g = rng.normal(size=(n, 3)).astype(np.float32)
    bg = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    kern = clrf.render_rays_backward(grid, o, d, g, step=0.3, background=bg)
    ana = ref.render_backward(dens, sh, BBOX, o, d, g, 0.3, bg)
    for k in ("density", "sh", "background"):
        np.testing.assert_allclose(kern[k], ana[k], atol=GRAD_ATOL, rtol=GRAD_RTOL, err_msg=k)
    for which, arr in (("density", dens), ("sh", sh), ("background", bg)):
        for flat in rng.choice(arr.size, 5, replace=False):
            idx = np.unravel_index(flat, arr.shape)
            fd = ref.finite_difference(dens, sh, BBOX, o, d, g, which, idx, step=0.3,
                                       background=bg)
            assert abs(fd - ana[which][idx]) <= FD_ATOL + FD_RTOL * abs(fd), (which, idx, fd)
    assert np.abs(ana["density"]).max() > 1e-3
    assert np.ptp(kern["background"] / np.where(g == 0, 1, g)) > 0.1   # T_end varies by ray


def test_per_ray_fused_mse_backward(render_device):
    """GRAD_MODE 1 (target colours in, MSE + beta prior) with a per-ray background: grid
    gradients and dL/d background = T_end g, g = 2 (pixel - target) loss_scale."""
    from clrf.grid.render import render_backward_device
    rng = np.random.default_rng(60)
    dens, sh = random_grid(rng, (5, 4, 6), 1, empty_frac=0.3, dens_hi=1.5)
    grid = clrf.SparseGrid.from_dense(render_device, dens, sh, BBOX)
    n = 200
    o, d = random_rays(rng, n)
    bg = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    target = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    ls, bs = 1.0 / (3 * n), 1e-2 / n
    q = render_device.queue
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    sq = cla.empty(q, n, np.float32)
    gbg = render_backward_device(grid, cla.to_device(q, o), cla.to_device(q, d),
                                 cla.to_device(q, target), 0.5, cla.to_device(q, bg), gd, gs,
                                 grad_mode=1, loss_scale=ls, ray_out=sq, beta_scale=bs)
    f = ref.render_forward(dens, sh, BBOX, o, d, 0.5, bg, record=True)
    g = 2 * ls * (f["rgb"] - target)
    ana = ref.render_backward(dens, sh, BBOX, o, d, g, 0.5, bg,
                              grad_T=ref.beta_grad_T(f["T_end"], bs))
    kd, ks = grid.rows_to_dense(gd.get(), gs.get())
    np.testing.assert_allclose(sq.get(), np.sum((f["rgb"] - target) ** 2, 1), atol=RENDER_ATOL,
                               rtol=RENDER_RTOL)
    np.testing.assert_allclose(kd, ana["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(ks, ana["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(gbg.get(), ana["background"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
