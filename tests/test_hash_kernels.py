"""The hash model's sampling, compositing and optimiser kernels (cl/hash_march.cl, cl/optim.cl's
Adam) against their float64 references, on every OpenCL implementation present: the march
(jittered, windowed, contracted), the packed composite forward and backward, training-time
termination, and Adam over spans with its subnormal flush."""
import numpy as np
import pyopencl.array as cla

from clrf.hash.occupancy import OccupancyGrid
from clrf.references import reference_hash as rh
from clrf.references import reference_nerf as rn
from clrf.testing import tolerances as tol
from test_hash_model import BOX, _rays, _up



def test_march_matches_reference(device):
    """Live samples (inside the box, occupied cell), packed per ray, jittered bins; rays that
    miss the box get none."""
    from clrf.hash.march import march
    occ = OccupancyGrid(device, 5, BOX)
    rng = np.random.default_rng(1)
    mask = rng.random(125) < 0.4
    occ.ema.set(np.where(mask, 1.0, 0.0).astype(np.float32))
    occ._threshold(0.5)
    o, d = _rays(37, seed=1)
    d[0] = -d[0]                                 # points away from the box
    for jitter in (False, True):
        pk = march(device, occ, _up(device, o), _up(device, d), 24, 1.0, 5.0, jitter, key=9)
        off, t, dt, xyz, vdir = rh.march_samples(o, d, 24, 1.0, 5.0, occ.occ.get(), BOX[0],
                                                 1 / (BOX[1] - BOX[0]), 5, jitter, 9)
        np.testing.assert_array_equal(pk.offsets_host, off)
        assert off[1] == 0 and 0 < pk.m < 37 * 24
        np.testing.assert_allclose(pk.t.get(), t, rtol=0, atol=tol.SAMPLE_ATOL)
        np.testing.assert_allclose(pk.dt.get(), dt, rtol=0, atol=tol.SAMPLE_ATOL)
        np.testing.assert_allclose(pk.xyz.get(), xyz, rtol=0, atol=tol.SAMPLE_ATOL)
        np.testing.assert_allclose(pk.vdir.get(), vdir, rtol=0, atol=tol.SAMPLE_ATOL)


def test_march_window_and_alive_rays(device):
    """A render's round: bins k0 .. k1-1 only (windows that straddle march_live's 16-bin lanes
    and end before S), and nothing for rays whose alive flag is 0."""
    from clrf.hash.march import march
    occ = OccupancyGrid(device, 5, BOX)
    mask = np.random.default_rng(2).random(125) < 0.5
    occ.ema.set(np.where(mask, 1.0, 0.0).astype(np.float32))
    occ._threshold(0.5)
    o, d = _rays(23, seed=3)
    S, near, far = 70, 1.0, 5.0
    off, t, _, xyz, _ = rh.march_samples(o, d, S, near, far, occ.occ.get(), BOX[0],
                                         1 / (BOX[1] - BOX[0]), 5)
    k = np.rint((t - near) / (far - near) * S - 0.5).astype(int)   # each sample's bin
    ray = np.repeat(np.arange(23), np.diff(off))
    alive = (np.arange(23) % 3 != 1).astype(np.uint8)
    counts = []
    for k0, k1 in ((0, 16), (5, 38), (33, 70), (69, 70)):
        pk = march(device, occ, _up(device, o), _up(device, d), S, near, far, False, 0, k0, k1,
                   alive=cla.to_device(device.queue, alive))
        keep = (k >= k0) & (k < k1) & (alive[ray] == 1)
        np.testing.assert_array_equal(np.diff(pk.offsets_host), np.bincount(ray[keep],
                                                                             minlength=23))
        assert pk.m == keep.sum()
        counts.append(pk.m)
        if pk.m:
            np.testing.assert_allclose(pk.t.get(), t[keep], rtol=0, atol=tol.SAMPLE_ATOL)
            np.testing.assert_allclose(pk.xyz.get(), xyz[keep], rtol=0, atol=tol.SAMPLE_ATOL)
    assert min(counts[:3]) > 0


