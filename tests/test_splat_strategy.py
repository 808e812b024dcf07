"""The splat model's density strategies (clrf/splat/strategies/, splat.strategy) and parameter
table (clrf/splat/params.py): each strategy's refinement on numpy arrays (no device, no
dataset: the cap holds, relocation keeps the count, a pruned Gaussian's moments go with it,
a changed Gaussian's moments start at zero), MCMC's relocation formula against the integral
it preserves, the MCMC kernels (regularisers' gradients, noise on the means) against their
float64 twins and central differences, stiff inputs, and short runs of each strategy through
the model (the cap, checkpoints)."""
import dataclasses
import math

import numpy as np
import pytest

from clrf.references import reference_strategy as rst
from clrf.splat import params as sp
from clrf.splat import strategies as ss
from clrf.splat.config import SplatConfig

from test_splat_model import _model


def _host(n, n_basis=4, seed=0):
    rng = np.random.default_rng(seed)
    return {"means": rng.normal(size=(n, 3)).astype(np.float32),
            "log_scales": rng.normal(-3, 0.5, (n, 3)).astype(np.float32),
            "quats": rng.normal(size=(n, 4)).astype(np.float32),
            "opacity_logits": rng.normal(0, 2, n).astype(np.float32),
            "sh": rng.normal(size=(n, n_basis, 3)).astype(np.float32)}


def _moments(host, seed=1):
    """Moments that name their row: m = row index + 1 everywhere, v random."""
    rng = np.random.default_rng(seed)
    out = {}
    for k in sp.NAMES:
        a = host[k]
        row = (np.arange(len(a)) + 1.0).reshape((-1,) + (1,) * (a.ndim - 1))
        out[f"{k}_m"] = np.broadcast_to(row, a.shape).astype(np.float32)
        out[f"{k}_v"] = rng.uniform(0.1, 1, a.shape).astype(np.float32)
    return out


def _rows_of(moments):
    """Which original row each row's moments came from (0: zeroed), checked consistent over
    every entry."""
    rows = np.asarray(moments["means_m"][:, 0], np.int64)
    for k in sp.NAMES:
        m = moments[f"{k}_m"].reshape(len(rows), -1)
        assert np.all(m == rows[:, None]), k
        v = moments[f"{k}_v"].reshape(len(rows), -1)
        assert np.all((v == 0) == (rows == 0)[:, None]), k
    return rows


# ---- the table and its edit -------------------------------------------------------------------
def test_table_covers_the_rasteriser_and_the_config():
    from clrf.splat.raster import PARAM_NAMES
    assert sp.NAMES == PARAM_NAMES
    assert sp.shapes(5, 9)["sh"] == (5, 9, 3) and sp.shapes(5, 9)["opacity_logits"] == (5,)
    c = SplatConfig(lr_scaling=0.123, lr_feature_dc=0.4, lr_feature_rest=0.02)
    lrs = sp.learning_rates(c, 7.5)
    assert lrs["means"] == 7.5 and lrs["log_scales"] == 0.123 and lrs["sh"] == (0.4, 0.02)
    names = {f.name for f in dataclasses.fields(SplatConfig)}
    assert all(f in names for p in sp.TABLE for f in p.lr)


def test_edit_rows_moves_moments_with_their_rows():
    host = _host(6)
    mo = _moments(host)
    keep = np.array([1, 0, 1, 1, 0, 1], bool)
    new = {k: v[:2] * 0 + 5 for k, v in _host(2, seed=3).items()}
    h2, m2 = sp.edit_rows(host, mo, assign=([3], {"opacity_logits": [9.0]}), keep=keep,
                          append=new)
    assert len(h2["means"]) == 6
    # rows 0, 2, 3, 5 kept (3 reassigned: moments zeroed), then two new ones (zero)
    assert list(_rows_of(m2)) == [1, 3, 0, 6, 0, 0]
    np.testing.assert_array_equal(h2["means"][:4], host["means"][keep])
    assert h2["opacity_logits"][2] == 9.0 and np.all(h2["sh"][4:] == 5)
    assert host["opacity_logits"][3] != 9.0   # the inputs are not modified
    with pytest.raises(KeyError, match="lack"):
        sp.edit_rows(host, mo, append={"means": np.zeros((1, 3))})
    with pytest.raises(ValueError, match="keep"):
        sp.edit_rows(host, mo, keep=np.ones(5, bool))


# ---- default ----------------------------------------------------------------------------------
def _default(resets=0, **kw):
    """The default strategy of SplatConfig() with ``kw`` changed, ``resets`` opacity resets
    done."""
    st = ss.DefaultStrategy.of(dataclasses.replace(SplatConfig(), **kw))
    st.state.resets = resets
    return st


