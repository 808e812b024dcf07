"""Multiresolution hash encoding (cl/hash.cl) vs the float64 reference, its backward on both
accumulation paths (float atomics, private copies per slot), and the SH direction encoding."""
from types import SimpleNamespace

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.hash.encoding import HashEncoding, level_resolutions
from clrf.references import reference_hash as ref
from clrf.testing import tolerances as tol

BOX = ((-1.5, -1.0, -0.5), (1.5, 1.0, 2.5))


@pytest.fixture(scope="module", params=["atomics", "owned"])
def hash_device(request, device):
    """Both backward paths on the session device: float atomics (the GPU path) and one
    work-item per level owning its table (the CPU path)."""
    return device.with_tuning(grad_slots=0 if request.param == "atomics" else 2)


def _enc(dev, L=4, F=2, log2_t=10, n_min=2, n_max=40, seed=0, box=BOX):
    rng = np.random.default_rng(seed)
    table = rng.uniform(-1, 1, (L, 1 << log2_t, F)).astype(np.float32)
    return HashEncoding(dev, L, F, log2_t, n_min, n_max, box, table=table), table


def _points(n, seed=1, lo=-0.1, hi=1.1, box=BOX):
    rng = np.random.default_rng(seed)
    u = rng.uniform(lo, hi, (n, 3))
    a, b = np.asarray(box[0]), np.asarray(box[1])
    return (a + u * (b - a)).astype(np.float32)


def _fwd(enc, x):
    return enc.forward(cla.to_device(enc.device.queue, x)).get()


def _ref_fwd(enc, x, table):
    return ref.hash_forward(x, enc.lo, enc.inv_ext, enc.res_host, table)


def test_level_resolutions_match_reference_and_ends():
    for L, a, b in [(16, 16, 2048), (8, 16, 512), (1, 4, 4), (5, 3, 7), (16, 16, 16)]:
        r = level_resolutions(L, a, b)
        np.testing.assert_array_equal(r, ref.level_resolutions(L, a, b))
        assert r[0] == a and r[-1] == b and np.all(np.diff(r) >= 0)
    with pytest.raises(ValueError, match="n_min"):
        level_resolutions(4, 8, 4)


@pytest.mark.parametrize("n", [0, 1, 7, 65])
@pytest.mark.parametrize("F", [1, 2, 4])
def test_forward_matches_reference(device, n, F):
    enc, table = _enc(device, F=F, seed=n + F)
    x = _points(n, seed=n)
    out = _fwd(enc, x)
    assert out.shape == (n, 4 * F)
    np.testing.assert_allclose(out, _ref_fwd(enc, x, table), rtol=0, atol=tol.HASH_ATOL)


def test_forward_dense_and_hashed_levels(device):
    """n_min 2 .. n_max 40 with T = 2^10: levels 0-1 dense ((N+1)^3 <= 1024), the rest hashed;
    a constant table interpolates to the constant on both kinds (weights sum to 1)."""
    enc, _ = _enc(device)
    R = enc.res_host.astype(np.int64) + 1
    assert np.any(R ** 3 <= enc.T) and np.any(R ** 3 > enc.T)
    enc.table.fill(np.float32(0.25))
    out = _fwd(enc, _points(33))
    np.testing.assert_allclose(out, 0.25, rtol=0, atol=tol.HASH_ATOL)


