"""The in-memory dataset every loader returns, and the error type for bad input."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class DataError(ValueError):
    """A dataset file is missing or malformed. The message names the file, the field and the fix."""


@dataclass
class Dataset:
    """Posed images of one scene.

    Conventions: poses are camera-to-world 4x4 matrices in OpenGL/Blender axes (camera x right,
    y up, looking down -z); images are float32 RGB in [0, 1], already composited on
    ``background``; ``intrinsics`` = (fx, fy, cx, cy) in pixels, shared by all images.
    The loaders store 8-bit images as their levels (clrf/data/images.py ``ImageStack``): they
    index like the float32 array and read as it, bit for bit, in a quarter of the memory.
    """

    name: str
    images: np.ndarray                 # float32 [N, H, W, 3] (or an ImageStack reading as one)
    poses: np.ndarray                  # float32 [N, 4, 4]
    intrinsics: np.ndarray             # float64 [4]: fx, fy, cx, cy
    split: dict                        # "train" / "test" (/ "val") -> int index arrays into images
    background: tuple = (1.0, 1.0, 1.0)
    bbox: np.ndarray = field(default_factory=lambda: np.array([[-1.5] * 3, [1.5] * 3]))  # [2, 3]
    near: float = 0.0
    far: float = 1e10
    ndc: bool = False                  # forward-facing scenes: rays in normalised device coords
    distortion: np.ndarray | None = None  # OpenCV k1, k2, p1, p2 (instant-ngp captures)
    preset: str = "synthetic"          # scene preset name (clrf.training.config)
    alpha: np.ndarray | None = None    # float32 [N, H, W]: coverage of RGBA captures (None: RGB);
    #                                    images = rgb * alpha + background * (1 - alpha)
    points: np.ndarray | None = None   # float32 [P, 6]: a sparse point cloud of the scene (COLMAP's
    #                                    points3D), xyz in the poses' frame and RGB in [0, 1]
    depth_bounds: np.ndarray | None = None   # float64 [N, 2]: per view the (near, far) depth of
    #                                    the scene along its viewing axis, in the poses' units
    #                                    (forward-facing captures: LLFF's bounds, rescaled with the
    #                                    poses; None elsewhere); clrf.data.world uses them

    @property
    def hw(self):
        return self.images.shape[1:3]

    def unit_far(self) -> float:
        """How far along a UNIT direction the scene's rays run (clrf.data.cameras.ndc_reach:
        ``far`` unless the rays are in NDC): the far bound of samplers that step along unit
        directions."""
        from .cameras import ndc_reach
        return ndc_reach(self)
