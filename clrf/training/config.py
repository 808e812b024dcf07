"""Typed, validated configuration: defaults < scene preset < config file < command line.

One dataclass per concern: the run (TrainConfig, here) and one section per model kind, each
beside its model (GridConfig in clrf/grid/config.py, NerfConfig in clrf/nerf/config.py,
HashConfig in clrf/hash/config.py); ``Config`` holds them all. Every field is commented; `validate()` rejects out-of-range values
with a message naming the field. The effective configuration is written next to the outputs
(config.json) and can be fed back with --config.

Schedules are in iterations and were chosen for CPU budgets of minutes (svox2's defaults
assume 100k+ GPU iterations): a coarse grid first, pruned by rendering weight
and upsampled twice within the first few hundred iterations, RMSProp with svox2's rates but
decay horizons of a few thousand iterations.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

from ..grid.config import GridConfig
from ..hash.config import HASH_PRESETS, HashConfig
from ..nerf.config import NERF_PRESETS, NerfConfig

# sections whose 'preset' key replaces the whole section: (preset names, section class)
MODEL_PRESETS = {"nerf": (NERF_PRESETS, NerfConfig), "hash": (HASH_PRESETS, HashConfig)}


class ConfigError(ValueError):
    """An unknown option or an out-of-range value; the message names the field and the fix."""


@dataclass
class TrainConfig:
    model: str = "grid"           # "grid" (Plenoxels), "nerf" or "hash" (hash grid + tiny MLPs)
    data: str = ""                # dataset path; empty: the built-in procedural scene
    preset: str = ""              # scene preset; empty: the dataset's own
    max_seconds: float = 120.0    # wall-clock training budget (evaluation excluded)
    max_iters: int = 100000       # iteration cap
    eval_every: float = 10.0      # seconds of training between evaluations
    eval_views: int = 4           # test views per periodic evaluation (all at the end)
    eval_downscale: int = 1       # periodic evaluations render views downscaled by this factor
                                  # (the final one is full size)
    final_eval: bool = True       # evaluate every test view at the end
    checkpoint_every: float = 60.0  # seconds of training between checkpoints
    seed: int = 0                 # batch sampling and initialisation seed
    background: list = field(default_factory=list)  # override the dataset background [r,g,b]
    downscale: int = 1            # load images downscaled by this integer factor
    max_train_images: int = 0     # train on the first this-many training images; 0: all


PRESETS = {
    # Blender-style synthetic 360: white/black background, no NDC, no background model.
    # The hash grid holds its full learning rate for 65 % of the budget, not 50 %: lego_400,
    # 900 s, one run each on a 2-vCPU Xeon, 200 test views: hold 0.3 31.89 dB, 0.5 31.94 and
    # 31.95 (two runs), 0.65 32.06; the 4 monitored views gained under 0.05 dB in the last
    # 150 s at 0.5 (the rate already below 1e-3) and 0.14 at 0.65.
    "synthetic": {"grid": {}, "hash": {"lr_hold": 0.65}},
    # The built-in procedural scene (the first run, `clrf train`): small images, smaller
    # grids over the whole box (its floor's corners lie outside the inscribed sphere: with the
    # sphere bound the grid could never hold them, 90 % of the error of a run that stalled at
    # 24 dB), learning rates decayed over about the steps of its 60 s so the curve keeps rising
    # as the steps get finer.
    "procedural": {"grid": {"reso": [[48, 48, 48], [96, 96, 96]], "upsample_at": [200],
                            "sh_degree": 2, "batch_size": 4000, "sphere_bound": False,
                            "lr_decay_steps": 2000},
                   "hash": {"preset": "tiny"},
                   "train": {"max_seconds": 60.0, "eval_every": 5.0}},
    # tiny_lego (100x100 images): a 160^3 final grid is as fine as the pixels can resolve.
    "tiny": {"grid": {"reso": [[64, 64, 64], [128, 128, 128]], "upsample_at": [250],
                      "batch_size": 4000},
             "hash": {"preset": "tiny"}},
    # Forward-facing (LLFF): NDC rays, stronger TV, sparsity prior (svox2 llff.json). The
    # resolutions are over the dataset's box, which in x, y is as wide as every view's frustum
    # (fern: 1.45 x 1.31 NDC units a side; clrf.data.llff.scene_extent).
    # The z-resolution stays fixed (as in svox2's LLFF schedule): NDC rays run along z, so the
    # samples per ray, and with them the cost of a step, stay those of the coarse stage. No
    # dilation at pruning: the density is scattered through the frustum at the upsample, so a
    # dilated mask covers nearly all of it, while resampling already keeps the new voxels that
    # interpolate a kept one. Periodic evaluations on 1/4-size views.
    "forward_facing": {"grid": {"reso": [[128, 128, 64], [256, 256, 64]], "upsample_at": [500],
                                "sphere_bound": False, "lambda_tv": 5e-4,
                                "lambda_tv_sh": 5e-3, "tv_early_only": False,
                                "lambda_sparsity": 1e-10, "prune_dilate": False},
                       # the hash grid's finest level at about two cells per pixel of the
                       # box's width (NDC: the frustum), not 2048: with 17-20 views the finer
                       # levels only fit the training views (fern, 900 s: 25.04 dB against
                       # 24.80 with 2048, one run each, Xeon)
                       "hash": {"max_res": 1024},
                       "train": {"eval_downscale": 4}},
    # Unbounded real 360: no sphere bound, sparsity prior, and an MSI background behind the
    # grid box (32 spheres of 128 x 256 texels from the box's circumscribed sphere outwards;
    # svox2's 360 configs use 64 layers at a finer resolution for 100k+ GPU iterations).
    "real360": {"grid": {"sphere_bound": False, "lambda_tv": 5e-5, "lambda_tv_sh": 5e-3,
                         "tv_early_only": False, "lambda_sparsity": 1e-10,
                         "lambda_beta": 1e-5, "background_layers": 32,
                         "background_height": 128}},
}
# Unbounded real 360 whose box is meant to hold the whole scene (instant-ngp captures: the
# aabb_scale cube; instant-ngp itself has no background model): real360 without the MSI, which
# there only slowed the step and cost accuracy (fox, 30 minutes: 24.93 dB without, 23.20 with).
PRESETS["real360_box"] = {"grid": dict(PRESETS["real360"]["grid"], background_layers=0)}


@dataclass
class Config:
    grid: GridConfig = field(default_factory=GridConfig)   # Plenoxels grid options (train.model grid)
    train: TrainConfig = field(default_factory=TrainConfig)   # the run: data, budget, evaluation
    nerf: NerfConfig = field(default_factory=NerfConfig)   # NeRF options (train.model nerf)
    hash: HashConfig = field(default_factory=HashConfig)   # hash-grid options (train.model hash)

    def to_dict(self):
        return {"grid": dataclasses.asdict(self.grid), "train": dataclasses.asdict(self.train),
                "nerf": dataclasses.asdict(self.nerf), "hash": dataclasses.asdict(self.hash)}

    def validate(self):
        g, t = self.grid, self.train
        checks = [
            (t.model in ("grid", "nerf", "hash"), "train.model",
             "must be 'grid', 'nerf' or 'hash'"),
            (not t.preset or t.preset in PRESETS, "train.preset", f"must be one of {sorted(PRESETS)}"),
            (t.max_seconds > 0, "train.max_seconds", "must be > 0"),
            (t.max_iters > 0, "train.max_iters", "must be > 0"),
            (t.eval_every > 0, "train.eval_every", "must be > 0"),
            (t.eval_views >= 1, "train.eval_views", "must be >= 1"),
            (t.eval_downscale >= 1, "train.eval_downscale", "must be an integer >= 1"),
            (t.checkpoint_every > 0, "train.checkpoint_every", "must be > 0"),
            (t.downscale >= 1, "train.downscale", "must be an integer >= 1"),
            (t.max_train_images >= 0, "train.max_train_images", "must be >= 0"),
            (len(t.background) in (0, 3) and all(0 <= b <= 1 for b in t.background),
             "train.background", "must be empty or three values in [0, 1]"),
            (isinstance(g.reso, list) and len(g.reso) >= 1
             and all(isinstance(r, list) and len(r) == 3 and all(isinstance(v, int) and 1 <= v <= 1024 for v in r)
                     for r in g.reso), "grid.reso", "must be a list of [x, y, z] integer resolutions in 1..1024"),
            (isinstance(g.upsample_at, list) and len(g.upsample_at) == len(g.reso) - 1
             and all(isinstance(v, int) and v > 0 for v in g.upsample_at)
             and g.upsample_at == sorted(g.upsample_at), "grid.upsample_at",
             "must list one increasing iteration per resolution after the first"),
            (g.sh_degree in (0, 1, 2, 3), "grid.sh_degree", "must be 0, 1, 2 or 3"),
            (0 < g.step <= 4, "grid.step", "must be in (0, 4] voxels"),
            (g.init_density >= 0, "grid.init_density", "must be >= 0"),
            (1 <= g.batch_size <= 1 << 22, "grid.batch_size", "must be in 1..4194304"),
            (g.optimizer in ("rmsprop", "sgd"), "grid.optimizer", "must be 'rmsprop' or 'sgd'"),
            (0 <= g.rms_beta < 1, "grid.rms_beta", "must be in [0, 1)"),
            (g.lr_density > 0 and g.lr_density_final > 0, "grid.lr_density", "must be > 0"),
            (g.lr_sh > 0 and g.lr_sh_final > 0, "grid.lr_sh", "must be > 0"),
            (g.lr_decay_steps > 0, "grid.lr_decay_steps", "must be > 0"),
            (g.lr_density_delay_steps >= 0, "grid.lr_density_delay_steps", "must be >= 0"),
            (0 < g.lr_density_delay_mult <= 1, "grid.lr_density_delay_mult", "must be in (0, 1]"),
            (g.lambda_tv >= 0 and g.lambda_tv_sh >= 0 and g.lambda_sparsity >= 0
             and g.lambda_beta >= 0,
             "grid.lambda_*", "regulariser weights must be >= 0"),
            (0 < g.tv_fraction <= 1, "grid.tv_fraction", "must be in (0, 1]"),
            (g.weight_thresh >= 0, "grid.weight_thresh", "must be >= 0"),
            (g.prune_rays >= 1, "grid.prune_rays", "must be >= 1"),
            (g.background_layers == 0 or 2 <= g.background_layers <= 256,
             "grid.background_layers", "must be 0 (off) or in 2..256 (samples lie between "
             "consecutive spheres)"),
            (1 <= g.background_height <= 4096, "grid.background_height", "must be in 1..4096"),
            (g.background_init_density >= 0, "grid.background_init_density", "must be >= 0"),
            (abs(g.background_init_color) <= 1e3, "grid.background_init_color",
             "must be a finite colour offset (|x| <= 1000)"),
            (g.lr_bg_density > 0 and g.lr_bg_density_final > 0, "grid.lr_bg_density",
             "must be > 0 (with lr_bg_density_final)"),
            (g.lr_bg_color > 0 and g.lr_bg_color_final > 0, "grid.lr_bg_color",
             "must be > 0 (with lr_bg_color_final)"),
        ] + self.nerf.checks() + self.hash.checks()
        for ok, name, msg in checks:
            if not ok:
                value = _get(self, name)
                raise ConfigError(f"{name} = {value!r}: {msg}")
        return self


def _get(cfg, dotted):
    sect, _, key = dotted.partition(".")
    obj = getattr(cfg, sect, None)
    if key.endswith("*"):
        return "..."
    return getattr(obj, key, None) if not isinstance(obj, dict) else obj.get(key)


def _merge(cfg: Config, d: dict, source: str):
    for sect, vals in d.items():
        if sect not in ("grid", "train", "nerf", "hash"):
            raise ConfigError(f"{source}: unknown section '{sect}'; use grid, train, nerf or "
                              f"hash")
        if not isinstance(vals, dict):
            raise ConfigError(f"{source}: '{sect}' must be an object of options, got {vals!r}")
        if sect in MODEL_PRESETS and "preset" in vals:
            presets, section_cls = MODEL_PRESETS[sect]
            vals = dict(vals)
            name = vals.pop("preset")
            if name not in presets:
                raise ConfigError(f"{source}: {sect}.preset = {name!r}: use one of "
                                  f"{', '.join(sorted(presets))}")
            setattr(cfg, sect, section_cls.from_preset(name))
        setattr(cfg, sect, dataclasses.replace(getattr(cfg, sect),
                                               **_typed(getattr(cfg, sect), sect, vals, source)))


def _typed(obj, sect: str, vals: dict, source: str) -> dict:
    """``vals`` checked against the fields of dataclass ``obj``: known names, and each value of
    its field's type (an integral float is taken as an int; ``int | None`` fields take null)."""
    names = {f.name: f for f in dataclasses.fields(obj)}
    out = {}
    for k, v in vals.items():
        if k not in names:
            raise ConfigError(f"{source}: unknown option '{sect}.{k}'; use one of "
                              f"{', '.join(sorted(names))}")
        cur = getattr(obj, k)
        optional = "None" in str(names[k].type)
        if v is None and optional:
            pass
        elif isinstance(cur, bool):
            if not isinstance(v, bool):
                raise ConfigError(f"{source}: {sect}.{k} must be true or false, got {v!r}")
        elif isinstance(cur, int) or (cur is None and "int" in str(names[k].type)):
            if isinstance(v, bool) or not isinstance(v, int):
                if isinstance(v, float) and v.is_integer():
                    v = int(v)
                else:
                    raise ConfigError(f"{source}: {sect}.{k} must be an integer"
                                      f"{' or null' if optional else ''}, got {v!r}")
        elif isinstance(cur, float):
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                raise ConfigError(f"{source}: {sect}.{k} must be a number, got {v!r}")
            v = float(v)
        elif isinstance(cur, list):
            if not isinstance(v, list):
                raise ConfigError(f"{source}: {sect}.{k} must be a list, got {v!r}")
        elif isinstance(cur, str) and not isinstance(v, str):
            raise ConfigError(f"{source}: {sect}.{k} must be a string, got {v!r}")
        out[k] = v
    return out


def load_config_file(path) -> dict:
    p = Path(path)
    if not p.is_file():
        raise ConfigError(f"config file {p} not found: pass an existing JSON file to --config")
    try:
        d = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ConfigError(f"config file {p}: invalid JSON at line {e.lineno} column {e.colno}: "
                          f"{e.msg}; fix the file (check it with python -m json.tool)") from None
    if not isinstance(d, dict):
        raise ConfigError(f"config file {p}: expected a JSON object with sections "
                          f"grid/train/nerf/hash")
    return d


def build_config(preset: str = "", file: str | None = None, overrides: dict | None = None,
                 dataset_preset: str = "synthetic") -> Config:
    """Defaults < preset (explicit, else the dataset's) < config file < overrides."""
    cfg = Config()
    file_d = load_config_file(file) if file else {}
    name = preset or file_d.get("train", {}).get("preset", "") or dataset_preset
    if name not in PRESETS:
        raise ConfigError(f"train.preset = {name!r}: must be one of {sorted(PRESETS)}")
    _merge(cfg, PRESETS[name], f"preset '{name}'")
    if file_d:
        _merge(cfg, file_d, f"config file {file}")
    if overrides:
        _merge(cfg, overrides, "command line")
    cfg.train.preset = name
    return cfg.validate()
