"""HashConfig: the options of a hash-grid model and its optimiser (the ``hash`` section of a run
configuration, clrf/training/config.py), its presets and the ranges the kernels accept."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..corrections.settings import ray_correction_checks
from ..mlp.tiling import MLP_ROWS


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
    max_res: int = 0                # N_max: finest level's cells per box side; 0: "auto", the
    #                                 published 2048 for 800-pixel-wide images, in proportion
    #                                 to the training images' width on object-centric scenes
    #                                 (resolve_max_res; 1024 for 400-pixel views), else 2048
    width: int = 64                 # density MLP hidden width (multiple of 16; published: 64)
    geo_features: int = 16          # density MLP feature outputs fed to the colour MLP besides
    #                                 sigma (multiple of 16; published: 15)
    color_width: int = 64           # colour MLP hidden width (multiple of 16; published: 64)
    color_depth: int = 2            # colour MLP hidden layers (published: 2)
    density_act: str = "trunc_exp"  # "trunc_exp": exp(min(x, 15)), whose gradient does not
    #                                 vanish (published: exp); "softplus": slower to sharpen
    samples: int = 256              # stratified samples per ray over [near, far]; only those
    #                                 in occupied cells are evaluated
    contract: str = "auto"          # "on": unbounded scene, contracted about the dataset's box
    #                                 (all of space in the encoding, samples even in log t out to
    #                                 1000 box half-sizes); "off": the box only; "auto": on for
    #                                 unbounded 360 captures (the real360 scene preset)
    render_oversample: int = 2      # renders march this many times `samples` bins: training's
    #                                 jittered bins estimate the continuous integral, which a
    #                                 render's fixed bin centres approximate better with more
    #                                 (lego_400, 900 s model, 10 views: 31.52 dB at 1x,
    #                                 31.89 at 2x)
    random_background: bool = True  # RGBA captures: train each step on a random background
    #                                 colour (the images recomposited on it), so that empty
    #                                 space must be transparent, not the background's colour
    perturb: bool = True            # jitter samples during training (never when rendering)
    train_t_stop: float = 1e-4      # a training step differentiates each ray only in front of
    #                                 its first point of transmittance below this (their
    #                                 gradients are below it; about 40 % of lego's samples lie
    #                                 behind); 0: every sample (a render stops at 1e-4 too)
    occ_res: int = 128              # occupancy grid cells per box side
    occ_every: int = 16             # iterations between occupancy updates
    occ_points: int = 131072        # cells measured (one random point each) per update
    occ_decay: float = 0.95         # measured cells' density estimate decays by this per update
    occ_tau: float = 1e-3           # a cell is empty when its density times the sample spacing
    #                                 (far - near) / samples stays below this optical depth
    occ_warmup: int = 256           # no occupancy updates (all cells occupied) before this step
    lr: float = 1e-2                # Adam learning rate at step 0 (published: 1e-2)
    lr_decay_steps: int = 20000     # lr_schedule "steps": lr = lr * 0.1^(step / lr_decay_steps)
    lr_schedule: str = "budget"     # "budget": lr until lr_hold of the run's budget (the larger
    #                                 of its seconds and iterations fractions) is spent, then an
    #                                 exponential fall to lr * lr_final at its end (a run of any
    #                                 length ends annealed); "steps": the fall over lr_decay_steps
    lr_hold: float = 0.5            # fraction of the budget trained at the full lr ("budget")
    lr_final: float = 0.03          # lr at the end of the budget over lr ("budget")
    beta1: float = 0.9              # Adam beta1 (published: 0.9)
    beta2: float = 0.99             # Adam beta2 (published: 0.99)
    adam_eps: float = 1e-15         # Adam epsilon (published: 1e-15; table entries that see
    #                                 tiny gradients still move)
    weight_decay: float = 1e-6      # L2 weight decay on the MLP parameters only (not tables)
    batch_rays: int = 4096          # rays per training step when batch_samples is 0
    batch_samples: int = 131072     # > 0: the rays per step adapt so that a step's live samples
    #                                 come near this (published: 2^18; on two CPU cores 2^17
    #                                 gave lego_400 0.76 dB more in 300 s): batch_samples / samples
    #                                 rays while every bin is live, more once the occupancy grid
    #                                 prunes; 0: always batch_rays
    mlp_rows: int | None = None     # samples per work-item in the fused MLP; None: per device
    exposure: bool = False          # learn a colour transform (3 x 3 matrix and offset) per
    #                                 training image, for captures whose exposure or white
    #                                 balance changes (phones); test views are scored under
    #                                 the identity (clrf/corrections/exposure.py)
    lr_exposure: float = 1e-3       # Adam learning rate of the transforms (every image with
    #                                 rays in a batch steps: each step, on a full batch)
    lr_exposure_final: float = 0.0  # ... falling log-linearly to this over the budget
    #                                 (0: a constant rate)
    exposure_reg: float = 1e-3      # pull of each transform toward the identity, reg
    #                                 (|A - I|^2 + |b|^2) weighted by the image's share of the batch
    exposure_matrix: str = "full"   # "full": A a 3 x 3 matrix (channels mix); "diagonal": a
    #                                 gain and an offset per channel; "gain": a gain per
    #                                 channel only (as splat.exposure_matrix)
    exposure_clip: bool = False     # the transformed colour clamped to [0, 1] in the loss, as
    #                                 the camera clipped it; clipped channels pass no gradient (as
    #                                 splat.exposure_clip)
    exposure_steady_spread: float = 0.05   # at exposure_steady_after of the budget, transforms
    #                                 whose gains spread less than this (the standard deviation
    #                                 of their logarithms over the images, the largest channel)
    #                                 found a capture of one exposure: they go back to the
    #                                 identity and their rates are scaled by exposure_steady_rate
    #                                 (bonsai's quarter, hash grid: 0.023; lego_400 with changed
    #                                 exposures, grid: 0.17); 0: never
    exposure_steady_rate: float = 0.01   # ... the factor of the rates then
    exposure_steady_after: float = 0.2   # ... the budget fraction of that check
    pose_opt: bool = False          # refine each training camera's pose (a rotation and a
    #                                 translation about a pivot, as splat.pose_opt), the rays
    #                                 of each batch remade from the corrected cameras; test
    #                                 views keep their given poses (clrf/corrections/ray_pose.py)
    lr_pose: float = 1e-3           # Adam learning rate of the corrections at the start:
    #                                 radians per step, translations this times the box's
    #                                 extent. A third of splat.lr_pose: here every image with
    #                                 rays in a batch steps every step (thousands of steps,
    #                                 against a few dozen a camera for splats), on a few dozen
    #                                 rays' noisy gradient (not tuned on a real capture)
    lr_pose_final: float = 1e-4     # ... decayed log-linearly to this over the budget
    pose_reg: float = 1e-4          # pull toward the given pose, reg (|w|^2 + |tau / extent|^2)
    pose_opt_after: float = 0.3     # budget fraction before the corrections take steps (the
    #                                 scene forms first on the given poses; 0: from the start;
    #                                 splat.pose_opt_after's default, chosen on splats)
    pose_opt_every: int = 4         # training steps a camera step: the camera gradient's pass
    #                                 runs on one step in this many (its cost and the number of
    #                                 its noisy steps that much less); 1: every step
    pose_opt_rays: int = 64         # rays an image gathers before its camera steps (its
    #                                 gradient summed over the batches meanwhile); 0: a step
    #                                 every batch the image has rays in. Bonsai's quarter,
    #                                 600 s, both corrections: 25.31 dB with 4 and 64 against
    #                                 25.24 with 1 and 0 (docs/hash.md); lego_400 with poses
    #                                 off by 1 degree: rotation error -90.0 % (-90.2 %)
    pose_hold_frame: bool = True    # take the corrections' common similarity out every 100
    #                                 steps, so the scene stays in the given poses' frame
    #                                 (as splat.pose_hold_frame; clrf/corrections/pose.py)

    @staticmethod
    def from_preset(name: str, **overrides) -> "HashConfig":
        """``"full"`` (the defaults) or ``"tiny"``: T = 2^16, N_max 512, 128 samples, a 64^3
        occupancy grid updated every 8 steps from step 32, 1024 rays per step, the learning
        rate down tenfold every 3,000 steps (100 x 100 scenes on a CPU)."""
        if name not in HASH_PRESETS:
            raise ValueError(f"unknown hash preset {name!r}; use one of {sorted(HASH_PRESETS)}")
        return dataclasses.replace(HashConfig(preset=name, **HASH_PRESETS[name]), **overrides)

    @staticmethod
    def from_dict(d: dict) -> "HashConfig":
        """From ``dataclasses.asdict`` output (a checkpoint's); unknown fields are an error.
        Fields newer than the checkpoint take the value that reproduces how it was trained
        (OLDER_DEFAULTS), not today's default."""
        names = {f.name for f in dataclasses.fields(HashConfig)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"HashConfig: unknown fields {sorted(unknown)}")
        return HashConfig(**{**OLDER_DEFAULTS, **d})

    def checks(self):
        """(ok, field, message) for Config.validate: the ranges the kernels accept."""
        return [
            (self.preset in HASH_PRESETS, "hash.preset", f"must be one of {sorted(HASH_PRESETS)}"),
            (1 <= self.levels <= 64, "hash.levels", "must be in 1..64"),
            (self.features in (1, 2, 4), "hash.features", "must be 1, 2 or 4"),
            (self.levels * self.features <= 256, "hash.levels",
             "levels * features must be <= 256 (the MLP input)"),
            (1 <= self.log2_table <= 24, "hash.log2_table", "must be in 1..24"),
            (1 <= self.min_res and (self.max_res == 0
                                    or self.min_res <= self.max_res <= 1 << 20),
             "hash.min_res", "must satisfy 1 <= min_res <= max_res <= 1048576 (max_res 0: auto)"),
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
            (1 <= self.render_oversample <= 8 and self.samples * self.render_oversample <= 8192,
             "hash.render_oversample", "must be in 1..8 with samples * it <= 8192"),
            (self.contract in ("auto", "on", "off"), "hash.contract",
             "must be 'auto', 'on' or 'off'"),
            (1 <= self.occ_res <= 256, "hash.occ_res", "must be in 1..256"),
            (self.occ_every >= 1, "hash.occ_every", "must be >= 1"),
            (0 <= self.occ_points <= 1 << 24, "hash.occ_points", "must be in 0..16777216"),
            (0 < self.occ_decay <= 1, "hash.occ_decay", "must be in (0, 1]"),
            (self.occ_tau >= 0, "hash.occ_tau", "must be >= 0"),
            (self.occ_warmup >= 0, "hash.occ_warmup", "must be >= 0"),
            (0 < self.lr <= 1, "hash.lr", "must be in (0, 1]"),
            *ray_correction_checks(self, "hash"),
            (self.lr_decay_steps >= 1, "hash.lr_decay_steps", "must be >= 1"),
            (self.lr_schedule in ("budget", "steps"), "hash.lr_schedule",
             "must be 'budget' or 'steps'"),
            (0 <= self.lr_hold < 1, "hash.lr_hold", "must be in [0, 1)"),
            (0 < self.lr_final <= 1, "hash.lr_final", "must be in (0, 1]"),
            (0 <= self.beta1 < 1 and 0 <= self.beta2 < 1, "hash.beta1",
             "Adam's beta1 and beta2 must be in [0, 1)"),
            (0 < self.adam_eps <= 1, "hash.adam_eps", "must be in (0, 1]"),
            (self.weight_decay >= 0, "hash.weight_decay", "must be >= 0"),
            (1 <= self.batch_rays <= 1 << 22, "hash.batch_rays", "must be in 1..4194304"),
            (0 <= self.batch_samples <= 1 << 24, "hash.batch_samples",
             "must be in 0..16777216 (0: a fixed batch_rays)"),
            (self.mlp_rows in (None, *MLP_ROWS), "hash.mlp_rows",
             f"must be null (per device) or one of {', '.join(map(str, MLP_ROWS))}"),
        ]


PUBLISHED_MAX_RES = 2048   # instant-ngp's N_max for 800 x 800 Blender views (box = unit cube)
PUBLISHED_WIDTH = 800

# Field values of each hash preset (the rest are HashConfig's defaults).
HASH_PRESETS = {
    "full": {},
    # small scenes train for hundreds, not tens of thousands, of steps: the occupancy grid
    # starts pruning after 32 and is refreshed every 8
    # a learning rate that falls tenfold over 3,000 steps (about a 120 s run's): tiny_lego
    # 31.14 dB at 120 s against 30.95 with the full preset's 20,000 (one run each, Zen 4)
    "tiny": {"log2_table": 16, "max_res": 512, "samples": 128, "occ_res": 64,
             "occ_points": 32768, "occ_warmup": 32, "occ_every": 8, "batch_rays": 1024,
             "batch_samples": 0, "lr_decay_steps": 3000},
}


# Checkpoints written before a field existed were trained as these values say: a fixed batch
# of batch_rays rays on the dataset's background, renders at the training's sample count, the
# box only, a learning rate that fell over lr_decay_steps, every sample differentiated.
OLDER_DEFAULTS = {"batch_samples": 0, "random_background": False, "render_oversample": 1,
                  "contract": "off", "lr_schedule": "steps", "train_t_stop": 0.0}