def _stats(a):
    """The default strategy's statistics of an array [3, n] (summed norms, counts, radii)."""
    return dict(zip(ss.DefaultStrategy.ROWS, np.asarray(a, np.float32)))


def test_default_refine_clones_splits_prunes_under_the_cap():
    n = 40
    host = _host(n)
    host["opacity_logits"][:] = 0.0
    host["opacity_logits"][:5] = -10.0                       # transparent: pruned
    host["log_scales"][5:15] = np.log(0.5)                   # large: split
    host["log_scales"][15:] = np.log(1e-3)                   # small: cloned
    mo = _moments(host)
    stats = np.zeros((3, n), np.float32)
    stats[0, :], stats[1, :] = 1.0, 1.0                      # every mean gradient 1 >= 2e-4
    stats[0, 30:] = 0.0                                      # but these ten
    st = _default()
    rng = np.random.default_rng(0)
    h, m, msg = st.refine(host, mo, _stats(stats), extent=1.0, cap=1000, rng=rng)
    assert msg == "densified: 40 -> 60 Gaussians (15 cloned, 10 split, 5 pruned)"
    rows = _rows_of(m)
    # survivors keep their moments in order (pruned and split ones are gone), new rows zero
    assert list(rows[:25]) == list(range(16, 41))
    assert np.all(rows[25:] == 0)
    np.testing.assert_array_equal(h["means"][25:40], host["means"][15:30])        # clones
    split_scales = np.exp(h["log_scales"][40:]).astype(np.float64)
    np.testing.assert_allclose(split_scales, 0.5 / 1.6, rtol=1e-6)
    # the cap: no room beyond it, highest gradients first
    stats[0, 15:30] = np.arange(15)
    h, m, msg = st.refine(host, mo, _stats(stats), extent=1.0, cap=40, rng=rng)
    assert len(h["means"]) == 40 and "5 pruned" in msg
    # after a reset, huge Gaussians go too
    h, m, _ = _default(resets=1).refine(host, mo, _stats(np.zeros((3, n))), extent=1.0,
                                        cap=1000, rng=rng)
    assert len(h["means"]) == 25


def test_default_never_removes_every_gaussian():
    host = _host(4)
    host["opacity_logits"][:] = -20.0
    h, m, _ = _default().refine(host, _moments(host), _stats(np.zeros((3, 4))), extent=1.0,
                                cap=10, rng=np.random.default_rng(0))
    assert len(h["means"]) == 1


# ---- mcmc: relocation -------------------------------------------------------------------------
@pytest.mark.parametrize("o", [0.02, 0.3, 0.9, 0.999, 1 - 1e-7])
@pytest.mark.parametrize("copies", [1, 2, 5, 51])
def test_relocation_keeps_peak_opacity_and_line_integral(o, copies):
    """N copies of (o', s') at one place: the peak opacity 1 - (1 - o')^N is o, and the
    opacity 1 - prod(1 - o' g'(x)) integrated along a line through the centre is what
    o g(x) integrated to (numerical quadrature, independent of the closed form)."""
    o_new, s_new = ss.relocation(np.array([o]), np.array([[0.7, 0.7, 0.7]]), np.array([copies]))
    assert 1 - (1 - o_new[0]) ** copies == pytest.approx(o, rel=1e-12)
    s1 = s_new[0, 0]
    x = np.linspace(-12, 12, 200001)
    trapz = getattr(np, "trapezoid", None) or np.trapz
    one = trapz(o * np.exp(-0.5 * (x / 0.7) ** 2), x)
    many = trapz(1 - (1 - o_new[0] * np.exp(-0.5 * (x / s1) ** 2)) ** copies, x)
    assert many == pytest.approx(one, rel=1e-6)
    if copies == 1:
        assert o_new[0] == pytest.approx(o) and s1 == pytest.approx(0.7)


def test_relocation_matches_the_published_double_sum():
    o, N = 0.6, 7
    on = 1 - (1 - o) ** (1 / N)
    denom = sum(math.comb(i - 1, k) * (-1) ** k * on ** (k + 1) / math.sqrt(k + 1)
                for i in range(1, N + 1) for k in range(i))
    _, s = ss.relocation(np.array([o]), np.array([2.0]), np.array([N]))
    assert s[0] == pytest.approx(2.0 * o / denom, rel=1e-12)
    _, s_cap = ss.relocation(np.array([o]), np.array([2.0]), np.array([500]))
    _, s_51 = ss.relocation(np.array([o]), np.array([2.0]), np.array([51]))
    assert s_cap[0] == s_51[0]   # N clipped to MCMC_MAX_COPIES


