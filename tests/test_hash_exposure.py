"""hash.exposure: the colour transform per training image for ray batches (cl/splat_exposure.cl
exposure_rays, exposure_rays_bg, exposure_rays_grad; clrf/corrections/exposure.py) against its float64
twin (clrf/references/reference_exposure.py) on every OpenCL implementation, and the twin
against central differences, masked (RGBA) captures and plain ones. The model's use of it:
tests/test_hash_exposure_model.py."""
import numpy as np
import pytest

from clrf.corrections.exposure import LOCAL, RayExposure
from clrf.references import reference_exposure as ref
from clrf.runtime.programs import download, upload
from clrf.testing import tolerances as tol

BG = (0.25, 0.5, 1.0)


def _batch(rng, n, n_images, pixels):
    """A ray batch: composite states [n, 8] (colour premultiplied, alpha), targets, indices
    (image 1 of n_images >= 3 left without rays), rows near the identity."""
    alpha = rng.uniform(0, 1, n)
    alpha[:2] = (0.0, 1.0)[:n]                   # all background, and none
    state = np.zeros((n, 8))
    state[:, :3] = rng.uniform(0, 1, (n, 3)) * alpha[:, None]
    state[:, 3] = alpha
    target = rng.uniform(0, 1, (n, 3))
    rows = np.array([v for v in range(n_images) if v != 1 or n_images < 3])
    index = rows[rng.integers(0, len(rows), n)] * pixels + rng.integers(0, pixels, n)
    P = np.tile(ref.IDENTITY, (n_images, 1)) + rng.normal(0, 0.2, (n_images, ref.ROW))
    return (state.astype(np.float32), target.astype(np.float32), index.astype(np.int32),
            P.astype(np.float32))


def _exposure(device, P, pixels, reg=0.0, lr=1e-2, masked=True):
    exp = RayExposure(device, len(P), pixels, lr=lr, reg=reg, masked=masked)
    exp.P.set(np.ascontiguousarray(P))
    return exp


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
@pytest.mark.parametrize("n", [1, 5, LOCAL - 1, LOCAL, 71, 3 * LOCAL + 7, 4099])
def test_rays_and_their_gradient_match_the_twin(device, n, masked):
    rng = np.random.default_rng(n)
    pixels, V = 37, 5
    state, target, index, P = _batch(rng, n, V, pixels)
    q = device.queue
    exp = _exposure(device, P, pixels, reg=0.3, masked=masked)
    st, idx = upload(q, state), upload(q, index)
    eff, sq = exp.forward(st, BG, upload(q, target), idx)
    r, want_eff, want_sq, want_bgt = ref.rays(state, BG, target, P, index, pixels, masked)
    for got, want in ((exp._resid, r), (eff, want_eff), (exp._bgt, want_bgt)):
        np.testing.assert_allclose(download(got), want, rtol=tol.EXPOSURE_GRAD_RTOL,
                                   atol=4 * tol.EXPOSURE_ATOL)
    np.testing.assert_allclose(download(sq), want_sq, rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=4 * tol.EXPOSURE_ATOL)
    scale = 1.0 / (3 * n)
    exp.lr = 1e-30       # the step leaves P (to float32) where it was: the gradient is read
    exp.backward_and_step(st, BG, idx, scale)
    want = ref.rays_grad(state, BG, r, P, index, pixels, scale, 0.3, masked)
    got = download(exp.grad).reshape(V, ref.ROW)
    np.testing.assert_allclose(got, want, rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=tol.EXPOSURE_SUM_ATOL_PER_SQRT_N * n ** 0.5 * scale)
    assert np.all(got[1] == 0)      # a row without rays: neither data nor pull


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_clipped_rays_match_the_twin_and_its_differences(device, masked):
    """hash.exposure_clip: the loss sees the transformed colour clamped to [0, 1]; a channel
    outside passes no gradient. The kernel's residuals, targets, squared errors and rows'
    gradient against the twin with clip (rows brightened by 1.6 so that about a third of the
    channels clip), and the twin's gradient against central differences of its clamped loss
    (no channel within the step of 0 or 1, where the clamp has its kinks)."""
    rng = np.random.default_rng(5)
    pixels, V, n = 31, 4, 2 * LOCAL + 9
    state, target, index, P = _batch(rng, n, V, pixels)
    P[:, :9] *= 1.6
    q = device.queue
    exp = RayExposure(device, V, pixels, lr=1e-30, reg=0.0, masked=masked, clip=True)
    exp.P.set(np.ascontiguousarray(P))
    st, idx = upload(q, state), upload(q, index)
    eff, sq = exp.forward(st, BG, upload(q, target), idx)
    r, want_eff, want_sq, want_bgt = ref.rays(state, BG, target, P, index, pixels, masked,
                                              clip=True)
    unclipped = ref.rays(state, BG, target, P, index, pixels, masked)[0]
    clipped = (r == 0) & (unclipped != 0)
    assert 0.15 < clipped.mean() < 0.6, clipped.mean()
    for got, want in ((exp._resid, r), (eff, want_eff), (exp._bgt, want_bgt), (sq, want_sq)):
        np.testing.assert_allclose(download(got), want, rtol=tol.EXPOSURE_GRAD_RTOL,
                                   atol=4 * tol.EXPOSURE_ATOL)
    assert np.all(download(exp._resid)[clipped] == 0)
    scale = 1.0 / (3 * n)
    exp.backward_and_step(st, BG, idx, scale)
    want = ref.rays_grad(state, BG, r, P, index, pixels, scale, 0.0, masked)
    np.testing.assert_allclose(download(exp.grad).reshape(V, ref.ROW), want,
                               rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=tol.EXPOSURE_SUM_ATOL_PER_SQRT_N * n ** 0.5 * scale)
    P64, h = P.astype(np.float64), 1e-6
    for v, e in ((0, 0), (2, 4), (3, 10), (0, 11)):
        Pp, Pm = P64.copy(), P64.copy()
        Pp[v, e] += h
        Pm[v, e] -= h
        fd = (ref.rays_loss(state, BG, target, Pp, index, pixels, scale, masked, clip=True)
              - ref.rays_loss(state, BG, target, Pm, index, pixels, scale, masked,
                              clip=True)) / (2 * h)
        assert abs(fd - want[v, e]) <= 1e-6 * max(1.0, abs(fd)), (v, e, fd, want[v, e])


