"""GridConfig: the options of a Plenoxels model and its optimiser (the ``grid`` section of a run
configuration, clrf/training/config.py, which checks their ranges)."""
from __future__ import annotations

from dataclasses import dataclass, field


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
