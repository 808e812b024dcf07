"""The bilateral grid per training image (cl/bilateral.cl, clrf/corrections/bilateral.py)
against its float64 twin (clrf/references/reference_bilateral.py), on every OpenCL
implementation: the slice and apply, the backward to the render (the luminance path included)
and to the grid cells, the total-variation prior's gradient, the Adam step of every grid, the
twin's gradients against central differences, stiff inputs (luminance 0 and 1 and beyond, bin
edges, a 1 x 1 image, an image much wider than the grid) and gsplat's schedule. The splat
model's use of it: tests/test_bilateral_model.py."""
import numpy as np
import pytest

from clrf.corrections.bilateral import FINAL, WARMUP, BilateralGrid
from clrf.references import reference_bilateral as ref
from clrf.runtime.optim import ADAM_BETAS, ADAM_EPS, adam_host_step
from clrf.runtime.programs import download, upload
from clrf.testing import tolerances as tol

BG = (1.0, 0.75, 0.25)
# (H, W, grid shape (x, y, luminance)): a 1 x 1 image, one smaller than the grid, one much
# wider than it, odd sizes, gsplat's shape, a grid of one cell on an axis
CASES = [(1, 1, (16, 16, 8)), (2, 3, (5, 4, 3)), (3, 97, (4, 3, 5)), (23, 37, (16, 16, 8)),
         (9, 11, (1, 3, 1)), (6, 5, (3, 1, 4))]
IDS = [f"{h}x{w}-grid{'x'.join(map(str, s))}" for h, w, s in CASES]


def _grid(device, V, shape, rng, spread=0.2, masked=False):
    """A BilateralGrid of V views whose cells are the identity plus N(0, spread) (float32), and
    those cells in float64 [V, L, GY, GX, 12]."""
    bil = BilateralGrid(device, V, shape=shape, masked=masked)
    G = bil.host_grids().astype(np.float64) + rng.normal(0, spread, bil.host_grids().shape)
    G = G.astype(np.float32)
    bil.grids.set(np.ascontiguousarray(G.reshape(-1)))
    return bil, G.astype(np.float64)


def _render(rng, H, W):
    """An [H, W, 3] render with colours a little outside [0, 1] too, T [H, W], g [H, W, 3]."""
    rgb = rng.uniform(-0.1, 1.1, (H, W, 3)).astype(np.float32)
    return rgb, rng.uniform(0, 1, (H, W)).astype(np.float32), \
        rng.normal(0, 1, (H, W, 3)).astype(np.float32)


def _close_to_max(got, want, rel):
    """|got - want| within rel of want's largest entry (and 1e-12 where it is all zero)."""
    err = np.abs(np.asarray(got, np.float64) - want).max()
    assert err <= rel * max(np.abs(want).max(), 1e-12 / rel), (err, np.abs(want).max())


def test_a_new_grid_is_the_identity_and_leaves_renders_unchanged(device):
    rng = np.random.default_rng(0)
    bil = BilateralGrid(device, 2, masked=True)
    assert bil.host_grids().shape == (2, 8, 16, 16, 12)
    rgb, T, _ = _render(rng, 7, 9)
    q = device.queue
    for t in (None, T):   # masked: A (rgb - T bg) + (1 - T) 0 + T bg = rgb
        out = download(bil.apply(upload(q, rgb), 1, None if t is None else upload(q, t), BG))
        np.testing.assert_allclose(out, rgb, rtol=tol.BILATERAL_RTOL, atol=tol.BILATERAL_ATOL)


@pytest.mark.parametrize("masked", [False, True], ids=["plain", "masked"])
@pytest.mark.parametrize("H,W,shape", CASES, ids=IDS)
def test_apply_and_backward_match_the_twin(device, H, W, shape, masked):
    rng = np.random.default_rng(H * 100 + W)
    bil, G = _grid(device, 3, shape, rng, masked=masked)
    rgb, T, g = _render(rng, H, W)
    q = device.queue
    Td = upload(q, T) if masked else None
    Tw = T if masked else None
    out = download(bil.apply(upload(q, rgb), 2, Td, BG)).reshape(-1, 3)
    np.testing.assert_allclose(out, ref.apply(G[2], rgb, H, W, Tw, BG),
                               rtol=tol.BILATERAL_RTOL, atol=tol.BILATERAL_ATOL)
    grad_rgb, grad_grid = bil.backward(upload(q, rgb), Td, BG, upload(q, g), 2)
    want_rgb, want_grid = ref.backward(G[2], rgb, H, W, g, Tw, BG)
    _close_to_max(download(grad_rgb).reshape(-1, 3), want_rgb, tol.BILATERAL_GRAD_REL_TO_MAX)
    np.testing.assert_allclose(download(grad_grid).reshape(want_grid.shape), want_grid, rtol=0,
                               atol=tol.BILATERAL_SUM_ATOL_PER_SQRT_N * (H * W) ** 0.5)


