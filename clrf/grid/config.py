"""GridConfig: the options of a Plenoxels model and its optimiser (the ``grid`` section of a run
configuration, clrf/training/config.py, which checks their ranges)."""
from __future__ import annotations

from dataclasses import dataclass, field

from ..corrections.settings import ray_correction_checks


@dataclass
class GridConfig:
    reso: list = field(default_factory=lambda: [[64, 64, 64], [128, 128, 128], [256, 256, 256]])
    # ^ grid resolutions, coarse to fine; the run moves to the next at each upsample_at entry
    upsample_at: list = field(default_factory=lambda: [300, 1200])
    # ^ iterations at which to prune (by rendering weight) and upsample to the next resolution
    sh_degree: int = 2            # SH degree of colour (0: diffuse .. 3)
    sh_diffuse_until: float = 0.0  # budget fraction during which only SH band 0 (a colour that
    #                               is the same from every side) learns; the higher bands start
    #                               from 0 after it. With grid.exposure the per-image transforms
    #                               settle first, before view-dependent colour can take up the
    #                               images' exposure changes (0: every band from the start)
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
    exposure: bool = False        # learn a colour transform (3 x 3 matrix and offset) per
    #                               training image, for captures whose exposure or white balance
    #                               changes; test views are scored under the identity
    #                               (clrf/corrections/exposure.py, as hash.exposure). Not on
    #                               RGBA captures (a masked background; docs/guide.md)
    lr_exposure: float = 1e-3     # Adam learning rate of the transforms (each step)
    lr_exposure_final: float = 0.0  # ... falling log-linearly to this over the budget
    #                               (0: a constant rate)
    exposure_reg: float = 1e-3    # pull of each transform toward the identity, reg
    #                               (|A - I|^2 + |b|^2) weighted by the image's share of the batch
    exposure_matrix: str = "full"  # "full": A a 3 x 3 matrix; "diagonal": a gain and an offset
    #                               per channel; "gain": a gain per channel only
    exposure_clip: bool = False   # the transformed colour clamped to [0, 1] in the loss, as the
    #                               camera clipped it; clipped channels pass no gradient (as
    #                               splat.exposure_clip)
    exposure_steady_spread: float = 0.05   # as hash.exposure_steady_spread: transforms whose
    #                               gains spread less than this at exposure_steady_after of the
    #                               budget go back to the identity, their rates times
    #                               exposure_steady_rate (0: never)
    exposure_steady_rate: float = 0.01   # ... the factor of the rates then
    exposure_steady_after: float = 0.2   # ... the budget fraction of that check
    pose_opt: bool = False        # refine each training camera's pose (a rotation and a
    #                               translation about a pivot), the rays of each batch remade from
    #                               the corrected cameras and trained by the renderer's gradient
    #                               with respect to each ray (GRID_POSE_GRAD); test views keep
    #                               their given poses (clrf/corrections/ray_pose.py, as
    #                               hash.pose_opt). Not with NDC (forward-facing) or MPI ranks
    lr_pose: float = 1e-3         # Adam learning rate of the corrections at the start: radians
    #                               per step, translations this times the box's extent
    lr_pose_final: float = 1e-4   # ... decayed log-linearly to this over the budget
    pose_reg: float = 1e-4        # pull toward the given pose, reg (|w|^2 + |tau / extent|^2)
    pose_opt_after: float = 0.0   # budget fraction before the corrections take steps (the scene
    #                               forms first; 0: from the start)
    pose_opt_every: int = 1       # training steps a camera step: the camera gradient's pass
    #                               runs on one step in this many (as hash.pose_opt_every)
    pose_opt_rays: int = 0        # rays an image gathers before its camera steps (its
    #                               gradient summed over the batches meanwhile); 0: a step
    #                               every batch the image has rays in
    pose_hold_frame: bool = True  # take the corrections' common rigid motion out every 100
    #                               steps, so the scene stays in the given poses' frame

    def checks(self):
        """(ok, field, message) for Config.validate: the ranges the kernels and the schedule
        accept."""
        g = self
        return [
            (isinstance(g.reso, list) and len(g.reso) >= 1
             and all(isinstance(r, list) and len(r) == 3 and all(isinstance(v, int) and 1 <= v <= 1024 for v in r)
                     for r in g.reso), "grid.reso", "must be a list of [x, y, z] integer resolutions in 1..1024"),
            (isinstance(g.upsample_at, list) and len(g.upsample_at) == len(g.reso) - 1
             and all(isinstance(v, int) and v > 0 for v in g.upsample_at)
             and g.upsample_at == sorted(g.upsample_at), "grid.upsample_at",
             "must list one increasing iteration per resolution after the first"),
            (g.sh_degree in (0, 1, 2, 3), "grid.sh_degree", "must be 0, 1, 2 or 3"),
            (0 <= g.sh_diffuse_until <= 1, "grid.sh_diffuse_until",
             "must be a budget fraction in [0, 1]"),
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
            *ray_correction_checks(g, "grid"),
        ]
