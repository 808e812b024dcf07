"""The CPU gradient path of render_backward (GRAD_SLOTS private copies + grad_slots_reduce, or
with GRAD_LOCKS adds under block locks + one atomic scratch copy) against the float64
reference, for every slot count including 0 (float atomics only) and 1 (with two compute units,
concurrently running work-items fall back to the atomic scratch).

Two backward calls into the same buffers must give twice the gradient, and a batch after
another one through other cells only its own: the scratch copies are left zero after each
call. ``touched`` must mark every row with a non-zero gradient.

A GPU without acquire/release atomics refuses slots (test_slots_refused_where_locks_order_nothing);
there the slot tests skip, and the slots = 0 cases test its atomic path.
"""
from types import SimpleNamespace

import numpy as np
import pyopencl.array as cla
import pytest

import clrf
from clrf.references import reference
import clrf.grid.render as render
from clrf.grid.render import _slot_buffers, grad_slots, launch, render_backward_device
from clrf.testing.tolerances import GRAD_ATOL, GRAD_RTOL
from clrf.runtime.device import DeviceError
from clrf.runtime.tuning import Tuning, slots_order_memory

BBOX = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _with_slots(device, **kw):
    """device.with_tuning(**kw), skipping where the device refuses gradient slots."""
    if kw.get("grad_slots", 0) > 0 and not slots_order_memory(device.caps):
        pytest.skip(f"{device.caps.name} refuses gradient slots (no acquire/release atomics)")
    return device.with_tuning(**kw)


def _scene(seed=3, reso=(9, 7, 8), degree=2, keep=0.6, dmin=0.0):
    rng = np.random.default_rng(seed)
    C = 3 * (degree + 1) ** 2
    dens = rng.uniform(dmin, 2.0, reso).astype(np.float32)
    sh = rng.normal(0, 0.3, reso + (C,)).astype(np.float32)
    mask = rng.uniform(size=reso) < keep
    n = 300
    o = rng.normal(size=(n, 3))
    o *= 3.0 / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-0.8, 0.8, (n, 3)) - o
    return dens * mask, sh * mask[..., None], mask, o.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("slots,locks", [(0, 0), (1, 0), (2, 0), (3, 0), (1, 1), (2, 1),
                                         (2, 4), (3, 1)])
