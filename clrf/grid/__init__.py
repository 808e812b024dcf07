"""Plenoxels: the sparse SH voxel grid (grid.py), its render kernels' host wrappers (render.py),
training ops on it (ops.py: total variation, pruning, resampling) and the training model
(model.py) the trainer drives. Kernels: cl/grid_render.cl, cl/march.h, cl/grid_ops.cl."""
from . import selfcheck  # noqa: F401 - registers the grid's gradient check with the runtime
from .grid import SparseGrid, sh_dim

__all__ = ["SparseGrid", "sh_dim"]
