"""NeRF's per-view corrections (nerf.pose_opt, nerf.exposure; clrf/nerf/model.py): each ray's
dL/d(origin, direction) (cl/sample.cl ray_points_backward) and the composite state
(cl/composite.cl composite_state) against their float64 twins (clrf/references/
reference_nerf.py ray_grad, composite_state), the twin's ray gradient against central
differences, stiff rays; a tiny model's whole step (both passes) against the float64 chain and
central differences of its loss in each ray's origin and direction (the sample distances held);
the network's and the transforms' gradients through the exposure of both passes against the
float64 chain; short runs in which the corrections move toward a known perturbation; the
checkpoint; the settings' errors."""
import dataclasses
from types import SimpleNamespace

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.corrections import CAMERA, RAYS, Corrections
from clrf.nerf import NerfConfig, NerfModel, ops
from clrf.references import reference_exposure as rex
from clrf.references import reference_nerf as rn
from clrf.testing import tolerances as tol

# tiny, smooth (softplus everywhere: central differences see no kink), no jitter
CFG = NerfConfig.from_preset("tiny", width=32, depth=2, color_width=16, pos_freqs=4,
                             dir_freqs=2, n_coarse=8, n_fine=8, perturb=False, lr=1e-2,
                             batch_rays=64, dw_chunk=64, hidden_act="softplus",
                             coarse_loss_weight=0.7)
NEAR, FAR, BG = 2.0, 6.0, (0.2, 0.5, 0.9)


def _up(dev, a, dtype=np.float32):
    return cla.to_device(dev.queue, np.ascontiguousarray(a, dtype))


def _ray_scale(t, gx, gv, d):
    """[n, 1] the magnitude of the terms each ray's gradient sums (float32 error grows with
    them, not with their possibly cancelling sum): sum_k (1 + |t_k|) |gx_k| + |gv_k|, over
    min(|d|, 1) (dL/dd carries 1 / |d|)."""
    n, K = t.shape
    term = ((1 + np.abs(t)).reshape(-1) * np.abs(gx).sum(1) + np.abs(gv).sum(1)).reshape(n, K)
    length = np.linalg.norm(np.asarray(d, np.float64), axis=1)    # float64: |d| may be 1e20
    return (term.sum(1) / np.minimum(length, 1.0))[:, None]


def _assert_rays(got, want, scale, rtol):
    err = np.abs(got - want)
    assert np.all(np.isfinite(got))
    assert np.all(err <= rtol * scale), (err / np.maximum(scale, 1e-300)).max()


def _kernel_ray_grad(dev, d, t, gx, gv, start=None):
    out = _up(dev, np.zeros((len(d), 6)) if start is None else start)
    ops.ray_points_backward(dev, _up(dev, d), _up(dev, t), _up(dev, gx), _up(dev, gv), out,
                            accumulate=start is not None)
    return out.get()


@pytest.mark.parametrize("n,K", [(1, 1), (37, 5), (70, 16)])
def test_ray_points_backward_matches_twin(device, n, K):
    """ray_points_backward against the twin: directions of length 1e-3 .. 50, axis-parallel
    ones, rays whose samples got no gradient (exactly 0 back); with accumulate it adds."""
    rng = np.random.default_rng(n + K)
    d = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 50.0], (n, 1))
    d[::7] = [[0.0, 0.0, 3.0]] if n > 1 else d[::7]
    d[1::9] = [[-0.2, 0.0, 0.0]] if n > 1 else d[1::9]
    t = np.sort(rng.uniform(0.05, 8.0, (n, K)), axis=1)
    gx, gv = rng.normal(size=(n * K, 3)), rng.normal(size=(n * K, 3))
    if n > 3:
        gx.reshape(n, K, 3)[2] = 0.0
        gv.reshape(n, K, 3)[2] = 0.0
    d32, t32 = d.astype(np.float32), t.astype(np.float32)
    got = _kernel_ray_grad(device, d, t, gx, gv)
    want = rn.ray_points_grad(d32, t32, gx.astype(np.float32), gv.astype(np.float32))
    scale = _ray_scale(t, gx, gv, d)
    _assert_rays(got, want, scale, tol.NERF_RAY_GRAD_RTOL)
    if n > 3:
        assert np.all(got[2] == 0)
    prev = rng.normal(size=(n, 6))
    added = _kernel_ray_grad(device, d, t, gx, gv, start=prev)
    _assert_rays(added, want + prev.astype(np.float32), scale + np.abs(prev),
                 tol.NERF_RAY_GRAD_RTOL)


