"""Fused MLP (cl/mlp.cl) vs the float64 reference, finite differences, awkward batch sizes and
every register tile the kernel allows. The reference tests run the device's own tiling (the GPU
tiling on GPUs and with CLRF_FORCE_GPU_KERNELS=1; tests/test_mlp_gpu.py forces it everywhere);
the register-tile tests run the CPU tiles on every device."""
from dataclasses import replace

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.testing import impls

from clrf.references import reference_nerf as ref
from clrf.mlp.mlp import MLP, MLPSpec
from clrf.testing import tolerances as tol

# tiny networks: skip into layer 1 with softplus everywhere; no skip with ReLU; a chunk of
# 16 rows so that the partial-sum reduction of the weight gradient has several chunks.
SPECS = {
    "skip-softplus": MLPSpec(width=16, depth=3, skip=0, color_width=16, in_dim=9, dir_dim=5,
                             hidden_act="softplus", sigma_act="softplus", dw_chunk=16),
    "relu": MLPSpec(width=32, depth=2, skip=-1, color_width=16, in_dim=15, dir_dim=9,
                    dw_chunk=16),
    "small-4x64": MLPSpec(width=64, depth=4, skip=1, color_width=32, in_dim=51, dir_dim=27),
    # the hash model's shape: 16 features from the head, two colour hidden layers
    "hash-1x64-c2": MLPSpec(width=64, depth=1, skip=-1, color_width=64, in_dim=32, dir_dim=16,
                            sigma_act="trunc_exp", color_depth=2, features=16),
    "deep-colour-softplus": MLPSpec(width=32, depth=2, skip=-1, color_width=16, in_dim=9,
                                    dir_dim=5, hidden_act="softplus", sigma_act="trunc_exp",
                                    color_depth=3, features=16, dw_chunk=16),
}
_nets = {}


def get_net(device, name):
    if name not in _nets:
        net = MLP(device, SPECS[name], seed=1)
        # non-zero biases so that every ReLU sees both signs and padding stays exercised
        p = net.params.get()
        rng = np.random.default_rng(2)
        for L, (rows, _) in zip(net.layout.layers, net.layout.logical_shapes(net.spec)):
            p[L["b_off"] + rows] = rng.uniform(-0.3, 0.3, len(rows))
        net.set_params(p)
        _nets[name] = net
    return _nets[name]


def inputs(spec, n, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, spec.in_dim)).astype(np.float32),
            rng.normal(size=(n, spec.dir_dim)).astype(np.float32))


def run_forward(net, x, d):
    q = net.device.queue
    s, c = net.forward(cla.to_device(q, x), cla.to_device(q, d))
    return s.get(), c.get()


def run_backward(net, x, d, ds, dr, accumulate=False):
    q = net.device.queue
    net.forward(cla.to_device(q, x), cla.to_device(q, d))
    dx, dd = net.backward(cla.to_device(q, ds), cla.to_device(q, dr), accumulate=accumulate,
                          want_input=True)
    return net.grad.get(), dx.get(), dd.get()


def _skip_on_a_slow_implementation(device, name):
    """A slow software implementation (rusticl's llvmpipe: ~40 s to compile each network) runs
    the first network of SPECS only; the session device and the others run every one."""
    from clrf.runtime.tuning import implementation
    impl = implementation(getattr(device.caps, "platform", ""))
    if name != next(iter(SPECS)) and impl != impls.default_implementation() \
            and impl in impls.present() and impls.is_slow(impl):
        pytest.skip(f"{impl} is a slow implementation here: it runs {next(iter(SPECS))} only")


