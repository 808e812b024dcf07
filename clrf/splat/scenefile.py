"""A splat file as a trained scene: ``clrf render``, ``eval``, ``view`` and ``export`` take
``--ckpt FILE`` where FILE is any splat file clrf reads (files.py: .ply, .spz, .glb, .gltf,
.compressed.ply, .splat), written by clrf or another tool in the 3DGS layout (SH degree 0-3,
extra properties ignored).

``state_from_file`` makes of the file what a checkpoint of a splat run holds: the model's
parameters (zero Adam moments and statistics), a configuration with the file's SH degree, and
the dataset metadata a render needs where no capture says otherwise: a square view of
DEFAULT_SIDE pixels with a DEFAULT_FOV_DEG vertical field of view, a black background, the
box of the Gaussians' means between their FRAME_PERCENTILE and 100 - FRAME_PERCENTILE
percentiles (a few stray far splats do not move the orbit), the scene preset "" (an orbit
about that box). ``--data`` gives test views and their cameras instead (``clrf eval``,
``clrf render --views test``).
"""
from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path

import numpy as np

from .files import format_of, read_splat_file

DEFAULT_SIDE = 512          # pixels of the default view's side
DEFAULT_FOV_DEG = 50.0      # its vertical field of view
FRAME_PERCENTILE = 1.0      # the scene box: the means' 1st to 99th percentiles


def is_scene_file(path) -> bool:
    """Whether ``path`` names an existing splat file (by its ending)."""
    p = Path(path)
    return p.is_file() and format_of(p) is not None


def state_from_file(path) -> dict:
    """A splat run's checkpoint state of the splats in file ``path`` (module doc); a file
    clrf cannot read raises SplatFileError naming it."""
    from .config import SplatConfig
    from .params import NAMES, moment_keys
    from .strategies import make_strategy
    g = read_splat_file(path)
    means = np.asarray(g["means"], np.float64)
    n = int(means.shape[0])
    sh = np.asarray(g["sh"], np.float32)
    degree = int(round(math.sqrt(sh.shape[1]))) - 1
    config = SplatConfig(sh_degree=degree, max_gaussians=max(n, 1))
    if n:
        lo = np.percentile(means, FRAME_PERCENTILE, axis=0)
        hi = np.percentile(means, 100 - FRAME_PERCENTILE, axis=0)
    else:
        lo, hi = -np.ones(3), np.ones(3)
    hi = np.maximum(hi, lo + 1e-6)
    extent = float(np.linalg.norm(hi - lo)) / 2
    f = 0.5 * DEFAULT_SIDE / math.tan(math.radians(DEFAULT_FOV_DEG) / 2)
    state = {"kind": "splat", "config": asdict(config), "background": [0.0, 0.0, 0.0],
             "extent": extent, "bbox": [lo.tolist(), hi.tolist()], "seed": 0,
             "max_count": max(n, 1),
             "step": 0, "active_degree": degree, "progress": 1.0,
             "lr_means": config.lr_position_final * extent,
             "iteration": 0, "seconds": 0.0,
             # what a run's configuration would say (the rest: the defaults)
             "run_config": {"train": {"model": "splat", "data": ""}, "splat": asdict(config)},
             "dataset": {"name": Path(path).name, "H": DEFAULT_SIDE, "W": DEFAULT_SIDE,
                         "intrinsics": [f, f, DEFAULT_SIDE / 2, DEFAULT_SIDE / 2],
                         "background": [0.0, 0.0, 0.0], "ndc": False,
                         "near": 0.01 * extent, "far": 100.0 * extent, "preset": "",
                         "bbox": [lo.tolist(), hi.tolist()], "distortion": None},
             "scene_file": str(path)}
    for k in NAMES:
        state[f"param_{k}"] = np.ascontiguousarray(g[k], np.float32)
        for mk in moment_keys(k):
            state[f"adam_{mk}"] = np.zeros_like(state[f"param_{k}"])
    strategy = make_strategy(config)
    state.update(strategy.state.state_dict())
    state.update({k: np.zeros(n, np.float32) for k in strategy.row_keys()})
    return state