def test_twin_ray_grad_vs_central_differences():
    """The twin's dL/d(o, d) of L = sum_k gx_k . x_k + gv_k . v_k (x_k = o + t_k d/|d|,
    v_k = d/|d|, t held) against central differences in o and d."""
    rng = np.random.default_rng(2)
    n, K = 9, 6
    o = rng.normal(size=(n, 3))
    d = rng.normal(size=(n, 3)) * np.repeat([1.0, 0.01, 30.0], 3)[:, None]
    d[0] = [0.0, 0.0, -2.0]                                       # axis-parallel
    t = np.sort(rng.uniform(0.1, 5, (n, K)), axis=1)
    gx, gv = rng.normal(size=(n * K, 3)), rng.normal(size=(n * K, 3))

    def loss(o, d):
        x, v = rn.ray_points(o, d, t)
        return np.sum(gx * x + gv * v, 1).reshape(n, K).sum(1)       # one loss per ray
    g = rn.ray_points_grad(d, t, gx, gv)
    h = 1e-6 * np.concatenate([np.ones((n, 3)), np.repeat(np.linalg.norm(d, axis=1)[:, None],
                                                          3, 1)], 1)
    for a in range(6):
        e = np.zeros((n, 3))
        e[:, a % 3] = h[:, a]
        args = [(o + s * e, d) if a < 3 else (o, d + s * e) for s in (1, -1)]
        fd = (loss(*args[0]) - loss(*args[1])) / (2 * h[:, a])
        scale = np.abs(g).max(axis=1)
        assert np.all(np.abs(fd - g[:, a]) <= tol.NERF_RAY_FD_RTOL * scale), a


def test_stiff_rays_are_finite_and_right(device):
    """Directions of length 1e-20 and 1e20 (|d|^2 under/overflows float32), a zero direction
    (dL/dd = 0, dL/do still the sum), and points at |x| ~ 1e3 through 16 frequencies (the
    encoding's derivative ~ 2^15 pi): the kernels' chain (encode_backward, then
    ray_points_backward) matches the float64 twins' and stays finite."""
    rng = np.random.default_rng(4)
    n, K, L = 8, 4, 16
    d = rng.normal(size=(n, 3))
    d[0] *= 1e-20
    d[1] *= 1e20
    d[2] = 0.0
    d[3] = [0.0, 1e-20, 0.0]
    o = rng.uniform(-1e3, 1e3, (n, 3))
    t = np.sort(rng.uniform(2.0, 6.0, (n, K)), axis=1)
    x = o[:, None] + t[..., None] * np.array([[0.0, 0, 1]])     # any points: only x is read
    x = x.reshape(-1, 3)
    dim = ops.enc_dim(L, True)
    gxe, gv = rng.normal(size=(n * K, dim)), rng.normal(size=(n * K, 3))
    gx = ops.encode_backward(device, _up(device, x), _up(device, gxe), L, True, 1 / np.pi)
    got = _kernel_ray_grad(device, d, t, gx.get(), gv)
    gx_want = rn.encode_backward(x.astype(np.float32), gxe, L, True, 1 / np.pi)
    np.testing.assert_allclose(gx.get(), gx_want, rtol=0, atol=tol.ENCODE_GRAD_RTOL
                               * np.linalg.norm(gx_want, axis=1, keepdims=True).max())
    live = [0, 1, 3, 4, 5, 6, 7]
    want = rn.ray_points_grad(d[live].astype(np.float32), t[live].astype(np.float32),
                       gx_want.reshape(n, K, 3)[live].reshape(-1, 3),
                       gv.reshape(n, K, 3)[live].reshape(-1, 3))
    scale = _ray_scale(t[live], gx_want.reshape(n, K, 3)[live].reshape(-1, 3),
                       gv.reshape(n, K, 3)[live].reshape(-1, 3), d[live].astype(np.float32))
    # the encoding's float32 error (ENCODE_GRAD_RTOL of its norm) dominates the sum's
    _assert_rays(got[live], want, scale, tol.ENCODE_GRAD_RTOL)
    assert np.all(got[2, 3:] == 0)
    np.testing.assert_allclose(got[2, :3], gx.get().reshape(n, K, 3)[2].sum(0), rtol=1e-6)
    assert abs(got[0, 3:]).max() > 1e15 and abs(got[1, 3:]).max() < 1e-15


