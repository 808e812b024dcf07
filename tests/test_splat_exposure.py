"""The splat model's colour transform per training image (cl/splat_exposure.cl,
clrf/corrections/exposure.py) against its float64 twin (clrf/references/reference_exposure.py), on
every OpenCL implementation: apply, the backward pass (dL/drgb and dL/dP, also against finite
differences of the twin), the Adam step with its pull toward the identity, stiff inputs, and
NeRF-W's half-fitted protocol. The model's use of it: tests/test_splat_exposure_model.py."""
import numpy as np
import pytest

from clrf.references import reference_exposure as ref
from clrf.runtime.programs import download, upload
from clrf.corrections.exposure import CHUNK, Exposure
from clrf.testing import tolerances as tol

SIZES = [1, 7, CHUNK - 1, CHUNK, CHUNK + 1, 3 * CHUNK + 5]


def _rows(rng, n_images):
    P = np.tile(ref.IDENTITY, (n_images, 1)) + rng.normal(0, 0.2, (n_images, ref.ROW))
    return P.astype(np.float32)


def _exposure(device, P, masked=False):
    exp = Exposure(device, len(P), lr=0.01, reg=0.0, masked=masked)
    exp.P = upload(device.queue, np.ascontiguousarray(P))
    return exp


def test_the_configs_name_the_kernels_modes_in_the_twins_order():
    """splat.exposure_matrix and hash.exposure_matrix are indexes of the kernels' ``matrix``
    argument; the corrections' settings, which the configs import, keep their own copy of the
    names (they may not import the twin)."""
    from clrf.corrections import EXPOSURE_MATRICES
    assert EXPOSURE_MATRICES == ref.MATRICES


@pytest.mark.parametrize("n", SIZES)
def test_apply_matches_the_twin(device, n):
    rng = np.random.default_rng(n)
    P = _rows(rng, 3)
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    exp = _exposure(device, P)
    got = download(exp.apply(upload(device.queue, rgb), 2))
    np.testing.assert_allclose(got, ref.apply(rgb, P, 2), rtol=tol.EXPOSURE_RTOL,
                               atol=tol.EXPOSURE_ATOL)


BG = (1.0, 0.75, 0.25)


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
@pytest.mark.parametrize("n", SIZES)
def test_backward_matches_the_twin(device, n, masked):
    rng = np.random.default_rng(100 + n)
    P = _rows(rng, 4)
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    T = rng.uniform(0, 1, n).astype(np.float32)
    g = rng.normal(0, 1, (n, 3)).astype(np.float32)
    exp = _exposure(device, P, masked)
    q = device.queue
    grad_rgb, partials = exp.backward(upload(q, rgb), upload(q, T), BG, upload(q, g), 1)
    want_rgb, want_p = ref.backward(rgb, g, P, 1, T if masked else None, BG)
    np.testing.assert_allclose(download(grad_rgb), want_rgb, rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=tol.EXPOSURE_ATOL)
    got_p = download(partials).astype(np.float64).sum(axis=0)
    np.testing.assert_allclose(got_p, want_p, rtol=tol.EXPOSURE_GRAD_RTOL,
                               atol=tol.EXPOSURE_SUM_ATOL_PER_SQRT_N * n ** 0.5)


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_twin_gradient_matches_finite_differences(masked):
    """What the loss sees (``shown``: masked, A c + (1 - T) b + T bg; else A (c + T bg) + b) is
    A rgb' + b of the render on bg' (A^-1 (bg - b) masked, else bg); the twin's dL/dP (bg' held
    as that function of P) and dL/drgb' = A^T g against central differences of
    L = sum(w * shown) in P, in the premultiplied colour c and in T (the rasteriser's
    background term, (A^T g).bg')."""
    rng = np.random.default_rng(5)
    P = _rows(rng, 2).astype(np.float64)
    c = rng.uniform(0, 1, (9, 3))
    T = rng.uniform(0, 1, 9)
    w = rng.normal(0, 1, (9, 3))
    bg2 = ref.render_background(P, 1, BG, masked)
    rgb2 = c + T[:, None] * bg2
    np.testing.assert_allclose(ref.apply(rgb2, P, 1), ref.shown(c, T, BG, P, 1, masked),
                               atol=1e-12)
    grad_rgb, grad_p = ref.backward(rgb2, w, P, 1, T if masked else None, bg2)
    h = 1e-6

    def L(P_=P, c_=c, T_=T):
        return np.sum(w * ref.shown(c_, T_, BG, P_, 1, masked))
    for k in range(ref.ROW):
        Pp, Pm = P.copy(), P.copy()
        Pp[1, k] += h
        Pm[1, k] -= h
        fd = (L(P_=Pp) - L(P_=Pm)) / (2 * h)
        assert fd == pytest.approx(grad_p[k], rel=tol.FD_RTOL, abs=tol.FD_ATOL)
    for i in range(3):
        x1, x0 = c.copy(), c.copy()
        x1[4, i] += h
        x0[4, i] -= h
        fd = (L(c_=x1) - L(c_=x0)) / (2 * h)
        assert fd == pytest.approx(grad_rgb[4, i], rel=tol.FD_RTOL, abs=tol.FD_ATOL)
    t1, t0 = T.copy(), T.copy()
    t1[6] += h
    t0[6] -= h
    fd = (L(T_=t1) - L(T_=t0)) / (2 * h)
    assert fd == pytest.approx(grad_rgb[6] @ bg2, rel=tol.FD_RTOL, abs=tol.FD_ATOL)


