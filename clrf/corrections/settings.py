"""The one place that reads the corrections' settings from a model's configuration section and
makes them: ``build`` for a new run or a model given its training views, ``from_state`` for a
checkpoint's.

The keys users type stay each model's own: ``splat.exposure``, ``hash.exposure`` and
``nerf.exposure`` (with ``lr_exposure``, ``exposure_reg``, ``exposure_matrix``; the splat
section also ``lr_exposure_final``, ``exposure_fit``, ``exposure_fit_after``,
``exposure_clip``, ``exposure_clip_inward``), ``splat.pose_opt``, ``hash.pose_opt`` and
``nerf.pose_opt`` (with ``lr_pose``, ``lr_pose_final``, ``pose_reg``, ``pose_hold_frame``,
``pose_opt_after``), ``splat.bilateral_grid`` (with ``bilateral_grid_shape``,
``lr_bilateral_grid``, ``bilateral_grid_tv``). One colour correction at a time
(``colour_conflict``: the configurations' validation names the keys). A section
without one of the optional keys takes what the correction does without it (a constant rate,
no fit, no clip; the Adam betas of clrf/runtime/optim.py where it has no ``beta1`` / ``beta2``
of its own). This module imports no correction until one is made (the configurations import
EXPOSURE_MATRICES and colour_conflict from here, before the self-check that reports a missing
clrf.references).

>>> corr = build(dev, cfg.splat, Views(len(ds.images), ds.alpha is not None, scale=extent,
...                                    pivots=lambda: depths), VIEWS)
>>> corr = from_state(dev, config, state, Views(scale=extent), VIEWS)
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

from ..interface import StateError
from .base import RAYS, VIEWS, Corrections

# <model>.exposure_matrix, in the order of the kernels' argument ``matrix`` (the float64 twin's
# MATRICES, tests/test_splat_exposure.py). Not imported from the twin: the command line reaches
# the self-check, which reports a missing clrf.references as an installation error, only if
# nothing before it imports the references.
EXPOSURE_MATRICES = ("full", "diagonal", "gain")

ORDER = ("exposure", "bilateral", "pose")             # the list's order (its checkpoint's)
SWITCH = {"exposure": "exposure", "bilateral": "bilateral_grid",   # the section's key that
          "pose": "pose_opt"}                                      # turns one on
STATE = {"exposure": "exposure", "bilateral": "bilateral_grid",    # the checkpoint key that
         "pose": "pose"}                                           # says one is there
WHAT = {"exposure": "the exposure transforms", "bilateral": "the bilateral grids",
        "pose": "the pose corrections"}
COLOURS = ("exposure", "bilateral")                    # change the colour: one at a time


def colour_conflict(section, prefix: str):
    """(ok, key, message) for a configuration's checks: at most one of the colour corrections
    ``section`` turns on (the list holds one correction of each kind of change)."""
    on = [f"{prefix}.{SWITCH[n]}" for n in COLOURS if getattr(section, SWITCH[n], False)]
    return (len(on) <= 1, on[-1] if on else f"{prefix}.{SWITCH[COLOURS[0]]}",
            f"one colour correction at a time: {' and '.join(on)} are both on; turn one off "
            f"(--set {on[-1] if on else ''}=false)")


def ray_correction_checks(section, prefix: str) -> list:
    """(ok, key, message) of the exposure and pose settings of a model whose batches mix rays
    (``<prefix>.lr_exposure``, ``lr_exposure_final``, ``exposure_reg``, ``exposure_matrix``,
    ``exposure_steady_spread``, ``exposure_steady_rate``, ``exposure_steady_after``, ``lr_pose``,
    ``lr_pose_final``, ``pose_reg``, ``pose_opt_after``, ``pose_opt_every``, ``pose_opt_rays``): the hash grid's, the grid's and
    NeRF's configuration checks share them."""
    s, p = section, prefix
    return [
        (0 < s.lr_exposure <= 1, f"{p}.lr_exposure", "must be in (0, 1]"),
        (0 <= s.lr_exposure_final and (s.lr_exposure_final <= s.lr_exposure
                                       or not s.lr_exposure > 0), f"{p}.lr_exposure_final",
         f"must be in [0, {p}.lr_exposure] (0: a constant rate)"),
        (s.exposure_reg >= 0, f"{p}.exposure_reg", "must be >= 0"),
        (s.exposure_matrix in EXPOSURE_MATRICES, f"{p}.exposure_matrix",
         f"must be one of {', '.join(EXPOSURE_MATRICES)}"),
        (s.exposure_steady_spread >= 0, f"{p}.exposure_steady_spread", "must be >= 0 (0: never)"),
        (0 < s.exposure_steady_rate <= 1, f"{p}.exposure_steady_rate", "must be in (0, 1]"),
        (0 <= s.exposure_steady_after < 1, f"{p}.exposure_steady_after", "must be in [0, 1)"),
        (0 < s.lr_pose <= 0.1, f"{p}.lr_pose", "must be in (0, 0.1] (radians a step)"),
        (0 < s.lr_pose_final <= s.lr_pose, f"{p}.lr_pose_final", f"must be in (0, {p}.lr_pose]"),
        (s.pose_reg >= 0, f"{p}.pose_reg", "must be >= 0"),
        (0 <= s.pose_opt_after < 1, f"{p}.pose_opt_after", "must be in [0, 1)"),
        (isinstance(s.pose_opt_every, int) and 1 <= s.pose_opt_every <= 1000,
         f"{p}.pose_opt_every", "must be a whole number of steps in 1..1000"),
        (isinstance(s.pose_opt_rays, int) and 0 <= s.pose_opt_rays <= 1 << 20,
         f"{p}.pose_opt_rays", "must be a whole number of rays in 0..1048576 (0: a step "
         "every batch)"),
    ]