def test_march_contracted_matches_reference(device):
    """Unbounded scenes: bins even in log t out to far = 200, points contracted about an
    off-centre inner box into [-2, 2]^3 and looked up there; rays from inside and outside the
    inner box, one along an axis; octant cells (no sample lands on a cell border)."""
    from clrf.hash.march import Contraction, contract_points, march
    inner = np.array([[-0.5, -1.0, 0.0], [1.5, 1.0, 1.0]])
    con = Contraction(inner)
    occ = OccupancyGrid(device, 2, Contraction.BOX)
    occ.ema.set(np.float32([1, 0, 0, 1, 1, 0, 1, 0]))
    occ._threshold(0.5)
    o, d = _rays(29, seed=5, radius=3.0)
    o[:9] *= 0.1                                  # cameras inside the inner box
    d[3] = (0, 0, 1)
    near, far, S = 0.05, 200.0, 40
    for jitter in (False, True):
        pk = march(device, occ, _up(device, o), _up(device, d), S, near, far, jitter, key=4,
                   contract=con)
        off, t, dt, xyz, vdir = rh.march_samples(o, d, S, near, far, occ.occ.get(),
                                                 Contraction.BOX[0], np.full(3, 0.25), 2,
                                                 jitter, 4, con.centre, con.half)
        np.testing.assert_array_equal(pk.offsets_host, off)
        assert 0 < pk.m < 29 * S and np.abs(xyz).max() > 1.9 and np.abs(xyz).max() < 2
        # t and the bin lengths are exp() of float32 arguments up to ln(4000) = 8.3
        np.testing.assert_allclose(pk.t.get(), t, rtol=tol.HASH_CONTRACT_RTOL, atol=0)
        np.testing.assert_allclose(pk.dt.get(), dt, rtol=tol.HASH_CONTRACT_RTOL, atol=0)
        # a point carries t's relative error times t (in inner-box half-sizes); contraction
        # only shrinks it further
        err = np.abs(pk.xyz.get() - xyz)
        assert np.all(err <= tol.HASH_CONTRACT_RTOL * t[:, None] / con.half.min()
                      + tol.HASH_CONTRACT_ATOL), err.max()
        np.testing.assert_allclose(pk.vdir.get(), vdir, rtol=0, atol=tol.SAMPLE_ATOL)
    # the bins tile [near, far] exactly
    _, dt_all = rh.bins(1, S, near, far, log=True)
    assert abs(dt_all.sum() - (far - near)) < 1e-9 * far
    pts = np.random.default_rng(6).normal(0, 3, (50, 3))
    got = contract_points(device, con, _up(device, pts)).get()
    np.testing.assert_allclose(got, rh.contract((pts - con.centre) / con.half), rtol=0,
                               atol=tol.HASH_CONTRACT_ATOL)


def test_packed_composite_matches_reference(device):
    """Forward (in two windows, state carried) and MSE backward over packed samples, densities
    0..1e30 and negative, one empty ray."""
    from clrf.hash import march as hm
    rng = np.random.default_rng(2)
    counts = np.array([0, 1, 7, 40, 13])
    off = np.concatenate([[0], np.cumsum(counts)])
    m = int(off[-1])
    t = np.concatenate([np.sort(rng.uniform(2, 6, c)) for c in counts]).astype(np.float32)
    sig = rng.uniform(-1, 20, m).astype(np.float32)
    sig[off[3] + 5] = 1e30
    rgb = rng.uniform(0, 1, (m, 3)).astype(np.float32)
    target = rng.uniform(0, 1, (5, 3)).astype(np.float32)
    dt, bg = rng.uniform(0.01, 0.1, m).astype(np.float32), (0.2, 0.5, 1.0)   # per sample
    q = device.queue
    n = 5

    def pk_of(lo, hi):
        sel = np.concatenate([np.arange(off[i] + min(lo, counts[i]), off[i] + min(hi, counts[i]))
                              for i in range(n)]).astype(int)
        c2 = np.array([max(0, min(hi, c) - min(lo, c)) for c in counts])
        o2 = np.concatenate([[0], np.cumsum(c2)])
        return hm.Packed(n, len(sel), cla.to_device(q, o2.astype(np.int32)),
                         _up(device, t[sel]), _up(device, dt[sel]),
                         _up(device, np.zeros((len(sel), 3))),
                         _up(device, np.zeros((len(sel), 3)))), sel

    state = cla.zeros(q, (n, hm.STATE), np.float32)
    for lo, hi in ((0, 10), (10, 64)):
        pk, sel = pk_of(lo, hi)
        hm.packed_forward(device, pk, _up(device, sig[sel]), _up(device, rgb[sel]), state)
    got = hm.finish_state(state.get(), bg)
    want = rh.packed_forward(off, t, dt, sig, rgb, bg)
    for k in ("rgb", "acc"):
        np.testing.assert_allclose(got[k], want[k], rtol=tol.RENDER_RTOL, atol=tol.RENDER_ATOL)
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=tol.DEPTH_RTOL,
                               atol=tol.DEPTH_ATOL)
    pk, _ = pk_of(0, 64)
    g = hm.packed_backward(device, pk, _up(device, sig), _up(device, rgb), bg,
                           _up(device, target), 0.1)
    r = rh.packed_backward(off, t, dt, sig, rgb, bg, target, 0.1)
    np.testing.assert_allclose(g["sq_err"].get(), r["sq_err"], rtol=tol.RENDER_RTOL,
                               atol=tol.RENDER_ATOL)
    for k in ("sigma", "rgb"):
        np.testing.assert_allclose(g[k].get(), r[k], rtol=tol.GRAD_RTOL, atol=tol.GRAD_ATOL)