def test_adam_step_matches_the_twin_and_pulls_toward_identity(device):
    rng = np.random.default_rng(9)
    P = _rows(rng, 3)
    n = 2 * CHUNK + 3
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    g = rng.normal(0, 1e-3, (n, 3)).astype(np.float32)
    exp = Exposure(device, 3, lr=0.02, reg=0.5, masked=True)
    exp.P = upload(device.queue, np.ascontiguousarray(P))
    want_P, want_m, want_v = P.astype(np.float64), np.zeros((3, 12)), np.zeros((3, 12))
    T = rng.uniform(0, 1, n).astype(np.float32)
    q = device.queue
    for t in (1, 2, 3):
        rows = download(exp.P)
        _, grad_p = ref.backward(rgb, g, rows, 2, T, BG)
        exp.backward_and_step(upload(q, rgb), upload(q, T), BG, upload(q, g), 2)
        want_P, want_m, want_v = ref.adam(want_P, want_m, want_v, 2, grad_p, 0.02, 0.5, 0.9,
                                          0.999, 1e-15, t)
    got = exp.rows()
    np.testing.assert_allclose(got, want_P, rtol=0, atol=tol.EXPOSURE_ADAM_ATOL)
    assert np.array_equal(got[:2], P[:2])             # other rows untouched
    assert exp.steps.tolist() == [0, 0, 3]
    # a zero image gradient: only the pull, so the row moves toward the identity
    before = np.abs(got[2] - ref.IDENTITY).sum()
    for _ in range(5):
        exp.backward_and_step(upload(q, rgb), upload(q, T), BG, upload(q, np.zeros_like(g)),
                              2)
    assert np.abs(exp.rows()[2] - ref.IDENTITY).sum() < before


def test_stiff_inputs_leave_finite_rows(device):
    """Huge and non-finite gradients: a NaN gradient skips the step; huge ones move a row by
    about the learning rate (Adam's normalised step), never to inf."""
    exp = Exposure(device, 2, lr=0.01, reg=1e-3, masked=True)
    q = device.queue
    rgb = np.full((CHUNK + 1, 3), 0.5, np.float32)
    T = upload(q, np.linspace(0, 1, CHUNK + 1).astype(np.float32))
    for scale in (1e30, 0.0):
        g = np.full_like(rgb, scale)
        exp.backward_and_step(upload(q, rgb), T, BG, upload(q, g), 0)
    rows = exp.rows()
    assert np.all(np.isfinite(rows))
    assert np.abs(rows[0] - ref.IDENTITY).max() <= 0.02 + 1e-6
    g = np.full_like(rgb, np.nan)
    before = exp.rows()
    exp.backward_and_step(upload(q, rgb), T, BG, upload(q, g), 0)
    assert np.array_equal(exp.rows(), before)
    # the background to render on: A^-1 (bg - b), and bg itself where A is singular
    assert np.allclose(exp.background(0, BG), ref.render_background(rows, 0, BG), atol=1e-5)
    exp.P.set(np.zeros((2, ref.ROW), np.float32))
    assert exp.background(1, BG) == BG


