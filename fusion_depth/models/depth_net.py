"""``model=densedepth``, the paper's network: input fusion → pretrained encoder → DenseDepth
decoder (the paper, Sec. 3; Alhashim & Wonka 2018)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch

from fusion_depth.errors import ArgumentError
from fusion_depth.models._registry import Recipe, register_model
from fusion_depth.models.base import DepthModel
from fusion_depth.models.decoder import DenseDepthDecoder
from fusion_depth.models.depth_prior import (
    NO_PRIOR,
    build_prior,
    keep_prior_out_of_checkpoints,
    normalized_prior,
)
from fusion_depth.models.encoder import Encoder
from fusion_depth.models.fusion import FUSION_MODES, InputFusion
from fusion_depth.models.prior_branch import PriorBranch


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

    ``prior`` (the ``prior`` config node: ``name``, ``weights``, ``input_size``, ``dropout``)
    adds a frozen monocular prior's relative depth as a further input, through its own branch
    (:class:`~fusion_depth.models.prior_branch.PriorBranch`, TacoDepth's plug-in mode), computed
    from the image (or given: a cached prior); in training
    a share ``dropout`` of the frames gets none, so that the network learns to work without it,
    and ``enabled: false`` serves it so (the prior is not built; its channel gets zeros). The
    prior's weights stay in their own files: a checkpoint holds the network's, and names the
    prior's file, from which the prior is built again when the checkpoint is loaded.

    Args:
        backbone: the encoder, a timm model name (``densenet169``, ``resnet50``, ``resnet10t``,
            ...; :class:`~fusion_depth.models.encoder.Encoder`).
        fusion: how the sparse depth enters: ``rgb`` (not at all), ``concat`` (as a further
            channel, mixed in by a 1×1 conv) or ``add`` (added to the image's channels).
        pretrained: start the encoder from its ImageNet weights (the local cache, else a
            download).
        weights: a local file of ImageNet weights for the encoder (``.safetensors`` or
            ``.pth``), instead of the cache or a download.
        min_depth: the smallest depth in metres the network predicts; predictions are clipped
            to ``[min_depth, max_depth]``.
        max_depth: the largest depth in metres the network predicts.
        depth_scale: the network predicts ``depth_scale / depth`` (the paper's 10).
        sparse_encoding: how a return at depth ``d`` enters: ``log``,
            ``log(d / min_depth) / log(max_depth / min_depth)``, or ``linear``,
            ``d / max_depth`` (0: no return, either way).
        backbone_taps: which encoder features feed the decoder: ``paper`` (the paper's
            DenseNet and ResNet layers) or ``pyramid`` (any timm model's own feature pyramid).
        prior: the ``prior`` config node (above); None or ``name: none``: no prior.

    Raises:
        ArgumentError: ``prior.dropout`` outside [0, 1], or an argument the encoder or the
            prior refuses, naming it.
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
        prior: Mapping[str, Any] | None = None,
    ) -> None:
        super().__init__(min_depth, max_depth, depth_scale)
        spec = dict(prior or {})
        self.prior_dropout = spec.pop("dropout", 0.0)
        if not 0 <= self.prior_dropout <= 1:
            raise ArgumentError(
                f"{{prior}}.dropout={self.prior_dropout}: expected a share in [0, 1]",
                "prior",
                owner=type(self),
            )
        spec.pop("cache", None)  # where the runner reads it from, not the network's concern
        # enabled: false serves a network trained with a prior without it: its channel gets
        # zeros, as prior.dropout trained it to take (evaluate ckpt_path=... prior=none).
        enabled = spec.pop("enabled", True)
        has_channel = spec.get("name", NO_PRIOR) != NO_PRIOR
        self.prior = build_prior(**spec) if enabled else None
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
        # The prior's own encoder, added to the image encoder's features (zero at the start).
        self.prior_branch = PriorBranch(self.encoder.channels) if has_channel else None
        self.decoder = DenseDepthDecoder(self.encoder.channels)
        if self.prior is not None:
            keep_prior_out_of_checkpoints(self)

    def prior_input(
        self, image: torch.Tensor, cached: torch.Tensor | None = None
    ) -> torch.Tensor | None:
        """The prior's channel for ``image``: its relative depth (``cached``, the batch's cached
        prior, or the prior run on ``image``) normalised per frame, zero for the frames dropped
        in training; None without a prior."""
        if self.prior is None:
            return None
        relative = self.prior(image) if cached is None else cached.float()
        prior = normalized_prior(relative)
        if self.training and self.prior_dropout > 0:
            kept = torch.rand(len(image), 1, 1, 1, device=image.device) >= self.prior_dropout
            prior = prior * kept
        return prior

    def forward(
        self,
        image: torch.Tensor,
        sparse: torch.Tensor | None = None,
        prior: torch.Tensor | None = None,
    ) -> torch.Tensor:
        self.check_input_size(image)
        features = self.encoder(self.fusion(image, sparse))
        if self.prior_branch is not None:  # no prior (dropped, or served without): zeros
            channel = self.prior_input(image, prior)
            if channel is None:
                channel = image.new_zeros((image.shape[0], 1, *image.shape[2:]))
            features = self.prior_branch(channel, features)
        # fp32 out even under autocast: depth = scale / reciprocal, the loss and the metrics
        # need more than bf16's 3 significant digits.
        return self.decoder(features).float()
