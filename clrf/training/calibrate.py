"""Exposure calibration (``splat.exposure_calibrate``): a short run at a fraction of the
resolution whose colour transforms start the real run.

A transform per training image (clrf/corrections/exposure.py) learns from the scene's render,
and the scene from the transformed images: early on, while the scene is still forming, the rows
are wrong and the scene keeps what it took under them. A run at an eighth of the resolution
takes several times the steps a second, and with the rows' first rate held throughout (not
decayed) its rows get close to the images' true exposures in a small part of the budget. The
real run starts from those rows, holds them while its own scene forms
(``splat.exposure_calibrate_hold``) and learns on from there; the calibration's scene is
dropped. Its metrics stay in ``OUT/calibration/`` (its checkpoint does not).

A steady capture (``splat.exposure_steady_spread``): where the calibrated gains spread less
than that across the images (``gain_spread``: the standard deviation of their logarithms, the
largest of the three channels), the capture is taken as one of a single exposure. What the
rows learned is then the calibration's own noise (its held rate moves each row by about the
rate a step, whatever the gradient's size: bonsai's quarter, 255 photos at one exposure,
spread 0.05 to 0.07; lego_400 with gains drawn from [0.6, 1.5], 0.25), which the run's scene
would keep. The run starts from the identity instead, its rates times
``splat.exposure_steady_rate``.

The bilateral grid (``splat.bilateral_grid_calibrate``) starts from the same calibration: each
image's transform in every cell of its grid (clrf/corrections/bilateral.py ``seed``).

>>> rows, info = calibrate_exposure(dev, ds, cfg, out / "calibration", log=print)
>>> cfg.train.max_seconds -= info["seconds_budget"]   # the run's own share
"""
from __future__ import annotations

import copy
import dataclasses

import numpy as np

from .. import corrections
from ..data.io import downscale_image
from ..outputs import checkpoint

CALIBRATION_DIR = "calibration"
MIN_SIDE = 32   # pixels: the calibration's images are no smaller a side (the loss's SSIM
#                 window is 11)


def calibration_share(section) -> float:
    """The budget fraction a calibration takes: ``bilateral_grid_calibrate`` where the model
    section trains a bilateral grid (and no exposure transforms), else
    ``exposure_calibrate`` (0 for a kind without them)."""
    if getattr(section, "bilateral_grid", False) and not getattr(section, "exposure", False):
        return float(getattr(section, "bilateral_grid_calibrate", 0.0))
    return float(getattr(section, "exposure_calibrate", 0.0))


def wants_calibration(cfg) -> bool:
    """Whether the run's model section asks for a calibration: its ``exposure`` or
    ``bilateral_grid`` on, with a ``calibration_share`` > 0."""
    s = cfg.section(cfg.train.model)
    on = getattr(s, "exposure", False) or getattr(s, "bilateral_grid", False)
    return bool(on) and calibration_share(s) > 0


def gain_spread(rows) -> float:
    """clrf/corrections/exposure.py ``gain_spread``, imported when called: nothing the command
    line imports before the device's self-check may import the float64 references, which
    that module does (a broken install is then the self-check's installation error)."""
    from ..corrections.exposure import gain_spread as spread
    return spread(rows)


def steady(info: dict, section) -> bool:
    """Whether a calibration (``calibrate_exposure``'s info) found a steady capture: its gains'
    spread below the section's ``exposure_steady_spread`` (module doc; 0: never)."""
    limit = float(getattr(section, "exposure_steady_spread", 0.0))
    return limit > 0 and info["gain_spread"] < limit


