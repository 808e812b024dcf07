"""Multi-sphere-image background (cl/background.cl, clrf/grid/msi.py) vs the float64 reference
(clrf/references/reference_background.py), closed forms, finite differences and a density scale sweep."""
import numpy as np
import pytest

from clrf.references import reference_background as ref
from clrf.grid.msi import MSIBackground
from clrf.runtime.programs import BuildError
from clrf.testing import tolerances as tol

CENTER = (0.1, -0.2, 0.05)
BG = (0.2, 0.5, 0.9)


def radii(L, r_inner):
    """r_l written out independently of the code: 1/r_l = (1 - (l + 0.5)/L) / r_inner."""
    return np.array([r_inner / (1.0 - (l + 0.5) / L) for l in range(L)])


def make_model(device, L, H, r_inner=1.3, seed=0, density=(0.05, 1.0), color=(-0.3, 0.3),
               center=CENTER, background=BG):
    """A model with random parameters; the default ranges keep every sample away from the
    ReLU kinks (density > 0, colour + 0.5 > 0), where finite differences are smooth."""
    rng = np.random.default_rng(seed)
    m = MSIBackground(device, L, H, r_inner, center=center, background=background)
    den = rng.uniform(*density, m.shape)
    col = rng.uniform(*color, m.shape + (3,))
    m.set_params(den, col)
    return m, den, col


def special_dirs():
    """Poles, the longitude seam (y = +-0 and just either side), the equator, random."""
    e = 1e-4
    return np.array([[0, 0, 1], [0, 0, -1], [-1, 0, 0], [-1, -0.0, 0], [-1, e, 0.3],
                     [-1, -e, 0.3], [1, 0, 0], [0, 1, 0], [1e-30, 0, 1], [0, 3e-7, -1]],
                    np.float64)


def make_rays(n, r_inner, seed=0, t_start_max=0.0, center=CENTER):
    """Rays from inside the inner sphere (|o - center| < 0.6 r_inner), the special directions
    first (from the centre itself), t_start in [0, t_start_max]."""
    rng = np.random.default_rng(seed + 100)
    d = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 50.0], (n, 1))   # any length
    o = rng.normal(size=(n, 3))
    o *= (0.6 * r_inner * rng.random((n, 1)) ** (1 / 3)) / np.linalg.norm(o, axis=1, keepdims=True)
    s = special_dirs()[: n]
    d[: len(s)] = s
    o[: len(s)] = 0.0
    o += np.asarray(center)
    t = rng.uniform(0.0, t_start_max, n) if t_start_max > 0 else np.zeros(n)
    return o.astype(np.float32), d.astype(np.float32), t.astype(np.float32)


def ref_forward(m, den, col, o, d, t):
    return ref.forward(den, col, m.r_inner, o, d, t, m.center, m.background)


@pytest.mark.parametrize("L,H", [(2, 1), (3, 2), (7, 5), (16, 8)])
@pytest.mark.parametrize("t_start_max", [0.0, 3.0])
def test_forward_matches_reference(device, L, H, t_start_max):
    m, den, col = make_model(device, L, H, seed=L * H, density=(-0.5, 1.5), color=(-0.8, 0.8))
    o, d, t = make_rays(57, m.r_inner, seed=L + H, t_start_max=t_start_max)
    rgb, T = m.forward(o, d, t)
    r_rgb, r_T = ref_forward(m, den, col, o, d, t)
    np.testing.assert_allclose(rgb, r_rgb, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)
    np.testing.assert_allclose(T, r_T, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)
    assert np.mean(T < 1.0) > 0.5      # most rays cross some density: the test is not trivial


def test_origins_outside_inner_sphere(device):
    # cameras between the spheres, looking anywhere: only the outgoing crossings count
    m, den, col = make_model(device, 6, 4, seed=3)
    rng = np.random.default_rng(4)
    o = rng.normal(size=(40, 3)) * 3.0 + np.asarray(CENTER)
    d = rng.normal(size=(40, 3))
    t = rng.uniform(0, 2, 40)
    rgb, T = m.forward(o, d, t)
    r_rgb, r_T = ref_forward(m, den, col, o, d, t)
    np.testing.assert_allclose(rgb, r_rgb, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)
    np.testing.assert_allclose(T, r_T, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)


