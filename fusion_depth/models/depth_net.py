"""``model=densedepth``, the paper's network: input fusion → pretrained encoder → DenseDepth
decoder (the paper, Sec. 3; Alhashim & Wonka 2018)."""

from __future__ import annotations

import torch

from fusion_depth.models._registry import Recipe, register_model
from fusion_depth.models.base import DepthModel
from fusion_depth.models.decoder import DenseDepthDecoder
from fusion_depth.models.encoder import Encoder
from fusion_depth.models.fusion import FUSION_MODES, InputFusion


# The paper's recipe (Siddiqui et al., Sec. IV): DenseNet-169 from ImageNet, SSIM + edge + L1 on
# reciprocal depth 1:1:1, Adam 1e-4 (DenseDepth's too: Alhashim & Wonka 2018, Sec. 3.4), lr × 0.2
# every 7 epochs, batch 2 and 20 epochs (conf/train.yaml and the trainer's defaults).
@register_model(
    "densedepth",
    label="DenseDepth",
    paper="Alhashim & Wonka 2018, fused as in the paper (Sec. 3)",
    fusions=FUSION_MODES,  # every mode InputFusion has
    recipe=Recipe(
        backbone="densenet169",
        loss="l1",
        optimizer="adam",
        schedule="step",
        schedule_args={"step_size": 7, "gamma": 0.2},
    ),
)
class DepthNet(DepthModel):
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
        backbone_taps: str = "paper",
    ) -> None:
        super().__init__(min_depth, max_depth, depth_scale)
        # backbone_taps: paper (the paper's DenseNet/ResNet taps) | pyramid (any timm model's
        # own feature pyramid, backbone=timm); see fusion_depth.models.encoder.Encoder.
        self.encoder = Encoder(backbone, pretrained=pretrained, weights=weights, taps=backbone_taps)
        self.fusion = InputFusion(
            fusion,
            max_depth=max_depth,
            min_depth=min_depth,
            sparse_encoding=sparse_encoding,
            mean=self.encoder.mean,
            std=self.encoder.std,
        )
        self.decoder = DenseDepthDecoder(self.encoder.channels)

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        self.check_input_size(image)
        # fp32 out even under autocast: depth = scale / reciprocal, the loss and the metrics
        # need more than bf16's 3 significant digits.
        return self.decoder(self.encoder(self.fusion(image, sparse))).float()