def test_forward_cell_boundaries_and_vertices(device):
    """Points exactly on cell faces and vertices (u = k / N for power-of-two N, exact in float32)
    and the box corners u = 0, 1: the kernel interpolates the vertex value itself."""
    box = ((0.0,) * 3, (1.0,) * 3)
    enc, table = _enc(device, L=3, n_min=4, n_max=16, log2_t=12, box=box)
    assert list(enc.res_host) == [4, 8, 16]
    k = np.arange(0, 17) / 16.0
    x = np.stack(np.meshgrid(k, k[::3], k[::5], indexing="ij"), -1).reshape(-1, 3)
    x = x.astype(np.float32)
    out = _fwd(enc, x)
    np.testing.assert_allclose(out, _ref_fwd(enc, x, table), rtol=0, atol=tol.HASH_ATOL)
    # level 2 (N = 16, dense since 17^3 = 4913 <= 4096 is false -> hashed): at a vertex v the
    # value is the table row of v, whatever the indexing
    rows, wts = ref.cell(ref.unit_coords(x, enc.lo, enc.inv_ext), 16, enc.T)
    hit = np.argmax(wts, axis=1)
    assert np.allclose(wts.max(axis=1), 1.0)
    np.testing.assert_allclose(out[:, 4:6], table[2][rows[np.arange(len(x)), hit]], rtol=0,
                               atol=tol.HASH_ATOL)


def test_forward_clamps_outside_box_and_nan(device):
    """Outside the box the encoding is that of the nearest boundary point; NaN reads u = 0."""
    enc, table = _enc(device)
    lo, hi = np.asarray(BOX[0]), np.asarray(BOX[1])
    inside = _points(9, lo=0.0, hi=1.0)
    far_out = inside.copy()
    far_out[:, 0] = hi[0] + 10.0      # clamps to u_x = 1
    far_out[:, 1] = lo[1] - 1e6       # clamps to u_y = 0
    on_face = inside.copy()
    on_face[:, 0], on_face[:, 1] = hi[0], lo[1]
    np.testing.assert_allclose(_fwd(enc, far_out), _fwd(enc, on_face), rtol=0, atol=0)
    nan = np.array([[np.nan, lo[1], lo[2]]], np.float32)
    np.testing.assert_allclose(_fwd(enc, nan), _fwd(enc, lo[None].astype(np.float32)), rtol=0,
                               atol=0)
    assert np.all(np.isfinite(_fwd(enc, np.full((3, 3), 1e30, np.float32))))


def test_forward_levels_finer_than_needed(device):
    """N_max = 4096 with T = 2^8: every fine level collides everywhere; still the reference."""
    enc, table = _enc(device, L=6, n_min=64, n_max=4096, log2_t=8, seed=3)
    x = _points(65, seed=4)
    np.testing.assert_allclose(_fwd(enc, x), _ref_fwd(enc, x, table), rtol=0,
                               atol=tol.HASH_ATOL)


def _bwd(enc, x, genc):
    q = enc.device.queue
    enc.grad.fill(np.float32(0))
    enc.backward(cla.to_device(q, x), cla.to_device(q, genc))
    return enc.grad.get()


def _assert_grad(got, want):
    np.testing.assert_allclose(got, want, rtol=0,
                               atol=tol.HASH_GRAD_ATOL + tol.HASH_GRAD_RTOL * np.abs(want).max())


@pytest.mark.parametrize("n", [0, 1, 7, 65])
def test_backward_matches_reference(hash_device, n):
    enc, _ = _enc(hash_device, seed=n)
    x = _points(n, seed=10 + n)
    genc = np.random.default_rng(n).uniform(-1, 1, (n, enc.dim)).astype(np.float32)
    want = ref.hash_backward(x, enc.lo, enc.inv_ext, enc.res_host, genc, enc.shape)
    _assert_grad(_bwd(enc, x, genc), want)


def test_backward_accumulates(hash_device):
    """backward ADDS to enc.grad (two calls = twice one call)."""
    enc, _ = _enc(hash_device, seed=2)
    x = _points(40, seed=2)
    genc = np.random.default_rng(2).uniform(-1, 1, (40, enc.dim)).astype(np.float32)
    one = _bwd(enc, x, genc)
    q = hash_device.queue
    enc.backward(cla.to_device(q, x), cla.to_device(q, genc))
    _assert_grad(enc.grad.get(), 2 * one.astype(np.float64))


