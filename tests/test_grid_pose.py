"""Each ray's dL/d(origin, direction) from the grid's backward (GRID_POSE_GRAD,
cl/grid_render.cl; grid.pose_opt) against its float64 twin (clrf/references/reference.py
ray_grad) on both kernel shapes, the twin against central differences (of the render with its
sample distances held, and of the whole render where the march's samples do not move with the
ray), and stiff and degenerate rays (the model: tests/test_grid_corrections.py)."""
import numpy as np
import pyopencl.array as cla
import pytest

import clrf
from clrf.references import reference as ref
from clrf.testing import tolerances as tol

BBOX = np.array([[-1.0, -1.2, -0.9], [1.1, 1.0, 1.0]])


def _up(dev, a, dtype=np.float32):
    return cla.to_device(dev.queue, np.ascontiguousarray(a, dtype))


def random_grid(rng, shape, degree, empty_frac=0.0, dens_hi=3.0):
    C = 3 * (degree + 1) ** 2
    dens = rng.uniform(0.05, dens_hi, shape).astype(np.float32)
    sh = rng.normal(0, 0.3, shape + (C,)).astype(np.float32)
    if empty_frac:
        empty = rng.random(shape) < empty_frac
        dens[empty] = 0
        sh[empty] = 0
    return dens, sh


def random_rays(rng, n, bbox=BBOX, spread=2.5):
    """Rays from points around the box aimed at points inside it (most hit, some miss)."""
    c = bbox.mean(0)
    o = c + rng.normal(0, spread, (n, 3))
    target = c + rng.uniform(-0.7, 0.7, (n, 3)) * (bbox[1] - bbox[0])
    return o.astype(np.float32), (target - o).astype(np.float32)


def kernel_ray_grad(device, dens, sh, bbox, o, d, g, step, bg):
    grid = clrf.SparseGrid.from_dense(device, dens, sh, bbox)
    return clrf.render_rays_backward(grid, o, d, g, step=step, background=bg,
                                     ray_grad=True)["ray_grad"]


def assert_rays_match(got, want, mag):
    """Per ray, within GRID_RAY_GRAD_RTOL of the magnitude of its terms (``mag``)."""
    err = np.abs(got - want).max(axis=1)
    bad = err > tol.GRID_RAY_GRAD_RTOL * mag
    assert not bad.any(), (np.flatnonzero(bad)[:5], err[bad][:5], mag[bad][:5])


# ---- the kernel against the twin ---------------------------------------------------------
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ray_grad_matches_twin(render_device, degree):
    """60 rays (some missing the box) through a grid with empty voxels, on both backward
    shapes (render_device): each ray's dL/d(o, d) equals the twin's; the rays that miss get
    exact zeros, and those the twin gives a gradient get one."""
    rng = np.random.default_rng(40 + degree)
    dens, sh = random_grid(rng, (6, 5, 4), degree, empty_frac=0.25)
    o, d = random_rays(rng, 60)
    g = rng.normal(size=(60, 3)).astype(np.float32)
    bg = (0.2, 0.5, 0.9)
    got = kernel_ray_grad(render_device, dens, sh, BBOX, o, d, g, 0.37, bg)
    t, delta, live = ref.held_samples(dens, sh, BBOX, o, d, 0.37)
    _, want, mag = ref.render_held(dens, sh, BBOX, o, d, t, delta, live, bg, g, magnitude=True)
    assert_rays_match(got, want, mag)
    missed = ~live.any(axis=1)
    assert missed.any() and (~missed).sum() > 30
    assert np.all(got[missed] == 0)
    np.testing.assert_array_equal(got.any(axis=1), want.any(axis=1))
    assert want.any(axis=1).sum() > 30


