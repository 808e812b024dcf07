"""The Plenoxels grid as the registry lists it (clrf/registry.py): its configuration section,
its settings per scene preset, its factories, memory estimate, device workload, gradient
self-check and multi-process (MPI) training."""
from __future__ import annotations

from ..interface import Kind
from . import budget, selfcheck
from .config import GridConfig
from .workload import WORKLOAD

# Schedules are in iterations and were chosen for CPU budgets of minutes (svox2's defaults
# assume 100k+ GPU iterations): a coarse grid first, pruned by rendering weight and upsampled
# within the first few hundred iterations, RMSProp with svox2's rates but decay horizons of a
# few thousand iterations.
_REAL360 = {"sphere_bound": False, "lambda_tv": 5e-5, "lambda_tv_sh": 5e-3,
            "tv_early_only": False, "lambda_sparsity": 1e-10, "lambda_beta": 1e-5,
            "background_layers": 32, "background_height": 128}
SCENE_PRESETS = {
    "synthetic": {},
    # The built-in procedural scene: smaller grids over the whole box (its floor's corners lie
    # outside the inscribed sphere: with the sphere bound the grid could never hold them, 90 %
    # of the error of a run that stalled at 24 dB), learning rates decayed over about the steps
    # of its 60 s so the curve keeps rising as the steps get finer.
    "procedural": {"reso": [[48, 48, 48], [96, 96, 96]], "upsample_at": [200], "sh_degree": 2,
                   "batch_size": 4000, "sphere_bound": False, "lr_decay_steps": 2000},
    # tiny_lego (100x100 images): a 160^3 final grid is as fine as the pixels can resolve.
    "tiny": {"reso": [[64, 64, 64], [128, 128, 128]], "upsample_at": [250], "batch_size": 4000},
    # Forward-facing (LLFF): stronger TV, sparsity prior (svox2 llff.json). The resolutions are
    # over the dataset's box, which in x, y is as wide as every view's frustum (fern: 1.45 x
    # 1.31 NDC units a side; clrf.data.llff.scene_extent). The z-resolution stays fixed (as in
    # svox2's LLFF schedule): NDC rays run along z, so the samples per ray, and with them the
    # cost of a step, stay those of the coarse stage. No dilation at pruning: the density is
    # scattered through the frustum at the upsample, so a dilated mask covers nearly all of
    # it, while resampling already keeps the new voxels that interpolate a kept one.
    "forward_facing": {"reso": [[128, 128, 64], [256, 256, 64]], "upsample_at": [500],
                       "sphere_bound": False, "lambda_tv": 5e-4, "lambda_tv_sh": 5e-3,
                       "tv_early_only": False, "lambda_sparsity": 1e-10,
                       "prune_dilate": False},
    # Unbounded real 360: no sphere bound, sparsity prior, and an MSI background behind the
    # grid box (32 spheres of 128 x 256 texels from the box's circumscribed sphere outwards;
    # svox2's 360 configs use 64 layers at a finer resolution for 100k+ GPU iterations).
    "real360": _REAL360,
    # real360 without the MSI (instant-ngp captures, whose aabb_scale cube holds the scene):
    # there it only slowed the step and cost accuracy (fox, 30 minutes: 24.93 dB without,
    # 23.20 with).
    "real360_box": dict(_REAL360, background_layers=0),
}


def create(device, cfg, ds, background):
    from .model import GridModel
    if cfg.grid.pose_opt and ds.ndc:
        raise ValueError(f"dataset {ds.name}: grid.pose_opt corrects the cameras that make the "
                         f"rays, and NDC (forward-facing) rays are not a camera's; pass --set "
                         f"grid.pose_opt=false")
    model = GridModel.create(device, cfg.grid, ds.bbox, background)
    if cfg.grid.exposure or cfg.grid.pose_opt:
        attach(model, cfg, ds)
    return model


def attach(model, cfg, ds):
    """The per-image corrections on ``model``: a row per training image, in the trainer's ray
    store's order (its first max_train_images training views), with their cameras."""
    import numpy as np

    from ..corrections.ray_pose import pivot_depth, viewmat_of
    if cfg.grid.exposure and ds.alpha is not None and model.bg_model is not None:
        raise ValueError(f"dataset {ds.name}: grid.exposure on a capture with alpha renders "
                         f"each image on a background of its own, which the MSI background "
                         f"(grid.background_layers) would replace; pass --set "
                         f"grid.exposure=false or --set grid.background_layers=0")
    views = ds.split["train"]
    if cfg.train.max_train_images:
        views = views[:cfg.train.max_train_images]
    poses = np.asarray(ds.poses, np.float64)[views]
    model.attach_corrections(len(views), int(ds.hw[0]) * int(ds.hw[1]),
                             masked=ds.alpha is not None,
                             viewmats=lambda: np.stack([viewmat_of(p) for p in poses]),
                             pivots=lambda: [pivot_depth(viewmat_of(p), ds.bbox) for p in poses])


def from_state(device, state, cfg):
    from .model import GridModel
    return GridModel.from_state_dict(device, state, cfg.grid)


