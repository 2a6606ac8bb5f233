"""``model=prior_correction``: a frozen monocular prior made metric by the frame's radar, then
corrected pixel by pixel by a learned network: the pipeline of RadarCam-Depth (Li et al., ICRA
2024), global scale-and-shift alignment followed by a learned scale map, with the platform's
DenseDepth encoder-decoder as the learner (the authors' nuScenes code is unreleased).

1. ``prior=...`` gives relative inverse depth (frozen; :mod:`fusion_depth.models.depth_prior`).
2. Mapped to [0, 1] per frame (:func:`~fusion_depth.models.depth_prior.normalized_prior`, which
   changes no affine fit), its scale and shift are fitted to the frame's radar returns in
   inverse depth by RANSAC with a least-squares refit
   (:func:`~fusion_depth.models.alignment.fit_scale_shift`); a frame without a fit (too few
   returns, or none keeping the depth order) takes the running median fit of training (a
   buffer, like batch norm's).
3. The learner sees the image, the sparse returns and the aligned depth (the last two
   log-encoded as :class:`~fusion_depth.models.fusion.InputFusion` encodes sparse depth) and
   predicts a log-scale map ``r`` at half resolution, bounded softly to ±2 (``2 tanh(x / 2)``);
   the output is the aligned inverse depth (clipped to the depth range) times ``exp(r)``, in
   reciprocal depth. ``r`` starts at 0, so before training the model is the global alignment.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from fusion_depth.errors import ArgumentError
from fusion_depth.models._registry import Recipe, check_model_takes, register_model
from fusion_depth.models.alignment import (
    DEFAULT_RANSAC_ITERATIONS,
    FallbackCount,
    fit_scale_shift,
)
from fusion_depth.models.depth_net import DepthNet
from fusion_depth.models.depth_prior import normalized_prior

# The learned scale's bound: |r| ≤ 2, a correction by a factor of at most e² ≈ 7.4 either way.
MAX_LOG_SCALE = 2.0


# No published recipe for nuScenes (its code is unreleased): the platform's DenseDepth one with
# ResNet-18, which the built-in dataset trains in minutes.
@register_model(
    "prior_correction",
    label="Prior + correction",
    paper="RadarCam-Depth (Li et al., ICRA 2024): global alignment, then a learned scale map",
    fusions=("concat",),
    needs_prior=True,
    recipe=Recipe(
        backbone="resnet18",
        loss="l1",
        optimizer="adam",
        schedule="step",
        schedule_args={"step_size": 7, "gamma": 0.2},
    ),
)
class PriorCorrection(FallbackCount, DepthNet):
    """The aligned prior times a learned per-pixel scale, in reciprocal depth.

    Args:
        prior: the ``prior`` config node (``name``, ``weights``, ``input_size``; ``dropout`` is
            for networks that take the prior as an input and is ignored here). Required.
        backbone: the learner's encoder (:class:`~fusion_depth.models.encoder.Encoder`).
        fusion: ``concat``: the image and the sparse returns.
        pretrained: ImageNet weights for the encoder.
        weights: the encoder's weights from a local file.
        min_depth: the depth range's lower end in metres.
        max_depth: its upper end in metres.
        depth_scale: ``depth_scale / depth`` is the output's value.
        backbone_taps: the encoder's feature taps (``paper`` or ``pyramid``).
        sparse_encoding: how the returns and the aligned depth enter (``log`` or ``linear``).
        fit_momentum: the weight of a batch's median fit in the running fit.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1]; sparse: (B, 1, H, W) metres, 0 = no return.
        - output: (B, 1, H/2, W/2) reciprocal depth.

    Raises:
        ArgumentError: no prior (``prior=none``), or a fusion mode other than ``concat``.
    """

    takes_points = True  # the global fit samples each radar return once, where the batch has them

    def __init__(
        self,
        prior: Mapping[str, Any] | None = None,
        backbone: str = "resnet18",
        fusion: str = "concat",
        pretrained: bool = False,
        weights: str | None = None,
        min_depth: float = 0.5,
        max_depth: float = 80.0,
        depth_scale: float = 10.0,
        backbone_taps: str = "paper",
        sparse_encoding: str = "log",
        fit_momentum: float = 0.01,
    ) -> None:
        spec = {**dict(prior or {}), "dropout": 0.0}  # the prior is always there
        check_model_takes("prior_correction", fusion=fusion, prior=spec.get("name", "none"))
        if not spec.get("enabled", True):
            raise ArgumentError(
                "{prior}=none: model=prior_correction corrects its prior and cannot run without it",
                "prior",
                owner=type(self),
            )
        if not 0 <= fit_momentum <= 1:
            raise ArgumentError(
                f"{{fit_momentum}}={fit_momentum}: expected a share in [0, 1]",
                "fit_momentum",
                owner=type(self),
            )
        # DenseDepth's encoder, input fusion with the prior's channel, and decoder
        super().__init__(
            backbone,
            fusion,
            pretrained,
            weights,
            min_depth,
            max_depth,
            depth_scale,
            sparse_encoding,
            backbone_taps,
            prior=spec,
        )
        nn.init.zeros_(self.decoder.head.weight)  # r = 0: the global alignment at the start
        nn.init.zeros_(self.decoder.head.bias)
        self.fit_momentum = fit_momentum
        self.register_buffer("fit_mean", torch.tensor([1.0, 0.0]))  # (scale, shift) of training

    @torch.no_grad()
    def global_fit(
        self, relative: torch.Tensor, sparse: torch.Tensor, points: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Inverse depth in 1/m: ``relative`` scaled and shifted to each frame's returns by
        RANSAC (:func:`~fusion_depth.models.alignment.fit_scale_shift`, one sample per return
        where ``points`` are given), the running fit where a frame has none; updates the
        running fit in training with the batch's median fit. Computed in float64 whatever the
        autocast: bf16's 8 bits of mantissa move the fitted shift by 10 % and more.

        Shape:
            - relative, sparse: (B, 1, H, W); points: (B, P, 6) or None; output: (B, 1, H, W),
              fp32.
        """
        with torch.autocast(relative.device.type, enabled=False):
            fit = fit_scale_shift(
                relative.float(),
                sparse.float(),
                "relative",
                fallback=tuple(self.fit_mean.tolist()),
                points=points,
            )
        self.count_fits(fit)
        fitted = ~fit.fallback
        if self.training and bool(fitted.any()):
            batch = torch.stack([fit.scale[fitted].median(), fit.shift[fitted].median()])
            self.fit_mean.lerp_(batch.to(self.fit_mean), self.fit_momentum)
        scale = fit.scale.to(relative.device, torch.float32).view(-1, 1, 1, 1)
        shift = fit.shift.to(relative.device, torch.float32).view(-1, 1, 1, 1)
        # In the depth range: a fit extrapolated to the frame's nearest pixels may say 1 cm.
        return (scale * relative.float() + shift).clamp(1.0 / self.max_depth, 1.0 / self.min_depth)

    def fit_summary(self) -> dict[str, Any]:
        """The fit's settings, and its frame fits and fallbacks since :meth:`reset_fits`."""
        settings = {"kind": "relative", "ransac_iterations": DEFAULT_RANSAC_ITERATIONS}
        return {**settings, **super().fit_summary()}

    def forward(
        self,
        image: torch.Tensor,
        sparse: torch.Tensor | None = None,
        points: torch.Tensor | None = None,
        prior: torch.Tensor | None = None,
    ) -> torch.Tensor:
        self.check_input_size(image)
        if sparse is None:
            raise ValueError("model=prior_correction needs the sparse depth map")
        # The fit is affine, so normalising the prior per frame changes no fit, and keeps an
        # SSI-trained prior's 1e5-sized values in range (and the cache's form, [0, 1]).
        relative = normalized_prior(self.prior(image) if prior is None else prior.float())
        inverse = self.global_fit(relative, sparse, points)
        aligned = self.fusion.encode_sparse((1.0 / inverse).clamp(self.min_depth, self.max_depth))
        features = self.prior_branch(aligned, self.encoder(self.fusion(image, sparse)))
        raw = self.decoder(features).float()
        # Bounded softly (slope 1 at 0): an unbounded exp(r) overflowed within an epoch at the
        # built-in recipe's learning rate (training loss 1.5e5, then every depth at a clip).
        log_scale = MAX_LOG_SCALE * torch.tanh(raw / MAX_LOG_SCALE)
        base = F.interpolate(inverse, size=log_scale.shape[-2:], mode="bilinear")
        return self.depth_scale * base * torch.exp(log_scale)
