"""Batch-level training augmentation (Kornia), run on the device after transfer."""

from __future__ import annotations

from collections.abc import Sequence

import kornia.augmentation as K
import torch
from torch import nn

from fusion_depth.utils.schema import PROBABILITY, Rule, Schema, is_number


class TrainAugmentation(nn.Module):
    """The paper's online augmentation: horizontal flip, brightness and contrast jitter.

    The flip moves image, sparse map, depth, a cached prior (``prior``) and radar points
    (``radar_points``: u → W - 1 - u) together; the colour jitter touches the image only.
    Kornia's ``ColorJitter`` uses the torchvision formulas (multiplicative brightness, contrast
    blended with the mean), which is what the paper's ranges refer to.
    """

    def __init__(
        self,
        flip_p: float = 0.5,
        color_p: float = 0.5,
        brightness: Sequence[float] = (0.75, 1.25),
        contrast: Sequence[float] = (0.9, 1.1),
    ) -> None:
        super().__init__()
        self.flip = K.RandomHorizontalFlip(p=flip_p)
        self.color = K.ColorJitter(
            brightness=tuple(brightness), contrast=tuple(contrast), p=color_p
        )

    @torch.no_grad()
    def forward(self, batch: dict) -> dict:
        image, sparse, depth = batch["image"], batch["sparse"], batch["depth"]
        maps = [image, sparse, depth]
        prior = batch.get("prior")
        if prior is not None:
            maps.append(prior.to(image.dtype))
        stacked = self.flip(torch.cat(maps, dim=1))
        image, sparse, depth, *flipped_prior = stacked.split([m.shape[1] for m in maps], dim=1)
        out = dict(batch)
        if prior is not None:
            out["prior"] = flipped_prior[0].contiguous()
        points = batch.get("radar_points")
        if points is not None:  # the flipped images' returns mirror too: u → W - 1 - u
            flipped = self.flip._params["batch_prob"].to(points.device) > 0.5
            mirror = flipped[:, None] & (points[..., 5] > 0)
            points = points.clone()
            points[..., 0] = torch.where(
                mirror, image.shape[-1] - 1 - points[..., 0], points[..., 0]
            )
            out["radar_points"] = points
        return {
            **out,
            "image": self.color(image.contiguous()),
            "sparse": sparse.contiguous(),
            "depth": depth.contiguous(),
        }


_FACTOR_RANGE = Rule(
    lambda v: (
        isinstance(v, list) and len(v) == 2 and all(is_number(x) for x in v) and 0 < v[0] <= v[1]
    ),
    "[low, high] factors with 0 < low ≤ high",
)
# What :class:`TrainAugmentation`'s arguments accept (fusion_depth.utils.schema).
ARGUMENT_RULES: Schema = {
    "flip_p": PROBABILITY,
    "color_p": PROBABILITY,
    "brightness": _FACTOR_RANGE,
    "contrast": _FACTOR_RANGE,
}
