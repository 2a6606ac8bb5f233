"""Model components: encoder (timm), DenseDepth decoder, input fusion, and the assembled net."""

from fusion_depth.models.decoder import DenseDepthDecoder, UpBlock
from fusion_depth.models.depth_net import DepthNet
from fusion_depth.models.encoder import ENCODER_SPECS, Encoder, WeightsUnavailableError
from fusion_depth.models.fusion import FUSION_MODES, InputFusion

__all__ = [
    "ENCODER_SPECS",
    "FUSION_MODES",
    "DenseDepthDecoder",
    "DepthNet",
    "Encoder",
    "InputFusion",
    "UpBlock",
    "WeightsUnavailableError",
]
