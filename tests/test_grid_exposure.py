"""The grid backward with each ray's image transform in its loss (RAY_EXPOSURE,
cl/grid_render.cl; grid.exposure's one-march step) against the float64 twin (the render of
clrf/references/reference.py under clrf/references/reference_exposure.py's transform) on both
kernel shapes, clamped and not, on a constant and a per-ray background; the twin's chain
against central differences; stiff rays; the rows' gradient from what the kernel writes (the
model's step: tests/test_grid_corrections.py)."""
import numpy as np
import pyopencl.array as cla
import pytest

import clrf
from clrf.references import reference as ref
from clrf.references import reference_exposure as rex
from clrf.testing import tolerances as tol

from test_grid_pose import BBOX, random_grid, random_rays

V, PIXELS = 3, 20


def _up(dev, a, dtype=np.float32):
    return cla.to_device(dev.queue, np.ascontiguousarray(a, dtype))


def _rows(rng, gain_hi=1.0):
    """V transforms near the identity; with gain_hi > 1 the diagonals drawn up to it (so that
    bright pixels leave [0, 1])."""
    P = np.tile(rex.IDENTITY, (V, 1)) + rng.normal(0, 0.08, (V, 12))
    P[:, [0, 4, 8]] = rng.uniform(0.6, gain_hi, (V, 3)) if gain_hi > 1 else P[:, [0, 4, 8]]
    return P.astype(np.float32)


def _fused(device, dens, sh, o, d, target, index, P, step, bg, clip, scale):
    """The kernel's outputs: (grid gradients as dense arrays, per-ray loss terms, state,
    residuals, rows' gradient, grad_bg or None)."""
    from clrf.corrections.exposure import RayExposure
    from clrf.grid.render import render_backward_device
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    q = device.queue
    exp = RayExposure(device, V, PIXELS, lr=1e-3, reg=0.0, clip=clip)
    exp.P.set(P)
    idx = _up(device, index, np.int32)
    xf = exp.in_backward(idx)
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    sq = cla.empty(q, len(o), np.float32)
    bg_arg = _up(device, bg) if np.ndim(bg) == 2 else bg
    gbg = render_backward_device(grid, _up(device, o), _up(device, d), _up(device, target),
                                 step, bg_arg, gd, gs, grad_mode=1, loss_scale=scale,
                                 ray_out=sq, exposure=xf)
    state, resid = xf.state.get(), xf.resid.get()
    exp.backward(xf.state, (0.0, 0.0, 0.0), idx, scale)
    dd, ds = grid.rows_to_dense(gd.get(), gs.get())
    return dd, ds, sq.get(), state, resid, exp.grad.get(), None if gbg is None else gbg.get()


def _twin(dens, sh, o, d, target, index, P, step, bg, clip):
    """(dL/dpixel / (2 s) = A^T r, r, per-ray terms, pixel, T_end) in float64."""
    f = ref.render_forward(dens, sh, BBOX, o, d, step, bg, record=True)
    pix = f["rgb"]
    state = np.concatenate([pix, np.ones((len(pix), 5))], axis=1)
    r, eff, sq, _ = rex.rays(state, (0, 0, 0), target, P, index, PIXELS, masked=False,
                             clip=clip)
    return pix - eff, r, sq, state, f["T_end"]