def _mcmc(**kw):
    return ss.MCMCStrategy.of(dataclasses.replace(SplatConfig(strategy="mcmc"), **kw))


def test_mcmc_relocation_keeps_the_count_and_growth_holds_the_cap():
    n = 50
    host = _host(n)
    host["opacity_logits"][:10] = -12.0                      # dead
    mo = _moments(host)
    rng = np.random.default_rng(0)
    st = _mcmc(mcmc_growth=1.0, mcmc_spread=0.0)   # copies in place, as published
    h, m, msg = st.refine(host, mo, None, cap=n, rng=rng)
    assert len(h["means"]) == n and msg.startswith("relocated 10 of 50")
    o = rst.sigmoid(h["opacity_logits"])
    assert o.min() > st.settings.min_opacity
    rows = _rows_of(m)
    changed = rows == 0
    # the dead rows now hold copies of live ones (same mean, relocated opacity and scale)
    for i in range(10):
        same = np.flatnonzero(np.all(h["means"] == h["means"][i], 1) & (np.arange(n) >= 10))
        assert len(same) == 1 and changed[same[0]] and changed[i]
        assert h["opacity_logits"][i] == h["opacity_logits"][same[0]]
        assert o[same[0]] < rst.sigmoid(host["opacity_logits"][same[0]])
    # untouched rows keep their values and moments
    keep = np.flatnonzero(~changed)
    assert list(rows[keep]) == list(keep + 1)
    np.testing.assert_array_equal(h["log_scales"][keep], host["log_scales"][keep])
    # growth: 5 % a refinement, never above the cap
    st = _mcmc()
    h, m, msg = st.refine(h, m, None, cap=n + 2, rng=rng)
    assert len(h["means"]) == n + 2 and "added 2" in msg
    h2, m2, _ = st.refine(h, m, None, cap=1000, rng=rng)
    assert len(h2["means"]) == int(1.05 * (n + 2))
    assert _rows_of(m2)[n + 2:].max() == 0


@pytest.mark.parametrize("grow", [False, True])
def test_mcmc_spread_starts_each_copy_off_its_original(grow):
    """splat.mcmc_spread: a copy starts at its original's mean plus ``spread`` times a draw
    from the original's relocated covariance (whitened, the offsets are standard normal
    times spread); the drawn Gaussian stays where it was, and every other value is the one
    the published (spread 0) edit gives."""
    n, dead = 400, 300
    host = _host(n)
    host["log_scales"][:] = np.log([0.02, 0.05, 0.1]).astype(np.float32)
    host["opacity_logits"][:dead] = -12.0
    cap = int(1.05 * n) if grow else n
    runs = {sp: _mcmc(mcmc_growth=1.05 if grow else 1.0, mcmc_spread=sp).refine(
        host, _moments(host), None, cap=cap, rng=np.random.default_rng(3)) for sp in (0.0, 1.5)}
    (h0, m0, _), (h1, m1, _) = runs[0.0], runs[1.5]
    for k in h0:
        if k != "means":
            np.testing.assert_array_equal(h1[k], h0[k])
    for k in m0:
        np.testing.assert_array_equal(m1[k], m0[k])
    moved = np.flatnonzero(np.any(h1["means"] != h0["means"], 1))
    copies = np.r_[np.arange(dead), np.arange(n, len(h0["means"]))] if grow else np.arange(dead)
    assert set(moved) == set(copies)          # only the copies moved; the drawn ones stay
    R = rst.quat_rot(h1["quats"][moved].astype(np.float64))
    off = np.einsum("nji,nj->ni", R, (h1["means"] - h0["means"])[moved].astype(np.float64))
    white = off / np.exp(h1["log_scales"][moved].astype(np.float64)) / 1.5
    assert abs(white.mean()) < 0.15 and abs(white.std() - 1) < 0.1


def test_mcmc_spread_on_by_default_but_not_for_older_checkpoints():
    """splat.mcmc_spread is 1 by default; a checkpoint written before the setting existed
    resumes with its copies in place (0), as it was trained; one that records it keeps it."""
    assert SplatConfig().mcmc_spread == 1.0
    old = {k: v for k, v in SplatConfig(strategy="mcmc").__dict__.items() if k != "mcmc_spread"}
    assert SplatConfig.from_dict(old).mcmc_spread == 0.0
    assert SplatConfig.from_dict(dict(old, mcmc_spread=0.5)).mcmc_spread == 0.5