def test_ray_grad_with_a_background_per_ray(device):
    """BG_PER_RAY (the MSI's build): the background's share in each ray's remaining radiance
    enters dL/dsigma and so the camera gradient (the background's own dependence on the ray
    is not part of it)."""
    rng = np.random.default_rng(7)
    dens, sh = random_grid(rng, (5, 4, 6), 2, empty_frac=0.2)
    o, d = random_rays(rng, 40)
    g = rng.normal(size=(40, 3)).astype(np.float32)
    bg = rng.uniform(0, 1, (40, 3)).astype(np.float32)
    got = kernel_ray_grad(device, dens, sh, BBOX, o, d, g, 0.4, bg)
    t, delta, live = ref.held_samples(dens, sh, BBOX, o, d, 0.4)
    _, want, mag = ref.render_held(dens, sh, BBOX, o, d, t, delta, live, bg, g, magnitude=True)
    assert_rays_match(got, want, mag)


# ---- the twin against central differences -----------------------------------------------
def _central(fn, x, h):
    out = []
    for j in range(x.shape[1]):
        e = np.zeros_like(x)
        e[:, j] = h
        out.append((fn(x + e) - fn(x - e)) / (2 * h))
    return np.stack(out, axis=1)


@pytest.mark.parametrize("degree", [0, 2, 3])
def test_twin_matches_differences_of_the_held_render(degree):
    """The twin's analytic dL/d(o, d) against central differences (float64) of the render
    whose sample distances along the unit direction are held (render_held): what the kernel
    differentiates, rays entering the box from outside, |d| != 1."""
    rng = np.random.default_rng(50 + degree)
    dens, sh = random_grid(rng, (5, 6, 4), degree, empty_frac=0.2)
    o, d = random_rays(rng, 30)
    o, d = o.astype(np.float64), 1.7 * d.astype(np.float64)
    g = rng.normal(size=(30, 3))
    bg = (0.3, 0.6, 0.1)
    t, delta, live = ref.held_samples(dens, sh, BBOX, o, d, 0.31)
    _, ana = ref.render_held(dens, sh, BBOX, o, d, t, delta, live, bg, g)

    def loss(oo, dd):
        return np.sum(g * ref.render_held(dens, sh, BBOX, oo, dd, t, delta, live, bg), axis=1)
    h = 1e-7
    fd = np.concatenate([_central(lambda x: loss(x, d), o, h),
                         _central(lambda x: loss(o, x), d, h)], axis=1)
    assert np.abs(ana).max() > 0.1
    np.testing.assert_allclose(ana, fd, atol=tol.FD_ATOL, rtol=tol.FD_RTOL)


def _inner_scene(rng, degree, n):
    """A cube grid (isotropic scale) whose two outer voxel shells are empty, and rays starting
    inside the box: the march starts at the origin (t0 = 0) with a step that does not depend
    on the ray, and the samples that move in or out at the far end see zero density, so the
    whole render is the held render: its differences must equal the held gradient."""
    shape = (9, 9, 9)
    dens, sh = random_grid(rng, shape, degree, dens_hi=1.5)
    inner = np.zeros(shape, bool)
    inner[2:-2, 2:-2, 2:-2] = True
    dens[~inner] = 0
    sh[~inner] = 0
    bbox = np.array([[-1.0] * 3, [1.0] * 3])
    o = rng.uniform(-0.5, 0.5, (n, 3))
    d = rng.normal(size=(n, 3))
    return dens, sh, bbox, o, d


@pytest.mark.parametrize("degree", [1, 3])
def test_twin_matches_differences_of_the_whole_render(degree):
    """Central differences of the whole float64 render (render_forward, its own march,
    no termination) in origin and direction equal the twin's gradient on rays whose samples
    the march does not re-place (_inner_scene)."""
    rng = np.random.default_rng(60 + degree)
    dens, sh, bbox, o, d = _inner_scene(rng, degree, 25)
    g = rng.normal(size=(25, 3))
    bg = (0.9, 0.2, 0.4)
    ana = ref.ray_grad(dens, sh, bbox, o, d, g, 0.5, bg, t_stop=0.0)

    def loss(oo, dd):
        return np.sum(g * ref.render_forward(dens, sh, bbox, oo, dd, 0.5, bg, 0.0)["rgb"],
                      axis=1)
    h = 1e-7
    fd = np.concatenate([_central(lambda x: loss(x, d), o, h),
                         _central(lambda x: loss(o, x), d, h)], axis=1)
    assert np.abs(ana).max() > 0.1
    np.testing.assert_allclose(ana, fd, atol=tol.FD_ATOL, rtol=tol.FD_RTOL)


