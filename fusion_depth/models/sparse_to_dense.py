"""``model=sparse_to_dense``: Ma & Karaman, "Sparse-to-Dense: Depth Prediction from Sparse Depth
Samples and a Single Image", ICRA 2018 (arXiv:1709.07492), as its authors' code builds it
(github.com/fangchangma/sparse-to-dense.pytorch, ``models.py``).

The network (the paper's Sec. III-A, Fig. 2):

1. a ResNet-18 or -50 encoder (timm) without its pooling and classifier, whose first convolution
   takes the RGB image (``fusion=rgb``) or RGB plus the sparse depth channel (``fusion=concat``,
   the paper's RGBd input);
2. a 1×1 convolution with batch normalisation that halves the channels at the bottleneck;
3. four up-projection blocks (Laina et al., 3DV 2016, Sec. 3.2: :class:`UpProjection`), each
   doubling the resolution and halving the channels;
4. a 3×3 convolution to one channel and bilinear upsampling to the input size.

It predicts depth in metres (output space ``depth``), trained with an L1 loss on depth (Sec.
III-B: "we use the L1 loss"); ``loss=l1_only`` is that loss, and ``sweeps/methods.yaml`` uses it.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from fusion_depth.models._registry import Recipe, check_model_takes, register_model
from fusion_depth.models.base import DepthModel
from fusion_depth.models.encoder import create_timm_model

# The encoders the paper evaluates (Sec. IV-A: ResNet-50; Sec. V-A also ResNet-18).
BACKBONES = ("resnet18", "resnet50")
FUSIONS = ("rgb", "concat")  # RGB, RGBd; no addition variant in the paper


def _kaiming_fan_out(module: nn.Module) -> None:
    """The reference code's ``weights_init``: convolutions ~ N(0, 2 / (k·k·out)), batch norm
    weight 1 and bias 0."""
    for m in module.modules():
        if isinstance(m, nn.Conv2d):
            n = m.kernel_size[0] * m.kernel_size[1] * m.out_channels
            nn.init.normal_(m.weight, 0.0, math.sqrt(2.0 / n))
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.BatchNorm2d):
            nn.init.ones_(m.weight)
            nn.init.zeros_(m.bias)


class Unpool(nn.Module):
    """2× unpooling (Laina et al. 2016, Fig. 4): each value goes to the top-left of its 2×2
    block, the other three are zero.

    Shape:
        - input: (B, C, H, W); output: (B, C, 2H, 2W).
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        weight = torch.zeros(channels, 1, 2, 2)
        weight[:, :, 0, 0] = 1.0
        self.register_buffer("weight", weight, persistent=False)
        self.channels = channels

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.conv_transpose2d(x, self.weight.to(x.dtype), stride=2, groups=self.channels)