@pytest.mark.parametrize("masked", [False, True], ids=["plain", "masked"])
def test_twin_gradients_match_central_differences(masked):
    """L = sum(w * apply) of a grid that varies along every axis (the luminance path too), at
    colours whose guidance lies inside the grid: the twin's dL/drgb (T held fixed) and dL/dG
    against central differences."""
    rng = np.random.default_rng(3)
    H, W, shape = 3, 4, (4, 3, 5)
    G = ref.identity_grid(*shape) + rng.normal(0, 0.3, (shape[2], shape[1], shape[0], 12))
    rgb = rng.uniform(0.05, 0.95, (H, W, 3))
    T = rng.uniform(0, 1, (H, W)) if masked else None
    w = rng.normal(0, 1, (H * W, 3))
    h = 1e-6

    def L(G_=G, rgb_=rgb):
        return float(np.sum(w * ref.apply(G_, rgb_, H, W, T, BG)))
    d_rgb, d_G = ref.backward(G, rgb, H, W, w, T, BG)
    assert np.abs(d_rgb).max() > 0.1 and np.count_nonzero(d_G) > 0
    for p in range(H * W):
        for j in range(3):
            a, b = rgb.copy(), rgb.copy()
            a.reshape(-1, 3)[p, j] += h
            b.reshape(-1, 3)[p, j] -= h
            fd = (L(rgb_=a) - L(rgb_=b)) / (2 * h)
            assert fd == pytest.approx(d_rgb[p, j], rel=tol.FD_RTOL, abs=tol.FD_ATOL)
    for idx in zip(*np.nonzero(np.abs(d_G) > 0)):
        a, b = G.copy(), G.copy()
        a[idx] += h
        b[idx] -= h
        fd = (L(G_=a) - L(G_=b)) / (2 * h)
        assert fd == pytest.approx(d_G[idx], rel=tol.FD_RTOL, abs=tol.FD_ATOL)


def test_the_luminance_path_is_what_a_grid_varying_in_luminance_adds():
    """Without it dL/drgb is A^T g: a grid constant along luminance gives exactly that; one that
    varies gives more, and the difference is the grey weights times one number per pixel."""
    rng = np.random.default_rng(4)
    H, W, shape = 2, 3, (3, 3, 4)
    flat = np.repeat(ref.identity_grid(*shape)[:1] + rng.normal(0, 0.3, (1, 3, 3, 12)), 4, 0)
    rgb = rng.uniform(0.1, 0.9, (H, W, 3))
    g = rng.normal(0, 1, (H * W, 3))
    M = ref.slice_grid(flat, rgb, H, W).reshape(-1, 3, 4)
    d_rgb, _ = ref.backward(flat, rgb, H, W, g)
    np.testing.assert_allclose(d_rgb, np.einsum("nij,ni->nj", M[:, :, :3], g), atol=1e-14)
    varied = flat + rng.normal(0, 0.3, flat.shape)
    d_var, _ = ref.backward(varied, rgb, H, W, g)
    M = ref.slice_grid(varied, rgb, H, W).reshape(-1, 3, 4)
    extra = d_var - np.einsum("nij,ni->nj", M[:, :, :3], g)
    assert np.abs(extra).max() > 1e-3
    np.testing.assert_allclose(extra, (extra[:, :1] / ref.GREY[0]) * ref.GREY, rtol=1e-12)