def test_composite_state_matches_twin(device):
    rng = np.random.default_rng(5)
    n, K = 33, 7
    t = np.sort(rng.uniform(NEAR, FAR, (n, K)), axis=1)
    sig = rng.uniform(0, 3, (n, K)) * (rng.random((n, K)) > 0.2)
    sig[0] = 0.0                                       # an empty ray: T = 1
    rgb = rng.uniform(0, 1, (n, K, 3))
    rs = ops.composite_state(device, _up(device, t), _up(device, sig.ravel()),
                             _up(device, rgb.reshape(-1, 3)), FAR)
    st, dt = rn.composite_state(t.astype(np.float32), sig, rgb, FAR)
    got = rs.state.get()
    np.testing.assert_allclose(got[:, :5], st[:, :5], rtol=tol.COMPOSITE_RTOL,
                               atol=tol.COMPOSITE_ATOL)
    np.testing.assert_allclose(got[:, 5], st[:, 5], rtol=tol.COMPOSITE_RTOL,
                               atol=tol.COMPOSITE_ATOL)
    assert np.all(got[:, 6:] == 0) and got[0, 3] == 0 and got[0, 5] == 0
    np.testing.assert_allclose(rs.dt.get(), dt.ravel(), rtol=0, atol=tol.COMPOSITE_ATOL)
    assert rs.offsets.get().tolist() == list(range(0, n * K + 1, K))
    assert (rs.n, rs.m) == (n, n * K)


# ---- a tiny model's whole step ---------------------------------------------------------------
class _Capture:
    """A camera correction that leaves the rays as they are and keeps the step's ray gradient
    (the model's dL/d(origin, direction), as RayPose would get it)."""
    name, changes, batches, n_images = "pose", CAMERA, RAYS, 1
    trains = True
    grad = None

    def rays(self, index, origins, dirs):
        return origins, dirs

    def gradient_due(self):
        return True

    def step_rays(self, index, dirs, ray_grad):
        self.grad = ray_grad.get()

    def schedule(self, progress):
        pass


def _rays(n, seed):
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, n)
    o = np.stack([4 * np.cos(ang), 4 * np.sin(ang), rng.uniform(-0.5, 0.5, n)], 1)
    d = -o + rng.normal(scale=0.4, size=o.shape)
    return o, d * rng.choice([0.3, 1.0, 2.0], (n, 1))


def _model(device, **cfg):
    return NerfModel(device, dataclasses.replace(CFG, **cfg), NEAR, FAR, BG, seed=3)


def _pass(net, params, c, o, d, t, exact):
    """(x, v, encodings, sigma [n, K], rgb [n, K, 3], composite) of one pass (float64)."""
    n, K = t.shape
    x, v = rn.ray_points(o, d, t)
    xe = rn.encode(x, c.pos_freqs, c.include_input, c.pos_scale, exact)
    de = rn.encode(v, c.dir_freqs, c.include_input, c.dir_scale, exact)
    sig, rgb = rn.mlp_forward(params, net.spec, net.layout, xe, de)
    sig, rgb = sig.reshape(n, K), rgb.reshape(n, K, 3)
    return x, v, xe, de, sig, rgb, rn.composite_forward(t, sig, rgb, FAR)


def _colour(f, P, rows, masked, target):
    """(residual [n, 3], dL/dc over 2 scale, dL/dT over 2 scale) of the colour the loss sees,
    A (c + T bg) + b (masked: A c + (1 - T) b + T bg) with row ``rows[i]`` of P."""
    A, b = P[rows, :9].reshape(-1, 3, 3), P[rows, 9:]
    c, T, bg = f["rgb"], f["T_end"][:, None], np.asarray(BG)
    x = c if masked else c + T * bg
    out = np.einsum("nij,nj->ni", A, x) + ((1 - T) * b + T * bg if masked else b)
    r = out - target
    dT = np.sum(r * ((bg - b) if masked else np.einsum("nij,j->ni", A, bg)), 1)
    return r, np.einsum("nji,nj->ni", A, r), dT