def test_packed_keep_and_gather_match_reference(device):
    """Training-time termination: each ray's kept prefix (transmittance in front >= t_stop;
    the first sample always) and the rows gathered into its packing, with empty rays, negative,
    NaN and 1e30 densities."""
    from clrf.hash import march as hm
    rng = np.random.default_rng(8)
    counts = np.array([0, 1, 9, 40, 13, 0, 25])
    off = np.concatenate([[0], np.cumsum(counts)])
    n, m = len(counts), int(off[-1])
    sig = rng.uniform(-2, 30, m).astype(np.float32)
    sig[off[3] + 2] = np.nan
    sig[off[4] + 6] = 1e30
    sig[off[6]:] = 0.01                       # a ray that never becomes opaque
    dt = rng.uniform(0.01, 0.2, m).astype(np.float32)
    t = np.cumsum(dt).astype(np.float32)
    xyz, vdir = rng.normal(size=(m, 3)), rng.normal(size=(m, 3))
    extra = rng.normal(size=(m, 5)).astype(np.float32)
    q = device.queue
    pk = hm.Packed(n, m, cla.to_device(q, off.astype(np.int32)), _up(device, t),
                   _up(device, dt), _up(device, xyz), _up(device, vdir))
    for t_stop in (1e-4, 0.3):
        want, T = rh.packed_keep(off, dt, sig, t_stop)
        got = hm.keep_front(device, pk, _up(device, sig), t_stop, (_up(device, extra),))
        kept, (ex,) = got
        assert 0 < want.sum() < m and want[6] == counts[6] and want[1] == 1
        np.testing.assert_array_equal(np.diff(kept.offsets_host), want)
        np.testing.assert_array_equal(kept.offsets.get(), kept.offsets_host)
        sel = np.concatenate([off[i] + np.arange(k) for i, k in enumerate(want)]).astype(int)
        assert np.all(T[sel] >= t_stop)
        for a, b in ((kept.t, t), (kept.dt, dt), (kept.xyz, xyz), (kept.vdir, vdir), (ex, extra)):
            np.testing.assert_array_equal(a.get(), np.asarray(b, np.float32)[sel])
        assert hm.keep_front(device, pk, _up(device, sig), t_stop,
                             max_fraction=0.99 * want.sum() / m) is None


def test_packed_backward_vs_finite_differences():
    """The packed composite reference's dL/dsigma against central differences of its loss."""
    rng = np.random.default_rng(3)
    off = np.array([0, 6, 6, 15])
    t = np.concatenate([np.sort(rng.uniform(2, 6, 6)), np.sort(rng.uniform(2, 6, 9))])
    sig = rng.uniform(0.1, 20, 15)
    rgb = rng.uniform(0, 1, (15, 3))
    target = rng.uniform(0, 1, (3, 3))
    dt = rng.uniform(0.01, 0.1, 15)             # per-sample segments (contracted scenes)

    def loss(s):
        f = rh.packed_forward(off, t, dt, s, rgb, (0.2, 0.5, 1.0))
        return 0.1 * np.sum((f["rgb"] - target) ** 2)
    g = rh.packed_backward(off, t, dt, sig, rgb, (0.2, 0.5, 1.0), target, 0.1)["sigma"]
    fd = rn.numeric_gradient(loss, sig, 1e-6)
    np.testing.assert_allclose(g, fd, rtol=tol.FD_RTOL, atol=tol.FD_ATOL)