def test_half_fitted_protocol_recovers_a_colour_change():
    rng = np.random.default_rng(3)
    render = rng.uniform(0.1, 0.7, (16, 20, 3))     # no channel leaves [0, 1] below
    A = np.diag([1.3, 0.9, 1.1])
    target = np.clip(render @ A.T + 0.02, 0, 1)
    fitted, plain = ref.half_fitted_psnr(render, target)
    assert fitted > 100 and plain < 30


@pytest.mark.parametrize("masked", [False, True], ids=["rgb", "masked"])
def test_shared_gain_score_is_the_least_squares_gain_of_all_views(masked):
    """shared_gain_psnr from the views' gain_sums equals the brute-force figure: the one
    per-channel gain minimising the squared error of every view's light together (a finer
    gain either way does worse), then each view's PSNR under it; views whose exposure all
    differ from the render by one gain score without error."""
    rng = np.random.default_rng(11)
    bg = np.array([1.0, 1.0, 1.0])
    views = []
    for n in (30, 50, 40):
        r = rng.uniform(0, 0.8, (n, 3))
        acc = rng.uniform(0.2, 1, n)
        views.append((r, acc, np.clip(r * 1.1 + rng.normal(0, 0.05, (n, 3)), 0, 1)))

    def light(x, acc):
        return x - (1 - acc)[:, None] * bg if masked else x

    def per_view(g):
        return np.array([-10 * np.log10(np.mean((light(r, a) * g - light(t, a)) ** 2))
                         for r, a, t in views])
    gain, psnr = ref.shared_gain_psnr([ref.gain_sums(r, a, t, bg, masked) for r, a, t in views])
    x = np.concatenate([light(r, a) for r, a, _ in views])
    y = np.concatenate([light(t, a) for _, a, t in views])
    np.testing.assert_allclose(gain, (x * y).sum(0) / (x * x).sum(0), rtol=1e-12)
    np.testing.assert_allclose(psnr, per_view(gain), rtol=1e-10)
    total = lambda g: np.sum((x * g - y) ** 2)   # noqa: E731
    for d in (1e-3, -1e-3):
        assert total(gain * (1 + d)) > total(gain)
    exact = [(r, a, (light(r, a) * [1.2, 0.9, 1.05] + ((1 - a)[:, None] * bg if masked else 0)))
             for r, a, _ in views]
    gain, psnr = ref.shared_gain_psnr([ref.gain_sums(r, a, t, bg, masked) for r, a, t in exact])
    np.testing.assert_allclose(gain, [1.2, 0.9, 1.05], rtol=1e-12)
    assert np.all(psnr > 100)


def test_recentre_takes_the_geometric_mean_out():
    """After recentre the rows' matrix logarithms average to zero, each row is the old one times
    one common inverse (the scene can follow with one transform), untrained rows stay, and a
    uniform gain pair 0.6 / 1.5 centres on their geometric mean sqrt(0.9)."""
    from scipy.linalg import logm
    rng = np.random.default_rng(11)
    P = _rows(rng, 6).astype(np.float64)
    P[:, :9] *= 0.5                                   # far from the identity: a real drift
    P[:, [0, 4, 8]] += 0.5
    rows = [0, 2, 3, 5]
    out = ref.recentre(P, rows)
    mean_log = np.mean([np.real(logm(ref.affine(out[v]))) for v in rows], axis=0)
    assert np.abs(mean_log).max() < 1e-10
    G = np.linalg.inv(ref.affine(out[0])) @ ref.affine(P[0])   # old = new G
    for v in rows:
        np.testing.assert_allclose(ref.affine(out[v]) @ G, ref.affine(P[v]), atol=1e-12)
    assert np.array_equal(out[[1, 4]], P[[1, 4]])
    pair = np.tile(ref.IDENTITY, (2, 1))
    pair[0, [0, 4, 8]], pair[1, [0, 4, 8]] = 0.6, 1.5
    got = ref.recentre(pair, [0, 1])
    np.testing.assert_allclose(got[0, [0, 4, 8]], 0.6 / np.sqrt(0.9), rtol=1e-12)
    # a transform with no real logarithm (a reflection) leaves the rows as they were
    bad = pair.copy()
    bad[0, 0] = -1.0
    assert np.array_equal(ref.recentre(bad, [0, 1]), bad)


def test_device_rows_recentre_as_the_twin(device):
    rng = np.random.default_rng(13)
    P = _rows(rng, 5)
    exp = _exposure(device, P)
    exp.steps[[0, 1, 3]] = 2
    exp.recentre()
    np.testing.assert_allclose(exp.rows(), ref.recentre(P, [0, 1, 3]), atol=1e-6)


