"""A depth prior as its own input branch of an encoder-decoder network (``model=densedepth
prior=...``): the plug-in mode of TacoDepth (Wang et al., CVPR 2025), where a frozen monocular
model's relative depth is a further input of the radar-camera network.

TacoDepth's abstract and method describe a plug-in inference mode that takes an initial
relative depth from another predictor; its code is not released, and the layers that take the
relative depth could not be checked against the paper's text here (issue 70 builds TacoDepth
itself from the paper). The branch here is the platform's choice, made so that the prior is a
plug-in and not a squeeze: its own small encoder, whose features at each of the image
encoder's five strides are added to the image encoder's, through 1×1 projections that start at
zero (ControlNet's "zero convolutions", Zhang et al., ICCV 2023, Sec. 3.1). At the start the
network is exactly the one without a prior, and the image encoder's input stays the image (and
the radar): the prior is never mixed into its three channels.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

# Channels of the branch's level at stride 2, 4, 8, 16 and 32: a small fraction of an image
# encoder's (ResNet-18's are 64, 64, 128, 256, 512), as the prior is one smooth channel.
BRANCH_WIDTHS = (16, 32, 64, 96, 128)


def _conv(in_channels: int, out_channels: int, stride: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


class PriorBranch(nn.Module):
    """The prior's encoder: five levels at strides 2 … 32, each added to the image encoder's
    feature map of the same stride by a zero-initialised 1×1 projection.

    Args:
        channels: the image encoder's channels at strides 2, 4, 8, 16, 32
            (:attr:`~fusion_depth.models.encoder.Encoder.channels`).
        widths: the branch's own channels per level.

    Shape:
        - prior: (B, 1, H, W), the prior's channel (normalised per frame to [0, 1]; zeros for
          no prior); H and W multiples of 32.
        - features: the image encoder's five maps (B, C_i, H / s, W / s).
        - output: the five maps, each plus the branch's projection.

    Raises:
        ValueError: ``channels`` and ``widths`` are not five each.
    """

    def __init__(self, channels: Sequence[int], widths: Sequence[int] = BRANCH_WIDTHS) -> None:
        super().__init__()
        if len(channels) != 5 or len(widths) != 5:
            raise ValueError(
                f"channels {list(channels)} and widths {list(widths)}: expected five each "
                "(strides 2, 4, 8, 16, 32)"
            )
        levels, before = [], 1
        for width in widths:
            levels.append(nn.Sequential(_conv(before, width, 2), _conv(width, width, 1)))
            before = width
        self.levels = nn.ModuleList(levels)
        self.projections = nn.ModuleList(
            nn.Conv2d(width, channel, 1) for width, channel in zip(widths, channels, strict=True)
        )
        for projection in self.projections:  # zero: the network starts as without a prior
            nn.init.zeros_(projection.weight)
            nn.init.zeros_(projection.bias)

    def forward(self, prior: torch.Tensor, features: Sequence[torch.Tensor]) -> list[torch.Tensor]:
        out, x = [], prior
        for level, projection, feature in zip(self.levels, self.projections, features, strict=True):
            x = level(x.to(feature.dtype))
            out.append(feature + projection(x))
        return out