def programs(device, cfg):
    """Every program a grid run of ``cfg`` asks ``device`` for (Kind.programs), through the
    functions the model calls: per stage's resolution the render forward and the training
    step's fused backward (with the tuning's gradient slots and ray order, the MSI's per-ray
    background), the distributed bricks' variants, the self-check's and the workload's, TV,
    export, the MSI background and the optimiser."""
    from types import SimpleNamespace

    from ..runtime import optim
    from . import bricks, msi, ops, workload
    from .model import export_program
    from .render import grid_program
    c, t = cfg.grid, device.tuning
    slots = max(0, int(t.grad_slots))
    record = slots > 0 and t.sample_record
    bg = c.background_layers > 0

    def grid(sh, reso):      # what grid_program reads of a grid
        return SimpleNamespace(device=device, sh_degree=sh, reso=tuple(reso),
                               march_reso=tuple(reso))
    for reso in c.reso:
        g = grid(c.sh_degree, reso)
        grid_program(g, step=c.step)         # block occupancy, max weight, ray order keys
        for order in ((False, True) if t.ray_order > 0 else (False,)):
            grid_program(g, step=c.step, bg_per_ray=bg, ray_order=order)
            grid_program(g, 1, True, step=c.step, slots=slots, record=record, bg_per_ray=bg,
                         ray_order=order)
            # grid.pose_opt: each ray's camera gradient (listed always, as the hash's)
            grid_program(g, 1, step=c.step, bg_per_ray=bg, ray_order=order, pose_grad=True)
            # grid.exposure's one-march backward, plain and clamped (listed always), on each
            # ray's own background (an RGBA capture's, or the MSI's)
            for clip in (1, 2):
                grid_program(g, 1, True, step=c.step, slots=slots, record=record,
                             bg_per_ray=True, ray_order=order, exposure=clip)
        if bg:
            grid_program(g, step=c.step, bg_per_ray=True)              # ray_exit
        bricks._program(g, c.step)                                     # MPI ranks
        bricks._program(g, c.step, track_touched=True, slots=slots, record=record)
    for sh, step in ((0, 0.25), (1, 0.5)):         # the self-check (selfcheck.py)
        g = grid(sh, (6, 5, 4))
        grid_program(g, step=step)
        grid_program(g, 0, False, step=step, slots=slots, record=record)
    g = grid(2, (workload.WORK_RESO,) * 3)                 # the device workload
    grid_program(g, 1, False, step=0.5, slots=slots, record=record)
    ops.program(device, c.sh_degree)
    ops.program(device, c.sh_degree, brick=True)
    export_program(device, c.sh_degree)
    if bg:
        msi.program(device, c.background_layers, c.background_height)
    optim.program(device, c.optimizer)
    from ..corrections import ray_pose
    ray_pose.program(device)                           # grid.pose_opt, listed always
    if c.exposure:
        from ..corrections import exposure
        exposure.program(device)                       # grid.exposure


class Distributed:
    """Plenoxels over MPI ranks, one brick each (clrf/grid/dist_model.py): the checks of a
    run's settings, the per-rank configuration the memory guard budgets, and the factories."""

    def __init__(self, comm):
        self.comm = comm
        self.brick = (comm.Get_rank(), comm.Get_size())   # checkpoint.load(brick=...)

    def check(self, cfg):
        """ValueError naming the setting when ``cfg`` cannot run on these ranks."""
        from .dist_model import check_schedule
        for key in ("exposure", "pose_opt"):
            if getattr(cfg.grid, key):
                raise ValueError(f"grid.{key}: the per-image corrections are not supported by "
                                 f"the distributed grid ({self.comm.Get_size()} MPI ranks); pass "
                                 f"--set grid.{key}=false or run as one process")
        if cfg.grid.background_layers > 0:
            raise ValueError(f"grid.background_layers = {cfg.grid.background_layers}: the "
                             f"distributed grid ({self.comm.Get_size()} MPI ranks) has no "
                             f"background model; pass --set grid.background_layers=0 or run as "
                             f"one process")
        check_schedule(cfg, self.comm.Get_size())

    def rank_config(self, cfg):
        """``cfg`` with each stage's resolution that of the largest brick: what one rank holds."""
        import copy
        from .bricks import split
        out = copy.deepcopy(cfg)
        out.grid.reso = [list(max((b.local_reso for b in split(r, self.comm.Get_size())),
                                  key=lambda x: x[0] * x[1] * x[2])) for r in cfg.grid.reso]
        return out

    def create(self, device, cfg, ds, background):
        from .dist_model import DistGridModel
        return DistGridModel.create(device, cfg.grid, ds.bbox, background, self.comm)

    def from_state(self, device, state, cfg):
        from .dist_model import DistGridModel   # BrickMismatchError is an interface.StateError
        return DistGridModel.from_state_dict(device, state, cfg.grid, self.comm)


KIND = Kind(name="grid", title="Plenoxels: a sparse voxel grid of density and SH colour",
            config=GridConfig, create=create, from_state=from_state, memory=budget.memory,
            scene_presets=SCENE_PRESETS, workload=WORKLOAD, selfcheck=selfcheck.CHECK,
            distributed=Distributed, programs=programs)
