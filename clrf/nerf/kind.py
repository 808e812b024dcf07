"""NeRF as the registry lists it (clrf/registry.py): its configuration section and presets,
factories, memory estimate and device workload."""
from __future__ import annotations

import numpy as np

from ..corrections.ray_pose import pivot_depth, viewmat_of
from ..interface import Kind
from . import budget
from .config import NERF_PRESETS, NerfConfig
from .workload import WORKLOAD


def create(device, cfg, ds, background):
    from .model import NerfModel
    if cfg.nerf.pose_opt and ds.ndc:
        raise ValueError(f"dataset {ds.name}: nerf.pose_opt corrects the cameras that make the "
                         f"rays, and NDC (forward-facing) rays are not a camera's; pass --set "
                         f"nerf.pose_opt=false")
    model = NerfModel(device, cfg.nerf, ds.near, ds.unit_far(), background, cfg.train.seed)
    # the per-view corrections: a row per training image, in the trainer's ray store's order
    # (the cameras, pivots and extent as the hash grid takes them: clrf/hash/kind.py)
    views = ds.split["train"]
    if cfg.train.max_train_images:
        views = views[:cfg.train.max_train_images]
    poses = np.asarray(ds.poses, np.float64)[views]
    box = np.asarray(ds.bbox, np.float64)
    model.attach_corrections(len(views), int(ds.hw[0]) * int(ds.hw[1]),
                             masked=ds.alpha is not None, extent=float((box[1] - box[0]).max()),
                             viewmats=lambda: np.stack([viewmat_of(p) for p in poses]),
                             pivots=lambda: [pivot_depth(viewmat_of(p), box) for p in poses],
                             bbox=box)
    return model


def from_state(device, state, cfg):
    from .model import NerfModel
    return NerfModel.from_state_dict(device, state)


def programs(device, cfg):
    """Every program a NeRF run of ``cfg`` asks ``device`` for (Kind.programs): the encodings,
    sampling, compositing (forward; backward with the MSE), the fused MLP, Adam and the
    workload's MLP."""
    from ..mlp import mlp
    from ..runtime import optim
    from . import ops, workload
    c = cfg.nerf
    for freqs in (c.pos_freqs, c.dir_freqs):
        ops._encode_prg(device, freqs, c.include_input)
    ops._sample_prg(device)
    for mode in (0, 1):
        ops._composite_prg(device, mode)
    from ..corrections import ray_pose
    ray_pose.program(device)                               # nerf.pose_opt, listed always
    if c.exposure:
        from ..corrections import exposure
        exposure.program(device)                           # clrf/corrections/exposure.py
    mlp.program(device, c.mlp_spec())
    mlp.program(device, mlp.MLPSpec(**workload.SPEC_FIELDS))
    optim.program(device, "adam")


KIND = Kind(name="nerf", title="positional encoding and a fused MLP, hierarchical sampling",
            config=NerfConfig, presets=NERF_PRESETS, create=create, from_state=from_state,
            memory=budget.memory, workload=WORKLOAD, programs=programs)