@pytest.mark.parametrize("n", [0, 1, 17])
def test_awkward_sizes(device, n):
    m, den, col = make_model(device, 4, 3, seed=n)
    o, d, t = make_rays(max(n, 1), m.r_inner, seed=n)
    o, d, t = o[:n], d[:n], t[:n]
    rgb, T = m.forward(o, d, t)
    assert rgb.shape == (n, 3) and T.shape == (n,)
    np.testing.assert_allclose(rgb, ref_forward(m, den, col, o, d, t)[0], rtol=tol.BG_RTOL,
                               atol=tol.BG_ATOL)
    gd, gc = m.backward(o, d, np.ones((n, 3)), t)
    assert gd.shape == m.shape and gc.shape == m.shape + (3,)


def test_toy_two_layers(device):
    # L = 2, r_inner = 1: r_0 = 4/3, r_1 = 4. A ray from the centre has one segment [4/3, 4]
    # (delta 8/3) sampled at radius 8/3: inverse radius 3/8 between u_0 = 3/4 and u_1 = 1/4,
    # so f = (3/4 - 3/8) * L * r_inner = 3/4. Density 0 on layer 0, 1 on layer 1 -> sigma 3/4,
    # tau = 2, T = exp(-2). Colour raw -0.5 (black) on layer 0, 0.5 (white) on layer 1 ->
    # c = 3/4 per channel; rgb = 3/4 (1 - e^-2) + e^-2 bg.
    m = MSIBackground(device, 2, 1, 1.0, center=(0, 0, 0), background=(0, 0.5, 1))
    m.set_params(np.array([0.0, 1.0]).reshape(2, 1, 1).repeat(2, 2),
                 np.array([-0.5, 0.5]).reshape(2, 1, 1, 1).repeat(2, 2).repeat(3, 3))
    rgb, T = m.forward(np.zeros((2, 3)), [[0.3, -0.2, 0.9], [0, 0, -1]])
    e2 = np.exp(-2.0)
    np.testing.assert_allclose(T, [e2, e2], atol=tol.TOY_ATOL)
    np.testing.assert_allclose(rgb, [0.75 * (1 - e2) + e2 * np.array([0, 0.5, 1])] * 2,
                               atol=tol.TOY_ATOL)


def test_zero_density_gives_background_exactly(device):
    m, _, _ = make_model(device, 5, 4, density=(0.0, 0.0), color=(-1, 1))
    o, d, t = make_rays(33, m.r_inner, t_start_max=2.0)
    rgb, T = m.forward(o, d, t)
    np.testing.assert_array_equal(T, np.ones(33, np.float32))
    np.testing.assert_array_equal(rgb, np.broadcast_to(np.float32(BG), (33, 3)))


def test_degenerate_direction_gives_background(device):
    m, _, _ = make_model(device, 4, 2)
    d = np.array([[0, 0, 0], [np.nan, 1, 0], [np.inf, 0, 0]], np.float32)
    rgb, T = m.forward(np.zeros((3, 3)), d)
    np.testing.assert_array_equal(T, np.ones(3, np.float32))
    np.testing.assert_array_equal(rgb, np.broadcast_to(np.float32(BG), (3, 3)))
    gd, gc = m.backward(np.zeros((3, 3)), d, np.ones((3, 3)))
    assert not gd.any() and not gc.any()


@pytest.mark.parametrize("t_start", [0.0, 2.0, 1e3])
def test_uniform_density_closed_form(device, t_start):
    # Constant density sigma and colour c everywhere: along a ray from the centre the segments
    # cover [max(r_0, t_start), r_{L-1}], so T = exp(-sigma (r_{L-1} - max(r_0, t_start)))
    # (1 when t_start is beyond the outermost sphere) and rgb = c (1 - T) + T bg.
    L, H, r_inner, sigma, raw_c = 9, 4, 1.3, 0.07, np.array([0.1, -0.2, 0.3])
    m = MSIBackground(device, L, H, r_inner, center=CENTER, background=BG)
    m.set_params(np.full(m.shape, sigma), np.broadcast_to(raw_c, m.shape + (3,)))
    o, d, _ = make_rays(30, r_inner)
    o[:] = np.float32(CENTER)
    t = np.full(30, t_start, np.float32)
    rgb, T = m.forward(o, d, t)
    r = radii(L, r_inner)
    T_exp = np.exp(-sigma * max(r[-1] - max(r[0], t_start), 0.0))
    np.testing.assert_allclose(T, T_exp, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)
    expect = (raw_c + 0.5) * (1 - T_exp) + T_exp * np.asarray(BG)
    np.testing.assert_allclose(rgb, np.broadcast_to(expect, rgb.shape),
                               rtol=tol.BG_RTOL, atol=tol.BG_ATOL)