@pytest.mark.parametrize("matrix", ["diagonal", "gain"])
def test_diagonal_rows_train_gains_and_offsets_only(device, matrix):
    """hash.exposure_matrix=diagonal (gain): the kernel's gradient is the twin's with the
    entries it does not train 0 (A's off-diagonal ones; with gain b too; the trained ones are
    the full model's), Adam leaves those entries at exactly 0, and so does recentring."""
    rng = np.random.default_rng(17)
    pixels, V, n = 29, 4, 3 * LOCAL + 5
    state, target, index, P = _batch(rng, n, V, pixels)
    k = ref.MATRICES.index(matrix)
    on, off = ref.TRAINED[k], ~ref.TRAINED[k]
    P[:, off] = 0.0                                  # rows of gains (and offsets)
    q = device.queue
    exp = RayExposure(device, V, pixels, lr=1e-30, reg=0.3, masked=True, matrix=matrix)
    exp.P.set(np.ascontiguousarray(P))
    st, idx = upload(q, state), upload(q, index)
    exp.forward(st, BG, upload(q, target), idx)
    r = ref.rays(state, BG, target, P, index, pixels)[0]
    scale = 1.0 / (3 * n)
    exp.backward_and_step(st, BG, idx, scale)
    got = download(exp.grad).reshape(V, ref.ROW)
    want = ref.rays_grad(state, BG, r, P, index, pixels, scale, 0.3, matrix=k)
    full = ref.rays_grad(state, BG, r, P, index, pixels, scale, 0.3)
    np.testing.assert_allclose(got, want, rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=tol.EXPOSURE_SUM_ATOL_PER_SQRT_N * n ** 0.5 * scale)
    assert np.all(got[:, off] == 0)
    np.testing.assert_array_equal(want[:, on],
                                  full[:, on])
    assert np.abs(full[[0, 2, 3]][:, off]).min() > 0   # full would move them
    exp.lr = 0.05
    for _ in range(3):
        exp.forward(st, BG, upload(q, target), idx)
        exp.backward_and_step(st, BG, idx, scale)
    rows = exp.rows()
    assert np.all(rows[:, off] == 0)
    assert np.abs(rows[[0, 2, 3]] - P[[0, 2, 3]])[:, on].min() > 0
    exp.recentre()
    assert np.all(exp.rows()[:, off] == 0)


