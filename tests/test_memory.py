"""The memory guard (clrf/training/budget.py over clrf/runtime/memory.py): per-stage estimates
against the device's global memory and largest allocation, checked before anything is allocated."""
from dataclasses import replace

import numpy as np
import pytest

from clrf.cli.main import main as cli
from clrf.training.config import build_config
from clrf.grid.budget import grid_stages, sphere_rows
from clrf.runtime.memory import RAY_PART, ray_build_host
from clrf.training.budget import MemoryBudgetError, check_training_fits

GiB = 1 << 30


def test_sphere_rows_matches_the_initial_grid_mask():
    for reso in ((48, 48, 48), (16, 20, 24), (1, 5, 7)):
        c = [(np.arange(r) + 0.5) / r * 2 - 1 for r in reso]
        x, y, z = np.meshgrid(*c, indexing="ij")
        assert sphere_rows(reso) == int((x * x + y * y + z * z <= 1.0).sum())


def test_grid_estimate_counts_every_term():
    # one dense 10^3 stage, SH degree 0 (C = 3, r = 16 bytes a row), no slots: links 4 V,
    # values + gradient + RMSProp state 3 r n, touched n, rays 36 N + 44 B on the device; on
    # the host a checkpoint's copies (4 V + 2 r n; the ray store keeps no host copy of its
    # rays); building the rays holds the device store (36 N) and one part of the rays on the
    # host (36 bytes a ray, at most RAY_PART of them) beside the grid and its optimiser
    cfg = build_config(overrides={"grid": {"reso": [[10, 10, 10]], "upsample_at": [],
                                           "sh_degree": 0, "sphere_bound": False,
                                           "batch_size": 100}})
    build, st = grid_stages(cfg, n_rays=1000, slots=0, global_mem=GiB)
    V = 1000
    assert st.total == 4 * V + 3 * 16 * V + V + 36 * 1000 + 44 * 100
    assert st.host == 4 * V + 2 * 16 * V
    assert st.largest == max(4 * 3 * V, 4 * V)
    assert build.total == 4 * V + 3 * 16 * V + V + 36 * 1000 and build.host == 36 * 1000
    assert ray_build_host(10 * RAY_PART) == 36 * RAY_PART
    assert build.name.startswith("building the training rays")


def test_upsample_holds_both_stages():
    # 10^3 -> 20^3 dense, SH degree 0, one scratch copy: the upsample holds the old stage whole
    # (grid, optimiser, scratch), its max weights and masks (6 n'), the new links (4 V) and
    # rows (r n) and the larger of the resample flags (4 V) and the new optimiser (2 r n + n)
    # less the old links and scratch copy, freed before it is allocated
    cfg = build_config(overrides={"grid": {"reso": [[10, 10, 10], [20, 20, 20]],
                                           "upsample_at": [5], "sh_degree": 0,
                                           "sphere_bound": False, "batch_size": 100}})
    _, st0, up, st1 = grid_stages(cfg, n_rays=0, slots=1, global_mem=GiB)
    V0, V1, r = 1000, 8000, 16
    old = 4 * V0 + r * V0 + 2 * r * V0 + V0 + V0 * (r + 1)
    assert st0.total == old + 44 * 100
    assert up.name.startswith("the upsample to grid stage 1")
    assert up.total == old + 6 * V0 + 4 * V1 + r * V1 + max(
        4 * V1, 2 * r * V1 + V1 - 4 * V0 - V0 * (r + 1)) + 44 * 100
    assert st1.total == 4 * V1 + 3 * r * V1 + V1 + V1 * (r + 1) + 44 * 100


def test_stage_estimates_grow_and_fit_a_normal_device(device):
    plan = check_training_fits(device.caps, device.is_cpu, build_config("procedural"),
                               72 * 64 * 64)
    st = plan.stages   # building the rays, stage 0, the upsample, stage 1
    assert len(st) == 4 and st[3].total > st[1].total and st[2].total > st[1].total


