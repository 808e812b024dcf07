"""Plenoxels: the sparse SH voxel grid (grid.py), its render kernels' host wrappers (render.py),
training ops on it (ops.py: total variation, pruning, resampling), its options (config.py) and
the training model (model.py) the trainer drives; the MSI background of unbounded scenes
(msi.py: the kernels' host; background.py: the model's use of it); the gradient self-check
(selfcheck.py) and the device-choice workload (workload.py); the distributed grid over MPI
(distributed.py, bricks.py, dist_model.py, dist_ops.py). Kernels: cl/grid_render.cl,
cl/march.h, cl/grid_ops.cl, cl/background.cl."""
from . import selfcheck  # noqa: F401 - registers the grid's gradient check with the runtime
from .grid import SparseGrid, sh_dim

__all__ = ["SparseGrid", "sh_dim"]
