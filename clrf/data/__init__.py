"""Datasets and cameras. Loaders: Blender synthetic, tiny .npz, LLFF, COLMAP, instant-ngp
transforms.json, procedural; beside them the cameras (cameras.py: pixel rays, NDC, view_rays;
camera_models.py: lens distortion), the published evaluation protocols (protocols.py) and
``clrf process`` (process.py: a video or photos posed with COLMAP into a scene folder).

``load_dataset(path=None, **options)`` is the one entry point: it detects the layout of ``path``
and forwards ``options`` to that loader (see each loader for the options it accepts).
"""
from __future__ import annotations

from pathlib import Path

from .base import Dataset, DataError

LAYOUTS = (
    "Blender synthetic: a folder with transforms_train.json (+ _val, _test) and RGBA PNGs",
    "instant-ngp: a folder with transforms.json (fl_x/fl_y or camera_angle_x, frames)",
    "LLFF / Mip-NeRF 360: a folder with poses_bounds.npy and images_N/ or images/",
    "COLMAP: a folder with images/ and sparse/0/ (cameras, images, points3D as .bin or .txt)",
    "tiny NeRF: a .npz file with images, poses, focal (or a folder holding exactly one)",
    "procedural: no path (None) for the built-in analytic scene",
)


def detect_layout(path) -> str:
    """'blender', 'ngp', 'llff', 'colmap', 'npz' or 'procedural' for ``path``; DataError
    otherwise. A folder with both poses_bounds.npy and a COLMAP model reads as LLFF."""
    if path is None:
        return "procedural"
    p = Path(path)
    if p.is_file() and p.suffix == ".npz":
        return "npz"
    if p.is_dir():
        if (p / "transforms_train.json").is_file():
            return "blender"
        if (p / "transforms.json").is_file():
            return "ngp"
        if (p / "poses_bounds.npy").is_file():
            return "llff"
        from .colmap import is_colmap
        if is_colmap(p):
            return "colmap"
        if len(list(p.glob("*.npz"))) == 1:
            return "npz"
    what = "does not exist" if not p.exists() else "is not a dataset layout clrf can read"
    raise DataError(f"{p}: {what}; pass a path in one of the accepted layouts:\n  - "
                    + "\n  - ".join(LAYOUTS))


def load_dataset(path=None, **options) -> Dataset:
    """Load the scene at ``path`` (None: the procedural scene), detecting its layout.

    Example: load_dataset("data/lego_400", max_images=4, downscale=2).images.shape
    -> (12, 200, 200, 3)
    """
    layout = detect_layout(path)
    if layout == "procedural":
        from .synthetic import load_procedural
        return load_procedural(**options)
    if layout == "blender":
        from .blender import load_blender
        return load_blender(path, **options)
    if layout == "npz":
        from .npz import load_npz
        return load_npz(path, **options)
    if layout == "llff":
        from .llff import load_llff
        return load_llff(path, **options)
    if layout == "colmap":
        from .colmap import load_colmap
        return load_colmap(path, **options)
    from .ngp import load_ngp
    return load_ngp(path, **options)


__all__ = ["Dataset", "DataError", "LAYOUTS", "detect_layout", "load_dataset"]
