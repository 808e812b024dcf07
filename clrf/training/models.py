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
    """(model, state, config) from a run directory or checkpoint file, or a file a model kind
    reads as a trained scene (Kind.scene_file: a splat file)."""
    state = None
    for k in registry.kinds():
        if k.scene_file is not None:
            try:
                state = k.scene_file(ckpt)
            except ValueError as e:
                raise checkpoint.CheckpointError(str(e)) from None
            if state is not None:
                break
    if state is None:
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


def load_data(path, downscale=1, kind=None):
    """The dataset at ``path`` (None or "": the built-in procedural scene), downscaled by an
    integer factor, as model kind ``kind`` (a name; None: as loaded) takes it
    (``dataset_for``)."""
    from ..data import load_dataset
    opts = {"downscale": int(downscale)} if downscale and int(downscale) > 1 else {}
    ds = load_dataset(path or None, **opts)
    return ds if kind is None else dataset_for(kind, ds)


def dataset_for(kind, ds):
    """Dataset ``ds`` as model kind ``kind`` (a name) trains and is evaluated on it: a
    forward-facing capture with world-space cameras for a kind that needs them
    (Kind.world_cameras; clrf/data/world.py), else ``ds`` itself."""
    if ds.ndc and registry.get(kind).world_cameras:
        from ..data.world import world_space
        return world_space(ds)
    return ds


def checkpoint_dataset(state, data_override=None):
    """The dataset of a checkpoint's run (or ``data_override``), loaded at the resolution the
    run trained on, as its model kind takes it."""
    tr = state["run_config"]["train"]
    path = data_override if data_override is not None else tr.get("data", "")
    return load_data(path, tr.get("downscale", 1) if path else 1,
                     str(state.get("kind", registry.DEFAULT)))


def adopt_capture(model, state, ds) -> dict:
    """A splat file read as a scene (``state["scene_file"]``) scored or rendered on capture
    ``ds`` (``--data``): the model renders on the capture's background (an RGBA capture's
    composite, as a run trained on it does) and the views take the capture's resolution and
    intrinsics. Returns the dataset metadata renders use (the checkpoint's own for a run)."""
    if not state.get("scene_file"):
        return state["dataset"]
    from .trainer import dataset_meta
    model.background = tuple(float(b) for b in ds.background)
    return dataset_meta(ds)