def test_tv_gradient_matches_the_twin_and_central_differences(device):
    rng = np.random.default_rng(6)
    shape = (4, 3, 5)
    bil, G = _grid(device, 3, shape, rng)
    got = download(bil.gradient(-1)).reshape(G.shape)
    want = ref.step_gradient(G, -1, None, bil.tv_weight)
    _close_to_max(got, want, tol.BILATERAL_TV_REL_TO_MAX)
    h = 1e-6
    g0 = G[1]
    d = ref.tv_grad(g0)
    for _ in range(20):
        idx = tuple(rng.integers(0, n) for n in g0.shape)
        a, b = g0.copy(), g0.copy()
        a[idx] += h
        b[idx] -= h
        assert (ref.tv(a) - ref.tv(b)) / (2 * h) == pytest.approx(d[idx], rel=tol.FD_RTOL,
                                                                   abs=tol.FD_ATOL)
    # the identity has no variation; gsplat's normalisation: one unit step along x between
    # two cells of a 2 x 1 x 1 grid is 1 / 12 (n_x = 1 difference times 12 channels)
    assert ref.tv(ref.identity_grid(*shape)) == 0.0
    two = ref.identity_grid(2, 1, 1)
    two[0, 0, 1, 0] += 1.0
    assert ref.tv(two) == pytest.approx(1 / 12, rel=1e-15)


def test_a_step_adds_the_views_data_gradient_to_its_grid_only(device):
    rng = np.random.default_rng(7)
    shape = (3, 4, 2)
    bil, G = _grid(device, 3, shape, rng)
    rgb, _, g = _render(rng, 5, 6)
    q = device.queue
    _, data = bil.backward(upload(q, rgb), None, BG, upload(q, g), 1)
    got = download(bil.gradient(1)).reshape(G.shape)
    want = ref.step_gradient(G, 1, download(data).reshape(G.shape[1:]), bil.tv_weight)
    _close_to_max(got, want, tol.BILATERAL_TV_REL_TO_MAX)
    tv_only = ref.step_gradient(G, -1, None, bil.tv_weight)
    np.testing.assert_array_equal(want[[0, 2]], tv_only[[0, 2]])


def test_adam_steps_every_grid_as_the_twin_does(device):
    """Three training steps (views 2, 0, 2): every grid steps each time (gsplat's dense Adam
    over all the grids), with one step count, at the rate ``schedule`` set."""
    rng = np.random.default_rng(8)
    shape = (3, 3, 4)
    bil, G = _grid(device, 3, shape, rng, spread=0.05)
    bil.schedule(0.5)
    lr = bil.lr
    assert lr == pytest.approx(2e-3 * ref.lr_factor(0.5, WARMUP, FINAL), rel=1e-15)
    m, v = np.zeros_like(G), np.zeros_like(G)
    want = G.copy()
    rgb, _, g = _render(rng, 8, 7)
    q = device.queue
    for t, view in enumerate((2, 0, 2), start=1):
        now = bil.host_grids().astype(np.float64)
        _, data = ref.backward(now[view], rgb, 8, 7, g)
        grad = ref.step_gradient(now, view, data, bil.tv_weight)
        bil.backward_and_step(upload(q, rgb), None, BG, upload(q, g), view)
        adam_host_step(want, m, v, grad, t, lr, ADAM_BETAS, ADAM_EPS)
    assert bil.steps == 3
    np.testing.assert_allclose(bil.host_grids(), want, rtol=0, atol=tol.BILATERAL_ADAM_ATOL)
    assert np.abs(bil.host_grids() - G).min() > 0   # every entry of every grid moved


def test_a_sparse_step_moves_the_trained_views_grid_alone(device):
    """splat.bilateral_grid_sparse: steps of views 2, 0, 2 move grid v by its data and prior
    gradients alone (the twin's step gradient, row v), Adam bias-corrected by that grid's own
    step count; grid 1, never trained, is left exactly as it was, and the optimiser's
    gradient outside the stepped grid is not written."""
    rng = np.random.default_rng(11)
    shape = (3, 3, 4)
    bil, G = _grid(device, 3, shape, rng, spread=0.05)
    bil.sparse = True
    bil.schedule(0.5)
    lr = bil.lr
    m, v = np.zeros_like(G), np.zeros_like(G)
    want = G.copy()
    rgb, _, g = _render(rng, 8, 7)
    q = device.queue
    counts = {0: 0, 2: 0}
    for view in (2, 0, 2):
        now = bil.host_grids().astype(np.float64)
        _, data = ref.backward(now[view], rgb, 8, 7, g)
        grad = ref.step_gradient(now, view, data, bil.tv_weight)[view]
        bil.backward_and_step(upload(q, rgb), None, BG, upload(q, g), view)
        counts[view] += 1
        adam_host_step(want[view], m[view], v[view], grad, counts[view], lr, ADAM_BETAS,
                       ADAM_EPS)
    assert bil.steps == 3 and list(bil.view_steps) == [1, 0, 2]
    got = bil.host_grids()
    np.testing.assert_allclose(got, want, rtol=0, atol=tol.BILATERAL_ADAM_ATOL)
    np.testing.assert_array_equal(got[1], G[1].astype(np.float32))
    assert np.abs(got[[0, 2]] - G[[0, 2]]).min() > 0
    assert not np.any(download(bil._opt.grad).reshape(G.shape)[1])


