"""Sparse Beats Dense's released nuScenes network (Li et al., "Sparse Beats Dense: Rethinking
Supervision in Radar-Camera Depth Completion", ECCV 2024), layer for layer as its authors' code
builds it, so that the ``model.ckpt`` they released loads strictly and computes what their code
computes.

Source: github.com/megvii-research/Sparse-Beats-Dense at 8b87d53 (Apache-2.0). None of its code
is in this package: this is a re-implementation, proved equal to it by
``tests/test_sparse_beats_dense_released.py`` on fixtures that its own code made
(``scripts/make_sparse_beats_dense_parity_fixtures.py``). The files named below are in that
repository; line numbers are at that commit.

**The network** (``model.py``; :class:`SparseBeatsDense` is their ``Network``, line 449). One
configuration, with no argument: every width is fixed in the code. 36.87 M parameters (37.03 M
values with the batch norms' statistics, 3258 keys, 148 MB in fp32).

* ``conv`` (line 8, :class:`Conv`): ``nn.Conv2d`` *with* bias, batch norm (``bn``), ReLU;
  ``deconv`` (line 44, :class:`Deconv`): ``nn.ConvTranspose2d`` 2×2 stride 2 with bias, batch
  norm except in a branch's last one, never an activation.
* ``resnext_block`` (line 81, :class:`ResNeXtBlock`): 1×1 shrink to ``out / 4``, grouped 3×3
  (stride s), 1×1 expand (no ReLU), plus the shortcut, then ReLU. The first block of a stage has
  the projection ``shortcut`` (1×1 conv + BN), after a 2×2 average pool ``dsp`` when s = 2.
* ``Encoder`` (line 140): ``conv00`` (3×3 stride 2, 16 channels), then five stages of ResNeXt
  blocks, each starting with stride 2: ``g03`` 3×64 (groups 2), ``g3`` 4×128 (2), ``g4`` 7×256
  (4), ``g5`` 7×512 (8), ``g6`` 7×1024 (8). Each stage's *input* is also average-pooled to the
  last stage's 1/64 resolution (``p03`` … ``p6``, kernels 32 … 2); the deepest output is the
  concatenation of those five pools and the last stage: 16 + 64 + 128 + 256 + 512 + 1024 = 2000
  channels. Levels out: 1/64 (2000), 1/32 (512), 1/16 (256), 1/8 (128), 1/4 (64), 1/2 (16).
* ``UNet`` (line 235): the encoder and two decoders of the same shape, ``score/refine/resize``
  (depth) and ``valid_score/valid_refine/valid_resize`` (a mask). Level i (deepest first):
  ``score_i`` (``conv_block``, two separable 1×3/3×1 paths summed, line 111, for the three
  deepest; a 3×3 ``conv`` without ReLU for the others) to 128, 128, 64, 16, 8, 8 channels, plus
  the previous level's output, ``refine_i`` (``refine_block``: two 3×3 convs and the input,
  line 128), ``resize_i`` (``deconv`` ×2, to 128, 64, 16, 8, 8, then 1 channel). Outputs
  (``UNet.forward``, line 283): ``relu`` of the depth branch, ``sigmoid`` of the valid branch,
  both at the UNet's input size, and ``last_fm``, the depth branch's level-4 output (8
  channels, half the UNet's input size).
* ``FullyConnectedEncoder`` (line 386, ``calibrated_params_encoder``): six linear layers
  3 → 32 → 64 → 96 → 64 → 32 → 8, each followed by a leaky ReLU of slope 0.1, the last one
  included.
* ``Network.forward`` (line 458), for a padded image ``img`` (B, 3, H, W) and radar map
  ``radar`` (B, 1, H, W): every radar point (x, y, z) goes through the point encoder and the
  first ``valid_radar_pts_cnt`` embeddings of a frame are averaged to one 8-vector. ``G1``
  (UNet of 4 channels) runs at 1/4 on ``cat(bilinear(img, 1/4), downsample_depthmap(radar,
  1/4))``; its ``last_fm`` (1/8) plus the 8-vector is upsampled bilinearly ×4 to 1/2 and
  concatenated to ``cat(bilinear(img, 1/2), downsample_depthmap(radar, 1/2))`` for ``G2`` (12
  channels, at 1/2); ``G2``'s ``last_fm`` (1/4) plus the 8-vector, ×4 to full size, goes with
  ``img`` and ``radar`` into ``G3`` (12 channels). It returns the three depth maps and three
  masks, coarsest first. ``downsample_depthmap`` (line 539, :func:`downsample_depthmap`) moves
  every non-zero pixel (r, c) to ``(int(r·f), int(c·f))`` by ``out[index] = value``.

**The inputs, as eval.py builds them** (``eval.py`` ``Vidar.__getitem__``, line 102, batch 1;
:func:`released_inputs` builds them from what a user has):

* ``img``: ``cv2.imread`` of the ``CAM_FRONT`` keyframe JPEG (``data/nuscenes/samples/``),
  (3, 900, 1600), **BGR**, 0-255, not normalised (``uint8``; ``forward_test`` casts it to
  float32). Training (``dataset.py``) feeds BGR too, after augmenting in RGB.
* ``radar_pts``: the ``RADAR_FRONT`` points of ``radar_infos['RADAR_FRONT'][0]`` (one sweep,
  although the info files are named ``nuscenes_radar_5sweeps_infos_*.pkl``), read with the
  devkit's ``RadarPointCloud.from_file`` and its default filters (``invalid_state`` 0,
  ``dynProp`` 0-6, ``ambig_state`` 3), moved into the camera frame (``utils.py``
  ``map_pointcloud1_to_pointcloud2``: radar → ego → global → camera's ego → camera, by each
  record's translation and quaternion): (x right, y down, z forward) in metres, not
  normalised. *All* of the sweep's points, also those outside the image or behind the camera,
  zero-padded to 200 rows (float64; ``forward_test`` casts to float32); a sweep of more than
  200 points gives 200 drawn at random (``np.random.default_rng()`` unseeded, kept in order).
* ``valid_radar_pts_cnt``: the number of points of the sweep (not capped at 200).
* ``radar``: (1, 900, 1600) float32. Each point is projected (``utils.py``
  ``project_3d_to_2d``: ``K·p``, divided by its third row, for points behind the camera too);
  those with 0 ≤ u < W and 0 ≤ v < H are kept (``canvas_filter``), and ``get_radar_map``
  (``utils.py`` line 154) writes each one's depth z into the **whole column** ``int(u)``
  (``depth[:, u] = z``): every row, the later point of a column winning. A point behind the
  camera whose projection lands in the image writes its negative z.
* The segmentation masks (their Google Drive ``seg_mask.tar``, unpacked in ``data/nuscenes/``)
  are **not** an input of the network: ``dataset.py`` (training only) reads
  ``data/nuscenes/seg_mask/<the camera file's base name, .png for .jpg>`` (a flat folder) with
  ``cv2.IMREAD_GRAYSCALE`` and compares the 8-bit values with class ids (ADE20K's 150 classes,
  by the table in ``dataset.py`` line 46; the files themselves could not be read here), making
  ``seg_mask_roi``, 1 on the classes wall, building, tree, person, car, fence, bus,
  truck, pole, bicycle, van, minibike (``semantic_mask_used_mask``), 0 elsewhere: the label of
  the valid branch (``forward_train``, L1 loss). eval.py reads no mask. :func:`valid_label`
  builds that label.
* Their info files (``data/nuscenes_radar_5sweeps_infos_{train,val,test}.pkl``) are neither in
  the repository nor made by any of its code; eval.py reads ``..._test.pkl``, and which frames
  it holds (nuScenes' test split, or a split of trainval as RadarNet's) is not said. Per frame
  eval.py uses ``cam_infos['CAM_FRONT']`` (``filename``, ``calibrated_sensor`` with
  ``camera_intrinsic``, ``ego_pose``), ``radar_infos['RADAR_FRONT'][0]`` (``data_path``,
  ``sensor2ego_*``, ``ego2global_*``) and ``lidar_infos['LIDAR_TOP']``. Everything they carry
  is in nuScenes' own tables (``sample_data``, ``calibrated_sensor``, ``ego_pose``), so the
  inputs can be built without them (:func:`radar_to_camera`, :func:`released_inputs`), save
  which sweep ``[0]`` is (presumably the keyframe's).

``Network.forward_test`` (line 629) pads ``img`` and ``radar`` with zeros at the bottom and
right to ``(H // 256 + 1) · 256`` rows and ``(W // 256 + 1) · 256`` columns (``padding``, line
507: 900×1600 → 1024×1792; a side that already is a multiple of 256 still gets 256 more), runs
``forward`` and crops ``G3``'s outputs back to H×W.

**The output.** ``G3``'s depth: **metres**, linear depth (the camera z of the lidar points it
was trained on, smooth L1), ≥ 0 (ReLU), not capped, at the input's full resolution (900×1600),
no crop. The second output is ``G3``'s valid mask in (0, 1), the predicted probability that a
pixel is of the mask classes above. :func:`released_depth` returns both.

**What eval.py scores** (``Vidar.eval``, line 162, and ``__getitem__``). The ground truth is
the keyframe's ``LIDAR_TOP`` sweep alone (one sweep, every point), moved into the camera frame
as the radar is and written by ``get_depth_map`` at ``(int(v), int(u))`` of the 900×1600
image: the later point of a pixel wins (no nearest-point rule, no occlusion filter), and points
behind the camera that project into the image write negative depths, which the mask drops. Per
frame, MAE (``epe``) and RMSE of ``pred - lidar`` in metres over the pixels with ``0 < lidar <=
cap``, for caps of 80, 50 and 70 m; the prediction is not clamped. The printed numbers are the
means over frames of the per-frame MAE and RMSE (``epe:0-80``, ``rmse:0-80``, ...); a frame
with no ground truth under a cap makes that mean NaN. The overlap filter of commit 0713eaa is
in ``dataset.py``, for training labels only; it reads ``conf.query_radius``, which no ``conf``
defines, so training as published stops there with an AttributeError.

**The checkpoint.** ``train_DDP.py`` ``Session.save_checkpoint`` writes ``{'network':
net.state_dict(), 'clock': {'epoch', 'minibatch', 'step'}, 'optimizer': AdamW state,
'lr_scheduler': LambdaLR state}`` as ``<name>.ckpt`` and ``{'network': ...}`` alone as
``<name>.net.ckpt``, both from the unwrapped network (``net.module`` of DDP): the keys have no
``module.`` prefix. ``eval.py`` ``Vidar.load_model`` (line 68) does ``torch.load`` and
``Network().load_state_dict(checkpoint['network'])`` (strict). Which of the two files
``model.ckpt`` is cannot be told from their code. The ``.net.ckpt`` holds tensors only. The
full ``.ckpt`` also holds numpy float64 scalars: ``train_DDP.py``'s learning rate function
(``customer_lr_func``) computes with ``np.cos``, so the optimizer's ``param_groups[i]['lr']``
and the scheduler's ``_last_lr`` are ``numpy.float64``, which ``torch.load(weights_only=True)``
refuses by default (it names ``numpy.core.multiarray.scalar``, ``numpy._core...`` under numpy 2,
and ``numpy.dtype``; measured on a file written as their ``Session`` writes it:
``shipped_layout.json``). :func:`load_released` reads the file through ``load_weights_only``
with exactly those allowed (:data:`NUMPY_FLOAT64_GLOBALS`: a numpy float64 is rebuilt from its
dtype and its 8 bytes, no code of the file's choosing runs) and ignores every entry but
``network``. The mapping is the identity:

| in the file | here |
| --- | --- |
| ``network[k]`` | :class:`SparseBeatsDense` key ``k`` |
| ``clock['step']`` | returned by :func:`load_released` (-1 if none) |
| ``optimizer``, ``lr_scheduler`` | not used |

The keys are the authors' own (``G1.encoder.g6_3.conv_3x3.bn.running_var``,
``G3.valid_resize5.deconv.bias``, ``calibrated_params_encoder.mlp.5.fully_connected.weight``).

**Differences.** None measured on the fixtures (two frames, random weights, fp32 on a CPU,
torch 2.14.1, the fixtures' two threads on a 2-core Xeon): the depth, the valid mask and
``G1``'s outputs are bitwise those of the authors' code (maximum absolute and relative
difference 0; the tests allow 1e-5 relative), and the inputs built by :func:`released_inputs`
are theirs: the image and the radar map pixel for pixel, the points in the camera frame within
1.2e-13 m (float64 rounding of the chain of rotations; equal once cast to float32 as the
network takes them). The same operations run in the same order.
A convolution's rounding depends on how its sums are split across threads (and on the CPU's
kernels): ours at one thread differs from theirs at two, on the same machine, by up to 1.0e-4
m of depth (6.4e-5 relative where the depth is over 1 m; 1.9e-2 at a depth of 2 mm) and 2.9e-5
of the valid mask, while ours and theirs both at one thread agree bitwise. That is float
rounding of three deep UNets, not a difference of the computation; the parity tests run at the
fixtures' thread count. By design:

* :func:`downsample_depthmap` gives each coarse pixel the value of the last of its non-zero
  fine pixels in row-major order (a deterministic scatter). That is what the authors' ``out[
  nonzero_idx] = nonzero_arr`` gives when it runs in order: on the fixtures, and on 20
  padded 1024×1792 maps of about 110 columns (98,100 non-zero pixels) on a CPU with two
  threads, where not one pixel differed. Which of several values written to one index wins is
  undefined in torch (``index_put_``), and on a GPU, where eval.py runs, any of them may. It
  matters only where two radar columns of different depths share a coarse column (c and c + 1
  for an even c at 1/2, four columns at 1/4).
* :func:`released_inputs` draws the 200 of a sweep of more than 200 points with a
  ``torch.Generator`` (theirs: an unseeded numpy generator; no run of theirs can be repeated).
* A frame with no radar point: their ``forward`` averages no embedding and gives NaN
  everywhere, and ``get_radar_map`` fails on a sweep with no point in the image (``max`` of an
  empty array). :func:`released_inputs` and :func:`released_depth` refuse a frame without
  points, and :func:`released_inputs` gives a zero map where no point falls in the image.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
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

PAD_MULTIPLE = 256  # model.py Network.padding(int=256)
RADAR_PTS_NUM = 200  # eval.py Vidar.RADAR_PTS_NUM
LEAKY_SLOPE = 0.1  # model.py FullyConnectedEncoder: LeakyReLU(negative_slope=0.10)
STEM_CHANNELS = 16  # model.py Encoder: base_ch // 2, base_ch = 32
# model.py Encoder.__init__: (stage, channels, blocks, groups, its input's pool, pool kernel).
ENCODER_STAGES = (
    ("g03", 64, 3, 2, "p03", 32),
    ("g3", 128, 4, 2, "p3", 16),
    ("g4", 256, 7, 4, "p4", 8),
    ("g5", 512, 7, 8, "p5", 4),
    ("g6", 1024, 7, 8, "p6", 2),
)
# model.py UNet.__init__: per level, deepest first.
DECODER_ENCODER_CHANNELS = (2000, 512, 256, 128, 64, 16)
DECODER_CHANNELS = (128, 128, 64, 16, 8, 8)
DECODER_OUT_CHANNELS = (128, 64, 16, 8, 8, 8)
DECODER_CONV_BLOCK = (True, True, True, False, False, False)
POINT_NEURONS = (32, 64, 96, 64, 32)  # model.py FullyConnectedEncoder's defaults
EMBEDDING = 8  # its latent_size
# dataset.py Vidar.semantic_mask_used_mask: ADE20K ids of wall, building, tree, person, car,
# fence, bus, truck, pole, bicycle, van, minibike.
SEG_MASK_CLASSES = (0, 1, 4, 12, 20, 32, 80, 83, 93, 127, 102, 116)
NETWORK_ENTRY = "network"  # train_DDP.py Session.save_checkpoint; eval.py Vidar.load_model
# What a float64 numpy scalar pickles as (the learning rates their training checkpoint holds),
# for torch.serialization.safe_globals: numpy's scalar constructor, under the name numpy 1 (their
# pin, 1.23.2) and numpy 2 pickle it with, numpy.dtype and the float64 dtype's class. Nothing
# else of numpy.
_NUMPY_SCALAR = np.float64(0).__reduce__()[0]
NUMPY_FLOAT64_GLOBALS = [
    (_NUMPY_SCALAR, "numpy.core.multiarray.scalar"),
    (_NUMPY_SCALAR, "numpy._core.multiarray.scalar"),
    np.dtype,
    type(np.dtype(np.float64)),
]


class Conv(nn.Module):
    """``model.py`` ``conv``: ``nn.Conv2d`` (with bias), then batch norm ``bn`` and ReLU where
    asked. (N, C_in, H, W) → (N, C_out, H', W') as ``nn.Conv2d`` gives."""

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        kernel_size: int | tuple[int, int] = 3,
        stride: int = 1,
        padding: int | tuple[int, int] = 1,
        has_bn: bool = True,
        has_relu: bool = True,
        groups: int = 1,
    ) -> None:
        super().__init__()
        self.conv = nn.Conv2d(
            in_channels, out_channels, kernel_size, stride, padding, groups=groups
        )
        self.bn = nn.BatchNorm2d(out_channels) if has_bn else None
        self.relu = nn.ReLU() if has_relu else None

    def forward(self, x: Tensor) -> Tensor:
        x = self.conv(x)
        if self.bn is not None:
            x = self.bn(x)
        return x if self.relu is None else self.relu(x)


class Deconv(nn.Module):
    """``model.py`` ``deconv`` as ``UNet`` uses it: ``nn.ConvTranspose2d`` 2×2, stride 2 (with
    bias), then batch norm ``bn`` where asked. (N, C_in, H, W) → (N, C_out, 2H, 2W)."""

    def __init__(self, in_channels: int, out_channels: int, has_bn: bool = True) -> None:
        super().__init__()
        self.deconv = nn.ConvTranspose2d(in_channels, out_channels, 2, stride=2, padding=0)
        self.bn = nn.BatchNorm2d(out_channels) if has_bn else None

    def forward(self, x: Tensor) -> Tensor:
        x = self.deconv(x)
        return x if self.bn is None else self.bn(x)


class ResNeXtBlock(nn.Module):
    """``model.py`` ``resnext_block``: ``relu(expand(conv_3x3(shrink(x))) + shortcut)``, the
    shortcut being ``x`` or, with ``has_proj``, a 1×1 conv + BN (``shortcut``) after a 2×2
    average pool (``dsp``) where the stride is 2."""

    def __init__(
        self, in_channels: int, out_channels: int, stride: int, groups: int, has_proj: bool
    ) -> None:
        super().__init__()
        bottleneck = out_channels // 4
        self.conv_1x1_shrink = Conv(in_channels, bottleneck, kernel_size=1, padding=0)
        self.conv_3x3 = Conv(bottleneck, bottleneck, 3, stride=stride, groups=groups)
        self.conv_1x1_expand = Conv(bottleneck, out_channels, 1, padding=0, has_relu=False)
        self.dsp = nn.AvgPool2d(kernel_size=2, stride=2) if has_proj and stride == 2 else None
        self.shortcut = (
            Conv(in_channels, out_channels, 1, padding=0, has_relu=False) if has_proj else None
        )
        self.relu = nn.ReLU()

    def forward(self, x: Tensor) -> Tensor:
        proj = x
        if self.shortcut is not None:
            proj = self.shortcut(proj if self.dsp is None else self.dsp(proj))
        x = self.conv_1x1_expand(self.conv_3x3(self.conv_1x1_shrink(x)))
        return self.relu(x + proj)


class ConvBlock(nn.Module):
    """``model.py`` ``conv_block``: ``conv01(conv00(x)) + conv11(conv10(x))``, a 1×k then k×1
    path and a k×1 then 1×k path (batch norm each, ReLU after the first of each)."""

    def __init__(self, in_channels: int, out_channels: int, ks: int = 3) -> None:
        super().__init__()
        row, col, half = (1, ks), (ks, 1), ks // 2
        self.conv00 = Conv(in_channels, out_channels, row, padding=(0, half))
        self.conv01 = Conv(out_channels, out_channels, col, padding=(half, 0), has_relu=False)
        self.conv10 = Conv(in_channels, out_channels, col, padding=(half, 0))
        self.conv11 = Conv(out_channels, out_channels, row, padding=(0, half), has_relu=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.conv01(self.conv00(x)) + self.conv11(self.conv10(x))


class RefineBlock(nn.Module):
    """``model.py`` ``refine_block``: ``refine1(refine0(x)) + x`` (k×k convs with batch norm,
    ReLU after the first)."""

    def __init__(self, channels: int, ks: int = 3) -> None:
        super().__init__()
        self.refine0 = Conv(channels, channels, ks, padding=ks // 2)
        self.refine1 = Conv(channels, channels, ks, padding=ks // 2, has_relu=False)

    def forward(self, x: Tensor) -> Tensor:
        return self.refine1(self.refine0(x)) + x


class Encoder(nn.Module):
    """``model.py`` ``Encoder`` (module docstring): ``conv00`` and the stages of
    :data:`ENCODER_STAGES`, each stage's input also average-pooled to 1/64."""

    def __init__(self, in_channels: int) -> None:
        super().__init__()
        self.conv00 = Conv(in_channels, STEM_CHANNELS, stride=2)
        channels = STEM_CHANNELS
        for stage, width, blocks, groups, pool, kernel in ENCODER_STAGES:
            for i in range(blocks):
                block = ResNeXtBlock(channels, width, 2 if i == 0 else 1, groups, i == 0)
                self.add_module(f"{stage}_{i}", block)
                channels = width
            self.add_module(pool, nn.AvgPool2d(kernel_size=kernel, stride=kernel))

    def forward(self, x: Tensor) -> tuple[Tensor, ...]:
        """(N, C, H, W), H and W multiples of 64 → the six levels, deepest first: (N, 2000,
        H/64, W/64), (N, 512, H/32, ...), 256 at 1/16, 128 at 1/8, 64 at 1/4, 16 at 1/2."""
        x = self.conv00(x)
        levels, pools = [x], []
        for stage, _, blocks, _, pool, _ in ENCODER_STAGES:
            pools.append(getattr(self, pool)(x))
            for i in range(blocks):
                x = getattr(self, f"{stage}_{i}")(x)
            levels.append(x)
        return (torch.cat([*pools, x], dim=1), *levels[-2::-1])


