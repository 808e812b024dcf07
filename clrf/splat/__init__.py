"""3D Gaussian splatting: the kernels (cl/splat_project.cl, cl/splat_raster.cl: projection of
anisotropic Gaussians, tile binning with a device sort, a tile rasteriser with its backward),
their host wrappers (raster.py) and the trainable model on them (model.py, ``--model splat``;
kind.py declares it to the registry)."""
from .raster import (GRAD2D_NAMES, PARAM_NAMES, Binned, Projected, Raster, SplatCamera,
                     SplatRasterizer)

__all__ = ["SplatRasterizer", "SplatCamera", "Projected", "Binned", "Raster", "PARAM_NAMES",
           "GRAD2D_NAMES"]