def test_seeded_grids_apply_each_images_affine_transform_and_hold(device):
    """``seed`` (an exposure calibration's rows P [V, 12]): every cell of grid v holds
    (A_v | b_v), so the slice gives A_v rgb + b_v at any pixel and luminance; before
    ``hold_until`` a training step leaves the grids as they are (dL/drgb through them), after
    it they step; the hold survives a checkpoint. Bad rows are refused."""
    rng = np.random.default_rng(12)
    bil = BilateralGrid(device, 2, shape=(4, 3, 5))
    P = np.zeros((2, 12))
    P[:, :9] = (np.eye(3)[None] * np.array([0.7, 1.3])[:, None, None]
                + rng.normal(0, 0.05, (2, 3, 3))).reshape(2, 9)
    P[:, 9:] = rng.normal(0, 0.05, (2, 3))
    bil.seed(P, hold_until=0.2)
    rgb, _, g = _render(rng, 6, 7)
    q = device.queue
    for v in range(2):
        A, b = P[v, :9].reshape(3, 3), P[v, 9:]
        np.testing.assert_allclose(download(bil.apply(upload(q, rgb), v)),
                                   rgb.astype(np.float64) @ A.T + b, rtol=0, atol=1e-5)
    before = bil.host_grids().copy()
    d_rgb = bil.train_view(1, upload(q, rgb), None, BG, upload(q, g), 0.1, None, BG)
    np.testing.assert_array_equal(bil.host_grids(), before)
    np.testing.assert_allclose(download(d_rgb), g.astype(np.float64) @ P[1, :9].reshape(3, 3),
                               rtol=0, atol=1e-5)
    back = BilateralGrid(device, 2, state=bil.state_dict())
    assert back.hold_until == 0.2 and back.steps == 0
    bil.train_view(1, upload(q, rgb), None, BG, upload(q, g), 0.3, None, BG)
    assert bil.steps == 1 and np.any(bil.host_grids() != before)
    with pytest.raises(ValueError, match="2 finite rows"):
        bil.seed(P[:1])
    with pytest.raises(ValueError, match="2 finite rows"):
        bil.seed(np.full((2, 12), np.nan))