def test_mcmc_with_no_live_gaussian_adds_nothing_dead():
    host = _host(8)
    host["opacity_logits"][:] = -30.0
    h, m, msg = _mcmc(mcmc_growth=1.0).refine(host, _moments(host), None, cap=8,
                                             rng=np.random.default_rng(0))
    assert len(h["means"]) == 8 and msg.startswith("relocated 0")


# ---- mcmc: the kernels ------------------------------------------------------------------------
def _up(device, a, dtype=np.float32):
    import pyopencl.array as cla
    return cla.to_device(device.queue, np.ascontiguousarray(a, dtype))


def test_mcmc_reg_matches_the_twin_and_central_differences(device):
    from clrf.runtime.programs import launch
    n = 257
    host = _host(n, seed=5)
    host["opacity_logits"][:3] = [-200.0, 200.0, 0.0]        # saturated and balanced
    # the step's own gradients, of the regularisers' size (their sum is compared)
    g_o0 = np.random.default_rng(2).normal(0, 1e-5, n).astype(np.float32)
    g_s0 = np.random.default_rng(3).normal(0, 1e-6, (n, 3)).astype(np.float32)
    go, gs = _up(device, g_o0), _up(device, g_s0)
    prg = device.program("splat_train.cl")
    ro, rs_ = 0.01, 0.03
    launch(device, prg.kernel("splat_mcmc_reg"), n,
           (np.int32(n), _up(device, host["opacity_logits"]).data,
            _up(device, host["log_scales"]).data, go.data, gs.data, np.float32(ro / n),
            np.float32(rs_ / (3 * n))))
    to, ts = rst.mcmc_reg_grads(host["opacity_logits"], host["log_scales"], ro, rs_)
    # the kernel's float32 sum g0 + term: its own rounding, a few float32 epsilons of the two
    # operands (where they nearly cancel, of the result), and 1e-5 of the term's float32 math
    eps = float(np.finfo(np.float32).eps)
    for got, g0, term in ((go.get(), g_o0, to), (gs.get(), g_s0, ts)):
        bound = 1e-5 * np.abs(term) + 4 * eps * (np.abs(g0) + np.abs(term))
        assert np.all(np.abs(got - (g0 + term)) <= bound), np.max(np.abs(got - (g0 + term)))

    def loss(lo, ls):
        return ro * rst.sigmoid(lo).mean() + rs_ * np.exp(ls).mean()
    lo = host["opacity_logits"].astype(np.float64)[3:9]
    ls = host["log_scales"].astype(np.float64)[3:9]
    to, ts = rst.mcmc_reg_grads(lo, ls, ro, rs_)
    h = 1e-6
    for i in range(6):
        e = np.zeros(6)
        e[i] = h
        assert (loss(lo + e, ls) - loss(lo - e, ls)) / (2 * h) == pytest.approx(to[i],
                                                                               rel=1e-6)
        e3 = np.zeros((6, 3))
        e3[i, 1] = h
        assert (loss(lo, ls + e3) - loss(lo, ls - e3)) / (2 * h) == pytest.approx(ts[i, 1],
                                                                                 rel=1e-6)


def test_mcmc_noise_matches_the_twin(device):
    from clrf.runtime.programs import launch
    n = 1000
    host = _host(n, seed=7)
    host["opacity_logits"][:500] = np.linspace(-9, 1, 500)   # transparent: moved
    host["opacity_logits"][500:] = np.linspace(-4, 60, 500)  # opaque: barely or not at all
    host["quats"][0] = 0.0                                   # degenerate: the identity
    host["log_scales"][1] = 60.0                             # exp overflows: left in place
    means = _up(device, host["means"])
    prg = device.program("splat_train.cl")
    scale, seed, step = 80.0, 12345, 77
    launch(device, prg.kernel("splat_mcmc_noise"), n,
           (np.int32(n), means.data, _up(device, host["log_scales"]).data,
            _up(device, host["quats"]).data, _up(device, host["opacity_logits"]).data,
            np.float32(scale), np.uint32(seed), np.uint32(step)))
    got = means.get()
    want = rst.mcmc_noise(host["means"], host["log_scales"], host["quats"],
                          host["opacity_logits"], scale, seed, step)
    assert np.all(np.isfinite(got))
    np.testing.assert_array_equal(got[1], host["means"][1])
    ok = np.arange(n) != 1
    moved = np.abs(want - host["means"]).max(1)
    np.testing.assert_allclose(got[ok], want[ok], rtol=0, atol=1e-6 + 1e-4 * moved[ok].max())
    assert moved[:100].min() > 0 and moved[-100:].max() == 0.0
    # the normals are standard normals, and a step draws new ones
    z = rst.normals(200000, seed, step)
    assert abs(z.mean()) < 0.01 and abs(z.std() - 1) < 0.01
    assert abs(np.corrcoef(z[:, 0], z[:, 1])[0, 1]) < 0.01
    assert not np.array_equal(z[:5], rst.normals(5, seed, step + 1))


