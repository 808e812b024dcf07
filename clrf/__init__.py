"""clrf: portable OpenCL radiance fields (Plenoxels and NeRF) with handwritten kernels."""
from .runtime.device import Device, DeviceError
from .grid import SparseGrid
from .grid.render import render_rays, render_rays_backward


def __getattr__(name):
    # NeRF is imported on first use: grid-only users do not pay for building its kernels' host.
    if name in ("NerfModel", "NerfConfig"):
        from . import nerf
        return getattr(nerf, name)
    raise AttributeError(f"module 'clrf' has no attribute {name!r}")


__all__ = ["Device", "DeviceError", "SparseGrid", "render_rays", "render_rays_backward",
           "NerfModel", "NerfConfig"]
from .runtime.version import VERSION as __version__  # noqa: E402