@pytest.mark.parametrize("j", [0, 3, 6])
def test_single_opaque_layer_gives_its_colour(device, j):
    # Layer j very dense, all others empty: the first segment touching layer j (between j - 1
    # and j, or 0 and 1 for j = 0) has sigma = (weight of layer j) * 1e4 * delta >> 100, so the
    # ray stops there (T = 0 in float32) and sees the colour around layer j. With layers j - 1
    # .. j + 1 coloured c, that is c; the other layers carry random colours that must not leak.
    L, H = 7, 4
    m, den, col = make_model(device, L, H, seed=j)
    den[:] = 0.0
    den[j] = 1e4
    c = np.array([0.2, -0.1, 0.4])
    col[max(j - 1, 0): j + 2] = c
    m.set_params(den, col)
    o, d, _ = make_rays(25, m.r_inner, seed=j)
    rgb, T = m.forward(o, d)
    np.testing.assert_array_equal(T, np.zeros(25, np.float32))
    np.testing.assert_allclose(rgb, np.broadcast_to(c + 0.5, (25, 3)), rtol=tol.BG_RTOL,
                               atol=tol.BG_ATOL)


def test_pole_uses_the_clamped_top_and_bottom_rows(device):
    # Straight up / down from the centre the latitude coordinate clamps to the last / first
    # row, whatever the longitude: uniform density and colour c_top (c_bot) on those rows only.
    L, H, sigma = 5, 6, 0.3
    m, den, col = make_model(device, L, H, seed=9, color=(-0.5, 0.5))
    den[:] = sigma
    col[:, H - 1] = [0.3, 0.1, -0.2]
    col[:, 0] = [-0.4, 0.0, 0.2]
    m.set_params(den, col)
    o = np.broadcast_to(np.float32(CENTER), (2, 3))
    rgb, T = m.forward(o, [[0, 0, 1], [0, 0, -1]])
    r = radii(L, m.r_inner)
    T_exp = np.exp(-sigma * (r[-1] - r[0]))
    expect = np.array([[0.8, 0.6, 0.3], [0.1, 0.5, 0.7]]) * (1 - T_exp) + T_exp * np.asarray(BG)
    np.testing.assert_allclose(rgb, expect, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)


def test_longitude_seam_is_continuous(device):
    # Directions either side of longitude +-pi (and on it, y = +0 / -0) must agree up to the
    # change of the field over the angle between them (2e-6 rad * |gradient| ~ 1e-5 here).
    m, _, _ = make_model(device, 6, 8, seed=5, density=(0.0, 2.0), color=(-1, 1))
    eps = 1e-6
    d = np.array([[-1, eps, 0.2], [-1, -eps, 0.2], [-1, 0.0, 0.2], [-1, -0.0, 0.2]], np.float32)
    rgb, T = m.forward(np.broadcast_to(np.float32(CENTER), (4, 3)), d)
    np.testing.assert_allclose(rgb, np.broadcast_to(rgb[2], (4, 3)), atol=tol.BG_ATOL)
    np.testing.assert_allclose(T, np.broadcast_to(T[2], 4), atol=tol.BG_ATOL)


# ---- backward --------------------------------------------------------------------------------

