"""The fused MLP's GPU tiling (cl/mlp_gpu.h, MLP_GPU=1) forced on every device, against the
float64 reference (clrf/references/reference_nerf.py) with the tolerances of the CPU tiles: NeRF's
8 x 256 (small batches), 4 x 64, the hash model's networks; awkward batch sizes around the
block of samples a work-group owns; the NVIDIA-sized tiling (48 KiB of local memory) and an
awkward one (K-slices of 3 rows, 2 x 2 register tiles, small weight-gradient tiles).
tests/test_oclgrind.py runs test_small_network_under_every_pass under Oclgrind's checks."""
from dataclasses import replace

import numpy as np
import pyopencl.array as cla
import pytest

from clrf.mlp.mlp import MLP, MLPSpec
from clrf.mlp.tiling import GPUTiling, gpu_default, mlp_tiling_for
from clrf.references import reference_nerf as ref
from clrf.testing import tolerances as tol

SHAPES = {
    "nerf-8x256": MLPSpec(width=256, depth=8, skip=4, color_width=128, in_dim=63, dir_dim=27),
    "small-4x64": MLPSpec(width=64, depth=4, skip=1, color_width=32, in_dim=51, dir_dim=27),
    # the hash model's networks (clrf/hash/model.py): 16 levels x 2 features in, SH degree 4
    "hash-1x64-c2": MLPSpec(width=64, depth=1, skip=-1, color_width=64, in_dim=32, dir_dim=16,
                            sigma_act="trunc_exp", color_depth=2, features=16),
    "softplus-c3": MLPSpec(width=32, depth=2, skip=0, color_width=16, in_dim=9, dir_dim=5,
                           hidden_act="softplus", sigma_act="softplus", color_depth=3,
                           features=16),
}
NVIDIA_LOCAL = 49152   # CL_DEVICE_LOCAL_MEM_SIZE of NVIDIA's driver (H100)
TILINGS = {
    "nvidia": lambda caps: replace(gpu_default(caps), wg=256, local_max=NVIDIA_LOCAL),
    # partial K-slices (3 rows), 2 x 2 tiles, a 16 x 8 weight-gradient tile over 5-row steps,
    # and several partial gradients (chunks of 40 rows)
    "awkward": lambda caps: GPUTiling(wg=64, local_max=NVIDIA_LOCAL, tm=2, tn=2, bk=3, dw_bj=16,
                                      dw_bs=5, chunk=40),
}
_nets = {}


@pytest.fixture(scope="session")
def gpu_tiling(device):
    """The session's device with the GPU tiling forced (as CLRF_FORCE_GPU_KERNELS=1)."""
    return device.with_tuning(gpu_kernels=True)


def get_net(dev, shape, tiling):
    key = (dev.cl_device.int_ptr, shape, tiling)
    if key not in _nets:
        spec = SHAPES[shape]
        t = replace(mlp_tiling_for(dev, spec), gpu=TILINGS[tiling](dev.caps))
        net = MLP(dev, spec, seed=1, tiling=t)
        p = net.params.get()
        rng = np.random.default_rng(2)   # non-zero biases: every ReLU sees both signs
        for L, (rows, _) in zip(net.layout.layers, net.layout.logical_shapes(spec)):
            p[L["b_off"] + rows] = rng.uniform(-0.3, 0.3, len(rows))
        net.set_params(p)
        _nets[key] = net
    return _nets[key]


def inputs(spec, n, seed):
    rng = np.random.default_rng(seed)
    return (rng.normal(size=(n, spec.in_dim)).astype(np.float32),
            rng.normal(size=(n, spec.dir_dim)).astype(np.float32),
            rng.normal(size=n).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32))


def batch_sizes(block, large):
    """0, 1, a block -1, +0, +1, and `large` (not a multiple of the block)."""
    return sorted({0, 1, max(block - 1, 1), block, block + 1, large})


def _close_rel_to_max(a, b):
    scale = max(np.abs(b).max(initial=0.0), 1e-30)
    np.testing.assert_allclose(a, b, rtol=0, atol=tol.MLP_GRAD_REL_TO_MAX * scale)


