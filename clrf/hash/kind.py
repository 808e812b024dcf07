"""The hash grid as the registry lists it (clrf/registry.py): its configuration section,
presets and settings per scene preset, factories and memory estimate. It has no workload of
its own: its default device is the probe's choice."""
from __future__ import annotations

import numpy as np

# the ray store's cameras and their pivots (pose corrections), shared with NeRF's kind
from ..corrections.ray_pose import OPENGL_TO_OPENCV, pivot_depth, viewmat_of  # noqa: F401
from ..interface import Kind
from . import budget
from .config import HASH_PRESETS, HashConfig

SCENE_PRESETS = {
    # Synthetic scenes hold the full learning rate for 65 % of the budget, not 50 %: lego_400,
    # 900 s, one run each on a 2-vCPU Xeon, 200 test views: hold 0.3 31.89 dB, 0.5 31.94 and
    # 31.95 (two runs), 0.65 32.06; the 4 monitored views gained under 0.05 dB in the last
    # 150 s at 0.5 (the rate already below 1e-3) and 0.14 at 0.65.
    "synthetic": {"lr_hold": 0.65},
    "procedural": {"preset": "tiny"},
    "tiny": {"preset": "tiny"},
    # the finest level at about two cells per pixel of the box's width (NDC: the frustum), not
    # 2048: with 17-20 views the finer levels only fit the training views (fern, 900 s:
    # 25.04 dB against 24.80 with 2048, one run each, Xeon)
    "forward_facing": {"max_res": 1024},
}


def programs(device, cfg):
    """Every program a hash run of ``cfg`` asks ``device`` for (Kind.programs): the encoding,
    the marcher (box and contracted; each also with the rays' camera gradient, listed whatever
    cfg says), the occupancy grid, the fused MLP and Adam."""
    from ..mlp import mlp
    from ..runtime import optim
    from . import encoding, march
    from .model import mlp_spec
    c = cfg.hash
    encoding.program(device, c.levels, c.features, c.log2_table)
    for contract in (False, True):
        march.program(device, contract)
        march.program(device, contract, pose=True)         # pose refinement
    device.program("hash_occ.cl", {})                      # occupancy.py
    from ..corrections import ray_pose
    ray_pose.program(device)                               # hash.pose_opt, listed always
    if c.exposure:
        from ..corrections import exposure
        exposure.program(device)                           # clrf/corrections/exposure.py
    mlp.program(device, mlp_spec(c))
    optim.program(device, "adam")


def _bounded(device) -> bool:
    """Training steps keep their sizes on the device (HashModel.train_step) where the device
    runs the GPU-shaped kernels: GPUs, or any device with CLRF_FORCE_GPU_KERNELS=1."""
    return bool(getattr(device.tuning, "gpu_kernels", False))


def create(device, cfg, ds, background):
    from .model import HashModel, ray_range, resolve_contract, resolve_max_res
    if cfg.hash.pose_opt and ds.ndc:
        raise ValueError(f"dataset {ds.name}: hash.pose_opt corrects the cameras that make the "
                         f"rays, and NDC (forward-facing) rays are not a camera's; pass --set "
                         f"hash.pose_opt=false")
    hc = resolve_max_res(resolve_contract(cfg.hash, ds), ds)
    near, far = ray_range(ds, hc.contract == "on", ds.unit_far() if ds.ndc else None)
    model = HashModel(device, hc, near, far, ds.bbox, background, cfg.train.seed,
                      bounded=_bounded(device))
    # the per-view corrections: a row per training image, in the trainer's ray store's order
    views = ds.split["train"]
    if cfg.train.max_train_images:
        views = views[:cfg.train.max_train_images]
    poses = np.asarray(ds.poses, np.float64)[views]
    model.attach_corrections(len(views), int(ds.hw[0]) * int(ds.hw[1]),
                             masked=ds.alpha is not None,
                             viewmats=lambda: np.stack([viewmat_of(p) for p in poses]),
                             pivots=lambda: [pivot_depth(viewmat_of(p), ds.bbox) for p in poses])
    return model


def from_state(device, state, cfg):
    from .model import HashModel
    return HashModel.from_state_dict(device, state, bounded=_bounded(device))


class Distributed:
    """The hash grid over MPI ranks, data-parallel (clrf/runtime/dataparallel.py): every rank
    holds the whole model and trains its share of each batch; the gradients are summed over
    the ranks before every Adam step, so the models stay identical and rank 0 writes the one
    checkpoint."""

    brick = None        # one checkpoint, read whole on every rank (checkpoint.load)

    def __init__(self, comm):
        self.comm = comm

    def check(self, cfg):
        """ValueError naming the setting when ``cfg`` cannot run on these ranks."""
        if cfg.hash.exposure:
            raise ValueError(f"hash.exposure: the colour transforms per image are not summed "
                             f"over MPI ranks yet ({self.comm.Get_size()} ranks); pass --set "
                             f"hash.exposure=false or run as one process")
        if cfg.hash.pose_opt:
            raise ValueError(f"hash.pose_opt: the pose corrections per image are not summed "
                             f"over MPI ranks yet ({self.comm.Get_size()} ranks); pass --set "
                             f"hash.pose_opt=false or run as one process")

    def rank_config(self, cfg):
        """Every rank holds the whole model: the configuration as it is."""
        return cfg

    def _join(self, model):
        from ..runtime.dataparallel import DataParallel
        model.ranks = DataParallel(self.comm)
        return model

    def create(self, device, cfg, ds, background):
        return self._join(create(device, cfg, ds, background))

    def from_state(self, device, state, cfg):
        return self._join(from_state(device, state, cfg))


KIND = Kind(name="hash", title="multiresolution hash encoding + tiny MLPs",
            config=HashConfig, presets=HASH_PRESETS, scene_presets=SCENE_PRESETS,
            create=create, from_state=from_state, memory=budget.memory, programs=programs,
            distributed=Distributed)