@pytest.mark.parametrize("L,H", [(2, 1), (4, 3), (9, 6)])
@pytest.mark.parametrize("t_start_max", [0.0, 3.0])
def test_backward_matches_reference(device, L, H, t_start_max):
    m, den, col = make_model(device, L, H, seed=L + 7 * H, density=(-0.5, 1.5), color=(-0.8, 0.8))
    o, d, t = make_rays(300, m.r_inner, seed=H, t_start_max=t_start_max)
    g = np.random.default_rng(L).normal(size=(300, 3)).astype(np.float32)
    gd, gc = m.backward(o, d, g, t)
    rd, rc = ref.backward(den, col, m.r_inner, o, d, t, g, m.center, m.background)
    assert np.abs(rd).max() > 0 and np.abs(rc).max() > 0
    np.testing.assert_allclose(gd, rd, rtol=tol.BG_GRAD_RTOL, atol=tol.BG_GRAD_ATOL)
    np.testing.assert_allclose(gc, rc, rtol=tol.BG_GRAD_RTOL, atol=tol.BG_GRAD_ATOL)


def test_backward_accumulates(device):
    # backward_device adds into the given arrays: twice gives twice
    import pyopencl.array as cla
    m, den, col = make_model(device, 4, 2, seed=1)
    o, d, t = make_rays(20, m.r_inner, seed=1)
    g = np.ones((20, 3), np.float32)
    gd1, gc1 = m.backward(o, d, g, t)
    q = device.queue
    args = [cla.to_device(q, a) for a in (o, d, t, g)]
    gd = cla.zeros(q, m.shape, np.float32)
    gc = cla.zeros(q, m.shape + (3,), np.float32)
    m.backward_device(*args, gd, gc)
    m.backward_device(*args, gd, gc)
    np.testing.assert_allclose(gd.get(), 2 * gd1, rtol=tol.BG_GRAD_RTOL, atol=tol.BG_GRAD_ATOL)
    np.testing.assert_allclose(gc.get(), 2 * gc1, rtol=tol.BG_GRAD_RTOL, atol=tol.BG_GRAD_ATOL)


@pytest.mark.parametrize("t_start_max", [0.0, 3.0])
def test_reference_gradient_vs_finite_differences(t_start_max):
    # tiny problem, every parameter; densities > 0 and colours > -0.5 keep away from the kinks
    L, H, r_inner = 3, 2, 1.3
    rng = np.random.default_rng(11)
    den = rng.uniform(0.05, 0.6, (L, H, 2 * H))
    col = rng.uniform(-0.3, 0.3, (L, H, 2 * H, 3))
    o, d, t = make_rays(12, r_inner, seed=3, t_start_max=t_start_max)
    g = rng.normal(size=(12, 3))
    rd, rc = ref.backward(den, col, r_inner, o, d, t, g, CENTER, BG)
    fd_d = np.array([ref.finite_difference(den, col, r_inner, o, d, t, g, "density", i, CENTER,
                                           BG, eps=tol.BG_FD_EPS)
                     for i in np.ndindex(den.shape)]).reshape(den.shape)
    fd_c = np.array([ref.finite_difference(den, col, r_inner, o, d, t, g, "color", i, CENTER, BG,
                                           eps=tol.BG_FD_EPS)
                     for i in np.ndindex(col.shape)]).reshape(col.shape)
    assert np.abs(fd_d).max() > 1e-2 and np.abs(fd_c).max() > 1e-2
    np.testing.assert_allclose(rd, fd_d, rtol=tol.BG_FD_RTOL, atol=tol.BG_FD_ATOL)
    np.testing.assert_allclose(rc, fd_c, rtol=tol.BG_FD_RTOL, atol=tol.BG_FD_ATOL)


def test_kernel_gradient_vs_kernel_finite_differences(device):
    # the float32 kernels against themselves: directional derivative of sum(g * rgb) along a
    # random unit direction v in parameter space, central difference with step e
    m, den, col = make_model(device, 4, 3, seed=21)
    o, d, t = make_rays(64, m.r_inner, seed=21)
    rng = np.random.default_rng(22)
    g = rng.normal(size=(64, 3))
    vd, vc = rng.normal(size=den.shape), rng.normal(size=col.shape)
    nrm = np.sqrt(np.sum(vd ** 2) + np.sum(vc ** 2))
    vd, vc = vd / nrm, vc / nrm
    gd, gc = m.backward(o, d, g, t)
    analytic = np.sum(gd * vd) + np.sum(gc * vc)
    e = tol.BG_KERNEL_FD_EPS
    vals = []
    for s in (e, -e):
        m.set_params(den + s * vd, col + s * vc)
        vals.append(np.sum(g * m.forward(o, d, t)[0].astype(np.float64)))
    fd = (vals[0] - vals[1]) / (2 * e)
    np.testing.assert_allclose(analytic, fd, rtol=tol.BG_KERNEL_FD_RTOL)


