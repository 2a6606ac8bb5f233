"""Colourised depth panels for dashboards and files (no plotting library needed)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

# Anchor colours of the Turbo colour map; near (high inverse depth) is red, far is dark blue.
_TURBO_ANCHORS = np.array(
    [
        [0.19, 0.07, 0.23],
        [0.27, 0.51, 0.96],
        [0.11, 0.90, 0.71],
        [0.64, 0.99, 0.24],
        [0.98, 0.73, 0.22],
        [0.89, 0.27, 0.05],
        [0.48, 0.02, 0.01],
    ],
    dtype=np.float32,
)


def colorize_depth(depth: np.ndarray, min_depth: float, max_depth: float) -> np.ndarray:
    """Depth (H, W) in metres → uint8 RGB (H, W, 3); inverse-depth scaled, 0 (invalid) black."""
    depth = np.asarray(depth, dtype=np.float32)
    valid = depth > 0
    inv = 1.0 / np.clip(depth, min_depth, max_depth)
    t = (inv - 1.0 / max_depth) / (1.0 / min_depth - 1.0 / max_depth)
    pos = np.clip(t, 0, 1) * (len(_TURBO_ANCHORS) - 1)
    lo = np.floor(pos).astype(int).clip(0, len(_TURBO_ANCHORS) - 2)
    frac = (pos - lo)[..., None]
    rgb = _TURBO_ANCHORS[lo] * (1 - frac) + _TURBO_ANCHORS[lo + 1] * frac
    rgb[~valid] = 0
    return (rgb * 255).round().astype(np.uint8)


def depth_panel(
    image: torch.Tensor,
    sparse: torch.Tensor,
    pred: torch.Tensor,
    target: torch.Tensor | None,
    min_depth: float,
    max_depth: float,
) -> np.ndarray:
    """One row ``image | sparse input | prediction | ground truth`` as uint8 (H, k·W, 3).

    Sparse points are dilated to 3×3 so they stay visible; the prediction is resized to the
    image with nearest neighbour so no colour is invented.
    """
    height, width = image.shape[-2:]
    rgb = (image.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255).astype(np.uint8)
    sparse = sparse.detach().float().view(1, 1, *sparse.shape[-2:])
    # Max-pool over 1/depth so the nearer return wins where dilated points overlap.
    inv = torch.where(sparse > 0, 1.0 / sparse.clamp_min(1e-6), torch.zeros_like(sparse))
    inv = F.max_pool2d(inv, 3, stride=1, padding=1)
    dilated = torch.where(inv > 0, 1.0 / inv.clamp_min(1e-12), torch.zeros_like(inv))[0, 0]
    sparse_rgb = colorize_depth(dilated.cpu().numpy(), min_depth, max_depth)
    sparse_rgb = np.where((dilated.cpu().numpy() > 0)[..., None], sparse_rgb, rgb // 3)
    pred = F.interpolate(
        pred.detach().float().view(1, 1, *pred.shape[-2:]), size=(height, width), mode="nearest"
    )[0, 0]
    tiles = [rgb, sparse_rgb, colorize_depth(pred.cpu().numpy(), min_depth, max_depth)]
    if target is not None:
        tiles.append(
            colorize_depth(
                target.detach().float().view(height, width).cpu().numpy(), min_depth, max_depth
            )
        )
    return np.concatenate(tiles, axis=1)