def test_background_share_matches_the_twin(device):
    """exposure_rays_bg adds -2 s dt_j bgt_i to the live samples' dL/dsigma only."""
    from types import SimpleNamespace
    rng = np.random.default_rng(12)
    counts = np.array([0, 3, 1, 7, 2])
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    m = int(offsets[-1])
    dt = rng.uniform(0.01, 0.1, m).astype(np.float32)
    sigma = rng.uniform(0, 5, m).astype(np.float32)
    sigma[::4] = 0.0                                # not live: untouched
    bgt = rng.normal(0, 1, len(counts)).astype(np.float32)
    dsigma = rng.normal(0, 1, m).astype(np.float32)
    q = device.queue
    exp = _exposure(device, np.tile(ref.IDENTITY, (2, 1)).astype(np.float32), 10)
    exp._bgt = upload(q, bgt)
    pk = SimpleNamespace(n=len(counts), m=m, offsets=upload(q, offsets), dt=upload(q, dt))
    got = upload(q, dsigma)
    exp.add_background(pk, upload(q, sigma), 0.25, got)
    want = ref.rays_bg(offsets, dt, sigma, bgt, 0.25, dsigma)
    np.testing.assert_allclose(download(got), want, rtol=1e-6, atol=1e-7)
    assert np.array_equal(download(got)[sigma == 0], dsigma[sigma == 0])