# ---- through the model ------------------------------------------------------------------------
def test_mcmc_model_grows_to_the_cap_and_checkpoints(device):
    from clrf.interface import Budget
    from clrf.splat.model import SplatModel
    m, _ = _model(device, strategy="mcmc", init_points=300, max_gaussians=330,
                  densify_min_steps=1)
    assert isinstance(m.strategy, ss.MCMCStrategy)
    p0 = m.host_params()
    msgs = []
    for it in range(12):
        assert np.isfinite(m.train_step(it))
        msg = m.on_iteration(it + 1, Budget(it + 1, 1.0, 0.05 * (it + 1), None))
        msgs.append(msg)
    assert m.n == 330 and any(msg and "relocated" in msg for msg in msgs)
    # mcmc keeps no per-Gaussian statistics (the stats kernel does not run for it)
    assert m.strategy.host_rows() == {} and m.strategy.row_keys() == ()
    # the means moved (Adam and noise; the noise itself: test_mcmc_noise_matches_the_twin)
    assert np.any(m.host_params()["means"][:300] != p0["means"])
    st = m.state_dict()
    assert st["strategy_last_refine"] == m.strategy.state.last_refine > 0
    back = SplatModel.from_state_dict(device, st)
    assert back.strategy.state == m.strategy.state and back.n == 330
    assert isinstance(back.strategy, ss.MCMCStrategy)


@pytest.mark.parametrize("spread", [0.0, 1.0])
def test_mcmc_relocation_in_place_is_the_host_edit(device, spread):
    """At the cap, mcmc relocates on the device (refine_in_place: the opacities down, the drawn
    rows gathered, the changed rows and their zeroed moments put back): the parameters and
    moments equal the host edit's (strategy.refine on the downloaded arrays, the same draws,
    the copies' offsets included); while the count grows it declines and the host edit runs."""
    from clrf.splat.model import SplatModel
    m, _ = _model(device, strategy="mcmc", init_points=300, max_gaussians=300,
                  densify_min_steps=1, mcmc_spread=spread)
    for it in range(3):
        assert np.isfinite(m.train_step(it))
    lo = m.get_rows("opacity_logits")
    lo[::7] = -12.0                                        # 43 dead Gaussians
    m.params["opacity_logits"].set(lo)
    st = m.state_dict()
    twin = SplatModel.from_state_dict(device, st)
    h, mo = m.host_params(), m.host_moments()
    want_h, want_m, want_msg = m.strategy.refine(h, mo, None, cap=300,
                                                 rng=np.random.default_rng(4))
    msg = twin.strategy.refine_in_place(twin, 300, np.random.default_rng(4))
    assert msg == want_msg and msg.startswith("relocated 43 of 300") and twin.n == 300
    got_h, got_m = twin.host_params(), twin.host_moments()
    for k in sp.NAMES:
        np.testing.assert_array_equal(got_h[k], want_h[k].astype(np.float32), err_msg=k)
        for mk in sp.moment_keys(k):
            np.testing.assert_array_equal(got_m[mk], want_m[mk], err_msg=mk)
    assert np.any(got_m["means_m"])
    # gathering rows is the download's rows
    np.testing.assert_array_equal(twin.get_rows("sh", [5, 2, 5]), got_h["sh"][[5, 2, 5]])
    with pytest.raises(IndexError, match="put_rows"):
        twin.put_rows([300], {})
    # under the cap the count grows: not in place
    m2, _ = _model(device, strategy="mcmc", init_points=300, max_gaussians=400)
    assert m2.strategy.refine_in_place(m2, m2.max_count, np.random.default_rng(0)) is None
    assert "added 15" in m2.refine() and m2.n == 315


def test_default_model_resumes_an_old_checkpoint_state(device):
    from clrf.splat.model import SplatModel
    m, _ = _model(device, init_points=200)
    st = m.state_dict()
    for k in list(st):
        if k.startswith("strategy_"):
            del st[k]
    st.update(resets=2, last_reset=40, last_densify=55, densify_frac=0.25)
    back = SplatModel.from_state_dict(device, st)
    assert back.strategy.state == ss.RefineState(55, 0.25, 2, 40)


