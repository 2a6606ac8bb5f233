"""DenseDepth decoder: bilinear up-blocks with skip concatenation (Alhashim & Wonka, 2018)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn


class UpBlock(nn.Module):
    """Upsample to the skip's size, concatenate, then two 3×3 convs with LeakyReLU(0.2)."""

    def __init__(self, in_channels: int, out_channels: int) -> None:
        super().__init__()
        self.conv_a = nn.Conv2d(in_channels, out_channels, 3, padding=1)
        self.conv_b = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.act = nn.LeakyReLU(0.2)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=True)
        x = self.act(self.conv_a(torch.cat([x, skip], dim=1)))
        return self.act(self.conv_b(x))


class DenseDepthDecoder(nn.Module):
    """1×1 conv halving the bottleneck, four up-blocks halving channels, 3×3 conv to one channel.

    ``encoder_channels`` lists the encoder outputs at strides 2, 4, 8, 16, 32; the output is at
    stride 2, i.e. half the input resolution, as in DenseDepth.
    """

    def __init__(self, encoder_channels: Sequence[int]) -> None:
        super().__init__()
        if len(encoder_channels) != 5:
            raise ValueError(f"expected 5 encoder feature widths, got {list(encoder_channels)}")
        *skips, bottleneck = encoder_channels
        width = bottleneck // 2
        self.bottleneck = nn.Conv2d(bottleneck, width, 1)
        blocks = []
        for skip in reversed(skips):  # strides 16, 8, 4, 2
            blocks.append(UpBlock(width + skip, width // 2))
            width //= 2
        self.up = nn.ModuleList(blocks)
        self.head = nn.Conv2d(width, 1, 3, padding=1)

    def forward(self, features: Sequence[torch.Tensor]) -> torch.Tensor:
        *skips, bottleneck = features
        x = self.bottleneck(bottleneck)
        for block, skip in zip(self.up, reversed(skips), strict=True):
            x = block(x, skip)
        return self.head(x)
