"""Colourised depth panels for dashboards and files: the tiles are coloured here, and
matplotlib's Agg canvas draws only the labels of colour bars and figures."""

from __future__ import annotations

import os
import zipfile
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from fusion_depth.data.depth_io import write_rgb_png
from fusion_depth.utils.atomic import write_atomic

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
    """Depth (H, W) in metres → uint8 RGB (H, W, 3); inverse-depth scaled, 0 and non-finite
    values (no depth) black."""
    with np.errstate(over="ignore"):  # a float64 beyond float32 is infinite: no depth
        depth = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    inv = 1.0 / np.clip(np.where(valid, depth, max_depth), min_depth, max_depth)
    t = (inv - 1.0 / max_depth) / (1.0 / min_depth - 1.0 / max_depth)
    pos = np.clip(t, 0, 1) * (len(_TURBO_ANCHORS) - 1)
    lo = np.floor(pos).astype(int).clip(0, len(_TURBO_ANCHORS) - 2)
    frac = (pos - lo)[..., None]
    rgb = _TURBO_ANCHORS[lo] * (1 - frac) + _TURBO_ANCHORS[lo + 1] * frac
    rgb[~valid] = 0
    return (rgb * 255).round().astype(np.uint8)


def _image_rgb(image: torch.Tensor) -> np.ndarray:
    """(3, H, W) RGB in [0, 1] → uint8 (H, W, 3)."""
    rgb = image.detach().float().clamp(0, 1).permute(1, 2, 0).cpu().numpy() * 255
    return rgb.round().astype(np.uint8)  # rounded: an image read back from uint8 is unchanged


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
    rgb = _image_rgb(image)
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


