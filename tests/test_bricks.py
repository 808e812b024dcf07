"""Bricks of a grid (clrf/grid/bricks.py) in one process: the partial kernels against the float64
reference, and composed partials against the single-grid render and gradients (no MPI: every
brick is rendered here in turn; tests/test_mpi.py runs the same across processes)."""
import numpy as np
import pyopencl.array as cla
import pytest

from clrf.grid import bricks as B
from clrf.grid.grid import SparseGrid
from clrf.grid.render import render_backward_device, render_forward_device
from clrf.references import reference as ref
from clrf.references import reference_bricks as rb
from clrf.testing.tolerances import (BRICK_COMPOSE_ATOL, BRICK_DEPTH_ATOL, BRICK_REF_ATOL,
                                     DEPTH_ATOL, DEPTH_RTOL, GRAD_ATOL, GRAD_RTOL, RENDER_ATOL,
                                     RENDER_RTOL)

from mpi_script import BBOX, SHAPE, STEP, BACKGROUND, scene


def test_split_partitions_the_voxels():
    for reso, n in [((10, 7, 9), 1), ((10, 7, 9), 2), ((10, 7, 9), 3), ((64, 32, 48), 8),
                    ((5, 1, 2), 4), ((2, 2, 2), 1)]:
        bl = B.split(reso, n)
        assert len(bl) == n
        count = np.zeros(reso, int)
        for b in bl:
            count[tuple(slice(l, h) for l, h in zip(b.lo, b.hi))] += 1
            assert b.local_reso == tuple(min(h + 1, r) - l for l, h, r in zip(b.lo, b.hi, reso))
        assert np.all(count == 1)
    # the longest axis is cut first, in proportion to the ranks on each side
    assert [(b.lo, b.hi) for b in B.split((8, 32, 8), 2)] == [((0, 0, 0), (8, 16, 8)),
                                                            ((0, 16, 0), (8, 32, 8))]
    with pytest.raises(ValueError, match="cannot be split"):
        B.split((3, 1, 1), 3)


def test_split_balances_a_weight():
    """With a weight per block of cells (expected rows), cuts split the weight, not the volume:
    here all rows sit in the first quarter of x."""
    reso = (65, 33, 33)                    # 64 x 32 x 32 cells
    w = np.zeros((64, 32, 32))             # blocks of one cell
    w[:16] = 1.0
    for n in (2, 3, 4):
        bl = B.split(reso, n, w, 1)
        count = np.zeros(reso, int)
        for b in bl:
            count[tuple(slice(l, h) for l, h in zip(b.lo, b.hi))] += 1
        assert np.all(count == 1)
        share = [w[tuple(slice(l, h) for l, h in zip(b.lo, b.hi))].sum() / w.sum() for b in bl]
        assert max(share) <= 1.0 / n + 1.0 / 16, share     # cuts fall on whole cells
    assert B.split(reso, 2, w, 1)[0].hi[0] == 8            # by volume it would be 32
    assert B.split(reso, 2, np.zeros_like(w), 1)[0].hi[0] == 32   # no weight: by volume
    # coarse blocks: cuts on block boundaries (multiples of 4 cells)
    wb = w.reshape(16, 4, 8, 4, 8, 4).sum(axis=(1, 3, 5))
    assert B.split(reso, 2, wb, 4)[0].hi[0] == 8