def test_small_device_names_the_stage_and_the_fix(device):
    cfg = build_config("synthetic")
    small = replace(device.caps, global_mem_size=int(0.5 * GiB), max_alloc_size=GiB)
    with pytest.raises(MemoryBudgetError, match=r"grid stage 2 \(256x256x256.*lower grid.reso"):
        check_training_fits(small, False, cfg, 1000)
    tiny_alloc = replace(device.caps, max_alloc_size=16 << 20)
    with pytest.raises(MemoryBudgetError, match="largest single allocation"):
        check_training_fits(tiny_alloc, False, cfg, 1000)
    nerf = build_config(overrides={"train": {"model": "nerf"}, "nerf": {"batch_rays": 1 << 16}})
    with pytest.raises(MemoryBudgetError, match="NeRF training.*nerf.batch_rays"):
        check_training_fits(small, False, nerf, 1000)


def test_too_large_scene_exits_2_before_allocating(tmp_path, capsys, monkeypatch):
    # the guard runs before the trainer: no model or ray store is ever built
    import clrf.training.trainer
    monkeypatch.setattr(clrf.training.trainer, "Trainer", None)
    out = tmp_path / "out"
    rc = cli(["train", "--out", str(out), "--set", "grid.reso=[[1024,1024,1024]]",
              "--set", "grid.upsample_at=[]", "--set", "grid.sh_degree=3"])
    err = capsys.readouterr().err
    assert rc == 2 and "grid stage 0 (1024x1024x1024, SH degree 3)) needs about" in err, err
    assert not out.exists()


def test_background_adds_its_texels():
    # MSI background: 2 L H^2 texels, 49 bytes each (4 floats x param, grad, state + a flag),
    # 32 bytes per batch ray; its colour buffer is 12 bytes a texel
    over = {"reso": [[10, 10, 10]], "upsample_at": [], "sh_degree": 0, "sphere_bound": False,
            "batch_size": 100}
    _, off = grid_stages(build_config(overrides={"grid": over}), 1000, 0, GiB)
    on_cfg = build_config(overrides={"grid": {**over, "background_layers": 4,
                                              "background_height": 8}})
    _, on = grid_stages(on_cfg, 1000, 0, GiB)
    T = 2 * 4 * 8 * 8
    assert on.total - off.total == 49 * T + 32 * 100
    assert on.host - off.host == 32 * T   # the checkpoint's copies of its values and states
    assert build_config("real360").grid.background_layers > 0
    assert build_config("real360_box").grid.background_layers == 0
    assert build_config("synthetic").grid.background_layers == 0


def test_uploads_keep_no_host_copy(device):
    """pyopencl's to_device keeps the host array alive (an event in the new array's list)
    until that array's own finish(), which kernels launched on its buffer never call: a grid
    held a second copy of itself in host memory. clrf's uploads leave no such event."""
    import sys
    import numpy as np
    from clrf import SparseGrid
    from clrf.runtime.programs import upload
    from clrf.training.trainer import RayStore
    a = np.ones(1000, np.float32)
    refs = sys.getrefcount(a)
    arr = upload(device.queue, a)
    assert sys.getrefcount(a) == refs and not arr.events
    grid = SparseGrid.from_dense(device, np.ones((3, 4, 5)), np.zeros((3, 4, 5, 3)),
                                 [[0, 0, 0], [1, 1, 1]])
    store = RayStore(device, np.zeros((7, 3)), np.ones((7, 3)), np.zeros((7, 3)))
    for x in (grid.links, grid.density, grid.sh, store.o, store.d, store.c):
        assert not x.events


def test_checkpoint_downloads_keep_no_host_copy(device):
    """pyopencl's get() leaves its read event, which holds the downloaded numpy array, in the
    device array's event list: each checkpoint of a long-lived table kept another host copy
    (resident memory grew ~0.2 GB a save on a full hash model). download() and the models'
    state_dict leave none, and a state_dict's arrays are freed once dropped."""
    import gc
    import sys
    import weakref
    import numpy as np
    from clrf.hash.config import HashConfig
    from clrf.hash.model import HashModel
    from clrf.runtime.programs import download, upload
    arr = upload(device.queue, np.arange(1000, dtype=np.float32))
    kept = arr.get()
    assert arr.events, "pyopencl's get() no longer keeps its event: download() can go"
    arr.finish()
    out = download(arr)
    assert not arr.events and sys.getrefcount(out) == sys.getrefcount(kept)
    assert np.array_equal(out, np.arange(1000))
    model = HashModel(device, HashConfig.from_preset("tiny", log2_table=10, max_res=32),
                      near=1.0, far=3.0, bbox=[[-1] * 3, [1] * 3])
    st = model.state_dict()
    for x in (model.enc.table, model._adam_table.state, model._adam_table.state2,
              model.net.params, model.occ.ema):
        assert not x.events
    ref = weakref.ref(st["table"])
    del st
    gc.collect()
    assert ref() is None