@pytest.mark.parametrize("field,value", [("strategy", "adc"), ("mcmc_growth", 0.5),
                                         ("mcmc_noise_lr", -1.0), ("mcmc_until", 1.5),
                                         ("init_opacity", 1.0), ("init_scale", -1.0),
                                         ("densify_absgrad_threshold", 0.0),
                                         ("mcmc_spread", -0.5)])
def test_bad_strategy_settings_are_refused(field, value):
    from clrf.training.config import build_config
    with pytest.raises(ValueError, match=f"splat.{field}"):
        build_config("procedural", overrides={"train": {"model": "splat"},
                                              "splat": {field: value}}).validate()


def test_absgrad_statistics_bound_the_plain_ones(device):
    """splat.absgrad: from the same Gaussians and view, each seen Gaussian's statistic (the
    norm of its per-pixel |dL/dxy| sums) is at least the plain one (the norm of the sums), and
    larger where pixels pull it different ways; the strategy's threshold is then
    densify_absgrad_threshold."""
    plain, _ = _model(device, init_points=300)
    absg, _ = _model(device, init_points=300, absgrad=True)
    assert absg.strategy.absgrad and absg.strategy.settings.grad_threshold == 8e-4
    assert plain.strategy.settings.grad_threshold == 2e-4
    plain.train_step(0)
    absg.train_step(0)
    a = np.stack(list(plain.strategy.host_rows().values()))
    b = np.stack(list(absg.strategy.host_rows().values()))
    np.testing.assert_array_equal(a[1], b[1])      # the same Gaussians seen
    seen = a[1] > 0
    assert seen.sum() > 50
    assert np.all(b[0][seen] >= a[0][seen] * (1 - 1e-5) - 1e-12)
    assert np.sum(b[0]) > 1.2 * np.sum(a[0])


def test_first_gaussians_follow_the_strategy():
    """The first Gaussians' opacity and size: the published 0.1 and 1 x the 3-nearest-
    neighbour distance for the default strategy, MCMC's 0.5 and 0.1 x; set ones win."""
    from clrf.data import load_dataset
    from clrf.splat import model as sm
    ds = load_dataset(None)
    base = SplatConfig.from_preset("tiny", init="random", init_points=200)
    h0, _ = sm.initial_host(base, ds, 1000, 3)
    h1, _ = sm.initial_host(dataclasses.replace(base, strategy="mcmc"), ds, 1000, 3)
    h2, _ = sm.initial_host(dataclasses.replace(base, strategy="mcmc", init_opacity=0.2,
                                                init_scale=2.0), ds, 1000, 3)
    np.testing.assert_allclose(rst.sigmoid(h0["opacity_logits"]), 0.1, rtol=1e-6)
    np.testing.assert_allclose(rst.sigmoid(h1["opacity_logits"]), 0.5, rtol=1e-6)
    np.testing.assert_allclose(rst.sigmoid(h2["opacity_logits"]), 0.2, rtol=1e-6)
    np.testing.assert_allclose(np.exp(h1["log_scales"]), 0.1 * np.exp(h0["log_scales"]),
                               rtol=1e-5)
    np.testing.assert_allclose(np.exp(h2["log_scales"]), 2.0 * np.exp(h0["log_scales"]),
                               rtol=1e-5)


# ---- the interface (clrf/splat/strategies/base.py) --------------------------------------------
def test_the_model_keeps_no_strategy_internals(device):
    """The model files name no strategy and hold no statistics: no ``strategy ==`` tests, no
    strategy names, no statistics attributes; a trained model's statistics are its
    strategy's, one float32 row per Gaussian."""
    import re
    from pathlib import Path
    from clrf.splat import config, distributed, model
    for mod in (model, distributed, config):
        text = Path(mod.__file__).read_text()
        assert not re.search(r"strategy\s*(==|!=)|strategy\s+in\s*[(\[{]", text), mod.__name__
        if mod is not config:   # (whose comments describe the strategies)
            assert not re.search(r"[\"'](mcmc|default)[\"']", text), mod.__name__
        assert not re.search(r"\.(accum|max_radius|refine_state|reset_opacity)\b", text), \
            mod.__name__
    m, _ = _model(device, init_points=200)
    m.train_step(0)
    assert not {"accum", "count", "max_radius", "refine_state", "stats"} & set(vars(m))
    rows = m.strategy.host_rows()
    assert list(rows) == list(ss.DefaultStrategy.ROWS)
    assert all(r.shape == (m.n,) and r.dtype == np.float32 for r in rows.values())
    assert rows["grad_count"].max() == 1
    assert set(m.host_moments()) == {mk for k in sp.NAMES for mk in sp.moment_keys(k)}
    # rows overwritten in place start their statistics afresh, the others keep theirs
    seen = np.flatnonzero(rows["grad_count"] > 0)[:3]
    m.put_rows(seen, {})
    for k, v in m.strategy.host_rows().items():
        assert not np.any(v[seen]), k
        np.testing.assert_array_equal(np.delete(v, seen), np.delete(rows[k], seen), err_msg=k)


