"""NeRF as the registry lists it (clrf/registry.py): its configuration section and presets,
factories, memory estimate and device workload."""
from __future__ import annotations

from ..interface import Kind
from . import budget
from .config import NERF_PRESETS, NerfConfig
from .workload import WORKLOAD


def create(device, cfg, ds, background):
    from .model import NerfModel
    return NerfModel(device, cfg.nerf, ds.near, ds.unit_far(), background, cfg.train.seed)


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
    mlp.program(device, c.mlp_spec())
    mlp.program(device, mlp.MLPSpec(**workload.SPEC_FIELDS))
    optim.program(device, "adam")


KIND = Kind(name="nerf", title="positional encoding and a fused MLP, hierarchical sampling",
            config=NerfConfig, presets=NERF_PRESETS, create=create, from_state=from_state,
            memory=budget.memory, workload=WORKLOAD, programs=programs)
