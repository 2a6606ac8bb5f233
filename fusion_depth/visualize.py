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


def _inverse_position(depth: float, min_depth: float, max_depth: float) -> float:
    """Where ``depth`` sits on ``colorize_depth``'s scale: 0 at max_depth, 1 at min_depth."""
    return (1.0 / depth - 1.0 / max_depth) / (1.0 / min_depth - 1.0 / max_depth)


def colorbar_ticks(
    height: int, min_depth: float, max_depth: float, min_gap: float
) -> list[tuple[float, float]]:
    """``(depth in metres, row)`` of the labelled ticks of a colour bar ``height`` rows tall.

    Far (max_depth) is row 0, near (min_depth) the last row, as in ``depth_colorbar``. The ends
    are always labelled; 1-2-5 values in between are added, nearest first (the inverse scale
    spreads them out there), wherever they stay ``min_gap`` rows from every other label.
    """

    def row(depth: float) -> float:
        return _inverse_position(depth, min_depth, max_depth) * (height - 1)

    def label_row(depth: float) -> float:  # labels at the ends are pushed inside the bar
        return float(np.clip(row(depth), min_gap / 2, height - 1 - min_gap / 2))

    ticks = [(min_depth, row(min_depth))]
    if abs(label_row(min_depth) - label_row(max_depth)) >= min_gap:
        ticks.append((max_depth, row(max_depth)))
    exponent = int(np.floor(np.log10(min_depth)))
    candidates = []
    while 10.0**exponent <= max_depth:
        candidates += [m * 10.0**exponent for m in (1, 2, 5)]
        exponent += 1
    for depth in sorted(candidates):
        depth = float(f"{depth:.6g}")  # 0.1 * 2 → 0.2, not 0.20000000000000001
        if min_depth < depth < max_depth and all(
            abs(label_row(depth) - label_row(d)) >= min_gap for d, _ in ticks
        ):
            ticks.append((depth, row(depth)))
    return sorted(ticks, key=lambda tick: tick[1])


def depth_colorbar(height: int, min_depth: float, max_depth: float) -> np.ndarray:
    """A vertical colour bar in metres for ``colorize_depth``'s scale, uint8 (height, w, 3).

    Every row of the bar is ``colorize_depth`` of the depth it stands for (far at the top,
    near at the bottom), so colours match the panels exactly; ticks are labelled in metres
    (white on black, rendered with matplotlib's Agg canvas, no pyplot state). The width depends
    only on ``height`` and the labels, so a caller can predict it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.transforms import IdentityTransform

    if height < 2:
        raise ValueError(f"colour bar height={height}: expected at least 2 rows")
    font = int(np.clip(height / 12, 7, 14))  # pixels (the figure's 72 dpi makes points pixels)
    strip, tick_len, pad = max(8, height // 24), 3, 2
    min_gap = font + 2
    ticks = colorbar_ticks(height, min_depth, max_depth, min_gap)
    labels = [f"{depth:g} m" for depth, _ in ticks]
    text_width = int(np.ceil(0.65 * font * max(len(label) for label in labels))) + pad
    width = pad + strip + tick_len + pad + text_width

    rows = np.arange(height, dtype=np.float64) / (height - 1)  # 0 = far … 1 = near
    inverse = 1.0 / max_depth + rows * (1.0 / min_depth - 1.0 / max_depth)
    depth = np.repeat((1.0 / inverse).astype(np.float32)[:, None], strip, axis=1)
    bar = np.zeros((height, width, 3), dtype=np.uint8)
    bar[:, pad : pad + strip] = colorize_depth(depth, min_depth, max_depth)
    for _, row in ticks:
        bar[int(round(row)), pad + strip : pad + strip + tick_len] = 255

    text_x = pad + strip + tick_len + pad
    figure = Figure(figsize=((width - text_x) / 72, height / 72), dpi=72, facecolor="black")
    canvas = FigureCanvasAgg(figure)
    for (_, row), label in zip(ticks, labels, strict=True):
        # Display coordinates count from the bottom; keep the label's half-height inside.
        y = float(np.clip(height - 1 - row, min_gap / 2, height - 1 - min_gap / 2))
        figure.text(
            1,
            y,
            label,
            color="white",
            fontsize=font,
            va="center",
            ha="left",
            transform=IdentityTransform(),
        )
    canvas.draw()
    text = np.asarray(canvas.buffer_rgba())[..., :3][:height, : width - text_x]
    bar[: text.shape[0], text_x : text_x + text.shape[1]] = text
    return bar


# Rows a colour bar needs for its two end labels (7 px font) to fit without overlapping.
MIN_COLORBAR_HEIGHT = 32


def with_colorbar(panel: np.ndarray, min_depth: float, max_depth: float) -> np.ndarray:
    """``panel`` (uint8 (H, W, 3), e.g. ``depth_panel``'s) with ``depth_colorbar`` on its right.

    A panel shorter than :data:`MIN_COLORBAR_HEIGHT` rows (a tiny image, down to 1 x 1) is first
    padded with black rows at the bottom to that height, so the bar and its labels stay legible;
    the result is then that many rows tall.
    """
    if panel.shape[0] < MIN_COLORBAR_HEIGHT:
        rows = MIN_COLORBAR_HEIGHT - panel.shape[0]
        panel = np.pad(panel, ((0, rows), (0, 0), (0, 0)))
    return np.concatenate([panel, depth_colorbar(panel.shape[0], min_depth, max_depth)], axis=1)
