"""SplatConfig: the options of a 3D Gaussian splatting model and its optimiser (the ``splat``
section of a run configuration, clrf/training/config.py), and its presets.

The run is time-budgeted, so every schedule is a FRACTION of the budget (Budget.fraction: the
larger of the seconds and iterations spent), not an iteration count. The published values
(Kerbl et al. 2023, 30,000 iterations) translate as: densify from 500 / 30,000 = 0.0167 to
15,000 / 30,000 = 0.5 every 100 / 30,000 = 0.0033, reset opacities every 3,000 / 30,000 = 0.1,
raise the SH degree every 1,000 / 30,000 = 0.033.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from ..corrections.settings import EXPOSURE_MATRICES, colour_conflict


@dataclass(frozen=True)
class SplatConfig:
    """Everything that defines a Gaussian-splatting model (train.model splat) and its
    optimiser. The defaults are the ``full`` preset (the published values); ``tiny`` is for
    small images (tiny_lego, the procedural scene)."""

    preset: str = "full"            # the preset these values start from: "full" | "tiny"
    sh_degree: int = 3              # spherical-harmonics degree of the colours, 0..3
    #                                 (published: 3); raised from 0 in steps (sh_increase_every)
    init: str = "auto"              # where the first Gaussians come from: "points" (the
    #                                 capture's sparse points, COLMAP's points3D, with their
    #                                 colours), "random" (init_points uniform in the scene's
    #                                 box, and for unbounded scenes as many again beyond it),
    #                                 "auto" (points when the dataset has them, else random)
    init_ply: str = ""              # a splat file to start from, any export --splats ending
    #                                 (.ply .spz .glb .gltf .compressed.ply .splat), read by
    #                                 its ending instead of init (clrf export --splats, the
    #                                 3DGS tools' point_cloud.ply, Scaniverse's .spz,
    #                                 SuperSplat's and gsplat's compressed PLY, in the
    #                                 dataset's world frame): its SH bands beyond sh_degree
    #                                 are dropped, missing ones start at zero; "" : use init
    init_points: int = 100000       # random Gaussians at the start (init "random"); with
    #                                 "points" the sparse points are subsampled to this many;
    #                                 capped by max_gaussians and by what fits the device
    init_max_pixels: float = 0.0    # largest standard deviation of a first Gaussian (points
    #                                 or random), in pixels of the nearest training view that
    #                                 sees it in front; 0: none (published: the 3-nearest-
    #                                 neighbour distance whatever it covers on screen)
    strategy: str = "default"       # density control (clrf/splat/strategies/): "default"
    #                                 (clone, split and prune by screen-space gradients, as
    #                                 published) or "mcmc" (3DGS as MCMC: a fixed budget of
    #                                 Gaussians, dead ones relocated onto live ones, noise on
    #                                 the means; grows by mcmc_growth to max_gaussians)
    mcmc_until: float = 0.833       # mcmc: budget fraction after which it stops relocating
    #                                 and adding (published: 25,000 of 30,000 steps)
    mcmc_growth: float = 1.05       # mcmc: each refinement multiplies the count by this, up
    #                                 to the cap (published: 5 %)
    mcmc_noise_lr: float = 5e5      # mcmc: the means' noise, times their learning rate and
    #                                 covariance (published: 5e5)
    mcmc_opacity_reg: float = 0.01  # mcmc: L1 pull of the opacities toward 0 (published)
    mcmc_scale_reg: float = 0.01    # mcmc: L1 pull of the scales toward 0 (published)
    mcmc_spread: float = 1.0        # mcmc: a copy starts this many of its sd's from the
    #                                 Gaussian it copies, at random (published: 0, in place;
    #                                 bonsai_800 at 1/4, 600 s: 29.89 dB against 29.16)
    init_opacity: float = 0.0       # opacity of the first Gaussians; 0: the strategy's
    #                                 published value (default 0.1, mcmc 0.5)
    init_scale: float = 0.0         # their size in units of the mean distance to the 3
    #                                 nearest neighbours; 0: the strategy's published value
    #                                 (default 1, mcmc 0.1: small Gaussians, which also keep
    #                                 the first steps of a CPU run fast)
    max_gaussians: int = 1000000    # hard cap on the number of Gaussians (densification stops
    #                                 adding at it); also lowered to what fits the device
    lr_position: float = 1.6e-4     # Adam learning rate of the means at the start, times the
    #                                 scene extent (published: 1.6e-4)
    lr_position_final: float = 1.6e-6   # the means' rate at the end of the budget, times the
    #                                 extent (published: 1.6e-6); exponential in between
    lr_feature_dc: float = 2.5e-3   # Adam rate of the SH degree-0 coefficients (published)
    lr_feature_rest: float = 1.25e-4   # Adam rate of the higher SH coefficients (published:
    #                                 2.5e-3 / 20)
    lr_opacity: float = 5e-2        # Adam rate of the opacity logits (published: 5e-2)
    lr_scaling: float = 5e-3        # Adam rate of the log scales (published: 5e-3)
    lr_rotation: float = 1e-3       # Adam rate of the quaternions (published: 1e-3)
    adam_eps: float = 1e-15         # Adam epsilon (published: 1e-15)
    lambda_dssim: float = 0.2       # loss = (1 - lambda) L1 + lambda (1 - SSIM), SSIM over an
    #                                 11 x 11 Gaussian window, sigma 1.5 (published: 0.2)
    densify_from: float = 0.0167    # budget fraction at which densification starts
    #                                 (published: step 500 of 30,000)
    densify_until: float = 0.5      # budget fraction after which it stops (published: 15,000
    #                                 of 30,000)
    densify_every: float = 0.0033   # budget fraction between densifications (published: 100
    #                                 of 30,000 steps)
    densify_min_steps: int = 50     # and at least this many steps between two, so that the
    #                                 gradient statistics of a short run mean something
    densify_grad_threshold: float = 2e-4   # a Gaussian is cloned or split where its mean
    #                                 screen-space position gradient norm (in NDC units: the
    #                                 pixel gradient times (W/2, H/2), as published) over the
    #                                 views that saw it reaches this (published: 2e-4)
    absgrad: bool = False           # default strategy: the densify test on absolute screen
    #                                 gradients (each pixel's |dL/dxy| summed, so opposite
    #                                 pixels cannot cancel; gsplat's absgrad), against
    #                                 densify_absgrad_threshold
    densify_absgrad_threshold: float = 8e-4   # the threshold with absgrad (gsplat pairs
    #                                 absgrad with 0.0008: absolute sums are larger)
    percent_dense: float = 0.01     # Gaussians larger than this fraction of the scene extent
    #                                 are split, smaller ones cloned (published: 0.01)
    prune_opacity: float = 0.005    # Gaussians with opacity below this are removed at each
    #                                 densification (published: 0.005)
    prune_screen_size: float = 20.0   # after the first opacity reset, Gaussians whose screen
    #                                 radius exceeded this many pixels are removed (published)
    prune_world_size: float = 0.1   # after the first opacity reset, Gaussians larger than this
    #                                 fraction of the scene extent are removed (published)
    opacity_reset_every: float = 0.0   # budget fraction between opacity resets to 0.01;
    #                                 0: never (published: every 3,000 of 30,000 steps; off
    #                                 here for runs of a few thousand steps: on lego_400 a
    #                                 reset at step 1,500 left 35k of 97k Gaussians, on bonsai
    #                                 one at step 3,100 took 24.7 dB to 5.7, 14 dB 200 s later)
    opacity_reset_min_steps: int = 1500   # and at least this many steps before the first
    #                                 reset and between two: a reset (and the size pruning
    #                                 that follows it) before the Gaussians have trained
    #                                 empties a short run (published: the first at step 3,000)
    sh_increase_every: float = 0.0333   # budget fraction between raising the active SH
    #                                 degree by one (published: 1,000 of 30,000 steps)
    seed: int = 0                   # initialisation and training-view order seed (added to
    #                                 train.seed)
    exposure: bool = False          # learn a colour transform (3 x 3 matrix and offset) per
    #                                 training image, for captures whose exposure or white
    #                                 balance changes (phones); test views are scored under
    #                                 the identity (clrf/corrections/exposure.py)
    lr_exposure: float = 0.05       # Adam learning rate of the transforms at the start (each
    #                                 row steps only when its image is trained: a few dozen
    #                                 times a CPU run, so they must move fast)
    lr_exposure_final: float = 0.0005   # ... decayed log-linearly to this over the budget
    exposure_fit: float = 0.0       # > 0: from exposure_fit_after of the budget on, each
    #                                 trained image's transform moves this far toward the
    #                                 least-squares fit of its render instead of an Adam step
    #                                 (a Gauss-Newton step: the squared error is quadratic in
    #                                 the transform); 0: Adam throughout (lego_400 with changed
    #                                 exposures, 900 s: 0.5 gave 28.60 dB, Adam 28.68)
    exposure_fit_after: float = 0.05   # budget fraction before the fits start (the scene has
    #                                 formed: a fit to an unformed render is noise)
    exposure_reg: float = 0.001     # pull of each transform toward the identity,
    #                                 reg (|A - I|^2 + |b|^2) added to the loss
    exposure_matrix: str = "gain"   # "gain": a gain per channel (exposure and white
    #                                 balance; A's other entries and b stay 0); "diagonal": a
    #                                 gain and an offset per channel; "full": A a 3 x 3 matrix
    #                                 and b (channels mix). lego_400 with changed exposures,
    #                                 900 s: gain 30.82 dB, full 30.14 (the offsets and the
    #                                 mixing wander: docs/splat.md)
    exposure_calibrate: float = 0.08   # with splat.exposure: this fraction of
    #                                 train.max_seconds goes first to a run at
    #                                 1/exposure_calibrate_downscale of the resolution whose
    #                                 transforms keep their first rate (lr_exposure); its
    #                                 transforms start the run, its scene is dropped (a scene
    #                                 formed under wrong exposures keeps what it took); 0: none.
    #                                 lego_400 with changed exposures, 900 s in all: 31.18 dB
    #                                 (0.08 at 1/8), 30.99 (0.15 at 1/4), none 30.44
    exposure_calibrate_downscale: int = 8   # the calibration's resolution divisor (no
    #                                 smaller than 32 pixels a side: clrf/training/calibrate.py)
    lr_exposure_calibrate: float = 0.0   # the calibration's rate, held (0: lr_exposure):
    #                                 large, to find the gains of a capture whose exposures
    #                                 differ a lot, while the run's own lr_exposure can stay
    #                                 small, so that the rows of a steady one do not wander
    exposure_steady_spread: float = 0.12   # a calibration whose gains spread less than
    #                                 this (the standard deviation of their logarithms over
    #                                 the images) found a capture of one exposure: the run
    #                                 starts from the identity, its exposure rates times
    #                                 exposure_steady_rate (clrf/training/calibrate.py;
    #                                 bonsai's quarter 0.05-0.07, lego_400 with changed
    #                                 exposures 0.25); 0: the calibration's rows always
    exposure_steady_rate: float = 0.01   # ... the factor of the rates then
    exposure_calibrate_fit: float = 0.3   # the calibration's last fraction in which each
    #                                 trained image's transform is set to the least-squares
    #                                 fit of its render (as exposure_fit=1), not an Adam step:
    #                                 the transforms then read the images' exposures off the
    #                                 calibration's scene, however few Adam steps the
    #                                 calibration gave them (a 19 s calibration of lego_400
    #                                 with changed exposures: gains spread 0.155 fitted, 0.083
    #                                 by Adam, so the steady rule took it for steady; bonsai's
    #                                 quarter 0.053 and 0.069); 0: Adam throughout
    exposure_calibrate_hold: float = 0.1   # budget fraction the calibrated transforms stay
    #                                 as they are while the scene forms under them
    exposure_clip: bool = True      # the transformed render clamped to [0, 1], as the camera
    #                                 clipped what it over- or under-exposed; clipped channels
    #                                 pass no gradient (cl/splat_exposure.cl); lego_400 with
    #                                 changed exposures, 900 s: 29.26 dB, without 28.68
    exposure_clip_inward: bool = False   # with exposure_clip, a clipped channel still
    #                                 passes a gradient that would bring it back inside
    #                                 [0, 1] (a render past white where the capture was not
    #                                 white is pulled down)
    bilateral_grid: bool = False    # learn a bilateral grid per training image (Wang et al.
    #                                 2024, gsplat's use_bilateral_grid): affine colour
    #                                 transforms sliced by pixel position and the render's
    #                                 luminance, for per-photo processing (exposure, white
    #                                 balance, tone curves, vignetting); test views are scored
    #                                 without it (clrf/corrections/bilateral.py). One colour
    #                                 correction at a time: not with splat.exposure
    bilateral_grid_shape: list = dataclasses.field(default_factory=lambda: [16, 16, 8])
    # ^ cells per image: x bins, y bins and luminance bins (gsplat's)
    lr_bilateral_grid: float = 0.002   # Adam rate of the grids (gsplat's), warmed up from 1 %
    #                                 over the first 1/30 of the budget and decayed to 1 % at
    #                                 its end, as gsplat's 1,000 of 30,000 steps
    bilateral_grid_tv: float = 10.0   # weight of the grids' total variation, summed over the
    #                                 images and divided by their number (gsplat's)
    bilateral_grid_sparse: bool = True   # each step moves the trained image's grid alone
    #                                 (its data and prior gradients, Adam counting its own
    #                                 steps), not every grid as gsplat does
    bilateral_grid_calibrate: float = 0.0   # with splat.bilateral_grid: this fraction of
    #                                 train.max_seconds goes first to an exposure calibration
    #                                 (as splat.exposure_calibrate, with its downscale, rate
    #                                 and steady rule), whose per-image transforms start every
    #                                 cell of each image's grid, held for
    #                                 exposure_calibrate_hold of the budget; 0: the identity
    pose_opt: bool = False          # refine each training camera's pose (a rotation and a
    #                                 translation of its frame), for poses from structure
    #                                 from motion that are a little off; test views keep
    #                                 their given poses (clrf/corrections/pose.py)
    lr_pose: float = 0.003          # Adam learning rate of the corrections at the start:
    #                                 radians per step, translations this times the scene's
    #                                 extent (each camera steps only when its image is
    #                                 trained: a few dozen times a CPU run)
    lr_pose_final: float = 0.0003   # ... decayed log-linearly to this over the budget (on
    #                                 lego_400 with 1-degree errors, 900 s: 3e-3 to 3e-4
    #                                 reached 1 degree of correction in half the time of a
    #                                 constant 1e-3, with the same rotation error, and its
    #                                 test views refined at the same rate to 0.50 dB more)
    pose_reg: float = 0.0001        # pull toward the given pose, reg (|w|^2 + |tau / extent|^2)
    pose_opt_after: float = 0.3     # budget fraction before the corrections take steps (the
    #                                 scene forms first on the given poses; 0: from the start).
    #                                 bonsai_800's quarter, 240 s: 28.89 dB without pose_opt,
    #                                 27.42 from the start, 28.95 after 0.3; lego_400 with
    #                                 1-degree errors, 240 s: rotation error -40 % from the
    #                                 start, -20 % after 0.3 (docs/splat.md): 0 for poses known
    #                                 to be off by a degree
    pose_hold_frame: bool = True    # take the corrections' common similarity (rigid motion and
    #                                 scale) out after each pass, so the scene stays in the
    #                                 given poses' frame and the test views' given poses fit it
    #                                 (clrf/corrections/pose.py); false: the frame drifts
    antialiased: bool = True        # Mip-Splatting's filters: a 3D low-pass filter per
    #                                 Gaussian bounded by the training views' sampling rate
    #                                 and the screen-space dilation with opacity compensation,
    #                                 so a render at another scale (zoom, clrf render --scale)
    #                                 neither fattens nor needles thin things. On by default
    #                                 (docs/splat.md: higher PSNR at the training scale on
    #                                 lego_400 and bonsai, fewer Gaussians); off in the tiny
    #                                 preset; false: 3DGS's fixed 0.3 px^2 dilation
    aa_filter2d: float = 0.1        # with antialiased, the 2D filter's variance (px^2):
    #                                 Mip-Splatting's 0.1 (about a one-pixel box; the 3D
    #                                 filter's 0.2 of a training pixel makes up the rest of
    #                                 3DGS's 0.3 dilation). gsplat's antialiased mode: 0.3
    images_on_device: str = "auto"  # "true": the training images are uploaded once (uint8
    #                                 where exact, else float16) and one is widened a step;
    #                                 "false": streamed, each step's image copied from the
    #                                 host's dataset (its float32 values exactly; an 8-bit
    #                                 capture's as its uint8 levels), so the device holds no
    #                                 second copy; "auto":
    #                                 streamed where the device's memory is the host's
    #                                 (HOST_UNIFIED_MEMORY: CPU runtimes, integrated GPUs),
    #                                 else uploaded (clrf/splat/targets.py)

    @staticmethod
    def from_preset(name: str, **overrides) -> "SplatConfig":
        """``"full"`` (the defaults) or ``"tiny"``: few initial Gaussians and a small cap,
        densification from the start of the run (small images, CPU budgets of a minute)."""
        if name not in SPLAT_PRESETS:
            raise ValueError(f"unknown splat preset {name!r}; use one of {sorted(SPLAT_PRESETS)}")
        return dataclasses.replace(SplatConfig(preset=name, **SPLAT_PRESETS[name]), **overrides)

    @staticmethod
    def from_dict(d: dict) -> "SplatConfig":
        """From ``dataclasses.asdict`` output (a checkpoint's); unknown fields are an error."""
        names = {f.name for f in dataclasses.fields(SplatConfig)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"SplatConfig: unknown fields {sorted(unknown)}")
        d = {**BEFORE_FIELD, **d}   # a field the checkpoint predates: what it trained with
        if d["antialiased"] and "aa_filter2d" not in d:
            d = dict(d, aa_filter2d=0.3)   # anti-aliased checkpoints from before the field
        return SplatConfig(**d)

    def checks(self):
        """(ok, field, message) for Config.validate."""
        from .strategies import REGISTRY
        frac = lambda x: 0.0 <= x <= 1.0   # noqa: E731
        return [
            (self.preset in SPLAT_PRESETS, "splat.preset",
             f"must be one of {sorted(SPLAT_PRESETS)}"),
            (self.sh_degree in (0, 1, 2, 3), "splat.sh_degree", "must be 0, 1, 2 or 3"),
            (self.init in INIT_MODES, "splat.init", f"must be one of {list(INIT_MODES)}"),
            (1 <= self.init_points <= 1 << 24, "splat.init_points", "must be in 1..16777216"),
            (self.init_max_pixels >= 0, "splat.init_max_pixels", "must be >= 0 (0: no limit)"),
            (self.strategy in REGISTRY, "splat.strategy", f"must be one of {list(REGISTRY)}"),
            (frac(self.mcmc_until), "splat.mcmc_until", "must be a budget fraction in [0, 1]"),
            (1.0 <= self.mcmc_growth <= 2.0, "splat.mcmc_growth", "must be in [1, 2]"),
            (self.mcmc_noise_lr >= 0, "splat.mcmc_noise_lr", "must be >= 0 (0: no noise)"),
            (self.mcmc_opacity_reg >= 0, "splat.mcmc_opacity_reg", "must be >= 0"),
            (self.mcmc_scale_reg >= 0, "splat.mcmc_scale_reg", "must be >= 0"),
            (self.mcmc_spread >= 0, "splat.mcmc_spread", "must be >= 0 (0: in place)"),
            (0 <= self.init_opacity < 1, "splat.init_opacity",
             "must be in (0, 1), or 0 for the strategy's published value"),
            (self.init_scale >= 0, "splat.init_scale",
             "must be > 0, or 0 for the strategy's published value"),
            (1 <= self.max_gaussians <= 1 << 26, "splat.max_gaussians",
             "must be in 1..67108864"),
            (0 < self.lr_position <= 1, "splat.lr_position", "must be in (0, 1]"),
            (0 < self.lr_position_final <= self.lr_position, "splat.lr_position_final",
             "must be in (0, lr_position]"),
            (0 <= self.lr_feature_dc <= 1, "splat.lr_feature_dc", "must be in [0, 1]"),
            (0 <= self.lr_feature_rest <= 1, "splat.lr_feature_rest", "must be in [0, 1]"),
            (0 <= self.lr_opacity <= 1, "splat.lr_opacity", "must be in [0, 1]"),
            (0 <= self.lr_scaling <= 1, "splat.lr_scaling", "must be in [0, 1]"),
            (0 <= self.lr_rotation <= 1, "splat.lr_rotation", "must be in [0, 1]"),
            (0 < self.adam_eps <= 1, "splat.adam_eps", "must be in (0, 1]"),
            (0 <= self.lambda_dssim <= 1, "splat.lambda_dssim", "must be in [0, 1]"),
            (frac(self.densify_from) and frac(self.densify_until), "splat.densify_from",
             "densify_from and densify_until must be budget fractions in [0, 1]"),
            (0 < self.densify_every <= 1, "splat.densify_every",
             "must be a budget fraction in (0, 1]"),
            (self.densify_min_steps >= 1, "splat.densify_min_steps", "must be >= 1"),
            (self.densify_grad_threshold > 0, "splat.densify_grad_threshold", "must be > 0"),
            (self.densify_absgrad_threshold > 0, "splat.densify_absgrad_threshold",
             "must be > 0"),
            (0 < self.percent_dense < 1, "splat.percent_dense", "must be in (0, 1)"),
            (0 <= self.prune_opacity < 1, "splat.prune_opacity", "must be in [0, 1)"),
            (self.prune_screen_size > 0, "splat.prune_screen_size", "must be > 0 pixels"),
            (self.prune_world_size > 0, "splat.prune_world_size", "must be > 0"),
            (frac(self.opacity_reset_every), "splat.opacity_reset_every",
             "must be a budget fraction in [0, 1] (0: never)"),
            (self.opacity_reset_min_steps >= 0, "splat.opacity_reset_min_steps",
             "must be >= 0"),
            (0 < self.sh_increase_every <= 1, "splat.sh_increase_every",
             "must be a budget fraction in (0, 1]"),
            (self.seed >= 0, "splat.seed", "must be >= 0"),
            (0 < self.lr_exposure <= 1, "splat.lr_exposure", "must be in (0, 1]"),
            (0 <= self.lr_exposure_calibrate <= 1, "splat.lr_exposure_calibrate",
             "must be in [0, 1] (0: splat.lr_exposure)"),
            (self.exposure_steady_spread >= 0, "splat.exposure_steady_spread", "must be >= 0"),
            (0 < self.exposure_steady_rate <= 1, "splat.exposure_steady_rate",
             "must be in (0, 1]"),
            (0 < self.lr_exposure_final <= self.lr_exposure, "splat.lr_exposure_final",
             "must be in (0, splat.lr_exposure]"),
            (self.exposure_reg >= 0, "splat.exposure_reg", "must be >= 0"),
            (self.exposure_matrix in EXPOSURE_MATRICES, "splat.exposure_matrix",
             f"must be one of {', '.join(EXPOSURE_MATRICES)}"),
            (self.exposure_clip or not self.exposure_clip_inward, "splat.exposure_clip_inward",
             "needs splat.exposure_clip=true"),
            (0 <= self.exposure_fit <= 1, "splat.exposure_fit", "must be in [0, 1]"),
            (0 <= self.exposure_fit_after <= 1, "splat.exposure_fit_after",
             "must be in [0, 1]"),
            (0 <= self.exposure_calibrate <= 0.5, "splat.exposure_calibrate",
             "must be a budget fraction in [0, 0.5] (0: no calibration)"),
            (isinstance(self.exposure_calibrate_downscale, int)
             and self.exposure_calibrate_downscale >= 1, "splat.exposure_calibrate_downscale",
             "must be an integer >= 1"),
            (0 <= self.exposure_calibrate_fit <= 1, "splat.exposure_calibrate_fit",
             "must be a fraction of the calibration in [0, 1]"),
            (0 <= self.exposure_calibrate_hold <= 1, "splat.exposure_calibrate_hold",
             "must be a budget fraction in [0, 1]"),
            colour_conflict(self, "splat"),
            (len(self.bilateral_grid_shape) == 3
             and all(isinstance(n, int) and 1 <= n <= 64 for n in self.bilateral_grid_shape),
             "splat.bilateral_grid_shape",
             "must be three whole numbers in 1..64: x, y and luminance bins (gsplat: "
             "[16, 16, 8])"),
            (0 < self.lr_bilateral_grid <= 1, "splat.lr_bilateral_grid",
             "must be in (0, 1] (gsplat: 0.002)"),
            (self.bilateral_grid_tv >= 0, "splat.bilateral_grid_tv", "must be >= 0 (gsplat: 10)"),
            (0 <= self.bilateral_grid_calibrate <= 0.5, "splat.bilateral_grid_calibrate",
             "must be a budget fraction in [0, 0.5] (0: no calibration)"),
            (0 < self.lr_pose <= 0.1, "splat.lr_pose", "must be in (0, 0.1] (radians a step)"),
            (0 < self.lr_pose_final <= self.lr_pose, "splat.lr_pose_final",
             "must be in (0, splat.lr_pose]"),
            (self.pose_reg >= 0, "splat.pose_reg", "must be >= 0"),
            (0 <= self.pose_opt_after < 1, "splat.pose_opt_after", "must be in [0, 1)"),
            (0 < self.aa_filter2d <= 1, "splat.aa_filter2d", "must be in (0, 1] px^2"),
            (self.images_on_device in IMAGES_ON_DEVICE, "splat.images_on_device",
             f"must be one of {list(IMAGES_ON_DEVICE)}"),
        ]


INIT_MODES = ("auto", "points", "random")
IMAGES_ON_DEVICE = ("auto", "true", "false")   # clrf/splat/targets.py resident
# The value of a setting whose default changed, for a checkpoint written before the setting
# existed: how that run was trained (SplatConfig.from_dict).
BEFORE_FIELD = {
    "antialiased": False,     # plain 3DGS
    "exposure_clip": False,   # unclipped
    "mcmc_spread": 0.0,       # copies in place
    "exposure_matrix": "full",   # a 3 x 3 matrix and an offset
    "exposure_calibrate": 0.0,   # no calibration (a resumed run never calibrates)
    "bilateral_grid_sparse": False,   # every grid stepped every step (gsplat's)
}

# Field values of each splat preset (the rest are SplatConfig's defaults).
SPLAT_PRESETS = {
    "full": {},
    # 100 x 100 views on a CPU: a minute is a few hundred steps, so densification starts at
    # once and runs every 50 steps or more, with a cap that keeps a step near 10 ms
    "tiny": {"init_points": 5000, "max_gaussians": 60000, "densify_from": 0.02,
             "densify_until": 0.7, "densify_every": 0.02, "densify_min_steps": 25,
             "opacity_reset_every": 0.3, "opacity_reset_min_steps": 300,
             "sh_increase_every": 0.1,
             # with the opacity resets above, the anti-aliased filters recovered slower on
             # tiny_lego (120 s: 30.30 dB against 33.04 without them)
             "antialiased": False},
}