def _composite(sig, dt, col, background):
    """float64 composite of one ray: (state [8], rgb on ``background``)."""
    T, c = 1.0, np.zeros(3)
    for s_, d_, k in zip(sig, dt, col):
        w = T * (1 - np.exp(-s_ * d_))
        c += w * k
        T *= np.exp(-s_ * d_)
    st = np.zeros(8)
    st[:3], st[3] = c, 1 - T
    return st, c + T * np.asarray(background)


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_twin_gradient_matches_finite_differences(masked):
    """rays_grad against central differences of rays_loss + the pulls (each row's weighted by
    its share of the batch); the colour's gradient through eff, and the densities' (the
    marcher's black-background terms plus the background's share) against central differences
    of a ray's loss in its samples' densities."""
    rng = np.random.default_rng(4)
    pixels, V, n = 11, 3, 40
    state, target, index, P = (a.astype(np.float64) if a.dtype != np.int32 else a
                               for a in _batch(rng, n, V, pixels))
    scale, reg = 1.0 / (3 * n), 0.7
    share = np.bincount(index // pixels, minlength=V) / n

    def loss(P_):
        pull = sum(reg * share[v] * np.sum((P_[v] - ref.IDENTITY) ** 2) for v in range(V))
        return ref.rays_loss(state, BG, target, P_, index, pixels, scale, masked) + pull
    r, eff, _, _ = ref.rays(state, BG, target, P, index, pixels, masked)
    g = ref.rays_grad(state, BG, r, P, index, pixels, scale, reg, masked)
    h = 1e-6
    for v in range(V):
        for k in range(ref.ROW):
            Pp, Pm = P.copy(), P.copy()
            Pp[v, k] += h
            Pm[v, k] -= h
            fd = (loss(Pp) - loss(Pm)) / (2 * h)
            assert fd == pytest.approx(g[v, k], rel=tol.FD_RTOL, abs=tol.FD_ATOL)
    # one ray of four samples: dL/dsigma_j of L = s |A c + a b + T bg - target|^2
    sig, dt = rng.uniform(0.5, 3, 4), rng.uniform(0.05, 0.3, 4)
    col = rng.uniform(0, 1, (4, 3))
    tgt = rng.uniform(0, 1, (1, 3))
    row = P[2:3]

    def ray_loss(sig_):
        st, _ = _composite(sig_, dt, col, BG)
        return ref.rays_loss(st[None], BG, tgt, row, np.array([0]), 1, scale, masked)
    st, _ = _composite(sig, dt, col, BG)
    r1, eff1, _, bgt1 = ref.rays(st[None], BG, tgt, row, np.array([0]), 1, masked)
    # the marcher's backward on black, given eff: g = 2 s (c - eff) = 2 s A^T r
    gc = 2 * scale * (st[:3] - eff1[0])
    T, prefix, total = 1.0, 0.0, gc @ st[:3]
    analytic = []
    for s_, d_, k in zip(sig, dt, col):
        w = T * (1 - np.exp(-s_ * d_))
        T *= np.exp(-s_ * d_)
        prefix += w * (gc @ k)
        analytic.append(d_ * (T * (gc @ k) - (total - prefix)))
    analytic = ref.rays_bg([0, 4], dt, sig, bgt1, scale, analytic)
    for j in range(4):
        sp, sm = sig.copy(), sig.copy()
        sp[j] += h
        sm[j] -= h
        fd = (ray_loss(sp) - ray_loss(sm)) / (2 * h)
        assert fd == pytest.approx(analytic[j], rel=tol.FD_RTOL, abs=tol.FD_ATOL)
    # and in its samples' colours: w_j dL/dc = w_j 2 s A^T r
    for j, c in ((0, 0), (2, 1), (3, 2)):
        cp, cm = col.copy(), col.copy()
        cp[j, c] += h
        cm[j, c] -= h
        fd = (ref.rays_loss(_composite(sig, dt, cp, BG)[0][None], BG, tgt, row,
                            np.array([0]), 1, scale, masked)
              - ref.rays_loss(_composite(sig, dt, cm, BG)[0][None], BG, tgt, row,
                              np.array([0]), 1, scale, masked)) / (2 * h)
        Tj = np.exp(-np.sum(sig[:j] * dt[:j]))
        w = Tj * (1 - np.exp(-sig[j] * dt[j]))
        assert fd == pytest.approx(w * gc[c], rel=tol.FD_RTOL, abs=tol.FD_ATOL)


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_identity_rows_leave_the_loss_as_without_them(device, masked):
    """Under the identity the loss is the plain squared error of c + T bg, and the marcher on
    black with eff has the gradient it has on bg with the target."""
    rng = np.random.default_rng(2)
    state, target, index, _ = _batch(rng, 300, 4, 50)
    P = np.tile(ref.IDENTITY, (4, 1)).astype(np.float32)
    q = device.queue
    exp = _exposure(device, P, 50, masked=masked)
    eff, sq = exp.forward(upload(q, state), BG, upload(q, target), upload(q, index))
    x = state[:, :3] + (1 - state[:, 3:4]) * np.asarray(BG)
    np.testing.assert_allclose(download(sq), np.sum((x - target) ** 2, axis=1), rtol=1e-5,
                               atol=1e-7)
    np.testing.assert_allclose(state[:, :3] - download(eff), x - target, atol=1e-6)


def test_adam_steps_every_row_and_the_pull_alone_returns_to_identity(device):
    rng = np.random.default_rng(8)
    state, target, index, P = _batch(rng, 500, 4, 20)
    q = device.queue
    exp = _exposure(device, P, 20, reg=1.0, lr=0.02)
    st, idx = upload(q, state), upload(q, index)
    want_P, want_m, want_v = P.astype(np.float64), np.zeros_like(P, np.float64), \
        np.zeros_like(P, np.float64)
    for t in (1, 2, 3):
        rows = exp.rows()
        exp.forward(st, BG, upload(q, target), idx)
        r = ref.rays(state, BG, target, rows, index, 20)[0]
        g = ref.rays_grad(state, BG, r, rows, index, 20, 1e-3, 1.0)
        exp.backward_and_step(st, BG, idx, 1e-3)
        want_m = 0.9 * want_m + 0.1 * g
        want_v = 0.999 * want_v + 0.001 * g * g
        want_P = want_P - 0.02 * (want_m / (1 - 0.9 ** t)) / (
            np.sqrt(want_v / (1 - 0.999 ** t)) + 1e-15)
    np.testing.assert_allclose(exp.rows(), want_P, rtol=0, atol=tol.EXPOSURE_ADAM_ATOL)
    assert exp.steps == 3
    # targets that are the rays' own colours under the transforms: no data gradient, only
    # the pull, so every row that has rays moves toward the identity
    before = np.abs(exp.rows() - ref.IDENTITY).sum()
    for _ in range(5):
        rows = exp.rows()
        own = ref.rays(state, BG, np.zeros_like(target), rows, index, 20)[0]
        exp.forward(st, BG, upload(q, own.astype(np.float32)), idx)
        exp.backward_and_step(st, BG, idx, 1e-3)
    assert np.abs(exp.rows() - ref.IDENTITY).sum() < before


def test_stiff_rays_stay_finite(device):
    """Saturated and empty rays, huge targets: residuals and the step stay finite."""
    n, pixels = 130, 10
    state = np.zeros((n, 8), np.float32)
    state[::2, :4] = 1.0                       # opaque white
    target = np.full((n, 3), 1e18, np.float32)
    index = (np.arange(n) % 20).astype(np.int32)
    q = device.queue
    exp = RayExposure(device, 2, pixels, lr=0.01, reg=1e-3)
    st, idx = upload(q, state), upload(q, index)
    eff, sq = exp.forward(st, BG, upload(q, target), idx)
    assert np.all(np.isfinite(download(eff))) and np.all(np.isfinite(download(sq)))
    exp.backward_and_step(st, BG, idx, 1.0 / (3 * n))
    rows = exp.rows()
    assert np.all(np.isfinite(rows)) and np.abs(rows - ref.IDENTITY).max() <= 0.01 + 1e-6


@pytest.mark.parametrize("n", [1, 37])
def test_each_rays_own_background_matches_the_twin(device, n):
    """RayExposure.behind (a masked capture on a renderer that composites the background
    itself): A_v^-1 (bg - b_v) of each ray's row, bg for a singular row and a non-finite one,
    and a render on it transformed is the masked pixel."""
    rng = np.random.default_rng(n)
    _, _, index, P = _batch(rng, n, 5, 16)
    P[3, :9] = (1, 2, 3, 2, 4, 6, 0, 1, 1)           # singular: rows 1 and 2 dependent
    P[4, 0] = np.inf
    index[: min(n, 2)] = np.array([3 * 16 + 1, 4 * 16])[: min(n, 2)]
    exp = _exposure(device, P, 16)
    q = device.queue
    got = exp.behind(BG, upload(q, index)).get()
    want = ref.rays_behind(P, index, 16, BG)
    np.testing.assert_allclose(got, want, rtol=tol.EXPOSURE_GRAD_RTOL, atol=tol.EXPOSURE_ATOL)
    if n > 2:
        assert np.abs(want - np.asarray(BG)).max() > 0.05     # moved off bg where A is regular
    np.testing.assert_array_equal(got[: min(n, 2)], np.tile(BG, (min(n, 2), 1)))
    # the transform of a whole pixel rendered on it is the masked capture's pixel
    c = rng.uniform(0, 1, (n, 3)) * 0.5
    T = rng.uniform(0, 1, n)
    for i in range(min(n, 2), n):
        v = index[i] // 16
        if v >= 3:
            continue                                 # the rows that fall back to bg
        A, b = ref.split(P[v].astype(np.float64))
        whole = A @ (c[i] + T[i] * want[i]) + b
        masked = ref.shown(c[i][None], T[i], BG, P.astype(np.float64), v, masked=True)[0]
        np.testing.assert_allclose(whole, masked, atol=1e-9)


def test_the_rate_falls_log_linearly_to_its_final_one(device):
    """<model>.lr_exposure_final: the ray transforms' rate falls log-linearly over the budget
    (constant where it is not given), and a final rate above the first is refused."""
    from clrf.hash.config import HashConfig
    exp = RayExposure(device, 3, 10, lr=1e-3, reg=0.0, lr_final=1e-5)
    for f, want in ((0.0, 1e-3), (0.5, 1e-4), (1.0, 1e-5)):
        exp.schedule(f)
        assert exp.lr == pytest.approx(want, rel=1e-9)
    flat = RayExposure(device, 3, 10, lr=1e-3, reg=0.0)
    flat.schedule(0.7)
    assert flat.lr == 1e-3
    bad = [key for ok, key, _ in HashConfig(lr_exposure=1e-3, lr_exposure_final=2e-3).checks()
           if not ok]
    assert bad == ["hash.lr_exposure_final"]
    for final in (0.0, 1e-5):    # 0: a constant rate; a lower lr_exposure alone is fine too
        assert all(ok for ok, _, _ in HashConfig(lr_exposure=1e-4,
                                                 lr_exposure_final=final).checks())


def _spread_rows(rng, n, sigma):
    """Rows P [n, 12] whose diagonal gains are exp(N(0, sigma)), the rest the identity's."""
    P = np.tile(ref.IDENTITY, (n, 1))
    P[:, [0, 4, 8]] = np.exp(rng.normal(0, sigma, (n, 3)))
    return P.astype(np.float32)


def test_a_steady_capture_goes_back_to_the_identity(device):
    """<model>.exposure_steady_spread: at exposure_steady_after of the budget, rows whose
    gains spread less than the limit return to the identity with their Adam moments cleared
    and their rates scaled by exposure_steady_rate, once; the finding is in the checkpoint
    (a resumed run keeps its scaled rates and checks no more) and in eval.json's summary."""
    from clrf.corrections.exposure import gain_spread
    rng = np.random.default_rng(3)
    P = _spread_rows(rng, 40, 0.02)
    exp = RayExposure(device, 40, 10, lr=1e-3, reg=0.0, lr_final=1e-4, steady_spread=0.05,
                      steady_rate=0.01, steady_after=0.2)
    exp.P.set(P)
    exp.opt.state.fill(0.5)
    exp.steps = 7
    exp.schedule(0.1)                                  # before the check: nothing changes
    assert exp.steady is None and exp.summary() == {}
    np.testing.assert_array_equal(exp.rows(), P)
    assert exp.lr == pytest.approx(1e-3 * (1e-4 / 1e-3) ** 0.1, rel=1e-9)
    exp.schedule(0.25)
    assert exp.steady is True
    assert exp.spread_seen == pytest.approx(gain_spread(P), rel=1e-6)
    np.testing.assert_array_equal(exp.rows(), np.tile(ref.IDENTITY, (40, 1)))
    assert not download(exp.opt.state).any() and not download(exp.opt.state2).any()
    assert exp.lr == pytest.approx(1e-5 * (1e-6 / 1e-5) ** 0.25, rel=1e-9)
    exp.schedule(0.5)                                  # once: the rates are scaled no more
    assert exp.lr == pytest.approx(1e-5 * (1e-6 / 1e-5) ** 0.5, rel=1e-9)
    summary = exp.summary()
    assert summary["steady"] is True and "identity" in exp.report(summary)
    assert "steady" in exp.describe()
    again = RayExposure(device, 40, 10, lr=1e-3, reg=0.0, lr_final=1e-4, steady_spread=0.05,
                        state=exp.state_dict())
    assert again.steady is True and again.lr_start == pytest.approx(1e-5, rel=1e-9)
    again.schedule(0.5)
    assert again.lr == pytest.approx(exp.lr, rel=1e-9)
    # a checkpoint from before the check: unchecked, so its run checks on resuming
    old = {k: v for k, v in exp.state_dict().items() if "steady" not in k and "seen" not in k}
    assert RayExposure(device, 40, 10, lr=1e-3, reg=0.0, state=old).steady is None


@pytest.mark.parametrize("sigma, limit", [(0.2, 0.05), (0.02, 0.0)],
                         ids=["changing-exposure", "check-off"])
def test_rows_of_a_changing_exposure_are_kept(device, sigma, limit):
    """Gains that spread more than the limit (lego_400 with changed exposures: 0.17), or a
    limit of 0, leave the rows and rates as they are."""
    rng = np.random.default_rng(4)
    P = _spread_rows(rng, 40, sigma)
    exp = RayExposure(device, 40, 10, lr=1e-3, reg=0.0, steady_spread=limit)
    exp.P.set(P)
    exp.steps = 7
    exp.schedule(0.9)
    np.testing.assert_array_equal(exp.rows(), P)
    assert exp.lr == 1e-3
    assert exp.steady is (None if limit == 0 else False)


@pytest.mark.parametrize("kind", ["hash", "grid", "nerf"])
def test_bad_steady_settings_are_refused(kind):
    from clrf.grid.config import GridConfig
    from clrf.hash.config import HashConfig
    from clrf.nerf.config import NerfConfig
    make = {"hash": HashConfig, "grid": GridConfig, "nerf": NerfConfig}[kind]
    for key, value in (("exposure_steady_spread", -0.1), ("exposure_steady_rate", 0.0),
                       ("exposure_steady_rate", 2.0), ("exposure_steady_after", 1.0)):
        bad = [k for ok, k, _ in make(**{key: value}).checks() if not ok]
        assert bad == [f"{kind}.{key}"], (key, value, bad)
