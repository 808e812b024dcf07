"""The hash-grid model: multiresolution hash encoding + fused tiny MLPs + occupancy grid."""
from .encoding import HashEncoding, level_resolutions  # noqa: F401