@pytest.mark.parametrize("n_bricks", [2, 3, 4])
def test_reference_partials_compose_to_single_grid(n_bricks):
    """The math alone, float64: partials over the bricks, composed, are the single-grid render,
    and the brick backwards with backward_inputs sum to the single-grid gradient."""
    dens, sh, o, d, g = scene(n_rays=150)
    full = ref.render_forward(dens, sh, BBOX, o, d, STEP, BACKGROUND, t_stop=0.0)
    bl = B.split(SHAPE, n_bricks)
    parts = [rb.render_partial(dens, sh, BBOX, o, d, b.lo, b.hi, STEP) for b in bl]
    packed = np.stack([rb.pack(p) for p in parts])
    comp = B.compose(packed, BACKGROUND)
    for k in ("rgb", "depth", "acc"):
        np.testing.assert_allclose(comp[k], full[k], rtol=0, atol=BRICK_REF_ATOL)
    gfull = ref.render_backward(dens, sh, BBOX, o, d, g, STEP, BACKGROUND, t_stop=0.0)
    inp = B.backward_inputs(packed, comp, g, BACKGROUND, dtype=np.float64)
    tot = {"density": 0.0, "sh": 0.0}
    for b, i4 in zip(bl, inp):
        gb = rb.backward_partial(dens, sh, BBOX, o, d, b.lo, b.hi, i4, STEP)
        tot = {k: tot[k] + gb[k] for k in tot}
    for k in tot:
        np.testing.assert_allclose(tot[k], gfull[k], rtol=0, atol=BRICK_REF_ATOL)


def _grids(device, dens, sh, bl):
    return [B.BrickGrid.from_dense(device, dens, sh, BBOX, b) for b in bl]


