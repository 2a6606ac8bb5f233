"""RadarNet's two released networks (Singh et al., "Depth Estimation from Camera Image and mmWave
Radar Point Cloud", CVPR 2023), layer for layer as its authors' code builds them, so that the
``.pth`` files they released load strictly and compute what their code computes.

Source: github.com/nesl/radar-camera-fusion-depth at c95c67d (Academic Software License, no
commercial use). None of its code is in this package: this is a re-implementation, proved equal
to it by ``tests/test_radarnet_released.py`` on fixtures that its own code made
(``scripts/make_radarnet_parity_fixtures.py``). The files named below are in that repository.
Unlike ``model=radarnet`` (:mod:`fusion_depth.models.radarnet`, a re-implementation on timm
encoders that trains at any size), these classes have the authors' own layers and key names.

**The building blocks** (``src/net_utils.py``). :class:`Conv` is ``Conv2d``: a bias-free k×k
convolution with padding k // 2, batch norm (``batch_norm`` in the shipped ``--encoder_type`` and
``--decoder_type``), then the activation; the activation is ``activation_func('leaky_relu')``,
a leaky ReLU of slope 0.2 (not the 0.1 of the classes' defaults, which the networks never use).
:class:`ResNetBlock` is ``ResNetBlock``: conv1 (3×3, stride s) and conv2 (3×3), each with batch
norm and the activation, then ``act(conv2 + shortcut)``, the shortcut being the 1×1 ``projection``
(no batch norm) when the shape or the channels change, else the input. The projection exists,
and is in the state dict, even where it is never used. :class:`DecoderBlock` is ``DecoderBlock``
with ``deconv_type='up'``: nearest-neighbour upsampling to the skip's size (or to ``shape`` where
there is no skip), a 3×3 convolution, concatenation with the skip, a second 3×3 convolution.

**Stage 1, the association network** (:class:`RadarNetV1`; ``src/radarnet_model.py``
``RadarNetModel``, ``src/networks.py`` ``RadarNetV1Encoder``, ``ResNetEncoder``,
``FullyConnectedEncoder``, ``MultiScaleDecoder``; shipped as ``bash/run_radarnet_nuscenes.sh``:
patch 900×288, image filters 32 64 128 128 128, point neurons 32 64 128 128 128, decoder 256 128
64 32 16). For one frame (their inference runs one image at a time, batch 1):

1. The image is read as 0-255 and divided by 255 (``src/radarnet_transforms.py``
   ``normalize_images``, ``--normalized_image_range 0 1``). Each radar point is ``(x, y, z)``:
   the pixel its return projects to (whole pixels: ``setup/setup_dataset_nuscenes_test.py``
   takes them with ``np.nonzero``) and its depth in metres.
2. ``setup/setup_dataset_nuscenes_radarnet_test.py`` (its main loop) adds ``pad = patch_w // 2``
   (144) to every point's x, in place, and gives each point the box ``(x - pad, 0, x + pad, H)``
   with the shifted x. ``src/radarnet_main.py`` ``forward`` pads the image by ``pad`` columns on
   each side, repeating the edge column (``padding_mode='edge'``): the box is the window of
   ``patch_w`` columns centred on the point's original column, over the full height.
3. ``ResNetEncoder`` (ResNet-18 layout: conv1 7×7 stride 2, 3×3 max pool, blocks2-blocks5 of two
   :class:`ResNetBlock` each, stride 1 for blocks2 and 2 after) runs once over the whole padded
   image. ``RadarNetV1Encoder.forward`` cuts every window out of each feature map with
   ``torchvision.ops.roi_pool`` (max pooling): the 1/2, 1/4, 1/8 and 1/16 maps (the skips) at
   the spatial scales 1/2 ... 1/16 to ``int(patch × scale)`` cells (450×144, 225×72, 112×36,
   56×18), the 1/32 map (the latent) to ``patch // 32`` cells (28×9). ``roi_pool`` rounds the
   box to whole cells and includes the end cell, so a window covers ``round(x2·s) - round(x1·s)
   + 1`` columns of the map, one more than the window's nominal width.
4. The point branch (``FullyConnectedEncoder``) is six fully connected layers, 3 → 32 → 64 →
   128 → 128 → 128 → 128·28·9, each followed by the leaky ReLU, the last one included. Its input
   is the point as it is after step 2, ``(x + pad, y, z)``, not normalised. Its output is viewed
   as K×128×28×9 and concatenated after the image latent (128 + 128 channels).
5. ``MultiScaleDecoder`` (``n_resolution=1``): deconv4 to deconv1, each to the next skip's size
   with that skip, deconv0 to the patch size (900×288) without a skip, and ``output0``, a 3×3
   convolution to one channel without batch norm or activation: a logit per window pixel. The
   sigmoid of it is the confidence (``RadarNetModel.forward(return_logits=False)``):
   :func:`window_confidences`.
6. The quasi-dense map (``src/radarnet_main.py`` ``forward``; :func:`quasi_dense_depth`).
   Confidences below 0.5 become 0. Each point's window is placed into a zero map of the padded
   image, rows ``H - patch_h`` on, columns ``int(x) - pad`` to ``int(x) + pad`` (shifted x), and
   the padding columns are cut away. Per pixel, the maximum over the points is the *response*
   and its arg-max (the first point among equals; 0 where no point claims the pixel) the
   point's index. The index map becomes depth through ``for i in range(K): out =
   torch.where(out == i, torch.full_like(out, z_i), out)``. The map is an int64 tensor, so
   ``full_like`` truncates each depth to whole metres. The loop also rewrites values it has
   already written: a pixel of point i whose depth truncates to j, for a point j > i, is
   rewritten to ``int(z_j)``, and so on down the chain. Pixels with response 0 get depth 0.
   The depth is whole metres, the response 0 or in [0.5, 1].
7. ``setup/setup_dataset_nuscenes_radarnet(_test).py`` store both as PNGs: ``src/data_utils.py``
   ``save_depth`` writes ``uint32(z·256)`` and ``save_response`` writes ``uint32(r·2^14)``, as
   16-bit PNGs (Pillow clips them at 65535). FusionNet's readers (``src/datasets.py``
   ``FusionNetTrainingDataset``, ``FusionNetInferenceDataset``) read *both* with ``load_depth``,
   which divides by 256. FusionNet's second input channel is therefore ``64 × response``,
   quantised to 1/256 (0 or in [32, 64]), not the response. The released FusionNet was trained
   on it that way (:func:`fusion_inputs`). (``src/save_stage_1_depth.py`` builds an older
   ``networks.RadarNet``, without windows pooled from one encoding; no shipped script runs it.)

**Stage 2, FusionNet** (:class:`FusionNet`; ``src/fusionnet_model.py`` ``FusionNetModel``,
``src/networks.py`` ``FusionNetEncoder``, ``MultiScaleDecoder``; shipped as
``bash/run_fusionnet_nuscenes_test.sh``: ``fusionnet18 batch_norm``, image filters 32 64 128
256 256 256, depth filters 16 32 64 128 128 128, ``weight_and_project``, decoder 256 256 128 64
64 32, ``--n_resolutions_decoder 1``, depth in [1, 100] m, leaky ReLU):

1. Inputs: the image divided by 255 (``src/fusionnet_transforms.py``) and the 2-channel map
   ``cat([depth, response])`` of stage 1 as read back in step 7 (``src/fusionnet_main.py``
   ``run``).
2. ``FusionNetEncoder``: an image branch and a depth branch, each ResNet-18-like (conv1 7×7
   stride 2, max pool, blocks2-blocks6 of two blocks each). At each level i both branches go on
   unfused, and the level's fused map is ``image_i + sigmoid(BN(conv_weight(depth_i))) ·
   BN(conv_project(depth_i))``, both 1×1 convolutions from the depth channels to the image
   channels (``weight_and_project``). Levels 1-5 are the skips, level 6 is the latent.
3. ``MultiScaleDecoder``: deconv5 to deconv1, each with a skip (1/32 to 1/2), deconv0 to the
   image size without one, and ``output0`` (3×3, one channel).
4. Depth: ``min / (sigmoid(y) + min / max)`` with min 1 m and max 100 m
   (``FusionNetModel.forward``).

**Key mapping.** The authors' ``save_model`` writes a dict of state dicts, and their training
scripts wrap each part in ``torch.nn.DataParallel`` first (``src/radarnet_main.py`` ``train``,
``src/fusionnet_main.py`` ``train``: ``data_parallel()``), so every key starts with
``module.``. Their inference code wraps the parts the same way before it loads a file.
:func:`load_released` drops that prefix where it is there and maps:

| in the file | here |
| --- | --- |
| ``radarnet_encoder_state_dict['module.' + k]`` | ``RadarNetV1.encoder`` key ``k`` |
| ``radarnet_decoder_state_dict['module.' + k]`` | ``RadarNetV1.decoder`` key ``k`` |
| ``encoder_state_dict['module.' + k]`` | ``FusionNet.encoder`` key ``k`` |
| ``decoder_state_dict['module.' + k]`` | ``FusionNet.decoder`` key ``k`` |
| ``train_step`` | returned by :func:`load_released` |
| ``radarnet_optimizer_state_dict``, ``optimizer_state_dict`` | not used |

Below ``encoder``/``decoder`` the key names are the authors' own (``encoder_image.blocks2.0.conv1
.conv.weight``, ``conv3_weight.batch_norm.running_var``, ``deconv4.deconv.conv.conv.weight``,
...), so the mapping is the prefix alone.

**Differences.** None measured. On the fixtures (two frames, random weights, reduced filter
counts, fp32 on a CPU, torch 2.14.1), stage 1's confidences and stage 2's depth are bitwise the
outputs of the authors' code (maximum absolute and relative difference 0; the tests allow 1e-5
relative to each window's largest confidence: on a Xeon without AMX a confidence of 0.157 came
out 1.8e-6 off, 1.14e-5 of itself), and the quasi-dense maps and FusionNet's inputs are theirs
pixel for pixel. The same operations run in the same order, so the rounding is the same. Where
a platform's convolutions round differently from the fixtures' machine, the confidences still
pass the 1e-5 test,
but a pixel where two windows' confidences are nearly equal could go to the other point: the
closest such pair in the fixtures is 2.4e-7 apart, near 1. The same holds for the response,
which FusionNet reads as its 16-bit PNG code (1/16384 steps): a confidence within rounding of a
step may land on the next one. With one thread instead of the fixtures' two, on the same 2-core
Xeon, that happens on the "border" frame, and the two stages end to end differ from the
authors' by up to 5.8e-4 m (3.95e-5 relative), while each stage alone stays within 1e-5.

What this module does otherwise, by design:

* It keeps a running maximum over the points' windows, where ``forward`` stacks one full-image
  map per point (K × H × W: about 400 MB at 60 points on 900×1888). The result is the same, ties
  included (the first point wins, as ``torch.max``'s arg-max).
* It takes a frame with no point and gives zero maps; the authors' code fails on one
  (``torch.stack`` of nothing).
* With ``as_released=False``, :func:`quasi_dense_depth` gives each pixel its point's exact depth
  instead of stage 1 step 6's whole metres and chain. On the fixtures' "border" frame that moves
  pixels by up to 4.2 m (a 5.2 m point given 1 m). The released FusionNet was not trained on
  such input.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torchvision.ops import roi_pool

from fusion_depth.errors import ArgumentError, check_choice
from fusion_depth.models.released_weights import (
    ReleasedWeightsError,
    matched_state,
    read_released,
    released_error,
)

LEAKY_SLOPE = 0.2  # src/net_utils.py activation_func('leaky_relu')
ACTIVATIONS = ("leaky_relu", "relu", "elu")  # the hidden activations activation_func names
# src/networks.py RadarNetV1Encoder.forward: the skips' nominal scales, finest first.
SKIP_SCALES = (1 / 2.0, 1 / 4.0, 1 / 8.0, 1 / 16.0, 1 / 32.0, 1 / 64.0, 1 / 128.0)
LATENT_SCALE = 1 / 32.0
THRESHOLD = 0.5  # src/radarnet_main.py forward: "Thresholding any response less than 0.5 to 0"
DEPTH_MULTIPLIER = 256.0  # src/data_utils.py save_depth / load_depth
RESPONSE_MULTIPLIER = 2.0**14  # src/data_utils.py save_response
PNG_MAX = 65535  # a 16-bit PNG: Pillow clips larger values when it writes one
DATA_PARALLEL_PREFIX = "module."  # torch.nn.DataParallel's, in every key of the released files

# The shipped configurations (bash/run_radarnet_nuscenes.sh, bash/run_fusionnet_nuscenes_test.sh).
RADARNET_PATCH = (900, 288)
RADARNET_IMAGE_FILTERS = (32, 64, 128, 128, 128)
RADARNET_POINT_NEURONS = (32, 64, 128, 128, 128)
RADARNET_DECODER_FILTERS = (256, 128, 64, 32, 16)
FUSIONNET_IMAGE_FILTERS = (32, 64, 128, 256, 256, 256)
FUSIONNET_DEPTH_FILTERS = (16, 32, 64, 128, 128, 128)
FUSIONNET_DECODER_FILTERS = (256, 256, 128, 64, 64, 32)


def _activation(name: str) -> nn.Module:
    """``src/net_utils.py`` ``activation_func`` for the hidden layers' names."""
    if name == "leaky_relu":
        return nn.LeakyReLU(negative_slope=LEAKY_SLOPE)
    return nn.ReLU() if name == "relu" else nn.ELU()