class UNet(nn.Module):
    """``model.py`` ``UNet``: :class:`Encoder` and the depth and valid decoders (module
    docstring)."""

    def __init__(self, in_channels: int) -> None:
        super().__init__()
        self.encoder = Encoder(in_channels)
        levels = len(DECODER_CHANNELS)
        for prefix in ("", "valid_"):
            for idx in range(levels):
                enc, width = DECODER_ENCODER_CHANNELS[idx], DECODER_CHANNELS[idx]
                score = (
                    ConvBlock(enc, width, 3)
                    if DECODER_CONV_BLOCK[idx]
                    else Conv(enc, width, has_relu=False)
                )
                self.add_module(f"{prefix}score{idx}", score)
                self.add_module(f"{prefix}refine{idx}", RefineBlock(width, 3))
                last = idx == levels - 1
                out = 1 if last else DECODER_OUT_CHANNELS[idx]
                self.add_module(f"{prefix}resize{idx}", Deconv(width, out, has_bn=not last))

    def _branch(self, prefix: str, blocks: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
        """One decoder's output and its level-4 output (``last_fm``)."""
        up, last_fm = None, None
        for idx, block in enumerate(blocks):
            x = getattr(self, f"{prefix}score{idx}")(block)
            if up is not None:
                x = x + up
            up = getattr(self, f"{prefix}resize{idx}")(getattr(self, f"{prefix}refine{idx}")(x))
            if idx == len(blocks) - 2:
                last_fm = up
        return up, last_fm

    def forward(self, data: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(N, C, H, W), H and W multiples of 64 → depth (N, 1, H, W), ReLU'd; valid (N, 1, H,
        W) in (0, 1); ``last_fm`` (N, 8, H/2, W/2)."""
        blocks = self.encoder(data)
        pred, last_fm = self._branch("", blocks)
        valid, _ = self._branch("valid_", blocks)
        return F.relu(pred), torch.sigmoid(valid), last_fm


class FullyConnected(nn.Module):
    """``model.py`` ``FullyConnected`` (no dropout): ``nn.Linear``, then a leaky ReLU (0.1)."""

    def __init__(self, in_features: int, out_features: int) -> None:
        super().__init__()
        self.fully_connected = nn.Linear(in_features, out_features)
        self.activation_func = nn.LeakyReLU(negative_slope=LEAKY_SLOPE)

    def forward(self, x: Tensor) -> Tensor:
        return self.activation_func(self.fully_connected(x))


class FullyConnectedEncoder(nn.Module):
    """``model.py`` ``FullyConnectedEncoder`` with its defaults: ``mlp``, six
    :class:`FullyConnected`, 3 → 32 → 64 → 96 → 64 → 32 → 8. (..., 3) → (..., 8)."""

    def __init__(self) -> None:
        super().__init__()
        sizes = (3, *POINT_NEURONS, EMBEDDING)
        self.mlp = nn.Sequential(
            *(FullyConnected(a, b) for a, b in zip(sizes, sizes[1:], strict=False))
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.mlp(x)


def downsample_depthmap(depth: Tensor, factor: float) -> Tensor:
    """``model.py`` ``Network.downsample_depthmap``: each non-zero pixel (r, c) of ``depth``
    (N, C, H, W) moved to ``(int(r·factor), int(c·factor))`` of a zero (N, C, int(H·factor),
    int(W·factor)) float32 map. Where several land on one pixel, the last in row-major order
    wins: what their ``out[index] = value`` gives run serially (module docstring,
    "Differences")."""
    n, c, h, w = depth.shape
    new_h, new_w = int(h * factor), int(w * factor)
    out = torch.zeros((n, c, new_h, new_w), device=depth.device)
    index = list(torch.nonzero(depth, as_tuple=True))
    values = depth[tuple(index)]
    index[2] = (index[2] * factor).long()
    index[3] = (index[3] * factor).long()
    flat = ((index[0] * c + index[1]) * new_h + index[2]) * new_w + index[3]
    order = torch.arange(flat.numel(), device=depth.device)
    last = torch.full((out.numel(),), -1, dtype=torch.int64, device=depth.device)
    last = last.scatter_reduce(0, flat, order, reduce="amax")
    hit = last >= 0
    out.view(-1)[hit] = values[last[hit]].to(out.dtype)
    return out


class SparseBeatsDense(nn.Module):
    """``model.py`` ``Network``: ``G1``, ``G2``, ``G3`` (:class:`UNet`) and
    ``calibrated_params_encoder`` (:class:`FullyConnectedEncoder`), with their key names; see
    the module docstring. Its only configuration is the released one."""

    def __init__(self) -> None:
        super().__init__()
        self.G1 = UNet(4)  # noqa: N815 - the authors' key names
        self.G2 = UNet(12)  # noqa: N815
        self.G3 = UNet(12)  # noqa: N815
        self.calibrated_params_encoder = FullyConnectedEncoder()

    def forward(
        self, img: Tensor, radar: Tensor, radar_pts: Tensor, valid_radar_pts_cnts: Tensor
    ) -> tuple[list[Tensor], list[Tensor]]:
        """``Network.forward`` on padded inputs (:func:`released_depth` pads and crops).

        Args:
            img: (B, 3, H, W) BGR, 0-255, float; H and W multiples of 256.
            radar: (B, 1, H, W) radar depth map in metres (:func:`released_inputs`).
            radar_pts: (B, K, 3) radar points in the camera frame, metres.
            valid_radar_pts_cnts: (B,) how many of each frame's points count (at least 1).

        Returns:
            The depth maps in metres (B, 1, H/4, W/4), (B, 1, H/2, W/2), (B, 1, H, W) and the
            valid masks of the same sizes, each list coarsest first.
        """
        b, k, _ = radar_pts.shape
        emb = self.calibrated_params_encoder(radar_pts.reshape(b * k, -1)).reshape(b, k, -1)
        counts = valid_radar_pts_cnts.reshape(-1)
        mean = torch.stack([e[: int(n)].mean(dim=0) for e, n in zip(emb, counts, strict=True)])
        mean = mean[..., None, None]
        data_dw2 = torch.cat((_bilinear(img, 0.5), downsample_depthmap(radar, 0.5)), dim=1)
        data_dw4 = torch.cat((_bilinear(img, 0.25), downsample_depthmap(radar, 0.25)), dim=1)
        pred1, valid1, fm1 = self.G1(data_dw4)
        pred2, valid2, fm2 = self.G2(torch.cat([data_dw2, _bilinear(fm1 + mean, 4.0)], dim=1))
        pred3, valid3, _ = self.G3(torch.cat((img, radar, _bilinear(fm2 + mean, 4.0)), dim=1))
        return [pred1, pred2, pred3], [valid1, valid2, valid3]


def _bilinear(x: Tensor, scale: float) -> Tensor:
    """``nnf.interpolate(x, scale_factor=scale, mode="bilinear")`` as ``Network.forward``
    calls it (``align_corners=False``, its default)."""
    return F.interpolate(x, scale_factor=scale, mode="bilinear", align_corners=False)


def pad_to_released(x: Tensor) -> Tensor:
    """``model.py`` ``Network.padding``: (B, C, H, W) zero-padded at the bottom and right to
    ``(H // 256 + 1) · 256`` × ``(W // 256 + 1) · 256``, float32 (a multiple of 256 still
    gets 256 more)."""
    b, c, h, w = x.shape
    new_h, new_w = (h // PAD_MULTIPLE + 1) * PAD_MULTIPLE, (w // PAD_MULTIPLE + 1) * PAD_MULTIPLE
    out = torch.zeros((b, c, new_h, new_w), device=x.device)
    out[:, :, :h, :w] = x
    return out


def _input_error(argument: str, message: str) -> ArgumentError:
    return ArgumentError(f"{{{argument}}}: {message}", argument, owner=released_depth)


def _check_inputs(img: Tensor, radar: Tensor, radar_pts: Tensor, counts: Tensor) -> None:
    if img.dim() != 4 or img.shape[1] != 3:
        raise _input_error("img", f"shape {list(img.shape)}, expected (B, 3, H, W), BGR 0-255")
    b, _, h, w = img.shape
    if tuple(radar.shape) != (b, 1, h, w):
        raise _input_error("radar", f"shape {list(radar.shape)}, expected {[b, 1, h, w]}")
    if radar_pts.dim() != 3 or radar_pts.shape[0] != b or radar_pts.shape[2] != 3:
        raise _input_error("radar_pts", f"shape {list(radar_pts.shape)}, expected ({b}, K, 3)")
    if counts.numel() != b:
        raise _input_error("valid_radar_pts_cnt", f"{counts.numel()} counts for {b} frames")
    if bool((counts < 1).any()):
        raise _input_error(
            "valid_radar_pts_cnt",
            "a frame without radar points: the authors' network averages no embedding and "
            "gives NaN everywhere",
        )


@torch.no_grad()
def released_depth(
    net: SparseBeatsDense,
    img: Tensor,
    radar: Tensor,
    radar_pts: Tensor,
    valid_radar_pts_cnt: Tensor,
) -> tuple[Tensor, Tensor]:
    """Depth from the inputs as eval.py gives them, as ``model.py`` ``Network.forward_test``
    computes it: cast to the network's dtype, :func:`pad_to_released`, ``forward``, crop.

    Args:
        net: the network (in eval mode: eval.py calls ``net.eval()``).
        img: (B, 3, H, W) BGR, 0-255 (uint8 or float).
        radar: (B, 1, H, W) radar map in metres.
        radar_pts: (B, K, 3) radar points in the camera frame, metres (K = 200 in eval.py).
        valid_radar_pts_cnt: (B,) or (B, 1): how many of each frame's points count.

    Returns:
        depth (B, 1, H, W) in metres (≥ 0, not capped) and valid (B, 1, H, W) in (0, 1).

    Raises:
        ArgumentError: inputs of the wrong shapes, or a frame without points (NaN in theirs).
    """
    counts = torch.as_tensor(valid_radar_pts_cnt).reshape(-1)
    _check_inputs(img, radar, radar_pts, counts)
    weight = next(net.parameters())
    h, w = img.shape[-2:]
    img = pad_to_released(img.to(device=weight.device, dtype=weight.dtype))
    radar = pad_to_released(radar.to(device=weight.device, dtype=weight.dtype))
    radar_pts = radar_pts.to(device=weight.device, dtype=weight.dtype)
    preds, valids = net(img, radar, radar_pts, counts.to(device=weight.device, dtype=torch.long))
    return preds[-1][:, :, :h, :w], valids[-1][:, :, :h, :w]


def _rotation(quaternion: Sequence[float]) -> Tensor:
    """The rotation matrix of a (w, x, y, z) quaternion after normalising it (as pyquaternion's
    ``Quaternion.rotation_matrix``), float64."""
    w, x, y, z = (torch.as_tensor(quaternion, dtype=torch.float64) / _norm(quaternion)).tolist()
    return torch.tensor(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ],
        dtype=torch.float64,
    )


def _norm(quaternion: Sequence[float]) -> float:
    return float(torch.as_tensor(quaternion, dtype=torch.float64).norm())


def _pose(record: Mapping[str, Any], name: str) -> tuple[Tensor, Tensor]:
    if not isinstance(record, Mapping) or not {"translation", "rotation"} <= set(record):
        raise ArgumentError(
            f"{{{name}}}: expected a nuScenes record with 'translation' and 'rotation' "
            "(w, x, y, z)",
            name,
            owner=radar_to_camera,
        )
    translation = torch.as_tensor(record["translation"], dtype=torch.float64).reshape(3)
    return _rotation(record["rotation"]), translation


def radar_to_camera(
    points: Tensor,
    radar_calibrated_sensor: Mapping[str, Any],
    radar_ego_pose: Mapping[str, Any],
    camera_calibrated_sensor: Mapping[str, Any],
    camera_ego_pose: Mapping[str, Any],
) -> Tensor:
    """Radar points moved into the camera frame as ``utils.py``
    ``map_pointcloud1_to_pointcloud2`` moves them: radar → ego (the radar's
    ``calibrated_sensor``) → global (the ego pose at the radar's timestamp) → ego at the
    camera's timestamp → camera, in float64.

    Args:
        points: (N, 3) x, y, z in the radar's frame, metres (a ``.pcd``'s first three fields).
        radar_calibrated_sensor: the radar's nuScenes ``calibrated_sensor`` record (their info
            files' ``sensor2ego_*``): ``translation`` (3,) in metres, ``rotation`` (w, x, y, z).
        radar_ego_pose: the ``ego_pose`` record at the radar's timestamp (``ego2global_*``).
        camera_calibrated_sensor: the camera's ``calibrated_sensor`` record.
        camera_ego_pose: the ``ego_pose`` record at the camera's timestamp.

    Returns:
        (N, 3) float64, (x right, y down, z forward) in the camera frame, metres.

    Raises:
        ArgumentError: ``points`` not (N, 3), or a record without translation and rotation.
    """
    if points.dim() != 2 or points.shape[1] != 3:
        raise ArgumentError(
            f"{{points}}: shape {list(points.shape)}, expected (N, 3)",
            "points",
            owner=radar_to_camera,
        )
    p = points.to(torch.float64).T
    rotation, translation = _pose(radar_calibrated_sensor, "radar_calibrated_sensor")
    p = rotation @ p + translation[:, None]
    rotation, translation = _pose(radar_ego_pose, "radar_ego_pose")
    p = rotation @ p + translation[:, None]
    rotation, translation = _pose(camera_ego_pose, "camera_ego_pose")
    p = rotation.T @ (p - translation[:, None])
    rotation, translation = _pose(camera_calibrated_sensor, "camera_calibrated_sensor")
    p = rotation.T @ (p - translation[:, None])
    return p.T.contiguous()


def _radar_map(points: Tensor, intrinsic: Tensor, height: int, width: int) -> Tensor:
    """``utils.py`` ``project_3d_to_2d``, ``canvas_filter`` and ``get_radar_map``: (H, W)
    float32, each kept point's depth in its whole column, the later point of a column
    winning."""
    uvw = intrinsic.to(torch.float64) @ points.T
    uvw = uvw / uvw[2]
    u, v = uvw[0], uvw[1]
    kept = (u >= 0) & (v >= 0) & (u < width) & (v < height)
    columns, depth = u[kept].long(), points[kept, 2]
    order = torch.arange(columns.numel())
    last = torch.full((width,), -1, dtype=torch.int64).scatter_reduce(
        0, columns, order, reduce="amax"
    )
    row = torch.zeros(width, dtype=torch.float32)
    hit = last >= 0
    row[hit] = depth[last[hit]].to(torch.float32)
    return row.expand(height, width).contiguous()


def released_inputs(
    image: Tensor,
    points: Tensor,
    intrinsic: Tensor,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """The network's inputs for one frame as eval.py's ``Vidar.__getitem__`` builds them
    (module docstring, "The inputs"), batched as its ``eval`` passes them on.

    Args:
        image: (3, H, W) the camera image, **RGB**, 0-255 (uint8 or float); it is handed on
            as BGR, as ``cv2.imread`` gives it.
        points: (N, 3) the radar sweep's points in the camera frame, metres, in file order
            (:func:`radar_to_camera`; read with the devkit's default radar filters).
        intrinsic: (3, 3) the camera matrix (``camera_intrinsic``) for this image's pixels.
        generator: draws the 200 points kept of a sweep of more (theirs: unseeded).

    Returns:
        ``img`` (1, 3, H, W) BGR, ``radar`` (1, 1, H, W) float32 metres, ``radar_pts`` (1,
        200, 3) float64, ``valid_radar_pts_cnt`` (1,) int64 (N): :func:`released_depth`'s
        arguments.

    Raises:
        ArgumentError: an image that is not (3, H, W), points not (N, 3) or none, an
            intrinsic that is not 3×3.
    """
    if image.dim() != 3 or image.shape[0] != 3:
        raise ArgumentError(
            f"{{image}}: shape {list(image.shape)}, expected (3, H, W), RGB 0-255",
            "image",
            owner=released_inputs,
        )
    if points.dim() != 2 or points.shape[1] != 3 or points.shape[0] == 0:
        raise ArgumentError(
            f"{{points}}: shape {list(points.shape)}, expected (N, 3) with N ≥ 1: the authors' "
            "network gives NaN for a frame without radar points",
            "points",
            owner=released_inputs,
        )
    if tuple(intrinsic.shape) != (3, 3):
        raise ArgumentError(
            f"{{intrinsic}}: shape {list(intrinsic.shape)}, expected (3, 3)",
            "intrinsic",
            owner=released_inputs,
        )
    points = points.to(torch.float64).cpu()
    height, width = image.shape[-2:]
    count = points.shape[0]
    padded = torch.zeros((RADAR_PTS_NUM, 3), dtype=torch.float64)
    if count <= RADAR_PTS_NUM:
        padded[:count] = points
    else:
        padded = points[torch.randperm(count, generator=generator)[:RADAR_PTS_NUM].sort().values]
    return {
        "img": image.flip(0)[None],
        "radar": _radar_map(points, intrinsic.cpu(), height, width)[None, None],
        "radar_pts": padded[None],
        "valid_radar_pts_cnt": torch.tensor([count]),
    }


def valid_label(seg_mask: Tensor) -> Tensor:
    """The valid branch's training label from one of the authors' segmentation masks
    (``dataset.py`` ``Vidar.__getitem__``: ``seg_mask_roi``). Not an input of the network.

    Args:
        seg_mask: (H, W) class ids (ADE20K, 0-149) as ``cv2.imread(path,
            cv2.IMREAD_GRAYSCALE)`` reads ``data/nuscenes/seg_mask/<image name>.png``.

    Returns:
        (1, H, W) float32: 1 on the classes of :data:`SEG_MASK_CLASSES`, 0 elsewhere.
    """
    classes = torch.tensor(SEG_MASK_CLASSES, device=seg_mask.device)
    return torch.isin(seg_mask.long(), classes).to(torch.float32)[None]


def _error(path: object, message: str, argument: str = "path") -> ReleasedWeightsError:
    return released_error(path, message, argument, owner=load_released)


_WHAT = "Sparse Beats Dense's released checkpoint"


def released_state(
    checkpoint: Any,
    net: SparseBeatsDense,
    path: str | os.PathLike = "<state>",
    argument: str = "path",
) -> dict[str, Tensor]:
    """``net``'s state dict from the released file's contents: ``checkpoint['network']``, key
    for key (module docstring, "The checkpoint"), checked against ``net`` key by key and shape
    by shape.

    Raises:
        ReleasedWeightsError: one line naming ``path`` and the first entry or key that is
            missing, unexpected, not a tensor or of another shape (in the file's own names).
    """
    stored = checkpoint.get(NETWORK_ENTRY) if isinstance(checkpoint, Mapping) else None
    if not isinstance(stored, Mapping):
        held = (
            f"it holds {', '.join(map(str, list(checkpoint)[:4]))}"
            if isinstance(checkpoint, Mapping) and checkpoint
            else f"it is a {type(checkpoint).__name__}"
        )
        raise _error(
            path, f"not {_WHAT}: expected a dict with a '{NETWORK_ENTRY}' dict; {held}", argument
        )

    def fail(message: str) -> ReleasedWeightsError:
        return _error(path, f"not {_WHAT}: {message}", argument)

    return matched_state(stored, net.state_dict(), NETWORK_ENTRY, fail)


def load_released(net: SparseBeatsDense, path: str | os.PathLike, argument: str = "path") -> int:
    """Load the authors' released ``model.ckpt`` (or a ``.net.ckpt``) into ``net``, with
    ``torch.load(weights_only=True)`` and strictly.

    ``argument`` is the name errors give the file (a caller's own argument).

    Returns:
        The training step the file records (``clock['step']``; -1 if none).

    Raises:
        ArgumentFileError: no file at ``path``.
        ReleasedWeightsError: a file that cannot be read with weights only, or not of this
            network (one line naming the file and the first wrong key).
    """
    checkpoint = read_released(path, argument, load_released, NUMPY_FLOAT64_GLOBALS)
    net.load_state_dict(released_state(checkpoint, net, path, argument), strict=True)
    clock = checkpoint.get("clock")
    step = clock.get("step", -1) if isinstance(clock, Mapping) else -1
    return step if isinstance(step, int) else -1
