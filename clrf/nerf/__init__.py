"""NeRF: the fused MLP (mlp.py, cl/mlp.cl), encoding / sampling / compositing wrappers (ops.py,
cl/encode.cl, cl/sample.cl, cl/composite.cl) and the model with its typed options (model.py)."""
from .model import NerfConfig, NerfModel

__all__ = ["NerfConfig", "NerfModel"]
