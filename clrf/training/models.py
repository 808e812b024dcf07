"""Loading a model, and the dataset it was trained on, back from a checkpoint; the model kinds
themselves are the registry's (clrf/registry.py)."""
from __future__ import annotations

from .. import registry
from ..interface import StateError
from ..outputs import checkpoint
from .config import Config, _merge


def config_from_state(state) -> Config:
    cfg = Config()
    _merge(cfg, state["run_config"], "checkpoint")
    return cfg


def load_model(device, ckpt):
    """(model, state, config) from a run directory or checkpoint file."""
    state = checkpoint.load(ckpt)
    kind = str(state.get("kind", registry.DEFAULT))
    if kind not in registry.names():
        raise checkpoint.CheckpointError(f"checkpoint {ckpt}: unknown model kind '{kind}'; "
                                         f"this clrf knows {', '.join(registry.names())}")
    cfg = config_from_state(state)
    try:
        model = registry.get(kind).from_state(device, state, cfg)
    except StateError as e:
        raise checkpoint.CheckpointError(f"checkpoint {ckpt}: {e}") from None
    return model, state, cfg


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
