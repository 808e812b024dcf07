"""Model kinds the trainer and CLI know, and loading a model back from a checkpoint."""
from __future__ import annotations

from ..outputs import checkpoint
from .config import Config, _merge


class GridFactory:
    @staticmethod
    def create(device, cfg, ds, background):
        from ..grid.model import GridModel
        return GridModel.create(device, cfg.grid, ds.bbox, background)

    @staticmethod
    def from_state(device, state, cfg):
        from ..grid.model import GridModel
        return GridModel.from_state_dict(device, state, cfg.grid)


class DistGridFactory:
    """Plenoxels over MPI ranks, one brick each (clrf/grid/dist_model.py)."""

    def __init__(self, comm):
        self.comm = comm
        self.brick = (comm.Get_rank(), comm.Get_size())   # checkpoint.load(brick=...)

    def create(self, device, cfg, ds, background):
        from ..grid.dist_model import DistGridModel
        return DistGridModel.create(device, cfg.grid, ds.bbox, background, self.comm)

    def from_state(self, device, state, cfg):
        from ..grid.dist_model import DistGridModel
        return DistGridModel.from_state_dict(device, state, cfg.grid, self.comm)


class NerfFactory:
    @staticmethod
    def create(device, cfg, ds, background):
        from ..nerf import NerfModel
        return NerfModel(device, cfg.nerf, ds.near, ds.far, background, cfg.train.seed)

    @staticmethod
    def from_state(device, state, cfg):
        from ..nerf import NerfModel
        return NerfModel.from_state_dict(device, state)


class HashFactory:
    @staticmethod
    def create(device, cfg, ds, background):
        from ..hash.model import HashModel, ray_range
        near, far = ray_range(ds)
        return HashModel(device, cfg.hash, near, far, ds.bbox, background, cfg.train.seed)

    @staticmethod
    def from_state(device, state, cfg):
        from ..hash.model import HashModel
        return HashModel.from_state_dict(device, state)


FACTORIES = {"grid": GridFactory, "nerf": NerfFactory, "hash": HashFactory}


def config_from_state(state) -> Config:
    cfg = Config()
    _merge(cfg, state["run_config"], "checkpoint")
    return cfg


def load_model(device, ckpt):
    """(model, state, config) from a run directory or checkpoint file."""
    state = checkpoint.load(ckpt)
    cfg = config_from_state(state)
    kind = state.get("kind", "grid")
    if kind not in FACTORIES:
        raise checkpoint.CheckpointError(f"checkpoint {ckpt}: unknown model kind '{kind}'")
    return FACTORIES[kind].from_state(device, state, cfg), state, cfg
