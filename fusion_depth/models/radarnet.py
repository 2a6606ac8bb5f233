"""``model=radarnet``: Singh et al., "Depth Estimation from Camera Image and mmWave Radar Point
Cloud", CVPR 2023, as its authors' code builds it (github.com/nesl/radar-camera-fusion-depth:
``src/radarnet_model.py``, ``src/networks.py``, ``src/radarnet_main.py``,
``src/fusionnet_model.py``, ``src/fusionnet_losses.py``, ``bash/train_*_nuscenes.sh``).

Two stages (the paper's Sec. 3, Fig. 2):

1. **Radar-camera association** (Sec. 3.1; ``RadarNetV1Encoder`` + ``MultiScaleDecoder``). For
   each radar point the network sees the image in a *tall window* around the point's projection:
   the full image height (radar has no elevation) × ``window_width`` columns centred on the
   point's column ``u``. The reference's patch is 900 × 288 on 900 × 1600 nuScenes images
   (``--patch_size 900 288``): the full height and 18 % of the width; ``window_width=None``
   scales that fraction to the input width, rounded to a multiple of 32 (the encoder's stride).
   A ResNet encoder (timm) takes the window; the point's features ``(v / H, depth / max_depth,
   u / W)`` go through a fully connected encoder (32-64-128-128-128 neurons, as the reference's
   ``--n_neurons_encoder_depth``) whose output is tiled over the encoder's 1/32 grid and
   concatenated with the image latent; a skip-connected decoder (256-128-64-32-16 filters, the
   reference's ``--n_filters_decoder``) predicts one confidence logit per window pixel.
   Differences from the reference: it pools windows out of whole-image features
   (``torchvision.ops.roi_pool``) where this crops the image, and its point vector is mapped to
   a fixed-size grid (a fixed patch size) where this tiles it, so any input size works.
2. **Quasi-dense depth** (Sec. 3.2; ``radarnet_main.forward``). Confidences (sigmoid of the
   logits) below ``threshold`` (the reference's 0.5) are dropped; each pixel takes the depth of
   the point with the highest remaining confidence, and that confidence as a second channel; a
   pixel no point claims is 0 in both (:func:`quasi_dense_depth`).
3. **Fusion** (Sec. 3.3; ``FusionNetModel``). An image encoder (timm ResNet) and a depth encoder
   (convolutions, 16-32-64-128-128 channels, the reference's ``--n_filters_encoder_depth``) over
   the quasi-dense depth and confidence, fused by concatenation at every scale (the reference's
   ``fusion_type=concat``; its shipped script uses ``weight_and_project``), and a decoder to
   depth in metres, ``min / (sigmoid(x) + min / max)`` as the reference's output.

Training (``training_loss``):

* ``stage=association``: binary cross-entropy (``pos_weight`` 2.0, ``--w_positive_class``) on
  ``train_points`` sampled points per image (``--total_points_sampled 4``; with probability
  ``fake_point_probability`` an image's points are fakes drawn from its ground truth,
  ``--sample_probability_lidar``), against labels from
  the ground-truth depth: a window pixel belongs to the point when the ground truth there is
  within ``max_distance`` = 0.4 m (``--max_distance_correspondence``) of the point's depth;
  pixels without ground truth count as negatives (``--set_invalid_to_negative``), pixels
  outside the image do not count. On nuScenes the ground truth is the (accumulated) lidar, on
  the built-in dataset the exact depth. The network's depth output in this stage is the
  quasi-dense map, 0 where no point passes the threshold: the module scores only the pixels it
  fills, as the reference's validation does (``validate``: the intersection of output and
  ground truth).
* ``stage=fusion``: the association network is loaded from ``association_weights`` (a stage-1
  checkpoint of this platform) and frozen; L1 on depth in metres over the ground truth
  (``--loss_func l1``), i.e. ``loss=l1_only``. With a filled target and
  ``lidar_loss_weight`` (``--w_lidar_loss``), that loss over the filled pixels only, plus the
  weight times it over the measured ones.
* ``stage=end_to_end``: both networks trained together with the sum of the two losses (the
  paper trains the stages apart; the quasi-dense map is built from the confidences without a
  gradient through its arg-max, so the association learns from its own loss only).

Points come from the batch's ``radar_points`` ((B, P, 6), columns
:data:`fusion_depth.data.RADAR_POINT_FIELDS`). Without them (``predict`` from files, export)
they are derived from the sparse map (:func:`points_from_sparse`): its non-zero pixels, nearest
first, at most ``max_points`` of them; a return drawn as a vertical line
(``radar_height_extension``) then yields several points.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn

from fusion_depth.errors import ArgumentError
from fusion_depth.models._registry import Recipe, check_model_takes, register_model
from fusion_depth.models.base import DepthModel
from fusion_depth.models.encoder import create_timm_model
from fusion_depth.utils.checkpoint_file import CheckpointError, read_checkpoint
from fusion_depth.utils.schema import NON_NEGATIVE, POSITIVE_INT, PROBABILITY

BACKBONES = ("resnet18",)  # the reference's encoders are ResNet-18 style (fusionnet18, radarnetv1)
FUSIONS = ("concat",)  # image + quasi-dense radar depth
STAGES = ("association", "fusion", "end_to_end")
PAPER_IMAGE_SIZE = (900, 1600)  # nuScenes, height × width
PAPER_PATCH_SIZE = (900, 288)  # bash/train_radarnet_nuscenes.sh: --patch_size 900 288
MAX_DISTANCE_CORRESPONDENCE = 0.4  # m, --max_distance_correspondence
POSITIVE_CLASS_WEIGHT = 2.0  # --w_positive_class
RESPONSE_THRESHOLD = 0.5  # radarnet_main.forward: responses < 0.5 set to 0
POINTS_PER_IMAGE = 4  # --total_points_sampled
# Fake radar points from the ground truth (src/datasets.py, RadarNetTrainingDataset): a frame's
# points are replaced, with probability --sample_probability_lidar (0.10 in
# bash/train_radarnet_nuscenes.sh), by ground-truth pixels deeper than 1 m, their column moved
# by N(0, 25) pixels at 1600 columns and their depth by U(0, 0.4) m; rows stay the radar's.
FAKE_COLUMN_NOISE = 25.0  # pixels at PAPER_IMAGE_SIZE's width
FAKE_DEPTH_NOISE = 0.4  # m, the upper end of the uniform depth noise
FAKE_MIN_DEPTH = 1.0  # m: ground-truth pixels a fake point may start from are deeper
POINT_NEURONS = (32, 64, 128, 128, 128)  # --n_neurons_encoder_depth
ASSOCIATION_DECODER = (256, 128, 64, 32, 16)  # --n_filters_decoder
DEPTH_ENCODER = (16, 32, 64, 128, 128)  # --n_filters_encoder_depth (five of its six levels)
FUSION_DECODER = (256, 128, 64, 64, 32)  # --n_filters_decoder (five of its six levels)
U, V, DEPTH, VALID = 0, 1, 2, 5  # columns of RADAR_POINT_FIELDS


def default_window_width(image_width: int) -> int:
    """The paper's patch width relative to its image (288 / 1600) at ``image_width``, rounded to
    a multiple of 32 (at least 32): 224 at 1248, 32 at 96."""
    fraction = PAPER_PATCH_SIZE[1] / PAPER_IMAGE_SIZE[1]
    return max(32, round(fraction * image_width / 32) * 32)


def window_columns(u: torch.Tensor, width: int) -> torch.Tensor:
    """The image columns of the window around each point: ``width`` columns starting at
    ``round(u) - width // 2``; columns outside the image (< 0 or >= W) are the caller's to drop.

    Shape:
        - u: (...) pixel columns; output: (..., width) long.
    """
    start = torch.round(u).long() - width // 2
    return start.unsqueeze(-1) + torch.arange(width, device=u.device)


def crop_windows(x: torch.Tensor, u: torch.Tensor, width: int) -> torch.Tensor:
    """The tall window around each point: all rows of ``x``, the columns of
    :func:`window_columns`, zero where they fall outside the image.

    Shape:
        - x: (B, C, H, W); u: (B, P) pixel columns; output: (B, P, C, H, width).
    """
    b, c, h, w = x.shape
    p = u.shape[1]
    columns = window_columns(u, width)  # (B, P, width)
    inside = (columns >= 0) & (columns < w)
    index = columns.clamp(0, w - 1).view(b, p, 1, 1, width).expand(b, p, c, h, width)
    crops = torch.gather(x.unsqueeze(1).expand(b, p, c, h, w), 4, index)
    return crops * inside.view(b, p, 1, 1, width).to(x.dtype)


def paste_windows(values: torch.Tensor, u: torch.Tensor, image_width: int) -> torch.Tensor:
    """The inverse of :func:`crop_windows` for one channel: each point's window values placed at
    their image columns, 0 elsewhere and where a window leaves the image.

    Shape:
        - values: (B, P, H, width); u: (B, P); output: (B, P, H, image_width).
    """
    b, p, h, width = values.shape
    columns = window_columns(u, width)
    inside = (columns >= 0) & (columns < image_width)
    # Outside columns go to one spare column past the image, cut off afterwards.
    target = torch.where(inside, columns, torch.full_like(columns, image_width))
    out = values.new_zeros(b, p, h, image_width + 1)
    out.scatter_(3, target.view(b, p, 1, width).expand(b, p, h, width), values)
    return out[..., :image_width]


def quasi_dense_depth(
    confidence: torch.Tensor, depth: torch.Tensor, threshold: float = RESPONSE_THRESHOLD
) -> tuple[torch.Tensor, torch.Tensor]:
    """Sparse points → quasi-dense depth (the paper's Sec. 3.2): per pixel, the depth of the
    point with the highest confidence among those at least ``threshold``, and that confidence;
    0 and 0 where no point passes.

    Shape:
        - confidence: (B, P, H, W) in [0, 1] (0 outside a point's window and for padded rows);
          depth: (B, P) metres; outputs: (B, 1, H, W) metres and (B, 1, H, W) confidence.
    """
    passed = torch.where(confidence >= threshold, confidence, torch.zeros_like(confidence))
    best, which = passed.max(dim=1, keepdim=True)
    chosen = torch.gather(depth.to(best.dtype), 1, which.flatten(1)).view_as(best)
    return torch.where(best > 0, chosen, torch.zeros_like(chosen)), best


def association_labels(
    ground_truth: torch.Tensor,
    depth: torch.Tensor,
    max_distance: float = MAX_DISTANCE_CORRESPONDENCE,
) -> torch.Tensor:
    """The association ground truth (``radarnet_main.train``): 1 where the ground-truth depth is
    valid (> 0) and within ``max_distance`` metres of the point's depth, else 0.

    Shape:
        - ground_truth: (B, P, 1, H, w) metres, 0 = none (the windows of the depth map);
          depth: (B, P) metres; output: like ``ground_truth``, float 0/1.
    """
    distance = (ground_truth - depth.view(*depth.shape, 1, 1, 1)).abs()
    return ((ground_truth > 0) & (distance < max_distance)).to(ground_truth.dtype)


def points_from_sparse(sparse: torch.Tensor, max_points: int) -> torch.Tensor:
    """Radar points from a sparse depth map alone (``predict`` from files, export): its non-zero
    pixels, nearest first, at most ``max_points``; rows past the returns are zero (valid 0).

    Shape:
        - sparse: (B, 1, H, W) metres; output: (B, max_points, 6), columns RADAR_POINT_FIELDS.
    """
    b, _, h, w = sparse.shape
    flat = sparse.reshape(b, h * w).float()
    flat = torch.where(flat > 0, flat, torch.full_like(flat, float("inf")))
    k = min(max_points, h * w)
    values, index = torch.topk(flat, k, dim=1, largest=False)
    valid = torch.isfinite(values)
    points = sparse.new_zeros(b, max_points, 6, dtype=torch.float32)
    points[:, :k, U] = (index % w).float()
    points[:, :k, V] = torch.div(index, w, rounding_mode="floor").float()
    points[:, :k, DEPTH] = torch.where(valid, values, torch.zeros_like(values))
    points[:, :k, VALID] = valid.float()
    return points * points[..., VALID : VALID + 1]


def _conv(in_channels: int, out_channels: int, stride: int = 1) -> nn.Sequential:
    """3×3 convolution, batch norm, leaky ReLU (the reference's ``Conv2d`` with batch norm and
    its default ``leaky_relu``)."""
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.LeakyReLU(0.2),
    )


class SkipDecoder(nn.Module):
    """The reference's ``MultiScaleDecoder`` with ``deconv_type='up'`` and one output scale: from
    stride 32 to 1 in five blocks (bilinear 2× upsampling, conv, concatenation with the skip of
    that stride, conv), then a 3×3 convolution to one channel (linear).

    Shape:
        - latent: (N, C, H/32, W/32); skips: strides 2, 4, 8, 16 (finest first);
          output: (N, 1, H, W).
    """

    def __init__(self, latent: int, skips: Sequence[int], filters: Sequence[int]) -> None:
        super().__init__()
        skip_channels = [*reversed(skips), 0]  # strides 16, 8, 4, 2, then none at 1
        self.up = nn.ModuleList()
        self.merge = nn.ModuleList()
        previous = latent
        for out, skip in zip(filters, skip_channels, strict=True):
            self.up.append(_conv(previous, out))
            self.merge.append(_conv(out + skip, out))
            previous = out
        self.head = nn.Conv2d(previous, 1, 3, padding=1)

    def forward(self, latent: torch.Tensor, skips: Sequence[torch.Tensor]) -> torch.Tensor:
        x = latent
        for i, (up, merge) in enumerate(zip(self.up, self.merge, strict=True)):
            x = up(F.interpolate(x, scale_factor=2, mode="bilinear", align_corners=False))
            if i < len(skips):
                x = torch.cat([x, skips[-1 - i]], dim=1)
            x = merge(x)
        return self.head(x)


def _resnet_pyramid(backbone: str, pretrained: bool, weights: str | None) -> nn.Module:
    """A timm ResNet as a feature pyramid at strides 2, 4, 8, 16, 32."""
    return create_timm_model(
        backbone, pretrained, weights, features_only=True, out_indices=(0, 1, 2, 3, 4)
    )


class AssociationNet(nn.Module):
    """Radar-camera association (module docstring, stage 1): a tall image window and one point's
    features → a confidence logit per window pixel.

    Shape:
        - windows: (N, 3, H, w) RGB in [0, 1], H and w multiples of 32;
          features: (N, 3); output: (N, 1, H, w) logits.
    """

    def __init__(self, backbone: str, pretrained: bool, weights: str | None) -> None:
        super().__init__()
        self.encoder = _resnet_pyramid(backbone, pretrained, weights)
        channels = self.encoder.feature_info.channels()
        layers: list[nn.Module] = []
        previous = 3
        for n in POINT_NEURONS:
            layers += [nn.Linear(previous, n), nn.LeakyReLU(0.2)]
            previous = n
        self.point_encoder = nn.Sequential(*layers)
        self.decoder = SkipDecoder(
            channels[-1] + POINT_NEURONS[-1], channels[:-1], ASSOCIATION_DECODER
        )

    def forward(self, windows: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        *skips, latent = self.encoder(windows)
        point = self.point_encoder(features.to(latent.dtype))
        point = point[:, :, None, None].expand(-1, -1, *latent.shape[-2:])
        return self.decoder(torch.cat([latent, point], dim=1), skips)


class FusionNet(nn.Module):
    """Image + quasi-dense depth and confidence → depth (module docstring, stage 3).

    Shape:
        - image: (B, 3, H, W); radar: (B, 2, H, W) (depth / max_depth, confidence);
          output: (B, 1, H, W) logits, mapped to metres by :meth:`RadarNet.forward`.
    """

    def __init__(self, backbone: str, pretrained: bool, weights: str | None) -> None:
        super().__init__()
        self.image_encoder = _resnet_pyramid(backbone, pretrained, weights)
        blocks, previous = [], 2
        for out in DEPTH_ENCODER:
            blocks.append(nn.Sequential(_conv(previous, out, stride=2), _conv(out, out)))
            previous = out
        self.depth_encoder = nn.ModuleList(blocks)
        channels = [
            i + d
            for i, d in zip(self.image_encoder.feature_info.channels(), DEPTH_ENCODER, strict=True)
        ]
        self.decoder = SkipDecoder(channels[-1], channels[:-1], FUSION_DECODER)

    def forward(self, image: torch.Tensor, radar: torch.Tensor) -> torch.Tensor:
        image_features = self.image_encoder(image)
        x, fused = radar.to(image_features[0].dtype), []
        for block, features in zip(self.depth_encoder, image_features, strict=True):
            x = block(x)
            fused.append(torch.cat([features, x], dim=1))
        *skips, latent = fused
        return self.decoder(latent, skips)


class AssociationWeightsError(ArgumentError, CheckpointError):
    """``association_weights`` is no usable association checkpoint (a CheckpointError)."""


def _weights_error(message: str) -> AssociationWeightsError:
    return AssociationWeightsError(message, "association_weights", owner=RadarNet)


def _is_window(width: object) -> bool:
    return width is None or (POSITIVE_INT.ok(width) and width % 32 == 0)


class RadarInput(nn.Module):
    """The fusion-mode holder the platform reads (``mode``, ``uses_sparse``): RadarNet takes the
    image and the radar (``concat``) only."""

    def __init__(self, mode: str) -> None:
        super().__init__()
        self.mode = mode  # one of FUSIONS: create_model checks it against the registration

    @property
    def uses_sparse(self) -> bool:
        return True


# The reference code's fusion-network recipe (nesl/radar-camera-fusion-depth at c95c67d,
# bash/train_fusionnet_nuscenes.sh lines 24, 41-46, src/fusionnet_main.py lines 307-312):
# ResNet-18 encoders, L1 on metres, Adam 1e-3 without weight decay at one rate for all 450 epochs,
# batch 16. Its association stage trains with 2e-4, batch 6, 200 epochs
# (bash/train_radarnet_nuscenes.sh): with model.net.stage=association give optimizer.lr=2e-4.
@register_model(
    "radarnet",
    label="RadarNet",
    paper="Singh et al., CVPR 2023 (radar-camera association, then fusion)",
    fusions=FUSIONS,
    backbones=("resnet18",),
    sensors=("radar",),
    recipe=Recipe(
        backbone="resnet18",
        loss="l1_only",
        optimizer="adam",
        optimizer_args={"lr": 1.0e-3, "weight_decay": 0.0},
        schedule="constant",
        batch_size=16,
        max_epochs=450,
        # bash/train_fusionnet_nuscenes.sh, src/fusionnet_transforms.py: each colour operation
        # on its own draw (p 0.5), then a flip; its 448×448 crops: conf/experiment/nuscenes_radarnet
        augment={
            "brightness": [0.8, 1.2],
            "contrast": [0.8, 1.2],
            "saturation": [0.8, 1.2],
            "color_each": True,
            "color_p": 0.5,
            "flip_p": 0.5,
        },
    ),
)
class RadarNet(DepthModel):
    """Singh et al. 2023 (module docstring): association, quasi-dense depth, fusion.

    Args:
        backbone: the ResNet of both encoders (``resnet18``).
        fusion: ``concat`` (image + radar).
        stage: ``association`` (train the association; output the quasi-dense map), ``fusion``
            (association frozen, loaded from ``association_weights``; output dense depth) or
            ``end_to_end`` (both trained, sum of losses; output dense depth).
        association_weights: a ``stage=association`` (or ``end_to_end``) checkpoint of
            ``model=radarnet`` whose association network the fusion stage uses.
        window_width: the window's width in pixels (a multiple of 32); None: the paper's
            fraction of the input width (:func:`default_window_width`).
        max_distance: the association label's depth tolerance, metres.
        positive_weight: BCE weight of the positive class.
        threshold: the confidence a point needs to claim a pixel of the quasi-dense map.
        train_points: points sampled per image for the association loss.
        max_points: points taken from a sparse map when the batch carries none.
        fake_point_probability: ``stage=association`` training: the probability that an
            image's sampled points are replaced by fake ones from its ground truth
            (:meth:`_fake_points`; the reference's ``--sample_probability_lidar``, 0.10 in its
            nuScenes script and in ``conf/experiment/nuscenes_radarnet.yaml``). 0: none.
        fake_column_noise: the fake points' column noise σ in pixels; None: the reference's 25
            at 1600 columns, scaled to the input's width (set it when training on crops).
        lidar_loss_weight: the fusion network's loss on a filled target (FusionNet's
            ``compute_loss``, ``--w_lidar_loss 2.0``): the depth loss over the filled pixels
            only, plus this weight times it over the measured ones (the batch's
            ``depth_measured``); 0, or a batch without that map: the depth loss over the target.
        pretrained: ImageNet weights for the encoders, as for the other models.
        weights: a local file of those weights, as for the other models.
        min_depth: see :class:`~fusion_depth.models.base.DepthModel`.
        max_depth: see :class:`~fusion_depth.models.base.DepthModel`.
        depth_scale: see :class:`~fusion_depth.models.base.DepthModel`.

    Shape:
        - image: (B, 3, H, W); sparse: (B, 1, H, W) metres; points: (B, P, 6) or None;
          output: (B, 1, H, W) metres (``association``: 0 where no point claims the pixel).

    Raises:
        ValueError: a backbone, fusion mode, stage or setting the model does not define.
        fusion_depth.utils.checkpoint_file.CheckpointError: ``association_weights`` is not a
            radarnet checkpoint with an association network.
    """

    output_space = "depth"
    takes_points = True

    def __init__(
        self,
        backbone: str = "resnet18",
        fusion: str = "concat",
        stage: str = "end_to_end",
        association_weights: str | None = None,
        window_width: int | None = None,
        max_distance: float = MAX_DISTANCE_CORRESPONDENCE,
        positive_weight: float = POSITIVE_CLASS_WEIGHT,
        threshold: float = RESPONSE_THRESHOLD,
        train_points: int = POINTS_PER_IMAGE,
        max_points: int = 64,
        fake_point_probability: float = 0.0,
        fake_column_noise: float | None = None,
        lidar_loss_weight: float = 0.0,
        pretrained: bool = False,
        weights: str | None = None,
        min_depth: float = 0.5,
        max_depth: float = 80.0,
        depth_scale: float = 10.0,
    ) -> None:
        super().__init__(min_depth, max_depth, depth_scale)
        check_model_takes("radarnet", fusion, backbone)  # also when built directly
        checks = (
            ("stage", stage, stage in STAGES, f"one of {list(STAGES)}"),
            (
                "window_width",
                window_width,
                _is_window(window_width),
                "null or a positive multiple of 32",
            ),
            ("max_distance", max_distance, max_distance > 0, "a positive number"),
            ("positive_weight", positive_weight, positive_weight > 0, "a positive number"),
            ("threshold", threshold, 0 < threshold < 1, "a number in (0, 1)"),
            ("train_points", train_points, POSITIVE_INT.ok(train_points), "an integer >= 1"),
            ("max_points", max_points, POSITIVE_INT.ok(max_points), "an integer >= 1"),
            (
                "fake_point_probability",
                fake_point_probability,
                PROBABILITY.ok(fake_point_probability),
                "a probability in [0, 1]",
            ),
            (
                "fake_column_noise",
                fake_column_noise,
                fake_column_noise is None or NON_NEGATIVE.ok(fake_column_noise),
                "null or pixels >= 0",
            ),
            (
                "lidar_loss_weight",
                lidar_loss_weight,
                NON_NEGATIVE.ok(lidar_loss_weight),
                "a number >= 0",
            ),
        )
        for argument, value, ok, expected in checks:
            if not ok:
                raise ArgumentError(
                    f"{{{argument}}}={value!r}: expected {expected}", argument, owner=RadarNet
                )
        self.fusion = RadarInput(fusion)
        self.stage = stage
        self.window_width = window_width
        self.max_distance, self.positive_weight = max_distance, positive_weight
        self.threshold, self.train_points, self.max_points = threshold, train_points, max_points
        self.fake_point_probability = float(fake_point_probability)
        self.fake_column_noise = fake_column_noise
        self.lidar_loss_weight = float(lidar_loss_weight)
        self.association = AssociationNet(backbone, pretrained, weights)
        self.fusion_net = (
            FusionNet(backbone, pretrained, weights) if stage != "association" else None
        )
        # Whether the association network holds trained weights (stage-1 checkpoint loaded, or
        # trained here): saved with the weights, so a rebuilt fusion checkpoint knows it too.
        self.register_buffer("association_trained", torch.tensor(stage != "fusion"))
        if association_weights:
            self.load_association(association_weights)
        if stage == "fusion":
            self.association.requires_grad_(False)

    @property
    def wants_measured_depth(self) -> bool:
        """Whether training batches should carry the measured ground truth beside a filled
        target (``depth_measured``): for :attr:`lidar_loss_weight`."""
        return self.lidar_loss_weight > 0 and self.stage != "association"

    @property
    def partial_output(self) -> bool:
        """The association stage outputs the quasi-dense map, 0 where no point claims a pixel."""
        return self.stage == "association"

    # -- stage 1 weights --------------------------------------------------------------------

    def load_association(self, path: str | Path) -> None:
        """Load the association network of a ``model=radarnet`` checkpoint (weights only,
        through :func:`fusion_depth.utils.checkpoint_file.read_checkpoint`).

        Raises:
            CheckpointError: the file is not a readable training checkpoint, or not one of
                ``model=radarnet`` with an association network of this shape.
        """
        key = f"{{association_weights}}={path}"
        try:
            checkpoint = read_checkpoint(path)
        except (CheckpointError, FileNotFoundError) as err:
            # read_checkpoint names the file as ckpt_path=...; here it is this setting's.
            reason = str(err).split(": ", 1)[-1]
            raise _weights_error(f"{key}: {reason}") from None
        model = checkpoint["fusion_depth_config"].get("model")
        net = model.get("net") if isinstance(model, Mapping) else None
        name = net.get("name") if isinstance(net, Mapping) else None
        prefix = "net.association."
        state = {
            k[len(prefix) :]: v for k, v in checkpoint["state_dict"].items() if k.startswith(prefix)
        }
        if name != "radarnet" or not state:
            raise _weights_error(
                f"{key}: not a radarnet association checkpoint (it is model={name})"
            )
        try:
            self.association.load_state_dict(state)
        except RuntimeError as err:
            raise _weights_error(
                f"{key}: its association network does not fit this one ({str(err).splitlines()[0]})"
            ) from None
        self.association_trained.fill_(True)

    def train(self, mode: bool = True) -> RadarNet:
        super().train(mode)
        if self.stage == "fusion":
            self.association.eval()  # frozen: its batch-norm statistics stay the stage-1 ones
        return self

    # -- association --------------------------------------------------------------------------

    def window(self, image_width: int) -> int:
        """The window width at an input ``image_width`` (``window_width`` or the paper's)."""
        return self.window_width or default_window_width(image_width)

    def _points(self, sparse: torch.Tensor | None, points: torch.Tensor | None) -> torch.Tensor:
        if points is not None:
            if points.dim() != 3 or points.shape[-1] <= VALID:
                raise ValueError(
                    f"radar_points {tuple(points.shape)}: expected (B, P, 6) with the columns "
                    "u, v, depth, rcs, velocity, valid"
                )
            return points
        if sparse is None:
            raise ValueError("model=radarnet needs radar points or the sparse depth map")
        return points_from_sparse(sparse, self.max_points)

    def association_logits(self, image: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
        """The confidence logits of each point's window; 0 for padding rows (``valid`` = 0 or
        depth 0), which the network does not see.

        Shape:
            - image: (B, 3, H, W); points: (B, P, 6); output: (B, P, H, window) logits.
        """
        if self.stage == "fusion" and self.association.training:
            # Frozen, batch-norm statistics included; Lightning sets each submodule's mode on
            # its own around validation, past :meth:`train`.
            self.association.eval()
        b, _, h, w = image.shape
        p = points.shape[1]
        width = self.window(w)
        windows = crop_windows(image, points[..., U], width).reshape(b * p, 3, h, width)
        features = torch.stack(
            [points[..., V] / h, points[..., DEPTH] / self.max_depth, points[..., U] / w], dim=-1
        ).reshape(b * p, 3)
        # Only the windows of valid points go through the network. Padding rows fill each frame
        # up to a fixed P (60 % of the rows on the built-in dataset); they would cost as much as
        # the returns, and their logits are masked out anyway, so here they stay 0. Traced for
        # export, every row goes through (a data-dependent count does not export).
        keep = None
        if not torch.compiler.is_compiling():
            keep = ((points[..., VALID] > 0) & (points[..., DEPTH] > 0)).flatten()
            windows, features = windows[keep], features[keep]
        if image.device.type == "cpu":
            # In fp32 under bf16 autocast too: oneDNN's bf16 convolutions (torch 2.14, AMX)
            # return NaN at random on the 1-pixel-wide deepest features of a 32-column window.
            with torch.autocast("cpu", enabled=False):
                logits = self._associate(windows.float(), features.float())
        else:
            logits = self._associate(windows, features)
        if keep is not None:
            logits = logits.new_zeros(b * p, *logits.shape[1:]).index_put((keep,), logits)
        return logits.view(b, p, h, width)

    def _associate(self, windows: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """The association network on ``N`` windows; (N, 1, H, w) logits, none for N = 0."""
        if windows.shape[0] == 0:
            return windows.new_zeros(0, 1, *windows.shape[-2:])
        return self.association(windows, features)

    def quasi_dense(
        self, image: torch.Tensor, points: torch.Tensor, grad: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Logits, quasi-dense depth and confidence (module docstring, stage 2).

        Shape:
            - outputs: (B, P, H, window) logits, (B, 1, H, W) metres, (B, 1, H, W) confidence.
        """
        with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
            logits = self.association_logits(image, points)
        valid = (points[..., VALID] > 0) & (points[..., DEPTH] > 0)
        confidence = torch.sigmoid(logits.float().detach()) * valid[..., None, None]
        maps = paste_windows(confidence, points[..., U], image.shape[-1])
        depth, best = quasi_dense_depth(maps, points[..., DEPTH].float(), self.threshold)
        return logits, depth, best

    # -- the network ----------------------------------------------------------------------------

    def _dense(self, image: torch.Tensor, depth: torch.Tensor, best: torch.Tensor) -> torch.Tensor:
        assert self.fusion_net is not None
        radar = torch.cat([depth / self.max_depth, best], dim=1)
        x = self.fusion_net(image, radar).float()
        return self.min_depth / (torch.sigmoid(x) + self.min_depth / self.max_depth)

    def forward(
        self,
        image: torch.Tensor,
        sparse: torch.Tensor | None = None,
        points: torch.Tensor | None = None,
    ) -> torch.Tensor:
        self.check_input_size(image)
        points = self._points(sparse, points)
        _, depth, best = self.quasi_dense(image, points)
        if self.stage == "association":
            return depth
        return self._dense(image, depth, best)

    def to_depth(self, output: torch.Tensor) -> torch.Tensor:
        """Metres; in the association stage pixels no point claims stay 0 (not scored)."""
        depth = super().to_depth(output)
        if self.stage == "association":
            return torch.where(output > 0, depth, torch.zeros_like(depth))
        return depth

    # -- training -----------------------------------------------------------------------------

    def _sample_points(self, points: torch.Tensor) -> torch.Tensor:
        """``train_points`` valid points per image drawn at random (invalid rows where an image
        has fewer)."""
        valid = (points[..., VALID] > 0) & (points[..., DEPTH] > 0)
        score = torch.rand(valid.shape, device=points.device) + valid.float()  # valid first
        k = min(self.train_points, points.shape[1])
        index = score.topk(k, dim=1).indices
        return torch.gather(points, 1, index[..., None].expand(-1, -1, points.shape[-1]))

    def _fake_points(self, sampled: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """``sampled`` with each image's rows replaced, with probability
        ``fake_point_probability``, by fake radar points from its ground truth (RadarNet's
        ``RadarNetTrainingDataset``): ground-truth pixels deeper than 1 m drawn at random, the
        column moved by N(0, σ) with σ = ``fake_column_noise`` (None: 25 pixels at 1600
        columns, scaled to the input's width), clipped to [0, W] and truncated to whole
        pixels, the depth raised by U(0, 0.4) m; each row keeps its radar row (truncated), as
        the reference does. An image without such a pixel keeps its points. In training only.

        Shape:
            - sampled: (B, P, K); depth: (B, 1, H, W) metres. Out: (B, P, K).
        """
        if self.fake_point_probability <= 0 or not self.training:  # a validation loss is fixed
            return sampled
        n, p = sampled.shape[:2]
        width = depth.shape[-1]
        deep = (depth[:, 0] > FAKE_MIN_DEPTH).flatten(1)  # (B, HW)
        chosen = (torch.rand(n, device=depth.device) < self.fake_point_probability) & deep.any(1)
        if not bool(chosen.any()):
            return sampled
        # p pixels per image among the deep ones, uniformly (random scores, the deep first)
        score = torch.rand(deep.shape, device=depth.device) + deep.float()
        pixel = score.topk(p, dim=1).indices  # (B, P); an image with fewer repeats none
        cols = pixel % width
        z = torch.gather(depth[:, 0].flatten(1), 1, pixel)
        sigma = self.fake_column_noise
        if sigma is None:
            sigma = FAKE_COLUMN_NOISE * width / PAPER_IMAGE_SIZE[1]
        u = (cols.float() + sigma * torch.randn(n, p, device=depth.device)).clamp(0, width)
        fake = sampled.clone()
        fake[..., U] = u.trunc().to(sampled.dtype)
        fake[..., V] = sampled[..., V].trunc()
        fake[..., DEPTH] = (z + FAKE_DEPTH_NOISE * torch.rand(n, p, device=depth.device)).to(
            sampled.dtype
        )
        fake[..., VALID] = torch.gather(deep, 1, pixel).to(sampled.dtype)
        return torch.where(chosen[:, None, None], fake, sampled)

    def association_loss(
        self, logits: torch.Tensor, points: torch.Tensor, ground_truth: torch.Tensor
    ) -> torch.Tensor:
        """BCE of the windows' logits against :func:`association_labels` (pos_weight
        ``positive_weight``), over the window pixels inside the image of valid points.

        Shape:
            - logits: (B, P, H, w); points: (B, P, 6); ground_truth: (B, 1, H, W) metres.
        """
        width = logits.shape[-1]
        gt = crop_windows(ground_truth.float(), points[..., U], width)  # (B, P, 1, H, w)
        labels = association_labels(gt, points[..., DEPTH].float(), self.max_distance)[:, :, 0]
        columns = window_columns(points[..., U], width)
        inside = (columns >= 0) & (columns < ground_truth.shape[-1])
        valid = (points[..., VALID] > 0) & (points[..., DEPTH] > 0)
        weight = (inside & valid[..., None])[:, :, None, :].expand_as(labels).float()
        loss = F.binary_cross_entropy_with_logits(
            logits.float(),
            labels,
            reduction="none",
            pos_weight=torch.tensor(self.positive_weight, device=logits.device),
        )
        return (loss * weight).sum() / weight.sum().clamp_min(1.0)

    def training_loss(
        self,
        batch: Mapping[str, Any],
        depth_loss: Callable[[torch.Tensor, torch.Tensor], dict[str, torch.Tensor]],
    ) -> dict[str, torch.Tensor]:
        """The stage's training loss (module docstring) and its terms, ``"loss"`` their sum.

        ``depth_loss(output, depth)`` is the module's depth loss (``loss=``; ``l1_only`` by
        default: the reference's L1 in metres).

        Raises:
            ValueError: ``stage=fusion`` with an untrained association network.
        """
        image, depth = batch["image"], batch["depth"]
        self.check_input_size(image)
        points = self._points(batch.get("sparse"), batch.get("radar_points"))
        if self.stage == "association":
            sampled = self._fake_points(self._sample_points(points), depth)
            logits = self.association_logits(image, sampled)
            bce = self.association_loss(logits, sampled, depth)
            return {"loss": bce, "association": bce.detach()}
        if self.stage == "fusion" and not bool(self.association_trained):
            raise ArgumentError(
                "{stage}=fusion trains on a trained association network: give "
                "{association_weights}=<a stage=association checkpoint>",
                "stage",
                "association_weights",
                owner=RadarNet,
            )
        end_to_end = self.stage == "end_to_end"
        logits, quasi, best = self.quasi_dense(image, points, grad=end_to_end)
        output = self._dense(image, quasi, best)
        measured = batch.get("depth_measured")
        if self.lidar_loss_weight > 0 and measured is not None:
            # FusionNet: the filled pixels where nothing was measured, and the measured ones
            # weighted, "to avoid double counting"
            filled_only = torch.where(measured > 0, torch.zeros_like(depth), depth)
            losses = dict(depth_loss(output, filled_only))
            lidar = depth_loss(output, measured)["loss"]
            losses["lidar"] = lidar.detach()
            losses["loss"] = losses["loss"] + self.lidar_loss_weight * lidar
        else:
            losses = dict(depth_loss(output, depth))
        if end_to_end:
            bce = self.association_loss(logits, points, depth)
            losses["association"] = bce.detach()
            losses["loss"] = losses["loss"] + bce
        return losses
