"""Pose refinement for the hash grid: each ray's dL/d(origin, direction) (cl/hash_march.cl
packed_ray_grad, HASH_POSE_GRAD) against its float64 twin, the contraction's vector-Jacobian
product and the SH direction share against central differences, and a tiny model's whole step
(MLP input gradient, hash_dx, packed_ray_grad) against the float64 chain and its central
differences in the rays."""
import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from clrf.hash.march import Contraction, Packed, ray_grad
from clrf.references import reference_hash as rh
from clrf.references import reference_nerf as rn
from clrf.references.reference import sh_basis
from clrf.testing import tolerances as tol

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_hash_model import SMALL, _rays, _up, seeded_model  # noqa: E402

INNER = np.array([[-0.5, -0.3, -0.4], [0.7, 0.5, 0.6]])
SH_DY_MAX = 4.0   # max |dY_b/dv_a| of sh.h's degree-3 basis on the unit sphere (3.7: 8 C3_2)


def _packed(dev, offsets, t, m):
    """A Packed holding offsets and t (the kernel reads no other row)."""
    z = _up(dev, np.zeros((max(m, 1), 3)))
    return Packed(len(offsets) - 1, m, _up(dev, offsets).astype(np.int32), _up(dev, t), _up(dev, t),
                  z, z)


def _ray_scale(off, t, gx, gsh, d):
    """[n, 1] the magnitude of the terms each ray's gradient sums (tolerances: float32 error
    grows with them, not with their possibly cancelling sum): sum_k (1 + t_k) |dL/dx_k| +
    SH_DY_MAX sum_b |dL/dY_kb|, over min(|d|, 1) (dL/dd carries 1 / |d|)."""
    ray = np.repeat(np.arange(len(off) - 1), np.diff(off))
    term = (1 + np.abs(t)) * np.abs(gx).sum(axis=1)
    if gsh is not None:
        term = term + SH_DY_MAX * np.abs(gsh).sum(axis=1)
    s = np.bincount(ray, term, minlength=len(off) - 1)
    return (s / np.minimum(np.linalg.norm(d, axis=1), 1.0))[:, None]


def _assert_rays(got, want, scale, rtol):
    err = np.abs(got - want)
    assert np.all(err <= rtol * scale), (err / np.maximum(scale, 1e-300)).max()


def test_contract_vjp_vs_central_differences():
    """The contraction's vector-Jacobian product (twin) against central differences of
    reference contract, inside the inner box and beyond it on each axis."""
    rng = np.random.default_rng(1)
    c = Contraction(INNER)
    x = c.centre + c.half * rng.uniform(-4, 4, (60, 3))
    x[:5] = c.centre + c.half * rng.uniform(-0.9, 0.9, (5, 3))   # inside: the identity part
    gp = rng.normal(size=(60, 3))
    g = rh.contract_vjp(x, gp, c.centre, c.half)
    h = 1e-7
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        f = [np.sum(gp * rh.contract((x + s * e - c.centre) / c.half), axis=1) for s in (1, -1)]
        np.testing.assert_allclose(g[:, a], (f[0] - f[1]) / (2 * h), rtol=1e-6, atol=1e-8)


def test_sh_share_vs_central_differences():
    """The direction encoding's share: sum_b w_b dY_b(d/|d|)/dd (twin's projection) against
    central differences of the SH basis of the normalised direction."""
    rng = np.random.default_rng(2)
    d = rng.normal(size=(20, 3))
    w = rng.normal(size=(20, 16))
    off = np.arange(21)
    got = rh.ray_grad(off, np.zeros(20), np.zeros((20, 3)), d, np.zeros((20, 3)), w)[:, 3:]
    h = 1e-7
    for a in range(3):
        e = np.zeros(3)
        e[a] = h

        def f(dd):
            return np.sum(w * sh_basis(dd / np.linalg.norm(dd, axis=1, keepdims=True), 3), 1)
        np.testing.assert_allclose(got[:, a], (f(d + e) - f(d - e)) / (2 * h), rtol=1e-6,
                                   atol=1e-8)


@pytest.mark.parametrize("contract", [False, True])
@pytest.mark.parametrize("sh", [False, True])
def test_ray_grad_matches_twin(device, contract, sh):
    """packed_ray_grad against the twin on 37 rays with 0 .. 9 samples each (some none), unit
    and long directions, contracted or not, with and without the SH share."""
    rng = np.random.default_rng(3 + 2 * contract + sh)
    n = 37
    counts = rng.integers(0, 10, n)
    counts[:3] = 0
    off = np.concatenate([[0], np.cumsum(counts)])
    m = int(off[-1])
    o = rng.uniform(-3, 3, (n, 3))
    d = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 50.0], (n, 1))
    t = rng.uniform(0.05, 8.0, m)
    gp = rng.normal(size=(m, 3))
    gsh = rng.normal(size=(m, 16)) if sh else None
    c = Contraction(INNER) if contract else None
    pk = _packed(device, off, t, m)
    got = ray_grad(device, pk, _up(device, o), _up(device, d), _up(device, gp),
                   _up(device, gsh) if sh else None, c).get()
    want = rh.ray_grad(off, t.astype(np.float32), o.astype(np.float32), d.astype(np.float32),
                       gp, gsh, *((c.centre, c.half) if c else ()))
    assert np.all(got[:3] == 0)
    gx = rh.contract_vjp(np.repeat(o, counts, 0) + t[:, None] * np.repeat(
        d / np.linalg.norm(d, axis=1, keepdims=True), counts, 0), gp, c.centre, c.half) \
        if c else gp
    _assert_rays(got, want, _ray_scale(off, t, gx, gsh, d), tol.HASH_RAY_GRAD_RTOL)


