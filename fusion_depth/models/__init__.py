"""Depth networks: the table of models (created by name), their shared contract, and their parts
(timm encoders, the DenseDepth decoder, input fusion, up-projection)."""

from fusion_depth.models._registry import (
    DEFAULT_MODEL,
    MODELS,
    ModelEntry,
    Recipe,
    create_model,
    model_arguments,
    model_class,
    model_entry,
    network_from_checkpoint,
    network_state,
    register_model,
)
from fusion_depth.models.base import DepthModel
from fusion_depth.models.decoder import DenseDepthDecoder, UpBlock
from fusion_depth.models.depth_net import DepthNet
from fusion_depth.models.encoder import ENCODER_SPECS, Encoder, WeightsUnavailableError
from fusion_depth.models.fusion import FUSION_MODES, InputFusion

__all__ = [
    "DEFAULT_MODEL",
    "ENCODER_SPECS",
    "FUSION_MODES",
    "MODELS",
    "DenseDepthDecoder",
    "DepthModel",
    "DepthNet",
    "Encoder",
    "InputFusion",
    "ModelEntry",
    "Recipe",
    "UpBlock",
    "WeightsUnavailableError",
    "create_model",
    "model_arguments",
    "model_class",
    "model_entry",
    "network_from_checkpoint",
    "network_state",
    "register_model",
]