@pytest.mark.parametrize("name", list(SPECS))
@pytest.mark.parametrize("n", [0, 1, 7, 8 - 1, 8 + 1, 37])
def test_forward_matches_reference(device, name, n):
    _skip_on_a_slow_implementation(device, name)
    net = get_net(device, name)
    x, d = inputs(net.spec, n, seed=n)
    s, c = run_forward(net, x, d)
    rs, rc = ref.mlp_forward(net.params.get(), net.spec, net.layout, x, d)
    assert s.shape == (n,) and c.shape == (n, 3)
    np.testing.assert_allclose(s, rs, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
    np.testing.assert_allclose(c, rc, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)


def _close_rel_to_max(a, b):
    scale = max(np.abs(b).max(initial=0.0), 1e-30)
    np.testing.assert_allclose(a, b, rtol=0, atol=tol.MLP_GRAD_REL_TO_MAX * scale)


@pytest.mark.parametrize("name", list(SPECS))
@pytest.mark.parametrize("n", [1, 7, 9, 37])
def test_backward_matches_reference(device, name, n):
    _skip_on_a_slow_implementation(device, name)
    net = get_net(device, name)
    x, d = inputs(net.spec, n, seed=10 + n)
    rng = np.random.default_rng(n)
    ds = rng.normal(size=n).astype(np.float32)
    dr = rng.normal(size=(n, 3)).astype(np.float32)
    g, dx, dd = run_backward(net, x, d, ds, dr)
    r = ref.mlp_backward(net.params.get(), net.spec, net.layout, x, d, ds, dr)
    for L in net.layout.layers:   # each layer's weights and biases relative to their own scale
        _close_rel_to_max(g[L["w_off"]:L["b_off"]], r["params"][L["w_off"]:L["b_off"]])
        _close_rel_to_max(g[L["b_off"]:L["b_off"] + L["nout"]],
                          r["params"][L["b_off"]:L["b_off"] + L["nout"]])
    _close_rel_to_max(dx, r["x_enc"])
    _close_rel_to_max(dd, r["d_enc"])


@pytest.mark.parametrize("name", list(SPECS))
def test_backward_without_input_gradients(device, name):
    """want_input=False (what training runs) skips layer 0's and the encoded direction's input
    columns: the parameter gradients must still match the float64 reference."""
    net = get_net(device, name)
    n = 37
    x, d = inputs(net.spec, n, seed=3)
    rng = np.random.default_rng(3)
    ds = rng.normal(size=n).astype(np.float32)
    dr = rng.normal(size=(n, 3)).astype(np.float32)
    q = net.device.queue
    net.G = None   # fresh scratch: nothing left from a want_input=True call
    net.forward(cla.to_device(q, x), cla.to_device(q, d))
    assert net.backward(cla.to_device(q, ds), cla.to_device(q, dr)) is None
    g = net.grad.get()
    r = ref.mlp_backward(net.params.get(), net.spec, net.layout, x, d, ds, dr)["params"]
    for L in net.layout.layers:
        _close_rel_to_max(g[L["w_off"]:L["b_off"] + L["nout"]],
                          r[L["w_off"]:L["b_off"] + L["nout"]])


def test_batch_over_many_chunks_and_accumulate(device):
    """n = 100 rows over 16-row chunks (7 partials) in groups of 2 chunks (backward and weight
    gradient interleaved), and accumulate=True adds to grad."""
    net = MLP(device, replace(SPECS["relu"], rows=8), seed=5)
    net.group_bytes = 2 * 16 * 8 * net.layout.nslot
    n = 100
    x, d = inputs(net.spec, n, seed=4)
    rng = np.random.default_rng(4)
    ds = rng.normal(size=n).astype(np.float32)
    dr = rng.normal(size=(n, 3)).astype(np.float32)
    g1, _, _ = run_backward(net, x, d, ds, dr)
    g2, _, _ = run_backward(net, x, d, ds, dr, accumulate=True)
    r = ref.mlp_backward(net.params.get(), net.spec, net.layout, x, d, ds, dr)["params"]
    _close_rel_to_max(g1, r)
    _close_rel_to_max(g2, 2 * r)


def test_zero_batch_gives_zero_gradient(device):
    net = get_net(device, "relu")
    x, d = inputs(net.spec, 0)
    g, dx, dd = run_backward(net, x, d, np.zeros(0, np.float32), np.zeros((0, 3), np.float32))
    assert dx.shape == (0, net.spec.in_dim) and np.all(g == 0)


@pytest.mark.parametrize("name", list(SPECS))
def test_padding_gradients_are_exactly_zero(device, name):
    net = get_net(device, name)
    n = 9
    x, d = inputs(net.spec, n, seed=7)
    rng = np.random.default_rng(7)
    g, _, _ = run_backward(net, x, d, rng.normal(size=n).astype(np.float32),
                           rng.normal(size=(n, 3)).astype(np.float32))
    mask = np.zeros(net.layout.n_params, bool)
    for L, (r, c) in zip(net.layout.layers, net.layout.logical_shapes(net.spec)):
        m = np.zeros((L["nout"], L["nin"]), bool)
        m[np.ix_(r, c)] = True
        mask[L["w_off"]:L["b_off"]] = m.ravel()
        mask[L["b_off"] + r] = True
    assert np.all(g[~mask] == 0.0)
    assert np.count_nonzero(g[mask]) > 0.5 * mask.sum()


@pytest.mark.parametrize("name", ["skip-softplus", "relu", "deep-colour-softplus"])
def test_reference_gradient_vs_finite_differences(device, name):
    net = get_net(device, name)
    spec, layout = net.spec, net.layout
    p0 = net.params.get().astype(np.float64)
    n = 5
    x, d = (a.astype(np.float64) for a in inputs(spec, n, seed=8))
    rng = np.random.default_rng(8)
    ds, dr = rng.normal(size=n), rng.normal(size=(n, 3))

    def loss(p=p0, xx=x, dd=d):
        s, c = ref.mlp_forward(p, spec, layout, xx, dd)
        return float(np.sum(ds * s) + np.sum(dr * c))

    an = ref.mlp_backward(p0, spec, layout, x, d, ds, dr)
    # every logical bias and a random subset of logical weights of every layer
    idx = []
    for L, (r, c) in zip(layout.layers, layout.logical_shapes(spec)):
        idx += list(L["b_off"] + r)
        flat = (r[:, None] * L["nin"] + c[None, :]).ravel() + L["w_off"]
        idx += list(rng.choice(flat, size=min(6, flat.size), replace=False))
    idx = np.array(idx)
    fd = ref.numeric_gradient(lambda v: loss(p=_put(p0, idx, v)),
                               p0[idx], tol.MLP_FD_EPS)
    np.testing.assert_allclose(an["params"][idx], fd, rtol=tol.MLP_FD_RTOL, atol=tol.MLP_FD_ATOL)
    fdx = ref.numeric_gradient(lambda v: loss(xx=v), x, tol.MLP_FD_EPS)
    np.testing.assert_allclose(an["x_enc"], fdx, rtol=tol.MLP_FD_RTOL, atol=tol.MLP_FD_ATOL)
    fdd = ref.numeric_gradient(lambda v: loss(dd=v), d, tol.MLP_FD_EPS)
    np.testing.assert_allclose(an["d_enc"], fdd, rtol=tol.MLP_FD_RTOL, atol=tol.MLP_FD_ATOL)


def _put(p, idx, v):
    q = p.copy()
    q[idx] = v
    return q


def test_kernel_directional_derivative(device):
    """The float32 kernels' gradient against their own forward: (L(p + e v) - L(p - e v)) / 2e."""
    net = MLP(device, SPECS["skip-softplus"], seed=3)   # smooth activations: no kinks
    n = 11
    x, d = inputs(net.spec, n, seed=9)
    rng = np.random.default_rng(9)
    ds = rng.normal(size=n).astype(np.float32)
    dr = rng.normal(size=(n, 3)).astype(np.float32)
    p0 = net.params.get()
    g, _, _ = run_backward(net, x, d, ds, dr)
    v = rng.normal(size=p0.size) * (g != 0)   # logical entries only (padding has g == 0)
    v /= np.linalg.norm(v)
    e = tol.MLP_KERNEL_FD_EPS

    def loss(p):
        net.set_params(p.astype(np.float32))
        s, c = run_forward(net, x, d)
        return float(np.sum(ds.astype(np.float64) * s) + np.sum(dr.astype(np.float64) * c))

    fd = (loss(p0 + e * v) - loss(p0 - e * v)) / (2 * e)
    an = float(np.dot(g.astype(np.float64), v))
    assert abs(fd - an) <= tol.MLP_KERNEL_FD_RTOL * max(abs(an), np.linalg.norm(g))


def test_extreme_head_values_stay_finite(device):
    """Pre-activations of +-1e30 at the density and colour heads: softplus and sigmoid give
    finite outputs and finite (zero or one) derivatives."""
    net = MLP(device, SPECS["skip-softplus"], seed=4)
    L = net.layout.layers
    D = net.spec.depth
    for big in (1e30, -1e30, 1e4, -1e4):
        p = net.params.get()
        p[L[D]["b_off"]] = big                      # sigma_raw
        p[L[D + 2]["b_off"]:L[D + 2]["b_off"] + 3] = big   # rgb pre-activations
        net.set_params(p)
        n = 5
        x, d = inputs(net.spec, n, seed=1)
        s, c = run_forward(net, x, d)
        g, dx, dd = run_backward(net, x, d, np.ones(n, np.float32), np.ones((n, 3), np.float32))
        assert np.all(np.isfinite(s)) and np.all(np.isfinite(c))
        assert np.all(np.isfinite(g)) and np.all(np.isfinite(dx)) and np.all(np.isfinite(dd))
        # sigma = softplus(big + W h) and rgb = sigmoid(big + w c): the W h terms are O(10)
        if big > 0:
            assert np.all(c == 1.0) and np.all(s > 0.99 * big)
        else:
            # softplus(-1e4 + O(10)) underflows to ~0: any density below 1e-3 is "empty"
            assert np.all(c == 0.0) and np.all(s >= 0) and np.all(s < 1e-3)


def test_original_nerf_size_builds_and_matches(device):
    """The original 8 x 256, skip at 4, 10/4 frequencies, 128-wide colour layer."""
    spec = MLPSpec(width=256, depth=8, skip=4, color_width=128, in_dim=63, dir_dim=27)
    net = MLP(device, spec, seed=0)
    assert net.layout.layers[5]["nin"] == 256 + 64   # h_4 ++ x (63 padded to 64)
    n = 9
    x, d = inputs(spec, n, seed=2)
    s, c = run_forward(net, x, d)
    rs, rc = ref.mlp_forward(net.params.get(), spec, net.layout, x, d)
    np.testing.assert_allclose(s, rs, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
    np.testing.assert_allclose(c, rc, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)


def test_invalid_shapes_fail_to_build(device):
    from clrf.runtime.programs import BuildError
    with pytest.raises(BuildError, match="MLP_WIDTH"):
        MLP(device, MLPSpec(width=40))
    with pytest.raises(BuildError, match="MLP_SKIP"):
        MLP(device, MLPSpec(depth=2, skip=1))


# ---- register tiles ---------------------------------------------------------------------------
@pytest.fixture(scope="session")
def cpu_tiles(device):
    """The device with the fused MLP's CPU register tiles, also where it would run the GPU
    tiling (a GPU, CLRF_FORCE_GPU_KERNELS=1): the tests below are about those tiles."""
    return device.with_tuning(gpu_kernels=False)


# (rows, cols, dw_rows, dw_cols): the AVX-512 defaults (wide and narrow MLPs) and the former
# one, the AVX2 default, one-row tiles, every other row count, and weight-gradient tiles of
# each allowed height and both widths.
TILES = [(12, 16, 8, 32), (8, 16, 8, 16), (8, 32, 8, 32), (6, 16, 8, 16), (6, 16, 4, 32),
         (1, 16, 1, 16), (1, 32, 16, 32), (2, 32, 2, 16),
         (3, 32, 4, 16), (4, 16, 16, 16), (5, 16, 8, 16), (8, 16, 1, 32), (12, 16, 2, 32),
         (16, 32, 8, 16)]
# width 48 = one 32-wide block + a 16-wide rest; the skip input is 48 + 16 = 64 columns
TILE_SPEC = MLPSpec(width=48, depth=3, skip=0, color_width=16, in_dim=9, dir_dim=5,
                    hidden_act="relu", sigma_act="softplus")


@pytest.mark.parametrize("tile", TILES, ids=lambda t: "r%d_c%d_dw%dx%d" % t)
def test_every_tile_matches_reference(cpu_tiles, tile):
    """Forward, input and parameter gradients of each tile against the float64 reference, for
    batches of 0, 1, 7, a tile -1, +0, +1 and several partial-gradient chunks (2 tiles)."""
    r, c, dwr, dwc = tile
    spec = replace(TILE_SPEC, rows=r, cols=c, dw_rows=dwr, dw_cols=dwc, dw_chunk=2 * r)
    net = MLP(cpu_tiles, spec, seed=3)
    assert (net.layout.rows, net.layout.cols, net.layout.dw_rows, net.layout.dw_cols,
            net.layout.dw_chunk) == (r, c, dwr, dwc, 2 * r)
    p = net.params.get()
    rng = np.random.default_rng(5)
    for L, (rr, _) in zip(net.layout.layers, net.layout.logical_shapes(spec)):
        p[L["b_off"] + rr] = rng.uniform(-0.3, 0.3, len(rr))
    net.set_params(p)
    for n in sorted({0, 1, 7, max(r - 1, 1), r, r + 1, 5 * r + 3}):
        x, d = inputs(spec, n, seed=n)
        s, col = run_forward(net, x, d)
        rs, rc = ref.mlp_forward(p, spec, net.layout, x, d)
        np.testing.assert_allclose(s, rs, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
        np.testing.assert_allclose(col, rc, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
        ds = rng.normal(size=n).astype(np.float32)
        dr = rng.normal(size=(n, 3)).astype(np.float32)
        g, dx, dd = run_backward(net, x, d, ds, dr)
        if n == 0:
            assert np.all(g == 0) and dx.shape == (0, spec.in_dim)
            continue
        want = ref.mlp_backward(p, spec, net.layout, x, d, ds, dr)
        for L in net.layout.layers:
            _close_rel_to_max(g[L["w_off"]:L["b_off"]], want["params"][L["w_off"]:L["b_off"]])
            _close_rel_to_max(g[L["b_off"]:L["b_off"] + L["nout"]],
                              want["params"][L["b_off"]:L["b_off"] + L["nout"]])
        _close_rel_to_max(dx, want["x_enc"])
        _close_rel_to_max(dd, want["d_enc"])


def test_chunk_rounds_up_to_whole_tiles(cpu_tiles):
    """dw_chunk = 16 with 6-row tiles builds with 18-row chunks (whole tiles)."""
    net = MLP(cpu_tiles, replace(TILE_SPEC, rows=6, cols=16, dw_rows=4, dw_cols=32, dw_chunk=16))
    assert net.layout.dw_chunk == 18 and net.tiling.dw_chunk == 16


@pytest.mark.parametrize("field,value,define", [("rows", 7, "MLP_ROWS"), ("cols", 24, "MLP_COLS"),
                                                ("dw_rows", 6, "DW_ROWS"),
                                                ("dw_cols", 8, "DW_COLS")])
def test_invalid_tiles_fail_to_build(cpu_tiles, field, value, define):
    from clrf.runtime.programs import BuildError
    with pytest.raises(BuildError, match=define):
        MLP(cpu_tiles, replace(TILE_SPEC, **{field: value}))