def calibration_factor(cfg, hw) -> int:
    """The model section's exposure_calibrate_downscale, lowered where the images would get
    smaller than MIN_SIDE pixels a side."""
    factor = int(cfg.section(cfg.train.model).exposure_calibrate_downscale)
    return max(1, min(factor, min(hw) // MIN_SIDE))


def downscaled(ds, factor: int):
    """``ds`` at 1/factor of its resolution (box-averaged images and coverage, the
    intrinsics scaled; poses, splits and points as they are)."""
    if factor == 1:
        return ds
    images = np.stack([downscale_image(np.asarray(ds.images[i], np.float32), factor)
                       for i in range(len(ds.images))])
    alpha = None
    if ds.alpha is not None:
        alpha = np.stack([downscale_image(np.asarray(ds.alpha[i], np.float32)[..., None],
                                          factor)[..., 0] for i in range(len(ds.alpha))])
    return dataclasses.replace(ds, images=images, alpha=alpha,
                               intrinsics=np.asarray(ds.intrinsics, np.float64) / factor)


def calibration_config(cfg):
    """The calibration run's configuration: ``cfg`` with the budget's calibration share, the
    exposure transforms on (in place of a bilateral grid) at their first rate, held (with
    ``exposure_calibrate_fit``, its last part sets each trained row to its render's
    least-squares fit instead), no calibration of its own, no final evaluation and no
    periodic one after the first."""
    small = copy.deepcopy(cfg)
    name = cfg.train.model   # the model's section
    t, s = small.train, small.section(name)
    t.max_seconds = float(cfg.train.max_seconds) * calibration_share(s)
    t.final_eval = False
    t.eval_every = t.checkpoint_every = 2.0 * t.max_seconds + 1.0
    rate = calibration_rate(s)
    s = dataclasses.replace(s, exposure=True, exposure_calibrate=0.0, lr_exposure=rate,
                            lr_exposure_final=rate)
    fit = float(getattr(s, "exposure_calibrate_fit", 0.0))
    if fit > 0:   # the last part: each row set to its render's least-squares fit
        s = dataclasses.replace(s, exposure_fit=1.0, exposure_fit_after=1.0 - fit)
    if getattr(s, "bilateral_grid", False):
        s = dataclasses.replace(s, bilateral_grid=False, bilateral_grid_calibrate=0.0)
    small.set_section(name, s)
    return small


def calibration_rate(section) -> float:
    """The transforms' rate in the calibration, held: ``lr_exposure_calibrate``, or where that
    is 0 (or the section has none) ``lr_exposure``."""
    return float(getattr(section, "lr_exposure_calibrate", 0.0) or section.lr_exposure)


def calibrate_exposure(device, ds, cfg, out, model_factory=None, log=print):
    """Runs the calibration (module doc) into folder ``out``; returns (the rows P [V, 12] its
    transforms reached, a summary dict: seconds_budget, seconds, iterations, downscale,
    folder). Raises KeyboardInterrupt when it was interrupted (nothing of it is kept)."""
    from .trainer import Trainer
    factor = calibration_factor(cfg, ds.hw)
    small_cfg = calibration_config(cfg)
    budget = small_cfg.train.max_seconds
    rate = calibration_rate(cfg.section(cfg.train.model))
    log(f"exposure calibration: {budget:.0f} s at 1/{factor} resolution, the transforms' "
        f"rate held at {rate:g}; then {cfg.train.max_seconds - budget:.0f} s "
        f"from its transforms")
    trainer = Trainer(device, downscaled(ds, factor), small_cfg, out,
                      model_factory=model_factory, log=log)
    result = trainer.run()
    (trainer.out / checkpoint.CKPT_NAME).unlink(missing_ok=True)   # its scene is dropped
    if result["interrupted"]:
        raise KeyboardInterrupt
    exposure = corrections.of(trainer.model).get("exposure")
    rows = exposure.rows().astype(np.float64)
    info = {"seconds_budget": budget, "seconds": float(result["seconds"]),
            "iterations": int(result["iteration"]), "downscale": factor,
            "images_trained": int(np.count_nonzero(exposure.steps)),
            "folder": str(trainer.out), "gain_spread": gain_spread(rows)}
    info["steady"] = steady(info, cfg.section(cfg.train.model))
    log(f"exposure calibration: {info['iterations']} steps in {info['seconds']:.1f} s; "
        f"{exposure.describe()}; the gains spread by {info['gain_spread']:.3f}"
        + (" (a steady capture: the run starts from the identity)" if info["steady"] else ""))
    return rows, info
