"""Early fusion of the RGB image with the sparse depth channel (the paper's three modalities)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from fusion_depth.errors import check_choice
from fusion_depth.utils.schema import Schema, one_of

FUSION_MODES = ("rgb", "concat", "add")
# How tables and plots name each mode (the paper's Table 1: RGB, RGB-Fusion, and addition).
FUSION_LABELS: dict[str, str] = {"rgb": "RGB", "concat": "RGB-Fusion", "add": "RGB-Add"}
SPARSE_ENCODINGS = ("log", "linear")


class InputMode(nn.Module):
    """A network's ``fusion`` where it has no fusion layer of its own (an exported model file, a
    prior's global alignment): what :func:`fusion_depth.models.inference.predict_depth` and the
    test stage ask of it, the mode recorded and whether the sparse map is fed."""

    def __init__(self, mode: str, uses_sparse: bool) -> None:
        super().__init__()
        self.mode, self.uses_sparse = mode, uses_sparse


class InputFusion(nn.Module):
    """Turns (image in [0, 1], sparse depth in metres) into the 3-channel encoder input.

    The sparse map enters as an image-like channel ``s`` in [0, 1], 0 meaning "no return", and
    is normalised with the image's statistics, as the paper fuses the radar image with the RGB
    image before the network sees either. ``sparse_encoding="log"`` (default) maps a return at
    depth ``d`` to ``log(d / min_depth) / log(max_depth / min_depth)`` (at least 1/256, so a return
    never reads as "none"): a 5 m and a 60 m return are both clearly visible. ``"linear"``,
    ``d / max_depth``, makes near returns almost vanish (5 m of 80 m is 0.06).

    - ``rgb``: the ImageNet-normalised image; the sparse map is ignored.
    - ``add``: ``s`` added to every colour channel, then ImageNet normalisation.
    - ``concat``: the normalised image and ``s`` stacked to 4 channels, then a learned 1×1 conv
      to 3 channels so the pretrained encoder's first layer still fits. The conv starts as
      ``add`` (identity on RGB, ``1 / std`` on ``s``): the image passes through untouched where
      there is no return, and the returns reach the encoder from the first step instead of
      waiting for a zero-initialised weight to grow (with Adam at 1e-4 it barely moves in a
      short run).

    A depth prior is not mixed in here: it has its own branch
    (:class:`~fusion_depth.models.prior_branch.PriorBranch`).
    """

    def __init__(
        self,
        mode: str = "rgb",
        max_depth: float = 80.0,
        min_depth: float = 0.5,
        sparse_encoding: str = "log",
        mean: Sequence[float] = (0.485, 0.456, 0.406),
        std: Sequence[float] = (0.229, 0.224, 0.225),
    ) -> None:
        super().__init__()
        check_choice(mode, FUSION_MODES, "mode", owner=InputFusion)
        # min_depth < max_depth: the network that holds this checks its range (DepthModel)
        if sparse_encoding not in SPARSE_ENCODINGS:
            raise ValueError(
                f"sparse_encoding={sparse_encoding!r}: expected one of {list(SPARSE_ENCODINGS)}"
            )
        self.mode = mode
        self.max_depth, self.min_depth = float(max_depth), float(min_depth)
        self.sparse_encoding = sparse_encoding
        self.register_buffer("mean", torch.tensor(mean).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(std).view(1, 3, 1, 1), persistent=False)
        if mode == "concat":
            self.mix = self._additive_mix()

    def _additive_mix(self) -> nn.Conv2d:
        """A 1×1 conv from 3 channels and one more to 3 that starts as ``add``: identity on the
        3, ``1 / std`` on the fourth (added to every channel before normalisation)."""
        mix = nn.Conv2d(4, 3, kernel_size=1)
        with torch.no_grad():
            mix.weight.zero_()
            mix.weight[:, :3, 0, 0] = torch.eye(3)
            mix.weight[:, 3, 0, 0] = 1.0 / self.std.view(3)
            mix.bias.zero_()
        return mix

    def encode_sparse(self, sparse: torch.Tensor) -> torch.Tensor:
        """Sparse depth in metres (0 = no return) → the [0, 1] channel described above."""
        if self.sparse_encoding == "linear":
            return (sparse / self.max_depth).clamp(0.0, 1.0)
        scale = torch.log(torch.tensor(self.max_depth / self.min_depth))
        code = (torch.log(sparse.clamp_min(1e-6) / self.min_depth) / scale).clamp(1 / 256, 1.0)
        return torch.where(sparse > 0, code, torch.zeros_like(code))

    @property
    def uses_sparse(self) -> bool:
        return self.mode != "rgb"

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        if self.mode == "rgb":
            return (image - self.mean) / self.std
        if sparse is None:
            raise ValueError(f"fusion mode {self.mode!r} needs the sparse depth map")
        s = self.encode_sparse(sparse)
        if self.mode == "add":
            return (image + s - self.mean) / self.std
        return self.mix(torch.cat([(image - self.mean) / self.std, s], dim=1))


# What a network's fusion arguments accept (fusion_depth.utils.schema).
ARGUMENT_RULES: Schema = {
    "fusion": one_of(*FUSION_MODES),
    "sparse_encoding": one_of(*SPARSE_ENCODINGS),
}