@pytest.mark.parametrize("clip", [False, True], ids=["plain", "clip"])
@pytest.mark.parametrize("per_ray", [False, True], ids=["bg", "bg_per_ray"])
def test_fused_transform_matches_the_twin(render_device, clip, per_ray):
    """50 rays (some missing the box) of three images through a grid with empty voxels, gains
    up to 3 with clip (so that channels leave [0, 1]): the grid's gradients, each ray's loss
    term, the state and residuals the kernel writes, the rows' gradient from them and, on a
    per-ray background, the background's gradient, against the twin."""
    rng = np.random.default_rng(60 + 2 * clip + per_ray)
    dens, sh = random_grid(rng, (6, 5, 4), 1, empty_frac=0.25)
    o, d = random_rays(rng, 50)
    index = rng.permutation(V * PIXELS)[:50]
    P = _rows(rng, 3.0 if clip else 1.0)
    target = rng.uniform(0, 1, (50, 3)).astype(np.float32)
    bg = rng.uniform(0, 1, (50, 3)).astype(np.float32) if per_ray else (0.2, 0.5, 0.9)
    s = 1.0 / 150
    dd, ds, sq, state, resid, grow, gbg = _fused(render_device, dens, sh, o, d, target, index,
                                                 P, 0.37, bg, clip, s)
    g, r, sq64, state64, T_end = _twin(dens, sh, o, d, target, index, P.astype(np.float64),
                                       0.37, bg, clip)
    if clip:   # some channels clipped, and they pass nothing
        assert (r == 0).sum() > 5 and (resid == 0).sum() >= (r == 0).sum()
    np.testing.assert_allclose(state[:, :4], state64[:, :4], atol=tol.RENDER_ATOL)
    np.testing.assert_allclose(sq, sq64, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(resid, r, atol=1e-5)
    want = ref.render_backward(dens, sh, BBOX, o, d, g, 0.37, bg)
    np.testing.assert_allclose(dd / (2 * s), want["density"], atol=tol.GRAD_ATOL,
                               rtol=tol.GRAD_RTOL)
    np.testing.assert_allclose(ds / (2 * s), want["sh"], atol=tol.GRAD_ATOL, rtol=tol.GRAD_RTOL)
    assert np.abs(want["density"]).max() > 500 * tol.GRAD_ATOL   # not a test of zeros
    np.testing.assert_allclose(grow, rex.rays_grad(state64, (0, 0, 0), r, P, index, PIXELS, s,
                                                   0.0, masked=False), atol=1e-5)
    if per_ray:
        np.testing.assert_allclose(gbg, 2 * s * T_end[:, None] * g, atol=1e-6)
    else:
        assert gbg is None


@pytest.mark.parametrize("clip", [False, True], ids=["plain", "clip"])
def test_one_march_is_the_two_pass_step(render_device, clip):
    """The step the model takes where the camera also takes one (the pixel rendered first,
    RayExposure.forward's target eff = pixel - A^T r, the backward of eff without the
    transform) gives the grid, the loss terms and the rows the one-march step's values."""
    from clrf.corrections.exposure import RayExposure
    from clrf.corrections import RAY_STATE as STATE
    from clrf.grid.model import pixel_state
    from clrf.grid.render import render_backward_device, render_forward_device
    rng = np.random.default_rng(67 + clip)
    dens, sh = random_grid(rng, (6, 5, 4), 2, empty_frac=0.25)
    o, d = random_rays(rng, 50)
    index = rng.permutation(V * PIXELS)[:50]
    P = _rows(rng, 3.0 if clip else 1.0)
    target = rng.uniform(0, 1, (50, 3)).astype(np.float32)
    bg, s = (0.2, 0.5, 0.9), 1.0 / 150
    one = _fused(render_device, dens, sh, o, d, target, index, P, 0.37, bg, clip, s)
    dev, q = render_device, render_device.queue
    grid = clrf.SparseGrid.from_dense(dev, dens, sh, BBOX)
    exp = RayExposure(dev, V, PIXELS, lr=1e-3, reg=0.0, clip=clip)
    exp.P.set(P)
    od, dd_, idx = _up(dev, o), _up(dev, d), _up(dev, index, np.int32)
    pixel = render_forward_device(grid, od, dd_, 0.37, bg)["rgb"]
    state = pixel_state(dev, pixel, cla.empty(q, (50, STATE), np.float32))
    eff, sq = exp.forward(state, (0.0, 0.0, 0.0), _up(dev, target), idx)
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    render_backward_device(grid, od, dd_, eff, 0.37, bg, gd, gs, grad_mode=1, loss_scale=s)
    exp.backward(state, (0.0, 0.0, 0.0), idx, s)
    two = (*grid.rows_to_dense(gd.get(), gs.get()), sq.get(), exp.grad.get())
    for a, b in zip((one[0], one[1], one[2], one[5]), two):
        assert np.abs(b).max() > 0
        np.testing.assert_allclose(a, b, rtol=0, atol=2e-6 * np.abs(b).max())


def test_the_twins_chain_matches_central_differences():
    """The gradient the kernel is held to (the float64 render's backward of A^T r) is the
    central difference of the float64 loss s sum |A pixel + b - target|^2 in the densities
    and SH coefficients of occupied voxels."""
    rng = np.random.default_rng(64)
    dens, sh = random_grid(rng, (5, 4, 4), 1, empty_frac=0.2)
    dens, sh = dens.astype(np.float64), sh.astype(np.float64)
    o, d = random_rays(rng, 30)
    index = rng.permutation(V * PIXELS)[:30]
    P = _rows(rng).astype(np.float64)
    target = rng.uniform(0, 1, (30, 3))
    bg = (0.3, 0.6, 0.1)

    def loss(dn, shn):
        pix = ref.render_forward(dn, shn, BBOX, o, d, 0.37, bg)["rgb"]
        state = np.concatenate([pix, np.ones((len(pix), 5))], axis=1)
        return rex.rays_loss(state, (0, 0, 0), target, P, index, PIXELS, 1.0, masked=False)

    g = _twin(dens, sh, o, d, target, index, P, 0.37, bg, False)[0]
    want = ref.render_backward(dens, sh, BBOX, o, d, g, 0.37, bg)
    live = np.argwhere(dens > 0.2)
    h = 1e-5
    for v in live[rng.choice(len(live), 6, replace=False)]:
        v = tuple(v)
        up, dn = dens.copy(), dens.copy()
        up[v] += h
        dn[v] -= h
        fd = (loss(up, sh) - loss(dn, sh)) / (2 * h)
        np.testing.assert_allclose(2 * want["density"][v], fd, rtol=1e-4, atol=1e-7)
        c = int(rng.integers(sh.shape[-1]))
        up, dn = sh.copy(), sh.copy()
        up[v + (c,)] += h
        dn[v + (c,)] -= h
        fd = (loss(dens, up) - loss(dens, dn)) / (2 * h)
        np.testing.assert_allclose(2 * want["sh"][v + (c,)], fd, rtol=1e-4, atol=1e-7)


def test_stiff_rays_stay_finite_and_match_the_twin(render_device):
    """Densities of 1e4 beside empty voxels, axis-parallel rays and rays along the box's
    faces, a tiny step, gains of 40 clamped: every output finite and the twin's."""
    rng = np.random.default_rng(65)
    dens, sh = random_grid(rng, (6, 5, 4), 1, empty_frac=0.3)
    dens[dens > 2.0] = 1e4
    o, d = random_rays(rng, 40)
    c = BBOX.mean(0)
    for k in range(12):   # along each axis, through the centre and along a face
        a = k % 3
        o[k] = c - 3.0 * np.eye(3)[a] + (0 if k < 6 else 0.999) * (BBOX[1] - c) * (
            1 - np.eye(3)[a])
        d[k] = np.eye(3)[a]
    index = rng.permutation(V * PIXELS)[:40]
    P = _rows(rng)
    P[1, [0, 4, 8]] = 40.0
    target = rng.uniform(0, 1, (40, 3)).astype(np.float32)
    s = 1.0 / 120
    dd, ds, sq, state, resid, grow, _ = _fused(render_device, dens, sh, o, d, target, index,
                                               P, 0.05, (1.0, 1.0, 1.0), True, s)
    for a in (dd, ds, sq, state[:, :4], resid, grow):   # (the state's other entries unread)
        assert np.all(np.isfinite(a))
    g, r, sq64, state64, _ = _twin(dens, sh, o, d, target, index, P.astype(np.float64), 0.05,
                                   (1.0, 1.0, 1.0), True)
    np.testing.assert_allclose(sq, sq64, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(resid, r, atol=1e-5)
    want = ref.render_backward(dens, sh, BBOX, o, d, g, 0.05, (1.0, 1.0, 1.0))
    scale = max(1.0, np.abs(want["density"]).max())
    np.testing.assert_allclose(dd / (2 * s), want["density"], atol=tol.GRAD_ATOL * scale,
                               rtol=tol.GRAD_RTOL)
    np.testing.assert_allclose(ds / (2 * s), want["sh"], atol=tol.GRAD_ATOL, rtol=tol.GRAD_RTOL)


def test_the_transform_in_the_backward_needs_the_target_loss(device):
    """grad_mode 0 (a given dL/drgb) or a camera gradient with the transform: one clear
    error, nothing launched."""
    from clrf.corrections.exposure import RayExposure
    from clrf.grid.render import render_backward_device
    rng = np.random.default_rng(66)
    dens, sh = random_grid(rng, (4, 4, 4), 0)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 8)
    exp = RayExposure(device, V, PIXELS, lr=1e-3, reg=0.0)
    xf = exp.in_backward(_up(device, np.arange(8), np.int32))
    q = device.queue
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    for kw in ({"grad_mode": 0}, {"grad_mode": 1, "ray_grad": cla.empty(q, (8, 6), np.float32)}):
        with pytest.raises(ValueError, match="exposure"):
            render_backward_device(grid, _up(device, o), _up(device, d), _up(device, o), 0.37,
                                   (1.0, 1.0, 1.0), gd, gs, exposure=xf, **kw)
    assert not gd.get().any()
