"""Per-view corrections: what a capture's images do not share with the scene, learned per
training image beside it. One protocol (base.py) for every correction, the list a model holds
and the trainer reports (``Corrections``), and one place that reads their settings from a
model's section and makes them (settings.py ``build``, ``from_state``):

- exposure.py   a colour transform per training image (``splat.exposure``: ``Exposure``, whole
                views; ``hash.exposure``, ``nerf.exposure``: ``RayExposure``, ray batches;
                cl/splat_exposure.cl)
- bilateral.py  a bilateral grid of affine colour transforms per training image
                (``splat.bilateral_grid``: ``BilateralGrid``, whole views; cl/bilateral.cl)
- pose.py       a pose correction per training camera (``splat.pose_opt``: ``PoseCorrection``,
                its SO(3) helpers)
- ray_pose.py   the same for ray batches (``hash.pose_opt``, ``nerf.pose_opt``: ``RayPose``;
                cl/ray_pose.cl)

This package sits below the trainer and outside every representation: it imports the runtime,
the float64 references and the model interface, never a representation, and a model calls the
list's hooks, never a correction by name (tests/test_layers.py). Importing the package imports
no correction (settings.py says why).
"""
from .base import (CAMERA, COLOUR, NONE, PROTOCOLS, RAY_STATE, RAYS, VIEWS,  # noqa: F401
                   CameraCorrection, Correction, Corrections, RayCameraCorrection,
                   RayColourCorrection, ViewColourCorrection, of)
from .settings import EXPOSURE_MATRICES, Views, build, clip_mode, from_state  # noqa: F401
