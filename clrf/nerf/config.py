"""NerfConfig: the options of a NeRF model and its optimiser (the ``nerf`` section of a run
configuration, clrf/training/config.py), its presets and the ranges the kernels accept."""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from ..corrections.settings import ray_correction_checks
from ..mlp.tiling import MLP_ROWS


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
    exposure: bool = False          # learn a colour transform (3 x 3 matrix and offset) per
    #                                 training image, seen by the coarse and the fine pass's
    #                                 loss; test views are scored under the identity
    #                                 (as hash.exposure: clrf/corrections/exposure.py)
    lr_exposure: float = 1e-3       # Adam learning rate of the transforms (one step a batch)
    lr_exposure_final: float = 0.0  # ... falling log-linearly to this over the budget
    #                                 (0: a constant rate)
    exposure_reg: float = 1e-3      # pull of each transform toward the identity, reg
    #                                 (|A - I|^2 + |b|^2) weighted by the image's share of the batch
    exposure_matrix: str = "full"   # "full" | "diagonal" | "gain" (as hash.exposure_matrix)
    exposure_clip: bool = False     # as hash.exposure_clip
    exposure_steady_spread: float = 0.05   # as hash.exposure_steady_spread (0: never)
    exposure_steady_rate: float = 0.01   # as hash.exposure_steady_rate
    exposure_steady_after: float = 0.2   # as hash.exposure_steady_after
    pose_opt: bool = False          # refine each training camera's pose (as hash.pose_opt): the
    #                                 rays of each batch remade from the corrected cameras,
    #                                 trained by both passes' dL/d(origin, direction); test
    #                                 views keep their given poses (clrf/corrections/ray_pose.py)
    lr_pose: float = 1e-3           # Adam learning rate of the corrections at the start:
    #                                 radians per step, translations this times the box's
    #                                 extent (hash.lr_pose's; not tuned for NeRF)
    lr_pose_final: float = 1e-4     # ... decayed log-linearly to this over the budget
    pose_reg: float = 1e-4          # pull toward the given pose, reg (|w|^2 + |tau / extent|^2)
    pose_opt_after: float = 0.0     # budget fraction before the corrections take steps
    pose_opt_every: int = 1         # training steps a camera step (as hash.pose_opt_every)
    pose_opt_rays: int = 0          # rays an image gathers before its camera steps (its
    #                                 gradient summed over the batches meanwhile); 0: a step
    #                                 every batch the image has rays in
    pose_hold_frame: bool = True    # take the corrections' common rigid motion out every 100
    #                                 steps (as hash.pose_hold_frame)

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
        """The fused MLP's shape (clrf.mlp.mlp.MLPSpec) for this configuration."""
        from ..nerf import ops
        from ..mlp.mlp import MLPSpec
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
            *ray_correction_checks(self, "nerf"),
        ]


# Field values of each NeRF preset (the rest are NerfConfig's defaults).
NERF_PRESETS = {
    "tiny": {},
    "original": {"width": 256, "depth": 8, "skip": 4, "color_width": 128, "pos_freqs": 10,
                 "dir_freqs": 4, "sigma_act": "relu", "n_coarse": 64, "n_fine": 128,
                 "lr": 5e-4, "lr_decay_steps": 500_000},
}
