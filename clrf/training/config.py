"""Typed, validated configuration: defaults < scene preset < config file < command line.

One dataclass per concern. Every field is commented; `validate()` rejects out-of-range values
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
import math
from dataclasses import dataclass, field
from pathlib import Path


class ConfigError(ValueError):
    """An unknown option or an out-of-range value; the message names the field and the fix."""


@dataclass
class GridConfig:
    reso: list = field(default_factory=lambda: [[64, 64, 64], [128, 128, 128], [256, 256, 256]])
    # ^ grid resolutions, coarse to fine; the run moves to the next at each upsample_at entry
    upsample_at: list = field(default_factory=lambda: [300, 1200])
    # ^ iterations at which to prune (by rendering weight) and upsample to the next resolution
    sh_degree: int = 2            # SH degree of colour (0: diffuse .. 3)
    step: float = 0.5             # ray-march step in voxels
    init_density: float = 0.1     # initial density of every voxel of the first grid
    sphere_bound: bool = True     # start with voxels inside the bbox's inscribed sphere only
    batch_size: int = 5000        # rays per step
    optimizer: str = "rmsprop"    # "rmsprop" (svox2) or "sgd"
    rms_beta: float = 0.95        # RMSProp decay
    lr_density: float = 30.0      # density learning rate (svox2: 3e1)
    lr_density_final: float = 0.05  # density learning rate at lr_decay_steps (svox2: 5e-2)
    lr_density_delay_steps: int = 100   # reverse-cosine warm-up of the density lr
    lr_density_delay_mult: float = 0.01  # warm-up starts at this fraction of lr_density
    lr_sh: float = 1e-2           # SH learning rate (svox2: 1e-2)
    lr_sh_final: float = 5e-6     # SH learning rate at lr_decay_steps (svox2: 5e-6)
    lr_decay_steps: int = 20000   # horizon of the log-linear decay
    lambda_tv: float = 1e-5       # TV weight on density (svox2 syn: 1e-5)
    lambda_tv_sh: float = 1e-3    # TV weight on SH (svox2 syn: 1e-3)
    tv_fraction: float = 0.01     # fraction of cells regularised per step (one contiguous window)
    tv_early_only: bool = True    # stop TV after the first upsample (svox2 syn)
    lambda_sparsity: float = 0.0  # Cauchy sparsity prior on density (svox2 llff: 1e-12 scale)
    lambda_beta: float = 0.0      # beta prior on each ray's transmittance (svox2 tnt: 1e-5),
                                  # averaged over the batch: rays end clear or opaque
    weight_thresh: float = 0.256  # prune rows whose max weight < weight_thresh / new z-reso
    prune_dilate: bool = True     # also keep every row within one voxel of a kept one
    prune_rays: int = 1 << 20     # training rays (evenly strided) used to find pruning weights
    background_layers: int = 0    # MSI background behind the grid (unbounded scenes): number of
                                  # spheres, >= 2; 0: off, a constant background colour only
    background_height: int = 128  # rows (latitude) of each MSI sphere image; columns = 2 x rows
    background_init_density: float = 0.1  # initial raw density of every MSI texel (svox2: 0.1)
    background_init_color: float = 0.0    # initial raw MSI colour (0: grey 0.5)
    lr_bg_density: float = 3.0    # MSI density learning rate (svox2: 3e0 -> 3e-3), decayed
                                  # log-linearly over lr_decay_steps like the grid's
    lr_bg_density_final: float = 3e-3     # MSI density learning rate at lr_decay_steps
    lr_bg_color: float = 0.1      # MSI colour learning rate (svox2: 1e-1 -> 5e-6)
    lr_bg_color_final: float = 5e-6       # MSI colour learning rate at lr_decay_steps


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


@dataclass(frozen=True)
class NerfConfig:
    """Everything that defines a NeRF model and its optimiser. The defaults are the ``tiny``
    preset; ``NerfConfig.from_preset`` gives the others. In a run configuration the ``nerf``
    section holds these fields; setting ``nerf.preset`` resets every field to that preset's
    values before the section's other options apply."""

    preset: str = "tiny"            # the preset these values start from: "tiny" | "original"
    width: int = 64                 # trunk width (multiple of 16); NeRF: 256
    depth: int = 4                  # trunk layers; NeRF: 8
    skip: int = -1                  # encoded position re-enters at layer skip+1; NeRF: 4; -1 none
    color_width: int = 32           # view-dependent colour layer (multiple of 16); NeRF: 128
    pos_freqs: int = 8              # position frequencies L; NeRF: 10
    dir_freqs: int = 2              # view-direction frequencies; NeRF: 4
    include_input: bool = True      # encoding starts with the scaled input itself (NeRF: yes)
    pos_scale: float = 1.0 / math.pi  # gamma(p) uses sin(2^k pi s p): 1/pi: NeRF's 2^k rad/unit
    dir_scale: float = 1.0 / math.pi  # the same for the unit view direction
    hidden_act: str = "relu"        # "relu" | "softplus"
    sigma_act: str = "softplus"     # "relu" (NeRF) | "softplus" (never dead at initialisation)
    n_coarse: int = 32              # stratified samples per ray; NeRF: 64
    n_fine: int = 32                # importance samples per ray (0: coarse only); NeRF: 128
    shared_net: bool = False        # True: one network evaluated on both sample sets
    perturb: bool = True            # jitter samples during training (never when rendering)
    coarse_loss_weight: float = 1.0  # weight of the coarse MSE in the loss (NeRF: 1)
    lr: float = 3e-3                # Adam learning rate at step 0; NeRF: 5e-4
    lr_decay_steps: int = 6000      # lr = lr * 0.1^(step / lr_decay_steps); NeRF: 500k (Blender)
    beta1: float = 0.9              # Adam beta1
    beta2: float = 0.999            # Adam beta2
    adam_eps: float = 1e-7          # Adam epsilon (NeRF used TF's 1e-7)
    batch_rays: int = 1024          # rays per training step
    mlp_rows: int | None = None     # samples per work-item in the fused MLP; None (null): per
                                    # device
    dw_chunk: int | None = None     # rows per partial weight gradient; None (null): 64 tiles

    @staticmethod
    def from_preset(name: str, **overrides) -> "NerfConfig":
        """``"tiny"`` (the defaults): CPU-friendly 4 x 64, 32 + 32 samples, for 100 x 100
        scenes such as tiny_lego; ``"original"``: NeRF's 8 x 256 with a skip at layer 4, 10/4
        frequencies, a 128-wide colour layer, 64 + 128 samples."""
        if name not in NERF_PRESETS:
            raise ValueError(f"unknown NeRF preset {name!r}; use one of {sorted(NERF_PRESETS)}")
        return dataclasses.replace(NerfConfig(preset=name, **NERF_PRESETS[name]), **overrides)

    @staticmethod
    def from_dict(d: dict) -> "NerfConfig":
        """From ``dataclasses.asdict`` output (a checkpoint's); unknown fields are an error."""
        names = {f.name for f in dataclasses.fields(NerfConfig)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"NerfConfig: unknown fields {sorted(unknown)}")
        return NerfConfig(**d)

    def mlp_spec(self):
        """The fused MLP's shape (clrf.nerf.mlp.MLPSpec) for this configuration."""
        from ..nerf import ops
        from ..nerf.mlp import MLPSpec
        return MLPSpec(width=self.width, depth=self.depth, skip=self.skip,
                       color_width=self.color_width,
                       in_dim=ops.enc_dim(self.pos_freqs, self.include_input),
                       dir_dim=ops.enc_dim(self.dir_freqs, self.include_input),
                       hidden_act=self.hidden_act, sigma_act=self.sigma_act,
                       rows=self.mlp_rows, dw_chunk=self.dw_chunk)

    def checks(self):
        """(ok, field, message) for Config.validate: the ranges the kernels accept."""
        acts = ("relu", "softplus")
        return [
            (self.preset in NERF_PRESETS, "nerf.preset", f"must be one of {sorted(NERF_PRESETS)}"),
            (self.width % 16 == 0 and 16 <= self.width <= 1024, "nerf.width",
             "must be a multiple of 16 in 16..1024"),
            (1 <= self.depth <= 32, "nerf.depth", "must be in 1..32"),
            (self.skip == -1 or 0 <= self.skip <= self.depth - 2, "nerf.skip",
             "must be -1 (none) or in 0..depth-2"),
            (self.color_width % 16 == 0 and 16 <= self.color_width <= 1024, "nerf.color_width",
             "must be a multiple of 16 in 16..1024"),
            (0 <= self.pos_freqs <= 16 and (self.pos_freqs > 0 or self.include_input),
             "nerf.pos_freqs", "must be in 0..16 (0 only with include_input)"),
            (0 <= self.dir_freqs <= 16 and (self.dir_freqs > 0 or self.include_input),
             "nerf.dir_freqs", "must be in 0..16 (0 only with include_input)"),
            (0 < self.pos_scale < 1e6, "nerf.pos_scale", "must be in (0, 1e6)"),
            (0 < self.dir_scale < 1e6, "nerf.dir_scale", "must be in (0, 1e6)"),
            (self.hidden_act in acts, "nerf.hidden_act", "must be 'relu' or 'softplus'"),
            (self.sigma_act in acts, "nerf.sigma_act", "must be 'relu' or 'softplus'"),
            (1 <= self.n_coarse <= 1024, "nerf.n_coarse", "must be in 1..1024"),
            (0 <= self.n_fine <= 1024, "nerf.n_fine", "must be in 0..1024"),
            (0 <= self.coarse_loss_weight <= 1e3, "nerf.coarse_loss_weight",
             "must be in [0, 1000]"),
            (0 < self.lr <= 1, "nerf.lr", "must be in (0, 1]"),
            (self.lr_decay_steps >= 1, "nerf.lr_decay_steps", "must be >= 1"),
            (0 <= self.beta1 < 1 and 0 <= self.beta2 < 1, "nerf.beta1",
             "Adam's beta1 and beta2 must be in [0, 1)"),
            (0 < self.adam_eps <= 1, "nerf.adam_eps", "must be in (0, 1]"),
            (1 <= self.batch_rays <= 1 << 22, "nerf.batch_rays", "must be in 1..4194304"),
            (self.mlp_rows in (None, *MLP_ROWS), "nerf.mlp_rows",
             f"must be null (per device) or one of {', '.join(map(str, MLP_ROWS))}"),
            (self.dw_chunk is None or 1 <= self.dw_chunk <= 1 << 20, "nerf.dw_chunk",
             "must be null (per device) or in 1..1048576"),
        ]


