"""The fused MLP shared by the NeRF and hash-grid models: the host of cl/mlp.cl (mlp.py: MLP,
MLPSpec), its per-device tiles (tiling.py: CPU register tiles, the GPU tiling) and the tile
tuner (autotune.py)."""
from .mlp import MLP, MLPSpec  # noqa: F401