@pytest.mark.parametrize("log2_t", [1, 4])
def test_backward_collisions_tiny_table(hash_device, log2_t):
    """T = 2 and T = 16: almost every vertex of every level collides; gradients still sum."""
    enc, _ = _enc(hash_device, L=5, log2_t=log2_t, n_min=4, n_max=64, seed=5)
    x = _points(65, seed=5)
    genc = np.random.default_rng(5).uniform(-1, 1, (65, enc.dim)).astype(np.float32)
    want = ref.hash_backward(x, enc.lo, enc.inv_ext, enc.res_host, genc, enc.shape)
    _assert_grad(_bwd(enc, x, genc), want)
    np.testing.assert_allclose(_fwd(enc, x), _ref_fwd(enc, x, enc.table.get()), rtol=0,
                               atol=tol.HASH_ATOL)


def test_backward_boundaries_and_outside(hash_device):
    """Cell-face points and points outside the box (clamped) scatter like the reference."""
    enc, _ = _enc(hash_device, L=3, n_min=4, n_max=16, log2_t=9, box=((0,) * 3, (1,) * 3))
    k = np.arange(-2, 19) / 16.0
    x = np.stack([k, k[::-1], np.full_like(k, 0.5)], 1).astype(np.float32)
    genc = np.random.default_rng(6).uniform(-1, 1, (len(x), enc.dim)).astype(np.float32)
    want = ref.hash_backward(x, enc.lo, enc.inv_ext, enc.res_host, genc, enc.shape)
    _assert_grad(_bwd(enc, x, genc), want)


def test_used_spans_hold_every_reachable_entry(device):
    """The optimiser's spans: every entry that the reference backward reaches (points all over
    the box, its 8 corners and beyond it) lies inside them; each dense level's span ends at
    its last vertex's row, which the box's far corner reaches; hashed levels span all T."""
    enc, _ = _enc(device, L=5, F=2, log2_t=12, n_min=3, n_max=40)
    corners = np.array(np.meshgrid(*zip(*BOX), indexing="ij")).reshape(3, -1).T
    x = np.concatenate([_points(3000, seed=8, lo=-0.2, hi=1.2), corners]).astype(np.float32)
    reach = ref.hash_backward(x, enc.lo, enc.inv_ext, enc.res_host,
                              np.ones((len(x), enc.dim), np.float32), enc.shape) != 0
    inside = np.zeros(reach.size, bool)
    for a, b in enc.used_spans():
        inside[a:b] = True
    assert not np.any(reach.reshape(-1) & ~inside)
    for l, N in enumerate(enc.res_host):
        rows = (int(N) + 1) ** 3
        if rows <= enc.T:
            assert reach[l, rows - 1].all() and not inside.reshape(enc.shape)[l, rows:].any()
        else:
            assert inside.reshape(enc.shape)[l].all()
    assert (int(enc.res_host[0]) + 1) ** 3 <= enc.T < (int(enc.res_host[-1]) + 1) ** 3
    assert len(enc.used_spans()) < enc.levels   # the hashed levels merge into one span