# Field values of each NeRF preset (the rest are NerfConfig's defaults).
NERF_PRESETS = {
    "tiny": {},
    "original": {"width": 256, "depth": 8, "skip": 4, "color_width": 128, "pos_freqs": 10,
                 "dir_freqs": 4, "sigma_act": "relu", "n_coarse": 64, "n_fine": 128,
                 "lr": 5e-4, "lr_decay_steps": 500_000},
}
MLP_ROWS = (1, 2, 3, 4, 5, 6, 8, 12, 16)   # the register-tile heights cl/mlp.cl accepts


@dataclass(frozen=True)
class HashConfig:
    """Everything that defines a hash-grid model (train.model hash) and its optimiser. The
    defaults are the ``full`` preset (the published sizes); ``HashConfig.from_preset("tiny")``
    is for small scenes (tiny_lego, the procedural scene). In a run configuration the ``hash``
    section holds these fields; ``hash.preset`` resets every field to that preset first."""

    preset: str = "full"            # the preset these values start from: "full" | "tiny"
    levels: int = 16                # L: resolution levels of the encoding (published: 16)
    features: int = 2               # F: features per level, 1, 2 or 4 (published: 2)
    log2_table: int = 19            # log2 T: table rows per level (published: 19)
    min_res: int = 16               # N_min: coarsest level's cells per box side (published: 16)
    max_res: int = 2048             # N_max: finest level's cells per box side (published:
    #                                 2048 x the box size in units of the unit cube)
    width: int = 64                 # density MLP hidden width (multiple of 16; published: 64)
    geo_features: int = 16          # density MLP feature outputs fed to the colour MLP besides
    #                                 sigma (multiple of 16; published: 15)
    color_width: int = 64           # colour MLP hidden width (multiple of 16; published: 64)
    color_depth: int = 2            # colour MLP hidden layers (published: 2)
    density_act: str = "trunc_exp"  # "trunc_exp": exp(min(x, 15)), whose gradient does not
    #                                 vanish (published: exp); "softplus": slower to sharpen
    samples: int = 256              # stratified samples per ray over [near, far]; only those
    #                                 in occupied cells are evaluated
    perturb: bool = True            # jitter samples during training (never when rendering)
    occ_res: int = 128              # occupancy grid cells per box side
    occ_every: int = 16             # iterations between occupancy updates
    occ_points: int = 131072        # cells measured (one random point each) per update
    occ_decay: float = 0.95         # measured cells' density estimate decays by this per update
    occ_tau: float = 1e-3           # a cell is empty when its density times the sample spacing
    #                                 (far - near) / samples stays below this optical depth
    occ_warmup: int = 256           # no occupancy updates (all cells occupied) before this step
    lr: float = 1e-2                # Adam learning rate at step 0 (published: 1e-2)
    lr_decay_steps: int = 20000     # lr = lr * 0.1^(step / lr_decay_steps)
    beta1: float = 0.9              # Adam beta1 (published: 0.9)
    beta2: float = 0.99             # Adam beta2 (published: 0.99)
    adam_eps: float = 1e-15         # Adam epsilon (published: 1e-15; table entries that see
    #                                 tiny gradients still move)
    weight_decay: float = 1e-6      # L2 weight decay on the MLP parameters only (not tables)
    batch_rays: int = 4096          # rays per training step
    mlp_rows: int | None = None     # samples per work-item in the fused MLP; None: per device

    @staticmethod
    def from_preset(name: str, **overrides) -> "HashConfig":
        """``"full"`` (the defaults) or ``"tiny"``: T = 2^16, N_max 512, 128 samples, a 64^3
        occupancy grid updated every 8 steps from step 32, 1024 rays per step (100 x 100
        scenes on a CPU)."""
        if name not in HASH_PRESETS:
            raise ValueError(f"unknown hash preset {name!r}; use one of {sorted(HASH_PRESETS)}")
        return dataclasses.replace(HashConfig(preset=name, **HASH_PRESETS[name]), **overrides)

    @staticmethod
    def from_dict(d: dict) -> "HashConfig":
        """From ``dataclasses.asdict`` output (a checkpoint's); unknown fields are an error."""
        names = {f.name for f in dataclasses.fields(HashConfig)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"HashConfig: unknown fields {sorted(unknown)}")
        return HashConfig(**d)

    def checks(self):
        """(ok, field, message) for Config.validate: the ranges the kernels accept."""
        return [
            (self.preset in HASH_PRESETS, "hash.preset", f"must be one of {sorted(HASH_PRESETS)}"),
            (1 <= self.levels <= 64, "hash.levels", "must be in 1..64"),
            (self.features in (1, 2, 4), "hash.features", "must be 1, 2 or 4"),
            (self.levels * self.features <= 256, "hash.levels",
             "levels * features must be <= 256 (the MLP input)"),
            (1 <= self.log2_table <= 24, "hash.log2_table", "must be in 1..24"),
            (1 <= self.min_res <= self.max_res <= 1 << 20, "hash.min_res",
             "need 1 <= min_res <= max_res <= 1048576"),
            (self.width % 16 == 0 and 16 <= self.width <= 1024, "hash.width",
             "must be a multiple of 16 in 16..1024"),
            (self.color_width % 16 == 0 and 16 <= self.color_width <= 1024, "hash.color_width",
             "must be a multiple of 16 in 16..1024"),
            (self.geo_features % 16 == 0 and 16 <= self.geo_features <= 1024,
             "hash.geo_features", "must be a multiple of 16 in 16..1024"),
            (1 <= self.color_depth <= 8, "hash.color_depth", "must be in 1..8"),
            (self.density_act in ("trunc_exp", "softplus"), "hash.density_act",
             "must be 'trunc_exp' or 'softplus'"),
            (1 <= self.samples <= 4096, "hash.samples", "must be in 1..4096"),
            (1 <= self.occ_res <= 256, "hash.occ_res", "must be in 1..256"),
            (self.occ_every >= 1, "hash.occ_every", "must be >= 1"),
            (0 <= self.occ_points <= 1 << 24, "hash.occ_points", "must be in 0..16777216"),
            (0 < self.occ_decay <= 1, "hash.occ_decay", "must be in (0, 1]"),
            (self.occ_tau >= 0, "hash.occ_tau", "must be >= 0"),
            (self.occ_warmup >= 0, "hash.occ_warmup", "must be >= 0"),
            (0 < self.lr <= 1, "hash.lr", "must be in (0, 1]"),
            (self.lr_decay_steps >= 1, "hash.lr_decay_steps", "must be >= 1"),
            (0 <= self.beta1 < 1 and 0 <= self.beta2 < 1, "hash.beta1",
             "Adam's beta1 and beta2 must be in [0, 1)"),
            (0 < self.adam_eps <= 1, "hash.adam_eps", "must be in (0, 1]"),
            (self.weight_decay >= 0, "hash.weight_decay", "must be >= 0"),
            (1 <= self.batch_rays <= 1 << 22, "hash.batch_rays", "must be in 1..4194304"),
            (self.mlp_rows in (None, *MLP_ROWS), "hash.mlp_rows",
             f"must be null (per device) or one of {', '.join(map(str, MLP_ROWS))}"),
        ]


