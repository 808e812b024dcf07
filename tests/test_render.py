"""Grid renderer: kernels against the float64 reference, finite differences and closed forms."""
import numpy as np
import pyopencl.array as cla
import pytest

import clrf
from clrf.grid import render as grid_render
from clrf.references import reference as ref
from clrf.runtime.tuning import Tuning

from clrf.testing.tolerances import (CLOSED_FORM_ATOL, DEPTH_ATOL, DEPTH_RTOL, FD_ATOL, FD_RTOL,
                                     GRAD_ATOL, GRAD_RTOL, RENDER_ATOL, RENDER_RTOL)

BBOX = np.array([[-1.0, -1.2, -0.9], [1.1, 1.0, 1.0]])
LOCAL_SIZE = Tuning().grid_local_size   # ray counts around one work-group


def random_grid(rng, shape, degree, empty_frac=0.0, dens_hi=3.0):
    C = 3 * (degree + 1) ** 2
    dens = rng.uniform(0.05, dens_hi, shape).astype(np.float32)
    sh = rng.normal(0, 0.3, shape + (C,)).astype(np.float32)
    if empty_frac:
        empty = rng.random(shape) < empty_frac
        dens[empty] = 0
        sh[empty] = 0
    return dens, sh


def random_rays(rng, n, bbox=BBOX, spread=2.5):
    """Rays from points around the box aimed at points inside it (most hit, some miss)."""
    c = bbox.mean(0)
    o = c + rng.normal(0, spread, (n, 3))
    target = c + rng.uniform(-0.7, 0.7, (n, 3)) * (bbox[1] - bbox[0])
    return o.astype(np.float32), (target - o).astype(np.float32)