class _SeenStrategy(ss.Strategy):
    """A strategy for the test: counts the views that see each Gaussian (its one statistic)
    and at each refinement removes the Gaussians no view saw; records what its hooks got."""
    name = "seen"
    FIRST_OPACITY = 0.3
    ROWS = ("seen",)

    @dataclasses.dataclass(frozen=True)
    class Settings:
        schedule: ss.Schedule

        @classmethod
        def of(cls, c):
            return cls(ss.Schedule(c.densify_from, c.densify_until, c.densify_every,
                                   c.densify_min_steps))

    def __init__(self, *args):
        super().__init__(*args)
        self.calls = []

    def step_post_backward(self, params, grads, moments, step, render):
        n = params["means"].shape[0]
        assert set(params) == set(grads) - {"camera"} == set(moments) == set(sp.NAMES)
        assert render.radius.shape == (n,) and render.grad_xy.shape == (n, 2)
        seen = self.rows["seen"].get() + (render.radius.get() > 0)
        self.rows["seen"].set(seen.astype(np.float32))
        self.calls.append(("backward", step, render.width, render.height))

    def step_post_update(self, params, moments, step, lr):
        self.calls.append(("update", step, lr))

    def refine(self, host, moments, rows, *, extent, cap, rng):
        keep = rows["seen"] > 0
        host, moments = sp.edit_rows(host, moments, keep=keep)
        return host, moments, f"kept the {int(keep.sum())} seen of {len(keep)}"


def test_a_registered_strategy_trains_and_checkpoints(device, monkeypatch):
    """A strategy registered in a test (one class, one ``register``): splat.strategy takes its
    name, the first Gaussians take its opacity, a step calls its hooks with the step's arrays
    (before and after the update), its refinement edits the rows, its statistic is zeroed
    after it, follows the rows and comes back from the checkpoint."""
    from clrf.interface import Budget
    from clrf.splat.model import SplatModel
    from clrf.training.config import build_config
    monkeypatch.setattr(ss, "REGISTRY", dict(ss.REGISTRY))
    assert ss.register(_SeenStrategy) is _SeenStrategy
    build_config("procedural", overrides={"train": {"model": "splat"},
                                          "splat": {"strategy": "seen"}}).validate()
    with pytest.raises(TypeError, match="not a Strategy"):
        ss.register(dict)
    m, ds = _model(device, strategy="seen", init_points=300, densify_from=0.0,
                   densify_every=0.25, densify_min_steps=1)
    assert isinstance(m.strategy, _SeenStrategy)
    np.testing.assert_allclose(rst.sigmoid(m.host_params()["opacity_logits"]), 0.3, rtol=1e-6)
    for it in range(3):
        m.train_step(it)
    H, W = ds.hw
    assert m.strategy.calls[:2] == [("backward", 0, W, H), ("update", 1, m.lr_means)]
    assert [c[1] for c in m.strategy.calls] == [0, 1, 1, 2, 2, 3]
    counts = m.strategy.host_rows()["seen"]
    assert counts.max() == 3 and np.all(counts >= 0)
    unseen = int((counts == 0).sum())
    msg = m.on_iteration(3, Budget(3, 1.0, 0.3, None))
    assert msg == f"kept the {300 - unseen} seen of 300" and m.n == 300 - unseen
    assert m.strategy.state.last_refine == 3
    assert not np.any(m.strategy.host_rows()["seen"])   # afresh after the edit
    m.train_step(3)
    st = m.state_dict()
    np.testing.assert_array_equal(st["strategy_row_seen"], m.strategy.host_rows()["seen"])
    back = SplatModel.from_state_dict(device, st)
    assert isinstance(back.strategy, _SeenStrategy) and back.strategy.state.last_refine == 3
    np.testing.assert_array_equal(back.strategy.host_rows()["seen"], st["strategy_row_seen"])


def _old_layout(st: dict, rows: tuple) -> dict:
    """A state as the model wrote it before strategies owned their statistics: the default
    strategy's three rows as ``adam_stats`` [3, n] among the moments (zeros for mcmc)."""
    old = {k: v for k, v in st.items() if not k.startswith("strategy_row_")}
    n = st["param_means"].shape[0]
    old["adam_stats"] = (np.stack([st[f"strategy_row_{k}"] for k in rows]) if rows
                         else np.zeros((3, n), np.float32))
    return old


