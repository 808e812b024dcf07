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


KIND = Kind(name="nerf", title="positional encoding and a fused MLP, hierarchical sampling",
            config=NerfConfig, presets=NERF_PRESETS, create=create, from_state=from_state,
            memory=budget.memory, workload=WORKLOAD)
