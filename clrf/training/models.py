"""Model kinds the trainer and CLI know (their factories and device-choice workloads), and
loading a model, and the dataset it was trained on, back from a checkpoint."""
from __future__ import annotations

from ..grid.workload import WORKLOAD as GRID_WORKLOAD
from ..nerf.workload import WORKLOAD as NERF_WORKLOAD
from ..outputs import checkpoint
from .config import Config, _merge

# The timed run that picks the default device of each model kind (clrf/runtime/workload.py);
# a kind without one gets the probe's choice.
WORKLOADS = {"grid": GRID_WORKLOAD, "nerf": NERF_WORKLOAD}


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
        from ..grid.dist_model import BrickMismatchError, DistGridModel
        try:
            return DistGridModel.from_state_dict(device, state, cfg.grid, self.comm)
        except BrickMismatchError as e:
            raise checkpoint.CheckpointError(str(e)) from None


class NerfFactory:
    @staticmethod
    def create(device, cfg, ds, background):
        from ..nerf import NerfModel
        from ..data.cameras import ndc_reach    # NDC rays: far along unit directions
        return NerfModel(device, cfg.nerf, ds.near, ndc_reach(ds), background, cfg.train.seed)

    @staticmethod
    def from_state(device, state, cfg):
        from ..nerf import NerfModel
        return NerfModel.from_state_dict(device, state)


class HashFactory:
    @staticmethod
    def create(device, cfg, ds, background):
        from ..hash.model import HashModel, ray_range, resolve_contract, resolve_max_res
        hc = resolve_max_res(resolve_contract(cfg.hash, ds), ds)
        from ..data.cameras import ndc_reach    # NDC rays: far along unit directions
        near, far = ray_range(ds, hc.contract == "on", ndc_reach(ds) if ds.ndc else None)
        return HashModel(device, hc, near, far, ds.bbox, background, cfg.train.seed)

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


def load_data(path, downscale=1):
    """The dataset at ``path`` (None or "": the built-in procedural scene), downscaled by an
    integer factor."""
    from ..data import load_dataset
    opts = {"downscale": int(downscale)} if downscale and int(downscale) > 1 else {}
    return load_dataset(path or None, **opts)


def checkpoint_dataset(state, data_override=None):
    """The dataset of a checkpoint's run (or ``data_override``), loaded at the resolution the
    run trained on."""
    tr = state["run_config"]["train"]
    path = data_override if data_override is not None else tr.get("data", "")
    return load_data(path, tr.get("downscale", 1) if path else 1)
