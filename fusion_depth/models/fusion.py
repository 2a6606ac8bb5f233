"""Early fusion of the RGB image with the sparse depth channel (the paper's three modalities)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

FUSION_MODES = ("rgb", "concat", "add")


class InputFusion(nn.Module):
    """Turns (image in [0, 1], sparse depth in metres) into the 3-channel encoder input.

    - ``rgb``: the ImageNet-normalised image; the sparse map is ignored.
    - ``concat``: image and normalised sparse channel stacked to 4 channels, then a learned 1×1
      conv to 3 channels so the pretrained encoder's first layer still fits. It starts as the
      identity on RGB and zero on depth, so pretrained features are undisturbed at step 0.
    - ``add``: the normalised sparse channel added to every normalised RGB channel.

    The sparse channel is normalised the same way in both fusion modes, ``depth / max_depth``,
    which keeps 0 meaning "no return".
    """

    def __init__(
        self,
        mode: str = "rgb",
        max_depth: float = 80.0,
        mean: Sequence[float] = (0.485, 0.456, 0.406),
        std: Sequence[float] = (0.229, 0.224, 0.225),
    ) -> None:
        super().__init__()
        if mode not in FUSION_MODES:
            raise ValueError(f"fusion.mode={mode!r}: expected one of {list(FUSION_MODES)}")
        if max_depth <= 0:
            raise ValueError(f"max_depth={max_depth}: expected a positive depth in metres")
        self.mode = mode
        self.max_depth = float(max_depth)
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        if mode == "concat":
            self.mix = nn.Conv2d(4, 3, kernel_size=1)
            with torch.no_grad():
                self.mix.weight.zero_()
                self.mix.weight[:, :3, 0, 0] = torch.eye(3)
                self.mix.bias.zero_()

    @property
    def uses_sparse(self) -> bool:
        return self.mode != "rgb"

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        x = (image - self.mean) / self.std
        if self.mode == "rgb":
            return x
        if sparse is None:
            raise ValueError(f"fusion mode {self.mode!r} needs the sparse depth map")
        s = sparse / self.max_depth
        if self.mode == "concat":
            return self.mix(torch.cat([x, s], dim=1))
        return x + s
