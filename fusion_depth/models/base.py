"""What every depth network of the platform is: the contract training, evaluation, prediction and
export rely on, whatever the architecture (``model=densedepth``, ``sparse_to_dense``, ...).

A network predicts in its own *output space*: the paper's DenseDepth predicts reciprocal depth
``depth_scale / depth`` (Sec. 3.2), sparse-to-dense predicts metres (Ma & Karaman 2018, Sec. III).
The loss compares the prediction with the ground truth mapped into that space
(:meth:`DepthModel.to_output`), and everything else reads metres (:meth:`DepthModel.to_depth`).
"""

from __future__ import annotations

from typing import ClassVar, Literal

import torch
from torch import nn

from fusion_depth.data.base import check_depth_range

OutputSpace = Literal["reciprocal", "depth"]


class DepthModel(nn.Module):
    """Base class of the platform's depth networks.

    Subclasses build their layers, set :attr:`fusion` (an input module with ``mode`` and
    ``uses_sparse``) and implement ``forward(image, sparse) -> output`` (``forward(image, sparse,
    points)`` with :attr:`takes_points`). A subclass may define ``training_loss(batch,
    depth_loss) -> dict`` to compute its own training loss (``model=radarnet``'s stages);
    :class:`~fusion_depth.runner.module.DepthModule` then uses it.

    Args:
        min_depth: the depth range's lower end in metres; predictions are clipped to it.
        max_depth: the depth range's upper end in metres.
        depth_scale: ``depth_scale / depth`` is the reciprocal output space's value.

    Shape:
        - image: (B, 3, H, W) RGB in [0, 1]; H and W multiples of 32.
        - sparse: (B, 1, H, W) metres, 0 = no return (None for ``fusion=rgb``).
        - output: (B, 1, h, w) in :attr:`output_space`, at the network's own resolution
          (DenseDepth: half the input; sparse-to-dense: the input's).

    Raises:
        ArgumentError: ``0 < min_depth < max_depth`` does not hold
            (:func:`~fusion_depth.data.base.check_depth_range`).
        ValueError: ``depth_scale > 0`` does not hold.
    """

    output_space: ClassVar[OutputSpace] = "reciprocal"
    # A network that also takes the radar returns as points: forward(image, sparse, points),
    # points (B, P, 6) with the columns of fusion_depth.data.RADAR_POINT_FIELDS or None.
    takes_points: ClassVar[bool] = False
    # The sides' multiple the network needs: predict_depth pads an image to it (and cuts the
    # output back). 1: any size as given (a released network run as its authors run it).
    input_multiple: ClassVar[int] = 32
    fusion: nn.Module

    @property
    def partial_output(self) -> bool:
        """Whether a depth of 0 in the output means "no prediction here", so that only the
        pixels it fills are scored (RadarNet's association stage). A network that predicts
        every pixel clips to ``min_depth`` > 0 and leaves this False: its 0 would be a bug, and
        scoring it keeps the bug visible."""
        return False

    def __init__(self, min_depth: float, max_depth: float, depth_scale: float) -> None:
        super().__init__()
        check_depth_range(min_depth, max_depth, owner=type(self))
        if depth_scale <= 0:
            raise ValueError(f"depth_scale={depth_scale}: expected a positive number")
        self.min_depth, self.max_depth, self.depth_scale = min_depth, max_depth, depth_scale

    @property
    def reciprocal_range(self) -> tuple[float, float]:
        """The reciprocal-depth values of max_depth and min_depth."""
        return self.depth_scale / self.max_depth, self.depth_scale / self.min_depth

    def to_reciprocal(self, depth: torch.Tensor) -> torch.Tensor:
        """Metres → clipped reciprocal depth (invalid zeros map to the far end; mask them)."""
        low, high = self.reciprocal_range
        return (self.depth_scale / depth.clamp_min(1e-6)).clamp(low, high)

    def to_output(self, depth: torch.Tensor) -> torch.Tensor:
        """Metres → the output space, where the loss compares prediction and ground truth."""
        if self.output_space == "depth":
            return depth.clamp(self.min_depth, self.max_depth)
        return self.to_reciprocal(depth)

    def to_depth(self, output: torch.Tensor) -> torch.Tensor:
        """The output space → metres in ``[min_depth, max_depth]``."""
        if self.output_space == "depth":
            return output.clamp(self.min_depth, self.max_depth)
        low, high = self.reciprocal_range
        return self.depth_scale / output.clamp(low, high)

    @staticmethod
    def check_input_size(image: torch.Tensor) -> None:
        """The encoders halve the resolution five times, and the decoders must line up."""
        height, width = image.shape[-2:]
        if height % 32 or width % 32:
            raise ValueError(
                f"input size {height}×{width}: height and width must be multiples of 32"
            )

    def predict_depth(
        self,
        image: torch.Tensor,
        sparse: torch.Tensor | None = None,
        points: torch.Tensor | None = None,
        prior: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Depth in metres at the network's output resolution, (B, 1, h, w). ``points`` (the
        batch's ``radar_points``) reach only a network that :attr:`takes_points`; ``prior``
        (the batch's cached prior, :mod:`fusion_depth.runner.prior_cache`) only a network
        built with one, which then does not run its own."""
        given = {} if prior is None else {"prior": prior}  # a network without one takes none
        if self.takes_points:
            return self.to_depth(self.forward(image, sparse, points, **given))
        return self.to_depth(self.forward(image, sparse, **given))