def test_reference_backward_vs_finite_differences():
    """L = sum genc * enc(table): the reference gradient against central differences."""
    rng = np.random.default_rng(7)
    shape = (3, 64, 2)
    table = rng.uniform(-1, 1, shape)
    res = ref.level_resolutions(3, 2, 9)
    lo, inv = np.zeros(3, np.float32), np.ones(3, np.float32)
    x = rng.uniform(0, 1, (11, 3)).astype(np.float32)
    genc = rng.uniform(-1, 1, (11, 6))
    g = ref.hash_backward(x, lo, inv, res, genc, shape)
    touched = np.argwhere(g != 0)
    assert len(touched) > 10
    for idx in touched[:: max(1, len(touched) // 25)]:
        e = np.zeros(shape)
        e[tuple(idx)] = tol.HASH_FD_EPS
        fd = (np.sum(genc * ref.hash_forward(x, lo, inv, res, table + e))
              - np.sum(genc * ref.hash_forward(x, lo, inv, res, table - e))) / (2 * tol.HASH_FD_EPS)
        assert abs(fd - g[tuple(idx)]) <= tol.HASH_FD_ATOL


def test_kernel_backward_vs_kernel_forward_differences(hash_device):
    """The kernels against each other: enc is linear in the table, so sum(genc * (enc(table +
    e_j) - enc(table))) is exactly dL/dtable_j (up to float32 rounding)."""
    enc, table = _enc(hash_device, L=3, log2_t=6, n_min=2, n_max=12, seed=8)
    x = _points(17, seed=8)
    genc = np.random.default_rng(8).uniform(-1, 1, (17, enc.dim)).astype(np.float32)
    g = _bwd(enc, x, genc)
    base = _fwd(enc, x).astype(np.float64)
    rng = np.random.default_rng(9)
    flat = np.flatnonzero(g)
    for j in rng.choice(flat, 12, replace=False):
        t2 = table.copy().reshape(-1)
        t2[j] += 1.0
        enc.table.set(t2.reshape(table.shape))
        d = np.sum(genc * (_fwd(enc, x).astype(np.float64) - base))
        assert abs(d - g.reshape(-1)[j]) <= tol.HASH_KERNEL_FD_ATOL * 17 * enc.dim
    enc.table.set(table)


@pytest.mark.parametrize("n", [0, 1, 65])
def test_sh_encode_matches_reference(device, n):
    enc, _ = _enc(device)
    d = np.random.default_rng(n).normal(size=(n, 3)).astype(np.float32)
    if n:
        d[0] = 0.0          # zero direction: the basis at (0, 0, 0)
        d[-1] *= 1e-20 if n > 1 else 1.0
    out = enc.sh_encode(cla.to_device(device.queue, d)).get()
    assert out.shape == (n, 16)
    np.testing.assert_allclose(out, ref.sh_encode(d), rtol=0, atol=tol.HASH_SH_ATOL)


def test_bad_sizes_raise(device):
    with pytest.raises(ValueError, match="features"):
        HashEncoding(device, features=3)
    with pytest.raises(ValueError, match="box"):
        HashEncoding(device, 2, 2, 4, 2, 4, box=((0, 0, 0), (1, 0, 1)))
    with pytest.raises(ValueError, match="table"):
        HashEncoding(device, 2, 2, 4, 2, 4, table=np.zeros((2, 8, 2)))


# ---- the spatial derivative dL/dx (hash_dx) ------------------------------------------------
def _dx(enc, x, genc):
    q = enc.device.queue
    return enc.dx(cla.to_device(q, x), cla.to_device(q, genc)).get()


def _ref_dx(enc, x, genc, table, f64=False):
    return ref.hash_dx(x, enc.lo, enc.inv_ext, enc.res_host, table, genc, f64)


def _dx_bound(enc, genc, table):
    """B [n, 3] = 2 inv_ext_a sum_l N_l sum_f |dL/denc_lf| max|table| (tolerances)."""
    gl = np.abs(np.asarray(genc, np.float64)).reshape(len(genc), enc.levels, enc.features).sum(axis=2)
    return 2 * (gl @ enc.res_host.astype(np.float64))[:, None] * np.abs(table).max() \
        * enc.inv_ext.astype(np.float64)[None, :]


def _assert_dx(enc, got, want, genc, table):
    """Kernel vs twin within HASH_DX_RTOL_OF_BOUND of each point's bound B_a."""
    assert got.shape == want.shape
    err = np.abs(got - want)
    assert np.all(err <= tol.HASH_DX_RTOL_OF_BOUND * _dx_bound(enc, genc, table)), err.max()


def _loss64(enc, x, genc, table):
    return np.sum(genc * ref.hash_forward(x, enc.lo, enc.inv_ext, enc.res_host, table, True),
                  axis=1)


def _off_faces(x, enc, margin):
    """Rows of x whose p = u N_l lies at least ``margin`` (in p units per unit of N_l u) from
    every cell face of every level, strictly inside the box."""
    u = ref.unit_coords(x, enc.lo, enc.inv_ext, True)
    ok = np.all((u > margin) & (u < 1 - margin), axis=1)
    for N in enc.res_host:
        fr = u * N - np.floor(u * N)
        ok &= np.all((fr > margin * N) & (fr < 1 - margin * N), axis=1)
    return x[ok]


@pytest.mark.parametrize("n", [0, 1, 7, 65])
@pytest.mark.parametrize("F", [1, 2, 4])
def test_dx_matches_twin(device, n, F):
    enc, table = _enc(device, F=F, seed=20 + n + F)
    x = _points(n, seed=30 + n)
    genc = np.random.default_rng(n + F).uniform(-1, 1, (n, enc.dim)).astype(np.float32)
    _assert_dx(enc, _dx(enc, x, genc), _ref_dx(enc, x, genc, table), genc, table)


def test_twin_dx_vs_central_differences():
    """The twin (float64 u and p) against central differences of L = sum genc * enc(x) with
    steps that stay inside each level's cell: the encoding is linear along an axis there."""
    rng = np.random.default_rng(11)
    L, T, F = 4, 1 << 10, 2
    table = rng.uniform(-1, 1, (L, T, F))
    lo, hi = np.asarray(BOX[0]), np.asarray(BOX[1])
    enc = SimpleNamespace(lo=lo, inv_ext=1 / (hi - lo), res_host=ref.level_resolutions(L, 2, 40),
                          levels=L, features=F)
    x = _off_faces(_points(200, seed=11, lo=0.0, hi=1.0).astype(np.float64), enc, 1e-4)[:25]
    assert len(x) >= 10
    genc = rng.uniform(-1, 1, (len(x), L * F))
    g = _ref_dx(enc, x, genc, table, True)
    h = tol.HASH_DX_FD_EPS
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        fd = (_loss64(enc, x + e, genc, table) - _loss64(enc, x - e, genc, table)) / (2 * h)
        np.testing.assert_allclose(g[:, a], fd, rtol=tol.HASH_DX_FD_RTOL,
                                   atol=tol.HASH_DX_FD_ATOL)
    assert np.abs(g).max() > 1.0     # the test is not of zeros


def test_kernel_dx_vs_kernel_forward_differences(device):
    """The float32 kernels against each other on the unit box: x on a 2^-20 grid and steps of
    h = 2^-8 (both exact in float32) that stay inside every level's cell, where the encoding is
    linear along the axis; each forward value is within HASH_ATOL of float64, so the central
    difference is within sum|genc| HASH_ATOL / h of the exact derivative, and the kernel's dx
    within its bound of it."""
    box = ((0.0,) * 3, (1.0,) * 3)
    enc, table = _enc(device, L=3, F=2, log2_t=10, n_min=2, n_max=12, seed=12, box=box)
    h = 2.0 ** -8
    rng = np.random.default_rng(12)
    x = np.round(rng.uniform(0, 1, (400, 3)) * 2 ** 20) / 2 ** 20
    x = _off_faces(x, enc, 2 * h)[:20].astype(np.float32)
    assert len(x) >= 10
    genc = rng.uniform(-1, 1, (len(x), enc.dim)).astype(np.float32)
    got = _dx(enc, x, genc)
    slack = np.abs(genc).sum(axis=1) * tol.HASH_ATOL / h
    for a in range(3):
        e = np.zeros(3, np.float32)
        e[a] = h
        fd = (np.sum(genc * _fwd(enc, x + e), axis=1, dtype=np.float64)
              - np.sum(genc * _fwd(enc, x - e), axis=1, dtype=np.float64)) / (2 * h)
        want = _ref_dx(enc, x, genc, table)[:, a]
        assert np.all(np.abs(fd - want) <= slack), np.abs(fd - want).max()
        bound = tol.HASH_DX_RTOL_OF_BOUND * _dx_bound(enc, genc, table)[:, a]
        assert np.all(np.abs(got[:, a] - fd) <= slack + bound)


def test_dx_on_faces_corners_and_box_bounds(device):
    """Points on cell faces, vertices and the box's faces (u = k / 16, exact): the kernel equals
    the twin, and the twin equals the one-sided difference into the cell the forward reads
    (from above on an interior face and at u = 0, from below at u = 1)."""
    box = ((0.0,) * 3, (1.0,) * 3)
    enc, table = _enc(device, L=3, n_min=4, n_max=16, log2_t=12, box=box, seed=13)
    k = np.arange(0, 17) / 16.0
    x = np.stack(np.meshgrid(k, k[::3], k[::5], indexing="ij"), -1).reshape(-1, 3)
    x = x.astype(np.float32)
    genc = np.random.default_rng(13).uniform(-1, 1, (len(x), enc.dim)).astype(np.float32)
    want = _ref_dx(enc, x, genc, table)
    _assert_dx(enc, _dx(enc, x, genc), want, genc, table)
    h = tol.HASH_DX_FD_EPS
    x64 = x.astype(np.float64)
    for a in range(3):
        step = np.where(x64[:, a] < 1.0, h, -h)     # into the cell the forward reads
        e = np.zeros_like(x64)
        e[:, a] = step
        fd = (_loss64(enc, x64 + e, genc, table) - _loss64(enc, x64, genc, table)) / step
        np.testing.assert_allclose(_ref_dx(enc, x64, genc, table, True)[:, a], fd, rtol=0,
                                   atol=tol.HASH_DX_FD_ATOL)


def test_dx_outside_the_box_nan_and_huge(device):
    """Outside the box on an axis the encoding is clamped there: that axis's derivative is 0,
    the others are the boundary point's; NaN and 1e30 give finite zeros."""
    enc, table = _enc(device, seed=14)
    lo, hi = np.asarray(BOX[0]), np.asarray(BOX[1])
    inside = _points(9, lo=0.05, hi=0.95)
    out = inside.copy()
    out[:, 0] = hi[0] + 10.0
    face = inside.copy()
    face[:, 0] = hi[0]
    genc = np.random.default_rng(14).uniform(-1, 1, (9, enc.dim)).astype(np.float32)
    g_out, g_face = _dx(enc, out, genc), _dx(enc, face, genc)
    assert np.all(g_out[:, 0] == 0) and np.all(g_face[:, 0] != 0)
    np.testing.assert_array_equal(g_out[:, 1:], g_face[:, 1:])
    _assert_dx(enc, g_out, _ref_dx(enc, out, genc, table), genc, table)
    odd = np.array([[np.nan, 0.0, 0.5], [1e30, -1e30, 1e30], [np.nan] * 3], np.float32)
    g = _dx(enc, odd, genc[:3])
    assert np.all(np.isfinite(g))
    assert np.all(g[1:] == 0) and g[0, 0] == 0
    _assert_dx(enc, g, _ref_dx(enc, odd, genc[:3], table), genc[:3], table)


@pytest.mark.parametrize("levels,n_min,n_max,log2_t", [(1, 1, 1, 4), (2, 1, 4096, 8)])
def test_dx_coarsest_and_finest_levels(device, levels, n_min, n_max, log2_t):
    """One cell over the whole box (N = 1, dense), and a 4096-cell level hashed into 256 rows
    next to N = 1: the kernel against the twin, and the twin against central differences."""
    enc, table = _enc(device, L=levels, n_min=n_min, n_max=n_max, log2_t=log2_t, seed=15)
    x = _points(65, seed=15, lo=0.0, hi=1.0)
    genc = np.random.default_rng(15).uniform(-1, 1, (65, enc.dim)).astype(np.float32)
    _assert_dx(enc, _dx(enc, x, genc), _ref_dx(enc, x, genc, table), genc, table)
    h = tol.HASH_DX_FD_EPS
    x64 = _off_faces(x.astype(np.float64), enc, 1e-5)
    assert len(x64) >= 10
    g = _ref_dx(enc, x64, genc[:len(x64)], table, True)
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        fd = (_loss64(enc, x64 + e, genc[:len(x64)], table)
              - _loss64(enc, x64 - e, genc[:len(x64)], table)) / (2 * h)
        np.testing.assert_allclose(g[:, a], fd, rtol=tol.HASH_DX_FD_RTOL,
                                   atol=tol.HASH_DX_FD_ATOL)