@pytest.mark.parametrize("masked", [False, True], ids=["plain", "masked"])
def test_stiff_colours_and_bin_edges(device, masked):
    """Pixels black and white, far below 0 and above 1 (the guidance clamped: no luminance
    path), and at luminance bin edges, over a grid wider and taller than the image's pixel
    grid allows a cell per pixel: finite outputs and gradients that match the twin. The
    derivative along luminance jumps at a bin edge, so dL/drgb is compared on a grid that
    varies in x and y only (float32 and float64 may pick either side of an edge)."""
    rng = np.random.default_rng(9)
    shape, H, W = (16, 16, 8), 3, 24
    grey = np.array([0.0, 1.0, -2.0, 3.0, 1 / 7, 2 / 7, 0.5, 6 / 7])
    rgb = np.repeat(grey, 3 * H * W // len(grey)).reshape(H, W, 3)
    rgb[0] = np.stack([grey[:3]] * W)    # colours whose grey is a bin edge in one channel
    rgb = rgb.astype(np.float32)
    T = rng.uniform(0, 1, (H, W)).astype(np.float32) if masked else None
    g = rng.normal(0, 1, (H, W, 3)).astype(np.float32)
    q = device.queue
    bil, G = _grid(device, 1, shape, rng, masked=masked)
    flat = np.repeat(G[:, :1], shape[2], axis=1)
    for grid, rgb_check in ((G, False), (flat, True)):
        bil.grids.set(np.ascontiguousarray(grid.astype(np.float32).reshape(-1)))
        Td = None if T is None else upload(q, T)
        out = download(bil.apply(upload(q, rgb), 0, Td, BG)).reshape(-1, 3)
        np.testing.assert_allclose(out, ref.apply(grid[0], rgb, H, W, T, BG),
                                   rtol=tol.BILATERAL_RTOL, atol=tol.BILATERAL_ATOL)
        d_rgb, d_grid = bil.backward(upload(q, rgb), Td, BG, upload(q, g), 0)
        want_rgb, want_grid = ref.backward(grid[0], rgb, H, W, g, T, BG)
        assert np.all(np.isfinite(download(d_rgb))) and np.all(np.isfinite(download(d_grid)))
        np.testing.assert_allclose(download(d_grid).reshape(want_grid.shape), want_grid, rtol=0,
                                   atol=tol.BILATERAL_SUM_ATOL_PER_SQRT_N * (H * W) ** 0.5)
        if rgb_check:
            _close_to_max(download(d_rgb).reshape(-1, 3), want_rgb,
                          tol.BILATERAL_GRAD_REL_TO_MAX)
    # the clamped guidance passes nothing along luminance: dL/drgb is A^T g there exactly
    bil.grids.set(np.ascontiguousarray(G.astype(np.float32).reshape(-1)))
    far = np.stack([np.full((1, 4, 3), -2.0), np.full((1, 4, 3), 3.0)]).reshape(2, 4, 3)
    far = far.astype(np.float32)
    gf = g[:2, :4].copy()
    d, _ = bil.backward(upload(q, far), None, BG, upload(q, gf), 0)
    M = ref.slice_grid(G[0], far, 2, 4).reshape(-1, 3, 4)
    _close_to_max(download(d).reshape(-1, 3), np.einsum("nij,ni->nj", M[:, :, :3],
                                                        gf.reshape(-1, 3)),
                  tol.BILATERAL_GRAD_REL_TO_MAX)


def test_gsplats_schedule():
    """1 % of the rate at the start, the full rate times the decay at the warm-up's end
    (1,000 of 30,000 steps), 1 % at the end."""
    assert ref.lr_factor(0.0, WARMUP, FINAL) == pytest.approx(0.01, rel=1e-15)
    assert ref.lr_factor(WARMUP, WARMUP, FINAL) == pytest.approx(0.01 ** (1 / 30), rel=1e-12)
    assert ref.lr_factor(1.0, WARMUP, FINAL) == pytest.approx(0.01, rel=1e-12)
    half = 0.01 + 0.99 * 0.5
    assert ref.lr_factor(WARMUP / 2, WARMUP, FINAL) == pytest.approx(
        half * 0.01 ** (1 / 60), rel=1e-12)


def test_state_round_trip(device):
    rng = np.random.default_rng(10)
    bil, G = _grid(device, 2, (3, 2, 4), rng, masked=True)
    rgb, T, g = _render(rng, 4, 5)
    q = device.queue
    bil.backward_and_step(upload(q, rgb), upload(q, T), BG, upload(q, g), 1)
    st = bil.state_dict()
    assert st["bilateral_grid"].shape == (2, 4, 2, 3, 12)
    back = BilateralGrid(device, 5, state=st)
    assert back.n_images == 2 and back.shape == (3, 2, 4) and back.masked and back.steps == 1
    for k, a in st.items():
        np.testing.assert_array_equal(back.state_dict()[k], a)
    assert list(back.view_steps) == [1, 1] and back.hold_until == 0.0
    older = {k: a for k, a in st.items()
             if k not in ("bilateral_grid_view_steps", "bilateral_grid_hold_until")}
    old = BilateralGrid(device, 2, state=older)   # a checkpoint from before these keys
    assert list(old.view_steps) == [1, 1] and old.hold_until == 0.0


def test_bad_arrays_are_refused_at_the_boundary(device):
    bil = BilateralGrid(device, 2, shape=(3, 3, 2), masked=True)
    q = device.queue
    rgb = np.zeros((4, 5, 3), np.float32)
    with pytest.raises(ValueError, match="float32"):
        bil.apply(upload(q, rgb.astype(np.float64)), 0)
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        bil.apply(upload(q, rgb.reshape(-1, 3)), 0)
    with pytest.raises(ValueError, match="view 2"):
        bil.apply(upload(q, rgb), 2)
    with pytest.raises(ValueError, match=r"T must be"):
        bil.apply(upload(q, rgb), 0, upload(q, np.zeros((4, 4), np.float32)), BG)
    with pytest.raises(ValueError, match="background"):
        bil.apply(upload(q, rgb), 0, upload(q, np.zeros((4, 5), np.float32)))
    with pytest.raises(ValueError, match="grad_out"):
        bil.backward(upload(q, rgb), None, BG, upload(q, np.zeros((4, 5), np.float32)), 0)