def test_kernel_matches_twin_on_rays_from_inside(device):
    """The kernel on _inner_scene's rays (the march starting at the origin) against the twin."""
    rng = np.random.default_rng(70)
    dens, sh, bbox, o, d = _inner_scene(rng, 2, 40)
    g = rng.normal(size=(40, 3)).astype(np.float32)
    o, d = o.astype(np.float32), d.astype(np.float32)
    got = kernel_ray_grad(device, dens, sh, bbox, o, d, g, 0.5, (0.0, 0.0, 0.0))
    t, delta, live = ref.held_samples(dens, sh, bbox, o, d, 0.5)
    _, want, mag = ref.render_held(dens, sh, bbox, o, d, t, delta, live, (0, 0, 0), g,
                                   magnitude=True)
    assert_rays_match(got, want, mag)


# ---- stiff and degenerate rays -----------------------------------------------------------
@pytest.mark.parametrize("scale", [0.0, 1e-3, 1.0, 1e3, 1e10, 1e20, 1e30])
def test_finite_across_density_scales(device, scale):
    """Densities from 0 to 1e30 (opaque at the first sample): every ray's gradient finite."""
    rng = np.random.default_rng(80)
    dens, sh = random_grid(rng, (5, 5, 5), 2)
    o, d = random_rays(rng, 50)
    g = rng.normal(size=(50, 3)).astype(np.float32)
    got = kernel_ray_grad(device, (dens * scale).astype(np.float32), sh, BBOX, o, d, g, 0.5,
                          (1.0, 1.0, 1.0))
    assert np.all(np.isfinite(got))


def test_homogeneous_huge_density_matches_twin(device):
    """A homogeneous density of 1e30: no density gradient inside the box, each ray opaque at
    its first sample, whose colour varies: the gradient is that of the first sample's colour
    and equals the twin's (no inf * 0 from the opaque sample)."""
    rng = np.random.default_rng(81)
    shape = (5, 4, 6)
    dens = np.full(shape, 1e30, np.float32)
    sh = rng.normal(0, 0.3, shape + (12,)).astype(np.float32)
    o, d = random_rays(rng, 50)
    g = rng.normal(size=(50, 3)).astype(np.float32)
    got = kernel_ray_grad(device, dens, sh, BBOX, o, d, g, 0.5, (1.0, 1.0, 1.0))
    t, delta, live = ref.held_samples(dens, sh, BBOX, o, d, 0.5)
    _, want, mag = ref.render_held(dens, sh, BBOX, o, d, t, delta, live, (1, 1, 1), g,
                                   magnitude=True)
    assert np.all(np.isfinite(got)) and np.abs(want).max() > 0
    assert_rays_match(got, want, mag)