def test_adam_weight_decay_and_clear_grad(device):
    """Adam with L2 weight decay (the MLP's) and clear_grad (the tables'): the formula, and the
    gradient is zero afterwards; a NaN gradient entry is skipped (and still cleared)."""
    from clrf.runtime.optim import Optimizer
    rng = np.random.default_rng(0)
    p, g = rng.normal(size=33), rng.normal(size=33) * 1e-3
    g[3] = np.nan
    pd, gd = _up(device, p), _up(device, g)
    opt = Optimizer(device, pd, "adam", beta=0.9, beta2=0.99, eps=1e-15, grad=gd,
                    weight_decay=0.1)
    opt.step(None, 1e-2, t=1, clear_grad=True)
    p32 = p.astype(np.float32).astype(np.float64)
    gw = g.astype(np.float32) + 0.1 * p32
    want = p32 - 1e-2 * (0.1 * gw / 0.1) / (np.sqrt(0.01 * gw * gw / 0.01) + 1e-15)
    want[3] = p32[3]
    np.testing.assert_allclose(pd.get(), want, rtol=tol.ADAM_RTOL, atol=tol.ADAM_ATOL)
    assert not np.any(gd.get())
    # spans: only entries 2..9 and 20..32 step (and have their gradient cleared)
    gd.set(g.astype(np.float32))
    before = pd.get()
    opt.step(None, 1e-2, t=2, clear_grad=True, spans=[(2, 10), (20, 33)])
    inside = np.zeros(33, bool)
    inside[2:10] = inside[20:] = True
    inside[3] = False                            # the NaN entry is skipped
    after = pd.get()
    assert np.all(after[~inside] == before[~inside]) and np.all(after[inside] != before[inside])
    outside = np.ones(33, bool)
    outside[2:10] = outside[20:] = False
    np.testing.assert_array_equal(gd.get() != 0, outside)   # cleared inside the spans only


def test_adam_over_many_spans_in_one_launch(device):
    """Spans of every length against the work-group size (1, 63, 64, 65, 200 entries, touching
    and apart) in one adam_multi launch (the GPU shape, forced): each entry inside steps
    exactly as adam_step over its span alone does (the CPU shape); entries outside keep their
    value, moments and gradient."""
    from clrf.runtime.optim import ADAM_LOCAL_SIZE, Optimizer, span_groups
    rng = np.random.default_rng(5)
    n = 700
    spans = [(0, 1), (1, 64), (100, 165), (165, 228), (300, 500), (640, 641), (650, 650)]
    p, g = rng.normal(size=n), rng.normal(size=n) * 1e-2
    m, v = rng.normal(size=n) * 1e-3, rng.uniform(0, 1e-4, n)

    def run(dev):
        arrs = [_up(dev, a) for a in (p, g, m, v)]
        opt = Optimizer(dev, arrs[0], "adam", beta=0.9, beta2=0.99, eps=1e-8, grad=arrs[1],
                        state=arrs[2], state2=arrs[3], weight_decay=0.01)
        opt.step(None, 3e-3, t=7, clear_grad=True, spans=spans)
        return [a.get() for a in arrs]

    one = run(device.with_tuning(gpu_kernels=True))      # adam_multi
    each = run(device.with_tuning(gpu_kernels=False))    # adam_step, a launch a span
    for a, b, name in zip(one, each, ("p", "g", "m", "v")):
        np.testing.assert_array_equal(a, b, err_msg=name)
    inside = np.zeros(n, bool)
    for a, b in spans:
        inside[a:b] = True
    for got, was in zip(one, (p, g, m, v)):
        np.testing.assert_array_equal(got[~inside], np.float32(was[~inside]))
    assert np.all(one[1][inside] == 0) and np.all(one[0][inside] != np.float32(p[inside]))
    table = span_groups(spans, ADAM_LOCAL_SIZE)
    assert table.shape == (1 + 1 + 2 + 1 + 4 + 1, 2)
    assert table.tolist()[2:4] == [[100, 165], [164, 165]]