@pytest.mark.parametrize("matrix", ["diagonal", "gain"])
def test_diagonal_adam_trains_gains_and_offsets_only(device, matrix):
    """splat.exposure_matrix=diagonal (gain): the kernel's step matches the twin's, the
    entries it does not train (A's off-diagonal ones; with gain b too) keep their values bit
    for bit (0 from the identity, or whatever a row held), their moments stay zero, and the
    trained ones move as the full model's would."""
    rng = np.random.default_rng(17)
    P = np.tile(ref.IDENTITY, (3, 1)).astype(np.float32)
    P[1] += rng.normal(0, 0.2, ref.ROW).astype(np.float32)    # a row with off-diagonals
    n = CHUNK + 9
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    g = rng.normal(0, 1e-3, (n, 3)).astype(np.float32)
    T = rng.uniform(0, 1, n).astype(np.float32)
    exp = Exposure(device, 3, lr=0.02, reg=0.5, masked=True, matrix=matrix)
    exp.P = upload(device.queue, np.ascontiguousarray(P))
    want_P, want_m, want_v = P.astype(np.float64), np.zeros((3, 12)), np.zeros((3, 12))
    q = device.queue
    k = ref.MATRICES.index(matrix)
    on, off = ref.TRAINED[k], ~ref.TRAINED[k]
    for v in (0, 1, 0):
        rows = download(exp.P)
        _, grad_p = ref.backward(rgb, g, rows, v, T, BG)
        assert np.abs(grad_p[off]).max() > 0                  # the data would move them
        exp.backward_and_step(upload(q, rgb), upload(q, T), BG, upload(q, g), v)
        want_P, want_m, want_v = ref.adam(want_P, want_m, want_v, v, grad_p, 0.02, 0.5, 0.9,
                                          0.999, 1e-15, int(exp.steps[v]), matrix=k)
    got = exp.rows()
    np.testing.assert_allclose(got, want_P, rtol=0, atol=tol.EXPOSURE_ADAM_ATOL)
    assert np.array_equal(got[:, off], P[:, off])
    assert not download(exp.m).reshape(3, 12)[:, off].any()
    assert np.abs(got[0, on] - P[0, on]).min() > 0
    # the full model moves the same row's other entries; the trained ones take this model's
    # step (Adam is per entry)
    zeros = np.zeros((3, 12))
    full = ref.adam(P, zeros, zeros, 0, grad_p, 0.02, 0.5, 0.9, 0.999, 1e-15, 1)[0]
    assert np.abs(full[0, off] - P[0, off]).min() > 0
    mine = ref.adam(P, zeros, zeros, 0, grad_p, 0.02, 0.5, 0.9, 0.999, 1e-15, 1, matrix=k)[0]
    np.testing.assert_array_equal(mine[0, on], full[0, on])


@pytest.mark.parametrize("matrix", ["diagonal", "gain"])
def test_diagonal_rows_recentre_to_diagonal_rows(device, matrix):
    """A diagonal (gain) model's rows stay diagonal through recentre, the entries it does not
    train exact (a gain model's offset stays what it was); their gains centre on the geometric
    mean (0.6 and 1.5 around sqrt(0.9))."""
    P = np.tile(ref.IDENTITY, (3, 1)).astype(np.float32)
    P[0, [0, 4, 8]], P[1, [0, 4, 8]] = 0.6, 1.5
    if matrix == "diagonal":
        P[0, 9:] = 0.02
    exp = Exposure(device, 3, lr=0.01, reg=0.0, masked=True, matrix=matrix)
    exp.P = upload(device.queue, np.ascontiguousarray(P))
    exp.steps[[0, 1]] = 1
    exp.recentre()
    got = exp.rows()
    on = ref.TRAINED[ref.MATRICES.index(matrix)]
    assert not got[:, ~on].any()
    np.testing.assert_allclose(got[1, [0, 4, 8]], 1.5 / np.sqrt(0.9), rtol=1e-6)
    np.testing.assert_allclose(got[:, on], ref.recentre(P, [0, 1])[:, on], atol=1e-6)