def assert_forward_matches(out, r):
    np.testing.assert_allclose(out["rgb"], r["rgb"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
    np.testing.assert_allclose(out["acc"], r["acc"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
    np.testing.assert_allclose(out["depth"], r["depth"], atol=DEPTH_ATOL, rtol=DEPTH_RTOL)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("shape", [(1, 1, 1), (2, 2, 2), (3, 50, 7), (6, 5, 4)])
def test_forward_vs_reference(device, degree, shape):
    rng = np.random.default_rng(hash((degree, shape)) % 2**32)
    dens, sh = random_grid(rng, shape, degree, empty_frac=0.25 if np.prod(shape) > 8 else 0.0)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 200)
    bg = (0.2, 0.5, 0.9)
    out = clrf.render_rays(grid, o, d, step=0.37, background=bg)
    r = ref.render_forward(dens, sh, BBOX, o, d, 0.37, bg)
    assert_forward_matches(out, r)
    assert np.any(out["acc"] > 0.1), "test rays should see the grid"


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_forward_gpu_shape_vs_reference(device_gpu_path, degree):
    """The GPU shape's forward (colours per corner, SH_PER_CORNER) against the reference, on a
    grid with empty voxels (corners without a row)."""
    rng = np.random.default_rng(40 + degree)
    dens, sh = random_grid(rng, (6, 5, 4), degree, empty_frac=0.25)
    grid = clrf.SparseGrid.from_dense(device_gpu_path, dens, sh, BBOX)
    o, d = random_rays(rng, 200)
    bg = (0.2, 0.5, 0.9)
    out = clrf.render_rays(grid, o, d, step=0.37, background=bg)
    assert_forward_matches(out, ref.render_forward(dens, sh, BBOX, o, d, 0.37, bg))
    assert np.any(out["acc"] > 0.1), "test rays should see the grid"


@pytest.mark.parametrize("n", [0, 1, 7, LOCAL_SIZE - 1, LOCAL_SIZE, LOCAL_SIZE + 1, 10000])
def test_forward_ray_counts(device, n):
    rng = np.random.default_rng(n)
    dens, sh = random_grid(rng, (4, 5, 6), 2, empty_frac=0.2)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, n)
    out = clrf.render_rays(grid, o, d, step=0.5)
    assert out["rgb"].shape == (n, 3) and out["acc"].shape == (n,) and out["depth"].shape == (n,)
    r = ref.render_forward(dens, sh, BBOX, o, d, 0.5)
    assert_forward_matches(out, r)


def test_forward_128_cubed(device):
    rng = np.random.default_rng(128)
    R = 128
    dens = rng.uniform(0, 0.6, (R, R, R)).astype(np.float32)
    dens[rng.random((R, R, R)) < 0.5] = 0  # half empty: exercises the cell skip at scale
    sh = rng.normal(0, 0.3, (R, R, R, 3)).astype(np.float32)
    bbox = np.array([[-1.0] * 3, [1.0] * 3])
    grid = clrf.SparseGrid.from_dense(device, dens, sh, bbox, mask=dens > 0)
    sh[dens == 0] = 0
    o, d = random_rays(rng, 48, bbox)
    out = clrf.render_rays(grid, o, d, step=0.5)
    r = ref.render_forward(dens, sh, bbox, o, d, 0.5)
    assert_forward_matches(out, r)


@pytest.mark.parametrize("degree", [0, 2, 3])
def test_backward_vs_finite_differences(render_device, degree):
    """Tiny grid: kernel gradient == reference analytic gradient == central differences, on
    both backward code paths (render_device)."""
    assert_tiny_backward_matches(render_device, degree, 10 + degree)


def assert_tiny_backward_matches(device, degree, seed):
    """A 2 x 3 x 2 grid, 24 rays: the kernel's gradients equal the reference's, and the
    reference's equal central differences at 6 entries of each."""
    rng = np.random.default_rng(seed)
    shape = (2, 3, 2)
    dens, sh = random_grid(rng, shape, degree, dens_hi=2.0)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 24, spread=2.0)
    g = rng.normal(size=(24, 3)).astype(np.float32)
    bg = (0.3, 0.6, 0.1)
    kern = clrf.render_rays_backward(grid, o, d, g, step=0.3, background=bg)
    ana = ref.render_backward(dens, sh, BBOX, o, d, g, 0.3, bg)
    np.testing.assert_allclose(kern["density"], ana["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(kern["sh"], ana["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    for which, arr in (("density", dens), ("sh", sh)):
        for flat in rng.choice(arr.size, 6, replace=False):
            idx = np.unravel_index(flat, arr.shape)
            fd = ref.finite_difference(dens, sh, BBOX, o, d, g, which, idx, step=0.3,
                                       background=bg)
            assert abs(fd - ana[which][idx]) <= FD_ATOL + FD_RTOL * abs(fd), (which, idx, fd)
    assert np.abs(ana["density"]).max() > 1e-3  # the rays do touch the grid


def assert_medium_backward_matches(device, degree, seed):
    """A 9 x 8 x 10 grid with empty voxels, 300 rays: the kernel's gradients equal the
    reference's; returns (kernel gradients, density)."""
    rng = np.random.default_rng(seed)
    dens, sh = random_grid(rng, (9, 8, 10), degree, empty_frac=0.3, dens_hi=1.5)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 300)
    g = rng.normal(size=(300, 3)).astype(np.float32)
    kern = clrf.render_rays_backward(grid, o, d, g, step=0.5, background=(1, 1, 1))
    ana = ref.render_backward(dens, sh, BBOX, o, d, g, 0.5, (1, 1, 1))
    np.testing.assert_allclose(kern["density"], ana["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(kern["sh"], ana["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    return kern, dens


@pytest.mark.parametrize("degree", [1, 2])
def test_backward_vs_reference_medium(render_device, degree):
    kern, dens = assert_medium_backward_matches(render_device, degree, 20 + degree)
    assert np.all(kern["density"][dens == 0] == 0), "empty voxels get no gradient"


@pytest.mark.parametrize("degree", [0, 2])
def test_backward_gpu_shape_on_the_cpu_path(device, degree):
    """CLRF_FORCE_GPU_KERNELS=1 on a CPU device: the GPU shape's per-corner colour gradients
    (SH_PER_CORNER) with the device's own gradient slots, block locks and sample record."""
    dev = device.with_tuning(gpu_kernels=True)
    if dev.tuning.grad_slots == 0:
        pytest.skip(f"{device}: no gradient slots (the atomic path is render_device's gpu_path)")
    assert_medium_backward_matches(dev, degree, 30 + degree)


@pytest.mark.parametrize("gpu_kernels", [True, False], ids=["gpu_shape", "cpu_shape"])
@pytest.mark.parametrize("degree", [0, 2])
def test_backward_per_sample_atomics(device, degree, gpu_kernels):
    """grad_merge off (GRAD_MERGE 0, Intel GPUs' default): every sample adds its corner
    gradients with atomics as it is met, instead of a cell's sums when the march leaves it.
    The same gradients, in both shapes, against the reference and finite differences; the
    program is built with the define."""
    dev = device.with_tuning(grad_slots=0, sample_record=False, grad_locks=0,
                             gpu_kernels=gpu_kernels, grad_merge=False)
    dev._programs = {}   # this copy's own program cache (with_tuning shares the device's)
    assert_tiny_backward_matches(dev, degree, 50 + degree)
    kern, dens = assert_medium_backward_matches(dev, degree, 60 + degree)
    assert np.all(kern["density"][dens == 0] == 0), "empty voxels get no gradient"
    built = [dict(d) for (src, d, _) in dev._programs if src == "grid_render.cl"]
    assert built and all(d.get("GRAD_MERGE") == 0 for d in built), built


def homogeneous(device, sigma, shape=(4, 4, 4), rgb=(0.2, 0.4, 0.6)):
    """Grid of constant density sigma (world units) and constant diffuse colour rgb."""
    dens = np.full(shape, sigma, np.float32)
    sh = np.zeros(shape + (3,), np.float32)
    sh[..., :] = (np.asarray(rgb) - 0.5) / ref.SH_C0
    bbox = np.array([[0.0] * 3, [1.0] * 3])
    return clrf.SparseGrid.from_dense(device, dens, sh, bbox), bbox


@pytest.mark.parametrize("sigma", [1e-6, 1e-3, 1.0, 10.0, 1e3, 1e6])
def test_homogeneous_slab_closed_form(device, sigma):
    grid, bbox = homogeneous(device, sigma)
    rng = np.random.default_rng(1)
    o = np.array([[0.5, 0.5, -2.0], [0.3, 0.6, -1.0], [-1, -1, -1]], np.float32)
    d = np.array([[0, 0, 1.0], [0.1, -0.05, 1.0], [1, 1, 1]], np.float32)
    o = np.concatenate([o, rng.uniform(0.1, 0.9, (5, 3)).astype(np.float32)])  # inside
    d = np.concatenate([d, rng.normal(size=(5, 3)).astype(np.float32)])
    ref_m = ref.march_setup(o, d, grid.reso, bbox, 0.5)
    L = ref_m["len"]
    acc_exact = -np.expm1(-sigma * L)
    out1 = clrf.render_rays(grid, o, d, step=0.5, background=(1, 1, 1))
    out0 = clrf.render_rays(grid, o, d, step=0.5, background=(0, 0, 0))
    np.testing.assert_allclose(out1["acc"], acc_exact, atol=CLOSED_FORM_ATOL, rtol=RENDER_RTOL)
    diff = out1["rgb"] - out0["rgb"]
    np.testing.assert_allclose(diff, np.repeat(1 - out1["acc"][:, None], 3, 1), atol=RENDER_ATOL)
    # colour: constant rgb weighted by acc
    np.testing.assert_allclose(out0["rgb"], out0["acc"][:, None] * [0.2, 0.4, 0.6],
                               atol=RENDER_ATOL, rtol=RENDER_RTOL)


def test_geometry_cases(device):
    rng = np.random.default_rng(3)
    shape = (4, 4, 4)
    dens, sh = random_grid(rng, shape, 1)
    bbox = np.array([[0.0] * 3, [1.0] * 3])
    grid = clrf.SparseGrid.from_dense(device, dens, sh, bbox)
    vox = 0.25
    cases = {
        "miss": ([2.0, 2.0, -1.0], [0, 0, 1.0]),
        "pointing away": ([0.5, 0.5, -1.0], [0, 0, -1.0]),
        "inside start": ([0.4, 0.45, 0.5], [0.3, -0.2, 1.0]),
        "along x axis": ([-1.0, 0.5 + 0.1 * vox, 0.5], [1.0, 0, 0]),
        "along voxel face": ([0.5, 2 * vox, -1.0], [0, 0, 1.0]),
        "through voxel edge": ([vox, 2 * vox, -1.0], [0, 0, 1.0]),
        "on box face": ([0.0, 0.5, -1.0], [0, 0, 1.0]),
        "tiny component": ([0.5, 0.5, -1.0], [1e-30, -1e-30, 1.0]),
        "unnormalised": ([0.2, 0.7, -1.0], [0.3e-3, -0.1e-3, 1e-3]),
        "diagonal corner": ([-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]),
    }
    o = np.array([v[0] for v in cases.values()], np.float32)
    d = np.array([v[1] for v in cases.values()], np.float32)
    out = clrf.render_rays(grid, o, d, step=0.5, background=(1, 1, 1))
    r = ref.render_forward(dens, sh, bbox, o, d, 0.5)
    assert_forward_matches(out, r)
    names = list(cases)
    for k in ("miss", "pointing away"):
        i = names.index(k)
        assert out["acc"][i] == 0 and np.all(out["rgb"][i] == 1) and out["depth"][i] == 0
    for k in names:
        if k not in ("miss", "pointing away"):
            assert out["acc"][names.index(k)] > 0.05, k
    # unnormalised == normalised
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    out_n = clrf.render_rays(grid, o, dn.astype(np.float32), step=0.5)
    np.testing.assert_allclose(out["rgb"], out_n["rgb"], atol=RENDER_ATOL)
    np.testing.assert_allclose(out["depth"], out_n["depth"], atol=DEPTH_ATOL)


def test_empty_grid(device):
    shape = (3, 3, 3)
    dens = np.zeros(shape, np.float32)
    sh = np.zeros(shape + (12,), np.float32)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, [[0, 0, 0], [1, 1, 1]])
    assert grid.n_rows == 0
    rng = np.random.default_rng(0)
    o = rng.uniform(-1, 2, (50, 3)).astype(np.float32)
    d = (0.5 - o).astype(np.float32)
    out = clrf.render_rays(grid, o, d, background=(0.1, 0.2, 0.3))
    assert np.all(out["acc"] == 0) and np.all(out["depth"] == 0)
    np.testing.assert_array_equal(out["rgb"], np.tile([0.1, 0.2, 0.3], (50, 1)).astype(np.float32))
    g = clrf.render_rays_backward(grid, o, d, np.ones((50, 3), np.float32))
    assert np.all(g["density"] == 0) and np.all(g["sh"] == 0)


def test_dense_roundtrip_and_validation(device):
    rng = np.random.default_rng(5)
    dens, sh = random_grid(rng, (3, 4, 5), 2, empty_frac=0.5)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    d2, s2 = grid.to_dense()
    np.testing.assert_array_equal(d2, dens)
    np.testing.assert_array_equal(s2, sh)
    with pytest.raises(ValueError, match="coefficients"):
        clrf.SparseGrid.from_dense(device, dens, sh[..., :5], BBOX)
    with pytest.raises(ValueError, match="bbox"):
        clrf.SparseGrid.from_dense(device, dens, sh, [[0, 0, 0], [1, -1, 1]])
    bad = dens.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="density.*NaN"):
        clrf.SparseGrid.from_dense(device, bad, sh, BBOX)
    o, d = random_rays(rng, 4)
    d[1, 0] = np.inf
    with pytest.raises(ValueError, match="dirs.*NaN or Inf"):
        clrf.render_rays(grid, o, d)
    d[1] = 0.0                                      # a zero direction has no ray to march
    with pytest.raises(ValueError, match="dirs: 1 of 4 direction vectors are zero"):
        clrf.render_rays(grid, o, d)
    with pytest.raises(ValueError, match="dirs.*zero"):
        clrf.render_rays_backward(grid, o, d, np.ones_like(o))
    with pytest.raises(ValueError, match="step"):
        clrf.render_rays(grid, o, np.ones_like(o), step=0)


def test_max_weight_vs_reference(device):
    import pyopencl.array as cla
    from clrf.grid.render import render_max_weight_device
    rng = np.random.default_rng(7)
    dens, sh = random_grid(rng, (5, 6, 7), 0, empty_frac=0.3)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX)
    o, d = random_rays(rng, 100)
    q = device.queue
    mw = cla.zeros(q, grid.density.shape[0], np.float32)
    render_max_weight_device(grid, cla.to_device(q, o), cla.to_device(q, d), 0.5, mw)
    dense_k, _ = grid.rows_to_dense(mw.get(), np.zeros((mw.shape[0], 3), np.float32))
    r = ref.max_weight(dens, BBOX, o, d, 0.5)
    r[~((dens != 0) | np.any(sh != 0, -1))] = 0  # unallocated voxels have no row
    np.testing.assert_allclose(dense_k, r, atol=RENDER_ATOL, rtol=RENDER_RTOL)
    assert r.max() > 0.05


@pytest.mark.parametrize("block, block_fine", [(0, 0), (4, 0), (8, 2), (8, 3), (16, 4)])
def test_empty_space_skipping_settings(device, block, block_fine):
    """Every empty-space skipping setting (no blocks; one level; two levels, including a fine
    size that does not divide the coarse one) evaluates the same samples: the forward outputs
    are bitwise those of the default build and match the float64 reference, and the backward
    (record walk) matches the reference. The grid is a hollow shell with scattered holes, so
    rays cross empty blocks, empty fine blocks and empty cells on both sides of it."""
    rng = np.random.default_rng(21)
    shape = (30, 26, 28)
    dens, sh = random_grid(rng, shape, 1, dens_hi=1.5)
    c = [(np.arange(n) + 0.5) / n * 2 - 1 for n in shape]
    r = np.sqrt(c[0][:, None, None] ** 2 + c[1][None, :, None] ** 2 + c[2][None, None, :] ** 2)
    mask = (np.abs(r - 0.6) < 0.12) & (rng.random(shape) > 0.1)
    dens, sh = dens * mask, sh * mask[..., None]
    o, d = random_rays(rng, 500)
    o[:40], d[:40] = [0.0, 0.0, -3.0], [0.0, 0.0, 1.0]   # along an axis, through the hollow
    tuned = device.with_tuning(block=block, block_fine=block_fine)
    got = clrf.render_rays(clrf.SparseGrid.from_dense(tuned, dens, sh, BBOX, mask=mask), o, d)
    base = clrf.render_rays(clrf.SparseGrid.from_dense(device, dens, sh, BBOX, mask=mask), o, d)
    for k in ("rgb", "depth", "acc"):
        np.testing.assert_array_equal(got[k], base[k])
    assert_forward_matches(got, ref.render_forward(dens, sh, BBOX, o, d, 0.5))
    g = rng.normal(size=(o.shape[0], 3)).astype(np.float32)
    grid = clrf.SparseGrid.from_dense(tuned, dens, sh, BBOX, mask=mask)
    bwd = clrf.render_rays_backward(grid, o, d, g)
    want = ref.render_backward(dens, sh, BBOX, o, d, g.astype(np.float64), 0.5, mask=mask)
    np.testing.assert_allclose(bwd["density"], want["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(bwd["sh"], want["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)


@pytest.mark.parametrize("per_ray_bg", [False, True])
def test_ray_order(render_device, per_ray_bg):
    """Rays rendered sorted by their entry cell (RAY_ORDER): the order is a permutation that
    sorts the kernel's keys with the rays that miss last; every per-ray output (colour, depth,
    opacity, squared error, background gradient) is bitwise that of the given order, and the
    grid gradients match the float64 reference, on both backward code paths."""
    rng = np.random.default_rng(31)
    shape = (12, 9, 14)
    dens, sh = random_grid(rng, shape, 2, empty_frac=0.3, dens_hi=1.5)
    n = 600
    o, d = random_rays(rng, n)
    o[:30], d[:30] = [0.05, 0.0, -3.0], [0.0, 0.0, 1.0]   # axis-parallel
    o[30:40], d[30:40] = [5.0, 5.0, 5.0], [1.0, 1.0, 1.0]   # miss the box
    target = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    bg_np = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    out = {}
    for name, k in (("given", 0), ("sorted", 1)):
        dev = render_device.with_tuning(ray_order=k)
        grid = clrf.SparseGrid.from_dense(dev, dens, sh, BBOX)
        q = dev.queue
        od, dd, td = (cla.to_device(q, a) for a in (o, d, target))
        bg = cla.to_device(q, bg_np) if per_ray_bg else (0.3, 0.6, 0.1)
        order = grid_render.ray_order(grid, od, dd, 0.5)
        if k:
            perm = order.get()
            assert sorted(perm.tolist()) == list(range(n))
            keys = cla.empty(q, n, np.uint32)
            grid_render.launch(dev, grid_render.grid_program(grid).kernel("ray_order_keys"), n,
                               (np.int32(n), od.data, dd.data, *grid.geometry_args(),
                                np.float32(0.5), np.int32(0), keys.data))
            kk = keys.get()
            assert np.all(np.diff(kk[perm].astype(np.int64)) >= 0)
            assert np.all(kk[30:40] == 0xFFFFFFFF)   # the largest key: misses go last
            assert np.all(kk[:30] < 0xFFFFFFFF) and len(np.unique(kk)) > 50
        else:
            assert order is None
        fwd = {key: v.get()
               for key, v in grid_render.render_forward_device(grid, od, dd, 0.5, bg).items()}
        gd = cla.zeros(q, grid.density.shape[0], np.float32)
        gs = cla.zeros(q, grid.sh.shape, np.float32)
        ro = cla.empty(q, n, np.float32)
        gbg = grid_render.render_backward_device(grid, od, dd, td, 0.5, bg, gd, gs,
                                                 grad_mode=1, loss_scale=1.0, ray_out=ro)
        bg_host = bg_np if per_ray_bg else bg
        out[name] = dict(fwd, loss=ro.get(), gbg=None if gbg is None else gbg.get(),
                         bwd=clrf.render_rays_backward(grid, o, d, 2 * (fwd["rgb"] - target),
                                                       step=0.5, background=bg_host))
    a, b = out["given"], out["sorted"]
    for key in ("rgb", "depth", "acc", "loss") + (("gbg",) if per_ray_bg else ()):
        np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    bg_host = bg_np if per_ray_bg else (0.3, 0.6, 0.1)
    assert_forward_matches(b, ref.render_forward(dens, sh, BBOX, o, d, 0.5, bg_host))
    g = 2 * (b["rgb"].astype(np.float64) - target)
    want = ref.render_backward(dens, sh, BBOX, o, d, g, 0.5, bg_host)
    np.testing.assert_allclose(b["bwd"]["density"], want["density"], atol=GRAD_ATOL,
                               rtol=GRAD_RTOL)
    np.testing.assert_allclose(b["bwd"]["sh"], want["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    assert np.abs(want["density"]).max() > 1e-3