class UpProjection(nn.Module):
    """Laina et al.'s up-projection (3DV 2016, Sec. 3.2, Fig. 4), as sparse-to-dense uses it.

    After :class:`Unpool`, an upper branch (5×5 conv → BN → ReLU → 3×3 conv → BN) and a
    projection branch (5×5 conv → BN) are summed and passed through a ReLU. Convolutions have no
    bias (batch norm follows each).

    Args:
        in_channels: C; the block outputs C // 2 channels.

    Shape:
        - input: (B, C, H, W); output: (B, C // 2, 2H, 2W).
    """

    def __init__(self, in_channels: int) -> None:
        super().__init__()
        out = in_channels // 2
        self.unpool = Unpool(in_channels)
        self.upper = nn.Sequential(
            nn.Conv2d(in_channels, out, 5, padding=2, bias=False),
            nn.BatchNorm2d(out),
            nn.ReLU(),
            nn.Conv2d(out, out, 3, padding=1, bias=False),
            nn.BatchNorm2d(out),
        )
        self.projection = nn.Sequential(
            nn.Conv2d(in_channels, out, 5, padding=2, bias=False),
            nn.BatchNorm2d(out),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.unpool(x)
        return F.relu(self.upper(x) + self.projection(x))


class RGBdInput(nn.Module):
    """The network's input: the RGB image in [0, 1] (``rgb``), or with the sparse depth in metres
    as a fourth channel, 0 where there is no sample (``concat``: the paper's RGBd). As in the
    reference code's loaders, neither is normalised further."""

    def __init__(self, mode: str) -> None:
        super().__init__()
        self.mode = mode  # one of FUSIONS: create_model checks it against the registration

    @property
    def uses_sparse(self) -> bool:
        return self.mode != "rgb"

    @property
    def channels(self) -> int:
        return 4 if self.uses_sparse else 3

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        if not self.uses_sparse:
            return image
        if sparse is None:
            raise ValueError(f"fusion mode {self.mode!r} needs the sparse depth map")
        return torch.cat([image, sparse.to(image.dtype)], dim=1)


# Its authors' recipe (fangchangma/sparse-to-dense.pytorch at 10efc6d): ResNet-18, L1 on metres,
# SGD 0.01 with momentum 0.9 and weight decay 1e-4 (main.py lines 127-128, utils.py lines 45-50),
# lr ÷ 10 every 5 epochs (utils.py lines 80-84, adjust_learning_rate), batch 8 and 15 epochs
# (utils.py lines 40-44).
@register_model(
    "sparse_to_dense",
    label="Sparse-to-Dense",
    paper="Ma & Karaman, ICRA 2018",
    fusions=FUSIONS,
    backbones=("resnet18", "resnet50"),
    recipe=Recipe(
        backbone="resnet18",
        loss="l1_only",
        optimizer="sgd",
        optimizer_args={"lr": 1.0e-2, "momentum": 0.9, "weight_decay": 1.0e-4},
        schedule="step",
        schedule_args={"step_size": 5, "gamma": 0.1},
        batch_size=8,
        max_epochs=15,
        # dataloaders/kitti_dataloader.py and dataloader.py: rotation ±5°, zoom 1-1.5 (depth ÷
        # zoom), nearest-neighbour resampling, flip, ColorJitter(0.4, 0.4, 0.4) on every frame;
        # its KITTI crop: conf/experiment/kitti_sparse_to_dense.yaml
        augment={
            "rotation": 5.0,
            "scale": [1.0, 1.5],
            "resample": "nearest",
            "flip_p": 0.5,
            "color_p": 1.0,
            "brightness": [0.6, 1.4],
            "contrast": [0.6, 1.4],
            "saturation": [0.6, 1.4],
        },
    ),
)
class SparseToDense(DepthModel):
    """Ma & Karaman 2018's network (module docstring): depth in metres at the input resolution.

    Args:
        backbone: ``resnet18`` or ``resnet50`` (timm).
        fusion: ``rgb`` or ``concat`` (RGBd).
        pretrained: ImageNet weights for the encoder, as for ``model=densedepth``. With
            ``concat`` the first convolution is new and randomly initialised, as in the
            reference code (``in_channels != 3``).
        weights: a local file of those weights, as for ``model=densedepth``.
        min_depth: see :class:`~fusion_depth.models.base.DepthModel`.
        max_depth: see :class:`~fusion_depth.models.base.DepthModel`.
        depth_scale: see :class:`~fusion_depth.models.base.DepthModel`.

    Shape:
        - image: (B, 3, H, W), sparse: (B, 1, H, W); output: (B, 1, H, W) metres.

    Raises:
        ValueError: a backbone or fusion mode the paper does not define.
    """

    output_space = "depth"

    def __init__(
        self,
        backbone: str = "resnet18",
        fusion: str = "concat",
        pretrained: bool = False,
        weights: str | None = None,
        min_depth: float = 0.5,
        max_depth: float = 80.0,
        depth_scale: float = 10.0,
    ) -> None:
        super().__init__(min_depth, max_depth, depth_scale)
        check_model_takes("sparse_to_dense", fusion, backbone)  # also when built directly
        self.fusion = RGBdInput(fusion)
        resnet = create_timm_model(backbone, pretrained, weights)
        if self.fusion.channels != 3:
            resnet.conv1 = nn.Conv2d(self.fusion.channels, 64, 7, stride=2, padding=3, bias=False)
            resnet.bn1 = nn.BatchNorm2d(64)
            _kaiming_fan_out(resnet.conv1)
            _kaiming_fan_out(resnet.bn1)
        self.encoder = nn.Sequential(
            resnet.conv1,
            resnet.bn1,
            resnet.act1,
            resnet.maxpool,
            resnet.layer1,
            resnet.layer2,
            resnet.layer3,
            resnet.layer4,
        )
        channels = resnet.num_features  # 512 (ResNet-18) or 2048 (ResNet-50) at stride 32
        self.bottleneck = nn.Sequential(
            nn.Conv2d(channels, channels // 2, 1, bias=False), nn.BatchNorm2d(channels // 2)
        )
        self.decoder = nn.Sequential(*(UpProjection(channels // 2**i) for i in range(1, 5)))
        self.head = nn.Conv2d(channels // 32, 1, 3, padding=1, bias=False)
        for part in (self.bottleneck, self.decoder, self.head):
            _kaiming_fan_out(part)

    def forward(self, image: torch.Tensor, sparse: torch.Tensor | None = None) -> torch.Tensor:
        self.check_input_size(image)
        x = self.decoder(self.bottleneck(self.encoder(self.fusion(image, sparse))))
        x = F.interpolate(self.head(x), size=image.shape[-2:], mode="bilinear", align_corners=True)
        return x.float()  # fp32 out under autocast too, as DepthNet