def _fit_case(rng, row, masked, n=400):
    """(rgb, T, bg_r, target) of n pixels of premultiplied colour c and transmittance T (a
    fifth of them background only) rendered under the identity, the target shown through
    ``row``."""
    c = rng.uniform(0, 0.8, (n, 3))
    T = rng.uniform(0, 1, n)
    T[:n // 5] = 1.0
    target = ref.shown(c, T, BG, np.stack([ref.IDENTITY, row]), 1, masked)
    bg_r = ref.render_background(ref.IDENTITY[None], 0, BG, masked)
    return c + T[:, None] * bg_r, T, bg_r, target


def _device_fit(device, rgb, T, bg_r, target, masked, matrix):
    """Row 1 after one device fit (eta 1, no pull) of a model of ``matrix``."""
    exp = Exposure(device, 2, lr=0.01, reg=0.0, masked=masked, matrix=matrix)
    q = device.queue
    exp.fit(1, upload(q, rgb.astype(np.float32)), upload(q, T.astype(np.float32)), bg_r, BG,
            target, 1.0)
    return exp.rows()[1]


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_diagonal_fit_recovers_gains_and_offsets(device, masked):
    """A target made by a gain and an offset per channel: the diagonal fit recovers them with
    eta 1 and no pull, leaves A's off-diagonal entries as they were, and a target made with
    mixing channels is fitted by the full model only (the diagonal's error stays)."""
    rng = np.random.default_rng(23)
    true = ref.IDENTITY.copy()
    true[[0, 4, 8]], true[9:] = (0.7, 1.2, 0.95), (0.03, -0.02, 0.01)
    rgb, T, bg_r, target = _fit_case(rng, true, masked)
    got = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, masked, matrix=1)
    np.testing.assert_allclose(got, true, atol=1e-9)
    np.testing.assert_allclose(_device_fit(device, rgb, T, bg_r, target, masked, "diagonal"),
                               true, atol=2e-5)
    mixed = true.copy()
    mixed[1] = 0.2
    c = rgb - T[:, None] * bg_r
    target = ref.shown(c, T, BG, np.stack([ref.IDENTITY, mixed]), 1, masked)
    diag = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, masked, matrix=1)
    assert diag[1] == 0.0
    full = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, masked)
    np.testing.assert_allclose(full, mixed, atol=1e-9)


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_gain_fit_recovers_gains_and_keeps_the_offset(device, masked):
    """splat.exposure_matrix=gain: a target made by a gain per channel is recovered by the fit
    with eta 1 and no pull, the device path as the twin; the row's offset and off-diagonal
    entries stay as they were (0), where the diagonal fit of a target with an offset as well
    takes it and the gain fit cannot (its error stays)."""
    rng = np.random.default_rng(29)
    true = ref.IDENTITY.copy()
    true[[0, 4, 8]] = (0.7, 1.2, 0.95)
    rgb, T, bg_r, target = _fit_case(rng, true, masked)
    gain = ref.MATRICES.index("gain")
    got = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, masked, matrix=gain)
    np.testing.assert_allclose(got, true, atol=1e-9)
    np.testing.assert_allclose(_device_fit(device, rgb, T, bg_r, target, masked, "gain"),
                               true, atol=2e-5)
    offset = true.copy()
    offset[9:] = (0.05, -0.03, 0.02)
    c = rgb - T[:, None] * bg_r
    target = ref.shown(c, T, BG, np.stack([ref.IDENTITY, offset]), 1, masked)
    only = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, masked, matrix=gain)
    fixed = ~ref.TRAINED[gain]            # A's off-diagonal entries and b: as the identity's
    assert np.all(only[fixed] == ref.IDENTITY[fixed])
    assert np.abs(only - offset).max() > 0.01
    diag = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, masked, matrix=1)
    np.testing.assert_allclose(diag, offset, atol=1e-9)


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_fit_recovers_a_transform_in_one_step(device, masked):
    """Targets made by a known transform of a render (rendered on the background that
    transform asks for): the fit with eta 1 and no pull recovers it, the device path (render and
    T downloaded) as the twin; eta 0.5 goes half-way; a pull keeps it nearer the identity."""
    rng = np.random.default_rng(21)
    n = 500
    c = rng.uniform(0, 0.8, (n, 3))
    T = rng.uniform(0, 1, n)
    T[:100] = 1.0                                    # background only
    true = ref.IDENTITY + np.concatenate([rng.normal(0, 0.15, 9), rng.normal(0, 0.05, 3)])
    P = np.stack([ref.IDENTITY, true])
    target = ref.shown(c, T, BG, P, 1, masked)
    start = ref.IDENTITY
    bg_r = ref.render_background(start[None], 0, BG, masked)
    rgb = c + T[:, None] * bg_r                      # the render under the current row
    got = ref.fit_row(rgb, T, bg_r, BG, target, start, 0.0, 1.0, masked)
    np.testing.assert_allclose(got, true, atol=1e-9)
    half = ref.fit_row(rgb, T, bg_r, BG, target, start, 0.0, 0.5, masked)
    np.testing.assert_allclose(half, 0.5 * (start + true), atol=1e-9)
    pulled = ref.fit_row(rgb, T, bg_r, BG, target, start, 0.1, 1.0, masked)
    assert np.abs(pulled - start).sum() < np.abs(true - start).sum()
    exp = Exposure(device, 2, lr=0.01, reg=0.0, masked=masked)
    q = device.queue
    exp.fit(1, upload(q, rgb.astype(np.float32)), upload(q, T.astype(np.float32)), bg_r, BG,
            target, 1.0)
    np.testing.assert_allclose(exp.rows()[1], true, atol=2e-5)
    assert exp.steps.tolist() == [0, 1]