@pytest.mark.parametrize("strategy", ["default", "mcmc"])
def test_a_checkpoint_of_the_old_layout_loads_renders_and_resumes(device, strategy):
    """A state with the statistics on the model (``adam_stats``) loads with them in the
    strategy's rows, renders as the model did, and resumes exactly as the same state in the
    new layout (parameters and statistics bit for bit, refinements included)."""
    from clrf.interface import Budget
    from clrf.splat.model import SplatModel
    m, ds = _model(device, strategy=strategy, init_points=300, max_gaussians=330,
                   densify_from=0.0, densify_every=0.2, densify_min_steps=1,
                   densify_grad_threshold=1e-7)
    for it in range(3):
        m.train_step(it)
    st = m.state_dict()
    rows = type(m.strategy).ROWS
    assert all(st[k].shape == (300,) for k in m.strategy.row_keys()) and "adam_stats" not in st
    old = SplatModel.from_state_dict(device, _old_layout(st, rows))
    new = SplatModel.from_state_dict(device, st)
    for k, v in m.strategy.host_rows().items():
        np.testing.assert_array_equal(old.strategy.host_rows()[k], v)
    if rows:
        assert old.strategy.host_rows()["grad_count"].max() == 3
    assert old.strategy.state == m.strategy.state
    c2w = ds.poses[ds.split["train"][0]]
    np.testing.assert_array_equal(old.render_image(c2w, ds.intrinsics, ds.hw)["rgb"],
                                  m.render_image(c2w, ds.intrinsics, ds.hw)["rgb"])
    msgs = []
    for r in (old, new):
        r.attach(ds)
        for it in range(3, 6):
            r.train_step(it)
            msgs.append(r.on_iteration(it + 1, Budget(it + 1, 1.0, 0.1 * (it + 1), None)))
    assert msgs[:3] == msgs[3:] and any(msgs)
    for k, v in new.host_params().items():
        np.testing.assert_array_equal(old.host_params()[k], v, err_msg=k)
    for k, v in new.strategy.host_rows().items():
        np.testing.assert_array_equal(old.strategy.host_rows()[k], v, err_msg=k)


def test_a_checkpoint_with_statistics_of_the_wrong_length_is_refused(device):
    from clrf.interface import StateError
    from clrf.splat.model import SplatModel
    m, _ = _model(device, init_points=100)
    st = m.state_dict()
    st["strategy_row_grad_count"] = st["strategy_row_grad_count"][:-1]
    with pytest.raises(StateError, match="grad_count.*expected \\(100,\\)"):
        SplatModel.from_state_dict(device, st)


@pytest.mark.parametrize("n", [1, 7, 257])
def test_default_statistics_match_the_twin(device, n):
    """The default strategy's post-backward hook (splat_densify_stats) over two steps against
    the float64 twin: seen Gaussians (radius > 0) add their NDC-scaled gradient norm and a
    view, non-finite norms add nothing, every seen one raises the largest radius; unseen
    rows keep what they had."""
    from clrf.testing.tolerances import SPLAT_STATS_RTOL
    rng = np.random.default_rng(n)
    st = ss.DefaultStrategy.of(SplatConfig(), device)
    start = [rng.uniform(0, 1, n), rng.integers(0, 4, n).astype(float), rng.uniform(0, 9, n)]
    st.allocate(n, dict(zip(st.ROWS, np.asarray(start, np.float32))))
    want = [np.asarray(a, np.float32) for a in start]
    params = {"means": _up(device, np.zeros((n, 3), np.float32))}
    for step, (W, H) in enumerate([(64, 48), (7, 101)]):
        g = rng.normal(0, 1e-3, (n, 2)).astype(np.float32)
        r = np.where(rng.uniform(size=n) < 0.3, 0.0, rng.uniform(0.5, 20, n)).astype(np.float32)
        r[: n // 7] = -1.0                          # negative: unseen too
        if n > 2:
            g[-1, 0], g[-2, 1] = np.nan, np.inf     # non-finite norms: not counted
            r[-2:] = 3.0
        st.step_post_backward(params, {}, {}, step, ss.RenderInfo(_up(device, r),
                                                                  _up(device, g), W, H))
        want = rst.densify_stats(g, r, W, H, want)
    got = st.host_rows()
    np.testing.assert_allclose(got["grad_accum"], want[0], rtol=SPLAT_STATS_RTOL, atol=0)
    np.testing.assert_array_equal(got["grad_count"], want[1])
    np.testing.assert_array_equal(got["max_radius"], want[2])
    assert np.any(got["grad_count"] > start[1])
