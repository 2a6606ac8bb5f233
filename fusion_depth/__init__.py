"""fusion-depth: dense depth from a camera image fused with sparse radar or lidar depth."""

from fusion_depth.config import register_resolvers

__version__ = "0.1.0"

register_resolvers()
