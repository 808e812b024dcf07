"""Gaussian splatting as the registry lists it (clrf/registry.py): its configuration section,
presets and settings per scene preset, factories, memory estimate and its own export (the
Gaussians as a 3DGS PLY). It trains on whole views (Kind.batches "views")."""
from __future__ import annotations

from ..interface import Export, Kind
from . import budget
from .config import SPLAT_PRESETS, SplatConfig

SCENE_PRESETS = {
    "procedural": {"preset": "tiny"},
    "tiny": {"preset": "tiny"},
}


def create(device, cfg, ds, background):
    from .model import create_model
    return create_model(device, cfg, ds, background)


def check(cfg, ds, caps):
    from .model import check_inputs
    check_inputs(cfg, ds, caps)


def from_state(device, state, cfg):
    from .model import model_from_state
    return model_from_state(device, state, cfg)


def write_splats(model, path):
    from .model import write_splats as write
    return write(model, path)


SPLATS = Export(help="3D Gaussian splats in the standard 3DGS PLY layout (x, y, z, nx, ny, nz, "
                     "f_dc_0..2, f_rest_*, opacity, scale_0..2, rot_0..3)",
                suffix=".ply", write=write_splats)

KIND = Kind(name="splat", title="3D Gaussian splatting (tile rasteriser, whole views)",
            config=SplatConfig, presets=SPLAT_PRESETS, scene_presets=SCENE_PRESETS,
            create=create, from_state=from_state, memory=budget.memory,
            exports={"splats": SPLATS}, batches="views", check=check)