@pytest.mark.parametrize("grad_mode", [0, 1])
@pytest.mark.parametrize("record", [False, True])
@pytest.mark.parametrize("dmin", [0.0, -1.5])
def test_grad_slots_match_reference(device, slots, locks, grad_mode, record, dmin):
    """dmin < 0: allocated voxels with negative density, so that some samples have sigma <= 0
    (recorded, then passed over by the backward) between ones that have sigma > 0. locks:
    tuning.grad_locks (0: private copies; 1: 2-voxel blocks, where the two compute units'
    work-items often want the same lock; 4: the CPU default, one block here)."""
    device = _with_slots(device, grad_slots=slots, sample_record=record, grad_locks=locks)
    dens, sh, mask, o, d = _scene(dmin=dmin)
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX, mask=mask)
    assert grad_slots(grid) == slots
    rng = np.random.default_rng(4)
    n = o.shape[0]
    ray_in = rng.uniform(0, 1, (n, 3)).astype(np.float32)
    if grad_mode == 1:
        rgb = reference.render_forward(dens, sh, BBOX, o, d, 0.5, (1, 1, 1))["rgb"]
        g = 2.0 * (rgb - ray_in)
    else:
        g = ray_in.astype(np.float64)
    ref = reference.render_backward(dens, sh, BBOX, o, d, g, 0.5, (1, 1, 1), mask=mask)
    q = device.queue
    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    touched = cla.zeros(q, grid.density.shape[0], np.uint8)
    args = (cla.to_device(q, o), cla.to_device(q, d), cla.to_device(q, ray_in), 0.5, (1, 1, 1),
            gd, gs)
    for _ in range(2):
        render_backward_device(grid, *args, grad_mode=grad_mode, loss_scale=1.0,
                               ray_out=cla.empty(q, n, np.float32), touched=touched)
    gdd, gsd = grid.rows_to_dense(gd.get(), gs.get())
    np.testing.assert_allclose(gdd, 2 * ref["density"], atol=2 * GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(gsd, 2 * ref["sh"], atol=2 * GRAD_ATOL, rtol=GRAD_RTOL)
    t = touched.get()[:grid.n_rows].astype(bool)
    nonzero = (gd.get()[:grid.n_rows] != 0) | np.any(gs.get()[:grid.n_rows] != 0, axis=1)
    assert np.all(t[nonzero])


@pytest.mark.parametrize("slots", [1, 2, 3])
@pytest.mark.parametrize("locks", [0, 1])
def test_scratch_left_over_from_another_batch(device, slots, locks):
    """Nothing of one batch's scratch copies leaks into the next: a batch after another batch
    through other cells gets exactly its own gradient (enough rays that every compute unit
    holds a private copy)."""
    device = _with_slots(device, grad_slots=slots, grad_locks=locks)
    dens, sh, mask, o, d = _scene(seed=5)
    o, d = np.tile(o, (6, 1)), np.tile(d, (6, 1))   # enough work-groups for every compute unit
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX, mask=mask)
    q = device.queue
    rng = np.random.default_rng(6)
    n = o.shape[0]
    half = n // 2
    for lo, hi in ((0, half), (half, n), (0, n)):
        g = rng.normal(size=(hi - lo, 3)).astype(np.float32)
        gd = cla.zeros(q, grid.density.shape[0], np.float32)
        gs = cla.zeros(q, grid.sh.shape, np.float32)
        render_backward_device(grid, cla.to_device(q, o[lo:hi]), cla.to_device(q, d[lo:hi]),
                               cla.to_device(q, g), 0.5, (1, 1, 1), gd, gs)
        want = reference.render_backward(dens, sh, BBOX, o[lo:hi], d[lo:hi], g, 0.5, (1, 1, 1),
                                         mask=mask)
        gdd, gsd = grid.rows_to_dense(gd.get(), gs.get())
        np.testing.assert_allclose(gdd, want["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
        np.testing.assert_allclose(gsd, want["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)


@pytest.mark.parametrize("held", ["none", "some", "all"])
def test_block_lock_held_elsewhere(device, held):
    """A cell whose block lock another work-item holds goes with atomics into the scratch copy,
    and grad_slots_reduce adds it in: with some or all of the locks held (set to 1 in the lock
    buffer for the whole call) the gradient is still the reference's, the scratch copy is used
    exactly when a lock was held, and it is left zero. The rays fit one work-group, so one
    work-item runs at a time and no lock is ever taken by the call itself."""
    device = _with_slots(device, grad_slots=2, sample_record=True, grad_locks=1,
                                grid_local_size=64)
    dens, sh, mask, o, d = _scene(seed=7)
    o, d = o[:64], d[:64]
    grid = clrf.SparseGrid.from_dense(device, dens, sh, BBOX, mask=mask)
    q = device.queue
    g = np.random.default_rng(8).normal(size=(o.shape[0], 3)).astype(np.float32)
    want = reference.render_backward(dens, sh, BBOX, o, d, g, 0.5, (1, 1, 1), mask=mask)
    sd, ss, st, _, locks = _slot_buffers(grid, grad_slots(grid))
    n_locks = locks.shape[0] // 16
    pick = {"none": np.zeros(n_locks, bool), "all": np.ones(n_locks, bool),
            "some": np.arange(n_locks) % 3 == 0}[held]
    hold = np.zeros((n_locks, 16), np.int32)
    hold[pick, 0] = 1
    locks.set(hold.ravel())
    seen = {}

    def spy(dev, kernel, *args, **kw):   # the scratch marks just before the reduction
        if kernel.function_name == "grad_slots_reduce":
            seen["scratch_rows"] = int(st.get().astype(bool).sum())
        return launch(dev, kernel, *args, **kw)

    gd = cla.zeros(q, grid.density.shape[0], np.float32)
    gs = cla.zeros(q, grid.sh.shape, np.float32)
    orig, render.launch = render.launch, spy
    try:
        render_backward_device(grid, cla.to_device(q, o), cla.to_device(q, d),
                               cla.to_device(q, g), 0.5, (1, 1, 1), gd, gs)
    finally:
        render.launch = orig
        locks.fill(0)
    gdd, gsd = grid.rows_to_dense(gd.get(), gs.get())
    np.testing.assert_allclose(gdd, want["density"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    np.testing.assert_allclose(gsd, want["sh"], atol=GRAD_ATOL, rtol=GRAD_RTOL)
    if held == "none" and device.caps.type == "cpu":   # a GPU runs the group's items at once
        assert seen["scratch_rows"] == 0
    else:
        assert seen["scratch_rows"] > 0
    if held == "all":   # every row with a gradient went through the scratch copy
        nonzero = (gd.get()[:grid.n_rows] != 0) | np.any(gs.get()[:grid.n_rows] != 0, axis=1)
        assert seen["scratch_rows"] >= int(nonzero.sum())
    assert not st.get().any() and not sd.get().any() and not ss.get().any()


def test_scratch_memory_rule():
    """The slot path is used while its scratch copies fit in a quarter of the device memory:
    with block locks one copy per grid, without them one per slot (1 M rows of SH2: 113 MB a
    copy, 150 MB allowed)."""
    def grid(locks):
        caps = SimpleNamespace(global_mem_size=4 * 150 * 2 ** 20, type="cpu")
        dev = SimpleNamespace(caps=caps, tuning=Tuning(grad_slots=2, grad_locks=locks))
        return SimpleNamespace(device=dev, sh_dim=27, density=np.zeros(2 ** 20, np.float32))

    assert grad_slots(grid(4)) == 2
    assert grad_slots(grid(0)) == 0


@pytest.mark.parametrize("kind,acq_rel,ok", [("cpu", False, True), ("cpu", True, True),
                                             ("gpu", True, True), ("gpu", False, False)])
def test_slots_refused_where_locks_order_nothing(kind, acq_rel, ok):
    """Slots on a GPU whose locks order nothing between work-groups (no acquire/release
    atomics: NVIDIA's driver) are refused with the fix, not run to wrong gradients; the
    float-atomic path (0 slots) runs everywhere."""
    def grid(slots):
        caps = SimpleNamespace(global_mem_size=2 ** 34, type=kind, acq_rel=acq_rel, name="dev")
        dev = SimpleNamespace(caps=caps, tuning=Tuning(grad_slots=slots, grad_locks=4))
        return SimpleNamespace(device=dev, sh_dim=27, density=np.zeros(64, np.float32))

    assert grad_slots(grid(0)) == 0
    if ok:
        assert grad_slots(grid(2)) == 2
    else:
        with pytest.raises(DeviceError, match="CLRF_GRAD_SLOTS=0"):
            grad_slots(grid(2))