@dataclass(frozen=True)
class Views:
    """What a correction needs to know of a model's training images.

    n_images  rows: one per image (the splat model: every image of the dataset, indexed as
              the dataset does; the hash model: its training views, in the ray store's order)
    masked    an RGBA capture (colour corrections leave its background alone)
    pixels    pixels of an image (ray batches: a ray's image is its index // pixels)
    scale     the scene's extent (pose translations and their pull are relative to it)
    pivots    a function giving each image's pivot depth (called when a pose correction is
              made)
    viewmats  a function giving each image's world-to-camera [V, 4, 4] (OpenCV axes; ray
              batches: the cameras that made the ray store's rays)
    """
    n_images: int = 0
    masked: bool = False
    pixels: int = 0
    scale: float = 1.0
    pivots: Optional[Callable] = None
    viewmats: Optional[Callable] = None


def clip_mode(section) -> int:
    """The colour transform's clip (``exposure_clip``, ``exposure_clip_inward``): 0 none, 1
    clipped channels pass no gradient, 2 only one pointing back inside [0, 1]."""
    if not getattr(section, "exposure_clip", False):
        return 0
    return 2 if getattr(section, "exposure_clip_inward", False) else 1


def _exposure(device, s, views: Views, batches: str, state=None):
    from .exposure import Exposure, RayExposure
    if batches == VIEWS:
        n = views.n_images if state is None else len(state["exposure"])
        return Exposure(device, n, s.lr_exposure, s.exposure_reg, state=state,
                        masked=views.masked, clip=clip_mode(s), matrix=s.exposure_matrix,
                        lr_final=getattr(s, "lr_exposure_final", None),
                        fit=getattr(s, "exposure_fit", 0.0),
                        fit_after=getattr(s, "exposure_fit_after", 0.0))
    from ..runtime.optim import ADAM_BETAS
    betas = (getattr(s, "beta1", ADAM_BETAS[0]), getattr(s, "beta2", ADAM_BETAS[1]))
    if state is None:
        n, pixels, masked = views.n_images, views.pixels, views.masked
    else:
        n, pixels = len(state["exposure"]), int(state["exposure_pixels"])
        masked = bool(state["exposure_masked"])
    return RayExposure(device, n, pixels, s.lr_exposure, s.exposure_reg, betas, state=state,
                       masked=masked, matrix=s.exposure_matrix, clip=clip_mode(s) > 0,
                       lr_final=getattr(s, "lr_exposure_final", 0.0) or None,
                       steady_spread=getattr(s, "exposure_steady_spread", 0.0),
                       steady_rate=getattr(s, "exposure_steady_rate", 0.01),
                       steady_after=getattr(s, "exposure_steady_after", 0.2))