# Field values of each hash preset (the rest are HashConfig's defaults).
HASH_PRESETS = {
    "full": {},
    # small scenes train for hundreds, not tens of thousands, of steps: the occupancy grid
    # starts pruning after 32 and is refreshed every 8
    "tiny": {"log2_table": 16, "max_res": 512, "samples": 128, "occ_res": 64,
             "occ_points": 32768, "occ_warmup": 32, "occ_every": 8, "batch_rays": 1024},
}


PRESETS = {
    # Blender-style synthetic 360: white/black background, no NDC, no background model.
    "synthetic": {"grid": {}},
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
        if sect == "nerf" and "preset" in vals:
            vals = dict(vals)
            name = vals.pop("preset")
            if name not in NERF_PRESETS:
                raise ConfigError(f"{source}: nerf.preset = {name!r}: use one of "
                                  f"{', '.join(sorted(NERF_PRESETS))}")
            cfg.nerf = NerfConfig.from_preset(name)
        if sect == "hash" and "preset" in vals:
            vals = dict(vals)
            name = vals.pop("preset")
            if name not in HASH_PRESETS:
                raise ConfigError(f"{source}: hash.preset = {name!r}: use one of "
                                  f"{', '.join(sorted(HASH_PRESETS))}")
            cfg.hash = HashConfig.from_preset(name)
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