def _chain(model, params, o, d, target, t_f=None, exact=False, P=None, index=None,
           masked=False):
    """(loss, dL/d(o, d) [n, 6], t_f, dL/dparams per net, dL/dP or None) of a step through the
    float64 references, the importance distances ``t_f`` held (drawn here where None)."""
    c = model.config
    B = len(o)
    scale = 1.0 / (3 * B)
    rows = None if index is None else np.asarray(index) // model.corrections.colour.pixels
    t_c = rn.sample_stratified(B, c.n_coarse, NEAR, FAR)
    loss, rg, gparams = 0.0, np.zeros((B, 6)), {}
    gP = None if P is None else np.zeros_like(P)
    passes = [(model.coarse, "coarse", t_c, scale * c.coarse_loss_weight)]
    for k, (net, name, t, s) in enumerate(passes):
        x, v, xe, de, sig, rgb, f = _pass(net, params[name], c, o, d, t, exact)
        if P is None:
            r = f["rgb"] + f["T_end"][:, None] * np.asarray(BG) - target
            gc, gT = r, np.sum(r * np.asarray(BG), 1)
        else:
            r, gc, gT = _colour(f, P, rows, masked, target)
            xx = f["rgb"] if masked else f["rgb"] + f["T_end"][:, None] * np.asarray(BG)
            yy = (1 - f["T_end"]) if masked else np.ones(B)
            for i in range(B):
                gP[rows[i], :9] += 2 * s * np.outer(r[i], xx[i]).ravel()
                gP[rows[i], 9:] += 2 * s * yy[i] * r[i]
        loss += s * np.sum(r * r)
        cb = rn.composite_backward(t, sig, rgb, FAR, 2 * s * gc)
        delta = np.diff(np.concatenate([t, np.full((B, 1), FAR)], 1), axis=1)
        cb["sigma"] -= 2 * s * delta * (f["T_end"] * gT)[:, None]   # dT_K/dsigma_k
        mb = rn.mlp_backward(params[name], net.spec, net.layout, xe, de, cb["sigma"].ravel(),
                             cb["rgb"].reshape(-1, 3))
        gparams[name] = gparams.get(name, 0) + mb["params"]
        gx = rn.encode_backward(x, mb["x_enc"], c.pos_freqs, c.include_input, c.pos_scale,
                                exact)
        gv = rn.encode_backward(v, mb["d_enc"], c.dir_freqs, c.include_input, c.dir_scale,
                                exact)
        rg += rn.ray_points_grad(d, t, gx, gv)
        if k == 0 and c.n_fine > 0:
            if t_f is None:
                t_f = rn.sample_importance(t_c, f["weights"], c.n_fine, NEAR, FAR)
            passes.append((model.fine, "fine", rn.merge_sorted(t_c, t_f), scale))
    return loss, rg, t_f, gparams, gP


def _params(model):
    p = {"coarse": model.coarse.params.get().astype(np.float64)}
    p["fine"] = p["coarse"] if model.fine is model.coarse else \
        model.fine.params.get().astype(np.float64)
    return p


@pytest.mark.parametrize("shared", [False, True])
def test_step_ray_gradient_matches_chain_and_differences(device, shared):
    """A tiny model's step (coarse and fine pass, MLP input gradient, encode_backward,
    ray_points_backward) gives each ray's dL/d(o, d) like the float64 chain, and the chain's
    equals central differences of its loss in each ray's origin and direction with the sample
    distances held (the stratified ones are fixed; the importance ones are drawn once)."""
    model = _model(device, shared_net=shared)
    cap = _Capture()
    model.corrections = Corrections([cap])
    o, d = _rays(6, seed=7)
    o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    target = np.random.default_rng(8).uniform(0, 1, (6, 3))
    params = _params(model)
    loss = model.train_step(0, _up(device, o), _up(device, d), _up(device, target),
                            index=_up(device, np.zeros(6), np.int32))
    want_loss, want, t_f, _, _ = _chain(model, params, o, d, target)
    assert np.abs(want).max() > 0
    np.testing.assert_allclose(cap.grad, want, rtol=0,
                               atol=tol.NERF_STEP_GRAD_REL_TO_MAX * np.abs(want).max())
    t_all = rn.merge_sorted(rn.sample_stratified(6, 8, NEAR, FAR), t_f)
    f = _pass(model.fine, params["fine"], model.config, o, d, t_all, False)[6]
    r = f["rgb"] + f["T_end"][:, None] * np.asarray(BG) - target
    assert abs(float(loss) - np.sum(r * r) / 18) <= tol.MLP_ATOL     # the fine pass's MSE
    _, g64, _, _, _ = _chain(model, params, o, d, target, t_f, exact=True)
    h = tol.NERF_RAY_FD_EPS
    for i in range(len(o)):
        for a in range(6):
            e = np.zeros((len(o), 3))
            e[i, a % 3] = h
            args = [(o + s * e, d) if a < 3 else (o, d + s * e) for s in (1, -1)]
            lp, lm = (_chain(model, params, *r, target, t_f, exact=True)[0] for r in args)
            fd = (lp - lm) / (2 * h)
            assert abs(fd - g64[i, a]) <= tol.NERF_RAY_FD_RTOL * np.abs(g64).max(), (i, a)