def test_scratch_copies_follow_the_tuning():
    """The grid estimate counts the scratch gradient copies the backward really holds: one on
    CPU devices with block locks, one per slot without them, none on the atomic path."""
    from clrf.grid.budget import scratch_copies
    from clrf.runtime.tuning import Tuning
    assert scratch_copies(True) == 1 and scratch_copies(False) == 0
    assert scratch_copies(True, Tuning(grad_slots=8, grad_locks=4)) == 1
    assert scratch_copies(True, Tuning(grad_slots=8, grad_locks=0)) == 8
    assert scratch_copies(False, Tuning(grad_slots=0, grad_locks=4)) == 0


def test_host_budget_counts_device_bytes_on_cpus_only(device):
    """On a CPU device the buffers are host memory: the growth checked against the host is
    device + host bytes; on a GPU only the host bytes (ray store copies, checkpoint copies,
    ray building). The predicted peak adds what the process holds and RUNTIME_GROWTH."""
    from clrf.runtime.hostmem import HostBudget
    from clrf.training.budget import RUNTIME_GROWTH, plan_training
    cfg = build_config("procedural")
    n = 72 * 64 * 64
    big = replace(device.caps, global_mem_size=64 * GiB, max_alloc_size=64 * GiB)
    cpu = plan_training(big, True, cfg, n, None, HostBudget(GiB, "test", 100 << 20, 0))
    gpu = plan_training(big, False, cfg, n, None, HostBudget(GiB, "test", 100 << 20, 0))
    st = cpu.stages
    assert cpu.peak == (100 << 20) + RUNTIME_GROWTH + max(s.total + s.host for s in st)
    assert gpu.peak == (100 << 20) + RUNTIME_GROWTH + max(s.host for s in st)
    assert "predicted peak" in cpu.describe() and "test" in cpu.describe()
    # a budget between the two: the GPU run fits, the CPU run is refused
    need_cpu = RUNTIME_GROWTH + max(s.total + s.host for s in st)
    need_gpu = RUNTIME_GROWTH + max(s.host for s in st)
    mid = HostBudget((need_cpu + need_gpu) // 2, "the memory limit of cgroup /x", 0, 0)
    check_training_fits(big, False, cfg, n, None, mid)
    with pytest.raises(MemoryBudgetError, match="more device and host memory.*cgroup /x"):
        check_training_fits(big, True, cfg, n, None, mid)
    # the peak so far (loading the images) is a floor of the prediction
    floor = plan_training(big, True, cfg, n, None, HostBudget(GiB, "test", 0, 50 * GiB))
    assert floor.peak == 50 * GiB


def test_cpu_devices_budget_against_the_host_not_global_mem(device):
    """PoCL reports a fraction of the host as global_mem_size (5.2 GiB on a 24 GiB host) but
    does not cap the sum of its buffers at it: with the host's budget known, a CPU run larger
    than global_mem_size but within the host's budget fits; a GPU run does not, nor a CPU run
    whose host budget is unknown. max_alloc_size binds everywhere."""
    from clrf.runtime.hostmem import HostBudget
    cfg = build_config("synthetic")
    small = replace(device.caps, global_mem_size=int(0.5 * GiB), max_alloc_size=2 * GiB)
    roomy = HostBudget(64 * GiB, "test", 0, 0)
    check_training_fits(small, True, cfg, 1000, None, roomy)
    with pytest.raises(MemoryBudgetError, match="of device memory"):
        check_training_fits(small, False, cfg, 1000, None, roomy)
    with pytest.raises(MemoryBudgetError, match="of device memory"):
        check_training_fits(small, True, cfg, 1000, None, HostBudget(-1, "unknown", 0, 0))
    tiny_alloc = replace(small, max_alloc_size=16 << 20)
    with pytest.raises(MemoryBudgetError, match="largest single allocation"):
        check_training_fits(tiny_alloc, True, cfg, 1000, None, roomy)
