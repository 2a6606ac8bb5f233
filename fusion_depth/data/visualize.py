"""Colourised depth panels for dashboards and files: the tiles are coloured here, and
matplotlib's Agg canvas draws only the labels of colour bars and figures."""

from __future__ import annotations

import os
import zipfile
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
    valid = torch.isfinite(target) & (target > 0) & torch.isfinite(pred)
    error = torch.where(valid, (pred - target).abs(), torch.zeros_like(target))
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
        ValueError: no frames, or frames of different sizes.
    """
    if not frames:
        raise ValueError("panel_figure: no frames to draw")
    sizes = {tuple(f.image.shape[-2:]) for f in frames}
    if len(sizes) != 1:
        raise ValueError(f"panel_figure: frames of different sizes {sorted(sizes)}")
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


def read_panel_frames(path: str | os.PathLike) -> tuple[list[PanelFrame], float, float]:
    """The frames and depth range :func:`write_panel_frames` wrote at ``path``, read as plain
    arrays (``allow_pickle=False``: nothing in the file becomes code). A frame whose ``target``
    is all zero gets ``target=None``.

    Returns:
        (frames, min_depth, max_depth), depths in metres.

    Raises:
        ValueError: ``path`` is not such a file (a missing array, mismatched shapes, or not an
            ``.npz`` at all), naming the file.
        OSError: reading failed.
    """
    names = (*_PANEL_ARRAYS, "depth_range")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in names if name in data.files}
    except (ValueError, zipfile.BadZipFile) as err:  # not an .npz, or an array needing pickle
        raise ValueError(f"{path}: not a panel-frames file ({type(err).__name__})") from None
    missing = [name for name in names if name not in arrays]
    if missing:
        raise ValueError(f"{path}: not a panel-frames file (no array {missing[0]!r})")
    count = len(arrays["label"])
    image = arrays["image"]
    if (
        image.dtype != np.uint8
        or image.ndim != 4
        or image.shape[1] != 3
        or any(len(arrays[n]) != count for n in _PANEL_ARRAYS)
        or arrays["sparse"].shape[1:] != image.shape[2:]
        or arrays["target"].shape[1:] != image.shape[2:]
        or arrays["prediction"].ndim != 3
        or arrays["depth_range"].shape != (2,)
    ):
        raise ValueError(f"{path}: not a panel-frames file (arrays of mismatched shapes)")
    frames = [
        PanelFrame(
            image=torch.from_numpy(image[i].astype(np.float32) / 255),
            sparse=torch.from_numpy(arrays["sparse"][i].astype(np.float32)),
            prediction=torch.from_numpy(arrays["prediction"][i].astype(np.float32)),
            target=(
                torch.from_numpy(arrays["target"][i].astype(np.float32))
                if arrays["target"][i].any()
                else None
            ),
            label=str(arrays["label"][i]),
        )
        for i in range(count)
    ]
    min_depth, max_depth = (float(v) for v in arrays["depth_range"])
    return frames, min_depth, max_depth
