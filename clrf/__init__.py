"""clrf: portable OpenCL radiance fields (Plenoxels and NeRF) with handwritten kernels."""
from .device import Device, DeviceError
from .grid import SparseGrid
from .render import render_rays, render_rays_backward

__all__ = ["Device", "DeviceError", "SparseGrid", "render_rays", "render_rays_backward"]
__version__ = "0.1.0"