class Conv(nn.Module):
    """``src/net_utils.py`` ``Conv2d``: bias-free k×k convolution (padding k // 2), batch norm
    if ``batch_norm``, then ``activation`` (None: linear). Keys ``conv.weight``,
    ``batch_norm.*``. (N, C_in, H, W) → (N, C_out, ⌈H/stride⌉, ⌈W/stride⌉)."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int = 3,
        stride: int = 1,
        activation: nn.Module | None = None,
        batch_norm: bool = True,
    ) -> None:
        super().__init__()
        self.conv = nn.Conv2d(
            in_channels, out_channels, kernel_size, stride, padding=kernel_size // 2, bias=False
        )
        self.batch_norm = nn.BatchNorm2d(out_channels) if batch_norm else None
        self.activation = activation

    def forward(self, x: Tensor) -> Tensor:
        x = self.conv(x)
        if self.batch_norm is not None:
            x = self.batch_norm(x)
        return x if self.activation is None else self.activation(x)


class ResNetBlock(nn.Module):
    """``src/net_utils.py`` ``ResNetBlock``: ``act(conv2(conv1(x)) + shortcut)``, the shortcut
    being the 1×1 ``projection`` (no batch norm) when the shape or the channels change."""

    def __init__(
        self, in_channels: int, out_channels: int, stride: int, activation: nn.Module, bn: bool
    ) -> None:
        super().__init__()
        self.conv1 = Conv(in_channels, out_channels, 3, stride, activation, bn)
        self.conv2 = Conv(out_channels, out_channels, 3, 1, activation, bn)
        self.projection = Conv(in_channels, out_channels, 1, stride, None, batch_norm=False)
        self.activation = activation

    def forward(self, x: Tensor) -> Tensor:
        out = self.conv2(self.conv1(x))
        shortcut = self.projection(x) if x.shape[1:] != out.shape[1:] else x
        return self.activation(out + shortcut)


def _resnet_layer(
    in_channels: int, out_channels: int, stride: int, activation: nn.Module, bn: bool
) -> nn.Sequential:
    """``ResNetEncoder._make_layer`` for ResNet-18: two blocks, the first with ``stride``."""
    return nn.Sequential(
        ResNetBlock(in_channels, out_channels, stride, activation, bn),
        ResNetBlock(out_channels, out_channels, 1, activation, bn),
    )


class ResNetEncoder(nn.Module):
    """``src/networks.py`` ``ResNetEncoder(n_layer=18)``: conv1 (7×7, stride 2), max pool,
    then ``blocks2`` … ``blocks{len(filters)}`` (stride 1, then 2). Returns the last level
    (1/2^len(filters)) and the others, finest first (the skips)."""

    def __init__(
        self, in_channels: int, filters: Sequence[int], activation: nn.Module, bn: bool
    ) -> None:
        super().__init__()
        self.conv1 = Conv(in_channels, filters[0], 7, 2, activation, bn)
        self.max_pool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        for i in range(1, len(filters)):
            layer = _resnet_layer(filters[i - 1], filters[i], 1 if i == 1 else 2, activation, bn)
            self.add_module(f"blocks{i + 1}", layer)
        self.levels = len(filters)

    def forward(self, x: Tensor) -> tuple[Tensor, list[Tensor]]:
        layers = [self.conv1(x)]
        x = self.max_pool(layers[0])
        for level in range(2, self.levels + 1):
            x = getattr(self, f"blocks{level}")(x)
            layers.append(x)
        return layers[-1], layers[:-1]


class FullyConnected(nn.Module):
    """``src/net_utils.py`` ``FullyConnected`` (no dropout): linear layer, then the activation."""

    def __init__(self, in_features: int, out_features: int, activation: nn.Module) -> None:
        super().__init__()
        self.fully_connected = nn.Linear(in_features, out_features)
        self.activation = activation

    def forward(self, x: Tensor) -> Tensor:
        return self.activation(self.fully_connected(x))


class FullyConnectedEncoder(nn.Module):
    """``src/networks.py`` ``FullyConnectedEncoder``: ``mlp``, six :class:`FullyConnected`
    layers, in → neurons[0] … neurons[4] → ``latent_size``, each with the activation."""

    def __init__(
        self, in_features: int, neurons: Sequence[int], latent_size: int, activation: nn.Module
    ) -> None:
        super().__init__()
        sizes = [in_features, *neurons, latent_size]
        self.mlp = nn.Sequential(
            *(FullyConnected(a, b, activation) for a, b in zip(sizes, sizes[1:], strict=False))
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.mlp(x)


class RadarNetV1Encoder(nn.Module):
    """``src/networks.py`` ``RadarNetV1Encoder``: the image encoder over the whole (padded)
    image, each point's window cut from every level with ``roi_pool``, and the point branch
    tiled to the latent's size (module docstring, stage 1 steps 3-4).

    Shapes: image (1, 3, H, W + 2·pad); points (K, 3) with x shifted by pad; boxes a list of one
    (K, 4) tensor ``(x1, y1, x2, y2)`` in padded pixels. Returns the latent (K, C_img + C_pt,
    ph // 32, pw // 32) and the pooled skips (K, C_i, int(ph·s_i), int(pw·s_i)), finest first.
    """

    def __init__(
        self,
        patch_size: tuple[int, int],
        image_filters: Sequence[int],
        point_neurons: Sequence[int],
        activation: nn.Module,
        bn: bool,
    ) -> None:
        super().__init__()
        height, width = patch_size
        self.patch_size = (height, width)
        self.latent_size = (int(height // 32.0), int(width // 32.0))
        self.point_channels = point_neurons[-1]
        latent = self.latent_size[0] * self.latent_size[1] * point_neurons[-1]
        self.encoder_image = ResNetEncoder(3, image_filters, activation, bn)
        self.encoder_depth = FullyConnectedEncoder(3, point_neurons, latent, activation)

    def forward(
        self, image: Tensor, points: Tensor, boxes: list[Tensor]
    ) -> tuple[Tensor, list[Tensor]]:
        height, width = self.patch_size
        latent_image, skips_image = self.encoder_image(image)
        latent_image = roi_pool(
            latent_image, boxes, output_size=self.latent_size, spatial_scale=LATENT_SCALE
        )
        skips = [
            roi_pool(
                skip,
                boxes,
                output_size=(int(height * scale), int(width * scale)),
                spatial_scale=scale,
            )
            for skip, scale in zip(skips_image, SKIP_SCALES, strict=False)
        ]
        latent_depth = self.encoder_depth(points).view(
            points.shape[0], self.point_channels, -1, self.latent_size[1]
        )
        return torch.cat([latent_image, latent_depth], dim=1), skips


class UpConv(nn.Module):
    """``src/net_utils.py`` ``UpConv2d``: nearest-neighbour upsampling to ``shape``, then a
    3×3 :class:`Conv` (key ``conv.*``)."""

    def __init__(
        self, in_channels: int, out_channels: int, activation: nn.Module, bn: bool
    ) -> None:
        super().__init__()
        self.conv = Conv(in_channels, out_channels, 3, 1, activation, bn)

    def forward(self, x: Tensor, shape: Sequence[int]) -> Tensor:
        return self.conv(F.interpolate(x, size=tuple(shape)))


class DecoderBlock(nn.Module):
    """``src/net_utils.py`` ``DecoderBlock(deconv_type='up')``: ``deconv`` (upsample to the
    skip's size, or ``shape``, or twice the size; conv), concatenation with the skip, ``conv``."""

    def __init__(
        self,
        in_channels: int,
        skip_channels: int,
        out_channels: int,
        activation: nn.Module,
        bn: bool,
    ) -> None:
        super().__init__()
        self.skip_channels = skip_channels
        self.deconv = UpConv(in_channels, out_channels, activation, bn)
        self.conv = Conv(skip_channels + out_channels, out_channels, 3, 1, activation, bn)

    def forward(
        self, x: Tensor, skip: Tensor | None = None, shape: Sequence[int] | None = None
    ) -> Tensor:
        if skip is not None:
            shape = skip.shape[2:4]
        elif shape is None:
            shape = (2 * x.shape[2], 2 * x.shape[3])
        x = self.deconv(x, shape)
        if self.skip_channels > 0:
            x = torch.cat([x, skip], dim=1)
        return self.conv(x)


class MultiScaleDecoder(nn.Module):
    """``src/networks.py`` ``MultiScaleDecoder`` with ``n_resolution=1``, ``output_func=
    'linear'``, one output channel: ``deconv{n-1}`` … ``deconv0`` (``n = len(filters)``), each
    with the skip it reaches, the last one to ``shape`` when no skip is left, then ``output0``
    (3×3 conv, no batch norm, no activation). Returns (N, 1, *shape) logits."""

    def __init__(
        self,
        in_channels: int,
        filters: Sequence[int],
        skips: Sequence[int],
        activation: nn.Module,
        bn: bool,
    ) -> None:
        super().__init__()
        self.names = [f"deconv{i}" for i in range(len(filters) - 1, -1, -1)]
        for name, skip, out_channels in zip(self.names, skips, filters, strict=True):
            self.add_module(name, DecoderBlock(in_channels, skip, out_channels, activation, bn))
            in_channels = out_channels
        self.output0 = Conv(in_channels, 1, 3, 1, None, batch_norm=False)

    def forward(self, x: Tensor, skips: Sequence[Tensor], shape: Sequence[int]) -> Tensor:
        n = len(skips) - 1
        for name in self.names[:-1]:
            x = getattr(self, name)(x, skips[n])
            n -= 1
        last = getattr(self, self.names[-1])
        x = last(x, skips[n]) if n == 0 else last(x, shape=shape)
        return self.output0(x)


def _check_filters(
    value: Sequence[int], argument: str, owner: object, count: int | None = None
) -> None:
    """Refuse filter counts the authors' code cannot build: 5 to 7 levels (``count`` levels
    where given), each a positive whole number."""
    counts = range(5, 8) if count is None else range(count, count + 1)
    if len(value) not in counts or not all(isinstance(v, int) and v > 0 for v in value):
        levels = "5 to 7" if count is None else str(count)
        raise ArgumentError(
            f"{{{argument}}}={list(value)}: expected {levels} positive whole numbers",
            argument,
            owner=owner,
        )


class RadarNetV1(nn.Module):
    """Stage 1, ``src/radarnet_model.py`` ``RadarNetModel`` with ``--encoder_type radarnetv1
    batch_norm --decoder_type multiscale batch_norm``: ``encoder`` (:class:`RadarNetV1Encoder`)
    and ``decoder`` (:class:`MultiScaleDecoder`). Defaults: the shipped configuration.

    Args:
        patch_size: (height, width) of a point's window in pixels; the width even.
        image_filters: the image encoder's filters per level (5 to 7).
        point_neurons: the point branch's five hidden sizes.
        decoder_filters: the decoder's filters, as many as ``image_filters``.
        activation: the hidden activation (leaky ReLU of slope 0.2 as shipped).
        batch_norm: batch norm in encoder and decoder (as shipped).

    Raises:
        ArgumentError: a size the authors' code cannot build, naming the argument.
    """

    def __init__(
        self,
        patch_size: Sequence[int] = RADARNET_PATCH,
        image_filters: Sequence[int] = RADARNET_IMAGE_FILTERS,
        point_neurons: Sequence[int] = RADARNET_POINT_NEURONS,
        decoder_filters: Sequence[int] = RADARNET_DECODER_FILTERS,
        activation: str = "leaky_relu",
        batch_norm: bool = True,
    ) -> None:
        super().__init__()
        check_choice(activation, ACTIVATIONS, "activation", owner=RadarNetV1)
        height, width = (int(v) for v in patch_size)
        if height < 32 or width < 32 or width % 2:
            raise ArgumentError(
                f"{{patch_size}}={list(patch_size)}: expected a height and an even width of "
                "at least 32 pixels",
                "patch_size",
                owner=RadarNetV1,
            )
        _check_filters(image_filters, "image_filters", RadarNetV1)
        _check_filters(point_neurons, "point_neurons", RadarNetV1, 5)
        _check_filters(decoder_filters, "decoder_filters", RadarNetV1, len(image_filters))
        act = _activation(activation)
        self.patch_size = (height, width)
        self.encoder = RadarNetV1Encoder(
            self.patch_size, image_filters, point_neurons, act, batch_norm
        )
        skips = [*list(image_filters[:-1])[::-1], 0]
        self.decoder = MultiScaleDecoder(
            image_filters[-1] + point_neurons[-1], decoder_filters, skips, act, batch_norm
        )

    def forward(self, image: Tensor, points: Tensor, boxes: list[Tensor]) -> Tensor:
        """Logits (K, 1, patch_h, patch_w) of the points' windows (``RadarNetModel.forward``);
        inputs as :class:`RadarNetV1Encoder` takes them (see :func:`window_confidences`)."""
        latent, skips = self.encoder(image, points, boxes)
        return self.decoder(latent, skips, self.patch_size)


class FusionNetEncoder(nn.Module):
    """``src/networks.py`` ``FusionNetEncoder(n_layer=18, fusion_type='weight_and_project')``:
    image and depth branches (``conv1_image``/``conv1_depth``, ``blocks{i}_image``/
    ``blocks{i}_depth``), each level fused as ``image_i + conv{i}_weight(depth_i) ·
    conv{i}_project(depth_i)`` (1×1 convolutions with batch norm; sigmoid, linear). Returns the
    last level's fused map and the others', finest first."""

    def __init__(
        self,
        in_channels_depth: int,
        image_filters: Sequence[int],
        depth_filters: Sequence[int],
        activation: nn.Module,
        bn: bool,
    ) -> None:
        super().__init__()
        self.levels = len(image_filters)
        for level in range(1, self.levels + 1):
            f_image, f_depth = image_filters[level - 1], depth_filters[level - 1]
            if level == 1:
                self.conv1_image = Conv(3, f_image, 7, 2, activation, bn)
                self.conv1_depth = Conv(in_channels_depth, f_depth, 7, 2, activation, bn)
            else:
                stride = 1 if level == 2 else 2
                for branch, filters in (("image", image_filters), ("depth", depth_filters)):
                    layer = _resnet_layer(
                        filters[level - 2], filters[level - 1], stride, activation, bn
                    )
                    self.add_module(f"blocks{level}_{branch}", layer)
            self.add_module(f"conv{level}_weight", Conv(f_depth, f_image, 1, 1, nn.Sigmoid(), bn))
            self.add_module(f"conv{level}_project", Conv(f_depth, f_image, 1, 1, None, bn))
            if level == 1:
                self.max_pool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)

    def _fuse(self, level: int, image: Tensor, depth: Tensor) -> Tensor:
        weight = getattr(self, f"conv{level}_weight")(depth)
        project = getattr(self, f"conv{level}_project")(depth)
        return weight * project + image

    def forward(self, image: Tensor, depth: Tensor) -> tuple[Tensor, list[Tensor]]:
        image, depth = self.conv1_image(image), self.conv1_depth(depth)
        fused = [self._fuse(1, image, depth)]
        image, depth = self.max_pool(image), self.max_pool(depth)
        for level in range(2, self.levels + 1):
            image = getattr(self, f"blocks{level}_image")(image)
            depth = getattr(self, f"blocks{level}_depth")(depth)
            fused.append(self._fuse(level, image, depth))
        return fused[-1], fused[:-1]


class FusionNet(nn.Module):
    """Stage 2, ``src/fusionnet_model.py`` ``FusionNetModel`` with ``--encoder_type fusionnet18
    batch_norm --fusion_type weight_and_project --decoder_type multiscale batch_norm
    --n_resolutions_decoder 1``: ``encoder`` (:class:`FusionNetEncoder`) and ``decoder``
    (:class:`MultiScaleDecoder`). Defaults: the shipped configuration.

    Args:
        image_filters: the image branch's filters per level (5 to 7).
        depth_filters: the depth branch's, as many.
        decoder_filters: the decoder's, as many.
        min_depth: the least depth it predicts, metres (``--min_predict_depth``).
        max_depth: the largest, metres (``--max_predict_depth``).
        activation: the hidden activation (leaky ReLU of slope 0.2 as shipped).
        batch_norm: batch norm in encoder and decoder (as shipped).
        in_channels_depth: the depth input's channels (2: depth, response).

    Raises:
        ArgumentError: a size the authors' code cannot build, naming the argument.
    """

    def __init__(
        self,
        image_filters: Sequence[int] = FUSIONNET_IMAGE_FILTERS,
        depth_filters: Sequence[int] = FUSIONNET_DEPTH_FILTERS,
        decoder_filters: Sequence[int] = FUSIONNET_DECODER_FILTERS,
        min_depth: float = 1.0,
        max_depth: float = 100.0,
        activation: str = "leaky_relu",
        batch_norm: bool = True,
        in_channels_depth: int = 2,
    ) -> None:
        super().__init__()
        check_choice(activation, ACTIVATIONS, "activation", owner=FusionNet)
        _check_filters(image_filters, "image_filters", FusionNet)
        _check_filters(depth_filters, "depth_filters", FusionNet, len(image_filters))
        _check_filters(decoder_filters, "decoder_filters", FusionNet, len(image_filters))
        if not 0 < min_depth < max_depth:
            raise ArgumentError(
                f"{{min_depth}}={min_depth}, {{max_depth}}={max_depth}: expected "
                "0 < min_depth < max_depth (metres)",
                "min_depth",
                "max_depth",
                owner=FusionNet,
            )
        act = _activation(activation)
        self.min_depth, self.max_depth = float(min_depth), float(max_depth)
        self.encoder = FusionNetEncoder(
            in_channels_depth, image_filters, depth_filters, act, batch_norm
        )
        skips = [*list(image_filters[:-1])[::-1], 0]
        self.decoder = MultiScaleDecoder(image_filters[-1], decoder_filters, skips, act, batch_norm)

    def forward(self, image: Tensor, depth: Tensor) -> Tensor:
        """Depth in metres, (N, 1, H, W), from the image (N, 3, H, W) in [0, 1] and the depth
        input (N, 2, H, W) as :func:`fusion_inputs` makes it (``FusionNetModel.forward``)."""
        latent, skips = self.encoder(image, depth)
        logits = self.decoder(latent, skips, image.shape[-2:])
        return self.min_depth / (torch.sigmoid(logits) + self.min_depth / self.max_depth)


def window_confidences(net: RadarNetV1, image: Tensor, points: Tensor) -> Tensor:
    """Each point's window confidences, as the authors' stage-1 inference computes them (module
    docstring, stage 1 steps 1-5: ``setup/setup_dataset_nuscenes_radarnet_test.py``'s main loop,
    ``src/radarnet_main.py`` ``forward``, ``RadarNetModel.forward(return_logits=False)``).

    Args:
        net: the association network.
        image: (3, H, W) or (1, 3, H, W), pixel values / 255; H at least the window height.
        points: (K, 3) radar points: x and y in pixels of this image, depth in metres.

    Returns:
        (K, 1, patch_h, patch_w) confidences in [0, 1]; (0, 1, patch_h, patch_w) for no point.

    Raises:
        ArgumentError: an image lower than the window, or a point outside the image's columns.
    """
    image = image if image.dim() == 4 else image[None]
    points = points.to(device=image.device, dtype=torch.float32)
    height, width = image.shape[-2:]
    _check_frame(net, height, width, points)
    patch_h, patch_w = net.patch_size
    if points.shape[0] == 0:
        return image.new_zeros((0, 1, patch_h, patch_w))
    pad = patch_w // 2
    shifted = points.clone()
    shifted[:, 0] = points[:, 0] + pad
    boxes = torch.stack(
        [
            shifted[:, 0] - pad,
            torch.zeros_like(shifted[:, 0]),
            shifted[:, 0] + pad,
            torch.full_like(shifted[:, 0], float(height)),
        ],
        dim=1,
    )
    padded = F.pad(image, (pad, pad, 0, 0), mode="replicate")
    return torch.sigmoid(net(padded, shifted, [boxes]))


def _check_frame(net: RadarNetV1, height: int, width: int, points: Tensor) -> None:
    if height < net.patch_size[0]:
        raise ArgumentError(
            f"{{image}}: {height} rows, lower than the window ({net.patch_size[0]}); the "
            "authors' network takes windows of the image's full height",
            "image",
            owner=window_confidences,
        )
    if points.dim() != 2 or points.shape[1] != 3:
        raise ArgumentError(
            f"{{points}}: shape {list(points.shape)}, expected (K, 3): x, y in pixels, depth",
            "points",
            owner=window_confidences,
        )
    outside = (points[:, 0] < 0) | (points[:, 0] >= width)
    if bool(outside.any()):
        raise ArgumentError(
            f"{{points}}: x={float(points[outside][0, 0])} is outside the image's {width} columns",
            "points",
            owner=window_confidences,
        )


def quasi_dense_depth(
    confidences: Tensor,
    points: Tensor,
    image_size: Sequence[int],
    threshold: float = THRESHOLD,
    as_released: bool = True,
) -> tuple[Tensor, Tensor]:
    """The quasi-dense depth and response maps from the windows' confidences, as
    ``src/radarnet_main.py`` ``forward`` builds them (module docstring, stage 1 step 6).

    Args:
        confidences: (K, 1, patch_h, patch_w), :func:`window_confidences`.
        points: (K, 3), the same points (x, y in pixels, depth in metres).
        image_size: (H, W) of the image.
        threshold: confidences below it are dropped (0.5 as shipped).
        as_released: depth as the authors' code gives it (whole metres, with the rewrite chain
            of its fill loop); False: each pixel the exact depth of its most confident point.

    Returns:
        depth (H, W) in metres and response (H, W) in [0, 1], float32; 0 where no point's
        confidence passes the threshold.
    """
    height, width = (int(v) for v in image_size)
    count, _, patch_h, patch_w = confidences.shape
    pad = patch_w // 2
    top = height - patch_h
    points = points.to(device=confidences.device, dtype=torch.float32)
    kept = torch.where(confidences < threshold, torch.zeros_like(confidences), confidences)
    response = confidences.new_zeros((height, width))
    index = torch.zeros((height, width), dtype=torch.int64, device=confidences.device)
    for k in range(count):
        first = int(points[k, 0] + pad) - 2 * pad  # the window's first column in the image
        lo, hi = max(first, 0), min(first + patch_w, width)
        tile = kept[k, 0, :, lo - first : hi - first]
        best = response[top:, lo:hi]
        better = tile > best  # strictly: the first point keeps a tie, as torch.max's arg-max
        response[top:, lo:hi] = torch.where(better, tile, best)
        index[top:, lo:hi] = torch.where(better, k, index[top:, lo:hi])
    if as_released:
        depth = index.clone()
        for k in range(count):  # int64: each depth truncated, values rewritten down the chain
            depth = torch.where(depth == k, points[k, 2].to(torch.int64), depth)
    else:
        depth = points[index, 2] if count else torch.zeros_like(response)
    depth = torch.where(response == 0, torch.zeros_like(depth), depth)
    return depth.to(torch.float32), response


def _png_round_trip(values: Tensor, save_multiplier: float, load_multiplier: float) -> Tensor:
    """``uint32(values · save_multiplier)`` stored in a 16-bit PNG (clipped at 65535), read back
    and divided by ``load_multiplier``, non-positive values 0 (``src/data_utils.py``)."""
    stored = (values.to(torch.float32) * save_multiplier).to(torch.int64).clamp(0, PNG_MAX)
    loaded = stored.to(torch.float32) / load_multiplier
    return torch.where(loaded <= 0, torch.zeros_like(loaded), loaded)


def fusion_inputs(depth: Tensor, response: Tensor) -> Tensor:
    """FusionNet's 2-channel depth input from the quasi-dense maps, as the authors' pipeline
    gives it: written by ``save_depth``/``save_response`` and read back by ``load_depth`` for
    both (module docstring, stage 1 step 7), so the second channel is 64 × response.

    Args:
        depth: (..., H, W) quasi-dense depth in metres.
        response: (..., H, W) response in [0, 1].

    Returns:
        (..., 2, H, W): depth quantised to 1/256 m, and ``floor(response · 2^14) / 256``.
    """
    return torch.stack(
        [
            _png_round_trip(depth, DEPTH_MULTIPLIER, DEPTH_MULTIPLIER),
            _png_round_trip(response, RESPONSE_MULTIPLIER, DEPTH_MULTIPLIER),
        ],
        dim=-3,
    )


class ReleasedRadarNet(nn.Module):
    """The two stages end to end, as the authors run them on a test frame: ``association``
    (:class:`RadarNetV1`) → :func:`window_confidences` → :func:`quasi_dense_depth` →
    :func:`fusion_inputs` → ``fusion`` (:class:`FusionNet`).

    Args:
        association: stage 1 (default: the shipped configuration, random weights).
        fusion: stage 2 (default: the shipped configuration, random weights).
        threshold: the confidence a point's pixel needs (0.5 as shipped).
        as_released: the quasi-dense depth as the authors' code makes it (see
            :func:`quasi_dense_depth`).
    """

    def __init__(
        self,
        association: RadarNetV1 | None = None,
        fusion: FusionNet | None = None,
        threshold: float = THRESHOLD,
        as_released: bool = True,
    ) -> None:
        super().__init__()
        self.association = association if association is not None else RadarNetV1()
        self.fusion = fusion if fusion is not None else FusionNet()
        self.threshold, self.as_released = threshold, as_released

    def quasi_dense(self, image: Tensor, points: Sequence[Tensor]) -> Tensor:
        """FusionNet's depth input (B, 2, H, W) for images (B, 3, H, W) in [0, 1] and each
        image's (K_b, 3) points."""
        maps = []
        for frame, frame_points in zip(image, points, strict=True):
            confidences = window_confidences(self.association, frame, frame_points)
            depth, response = quasi_dense_depth(
                confidences, frame_points, frame.shape[-2:], self.threshold, self.as_released
            )
            maps.append(fusion_inputs(depth, response))
        return torch.stack(maps)

    def forward(self, image: Tensor, points: Sequence[Tensor]) -> Tensor:
        """Depth in metres (B, 1, H, W) for images (B, 3, H, W) in [0, 1] and their points."""
        return self.fusion(image, self.quasi_dense(image, points))


# Which entries of a released file hold which part (src/radarnet_model.py save_model,
# src/fusionnet_model.py save_model), and what the file is called in the authors' scripts.
_ENTRIES: dict[type, tuple[str, dict[str, str]]] = {
    RadarNetV1: (
        "RadarNet's released association network (radarnetv1, model-195000.pth)",
        {"encoder": "radarnet_encoder_state_dict", "decoder": "radarnet_decoder_state_dict"},
    ),
    FusionNet: (
        "RadarNet's released FusionNet (fusionnet18, model-815000.pth)",
        {"encoder": "encoder_state_dict", "decoder": "decoder_state_dict"},
    ),
}


def _error(path: object, message: str, argument: str = "path") -> ReleasedWeightsError:
    return released_error(path, message, argument, owner=load_released)


def released_state(
    checkpoint: Any,
    net: RadarNetV1 | FusionNet,
    path: str | os.PathLike = "<state>",
    argument: str = "path",
) -> dict[str, Tensor]:
    """``net``'s state dict from a released file's contents, by the key mapping of the module
    docstring, checked against ``net`` key by key and shape by shape.

    Raises:
        ReleasedWeightsError: one line naming ``path`` and the first entry or key that is
            missing, unexpected, not a tensor or of another shape (in the file's own names).
    """
    what, entries = _ENTRIES[type(net)]
    if not isinstance(checkpoint, Mapping) or not all(e in checkpoint for e in entries.values()):
        others = [e for _, (_, es) in _ENTRIES.items() for e in es.values()]
        found = [e for e in others if isinstance(checkpoint, Mapping) and e in checkpoint]
        held = f"it holds {', '.join(found)}" if found else "it holds neither"
        raise _error(
            path, f"not {what}: expected {' and '.join(entries.values())}; {held}", argument
        )

    def fail(message: str) -> ReleasedWeightsError:
        return _error(path, f"not {what} as built here: {message}", argument)

    expected = net.state_dict()
    state: dict[str, Tensor] = {}
    for part, entry in entries.items():
        stored = checkpoint[entry]
        if not isinstance(stored, Mapping):
            raise _error(
                path, f"not {what}: {entry} is a {type(stored).__name__}, not a dict", argument
            )
        prefix = DATA_PARALLEL_PREFIX
        prefix = prefix if any(str(k).startswith(prefix) for k in stored) else ""
        own = f"{part}."
        below = {k.removeprefix(own): v for k, v in expected.items() if k.startswith(own)}
        matched = matched_state(stored, below, entry, fail, prefix)
        state.update({f"{part}.{name}": value for name, value in matched.items()})
    return state


def load_released(
    net: RadarNetV1 | FusionNet, path: str | os.PathLike, argument: str = "path"
) -> int:
    """Load one of the authors' released files (``torch.load(weights_only=True)``, strict)
    into ``net``: ``model-195000.pth`` into a :class:`RadarNetV1`, ``model-815000.pth`` into a
    :class:`FusionNet`, built in the shipped configuration (their defaults).

    ``argument`` is the name errors give the file (a caller's own argument, e.g.
    ``association_weights``).

    Returns:
        The training step the file records (``train_step``; -1 if none).

    Raises:
        ArgumentFileError: no file at ``path``.
        ReleasedWeightsError: a file that cannot be read with weights only, or not of this
            network as built (one line naming the file and the first wrong key).
    """
    checkpoint = read_released(path, argument, owner=load_released)
    net.load_state_dict(released_state(checkpoint, net, path, argument), strict=True)
    step = checkpoint.get("train_step", -1)
    return step if isinstance(step, int) else -1