@pytest.mark.parametrize("scale", [0.0] + [10.0 ** k for k in range(-30, 31, 5)])
def test_density_scale_sweep_finite(device, scale):
    m, den, col = make_model(device, 6, 4, seed=2, density=(-1, 1), color=(-1, 1))
    m.set_params(den * scale)
    o, d, t = make_rays(40, m.r_inner, seed=2, t_start_max=2.0)
    rgb, T = m.forward(o, d, t)
    assert np.all(np.isfinite(rgb)) and np.all(np.isfinite(T))
    assert np.all((T >= 0) & (T <= 1))
    gd, gc = m.backward(o, d, np.ones((40, 3)), t)
    assert np.all(np.isfinite(gd)) and np.all(np.isfinite(gc))
    if scale <= 1e3:   # float64 reference stays meaningful where float32 is not saturated
        r_rgb, r_T = ref_forward(m, den * scale, col, o, d, t)
        np.testing.assert_allclose(rgb, r_rgb, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)


# ---- host ------------------------------------------------------------------------------------

def test_state_dict_round_trip(device):
    m, den, col = make_model(device, 5, 3, seed=4)
    o, d, t = make_rays(16, m.r_inner, seed=4)
    st = m.state_dict()
    m2 = MSIBackground.from_state_dict(device, st)
    assert (m2.layers, m2.height, m2.width) == (5, 3, 6)
    np.testing.assert_array_equal(m2.forward(o, d, t)[0], m.forward(o, d, t)[0])
    with pytest.raises(ValueError, match="bg_density"):
        m2.load_state_dict(dict(st, bg_density=np.zeros((5, 3, 5))))
    with pytest.raises(ValueError, match="bg_color"):
        m2.load_state_dict({k: v for k, v in st.items() if k != "bg_color"})


def test_invalid_sizes(device):
    with pytest.raises(ValueError, match="layers"):
        MSIBackground(device, 1, 4, 1.0)
    with pytest.raises(ValueError, match="height"):
        MSIBackground(device, 4, 0, 1.0)
    with pytest.raises(ValueError, match="r_inner"):
        MSIBackground(device, 4, 4, 0.0)
    with pytest.raises(BuildError, match="BG_LAYERS"):
        device.program("background.cl", {"BG_LAYERS": 1, "BG_H": 4})
    with pytest.raises(BuildError, match="BG_H"):
        device.program("background.cl", {"BG_LAYERS": 4, "BG_H": 0})


@pytest.mark.parametrize("caps", [{"fp64": False}, {"float_atomics": False}])
def test_portable_paths(device, monkeypatch, caps):
    # devices without fp64 (per-ray set-up in float32) and without native float atomics
    # (compare-and-swap loop): same results within the same tolerances
    import dataclasses
    monkeypatch.setattr(device, "caps", dataclasses.replace(device.caps, **caps))
    m, den, col = make_model(device, 12, 6, seed=31, density=(-0.5, 1.5), color=(-0.8, 0.8))
    o, d, t = make_rays(200, m.r_inner, seed=31, t_start_max=3.0)
    g = np.random.default_rng(31).normal(size=(200, 3)).astype(np.float32)
    rgb, T = m.forward(o, d, t)
    r_rgb, r_T = ref_forward(m, den, col, o, d, t)
    np.testing.assert_allclose(rgb, r_rgb, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)
    np.testing.assert_allclose(T, r_T, rtol=tol.BG_RTOL, atol=tol.BG_ATOL)
    gd, gc = m.backward(o, d, g, t)
    rd, rc = ref.backward(den, col, m.r_inner, o, d, t, g, m.center, m.background)
    np.testing.assert_allclose(gd, rd, rtol=tol.BG_GRAD_RTOL, atol=tol.BG_GRAD_ATOL)
    np.testing.assert_allclose(gc, rc, rtol=tol.BG_GRAD_RTOL, atol=tol.BG_GRAD_ATOL)