def _text_image(
    labels: Sequence[tuple[float, float, str]], height: int, width: int, font: int
) -> np.ndarray:
    """White ``(x, y, text)`` labels on black, uint8 (height, width, 3); ``x`` is the left edge
    and ``y`` the vertical centre, in pixels from the top left. Drawn with matplotlib's Agg
    canvas (no pyplot state); the figure's 72 dpi makes font points pixels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.transforms import IdentityTransform

    figure = Figure(figsize=(width / 72, height / 72), dpi=72, facecolor="black")
    canvas = FigureCanvasAgg(figure)
    for x, y, text in labels:
        # Display coordinates count from the bottom; keep the label's half-height inside.
        row = float(np.clip(height - 1 - y, (font + 2) / 2, height - 1 - (font + 2) / 2))
        figure.text(
            x,
            row,
            text,
            color="white",
            fontsize=font,
            va="center",
            ha="left",
            transform=IdentityTransform(),
            parse_math=False,  # a label is text: "$x^$" is drawn, not parsed as mathtext
        )
    canvas.draw()
    text = np.asarray(canvas.buffer_rgba())[..., :3][:height, :width]
    out = np.zeros((height, width, 3), dtype=np.uint8)
    out[: text.shape[0], : text.shape[1]] = text
    return out


def _text_width(text: str, font: int) -> int:
    """Pixels a label of ``font`` pixels needs (a safe over-estimate for the default font)."""
    return int(np.ceil(0.65 * font * len(text)))


def _colorbar_font(height: int) -> int:
    """Label size, in pixels, of a colour bar ``height`` rows tall."""
    return int(np.clip(height / 12, 7, 14))


def _labelled_bar(colours: np.ndarray, ticks: Sequence[tuple[float, str]]) -> np.ndarray:
    """A vertical bar of ``colours`` (uint8 (height, 3), row 0 at the top) with white tick marks
    and labels at ``(row, label)``, uint8 (height, w, 3). The width depends only on the height
    and the labels."""
    height = len(colours)
    font = _colorbar_font(height)
    strip, tick_len, pad = max(8, height // 24), 3, 2
    text_width = max(_text_width(label, font) for _, label in ticks) + pad
    width = pad + strip + tick_len + pad + text_width
    bar = np.zeros((height, width, 3), dtype=np.uint8)
    bar[:, pad : pad + strip] = colours[:, None, :]
    for row, _ in ticks:
        bar[int(round(row)), pad + strip : pad + strip + tick_len] = 255
    text_x = pad + strip + tick_len + pad
    bar[:, text_x:] = _text_image(
        [(1, row, label) for row, label in ticks], height, width - text_x, font
    )
    return bar


def depth_colorbar(height: int, min_depth: float, max_depth: float) -> np.ndarray:
    """A vertical colour bar in metres for ``colorize_depth``'s scale, uint8 (height, w, 3).

    Every row of the bar is ``colorize_depth`` of the depth it stands for (far at the top,
    near at the bottom), so colours match the panels exactly; ticks are labelled in metres
    (white on black, rendered with matplotlib's Agg canvas, no pyplot state). The width depends
    only on ``height`` and the labels, so a caller can predict it.

    Raises:
        ValueError: ``height`` < 2.
    """
    if height < 2:
        raise ValueError(f"colour bar height={height}: expected at least 2 rows")
    ticks = colorbar_ticks(height, min_depth, max_depth, _colorbar_font(height) + 2)
    rows = np.arange(height, dtype=np.float64) / (height - 1)  # 0 = far … 1 = near
    inverse = 1.0 / max_depth + rows * (1.0 / min_depth - 1.0 / max_depth)
    colours = colorize_depth((1.0 / inverse).astype(np.float32), min_depth, max_depth)
    return _labelled_bar(colours, [(row, f"{depth:g} m") for depth, row in ticks])


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


# The columns of panel_figure, left to right (the error column only where every row has GT).
PANEL_COLUMNS = ("image", "sparse input", "prediction", "ground truth", "|error|")
PANEL_CAPTION = " | ".join(PANEL_COLUMNS) + " (depth and error colour bars in metres)"
ERROR_COLORMAP = "magma"  # matplotlib's; perceptually uniform, dark = small error


@dataclass(frozen=True)
class PanelFrame:
    """One row of :func:`panel_figure` (tensors on any device, any float dtype).

    Attributes:
        image: (3, H, W) RGB in [0, 1].
        sparse: (1, H, W) or (H, W) sparse input in metres, 0 = no return (zeros for RGB-only).
        prediction: (h, w) predicted depth in metres at any resolution (resized to H × W with
            nearest neighbour).
        target: (H, W) ground-truth depth in metres, 0 = none; None where it is not known.
        label: what the row shows (a condition, a frame name), written at its left.
    """

    image: torch.Tensor
    sparse: torch.Tensor
    prediction: torch.Tensor
    target: torch.Tensor | None
    label: str = ""


def _one_two_five_below(value: float) -> float:
    """The largest 1-2-5 value (…, 0.5, 1, 2, 5, 10, …) that is ≤ ``value`` > 0."""
    exponent = int(np.floor(np.log10(value)))
    for step in (5, 2, 1):
        candidate = float(f"{step * 10.0**exponent:.6g}")
        if candidate <= value:
            return candidate
    return float(f"{0.5 * 10.0**exponent:.6g}")


def display_near(targets: Sequence[np.ndarray], min_depth: float, max_depth: float) -> float:
    """Near end of a figure's depth colour scale, metres: the 1st percentile of the valid
    ground-truth depths in ``targets`` rounded down to a 1-2-5 value, within
    [``min_depth``, ``max_depth`` / 2]. On an inverse scale from ``min_depth`` (0.5 m) half
    the colours go to depths below 1 m; starting the scale at the nearest depth the frames
    actually show gives their depths the colours (``min_depth`` without ground truth)."""
    values = np.concatenate([np.ravel(t) for t in targets]) if targets else np.zeros(0)
    values = values[np.isfinite(values) & (values > 0)]
    if not values.size:
        return min_depth
    near = _one_two_five_below(max(float(np.quantile(values, 0.01)), min_depth))
    return float(np.clip(near, min_depth, max_depth / 2))


# Tiles shorter than this are enlarged by a whole factor (nearest neighbour) in panel_figure, so
# the built-in dataset's 64-row frames and their labels stay legible.
MIN_TILE_HEIGHT = 128


def _one_two_five_above(value: float) -> float:
    """The smallest 1-2-5 value (…, 0.5, 1, 2, 5, 10, …) that is ≥ ``value`` > 0."""
    exponent = int(np.floor(np.log10(value)))
    for step in (1, 2, 5, 10):
        candidate = float(f"{step * 10.0**exponent:.6g}")
        if candidate >= value:
            return candidate
    return 10.0 ** (exponent + 1)


def error_scale(errors: Sequence[np.ndarray], quantile: float = 0.95) -> float:
    """Top of the shared error colour scale, metres: the ``quantile`` of every absolute error in
    ``errors`` (1-D arrays of valid pixels) rounded up to a 1-2-5 value, at least 0.1 m, so
    that a few outliers do not wash out the rest (larger errors take the top colour)."""
    values = np.concatenate([np.ravel(e) for e in errors]) if errors else np.zeros(0)
    top = float(np.quantile(values, quantile)) if values.size else 0.0
    return _one_two_five_above(max(top, 0.1))


def _frame_error(frame: PanelFrame) -> tuple[np.ndarray, np.ndarray]:
    """(|prediction − target| in metres, valid mask), both (H, W), at the image's size."""
    assert frame.target is not None
    height, width = frame.image.shape[-2:]
    target = frame.target.detach().float().reshape(height, width).cpu()
    pred = frame.prediction.detach().float()
    pred = F.interpolate(pred.reshape(1, 1, *pred.shape[-2:]).cpu(), size=(height, width))[0, 0]
    difference = pred - target
    valid = torch.isfinite(target) & (target > 0) & torch.isfinite(difference)
    error = torch.where(valid, difference.abs(), torch.zeros_like(target))
    return error.numpy(), valid.numpy()


def _error_colours(values: np.ndarray) -> np.ndarray:
    """uint8 RGB of ERROR_COLORMAP at ``values`` in [0, 1] (any shape + (3,))."""
    from matplotlib import colormaps

    table = (colormaps[ERROR_COLORMAP](np.linspace(0, 1, 256))[:, :3] * 255).round()
    return table.astype(np.uint8)[np.clip(np.round(values * 255), 0, 255).astype(int)]


def _error_tile(
    frame: PanelFrame, error: np.ndarray, valid: np.ndarray, max_error: float
) -> np.ndarray:
    """``frame``'s error tile from its :func:`_frame_error` (``error``, ``valid``)."""
    # Where there is no ground truth the tile shows the dimmed image, as the sparse tile does.
    colours = _error_colours(error / max_error)
    return np.where(valid[..., None], colours, _image_rgb(frame.image) // 3)


def error_colorbar(height: int, max_error: float) -> np.ndarray:
    """A vertical colour bar for the error tiles of :func:`panel_figure`: 0 m at the bottom,
    ``max_error`` metres (and above) at the top, labelled in metres; uint8 (height, w, 3)."""
    if height < 2:
        raise ValueError(f"colour bar height={height}: expected at least 2 rows")
    colours = _error_colours(np.linspace(1, 0, height))
    min_gap = _colorbar_font(height) + 2
    ticks: list[tuple[float, str]] = [(height - 1, "0 m"), (0, f"≥{max_error:g} m")]
    for fraction in (0.25, 0.5, 0.75):
        row = (1 - fraction) * (height - 1)
        if all(abs(row - r) >= min_gap for r, _ in ticks):
            ticks.append((row, f"{fraction * max_error:g} m"))
    return _labelled_bar(colours, sorted(ticks))


# The depths a colour scale may span, metres (beyond them 1/depth under- or overflows).
DEPTH_RANGE_LIMITS = (1e-6, 1e6)


def check_depth_range(min_depth: float, max_depth: float, where: str) -> None:
    """Refuse a colour scale from ``min_depth`` to ``max_depth`` (metres) that cannot be drawn:
    expected 0 < min_depth < max_depth, both finite, within :data:`DEPTH_RANGE_LIMITS`.

    Raises:
        ValueError: in one line starting with ``where``.
    """
    low, high = DEPTH_RANGE_LIMITS
    try:
        ok = low <= float(min_depth) < float(max_depth) <= high  # False for NaN
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(
            f"{where}: depth range [{min_depth}, {max_depth}]: expected 0 < min_depth < "
            f"max_depth, finite metres within [{low:g}, {high:g}]"
        )


def panel_figure(frames: Sequence[PanelFrame], min_depth: float, max_depth: float) -> np.ndarray:
    """Rows of ``image | sparse input | prediction | ground truth | |error|`` with a header,
    each row's label at its left, and labelled colour bars in metres, as uint8 (H', W', 3).

    The depth tiles share one scale (``colorize_depth``'s, inverse depth from
    :func:`display_near` of the ground truth, at least ``min_depth``, to ``max_depth``) shown
    by the depth bar; the error tiles (absolute error where the ground
    truth is known, the dimmed image elsewhere) share a linear scale from 0 to
    :func:`error_scale` of all rows, shown by the second bar. Without ground truth in every row
    the ground-truth and error columns are left out. Every frame must have the same image size.

    Raises:
        ValueError: no frames, frames of different sizes or of no pixels, or a depth range that
            is not :func:`check_depth_range`'s.
    """
    check_depth_range(min_depth, max_depth, "panel_figure")
    if not frames:
        raise ValueError("panel_figure: no frames to draw")
    sizes = {tuple(f.image.shape[-2:]) for f in frames}
    if len(sizes) != 1:
        raise ValueError(f"panel_figure: frames of different sizes {sorted(sizes)}")
    if min(next(iter(sizes))) < 1 or any(min(f.prediction.shape[-2:]) < 1 for f in frames):
        raise ValueError("panel_figure: frames of no pixels; expected at least 1 x 1")
    with_error = all(f.target is not None for f in frames)
    max_error = 0.0
    if with_error:
        targets = [f.target.detach().float().cpu().numpy() for f in frames if f.target is not None]
        min_depth = display_near(targets, min_depth, max_depth)
        frame_errors = [_frame_error(frame) for frame in frames]  # once per frame
        max_error = error_scale([error[valid] for error, valid in frame_errors])
    rows = []
    for i, frame in enumerate(frames):
        tiles = [
            depth_panel(
                frame.image,
                frame.sparse,
                frame.prediction,
                frame.target if with_error else None,
                min_depth,
                max_depth,
            )
        ]
        if with_error:
            tiles.append(_error_tile(frame, *frame_errors[i], max_error))
        rows.append(np.concatenate(tiles, axis=1))
    tile_height, tile_width = next(iter(sizes))
    scale = -(-MIN_TILE_HEIGHT // tile_height)  # ceil; 1 for tiles at least that tall
    tile_height, tile_width = tile_height * scale, tile_width * scale
    body = np.concatenate(rows, axis=0).repeat(scale, axis=0).repeat(scale, axis=1)
    if body.shape[0] < MIN_COLORBAR_HEIGHT:
        body = np.pad(body, ((0, MIN_COLORBAR_HEIGHT - body.shape[0]), (0, 0), (0, 0)))
    bars = [depth_colorbar(body.shape[0], min_depth, max_depth)]
    if with_error:
        bars.append(error_colorbar(body.shape[0], max_error))
    font = int(np.clip(tile_height / 6, 8, 14))
    labels = [f.label for f in frames]
    label_width = max((_text_width(t, font) for t in labels if t), default=0)
    left = np.zeros((body.shape[0], 0, 3), np.uint8)  # no row labels: no column for them
    if label_width:
        row_labels = [(2, (i + 0.5) * tile_height, t) for i, t in enumerate(labels) if t]
        left = _text_image(row_labels, body.shape[0], label_width + 4, font)
    figure = np.concatenate([left, body, *bars], axis=1)
    columns = PANEL_COLUMNS if with_error else PANEL_COLUMNS[:3]
    heads = [(left.shape[1] + i * tile_width + 2, c) for i, c in enumerate(columns)]
    x = left.shape[1] + body.shape[1]
    heads.append((x + 2, "depth"))
    if with_error:
        heads.append((x + bars[0].shape[1] + 2, "|error|"))
    header_height = font + 8
    header = _text_image(
        [(hx, header_height / 2, text) for hx, text in heads], header_height, figure.shape[1], font
    )
    return np.concatenate([header, figure], axis=0)


def write_panel_figure(
    path: str | os.PathLike, frames: Sequence[PanelFrame], min_depth: float, max_depth: float
) -> Path:
    """:func:`panel_figure` of ``frames`` written as an RGB PNG at ``path`` (atomically: an
    earlier file survives a failure). Returns the path.

    Raises:
        ValueError: as :func:`panel_figure`.
        OSError: writing failed.
    """
    write_rgb_png(path, panel_figure(frames, min_depth, max_depth))
    return Path(path)


# The arrays of a panel-frames file (:func:`write_panel_frames`), each stacked over frames.
_PANEL_ARRAYS = ("image", "sparse", "prediction", "target", "label")


def write_panel_frames(
    path: str | os.PathLike, frames: Sequence[PanelFrame], min_depth: float, max_depth: float
) -> Path:
    """``frames`` and their depth range as a compressed ``.npz`` of plain arrays (no pickle),
    written atomically: the record from which :func:`read_panel_frames` and
    :func:`panel_figure` draw the same figure again, without the checkpoint.

    Arrays: ``image`` uint8 (N, 3, H, W); ``sparse``, ``target`` float32 (N, H, W) in metres
    (``target`` all zero where a frame has none); ``prediction`` float32 (N, h, w);
    ``label`` str (N,); ``depth_range`` float64 (2,) = (min_depth, max_depth).

    Raises:
        ValueError: no frames, or frames of different sizes.
        OSError: writing failed.
    """
    if not frames:
        raise ValueError(f"{path}: no panel frames to write")
    sizes = {(tuple(f.image.shape[-2:]), tuple(f.prediction.shape[-2:])) for f in frames}
    if len(sizes) != 1:
        raise ValueError(f"{path}: panel frames of different sizes {sorted(sizes)}")

    def plain(tensor: torch.Tensor) -> np.ndarray:
        return tensor.detach().float().cpu().numpy()

    height, width = frames[0].image.shape[-2:]
    arrays = {
        "image": np.stack([_image_rgb(f.image).transpose(2, 0, 1) for f in frames]),
        "sparse": np.stack([plain(f.sparse).reshape(height, width) for f in frames]),
        "prediction": np.stack(
            [plain(f.prediction).reshape(f.prediction.shape[-2:]) for f in frames]
        ),
        "target": np.stack(
            [
                plain(f.target).reshape(height, width)
                if f.target is not None
                else np.zeros((height, width), np.float32)
                for f in frames
            ]
        ),
        "label": np.array([f.label for f in frames], dtype=str),
        "depth_range": np.array([min_depth, max_depth], dtype=np.float64),
    }

    def save(tmp: Path) -> None:
        with tmp.open("wb") as f:
            np.savez_compressed(f, **arrays)

    write_atomic(path, save, suffix=".npz")
    return Path(path)


# What a figure drawn from a record (:func:`read_panel_frames`) may cost. A record beyond these
# is refused from its arrays' headers, before any array is read: a few kilobytes of compressed
# zeros can declare gigabytes, and one row of 300,000 pixels is drawn 128 rows tall.
MAX_PANEL_PIXELS = 50_000_000  # five frames of 900x1600 in five columns make about 40 MP
MAX_PANEL_SIDE = 2**15  # pixels, either side
MAX_PANEL_LABEL_CHARS = 120  # a row's label (a condition, a frame's name)
MAX_PREDICTION_SCALE = 4  # a prediction may hold up to this many times its image's pixels
_LARGEST_FONT = 14  # pixels: panel_figure's labels and a colour bar's are at most this size


def _label_width(chars: int, font: int = _LARGEST_FONT) -> int:
    """:func:`_text_width` of a label of ``chars`` characters, without making it."""
    return int(np.ceil(0.65 * font * chars))


def panel_figure_bound(count: int, height: int, width: int, label_chars: int) -> tuple[int, int]:
    """At least the (rows, columns) of :func:`panel_figure` of ``count`` frames of ``height`` x
    ``width`` pixels (``height`` >= 1) whose labels have at most ``label_chars`` characters,
    with every column and both colour bars: what the figure costs, known before any array is
    read."""
    scale = -(-MIN_TILE_HEIGHT // height)  # as panel_figure enlarges short tiles
    body_rows = max(count * height * scale, MIN_COLORBAR_HEIGHT)
    label = _label_width(label_chars) + 4 if label_chars else 0
    # Each bar: pads, its strip, ticks and labels of at most 16 characters ("≥0.000125 m").
    bars = 2 * (max(8, body_rows // 24) + 9 + _label_width(16))
    rows = body_rows + _LARGEST_FONT + 8  # and the header
    return rows, label + len(PANEL_COLUMNS) * width * scale + bars


# The kind of each array of a panel-frames file (numpy's dtype.kind) and its number of axes.
_PANEL_LAYOUT = {
    "image": ("u", 4),
    "sparse": ("f", 3),
    "prediction": ("f", 3),
    "target": ("f", 3),
    "label": ("U", 1),
    "depth_range": ("f", 1),
}
# What reading a damaged or foreign archive raises (RuntimeError: an encrypted member).
_ARCHIVE_ERRORS = (
    ValueError,
    zipfile.BadZipFile,
    zlib.error,
    EOFError,
    NotImplementedError,
    RuntimeError,
)


def _npz_headers(archive: zipfile.ZipFile) -> dict[str, tuple[tuple[int, ...], np.dtype]]:
    """Shape and dtype of each array of :data:`_PANEL_LAYOUT` that ``archive`` (an ``.npz``)
    holds, from the member's ``.npy`` header alone (nothing of the array is read)."""
    readers = {
        (1, 0): np.lib.format.read_array_header_1_0,
        (2, 0): np.lib.format.read_array_header_2_0,
    }
    members = set(archive.namelist())
    headers = {}
    for name in _PANEL_LAYOUT:
        if f"{name}.npy" not in members:
            continue
        with archive.open(f"{name}.npy") as f:
            version = np.lib.format.read_magic(f)
            if version not in readers:
                raise ValueError(f"{name}: .npy format version {version}")
            shape, _, dtype = readers[version](f)
        headers[name] = (tuple(int(n) for n in shape), dtype)
    return headers


def _check_panel_headers(
    path: str | os.PathLike, headers: dict[str, tuple[tuple[int, ...], np.dtype]]
) -> None:
    """Refuse, from the arrays' headers (:func:`_npz_headers`), a record that is not a
    panel-frames file, holds no frame, or whose figure would pass the limits above.

    Raises:
        ValueError: naming ``path``, what was found and what was expected (or the limit).
    """
    missing = [name for name in _PANEL_LAYOUT if name not in headers]
    if missing:
        raise ValueError(f"{path}: not a panel-frames file (no array {missing[0]!r})")
    for name, (kind, ndim) in _PANEL_LAYOUT.items():
        shape, dtype = headers[name]
        if dtype.kind != kind or len(shape) != ndim or (name == "image" and dtype.itemsize != 1):
            raise ValueError(
                f"{path}: not a panel-frames file ({name}: {dtype} of {len(shape)} axes)"
            )
    (count, channels, height, width), _ = headers["image"]
    _, pred_height, pred_width = headers["prediction"][0]
    if (
        channels != 3
        or any(headers[n][0][0] != count for n in _PANEL_ARRAYS)
        or any(headers[n][0][1:] != (height, width) for n in ("sparse", "target"))
        or headers["depth_range"][0] != (2,)
    ):
        raise ValueError(f"{path}: not a panel-frames file (arrays of mismatched shapes)")
    if count == 0:
        raise ValueError(f"{path}: no frames (its arrays hold none); expected at least one")
    if min(height, width, pred_height, pred_width) < 1:
        raise ValueError(
            f"{path}: frames of {height}x{width} pixels, predictions of {pred_height}x"
            f"{pred_width}; expected at least 1x1"
        )
    chars = headers["label"][1].itemsize // 4  # numpy's str holds 4 bytes a character
    if chars > MAX_PANEL_LABEL_CHARS:
        raise ValueError(
            f"{path}: labels of up to {chars} characters; expected at most "
            f"{MAX_PANEL_LABEL_CHARS} characters (the limit of a row's label)"
        )
    if pred_height * pred_width > MAX_PREDICTION_SCALE * height * width:
        raise ValueError(
            f"{path}: predictions of {pred_height}x{pred_width} pixels for images of "
            f"{height}x{width}; the limit is {MAX_PREDICTION_SCALE}x the image's pixels"
        )
    rows, columns = panel_figure_bound(count, height, width, chars)
    if rows * columns > MAX_PANEL_PIXELS or max(rows, columns) > MAX_PANEL_SIDE:
        raise ValueError(
            f"{path}: {count} frame{'s' if count != 1 else ''} of {height}x{width} pixels "
            "would make a figure of up to "
            f"{rows}x{columns} pixels; the limit is {MAX_PANEL_PIXELS:,} pixels and "
            f"{MAX_PANEL_SIDE:,} a side"
        )


def _not_panel_frames(path: str | os.PathLike, err: BaseException) -> ValueError:
    return ValueError(f"{path}: not a panel-frames file ({type(err).__name__})")


def _read_panel_arrays(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The arrays of the panel-frames file at ``path``, each read only once every header has
    passed :func:`_check_panel_headers` (``allow_pickle=False``: nothing becomes code)."""
    try:
        archive = zipfile.ZipFile(path)
    except (zipfile.BadZipFile, ValueError, EOFError) as err:
        raise _not_panel_frames(path, err) from None
    with archive:
        try:
            headers = _npz_headers(archive)
        except _ARCHIVE_ERRORS as err:
            raise _not_panel_frames(path, err) from None
        _check_panel_headers(path, headers)
        arrays = {}
        for name, (shape, _) in headers.items():
            try:
                with archive.open(f"{name}.npy") as f:
                    arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
            except _ARCHIVE_ERRORS as err:
                raise _not_panel_frames(path, err) from None
            if arrays[name].shape != shape:  # the file changed while it was read
                raise ValueError(f"{path}: not a panel-frames file ({name} changed its shape)")
    return arrays


def read_panel_frames(path: str | os.PathLike) -> tuple[list[PanelFrame], float, float]:
    """The frames and depth range :func:`write_panel_frames` wrote at ``path``, read as plain
    arrays (``allow_pickle=False``: nothing in the file becomes code). A frame whose ``target``
    is all zero gets ``target=None``.

    What the figure of the frames would cost is checked from the arrays' headers before any of
    them is read: at most :data:`MAX_PANEL_PIXELS` pixels (:func:`panel_figure_bound`) and
    :data:`MAX_PANEL_SIDE` a side, labels of at most :data:`MAX_PANEL_LABEL_CHARS` characters,
    predictions of at most :data:`MAX_PREDICTION_SCALE` times their image's pixels.

    Returns:
        (frames, min_depth, max_depth), depths in metres.

    Raises:
        ValueError: ``path`` is not such a file (a missing array, mismatched shapes, or not an
            ``.npz`` at all), holds no frame or frames of no pixels, a depth range that
            :func:`check_depth_range` refuses, or passes a limit; in one line naming the file.
        OSError: reading failed.
    """
    arrays = _read_panel_arrays(path)
    min_depth, max_depth = (float(v) for v in arrays["depth_range"])
    check_depth_range(min_depth, max_depth, f"{path}: depth_range")

    def plain(array: np.ndarray) -> torch.Tensor:
        with np.errstate(over="ignore"):  # a float64 beyond float32 becomes inf: no depth
            return torch.from_numpy(array.astype(np.float32))

    image, target = arrays["image"], arrays["target"]
    frames = [
        PanelFrame(
            image=torch.from_numpy(image[i].astype(np.float32) / 255),
            sparse=plain(arrays["sparse"][i]),
            prediction=plain(arrays["prediction"][i]),
            target=plain(target[i]) if target[i].any() else None,
            label=str(arrays["label"][i]),
        )
        for i in range(len(image))
    ]
    return frames, min_depth, max_depth