def check_net(net, n, seed, want_input=True):
    """Forward, density, backward (parameter and, with want_input, input gradients) of n
    samples against the float64 reference."""
    spec, q = net.spec, net.device.queue
    x, d, ds, dr = inputs(spec, n, seed)
    p = net.params.get()
    xd = cla.to_device(q, x)
    sd = net.density(xd).get()
    s, c = net.forward(xd, cla.to_device(q, d))
    s, c = s.get(), c.get()
    rs, rc = ref.mlp_forward(p, spec, net.layout, x, d)
    assert s.shape == (n,) and c.shape == (n, 3) and sd.shape == (n,)
    np.testing.assert_allclose(s, rs, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
    np.testing.assert_allclose(c, rc, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
    np.testing.assert_allclose(sd, rs, rtol=tol.MLP_RTOL, atol=tol.MLP_ATOL)
    out = net.backward(cla.to_device(q, ds), cla.to_device(q, dr), want_input=want_input)
    g = net.grad.get()
    if n == 0:
        assert np.all(g == 0)
        return
    r = ref.mlp_backward(p, spec, net.layout, x, d, ds, dr)
    for L in net.layout.layers:   # each layer's weights and biases relative to their own scale
        _close_rel_to_max(g[L["w_off"]:L["b_off"]], r["params"][L["w_off"]:L["b_off"]])
        _close_rel_to_max(g[L["b_off"]:L["b_off"] + L["nout"]],
                          r["params"][L["b_off"]:L["b_off"] + L["nout"]])
    if want_input:
        dx, dd = (a.get() for a in out)
        _close_rel_to_max(dx, r["x_enc"])
        _close_rel_to_max(dd, r["d_enc"])
    else:
        assert out is None


@pytest.mark.parametrize("tiling", list(TILINGS))
@pytest.mark.parametrize("shape", ["small-4x64", "hash-1x64-c2", "softplus-c3"])
def test_matches_reference_at_awkward_batches(gpu_tiling, shape, tiling):
    net = get_net(gpu_tiling, shape, tiling)
    assert net.gpu and net.layout.gpu is not None and net.layout.gpu["wg"] == net.tiling.gpu.wg
    block = net.layout.rows
    for n in batch_sizes(block, 2345):
        check_net(net, n, seed=n, want_input=n % 2 == 1)


@pytest.mark.parametrize("tiling", list(TILINGS))
def test_nerf_8x256_small_batches(gpu_tiling, tiling):
    """NeRF's 8 x 256 with its skip: on NVIDIA's 48 KiB, blocks of 32 samples of 8 x 4 tiles
    in K-slices of 4 rows (the skip layer's 320 input columns fill the local memory)."""
    net = get_net(gpu_tiling, "nerf-8x256", tiling)
    if tiling == "nvidia":
        g = net.layout.gpu
        assert (net.layout.rows, g["tm"], g["tn"], g["nc"], g["bk"]) == (32, 8, 4, 256, 4)
        assert g["local_bytes"] <= NVIDIA_LOCAL
    block = net.layout.rows
    for n in batch_sizes(block, 3 * block + 5):
        check_net(net, n, seed=100 + n)


@pytest.mark.parametrize("shape", ["small-4x64", "hash-1x64-c2"])
def test_device_default_tiling(gpu_tiling, shape):
    """The tiling a forced device gets on its own (its local memory, its work-group size)."""
    spec = replace(SHAPES[shape], dw_chunk=64)   # several partial gradients at 300 samples
    net = MLP(gpu_tiling, spec, seed=4)
    assert net.tiling.gpu == gpu_default(gpu_tiling.caps, 64)
    assert net.layout.gpu["local_bytes"] <= gpu_tiling.caps.local_mem_size
    check_net(net, 300, seed=4)


def test_accumulate_and_chunks_per_batch(gpu_tiling):
    """accumulate=True adds to grad; the automatic chunk count (no dw_chunk) gives the same
    gradient as chunks of 40 rows."""
    auto = MLP(gpu_tiling, SHAPES["hash-1x64-c2"], seed=1,
               params=get_net(gpu_tiling, "hash-1x64-c2", "awkward").params.get(),
               tiling=replace(mlp_tiling_for(gpu_tiling, SHAPES["hash-1x64-c2"]),
                              gpu=replace(TILINGS["awkward"](gpu_tiling.caps), chunk=None)))
    n = 3000
    chunk, n_chunks = auto._gpu_chunks(auto.n_rows(n))
    assert n_chunks >= 1 and chunk % auto.layout.gpu["dw_bs"] == 0
    assert chunk * n_chunks >= auto.n_rows(n) > chunk * (n_chunks - 1)
    x, d, ds, dr = inputs(auto.spec, n, seed=6)
    q = auto.device.queue
    grads = []
    for net in (auto, get_net(gpu_tiling, "hash-1x64-c2", "awkward")):
        net.forward(cla.to_device(q, x), cla.to_device(q, d))
        net.backward(cla.to_device(q, ds), cla.to_device(q, dr))
        net.backward(cla.to_device(q, ds), cla.to_device(q, dr), accumulate=True)
        grads.append(net.grad.get())
    r = ref.mlp_backward(auto.params.get(), auto.spec, auto.layout, x, d, ds, dr)["params"]
    _close_rel_to_max(grads[0], 2 * r)
    _close_rel_to_max(grads[1], 2 * r)


@pytest.mark.parametrize("shape", ["small-4x64", "hash-1x64-c2"])
def test_padding_gradients_are_exactly_zero(gpu_tiling, shape):
    net = get_net(gpu_tiling, shape, "nvidia")
    n = 70
    x, d, ds, dr = inputs(net.spec, n, seed=7)
    q = net.device.queue
    net.forward(cla.to_device(q, x), cla.to_device(q, d))
    net.backward(cla.to_device(q, ds), cla.to_device(q, dr))
    g = net.grad.get()
    mask = np.zeros(net.layout.n_params, bool)
    for L, (r, c) in zip(net.layout.layers, net.layout.logical_shapes(net.spec)):
        m = np.zeros((L["nout"], L["nin"]), bool)
        m[np.ix_(r, c)] = True
        mask[L["w_off"]:L["b_off"]] = m.ravel()
        mask[L["b_off"] + r] = True
    assert np.all(g[~mask] == 0.0)
    assert np.count_nonzero(g[mask]) > 0.5 * mask.sum()


def test_small_network_under_every_pass(gpu_tiling):
    """A small network with small work-groups (the Oclgrind case, tests/test_oclgrind.py):
    forward, density, backward with and without input gradients, partial gradients of 16-row
    chunks, batches 0, 1, a block + 1 and two blocks + 3."""
    spec = SHAPES["softplus-c3"]
    t = replace(mlp_tiling_for(gpu_tiling, spec),
                gpu=GPUTiling(wg=16, local_max=8192, tm=2, tn=2, bk=3, dw_bj=8, dw_bs=3,
                              chunk=16))
    net = MLP(gpu_tiling, spec, seed=2, tiling=t)
    block = net.layout.rows
    for i, n in enumerate((0, 1, block + 1, 2 * block + 3)):
        check_net(net, n, seed=n, want_input=i % 2 == 0)
        check_net(net, n, seed=n, want_input=i % 2 == 1)


def test_selection_by_device_class_and_environment(device):
    """GPU devices default to the GPU tiling, others to the CPU tiles; CLRF_FORCE_GPU_KERNELS
    sets it either way (clrf/runtime/tuning.py)."""
    from clrf.runtime.tuning import Tuning
    caps = device.caps
    assert Tuning.for_device(replace(caps, type="gpu")).gpu_kernels
    assert not Tuning.for_device(replace(caps, type="cpu")).gpu_kernels
    assert Tuning.from_env(replace(caps, type="cpu"), {"CLRF_FORCE_GPU_KERNELS": "1"}).gpu_kernels
    assert not Tuning.from_env(replace(caps, type="gpu"), {"CLRF_FORCE_GPU_KERNELS": "0"}).gpu_kernels
    spec = SHAPES["hash-1x64-c2"]
    assert mlp_tiling_for(device.with_tuning(gpu_kernels=True), spec).gpu is not None
    assert mlp_tiling_for(device.with_tuning(gpu_kernels=False), spec).gpu is None


@pytest.mark.parametrize("gpu,define", [(GPUTiling(tm=3), "GPU_TM"), (GPUTiling(tn=3), "GPU_TN"),
                                        (GPUTiling(wg=96), "GPU_WG"),
                                        (GPUTiling(local_max=4096, tm=8), "GPU_TM, GPU_BK"),
                                        (GPUTiling(dw_bj=6), "GPU_DW_BJ")])
def test_invalid_gpu_tiles_fail_to_build(gpu_tiling, gpu, define):
    from clrf.runtime.programs import BuildError
    spec = SHAPES["small-4x64"]
    with pytest.raises(BuildError, match=define):
        MLP(gpu_tiling, spec, tiling=replace(mlp_tiling_for(gpu_tiling, spec), gpu=gpu))