@pytest.mark.parametrize("clip", [1, 2], ids=["clip", "inward"])
@pytest.mark.parametrize("n", [7, 3 * CHUNK + 5])
def test_clipped_apply_and_backward_match_the_twin(device, n, clip):
    """splat.exposure_clip: out clamped to [0, 1] as a camera clips; a channel whose A rgb' + b
    lies outside [0, 1] passes no gradient to the render or the row (clip 2,
    splat.exposure_clip_inward: only one pointing back inside). Transforms far from the
    identity so that about a third of the channels clip at each end."""
    rng = np.random.default_rng(300 + n)
    P = _rows(rng, 3)
    P[2, [0, 4, 8]] = 1.8                            # gains that push bright pixels past white
    P[2, 9:] = -0.3                                  # an offset that pushes dark ones below 0
    rgb = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    rgb[0], rgb[1] = 0.02, 0.98                      # one pixel clipped at each end
    T = rng.uniform(0, 1, n).astype(np.float32)
    g = rng.normal(0, 1, (n, 3)).astype(np.float32)
    unclipped = ref.apply(rgb, P, 2)
    low, high = np.mean(unclipped < 0), np.mean(unclipped > 1)
    assert low > 0 and high > 0 and (n < 100 or (0.1 < low < 0.5 and 0.1 < high < 0.5))
    for masked in (True, False):
        exp = _exposure(device, P, masked)
        exp.clip = clip
        q = device.queue
        got = download(exp.apply(upload(q, rgb), 2))
        assert got.min() >= 0 and got.max() <= 1
        np.testing.assert_allclose(got, ref.apply(rgb, P, 2, clip=True), rtol=tol.EXPOSURE_RTOL,
                                   atol=tol.EXPOSURE_ATOL)
        grad_rgb, partials = exp.backward(upload(q, rgb), upload(q, T), BG, upload(q, g), 2)
        want_rgb, want_p = ref.backward(rgb, g, P, 2, T if masked else None, BG, clip=clip)
        plain_rgb, _ = ref.backward(rgb, g, P, 2, T if masked else None, BG)
        assert np.abs(want_rgb - plain_rgb).max() > 0.1     # the clip changed the gradient
        np.testing.assert_allclose(download(grad_rgb), want_rgb, rtol=tol.EXPOSURE_GRAD_RTOL,
                                   atol=tol.EXPOSURE_ATOL)
        np.testing.assert_allclose(download(partials).astype(np.float64).sum(axis=0), want_p,
                                   rtol=tol.EXPOSURE_GRAD_RTOL,
                                   atol=tol.EXPOSURE_SUM_ATOL_PER_SQRT_N * n ** 0.5)