def test_adam_set_steps_every_buffer_in_one_launch(device):
    """AdamSet (adam_multi: up to four buffers, the GPU shape) against each optimiser's own
    step: every buffer with its own learning rate, weight decay, spans and clear flag, entries
    outside the spans untouched; bad sets refused."""
    import pytest
    from clrf.runtime.optim import AdamSet, Optimizer
    rng = np.random.default_rng(6)
    sizes, lrs, wds = (700, 65, 1, 130), (3e-3, 1e-2, 5e-4, 2e-3), (0.01, 0.0, 0.0, 0.1)
    spans = ([(0, 1), (1, 64), (100, 165), (300, 500)], None, None, [(64, 130)])
    clear = (True, False, True, False)
    data = [[rng.normal(size=n), rng.normal(size=n) * 1e-2, rng.normal(size=n) * 1e-3,
             rng.uniform(0, 1e-4, n)] for n in sizes]

    def opts():
        out = []
        for (p, g, m, v), wd in zip(data, wds):
            arrs = [_up(device, a) for a in (p, g, m, v)]
            out.append(Optimizer(device, arrs[0], "adam", beta=0.9, beta2=0.99, eps=1e-8,
                                 grad=arrs[1], state=arrs[2], state2=arrs[3], weight_decay=wd))
        return out

    together, alone = opts(), opts()
    AdamSet(device, together).step(lrs, 7, spans=spans, clear_grad=clear)
    for o, lr, sp, c in zip(alone, lrs, spans, clear):
        o.step(None, lr, t=7, clear_grad=c, spans=sp)
    for a, b in zip(together, alone):
        for x, y, name in ((a.param, b.param, "p"), (a.grad, b.grad, "g"),
                           (a.state, b.state, "m"), (a.state2, b.state2, "v")):
            np.testing.assert_array_equal(x.get(), y.get(), err_msg=name)
    p0 = together[0].param.get()
    assert np.all(p0[500:] == np.float32(data[0][0][500:])) and np.all(p0[:64] != data[0][0][:64])
    with pytest.raises(ValueError, match="1 to 4"):
        AdamSet(device, opts() + opts()[:1])
    rms = Optimizer(device, _up(device, np.zeros(4)))
    with pytest.raises(ValueError, match="same beta"):
        AdamSet(device, [together[0], rms])
    with pytest.raises(ValueError, match="one lr"):
        AdamSet(device, together[:2]).step([1e-3], 1)


def test_adam_moments_flush_below_float_min(device):
    """Moments that decay below FLT_MIN are stored as 0, never subnormal (x86 computes on
    subnormals ~100x slower): entries with no gradient and moments near FLT_MIN (or already
    subnormal, from an older checkpoint) end at 0 with the parameter unmoved (within a step
    below 1e-22); a normal moment stays as the formula has it."""
    from clrf.runtime.optim import Optimizer
    tiny = np.finfo(np.float32).tiny
    m0 = np.float32([1.1 * tiny, 1e-39, 0.0, 1e-3, -1.05 * tiny])
    v0 = np.float32([1.001 * tiny, 1e-40, 1e-39, 1e-6, 2e-39])
    p = np.float32([0.5, -0.25, 1.0, 0.125, 2.0])
    pd, gd = _up(device, p), _up(device, np.zeros(5))
    md, vd = _up(device, m0), _up(device, v0)
    opt = Optimizer(device, pd, "adam", beta=0.9, beta2=0.99, eps=1e-15, grad=gd, state=md,
                    state2=vd)
    opt.step(None, 1e-2, t=50, clear_grad=True)
    m, v = md.get(), vd.get()
    assert np.all((m == 0) | (np.abs(m) >= tiny)) and np.all((v == 0) | (v >= tiny))
    np.testing.assert_array_equal(m[[0, 1, 2, 4]], 0)
    np.testing.assert_array_equal(v[[0, 1, 2]], 0)
    assert v[4] == 0 and abs(m[3] - 0.9e-3) < 1e-9 and abs(v[3] - 0.99e-6) < 1e-12
    np.testing.assert_allclose(pd.get()[[0, 1, 2, 4]], p[[0, 1, 2, 4]], rtol=0, atol=1e-22)
