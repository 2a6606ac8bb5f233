"""fusion-depth: dense depth from a camera image fused with sparse radar or lidar depth."""

from fusion_depth.config import register_resolvers
from fusion_depth.version import __version__

__all__ = ["__version__"]

register_resolvers()