def test_inward_clip_passes_only_gradients_back_into_range():
    """clip 2 (splat.exposure_clip_inward): a channel clipped above 1 passes dL/dout > 0 (which
    lowers it), one clipped below 0 passes dL/dout < 0; the other direction, and everything
    with clip 1, passes nothing there; inside [0, 1] both pass all of it."""
    P = np.tile(ref.IDENTITY, (1, 1)).astype(np.float64)
    P[0, [0, 4, 8]] = 2.0
    P[0, 9:] = -1.0                                 # out = 2 rgb - 1
    rgb = np.array([[1.1, 1.1, 0.6], [-0.1, -0.1, 0.7]])   # out 1.2 1.2 0.2 / -1.2 -1.2 0.4
    g = np.array([[1.0, -1.0, 0.5], [-1.0, 1.0, -0.5]])
    passed = {1: np.array([[0, 0, 1], [0, 0, 1]], float),
              2: np.array([[1, 0, 1], [1, 0, 1]], float)}
    for clip, mask in passed.items():
        grad_rgb, grad_p = ref.backward(rgb, g, P, 0, clip=clip)
        np.testing.assert_allclose(grad_rgb, (g * mask) @ P[0, :9].reshape(3, 3), atol=1e-15)
        np.testing.assert_allclose(grad_p[9:], (g * mask).sum(axis=0), atol=1e-15)


@pytest.mark.parametrize("masked", [True, False], ids=["masked", "plain"])
def test_clipped_twin_gradient_matches_finite_differences(masked):
    """The clipped twin's dL/dP and dL/dc against central differences of
    L = sum(w * clip(shown)), at points away from the clip's kinks (no channel within 1e-3 of
    0 or 1), with about a third of the channels clipped."""
    rng = np.random.default_rng(8)
    P = _rows(rng, 2).astype(np.float64)
    P[1, [0, 4, 8]] += 0.6
    c = rng.uniform(0, 1, (40, 3))
    T = rng.uniform(0, 1, 40)
    out = ref.shown(c, T, BG, P, 1, masked)
    ok = np.all((np.abs(out) > 1e-3) & (np.abs(out - 1) > 1e-3), axis=1)
    c, T = c[ok], T[ok]
    out = out[ok]
    assert 0.1 < np.mean((out > 1) | (out < 0)) < 0.8
    w = rng.normal(0, 1, c.shape)
    bg2 = ref.render_background(P, 1, BG, masked)
    rgb2 = c + T[:, None] * bg2
    grad_rgb, grad_p = ref.backward(rgb2, w, P, 1, T if masked else None, bg2, clip=True)
    h = 1e-7

    def L(P_=P, c_=c):
        return np.sum(w * ref.shown(c_, T, BG, P_, 1, masked, clip=True))
    for k in range(ref.ROW):
        Pp, Pm = P.copy(), P.copy()
        Pp[1, k] += h
        Pm[1, k] -= h
        fd = (L(P_=Pp) - L(P_=Pm)) / (2 * h)
        assert fd == pytest.approx(grad_p[k], rel=tol.FD_RTOL, abs=tol.FD_ATOL), k
    for p in range(len(c)):
        for i in range(3):
            x1, x0 = c.copy(), c.copy()
            x1[p, i] += h
            x0[p, i] -= h
            fd = (L(c_=x1) - L(c_=x0)) / (2 * h)
            assert fd == pytest.approx(grad_rgb[p, i], rel=tol.FD_RTOL, abs=tol.FD_ATOL)


def test_clipped_fit_leaves_out_saturated_targets():
    """With clip, the fit regresses only pixels whose target channels all lie inside (0, 1):
    targets made by a transform that clips a third of them give the transform back (without
    clip the clipped pixels bias it), and a fit with fewer than four pixels left keeps the row."""
    rng = np.random.default_rng(22)
    n = 600
    c = rng.uniform(0, 0.8, (n, 3))
    T = rng.uniform(0, 0.5, n)
    true = ref.IDENTITY.copy()
    true[[0, 4, 8]] = 1.5
    P = np.stack([ref.IDENTITY, true])
    target = ref.shown(c, T, BG, P, 1, False, clip=True)
    assert 0.1 < np.mean(np.any(target >= 1, axis=1)) < 0.9
    bg_r = ref.render_background(ref.IDENTITY[None], 0, BG, False)
    rgb = c + T[:, None] * bg_r
    got = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, False, clip=True)
    np.testing.assert_allclose(got, true, atol=1e-9)
    biased = ref.fit_row(rgb, T, bg_r, BG, target, ref.IDENTITY, 0.0, 1.0, False)
    assert np.abs(biased - true).max() > 0.05
    few = np.ones_like(target)
    few[:3] = 0.5
    np.testing.assert_array_equal(
        ref.fit_row(rgb, T, bg_r, BG, few, ref.IDENTITY, 0.0, 1.0, False, clip=True),
        ref.IDENTITY)
