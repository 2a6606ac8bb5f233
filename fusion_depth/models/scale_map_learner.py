"""RadarCam-Depth's Scale Map Learner (SML; Li et al., "RadarCam-Depth: Radar-Camera Fusion for
Depth Estimation with Learned Metric Scale", ICRA 2024), layer for layer as its authors' code
builds it, so that the checkpoint they released (``weights/sml_dpt_var/model-6000.pth``) loads
strictly and computes what their code computes, with the inputs their code builds, their
output formula, their losses and their training recipe.

Source: github.com/MMOCKING/RadarCam-Depth at 3762f2f (no licence file). None of its code is in
this package: this is a re-implementation, proved equal to it by
``tests/test_scale_map_learner.py`` on fixtures that its own code made
(``scripts/make_scale_map_learner_parity_fixtures.py``). The files named below are in that
repository; line numbers are at that commit. Their SML is VI-Depth's ``MidasNet_small_videpth``
(isl-org/VI-Depth) with VI-Depth's input normalisation.

**The network** (``modules/midas/midas_net_custom.py`` ``MidasNet_small_videpth``, line 22;
:class:`ScaleMapLearner`). Their defaults (line 26-27), which both of their scripts use
(``SML/sml_main.py`` ``train`` line 109, which ``SML/sml_train_zju.py`` runs, and
``SML/sml_run_zju.py`` line 15): ``features=64``, ``backbone="efficientnet_lite3"``,
``non_negative=False``, ``exportable=True``, ``align_corners=True``, ``blocks={'expand':
True}``, ``in_channels=2``.
21.32 M parameters, 489 keys, 21.39 M values (86 MB in fp32; their keys and shapes are the
fixtures' ``shipped_layout.json``).

* ``first`` (line 64): 3×3 conv 2 → 3 (bias), ``BatchNorm2d(3)``, ReLU: the two input channels
  made an "image" for the ImageNet encoder. Initialised by ``weights_init`` (line 9: normal with
  std ``sqrt(2 / (3·3·3))``, zero bias; batch norm 1, 0).
* ``pretrained`` (``modules/midas/blocks.py`` ``_make_efficientnet_backbone``, line 54): the
  EfficientNet-Lite3 of ``torch.hub.load("rwightman/gen-efficientnet-pytorch",
  "tf_efficientnet_lite3", pretrained=..., exportable=True)`` (line 45) cut into ``layer1`` =
  ``conv_stem, bn1, act1, blocks[0], blocks[1]`` (32 channels at 1/4), ``layer2`` = ``blocks[2]``
  (48, 1/8), ``layer3`` = ``blocks[3:5]`` (136, 1/16), ``layer4`` = ``blocks[5:9]`` (that is 5
  and 6: 384, 1/32); ``conv_head`` and the classifier are not used. ``pretrained=True`` (ImageNet)
  whenever no ``path`` is given (line 39), so their training starts from ImageNet weights. Here
  it is timm's ``tf_efficientnet_lite3`` (:data:`BACKBONE`): the same blocks with the same key
  names (geffnet 1.0.2 against timm 1.0, compared key by key and shape by shape), the same
  TensorFlow "same" padding (zero padding ``(k - 2)`` split ``floor/ceil`` left/right for a
  stride-2 convolution of an even input) and the same ImageNet weights file
  (``tf_efficientnet_lite3-b733e338.pth`` in both). One difference of module layout: geffnet's
  stem has ``bn1`` and ``act1`` (ReLU6), timm's ``bn1`` applies the ReLU6 itself, so
  ``layer1.2`` is an ``nn.Identity`` here (no parameters either way, so the keys are the same).
  geffnet's ``exportable`` convolution (``Conv2dSameExport``) computes its padding on the first
  input and keeps it for every later one; for the sizes their transform gives (multiples of 32)
  that padding is the one every input needs, which timm's ``Conv2dSame`` computes each time.
* ``scratch`` (``_make_scratch``, line 15): ``layer1_rn`` ... ``layer4_rn``, bias-free 3×3 convs
  from 32, 48, 136, 384 channels to 64, 128, 256, 512 (``expand``); ``refinenet4`` ...
  ``refinenet1`` (``FeatureFusionBlock_custom``, line 125; :class:`FeatureFusionBlock`): the
  deeper path plus ``resConfUnit1`` of the skip, ``resConfUnit2``, bilinear ×2 with
  ``align_corners=True``, ``out_conv`` 1×1 to half the channels (``refinenet1`` keeps 64);
  each ``ResidualConvUnit_custom`` (line 67; :class:`ResidualConvUnit`) is ``x + conv2(relu(
  conv1(relu(x))))`` with biased 3×3 convs, no batch norm; ``refinenet4`` has a
  ``resConfUnit1`` it never uses. ``output_conv`` (``OutputConv``, line 177): 3×3 64 → 32,
  bilinear ×2 (``align_corners=False``), 3×3 32 → 32, ReLU, 1×1 32 → 1, no activation
  (``non_negative=False``). Output at the input's resolution.

**The output** (``midas_net_custom.py`` ``forward``, lines 102-133; :func:`sml_prediction`).
With ``out`` the raw output, ``scales = relu(1 + out)`` and ``pred = d · scales``, ``d`` being
the globally aligned **inverse depth** (1/m) at the network's resolution, not normalised. Then
``pred`` is clamped in place to at most ``1 / min_pred`` and at least ``1 / max_pred``:
``min_pred`` 0.1 m in both scripts, ``max_pred`` 255 m in training (``sml_train_zju.py`` lines
55-56) and 100 m at test (``sml_run_zju.py`` lines 17-18). The depth is ``1 / pred``; at test it
is resized to the input's size by bicubic interpolation of depth (``sml_main.py`` ``validate``
lines 404-414; :func:`released_depth`); training scores it at the network's resolution.

**The inputs** (``sml_main.py`` ``train`` lines 166-225, ``validate`` lines 375-400;
:func:`scale_scaffold`, :func:`sml_inputs`), per frame, from two maps read as 16-bit PNGs
divided by 256 (``data/SML_dataset.py`` ``load_sparse_depth``, line 10: metres, 0 = none):
RC-Net's quasi-dense depth ``rcnet`` and the globally aligned monocular depth ``mono_ga``
(:func:`global_alignment`). A ZJU frame (720 rows) is cropped to rows 240-539
(``SML_dataset.py`` lines 56-75: the image, the radar, both ground truths and ``mono_ga``; not
``rcnet``, which RC-Net wrote at the crop's size already).

1. ``rcnet`` is valid where ``0 < rcnet < 80`` (``min/max_radar_valid_depth``,
   ``sml_train_zju.py`` lines 57-58, ``sml_run_zju.py`` lines 70-71); elsewhere it becomes
   ``inf`` and its inverse 0. ``int_depth = 1 / mono_ga`` (inverse depth, 1/m).
2. The scaffold (``int_scales``): **1.0** everywhere, ``(1 / rcnet) / int_depth`` (the scale
   that takes the aligned inverse depth to RC-Net's) at valid pixels; then min-max normalised
   to [0, 1] over the whole frame, the 1.0 fill included (``modules/midas/utils.py``
   ``normalize_unit_range``, line 223: a frame whose map is constant raises ``ValueError``).
3. Both maps, and every other map of the sample, are resized with ``cv2.INTER_NEAREST`` to the
   network's size (``modules/midas/transforms.py`` ``get_transforms`` line 245, ``Resize``
   line 10 with ``keep_aspect_ratio``, ``ensure_multiple_of=32`` and the ``"minimal"`` method:
   the side whose scale to 288 is closer to 1 is scaled to 288, the other by the same factor,
   each then rounded half-to-even to a multiple of 32; :func:`network_size`): 300×1280 (ZJU's
   crop) runs at 288×1216.
4. ``NormalizeIntermediate`` (``transforms.py`` line 164) with VI-Depth's VOID statistics for
   ``dpt_hybrid``, ``void_150`` (``modules/midas/normalization.py`` lines 48-51, chosen by
   ``get_transforms('dpt_hybrid', 'void', '150')``, ``sml_main.py`` lines 88 and 373):
   ``(int_depth - 0.729) / 0.210`` and ``(int_scales - 0.404) / 0.117``. The network's input
   is ``cat([int_depth, int_scales])`` (2, h, w); ``d`` is the resized ``int_depth`` before
   this step (``int_depth_no_tf``).

**The losses** (``utils/loss.py`` ``compute_loss``, line 4, as ``sml_main.py`` lines 229-253
calls it; :func:`sml_loss`): on **depth** in metres (``1 / pred``) at the network's resolution,
against ``gt`` (ZJU's ``gt_interp``, interpolated lidar) and ``sparse_gt`` (the lidar scan),
both resized by nearest neighbour with the inputs. ``gt`` is zeroed where the lidar scan has a
point; ``loss = smooth_l1(pred[gt > 0], gt) + w_smoothness · smoothness + w_lidar ·
smooth_l1(pred[lidar > 0], lidar)``, each a mean over its pixels (``beta = 1``), with
``w_lidar = 3`` and ``w_smoothness = 0`` (``sml_train_zju.py`` lines 44-48). The smoothness
terms (:func:`smoothness_loss`, :func:`sobel_smoothness_loss`) are weighted by the gradients of
the aligned *depth* ``1 / d`` (passed as their ``image``), not of the RGB image.

**The recipe** (``sml_train_zju.py`` ``train(...)`` lines 27-61, ``sml_main.py`` ``train``):
Adam (line 124) over all parameters, weight decay 0, learning rate 2e-4 for epochs 1-20 and
1e-4 for epochs 21-80 (``learning_rates=[2e-4, 1e-4]``, ``learning_schedule=[20, 80]``; lines
146-155), **batch 1** (the ``DataLoader`` is built with ``batch_size=1``, line 83; the
``batch_size=12`` the script passes only sizes a log line, line 71), ``shuffle=False`` (line
84), no augmentation, no gradient clipping, no ground-truth dilation or outlier removal
(kernel sizes -1), ``torch.save(state_dict())`` every 2000 steps and at the end as
``model-<step>.pth`` (lines 63, 277-288). The model stays in train mode throughout (batch norm
with batch statistics, batch 1); ``sml_run_zju.py`` evaluates in eval mode. Constants:
:data:`LEARNING_RATES`, :data:`LEARNING_SCHEDULE`, :data:`EPOCHS`, :data:`BATCH_SIZE`, ...

**The checkpoint.** ``BaseModel.save`` (``modules/midas/base_model.py`` line 28) writes
``torch.save(self.state_dict(), path)`` from the unwrapped network (``train`` never wraps it;
``sml_run_zju.py`` wraps it in ``DataParallel``, line 23, and loads through ``.module.load``,
line 46): a flat ``OrderedDict`` of the network's keys, without a ``module.`` prefix and with
nothing else (no step, no optimizer).
``BaseModel.load`` (line 5) also takes ``{"model": ..., "optimizer": ...}`` (line 13) and a
Lightning checkpoint's ``state_dict`` whose ``model.`` keys it keeps (lines 16-23; VI-Depth's
released ``.ckpt`` files). :func:`load_released` reads the three the same way. The mapping is
the identity:

| in the file | here |
| --- | --- |
| ``k`` (their ``MidasNet_small_videpth`` key) | :class:`ScaleMapLearner` key ``k`` |
| ``model[k]`` (a dict with ``optimizer``) | :class:`ScaleMapLearner` key ``k`` |
| ``state_dict['model.' + k]`` | :class:`ScaleMapLearner` key ``k`` (other keys ignored) |
| the step in ``model-<step>.pth`` | returned by :func:`load_released` |

Their keys (``first.0.weight``, ``pretrained.layer1.3.0.conv_dw.weight``,
``pretrained.layer4.0.4.bn3.running_var``, ``scratch.refinenet4.resConfUnit1.conv1.bias``,
``scratch.output_conv.output_conv.4.weight``) are this module's.

**Differences.** None measured on the fixtures (three frames, hashed random weights in the
shipped configuration, fp32 on a CPU, torch 2.14.1, the fixtures' two threads on a 2-core
Xeon): the raw output, ``pred`` and the final depth in eval mode, and the raw output and
``pred`` in train mode (batch statistics, their training step), are bitwise the authors'
(maximum absolute and relative difference 0; the tests allow 1e-5 relative); the scaffold,
the network's inputs ``x`` and ``d`` and the resized targets are theirs bit for bit, and so is
the loss. At one thread instead of two, on the same machine, the convolutions round otherwise:
the raw output moves by up to 8.9e-6, ``pred`` by 1.5e-4 relative, the final depth by 4.8 mm
(5.8e-4 relative), while ours and theirs at one thread agree. :func:`global_alignment` sums in
float64 where theirs sums in numpy float32: on the fixture frame their shift is 1.3e-5 m off
(-0.135795 against -0.135782 m), and ours is their formula evaluated in float64 bit for bit.
By design:

* :func:`scale_scaffold` and :func:`sml_inputs` refuse an aligned depth that is not positive
  and finite (theirs feeds ``inf`` to the network and gives NaN), and :func:`network_size` a
  frame whose network size has a side of 0 (theirs fails in ``cv2.resize``); each is one
  line (``ArgumentError``).
* :func:`sml_prediction` clamps with ``torch.where`` instead of an in-place masked write: the
  same values, the same (zero) gradient where it clamps.
* :class:`ScaleMapLearner` returns the raw output; their ``forward`` returns ``(pred,
  scales)`` (:func:`sml_prediction`).

**What their code leaves open.**

* The normalisation of the inputs is VI-Depth's, measured on VOID (indoor, ``dpt_hybrid``,
  150 points): mean 0.729 1/m for the inverse depth, where ZJU's lie mostly under 0.2 1/m, so
  the first channel is about -3 on most of a frame. The released weights were trained so.
* The global alignment (``data/global_alignment.py``) fits scale and shift to **depth**
  (``depth_type='pos'``) on radar points in (2, 80) m, not to inverse depth, and its clamp
  treats its bounds as inverse depths: a floor of 1/255 m, no ceiling. Which monocular
  network's output (``data/dpt``, "dpt_var") it aligned, and in what units that was saved,
  is not in the repository.
* ``model-6000.pth`` is step 6000 at batch 1: 6000 frames, not the 80 epochs of the recipe,
  unless ZJU's training split is under 75 frames; ``sml_run_zju.py`` scores every ``.pth`` of
  the folder, and ``results.txt`` holds step 6000 only.
* ``SML_dataset.py`` crops ``rcnet`` nowhere: a 720-row RC-Net map would not match the
  cropped ``mono_ga`` (RC-Net's own dataset writes the crop, ``data/datasets.py`` line 334).
  It also reads ``mono_pred`` from ``mono_ga_paths`` (line 64; unused).
* ``sml_train_zju.py`` passes ``batch_size=12``, which only sizes the step count it logs.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from fusion_depth.errors import ArgumentError
from fusion_depth.models.released_weights import (
    ReleasedWeightsError,
    matched_state,
    read_released,
    released_error,
)

AUTHORS_COMMIT = "3762f2ffc02e8809c234b27c2bf288b557bfc27d"
# The network (midas_net_custom.py line 26-27, blocks.py lines 7 and 44-62, 185-192).
FEATURES = 64
IN_CHANNELS = 2
BACKBONE = "tf_efficientnet_lite3"
ENCODER_CHANNELS = (32, 48, 136, 384)  # blocks.py _make_encoder, line 7
ENCODER_BLOCKS = ((0, 2), (2, 3), (3, 5), (5, 9))  # blocks.py lines 57-62 (layer1 adds the stem)
OUTPUT_HIDDEN = 32  # blocks.py OutputConv, line 188
# The inputs (transforms.py get_transforms lines 245-257, normalization.py lines 48-51).
NETWORK_SIDE = 288
NETWORK_MULTIPLE = 32
INT_DEPTH_MEAN, INT_DEPTH_STD = 0.729, 0.210
INT_SCALES_MEAN, INT_SCALES_STD = 0.404, 0.117
SCAFFOLD_FILL = 1.0  # sml_main.py lines 198 and 386: np.ones_like
UNIT_RANGE_EPS = 2.220446049250313e-16  # utils.py line 232: np.finfo("float").eps (float64)
MIN_VALID_DEPTH, MAX_VALID_DEPTH = 0.0, 80.0  # sml_train_zju.py 57-58, sml_run_zju.py 70-71
ZJU_HEIGHT, ZJU_ROWS = 720, (240, 540)  # SML_dataset.py lines 56-75: 720 // 3, 720 // 4 * 3
# The output (midas_net_custom.py lines 121-130; the scripts' min_pred / max_pred).
MIN_PRED_DEPTH = 0.1  # sml_train_zju.py line 55, sml_run_zju.py line 17
MAX_PRED_DEPTH_TRAIN = 255.0  # sml_train_zju.py line 56
MAX_PRED_DEPTH_TEST = 100.0  # sml_run_zju.py line 18
# sml_main.py lines 438-443: with save_output=True (sml_run_zju.py line 79 passes False), the
# saved depth keeps mono_ga where it is >= 200 m.
SKY_DEPTH = 200.0
# Global alignment (data/global_alignment.py process_scale defaults, line 10-13).
ALIGN_MIN_DEPTH, ALIGN_MAX_DEPTH = 2.0, 80.0
ALIGN_CLAMP_MIN, ALIGN_CLAMP_MAX = 0.0, 255.0  # "min_pred", "max_pred", applied as inverses
# The recipe (sml_train_zju.py lines 37-58, sml_main.py train).
OPTIMIZER = "Adam"  # sml_main.py line 124
LEARNING_RATES = (2e-4, 1e-4)  # sml_train_zju.py line 37
LEARNING_SCHEDULE = (20, 80)  # line 38: epochs up to which each rate holds
EPOCHS = LEARNING_SCHEDULE[-1]  # sml_main.py line 146
BATCH_SIZE = 1  # sml_main.py line 83 (the script's batch_size=12, line 39, sizes a log line)
SHUFFLE = False  # sml_main.py line 84
WEIGHT_DECAY = 0.0  # sml_train_zju.py line 47
GRADIENT_CLIP = None  # sml_main.py lines 256-259: zero_grad, backward, step
AUGMENTATIONS: tuple[str, ...] = ()  # SML_dataset.py: none
LOSS_FUNC = "smoothl1"  # sml_train_zju.py line 44
W_SMOOTHNESS = 0.0  # line 45
W_LIDAR = 3.0  # line 46
SMOOTHNESS_KERNEL_SIZE = -1  # line 48
CHECKPOINT_EVERY = 2000  # line 41 (steps)
# VI-Depth's Lightning module holds the network as its attribute ``model`` (base_model.py
# lines 16-23 keep the state dict's keys under it).
LIGHTNING_ATTRIBUTE = "model"
CHECKPOINT_NAME = re.compile(r"model-(\d+)\.pth$")  # sml_main.py line 63


def learning_rate(epoch: int) -> float:
    """The learning rate of 1-based ``epoch`` under their schedule (``sml_main.py`` lines
    146-155): :data:`LEARNING_RATES` [i] for epochs up to :data:`LEARNING_SCHEDULE` [i].

    Raises:
        ArgumentError: an epoch outside 1 … :data:`EPOCHS`.
    """
    if not 1 <= epoch <= EPOCHS:
        raise ArgumentError(
            f"{{epoch}}={epoch}: their schedule has epochs 1-{EPOCHS}", "epoch", owner=learning_rate
        )
    position = 0
    for e in range(1, epoch + 1):
        if e > LEARNING_SCHEDULE[position]:
            position += 1
    return LEARNING_RATES[position]


class ResidualConvUnit(nn.Module):
    """``blocks.py`` ``ResidualConvUnit_custom`` (line 67) without batch norm: ``x +
    conv2(act(conv1(act(x))))``, biased 3×3 convolutions. (N, C, H, W) → the same."""

    def __init__(self, features: int, activation: nn.Module) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1, bias=True)
        self.activation = activation

    def forward(self, x: Tensor) -> Tensor:
        out = self.conv1(self.activation(x))
        out = self.conv2(self.activation(out))
        return out + x


class FeatureFusionBlock(nn.Module):
    """``blocks.py`` ``FeatureFusionBlock_custom`` (line 125) with ``bn=False``: ``xs[0]``
    plus ``resConfUnit1(xs[1])`` where a skip is given, ``resConfUnit2``, bilinear ×2
    (``align_corners=True``), ``out_conv`` 1×1 to ``features // 2`` (``expand``) or
    ``features``. (N, C, H, W) → (N, C', 2H, 2W)."""

    def __init__(self, features: int, activation: nn.Module, expand: bool) -> None:
        super().__init__()
        out = features // 2 if expand else features
        self.out_conv = nn.Conv2d(features, out, 1, padding=0, bias=True)
        self.resConfUnit1 = ResidualConvUnit(features, activation)  # noqa: N815 - their key
        self.resConfUnit2 = ResidualConvUnit(features, activation)  # noqa: N815

    def forward(self, *xs: Tensor) -> Tensor:
        output = xs[0]
        if len(xs) == 2:
            output = output + self.resConfUnit1(xs[1])
        output = self.resConfUnit2(output)
        output = F.interpolate(output, scale_factor=2, mode="bilinear", align_corners=True)
        return self.out_conv(output)


class OutputConv(nn.Module):
    """``blocks.py`` ``OutputConv`` (line 177) with ``non_negative=False``: ``output_conv``,
    3×3 to ``features // 2``, bilinear ×2 (``align_corners=False``), 3×3 to 32, the activation,
    1×1 to 1. (N, features, H, W) → (N, 1, 2H, 2W)."""

    def __init__(self, features: int, activation: nn.Module) -> None:
        super().__init__()
        self.output_conv = nn.Sequential(
            nn.Conv2d(features, features // 2, 3, padding=1),
            nn.Upsample(scale_factor=2, mode="bilinear", align_corners=False),
            nn.Conv2d(features // 2, OUTPUT_HIDDEN, 3, padding=1),
            activation,
            nn.Conv2d(OUTPUT_HIDDEN, 1, 1, padding=0),
            nn.Identity(),
            nn.Identity(),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.output_conv(x)


def _init_first(module: nn.Module) -> None:
    """``midas_net_custom.py`` ``weights_init`` (line 9), which ``first`` is given (line 69)."""
    if isinstance(module, nn.Conv2d):
        n = module.kernel_size[0] * module.kernel_size[1] * module.out_channels
        module.weight.data.normal_(0, math.sqrt(2.0 / n))
        if module.bias is not None:
            module.bias.data.zero_()
    elif isinstance(module, nn.BatchNorm2d):
        module.weight.data.fill_(1)
        module.bias.data.zero_()


def _encoder(pretrained: bool) -> nn.Module:
    """``blocks.py`` ``_make_efficientnet_backbone`` (line 54) on timm's
    ``tf_efficientnet_lite3``: ``layer1`` … ``layer4`` with geffnet's indices (module
    docstring: ``layer1.2`` stands for geffnet's ``act1``, which timm's ``bn1`` applies)."""
    from fusion_depth.models.encoder import create_timm_model  # ImageNet's from the cache

    effnet = create_timm_model(BACKBONE, pretrained, None)
    encoder = nn.Module()
    (a, b), *rest = ENCODER_BLOCKS
    encoder.layer1 = nn.Sequential(
        effnet.conv_stem, effnet.bn1, nn.Identity(), *list(effnet.blocks)[a:b]
    )
    for i, (start, stop) in enumerate(rest, start=2):
        setattr(encoder, f"layer{i}", nn.Sequential(*list(effnet.blocks)[start:stop]))
    return encoder


class ScaleMapLearner(nn.Module):
    """Their ``MidasNet_small_videpth`` (module docstring): ``first``, ``pretrained`` (the
    EfficientNet-Lite3 encoder), ``scratch`` (the decoder), with their key names.

    Args:
        features: their ``features`` (64 as shipped); the decoder's widths are ``features``,
            2×, 4×, 8× (``blocks={'expand': True}``).
        pretrained: start the encoder from timm's ImageNet weights (what their training does,
            ``midas_net_custom.py`` line 39); False: timm's initialisation.

    Shape:
        - x: (N, 2, H, W), H and W multiples of 32: the normalised aligned inverse depth and
          the normalised scaffold (:func:`sml_inputs`).
        - output: (N, 1, H, W), the raw output ``out`` (:func:`sml_prediction` makes it
          inverse depth).
    """

    def __init__(self, features: int = FEATURES, pretrained: bool = False) -> None:
        super().__init__()
        widths = (features, features * 2, features * 4, features * 8)
        self.first = nn.Sequential(
            nn.Conv2d(IN_CHANNELS, 3, kernel_size=3, stride=1, padding=1),
            nn.BatchNorm2d(3),
            nn.ReLU(inplace=True),
        )
        self.first.apply(_init_first)
        self.pretrained = _encoder(pretrained)
        self.scratch = nn.Module()
        for i, (inputs, width) in enumerate(zip(ENCODER_CHANNELS, widths, strict=True), 1):
            conv = nn.Conv2d(inputs, width, 3, stride=1, padding=1, bias=False)
            setattr(self.scratch, f"layer{i}_rn", conv)
        self.scratch.activation = nn.ReLU(False)
        for i, width in reversed(list(enumerate(widths, 1))):
            block = FeatureFusionBlock(width, self.scratch.activation, expand=i > 1)
            setattr(self.scratch, f"refinenet{i}", block)
        self.scratch.output_conv = OutputConv(features, self.scratch.activation)

    def forward(self, x: Tensor) -> Tensor:
        """``midas_net_custom.py`` ``forward`` lines 102-119: the raw output ``out``."""
        s = self.scratch
        layer_1 = self.pretrained.layer1(self.first(x))
        layer_2 = self.pretrained.layer2(layer_1)
        layer_3 = self.pretrained.layer3(layer_2)
        layer_4 = self.pretrained.layer4(layer_3)
        path_4 = s.refinenet4(s.layer4_rn(layer_4))
        path_3 = s.refinenet3(path_4, s.layer3_rn(layer_3))
        path_2 = s.refinenet2(path_3, s.layer2_rn(layer_2))
        path_1 = s.refinenet1(path_2, s.layer1_rn(layer_1))
        return s.output_conv(path_1)


def sml_prediction(
    out: Tensor,
    d: Tensor,
    min_pred: float | None = MIN_PRED_DEPTH,
    max_pred: float | None = MAX_PRED_DEPTH_TEST,
) -> tuple[Tensor, Tensor]:
    """Their prediction from the network's raw output (``midas_net_custom.py`` lines 121-133):
    ``scales = relu(1 + out)``, ``pred = d · scales``, then ``pred`` set to ``1 / min_pred``
    where above it and to ``1 / max_pred`` where below it, in that order.

    Args:
        out: (N, 1, H, W) :class:`ScaleMapLearner`'s output.
        d: (N, 1, H, W) the aligned inverse depth in 1/m at the network's size, not
            normalised (:func:`sml_inputs`' second value).
        min_pred: metres (None: no bound); 0.1 in both of their scripts.
        max_pred: metres (None: no bound); 255 in training, 100 at test.

    Returns:
        ``pred`` (N, 1, H, W), inverse depth in 1/m, and ``scales`` (N, 1, H, W) ≥ 0.
    """
    scales = F.relu(1.0 + out)
    pred = d * scales
    if min_pred is not None:
        bound = 1.0 / min_pred
        pred = torch.where(pred > bound, torch.full_like(pred, bound), pred)
    if max_pred is not None:
        bound = 1.0 / max_pred
        pred = torch.where(pred < bound, torch.full_like(pred, bound), pred)
    return pred, scales


def network_size(height: int, width: int) -> tuple[int, int]:
    """The size their transform resizes a ``height`` × ``width`` frame to (``transforms.py``
    ``Resize.get_size``, line 67, as ``get_transforms`` sets it up, line 245): each side
    times the scale (288 / side) of the side whose scale is closer to 1, rounded half to even
    to a multiple of 32. 300×1280 → (288, 1216).

    Raises:
        ArgumentError: a side that comes out 0 (theirs fails in ``cv2.resize``).
    """
    scale_height, scale_width = NETWORK_SIDE / height, NETWORK_SIDE / width
    if abs(1 - scale_width) < abs(1 - scale_height):
        scale_height = scale_width
    else:
        scale_width = scale_height
    new_height = int(round(scale_height * height / NETWORK_MULTIPLE) * NETWORK_MULTIPLE)
    new_width = int(round(scale_width * width / NETWORK_MULTIPLE) * NETWORK_MULTIPLE)
    if new_height == 0 or new_width == 0:
        raise ArgumentError(
            f"{{size}}={height}x{width}: their transform resizes it to {new_height}x{new_width}",
            "size",
            owner=network_size,
        )
    return new_height, new_width


def _nearest_index(source: int, target: int, device: torch.device) -> Tensor:
    """OpenCV's ``INTER_NEAREST`` source index of each target pixel: ``floor(i / (target /
    source))`` in double precision, at most ``source - 1``."""
    inverse = 1.0 / (target / source)
    index = [min(math.floor(i * inverse), source - 1) for i in range(target)]
    return torch.tensor(index, dtype=torch.long, device=device)


def resize_nearest(x: Tensor, size: tuple[int, int]) -> Tensor:
    """``cv2.resize(x, (w, h), interpolation=cv2.INTER_NEAREST)`` on the last two dimensions:
    how their transform resizes every map of a sample (``transforms.py`` line 130-136),
    targets included. (..., H, W) → (..., h, w), values copied."""
    height, width = size
    rows = _nearest_index(x.shape[-2], height, x.device)
    columns = _nearest_index(x.shape[-1], width, x.device)
    return x.index_select(-2, rows).index_select(-1, columns)


def _frames(tensor: Tensor, name: str, owner: object) -> Tensor:
    if tensor.dim() != 4 or tensor.shape[1] != 1:
        raise ArgumentError(
            f"{{{name}}}: shape {list(tensor.shape)}, expected (N, 1, H, W) in metres",
            name,
            owner=owner,
        )
    return tensor.to(torch.float32)


def scale_scaffold(
    quasi_dense: Tensor,
    aligned: Tensor,
    min_valid: float = MIN_VALID_DEPTH,
    max_valid: float = MAX_VALID_DEPTH,
    constant_frames: str = "raise",
    check: bool = True,
) -> Tensor:
    """Their scale-map scaffold ``int_scales`` at the input's resolution (``sml_main.py``
    lines 375-388, 173-200; module docstring, "The inputs", steps 1-2), in float32 as theirs.

    Args:
        quasi_dense: (N, 1, H, W) RC-Net's quasi-dense depth in metres (any depth: a sparse
            radar map works the same), 0 where none.
        aligned: (N, 1, H, W) the globally aligned monocular depth in metres (``mono_ga``),
            positive.
        min_valid: depths of ``quasi_dense`` at or below it are no point (0 m in theirs).
        max_valid: depths at or above it are no point (80 m in theirs).
        constant_frames: ``raise`` (theirs) for a frame whose map is constant (no valid point,
            or every point at the aligned depth), or ``zero``: such a frame's scaffold is 0
            everywhere (a platform network trains on frames without returns too).
        check: refuse an aligned depth that is not positive and finite (False: the caller
            guarantees it, and the function then has no value-dependent branch to export).

    Returns:
        (N, 1, H, W) in [0, 1]: ``1.0`` where no point, ``(1 / quasi_dense) / (1 / aligned)``
        where one is, min-max normalised per frame.

    Raises:
        ArgumentError: inputs not (N, 1, H, W) of one shape, an aligned depth that is not
            positive and finite, or a frame whose map is constant (theirs: ``ValueError``).
    """
    quasi_dense = _frames(quasi_dense, "quasi_dense", scale_scaffold)
    aligned = _frames(aligned, "aligned", scale_scaffold)
    if aligned.shape != quasi_dense.shape:
        raise ArgumentError(
            f"{{aligned}}: shape {list(aligned.shape)}, {{quasi_dense}} is "
            f"{list(quasi_dense.shape)}",
            "aligned",
            "quasi_dense",
            owner=scale_scaffold,
        )
    if check and not bool(((aligned > 0) & aligned.isfinite()).all()):
        raise ArgumentError(
            "{aligned}: a depth that is not positive and finite (their network then gets inf)",
            "aligned",
            owner=scale_scaffold,
        )
    valid = (quasi_dense < max_valid) & (quasi_dense > min_valid)
    inverse = 1.0 / torch.where(valid, quasi_dense, torch.full_like(quasi_dense, math.inf))
    int_depth = 1.0 / aligned
    scales = torch.where(valid, inverse / int_depth, torch.full_like(int_depth, SCAFFOLD_FILL))
    low = scales.amin(dim=(1, 2, 3), keepdim=True)
    high = scales.amax(dim=(1, 2, 3), keepdim=True)
    spread = high - low > UNIT_RANGE_EPS
    if constant_frames == "zero":
        return torch.where(spread, (scales - low) / torch.where(spread, high - low, 1.0), 0.0)
    if not bool(spread.all()):
        raise ArgumentError(
            "{quasi_dense}: a frame whose scale map is constant (no valid point, or every "
            "point at the aligned depth): their normalize_unit_range refuses it",
            "quasi_dense",
            owner=scale_scaffold,
        )
    return (scales - low) / (high - low)


def sml_inputs(
    quasi_dense: Tensor,
    aligned: Tensor,
    min_valid: float = MIN_VALID_DEPTH,
    max_valid: float = MAX_VALID_DEPTH,
) -> tuple[Tensor, Tensor]:
    """The network's input ``x`` and the inverse depth ``d`` as their code builds them
    (module docstring, "The inputs", steps 1-4).

    Args:
        quasi_dense: (N, 1, H, W) RC-Net's quasi-dense depth in metres, 0 where none.
        aligned: (N, 1, H, W) the globally aligned monocular depth in metres, positive.
        min_valid: see :func:`scale_scaffold`.
        max_valid: see :func:`scale_scaffold`.

    Returns:
        ``x`` (N, 2, h, w): ``(1 / aligned - 0.729) / 0.210`` and ``(scaffold - 0.404) /
        0.117``; ``d`` (N, 1, h, w): ``1 / aligned`` in 1/m; (h, w) = :func:`network_size`.

    Raises:
        ArgumentError: as :func:`scale_scaffold` and :func:`network_size`.
    """
    scaffold = scale_scaffold(quasi_dense, aligned, min_valid, max_valid)
    size = network_size(*scaffold.shape[-2:])
    d = resize_nearest(1.0 / aligned.to(torch.float32), size)
    scaffold = resize_nearest(scaffold, size)
    x = torch.cat(
        [(d - INT_DEPTH_MEAN) / INT_DEPTH_STD, (scaffold - INT_SCALES_MEAN) / INT_SCALES_STD],
        dim=1,
    )
    return x, d


@torch.no_grad()
def released_depth(
    net: ScaleMapLearner,
    quasi_dense: Tensor,
    aligned: Tensor,
    min_pred: float | None = MIN_PRED_DEPTH,
    max_pred: float | None = MAX_PRED_DEPTH_TEST,
    sky_depth: float | None = None,
) -> Tensor:
    """Depth from RC-Net's quasi-dense depth and the aligned monocular depth as their
    ``validate`` computes it (``sml_main.py`` lines 375-414): :func:`sml_inputs`, the
    network, :func:`sml_prediction`, ``1 / pred`` resized bicubically to the input's size.

    Args:
        net: the network (in eval mode, as ``sml_run_zju.py`` line 21 sets it).
        quasi_dense: (N, 1, H, W) metres, 0 where none.
        aligned: (N, 1, H, W) metres, positive.
        min_pred: see :func:`sml_prediction`.
        max_pred: see :func:`sml_prediction` (100 m as ``sml_run_zju.py``).
        sky_depth: None: the depth their metrics score; :data:`SKY_DEPTH`: the depth their
            ``save_output=True`` writes, ``aligned`` wherever it is at least that (lines
            441-442; ``sml_run_zju.py`` line 79 does not save).

    Returns:
        (N, 1, H, W) depth in metres.

    Raises:
        ArgumentError: as :func:`sml_inputs`.
    """
    weight = next(net.parameters())
    x, d = sml_inputs(quasi_dense.to(weight.device), aligned.to(weight.device))
    pred, _ = sml_prediction(net(x.to(weight.dtype)), d.to(weight.dtype), min_pred, max_pred)
    depth = F.interpolate(1.0 / pred, size=aligned.shape[-2:], mode="bicubic", align_corners=False)
    if sky_depth is not None:
        sky = aligned.to(depth) >= sky_depth
        depth = torch.where(sky, aligned.to(depth), depth)
    return depth


def global_alignment(
    mono: Tensor,
    radar: Tensor,
    min_depth: float = ALIGN_MIN_DEPTH,
    max_depth: float = ALIGN_MAX_DEPTH,
    clamp_min: float | None = ALIGN_CLAMP_MIN,
    clamp_max: float | None = ALIGN_CLAMP_MAX,
) -> Tensor:
    """Their global alignment of a monocular depth to the frame's radar (``data/
    global_alignment.py`` ``process_scale`` with its defaults, ``depth_type='pos'``, line 9;
    ``modules/estimator.py`` ``compute_scale_and_shift_ls``, line 5, and
    ``LeastSquaresEstimator.clamp_min_max``, line 117): the least-squares scale and shift of
    *depth* (not inverse depth) on the radar pixels with ``min_depth < z < max_depth``; scale
    and shift 0 where the system is singular (fewer than two distinct depths); the result set to
    ``1 / clamp_max`` where below it (``clamp_max`` is read as an inverse depth bound although
    the map is depth: 1/255 m) and to ``1 / clamp_min`` where above it if ``clamp_min > 0``
    (their default 0 skips it). Sums in float64 (theirs: numpy float32).

    Args:
        mono: (N, 1, H, W) the monocular depth as their PNGs hold it (metres, up to scale).
        radar: (N, 1, H, W) the radar depth in metres, 0 where none.
        min_depth: radar depths at or below it are not used (2 m).
        max_depth: radar depths at or above it are not used (80 m).
        clamp_min: see above (0: none).
        clamp_max: see above (255: a floor of 1/255 m).

    Returns:
        (N, 1, H, W) float32, the aligned depth ``mono_ga`` in metres (their PNG then keeps
        it to 1/256 m).
    """
    mono, radar = _frames(mono, "mono", global_alignment), _frames(radar, "radar", global_alignment)
    mask = ((radar < max_depth) & (radar > min_depth)).to(torch.float64)
    p, t = mono.to(torch.float64), torch.where(mask > 0, radar, 0.0).to(torch.float64)
    dims = (1, 2, 3)
    a_00, a_01, a_11 = (mask * p * p).sum(dims), (mask * p).sum(dims), mask.sum(dims)
    b_0, b_1 = (mask * p * t).sum(dims), (mask * t).sum(dims)
    det = a_00 * a_11 - a_01 * a_01
    solvable = det > 0
    safe = torch.where(solvable, det, 1.0)
    scale = torch.where(solvable, (a_11 * b_0 - a_01 * b_1) / safe, 0.0)
    shift = torch.where(solvable, (-a_01 * b_0 + a_00 * b_1) / safe, 0.0)
    out = (p * scale[:, None, None, None] + shift[:, None, None, None]).to(torch.float32)
    if clamp_min is not None and clamp_min > 0:
        out = torch.where(out > 1.0 / clamp_min, torch.full_like(out, 1.0 / clamp_min), out)
    if clamp_max is not None:
        out = torch.where(out < 1.0 / clamp_max, torch.full_like(out, 1.0 / clamp_max), out)
    return out


def _pixel_loss(loss_func: str, output: Tensor, target: Tensor) -> Tensor:
    """``utils/loss.py`` ``l1_loss``, ``l2_loss``, ``smooth_l1_loss`` (lines 164-207): means."""
    if loss_func == "l1":
        return F.l1_loss(output, target, reduction="mean")
    if loss_func == "l2":
        return F.mse_loss(output, target, reduction="mean")
    return F.smooth_l1_loss(output, target, reduction="mean")


def _gradient_yx(t: Tensor) -> tuple[Tensor, Tensor]:
    """``utils/loss.py`` ``gradient_yx`` (line 290): forward differences ``t[i] - t[i+1]``."""
    return t[:, :, :-1, :] - t[:, :, 1:, :], t[:, :, :, :-1] - t[:, :, :, 1:]


def smoothness_loss(predict: Tensor, image: Tensor) -> Tensor:
    """``utils/loss.py`` ``smoothness_loss_func`` (line 209): ``mean(exp(-mean_c|∂x image|) ·
    |∂x predict|) + the same in y``. (N, 1, H, W) and (N, C, H, W) → a scalar."""
    predict_dy, predict_dx = _gradient_yx(predict)
    image_dy, image_dx = _gradient_yx(image)
    weights_x = torch.exp(-torch.mean(torch.abs(image_dx), dim=1, keepdim=True))
    weights_y = torch.exp(-torch.mean(torch.abs(image_dy), dim=1, keepdim=True))
    return torch.mean(weights_x * torch.abs(predict_dx)) + torch.mean(
        weights_y * torch.abs(predict_dy)
    )


def sobel_filter(size: int) -> tuple[Tensor, Tensor]:
    """``utils/loss.py`` ``sobel_filter`` (line 306) for a ``size`` × ``size`` kernel (odd):
    ones, 0 in the middle column (x) or row (y), 2 beside the centre, the right (x) or lower
    (y) half negated. (1, 1, size, size) each; size 3 is the Sobel pair."""
    c = size // 2
    gx = torch.ones(1, 1, size, size)
    gx[..., c] = 0
    gx[..., c, c - 1] = 2
    gx[..., c, c + 1] = 2
    gx[..., c:] = -gx[..., c:]
    gy = torch.ones(1, 1, size, size)
    gy[..., c, :] = 0
    gy[..., c - 1, c] = 2
    gy[..., c + 1, c] = 2
    gy[..., c + 1 :, :] = -gy[..., c + 1 :, :]
    return gx, gy


def sobel_smoothness_loss(predict: Tensor, image: Tensor, weights: Tensor, size: int) -> Tensor:
    """``utils/loss.py`` ``sobel_smoothness_loss_func`` (line 237): ``size``-wide Sobel-like
    gradients of ``predict`` (replicate padding), weighted by ``weights`` and by
    ``exp(-|3×3 Sobel of image|)`` (grey if it has 3 channels), summed over x and y, divided by
    ``size²``. (N, 1, H, W) each → a scalar."""
    half = size // 2
    predict = F.pad(predict, (half, half, half, half), mode="replicate")
    gx, gy = (g.to(predict.device) for g in sobel_filter(size))
    predict_dy, predict_dx = F.conv2d(predict, gy), F.conv2d(predict, gx)
    if image.shape[1] == 3:
        image = image[:, 0] * 0.30 + image[:, 1] * 0.59 + image[:, 2] * 0.11
        image = image.unsqueeze(1)
    image = F.pad(image, (1, 1, 1, 1), mode="replicate")
    gx_i, gy_i = (g.to(predict.device) for g in sobel_filter(3))
    image_dy, image_dx = F.conv2d(image, gy_i), F.conv2d(image, gx_i)
    weights_x = torch.exp(-torch.mean(torch.abs(image_dx), dim=1, keepdim=True))
    weights_y = torch.exp(-torch.mean(torch.abs(image_dy), dim=1, keepdim=True))
    smoothness_x = torch.mean(weights * weights_x * torch.abs(predict_dx))
    smoothness_y = torch.mean(weights * weights_y * torch.abs(predict_dy))
    return (smoothness_x + smoothness_y) / float(size * size)


def sml_loss(
    output_depth: Tensor,
    ground_truth: Tensor,
    lidar_map: Tensor,
    image: Tensor | None = None,
    loss_func: str = LOSS_FUNC,
    w_lidar: float = W_LIDAR,
    w_smoothness: float = W_SMOOTHNESS,
    smoothness_kernel_size: int = SMOOTHNESS_KERNEL_SIZE,
) -> tuple[Tensor, dict[str, Tensor | float]]:
    """Their training loss (``sml_main.py`` lines 239-253 and ``utils/loss.py``
    ``compute_loss``, line 4, with one output and no sky term; module docstring, "The
    losses"). A frame without a pixel of ground truth (or lidar) gives NaN, as theirs.

    Args:
        output_depth: (N, 1, h, w) the predicted depth in metres (``1 / pred``).
        ground_truth: (N, 1, h, w) the dense target in metres (ZJU's ``gt_interp``), 0 = none.
        lidar_map: (N, 1, h, w) the lidar scan in metres (``gt``), 0 = none.
        image: (N, C, h, w) what the smoothness terms take their edges from (theirs: the
            aligned depth ``1 / d``); needed only when ``w_smoothness > 0``.
        loss_func: ``"l1"``, ``"l2"`` or ``"smoothl1"`` (theirs).
        w_lidar: the lidar term's weight (3); > 0 also zeroes ``ground_truth`` where the
            lidar has a point.
        w_smoothness: the smoothness term's weight (0 in their recipe).
        smoothness_kernel_size: ≤ 1: :func:`smoothness_loss`; else
            :func:`sobel_smoothness_loss` of that size, weighted by ``ground_truth == 0``.

    Returns:
        The loss and theirs ``loss_info``: ``loss``, ``loss_supervised``, ``loss_smoothness``,
        ``loss_lidar`` (a float 0.0 where not computed, as theirs).

    Raises:
        ArgumentError: another ``loss_func``, or smoothness without an ``image``.
    """
    if loss_func not in ("l1", "l2", "smoothl1"):
        raise ArgumentError(
            f"{{loss_func}}={loss_func!r}: their compute_loss has 'l1', 'l2', 'smoothl1'",
            "loss_func",
            owner=sml_loss,
        )
    if w_smoothness > 0.0 and image is None:
        raise ArgumentError(
            "{image}: the smoothness term (w_smoothness > 0) takes its edges from it",
            "image",
            owner=sml_loss,
        )
    smoothness_weights = torch.where(
        ground_truth > 0, torch.zeros_like(ground_truth), torch.ones_like(ground_truth)
    )
    if w_lidar > 0.0:
        keep = torch.where(lidar_map > 0.0, torch.zeros_like(lidar_map), torch.ones_like(lidar_map))
        ground_truth = ground_truth * keep
    valid_gt, valid_lidar = ground_truth > 0, lidar_map > 0
    output = output_depth
    if output.shape[-2] > ground_truth.shape[-2] and output.shape[-1] > ground_truth.shape[-1]:
        output = F.interpolate(
            output, size=ground_truth.shape[-2:], mode="bilinear", align_corners=True
        )
    supervised = 0.0 + 1.0 * _pixel_loss(loss_func, output[valid_gt], ground_truth[valid_gt])
    lidar: Tensor | float = 0.0
    if w_lidar > 0.0:
        lidar = 0.0 + 1.0 * _pixel_loss(loss_func, output[valid_lidar], lidar_map[valid_lidar])
    smoothness: Tensor | float = 0.0
    if w_smoothness > 0.0:
        assert image is not None
        if smoothness_kernel_size <= 1:
            smoothness = 0.0 + 1.0 * smoothness_loss(output, image)
        else:
            term = sobel_smoothness_loss(output, image, smoothness_weights, smoothness_kernel_size)
            smoothness = 0.0 + 1.0 * term
    loss = supervised + w_smoothness * smoothness + w_lidar * lidar
    return loss, {
        "loss": loss,
        "loss_supervised": supervised,
        "loss_smoothness": smoothness,
        "loss_lidar": lidar,
    }


def _error(path: object, message: str, argument: str = "path") -> ReleasedWeightsError:
    return released_error(path, message, argument, owner=load_released)


_WHAT = "RadarCam-Depth's Scale Map Learner checkpoint"


def released_state(
    checkpoint: Any,
    net: ScaleMapLearner,
    path: str | os.PathLike = "<state>",
    argument: str = "path",
) -> dict[str, Tensor]:
    """``net``'s state dict from a file's contents as their ``BaseModel.load`` reads it
    (module docstring, "The checkpoint"): a flat state dict; ``checkpoint['model']`` when it
    has an ``optimizer``; the ``model.`` keys of ``checkpoint['state_dict']``. Checked against
    ``net`` key by key and shape by shape.

    Raises:
        ReleasedWeightsError: one line naming ``path`` and the first key that is missing,
            unexpected, not a tensor or of another shape (in the file's own names), or saying
            what the file holds instead of a state dict.
    """

    def fail(message: str) -> ReleasedWeightsError:
        return _error(path, f"not {_WHAT}: {message}", argument)

    if not isinstance(checkpoint, Mapping):
        raise fail(f"expected a state dict; it is a {type(checkpoint).__name__}")
    entry, prefix, stored = "state_dict", "", checkpoint
    if "optimizer" in checkpoint:
        entry, stored = "model", checkpoint.get("model")
    elif "state_dict" in checkpoint:
        state = checkpoint["state_dict"]
        prefix = f"{LIGHTNING_ATTRIBUTE}."
        if isinstance(state, Mapping):
            stored = {k: v for k, v in state.items() if str(k).startswith(prefix)}
        else:
            stored = state
    if not isinstance(stored, Mapping):
        raise fail(f"its '{entry}' is a {type(stored).__name__}, not a state dict")
    return matched_state(stored, net.state_dict(), entry, fail, prefix)


def load_released(net: ScaleMapLearner, path: str | os.PathLike, argument: str = "path") -> int:
    """Load their released ``model-6000.pth`` (or another checkpoint their ``BaseModel.load``
    reads) into ``net``, with ``torch.load(weights_only=True)`` and strictly.

    ``argument`` is the name errors give the file (a caller's own argument).

    Returns:
        The training step in the file's name ``model-<step>.pth`` (their ``sml_main.py`` line
        63, read back by ``sml_run_zju.py`` line 40); -1 for another name.

    Raises:
        ArgumentFileError: no file at ``path``.
        ReleasedWeightsError: a file that cannot be read with weights only, or not of this
            network (one line naming the file and the first wrong key).
    """
    checkpoint = read_released(path, argument, owner=load_released)
    net.load_state_dict(released_state(checkpoint, net, path, argument), strict=True)
    named = CHECKPOINT_NAME.search(os.fspath(path))
    return int(named.group(1)) if named else -1
