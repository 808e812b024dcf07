"""NeRF: the fused MLP (mlp.py, cl/mlp.cl) with its register tiles (tiling.py) and their tuner
(autotune.py), encoding / sampling / compositing wrappers (ops.py, cl/encode.cl, cl/sample.cl,
cl/composite.cl), the typed options (config.py), the model (model.py) and the device-choice
workload (workload.py)."""
from .model import NerfConfig, NerfModel

__all__ = ["NerfConfig", "NerfModel"]
