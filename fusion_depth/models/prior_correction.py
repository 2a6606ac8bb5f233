"""``model=prior_correction``: RadarCam-Depth's pipeline (Li et al., ICRA 2024, Sec. III): a frozen
monocular prior made metric frame by frame by the radar (global alignment), a quasi-dense map of
the radar's depth, and their Scale Map Learner (SML), which corrects the aligned prior pixel by
pixel. The learner is theirs layer for layer, proved equal to their code
(:mod:`fusion_depth.models.scale_map_learner`); around it:

1. ``prior=...`` gives relative inverse depth (or a metric prior's metres), frozen
   (:mod:`fusion_depth.models.depth_prior`).
2. **Global alignment** (their Sec. III-B): a relative prior, normalised per frame (which
   changes no affine fit), is scaled and shifted to the frame's radar returns in inverse depth,
   a metric prior scaled in metres, by RANSAC over the returns with a least-squares refit
   (:func:`~fusion_depth.models.alignment.fit_scale_shift`); a frame without a fit takes the
   running median fit of training (a buffer, like batch norm's). Their code fits in depth
   (``data/global_alignment.py``); their paper, and this, in inverse depth, where a relative
   prior's model is exact.
3. **Quasi-dense depth** (their Sec. III-C, RC-Net): ``quasi_dense=association`` runs a trained
   RadarNet association network (``model=radarnet stage=association``, frozen, from
   ``association_weights``): RC-Net is that network with a linear-attention transformer between
   each point's and its window's features (``RCNet/`` of their code), which is not built here,
   and its quasi-dense map is RadarNet's (threshold, most confident point per pixel).
   ``quasi_dense=radar`` takes the frame's sparse radar map as it is (each return as the
   dataset draws it): no network, the scaffold VI-Depth builds from sparse points.
4. **The scale map learner** (their Sec. III-D; :class:`~fusion_depth.models.scale_map_learner.
   ScaleMapLearner`): the aligned inverse depth and the scaffold (1 where no point, the scale
   that takes the aligned inverse depth to the quasi-dense one where there is, min-max
   normalised per frame), normalised with their statistics, in; ``pred = d · ReLU(1 + out)``
   out, inverse depth clipped to the depth range. The learner starts at ``out`` near 0: near
   the aligned prior. It runs at the input's size (theirs resizes to a side of 288 first).
5. **Their loss**: smooth L1 on depth in metres against the ground truth
   (:func:`~fusion_depth.models.scale_map_learner.sml_loss`; their second term, 3 × smooth L1
   against the single lidar scan, needs a second ground truth, which the platform's samples do
   not carry: it is left out).

Why ``d · ReLU(1 + out)`` trains at a learning rate where the earlier design did not: its scale
is linear in the output, so a large output is a large correction, not ``exp`` of it (the earlier
``exp(r)`` overflowed at 3e-3); gradient clipping is in the built-in recipe besides.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
import torch.nn.functional as F

from fusion_depth.errors import ArgumentError, check_choice
from fusion_depth.models._registry import Recipe, check_model_takes, register_model
from fusion_depth.models.alignment import (
    DEFAULT_RANSAC_ITERATIONS,
    DEFAULT_RANSAC_THRESHOLD,
    FallbackCount,
    check_alignment_arguments,
    fit_scale_shift,
    prior_kind,
)
from fusion_depth.models.base import DepthModel
from fusion_depth.models.depth_prior import (
    build_prior,
    keep_prior_out_of_checkpoints,
    normalized_prior,
)
from fusion_depth.models.fusion import InputMode
from fusion_depth.models.scale_map_learner import (
    BACKBONE,
    FEATURES,
    INT_DEPTH_MEAN,
    INT_DEPTH_STD,
    INT_SCALES_MEAN,
    INT_SCALES_STD,
    LEARNING_RATES,
    LEARNING_SCHEDULE,
    ScaleMapLearner,
    load_released,
    scale_scaffold,
    sml_loss,
    sml_prediction,
)

QUASI_DENSE_SOURCES = ("radar", "association")


# Their recipe (sml_train_zju.py, sml_main.py): Adam, 2e-4 for 20 epochs then 1e-4 to 80, batch
# 1, their own loss (training_loss), the ImageNet EfficientNet-Lite3 encoder.
@register_model(
    "prior_correction",
    label="Prior + scale map",
    paper="RadarCam-Depth (Li et al., ICRA 2024): global alignment, quasi-dense depth, scale map",
    fusions=("concat",),
    backbones=(BACKBONE,),
    needs_prior=True,
    recipe=Recipe(
        backbone=BACKBONE,
        loss="l1_only",  # not used: the model's own loss (training_loss)
        optimizer="adam",
        optimizer_args={"lr": LEARNING_RATES[0]},
        schedule="step",
        schedule_args={"step_size": LEARNING_SCHEDULE[0], "gamma": 0.5},
        batch_size=1,
        max_epochs=LEARNING_SCHEDULE[-1],
    ),
)
class PriorCorrection(FallbackCount, DepthModel):
    """The aligned prior corrected by RadarCam-Depth's scale map learner, in reciprocal depth
    (module docstring).

    Args:
        prior: the ``prior`` config node (``name``, ``weights``, ``input_size``, ``kind``, ...;
            ``dropout`` and ``cache`` are not its concern). Required.
        backbone: the learner's encoder: their ``tf_efficientnet_lite3`` only.
        fusion: ``concat``: the image and the radar.
        pretrained: the encoder's ImageNet weights (what their training starts from).
        weights: their released learner, ``model-<step>.pth`` (``sml_dpt_var/model-6000.pth``),
            loaded strictly (:func:`~fusion_depth.models.scale_map_learner.load_released`).
        min_depth: the depth range's lower end in metres.
        max_depth: its upper end in metres.
        depth_scale: ``depth_scale / depth`` is the output's value.
        quasi_dense: ``radar`` (the sparse map as it is) or ``association`` (a trained RadarNet
            association network's quasi-dense map).
        association_weights: with ``quasi_dense=association``, a ``model=radarnet
            stage=association`` checkpoint (its association network, frozen; kept in this
            model's checkpoints).
        features: the learner's width (64 as theirs).
        ransac_iterations: the global fit's RANSAC samples (0: least squares).
        ransac_threshold: its inlier bound (a relative error).
        fit_momentum: the weight of a batch's median fit in the running fit.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1], H and W multiples of 32; sparse: (B, 1, H, W)
          metres, 0 = no return; points: (B, P, 6) ``radar_points`` or None; prior: (B, 1, H,
          W) the cached prior or None.
        - output: (B, 1, H, W) reciprocal depth, at the input's resolution.

    Raises:
        ArgumentError: no prior, a fusion mode other than ``concat``, an unknown
            ``quasi_dense``, ``association`` without ``association_weights``, or a setting out
            of range; naming it.
    """

    takes_points = True  # the global fit samples each radar return once, where the batch has them

    def __init__(
        self,
        prior: Mapping[str, Any] | None = None,
        backbone: str = BACKBONE,
        fusion: str = "concat",
        pretrained: bool = False,
        weights: str | None = None,
        min_depth: float = 0.5,
        max_depth: float = 80.0,
        depth_scale: float = 10.0,
        quasi_dense: str = "radar",
        association_weights: str | None = None,
        features: int = FEATURES,
        ransac_iterations: int = DEFAULT_RANSAC_ITERATIONS,
        ransac_threshold: float = DEFAULT_RANSAC_THRESHOLD,
        fit_momentum: float = 0.01,
    ) -> None:
        super().__init__(min_depth, max_depth, depth_scale)
        spec = {**dict(prior or {})}
        check_model_takes("prior_correction", fusion, backbone, prior=spec.get("name", "none"))
        if not spec.pop("enabled", True):
            raise ArgumentError(
                "{prior}=none: model=prior_correction corrects its prior and cannot run without it",
                "prior",
                owner=type(self),
            )
        check_choice(quasi_dense, QUASI_DENSE_SOURCES, "quasi_dense", owner=type(self))
        check_alignment_arguments(ransac_iterations, ransac_threshold, owner=type(self))
        if not 0 <= fit_momentum <= 1:
            raise ArgumentError(
                f"{{fit_momentum}}={fit_momentum}: expected a share in [0, 1]",
                "fit_momentum",
                owner=type(self),
            )
        for key in ("dropout", "cache"):  # a plug-in's and the runner's, not the correction's
            spec.pop(key, None)
        self.prior = build_prior(**spec)
        self.kind = prior_kind(self.prior)
        keep_prior_out_of_checkpoints(self)
        self.fusion = InputMode(fusion, uses_sparse=True)
        self.learner = ScaleMapLearner(features, pretrained=pretrained)
        if weights:
            load_released(self.learner, weights, argument="weights")
        self.quasi_dense = quasi_dense
        self.association = None
        if quasi_dense == "association":
            self.association = self._association(association_weights, min_depth, max_depth)
        # Whether the association network holds trained weights (loaded here, or with a state
        # dict of this model): saved with the weights, so a rebuilt model knows it too.
        self.register_buffer("association_loaded", torch.tensor(bool(association_weights)))
        self.ransac_iterations, self.ransac_threshold = ransac_iterations, ransac_threshold
        self.fit_momentum = fit_momentum
        self.register_buffer("fit_mean", torch.tensor([1.0, 0.0]))  # (scale, shift) of training
        self.reset_fits()

    @staticmethod
    def _association(weights: str | None, min_depth: float, max_depth: float) -> DepthModel:
        """RadarNet's association stage, frozen; its weights from ``weights`` (none when the
        model is rebuilt from its own checkpoint, which holds them)."""
        from fusion_depth.models.radarnet import RadarNet

        net = RadarNet(
            stage="association",
            association_weights=weights,
            min_depth=min_depth,
            max_depth=max_depth,
        )
        return net.eval().requires_grad_(False)

    def train(self, mode: bool = True) -> PriorCorrection:
        super().train(mode)
        if self.association is not None:
            self.association.eval()  # frozen: its batch norms keep their statistics
        return self

    @torch.no_grad()
    def aligned_inverse(
        self, given: torch.Tensor, sparse: torch.Tensor, points: torch.Tensor | None
    ) -> torch.Tensor:
        """The globally aligned prior as inverse depth in 1/m, clipped to the depth range, in
        fp32: a relative prior (normalised per frame) scaled and shifted in inverse depth, a
        metric one scaled in metres; a frame without a fit takes its batch's median fit, or in
        a batch without any the running fit (updated in training by the batch's median fit).
        The fit runs in float64 whatever the autocast.

        Shape:
            - given, sparse: (B, 1, H, W); points: (B, P, 6) or None; output: (B, 1, H, W).
        """
        with torch.autocast(given.device.type, enabled=False):
            prior = given.float() if self.kind == "metric" else normalized_prior(given.float())
            fit = fit_scale_shift(
                prior,
                sparse.float(),
                self.kind,
                self.ransac_iterations,
                self.ransac_threshold,
                fallback=self.fit_mean,
                points=points,
            )
            self.count_fits(fit)
            own = ~fit.fallback
            if self.training and bool(own.any()):
                batch = torch.stack([fit.scale[own].median(), fit.shift[own].median()])
                self.fit_mean.lerp_(batch.to(self.fit_mean), self.fit_momentum)
            scale = fit.scale.to(prior.device, torch.float32).view(-1, 1, 1, 1)
            shift = fit.shift.to(prior.device, torch.float32).view(-1, 1, 1, 1)
            fitted = scale * prior + shift  # inverse depth (relative) or metres (metric)
            inverse = fitted if self.kind == "relative" else 1.0 / fitted.clamp_min(1e-6)
            return inverse.clamp(1.0 / self.max_depth, 1.0 / self.min_depth)

    @torch.no_grad()
    def quasi_dense_depth(
        self, image: torch.Tensor, sparse: torch.Tensor, points: torch.Tensor | None
    ) -> torch.Tensor:
        """The quasi-dense radar depth in metres (0 = none): the sparse map, or the
        association network's map (:attr:`quasi_dense`)."""
        if self.association is None:
            return sparse.float()
        if not torch.compiler.is_exporting() and not bool(self.association_loaded):
            raise ArgumentError(
                "{quasi_dense}=association needs a trained association network: give "
                "{association_weights}=<a model=radarnet stage=association checkpoint>",
                "quasi_dense",
                "association_weights",
                owner=PriorCorrection,
            )
        return self.association(image, sparse, points).float()

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
        given = self.prior(image) if prior is None else prior
        d = self.aligned_inverse(given, sparse, points)
        quasi = self.quasi_dense_depth(image, sparse, points)
        # d is clipped to the depth range: positive and finite, nothing to check
        scaffold = scale_scaffold(
            quasi, 1.0 / d, 0.0, self.max_depth, constant_frames="zero", check=False
        )
        x = torch.cat(
            [(d - INT_DEPTH_MEAN) / INT_DEPTH_STD, (scaffold - INT_SCALES_MEAN) / INT_SCALES_STD],
            dim=1,
        )
        pred, _ = sml_prediction(self.learner(x).float(), d, self.min_depth, self.max_depth)
        return self.depth_scale * pred  # reciprocal output space: depth_scale / depth

    def fit_summary(self) -> dict[str, Any]:
        """The fit's settings, and its frame fits and fallbacks since :meth:`reset_fits`."""
        settings = {"kind": self.kind, "ransac_iterations": self.ransac_iterations}
        return {**settings, **super().fit_summary()}

    def training_loss(
        self,
        batch: Mapping[str, Any],
        depth_loss: Callable[[torch.Tensor, torch.Tensor], dict[str, torch.Tensor]],
    ) -> dict[str, torch.Tensor]:
        """Their loss (:func:`~fusion_depth.models.scale_map_learner.sml_loss`, smooth L1 on
        depth in metres against the ground truth; module docstring, 5); ``depth_loss`` (the
        ``loss=`` group) is not used. A batch without ground truth gives 0."""
        output = self(
            batch["image"], batch["sparse"], batch.get("radar_points"), prior=batch.get("prior")
        )
        depth = self.depth_scale / output.float()
        target = batch["depth"].float()
        if target.shape[-2:] != depth.shape[-2:]:
            target = F.interpolate(target, size=depth.shape[-2:], mode="nearest")
        target = torch.where(torch.isfinite(target), target, 0.0)
        if not bool((target > 0).any()):
            zero = depth.sum() * 0.0
            return {"loss": zero, "smooth_l1": zero.detach()}
        loss, _ = sml_loss(depth, target, torch.zeros_like(target), w_lidar=0.0)
        return {"loss": loss, "smooth_l1": loss.detach()}