@pytest.mark.parametrize("masked", [False, True])
def test_exposure_gradients_of_both_passes_match_the_chain(device, masked):
    """With nerf.exposure, the coarse and fine losses both see each ray's transform: the
    networks' dL/dparams, the transforms' dL/dP (both passes plus the pull) and the reported
    loss (the fine pass's, transformed) match the float64 chain."""
    model = _model(device, exposure=True, exposure_reg=0.3)
    model.attach_corrections(2, 4, masked, extent=1.0)
    exp = model.corrections.colour
    assert model.ray_index and model.corrections.get("pose") is None
    rng = np.random.default_rng(9)
    P = np.tile(rex.IDENTITY, (2, 1)) + rng.normal(scale=0.2, size=(2, 12))
    exp.P.set(P.astype(np.float32))
    P = P.astype(np.float32).astype(np.float64)
    o, d = _rays(8, seed=10)
    o, d = o.astype(np.float32).astype(np.float64), d.astype(np.float32).astype(np.float64)
    target = rng.uniform(0, 1, (8, 3))
    index = np.array([0, 5, 1, 6, 2, 3, 7, 4])
    params = _params(model)
    loss = model.train_step(0, _up(device, o), _up(device, d), _up(device, target),
                            index=_up(device, index, np.int32))
    _, _, t_f, gparams, gP = _chain(model, params, o, d, target, P=P, index=index,
                                    masked=masked)
    share = np.bincount(index // 4, minlength=2) / 8
    gP += 2 * 0.3 * share[:, None] * (P - rex.IDENTITY)
    np.testing.assert_allclose(exp.grad.get(), gP, rtol=0,
                               atol=tol.NERF_STEP_GRAD_REL_TO_MAX * np.abs(gP).max())
    for net, name in ((model.coarse, "coarse"), (model.fine, "fine")):
        g = gparams[name]
        np.testing.assert_allclose(net.grad.get(), g, rtol=0,
                                   atol=tol.NERF_STEP_GRAD_REL_TO_MAX * np.abs(g).max())
    # the reported loss: the fine pass's squared transformed residual over 3 B
    f = _pass(model.fine, params["fine"], model.config, o, d,
              rn.merge_sorted(rn.sample_stratified(8, 8, NEAR, FAR), t_f), False)[6]
    r = _colour(f, P, index // 4, masked, target)[0]
    assert abs(float(loss) - np.sum(r * r) / 24) <= tol.MLP_ATOL


# ---- short runs --------------------------------------------------------------------------------
def _views(hw=(12, 12), focal=10.0):
    from clrf.data.cameras import _posed, camera_dirs, look_at
    c2w = [look_at([0.3, -3.6, 0.8], [0.0, 0.0, 0.0]), look_at([3.4, 1.0, -0.5], [0, 0, 0])]
    d_cam = camera_dirs([focal, focal, hw[1] / 2, hw[0] / 2], *hw).reshape(-1, 3)
    return c2w, lambda p: _posed(np.asarray(p, np.float64)[None], d_cam)


def test_pose_opt_moves_a_perturbed_camera_toward_its_true_pose(device):
    """Targets rendered by the model from two true cameras; image 0's rays come from a given
    camera off by a known correction (w*, tau*) (0.03 rad, 0.05). Steps of nerf.pose_opt (the
    networks' rate 1e-9: the scene held still) bring its correction toward (w*, tau*): the
    error falls fourfold (seen 0.032 -> 0.0024 in 40 steps). The targets are the fine pass's
    renders, which the coarse pass does not reproduce, so the coarse loss (weight 0 here)
    would pull toward another pose."""
    from clrf.corrections.pose import so3_exp
    from clrf.corrections.ray_pose import OPENGL_TO_OPENCV, pivot_depth, viewmat_of
    model = _model(device, pose_opt=True, lr=1e-9, lr_pose=3e-3, lr_pose_final=3e-3,
                   pose_reg=0.0, pose_hold_frame=False, coarse_loss_weight=0.0)
    c2w, view = _views()
    box = np.array([[-1.5] * 3, [1.5] * 3])
    pivots = [pivot_depth(viewmat_of(p), box) for p in c2w]
    w, tau = np.array([0.02, -0.015, 0.01]), np.array([-0.03, 0.04, 0.01])
    V = viewmat_of(c2w[0])           # the given camera whose correction (w, tau) is the true
    E, p = so3_exp(-w), np.array([0.0, 0.0, pivots[0]])
    V0 = np.eye(4)
    V0[:3, :3], V0[:3, 3] = E @ V[:3, :3], E @ (V[:3, 3] - p - tau) + p
    given = np.linalg.inv(OPENGL_TO_OPENCV @ V0)
    targets = [model.render(*view(q))["rgb"] for q in c2w]
    pixels = len(targets[0])
    model.attach_corrections(2, pixels, False, extent=3.0,
                             viewmats=lambda: np.stack([V0, viewmat_of(c2w[1])]),
                             pivots=lambda: pivots)
    pose = model.corrections.get("pose")
    rays = [view(given), view(c2w[1])]
    o, d = (_up(device, np.concatenate([r[k] for r in rays])) for k in (0, 1))
    target = _up(device, np.concatenate(targets))
    index = _up(device, np.arange(2 * pixels), np.int32)
    star = np.concatenate([w, tau / 3.0])

    def error():
        q = pose.pose.params[0]
        return np.linalg.norm(np.concatenate([q[:3], q[3:] / 3.0]) - star)
    before = error()
    for it in range(40):
        assert np.isfinite(float(model.train_step(it, o, d, target, index=index)))
    assert error() < 0.25 * before, (before, error(), pose.pose.params[0], star)
    assert pose.pose.steps.tolist() == [40, 40]
    assert "pose" in model.describe()


def test_exposure_moves_gains_toward_the_truth(device):
    """Targets rendered by the model (held still) and scaled per image by gains 0.8 and 1.25:
    nerf.exposure (gains only) moves each image's gain toward its own (within a quarter of
    its distance from 1; seen 0.820 and 1.240 after 40 steps), and the checkpoint keeps the rows.
    The coarse loss is off as in the pose test: the targets are the fine pass's renders."""
    model = _model(device, exposure=True, exposure_matrix="gain", lr=1e-9,
                   lr_exposure=0.02, exposure_reg=0.0, coarse_loss_weight=0.0)
    c2w, view = _views()
    rays = [view(q) for q in c2w]
    gains = np.array([0.8, 1.25])
    targets = [g * model.render(*r)["rgb"] for g, r in zip(gains, rays)]
    pixels = len(targets[0])
    model.attach_corrections(2, pixels, False, extent=3.0)
    exp = model.corrections.colour
    o, d = (_up(device, np.concatenate([r[k] for r in rays])) for k in (0, 1))
    target = _up(device, np.concatenate(targets))
    index = _up(device, np.arange(2 * pixels), np.int32)
    for it in range(40):
        model.train_step(it, o, d, target, index=index)
    rows = exp.rows()
    got = rows[:, [0, 4, 8]].mean(1)
    assert np.all(np.abs(got - gains) < 0.25 * np.abs(1 - gains)), got
    assert np.all(rows[:, [1, 2, 3, 5, 6, 7, 9, 10, 11]] == 0)
    back = NerfModel.from_state_dict(device, model.state_dict()).corrections.colour
    assert np.array_equal(back.rows(), rows) and back.steps == 40


def test_checkpoint_round_trip_with_corrections_and_an_older_one(device):
    """Both corrections after a few steps, through state_dict and from_state_dict: the same
    rows, poses, Adam moments and extent, and the next step alike; a checkpoint written before
    the corrections (no keys of theirs, in the state or its config) still loads."""
    model = _model(device, exposure=True, pose_opt=True)
    c2w, view = _views((6, 6))
    from clrf.corrections.ray_pose import viewmat_of
    model.attach_corrections(2, 36, False, extent=2.5,
                             viewmats=lambda: np.stack([viewmat_of(p) for p in c2w]),
                             pivots=lambda: [3.0, 3.0])
    rays = [view(q) for q in c2w]
    o, d = (_up(device, np.concatenate([r[k] for r in rays])) for k in (0, 1))
    target = _up(device, np.random.default_rng(1).uniform(0, 1, (72, 3)))
    index = _up(device, np.arange(72), np.int32)
    for it in range(3):
        model.train_step(it, o, d, target, index=index)
    back = NerfModel.from_state_dict(device, model.state_dict())
    assert back.extent == 2.5 and back.ray_index
    a, b = model.corrections.get("pose"), back.corrections.get("pose")
    for k in ("params", "m", "v", "steps", "pivots"):
        np.testing.assert_array_equal(getattr(a.pose, k), getattr(b.pose, k))
    assert a.pose.scale == b.pose.scale == 2.5
    np.testing.assert_array_equal(model.corrections.colour.rows(), back.corrections.colour.rows())
    la = model.train_step(3, o, d, target, index=index)
    lb = back.train_step(3, o, d, target, index=index)
    assert float(la) == float(lb)
    np.testing.assert_array_equal(a.pose.params, b.pose.params)
    np.testing.assert_array_equal(model.corrections.colour.rows(), back.corrections.colour.rows())
    assert set(model.corrections.summaries()) == {"pose_correction"}
    old = _model(device).state_dict()
    for k in [f.name for f in dataclasses.fields(NerfConfig)
              if "exposure" in f.name or "pose" in f.name]:
        del old["config"][k]
    loaded = NerfModel.from_state_dict(device, old)
    assert not loaded.corrections and not loaded.ray_index


BAD = [("lr_pose", 0.0), ("lr_pose", -1e-3), ("lr_pose", float("nan")), ("lr_pose_final", 1.0),
       ("pose_reg", -1.0), ("pose_opt_after", 1.0), ("lr_exposure", 0.0),
       ("lr_exposure", -1.0), ("exposure_reg", -0.1), ("exposure_matrix", "mixed")]


def test_bad_settings_fail_the_sections_checks():
    """Each bad value fails the check that names its key (a rate of 0 also its final rate's,
    which must lie in (0, lr_pose]); the defaults pass."""
    assert all(ok for ok, _, _ in NerfConfig(pose_opt=True, exposure=True).checks())
    for key, value in BAD:
        failed = [f for ok, f, _ in NerfConfig(pose_opt=True, exposure=True,
                                               **{key: value}).checks() if not ok]
        want = {f"nerf.{key}"} | ({"nerf.lr_pose_final"} if key == "lr_pose" else set())
        assert f"nerf.{key}" in failed and set(failed) <= want, (key, value, failed)


@pytest.mark.parametrize("key,value", [("lr_pose", 0.0), ("exposure_matrix", "mixed")])
def test_bad_settings_are_one_clear_error(key, value, capsys, tmp_path):
    from clrf.cli.main import main as cli
    rc = cli(["--quiet", "train", "--model", "nerf", "--out", str(tmp_path / "run"),
              "--set", "nerf.pose_opt=true", "--set", "nerf.exposure=true",
              "--set", f"nerf.{key}={value}", "--max-seconds", "1"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("clrf: error:") == 1 and f"nerf.{key}" in err, err


def test_pose_opt_is_refused_on_ndc_scenes_and_nerf_has_no_ranks():
    """NDC rays are not a camera's: one error naming nerf.pose_opt. NeRF does not train over
    MPI ranks at all (no ``distributed``: the command line refuses such a run)."""
    from clrf import registry
    from clrf.nerf.kind import create
    cfg = SimpleNamespace(nerf=NerfConfig(pose_opt=True))
    with pytest.raises(ValueError, match="nerf.pose_opt.*NDC.*nerf.pose_opt=false"):
        create(None, cfg, SimpleNamespace(name="fern", ndc=True), (0, 0, 0))
    assert registry.get("nerf").distributed is None


def test_the_grid_reference_keeps_its_own_names():
    """clrf/references/reference.py ends by re-exporting NeRF's twins (``from .reference_nerf
    import *``): none of those may share a name with a function reference.py defines, or the
    grid's twin of that name is silently replaced (it happened to ``ray_grad``)."""
    import ast
    import inspect

    from clrf.references import reference, reference_nerf
    tree = ast.parse(inspect.getsource(reference))
    own = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
    assert own and not own & set(reference_nerf.__all__), own & set(reference_nerf.__all__)