@pytest.mark.parametrize("n_bricks", [2, 3])
def test_partial_kernel_vs_reference(device, n_bricks):
    dens, sh, o, d, _ = scene(n_rays=200)
    q = device.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    for b, bg in zip(B.split(SHAPE, n_bricks), _grids(device, dens, sh, B.split(SHAPE, n_bricks))):
        got = B.render_partial_device(bg, od, dd, STEP)
        want = rb.render_partial(dens, sh, BBOX, o, d, b.lo, b.hi, STEP)
        np.testing.assert_allclose(got["rgb"].get(), want["rgb"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
        np.testing.assert_allclose(got["acc"].get(), want["acc"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
        np.testing.assert_allclose(np.exp(got["logT"].get()), np.exp(want["logT"]),
                                   atol=RENDER_ATOL, rtol=RENDER_RTOL)
        np.testing.assert_allclose(got["depth"].get(), want["depth"], atol=DEPTH_ATOL, rtol=DEPTH_RTOL)
        # the first evaluated segment is the first owned one with an allocated corner
        np.testing.assert_array_equal(got["key"].get(), want["key"])


@pytest.mark.parametrize("n_bricks", [1, 2, 3, 4])
def test_composed_kernels_equal_single_device(render_device, n_bricks):
    """Partials of every brick, composed, vs the single-device render without early
    termination (to 1e-5), and the bricks' gradients vs the single-device gradients."""
    dens, sh, o, d, g = scene()
    dev = render_device
    q = dev.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    grid = SparseGrid.from_dense(dev, dens, sh, BBOX)
    single = {k: v.get() for k, v in
              render_forward_device(grid, od, dd, STEP, BACKGROUND, t_stop=0.0).items()}
    bl = B.split(SHAPE, n_bricks)
    bgs = _grids(dev, dens, sh, bl)
    packed = np.stack([B.pack_partials(B.render_partial_device(b, od, dd, STEP)) for b in bgs])
    comp = B.compose(packed, BACKGROUND)
    np.testing.assert_allclose(comp["rgb"], single["rgb"], rtol=0, atol=BRICK_COMPOSE_ATOL)
    np.testing.assert_allclose(comp["acc"], single["acc"], rtol=0, atol=BRICK_COMPOSE_ATOL)
    np.testing.assert_allclose(comp["depth"], single["depth"], rtol=0, atol=BRICK_DEPTH_ATOL)

    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    render_backward_device(grid, od, dd, cla.to_device(q, g), STEP, BACKGROUND, gd, gs,
                           t_stop=0.0)
    want_d, want_s = grid.rows_to_dense(gd.get(), gs.get())
    inp = B.backward_inputs(packed, comp, g, BACKGROUND)
    got_d = np.zeros_like(want_d)
    got_s = np.zeros_like(want_s)
    for b, bg, i4 in zip(bl, bgs, inp):
        ld = cla.zeros(q, bg.density.shape[0], np.float32)
        ls = cla.zeros(q, bg.sh.shape, np.float32)
        B.render_backward_partial_device(bg, od, dd, cla.to_device(q, np.ascontiguousarray(i4)),
                                         STEP, ld, ls)
        a, s = bg.rows_to_dense(ld.get(), ls.get())
        got_d[b.local_slices] += a      # halo rows: the sum over holders (distributed.sum_halo)
        got_s[b.local_slices] += s
    np.testing.assert_allclose(got_d, want_d, atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(got_s, want_s, atol=GRAD_ATOL, rtol=GRAD_RTOL)


def test_composed_matches_reference_with_background(device):
    """The composed kernel render against the float64 single-grid reference (no T_STOP)."""
    dens, sh, o, d, _ = scene(n_rays=150)
    q = device.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    bgs = _grids(device, dens, sh, B.split(SHAPE, 3))
    comp = B.compose(np.stack([B.pack_partials(B.render_partial_device(b, od, dd, STEP))
                               for b in bgs]), BACKGROUND)
    want = ref.render_forward(dens, sh, BBOX, o, d, STEP, BACKGROUND, t_stop=0.0)
    np.testing.assert_allclose(comp["rgb"], want["rgb"], atol=RENDER_ATOL, rtol=RENDER_RTOL)
    np.testing.assert_allclose(comp["depth"], want["depth"], atol=DEPTH_ATOL, rtol=DEPTH_RTOL)


def _edge_rays():
    """Rays whose samples sit on brick faces and cell boundaries: axis-aligned rays in the
    planes where a brick starts (box units lo + 0.5, the exact lerp_axis boundary), along the
    faces and across them, plus the scene's random rays."""
    _, _, o, d, _ = scene(n_rays=64)
    scale = np.array(SHAPE) / (BBOX[1] - BBOX[0])
    world = lambda p: BBOX[0] + np.asarray(p, np.float64) / scale   # box units -> world
    oo, dd = [o], [d]
    for b in B.split(SHAPE, 3):
        for a in range(3):
            if b.lo[a] == 0:
                continue
            for other in range(3):          # along the other axes, in the plane u_a = lo
                if other == a:
                    continue
                p = np.array(SHAPE) / 2.0 + 0.25
                p[a] = b.lo[a] + 0.5
                p[other] = -3.0
                v = np.zeros(3)
                v[other] = 1.0
                oo.append(world(p)[None].astype(np.float32))
                dd.append(v[None].astype(np.float32))
            p = np.array(SHAPE) / 2.0 + 0.25      # straight across the face
            p[a] = -3.0
            v = np.zeros(3)
            v[a] = 1.0
            oo.append(world(p)[None].astype(np.float32))
            dd.append(v[None].astype(np.float32))
    return np.concatenate(oo), np.concatenate(dd)


@pytest.mark.parametrize("n_bricks", [2, 3])
def test_rays_on_brick_faces(device, n_bricks):
    """Samples exactly on the planes where bricks meet are owned once: the composed render
    equals the single-device one."""
    dens, sh, _, _, _ = scene()
    o, d = _edge_rays()
    q = device.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    grid = SparseGrid.from_dense(device, dens, sh, BBOX)
    single = render_forward_device(grid, od, dd, STEP, BACKGROUND, t_stop=0.0)
    bgs = _grids(device, dens, sh, B.split(SHAPE, n_bricks))
    comp = B.compose(np.stack([B.pack_partials(B.render_partial_device(b, od, dd, STEP))
                               for b in bgs]), BACKGROUND)
    np.testing.assert_allclose(comp["rgb"], single["rgb"].get(), rtol=0, atol=BRICK_COMPOSE_ATOL)
    np.testing.assert_allclose(comp["acc"], single["acc"].get(), rtol=0, atol=BRICK_COMPOSE_ATOL)
    assert np.all(single["acc"].get()[64:] > 0)    # the edge rays do cross matter


def test_empty_brick(device):
    """A brick without rows (pruned empty) renders the identity partial."""
    dens, sh, o, d, g = scene()
    dens[:5] = 0
    sh[:5] = 0
    q = device.queue
    od, dd = cla.to_device(q, o), cla.to_device(q, d)
    bl = B.split(SHAPE, 2)
    assert bl[0].local_hi[0] == 5           # voxels 0..4 held, halo included: all empty
    bgs = _grids(device, dens, sh, bl)
    assert bgs[0].n_rows == 0
    part = B.render_partial_device(bgs[0], od, dd, STEP)
    lt = part["logT"].get()
    np.testing.assert_array_equal(part["rgb"].get()[lt == 0], 0)
    grid = SparseGrid.from_dense(device, dens, sh, BBOX)
    single = render_forward_device(grid, od, dd, STEP, BACKGROUND, t_stop=0.0)
    comp = B.compose(np.stack([B.pack_partials(B.render_partial_device(b, od, dd, STEP))
                               for b in bgs]), BACKGROUND)
    np.testing.assert_allclose(comp["rgb"], single["rgb"].get(), rtol=0, atol=BRICK_COMPOSE_ATOL)


def test_world_is_none_without_a_launcher(monkeypatch):
    """A single process never imports mpi4py; a launcher without mpi4py is a clear error."""
    import subprocess
    import sys
    from clrf.grid import distributed
    for v in distributed.LAUNCHER_SIZE_VARS:
        monkeypatch.delenv(v, raising=False)
    code = ("import sys, clrf.grid.distributed as d; assert d.world() is None; "
            "assert 'mpi4py' not in sys.modules")
    env = {k: v for k, v in __import__('os').environ.items()
           if k not in distributed.LAUNCHER_SIZE_VARS}
    subprocess.run([sys.executable, "-c", code], check=True, env=env)
    monkeypatch.setenv("OMPI_COMM_WORLD_SIZE", "2")
    monkeypatch.setitem(sys.modules, "mpi4py", None)     # import fails as if not installed
    with pytest.raises(RuntimeError, match="mpi4py is not installed"):
        distributed.world()


def test_pin_threads_tells_pocl_the_ranks_cpus(monkeypatch):
    """Under MPI a rank bound to fewer CPUs than are online tells PoCL that many threads,
    unless the environment already says; a process with every CPU is left alone."""
    import os
    from clrf.runtime import mpi
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    monkeypatch.delenv("POCL_MAX_PTHREAD_COUNT", raising=False)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {3})
    mpi.pin_threads()
    assert os.environ["POCL_MAX_PTHREAD_COUNT"] == "1"
    monkeypatch.setenv("POCL_MAX_PTHREAD_COUNT", "4")
    mpi.pin_threads()
    assert os.environ["POCL_MAX_PTHREAD_COUNT"] == "4"
    monkeypatch.delenv("POCL_MAX_PTHREAD_COUNT")
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(8)))
    mpi.pin_threads()
    assert "POCL_MAX_PTHREAD_COUNT" not in os.environ


def test_each_rank_builds_into_a_kernel_cache_of_its_own(monkeypatch, tmp_path):
    """Ranks building the same program at once must not share PoCL's kernel cache: under a
    launcher each rank gets a folder named by its rank (stable over runs); a cache the
    environment names, or a process no launcher started, is left alone."""
    import os
    from clrf.runtime import mpi
    for v in mpi.LAUNCHER_RANK_VARS:
        monkeypatch.delenv(v, raising=False)
    monkeypatch.delenv("POCL_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    mpi.own_kernel_cache()
    assert "POCL_CACHE_DIR" not in os.environ
    monkeypatch.setenv("PMI_RANK", "3")
    mpi.own_kernel_cache()
    assert os.environ["POCL_CACHE_DIR"] == str(tmp_path / "pocl" / "kcache-rank3")
    monkeypatch.setenv("POCL_CACHE_DIR", "/elsewhere")
    monkeypatch.setenv("OMPI_COMM_WORLD_RANK", "1")
    mpi.own_kernel_cache()
    assert os.environ["POCL_CACHE_DIR"] == "/elsewhere"