def _pose(device, s, views: Views, batches: str, state=None):
    from .pose import PoseCorrection
    hold = getattr(s, "pose_hold_frame", True)
    start = getattr(s, "pose_opt_after", 0.0)
    if batches == RAYS:
        from .ray_pose import RayPose
        every = getattr(s, "pose_opt_every", 1)
        rays = getattr(s, "pose_opt_rays", 0)
        if state is not None:
            return RayPose(device, None, 0, s.lr_pose, s.pose_reg, views.scale, state=state,
                           lr_final=s.lr_pose_final, hold_frame=hold, start=start,
                           every=every, min_rays=rays)
        if views.viewmats is None:
            raise ValueError("a pose correction of ray batches needs the training cameras")
        return RayPose(device, views.viewmats(), views.pixels, s.lr_pose, s.pose_reg,
                       views.scale, pivots=views.pivots() if views.pivots else None,
                       lr_final=s.lr_pose_final, hold_frame=hold, start=start, every=every,
                       min_rays=rays)
    if state is not None:
        return PoseCorrection(len(state["pose"]), s.lr_pose, s.pose_reg, views.scale,
                              state=state, lr_final=s.lr_pose_final, hold_frame=hold,
                              start=start)
    return PoseCorrection(views.n_images, s.lr_pose, s.pose_reg, views.scale,
                          pivots=views.pivots() if views.pivots else None,
                          lr_final=s.lr_pose_final, hold_frame=hold, start=start)


def _bilateral(device, s, views: Views, batches: str, state=None):
    from .bilateral import BilateralGrid
    if batches != VIEWS:
        raise ValueError("a bilateral grid needs a model that trains on whole views")
    n = views.n_images if state is None else len(state["bilateral_grid"])
    return BilateralGrid(device, n, s.lr_bilateral_grid, s.bilateral_grid_tv,
                         shape=s.bilateral_grid_shape, state=state, masked=views.masked,
                         sparse=s.bilateral_grid_sparse)


MAKE = {"exposure": _exposure, "bilateral": _bilateral, "pose": _pose}


def build(device, section, views: Views, batches: str, current=None) -> Corrections:
    """The corrections ``section`` (a model's configuration) turns on over ``views``, for a
    model of ``batches`` (VIEWS or RAYS). Those of ``current`` (a checkpoint's) are kept where
    they have a row per image; a view-colour correction takes the capture's masking and the
    section's clip."""
    if batches not in (VIEWS, RAYS):
        raise ValueError(f"batches {batches!r}: {VIEWS!r} or {RAYS!r}")
    have = {c.name: c for c in (current or ())}
    for name in ORDER:
        if not getattr(section, SWITCH[name], False):
            continue
        c = have.get(name)
        if c is None or c.n_images != views.n_images:
            have[name] = MAKE[name](device, section, views, batches)
    ex = have.get("exposure")
    if ex is not None and ex.batches == VIEWS:   # an RGBA capture: its background stays
        ex.masked = views.masked
        ex.clip = clip_mode(section)
    elif ex is not None:
        ex.clip = clip_mode(section) > 0
    if "bilateral" in have:
        have["bilateral"].masked = views.masked
    return Corrections(have[n] for n in ORDER if n in have)


def from_state(device, section, state: dict, views: Views, batches: str) -> Corrections:
    """The corrections a checkpoint's ``state`` holds (its keys: ``exposure``, ``exposure_m``,
    ..., ``bilateral_grid``, ``bilateral_grid_m``, ..., ``pose``, ``pose_m``, ...), with
    ``section``'s settings; StateError where one is unreadable."""
    out = []
    for name in ORDER:
        if STATE[name] not in state:
            continue
        try:
            out.append(MAKE[name](device, section, views, batches, state=state))
        except (KeyError, ValueError, TypeError) as e:
            raise StateError(f"state_dict: {WHAT[name]} are unreadable ({e})") from None
    return Corrections(out)