def _chain(model, o, d, target, f64):
    """(loss, dL/d(o, d) [n, 6], offsets) of a step (no jitter, no termination) through the
    float64 references; ``f64``: the encoding's u and p in float64 (finite differences)."""
    enc, net, con = model.enc, model.net, model.contraction
    c = model.config
    off, t, dt, xyz, vdir = rh.march_samples(
        o, d, c.samples, model.near, model.far, model.occ.occ.get(), enc.lo, enc.inv_ext,
        c.occ_res, centre=con.centre if con else None, half=con.half if con else None)
    table, params = enc.table.get(), net.params.get()
    x_enc = rh.hash_forward(xyz, enc.lo, enc.inv_ext, enc.res_host, table, f64)
    d_enc = rh.sh_encode(vdir)
    sigma, rgb = rn.mlp_forward(params, net.spec, net.layout, x_enc, d_enc)
    scale = 1.0 / (3 * len(o))
    g = rh.packed_backward(off, t, dt, sigma, rgb, model.background, target, scale)
    mb = rn.mlp_backward(params, net.spec, net.layout, x_enc, d_enc, g["sigma"], g["rgb"])
    gp = rh.hash_dx(xyz, enc.lo, enc.inv_ext, enc.res_host, table, mb["x_enc"], f64)
    gr = rh.ray_grad(off, t, o, d, gp, mb["d_enc"], *((con.centre, con.half) if con else ()))
    gx = rh.contract_vjp(xyz_world(o, d, off, t), gp, con.centre, con.half) if con else gp
    return scale * np.sum(g["sq_err"]), gr, off, _ray_scale(off, t, gx, mb["d_enc"], d)


def xyz_world(o, d, off, t):
    """The world points o + t_k d / |d| of packed samples."""
    n = np.diff(off)
    dh = np.asarray(d, np.float64) / np.linalg.norm(d, axis=1, keepdims=True)
    return np.repeat(np.asarray(o, np.float64), n, 0) + np.asarray(t)[:, None] * np.repeat(dh, n, 0)


@pytest.mark.parametrize("contract,bounded", [("off", False), ("on", False), ("off", True)])
def test_step_ray_gradient_matches_chain_and_differences(device, contract, bounded):
    """A tiny model's step fills dL/d(o, d) like the float64 chain, and the chain's gradient
    equals central differences of its loss in each ray's origin and direction (every cell
    occupied and no termination: the samples move with the ray, none appears or goes).
    ``bounded``: the step of GPUs, whose sizes stay on the device (the kernels read the live
    count)."""
    near, far = (1.5, 4.5) if contract == "off" else (0.05, 60.0)
    cfg = dataclasses.replace(SMALL, contract=contract, train_t_stop=0.0)
    model = seeded_model(device, cfg, near, far, bounded=bounded)
    model.occ.ema.fill(np.float32(1.0))
    model.occ._threshold(0.5)
    o, d = _rays(6, seed=7)
    target = np.random.default_rng(8).uniform(0, 1, (6, 3))
    out = _up(device, np.zeros((6, 6)))
    model.loss_and_grad(0, _up(device, o), _up(device, d), _up(device, target), jitter=False,
                        ray_grad=out)
    _, want, _, scale = _chain(model, o, d, target, False)
    assert np.abs(want).max() > 0
    _assert_rays(out.get(), want, scale, tol.HASH_STEP_GRAD_REL_TO_MAX)
    o64, d64 = o.astype(np.float64), d.astype(np.float64)
    _, g64, off, _ = _chain(model, o64, d64, target, True)
    h = tol.HASH_RAY_FD_EPS
    for i in range(len(o)):
        for a in range(6):
            e = np.zeros((len(o), 3))
            e[i, a % 3] = h
            args = [(o64 + s * e, d64) if a < 3 else (o64, d64 + s * e) for s in (1, -1)]
            (lp, _, op, _), (lm, _, om, _) = (_chain(model, *r, target, True) for r in args)
            assert np.array_equal(op, off) and np.array_equal(om, off)
            fd = (lp - lm) / (2 * h)
            assert abs(fd - g64[i, a]) <= tol.HASH_RAY_FD_RTOL * np.abs(g64).max(), (i, a)
