"""The paper's network: input fusion → pretrained encoder → DenseDepth decoder."""

from __future__ import annotations

import torch
from torch import nn

from fusion_depth.models.decoder import DenseDepthDecoder
from fusion_depth.models.encoder import Encoder
from fusion_depth.models.fusion import InputFusion


class DepthNet(nn.Module):
    """Predicts reciprocal depth ``depth_scale / depth`` at half the input resolution.

    ``forward`` returns the reciprocal map the loss is computed on; ``predict_depth`` returns
    metres, clipped to ``[min_depth, max_depth]``, for everything outside training.
    """

    def __init__(
        self,
        backbone: str = "densenet169",
        fusion: str = "rgb",
        pretrained: bool = False,
        weights: str | None = None,
        min_depth: float = 0.5,
        max_depth: float = 80.0,
        depth_scale: float = 10.0,
        sparse_encoding: str = "log",
    ) -> None:
        super().__init__()
        if not 0 < min_depth < max_depth:
            raise ValueError(
                f"depth range min_depth={min_depth}, max_depth={max_depth}: "
                "expected 0 < min_depth < max_depth"
            )
        if depth_scale <= 0:
            raise ValueError(f"depth_scale={depth_scale}: expected a positive number")
        self.encoder = Encoder(backbone, pretrained=pretrained, weights=weights)
        self.fusion = InputFusion(
            fusion,
            max_depth=max_depth,
            min_depth=min_depth,
            sparse_encoding=sparse_encoding,
            mean=self.encoder.mean,
            std=self.encoder.std,
        )
        self.decoder = DenseDepthDecoder(self.encoder.channels)
        self.min_depth, self.max_depth, self.depth_scale = min_depth, max_depth, depth_scale

    @property
    def reciprocal_range(self) -> tuple[float, float]:
        """The reciprocal-depth values of max_depth and min_depth."""
        return self.depth_scale / self.max_depth, self.depth_scale / self.min_depth

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        height, width = image.shape[-2:]
        if height % 32 or width % 32:
            raise ValueError(
                f"input size {height}×{width}: height and width must be multiples of 32"
            )
        # fp32 out even under autocast: depth = scale / reciprocal, the loss and the metrics
        # need more than bf16's 3 significant digits.
        return self.decoder(self.encoder(self.fusion(image, sparse))).float()

    def to_reciprocal(self, depth: torch.Tensor) -> torch.Tensor:
        """Metres → clipped reciprocal depth (invalid zeros map to the far end; mask them)."""
        low, high = self.reciprocal_range
        return (self.depth_scale / depth.clamp_min(1e-6)).clamp(low, high)

    def to_depth(self, reciprocal: torch.Tensor) -> torch.Tensor:
        """Clipped reciprocal depth → metres in [min_depth, max_depth]."""
        low, high = self.reciprocal_range
        return self.depth_scale / reciprocal.clamp(low, high)

    def predict_depth(
        self, image: torch.Tensor, sparse: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Depth in metres at half the input resolution."""
        return self.to_depth(self.forward(image, sparse))