def test_tiny_step_and_axis_parallel_rays_match_twin(device):
    """A step of 0.01 voxel (~900 samples a ray) and rays parallel to each axis (an
    infinite slab distance on the other two): the twin's. (Not through voxel-centre planes:
    there the interpolation has a kink across the ray, and which side's slope a float32
    position takes is a matter of rounding, not a gradient to compare.)"""
    rng = np.random.default_rng(82)
    dens, sh = random_grid(rng, (6, 5, 4), 1, empty_frac=0.2, dens_hi=0.5)
    n = 24
    d = np.zeros((n, 3), np.float32)
    d[np.arange(n), np.arange(n) % 3] = np.where(np.arange(n) % 2, 1.0, -2.0)
    o = (BBOX.mean(0) + rng.uniform(-0.8, 0.8, (n, 3)) * (BBOX[1] - BBOX[0]) / 2)
    o[:n // 2][d[:n // 2] != 0] = 0.0           # half start inside the box,
    o[n // 2:][d[n // 2:] != 0] = -3.0 * d[n // 2:][d[n // 2:] != 0]   # half outside it
    o = o.astype(np.float32)
    g = rng.normal(size=(n, 3)).astype(np.float32)
    for step, rays in ((0.01, slice(0, 8)), (0.5, slice(None))):
        oo, dd, gg = o[rays], d[rays], g[rays]
        got = kernel_ray_grad(device, dens, sh, BBOX, oo, dd, gg, step, (0.5, 0.5, 0.5))
        t, delta, live = ref.held_samples(dens, sh, BBOX, oo, dd, step)
        _, want, mag = ref.render_held(dens, sh, BBOX, oo, dd, t, delta, live, (0.5,) * 3, gg,
                                       magnitude=True)
        assert_rays_match(got, want, mag)
        assert np.abs(got).max() > 0


def test_missing_zero_and_empty_rays_get_zeros(device):
    """Rays that miss the box and every ray of an empty grid: exact zeros; a direction of
    length 1e-19 (whose square underflows: scaled before its length is taken): the twin's
    (dL/dd ~ 1e19). A subnormal |d| would give a dL/dd past float32's range, and that is
    its value."""
    rng = np.random.default_rng(83)
    dens, sh = random_grid(rng, (4, 4, 4), 2)
    o = np.array([[5.0, 5.0, 5.0], [0.0, 0.0, -5.0], [0.1, 0.0, 0.0]], np.float32)
    d = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [3e-20, -5e-20, 8e-20]], np.float32)
    g = np.ones((3, 3), np.float32)
    got = kernel_ray_grad(device, dens, sh, BBOX, o, d, g, 0.5, (1, 1, 1))
    assert np.all(got[:2] == 0)
    t, delta, live = ref.held_samples(dens, sh, BBOX, o, d, 0.5)
    _, want, mag = ref.render_held(dens, sh, BBOX, o, d, t, delta, live, (1, 1, 1), g,
                                   magnitude=True)
    assert np.abs(want[2, 3:]).min() > 1e15      # dL/dd ~ 1 / |d|, still a float32
    assert_rays_match(got, want, mag)
    o2, d2 = random_rays(rng, 20)
    zero = kernel_ray_grad(device, np.zeros_like(dens), np.zeros_like(sh), BBOX, o2, d2,
                           np.ones((20, 3), np.float32), 0.5, (1, 1, 1))
    assert np.all(zero == 0)


@pytest.mark.parametrize("order", [0, 1], ids=["given", "sorted"])
def test_training_loss_and_ray_order_match_twin(render_device, order):
    """The training step's call (render_backward_device, GRAD_MODE 1: the MSE against targets
    with loss_scale and the beta prior on T_end) with each ray's gradient, rays rendered in the
    given order or sorted (RAY_ORDER, dense grids): the twin's gradient of loss_scale |rgb -
    target|^2 + the prior, each ray's at its own index."""
    from clrf.grid.render import ray_order, render_backward_device
    rng = np.random.default_rng(90 + order)
    dens, sh = random_grid(rng, (7, 6, 8), 2, dens_hi=1.0)
    n = 300
    o, d = random_rays(rng, n)
    target = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    dev = render_device.with_tuning(ray_order=order)
    grid = clrf.SparseGrid.from_dense(dev, dens, sh, BBOX)
    assert (ray_order(grid, _up(dev, o), _up(dev, d), 0.5) is not None) == bool(order)
    s, beta = 0.7, 0.05
    rg = cla.empty(dev.queue, (n, 6), np.float32)
    gd = cla.zeros(dev.queue, grid.density.shape, np.float32)
    gs = cla.zeros(dev.queue, grid.sh.shape, np.float32)
    render_backward_device(grid, _up(dev, o), _up(dev, d), _up(dev, target), 0.5, (0.1, 0.2, 0.3),
                           gd, gs, grad_mode=1, loss_scale=s, beta_scale=beta, ray_grad=rg)
    f = ref.render_forward(dens, sh, BBOX, o, d, 0.5, (0.1, 0.2, 0.3), record=True)
    g = 2 * s * (f["rgb"] - target)
    gT = ref.beta_grad_T(f["T_end"], beta)
    t, delta, live = ref.held_samples(dens, sh, BBOX, o, d, 0.5)
    _, want, mag = ref.render_held(dens, sh, BBOX, o, d, t, delta, live, (0.1, 0.2, 0.3), g,
                                   gT, magnitude=True)
    assert np.abs(want).max() > 0.1
    assert_rays_match(rg.get(), want, mag)
