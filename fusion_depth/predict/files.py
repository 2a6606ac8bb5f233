"""Depth for image files, folders and dataset splits from a loaded checkpoint, written as files.

:func:`predict_file`, :func:`predict_folder` and :func:`predict_split` read their inputs as
:class:`Frame` s, predict them in batches of one size with
:func:`fusion_depth.models.inference.predict_depth` and write, for every input ``<stem>``
(``<split>_<index:06d>`` for splits), into ``output_dir``:

* ``<stem>.png``: the depth as a single-channel uint16 PNG in 1/256 m (KITTI's convention:
  ``value / 256`` = metres, 0 = none; lossless to 1/512 m and readable by every depth tool).
  The format ends at 65535/256 ≈ 256 m: deeper values are clipped to it (the network's own
  range, ``max_depth``, normally ends well before);
* ``<stem>.npy``: float32 (H, W) metres, with ``npy=True``;
* ``<stem>.viz.png``: image | sparse input | prediction | ground truth (when there is one) and a
  colour bar in metres, with ``visualize=True`` (the default).

Depth is predicted at each image's own resolution (a visualisation less than 32 rows tall is
padded with black rows so its colour bar stays legible), up to ``max_pixels`` an image
(:data:`MAX_PIXELS` by default: the network's memory grows with the pixels, about 0.9 KB a pixel
for DenseNet-169 in fp32), checked from the file's header before it is decoded. Every file is
written under a temporary name and renamed, so nothing half-written is left.

No output replaces another output or an input of the same run: in a folder, an input whose
output names are taken by an input before it (by name: ``x.viz.png`` after ``x.png``, whose
visualisation is ``x.viz.png``; ``x.jpg`` after ``x.png``) is skipped, naming the other, and
an ``output_dir`` that is an input folder, or would receive a file the run reads, is refused.

Failures. In a folder or split run, whatever goes wrong with one input makes it a skip, reported
as ``skipped <path>: <reason>`` (one line), and the other inputs are still predicted and written:
an input that cannot be read or has more than ``max_pixels`` pixels, an input whose outputs
would replace another's, a sparse map that is missing or of another size, the network
failing on that image (a batch that fails is retried one image at a time, so only the culprit is
skipped), or writing its outputs failing (its files already written are removed again, so a
skipped input has no outputs from this run). The run ends with the summary line ``predicted N of
M inputs into <dir>; skipped K: <paths>`` and returns a :class:`PredictSummary`. Failures that
are not about one input stop the run at once: an ``output_dir`` that is not a writable folder
(checked before the first prediction), a disk that is full or a folder that became read-only
(no space, quota, read-only file system, permission denied), the network failing on 3 inputs in
a row (the model or the device is broken, not the images), and KeyboardInterrupt. A single file
input raises instead of skipping.
"""

from __future__ import annotations

import errno
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from PIL import Image

from fusion_depth.config import check_output_dir
from fusion_depth.data import SPLITS
from fusion_depth.data.cache import one_line
from fusion_depth.data.depth_io import (
    DataFileError,
    read_depth_png,
    read_rgb,
    write_depth_png,
    write_rgb_png,
)
from fusion_depth.data.visualize import depth_panel, with_colorbar
from fusion_depth.models.inference import predict_depth
from fusion_depth.runner.checkpoints import LoadedModel, dataset_config, make_reader
from fusion_depth.utils.atomic import write_atomic
from fusion_depth.utils.progress import Progress

# Named after the command, as its log lines have always been (and as users filter them).
log = logging.getLogger("fusion_depth.predict")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
# What an input <stem> writes: the depth PNG, and with npy=true / visualize=true these.
DEPTH_SUFFIX, NPY_SUFFIX, VIZ_SUFFIX = ".png", ".npy", ".viz.png"
# The most pixels an image predicts at by default: 4096 × 4096 (a 12 MP photo passes), about
# 14 GiB for DenseNet-169 in fp32 on a CPU (0.87 KB a pixel; ResNet-18: 0.42 KB).
MAX_PIXELS = 4096 * 4096
SPLIT_PREFIX = "split:"
# The network failing on this many inputs in a row means the model or device is broken.
MAX_FAILED_IN_A_ROW = 3
# What the forward pass raises for one input (torch's out-of-memory errors are RuntimeErrors).
FORWARD_ERRORS = (RuntimeError, ValueError)
# What drawing or writing one input's outputs raises (OSErrors of these errnos aside).
WRITE_ERRORS = (ValueError, RuntimeError, OSError)
# Write errors about the output folder or disk, not one input: they stop the run.
NOT_ONE_INPUT_ERRNOS = frozenset(
    {errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM}
)


@dataclass
class Frame:
    """One input: image (3, H, W) in [0, 1]; sparse and target (1, H, W) metres, 0 = none."""

    name: str  # output stem
    source: str  # what error messages call it: a path, or "<split> #<index>"
    image: torch.Tensor
    sparse: torch.Tensor | None = None
    target: torch.Tensor | None = None


@dataclass
class Skipped:
    """An input that could not be predicted, and why."""

    source: str
    reason: str


@dataclass
class PredictSummary:
    """What a folder or split run wrote (depth PNG paths) and skipped (with reasons)."""

    output_dir: Path
    total: int = 0
    written: list[Path] = field(default_factory=list)
    skipped: list[Skipped] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.skipped

    def line(self) -> str:
        text = f"predicted {len(self.written)} of {self.total} inputs into {self.output_dir}"
        if self.skipped:
            text += f"; skipped {len(self.skipped)}: " + ", ".join(s.source for s in self.skipped)
        return text


# --------------------------------------------------------------------------- reading inputs


def list_images(folder: str | os.PathLike) -> list[Path]:
    """The images of ``folder`` (``.png``/``.jpg``/``.jpeg``, any case), sorted by name.

    Hidden files (``.name``, e.g. another writer's temporary files) are left out.
    """
    folder = Path(folder)
    return sorted(
        p
        for p in folder.iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES and not p.name.startswith(".")
    )


def check_pixels(path: Path, max_pixels: int | None) -> None:
    """Refuse an image of more than ``max_pixels`` pixels (None: any), from its header alone:
    Pillow reads the size without decoding, so nothing of the image is allocated. A file whose
    header cannot be read passes, for the reader to name what is wrong with it.

    Raises:
        DataFileError: ``<path>: an image of <W>×<H> pixels (<n> MP), more than
            max_pixels=<m> ...``, one line.
    """
    if max_pixels is None:
        return
    try:
        with Image.open(path) as image:
            width, height = image.size
    except Exception:  # noqa: BLE001 - unreadable: read_rgb says why, naming the file
        return
    if width * height > max_pixels:
        raise DataFileError(
            path,
            f"an image of {width}×{height} pixels ({width * height / 1e6:.1f} MP), more than "
            f"max_pixels={max_pixels} ({max_pixels / 1e6:.1f} MP) that predict takes at full "
            "resolution, where the network's memory grows with the pixels; downscale the image, "
            "or raise max_pixels where the memory allows",
        )


def _read_image(path: Path) -> torch.Tensor:
    return torch.from_numpy(read_rgb(path).copy()).permute(2, 0, 1).float() / 255.0


def _read_depth_like(path: Path, image: torch.Tensor, image_path: Path, what: str) -> torch.Tensor:
    depth = read_depth_png(path)
    if depth.shape != tuple(image.shape[-2:]):
        raise ValueError(
            f"{path}: {what} is {depth.shape[0]}×{depth.shape[1]}, but the image {image_path} is "
            f"{image.shape[-2]}×{image.shape[-1]}; expected the same size"
        )
    return torch.from_numpy(depth)[None]


def _companion(spec: Path | None, image_path: Path) -> Path | None:
    """The sparse/ground-truth PNG for ``image_path``: ``spec`` itself, or ``spec/<stem>.png``."""
    if spec is None:
        return None
    return spec / f"{image_path.stem}.png" if spec.is_dir() else spec


def _load_frame(
    image_path: Path,
    sparse: Path | None,
    ground_truth: Path | None,
    needs_sparse: bool,
    max_pixels: int | None = MAX_PIXELS,
) -> Frame:
    """Image, sparse map and ground truth of one file input (errors name the file); an image
    of more than ``max_pixels`` pixels is refused before it is decoded (:func:`check_pixels`)."""
    check_pixels(image_path, max_pixels)
    image = _read_image(image_path)
    frame = Frame(name=image_path.stem, source=str(image_path), image=image)
    sparse_path = _companion(sparse, image_path)
    if sparse_path is not None and (sparse_path.is_file() or needs_sparse):
        if not sparse_path.is_file():
            raise FileNotFoundError(f"{sparse_path}: missing sparse depth PNG for {image_path}")
        frame.sparse = _read_depth_like(sparse_path, image, image_path, "the sparse depth")
    target_path = _companion(ground_truth, image_path)
    if target_path is not None and target_path.is_file():
        frame.target = _read_depth_like(target_path, image, image_path, "the ground truth")
    return frame


def _check_sparse(loaded: LoadedModel, sparse: Path | None, where: str) -> None:
    if sparse is None and loaded.net.fusion.uses_sparse:
        raise ValueError(
            f"sparse=null: {loaded.key}={loaded.path} was trained with fusion={loaded.fusion}, "
            f"which needs a sparse depth map for every image; pass sparse=<{where}> (depth PNGs in "
            "1/256 m, 0 = no return) or use an RGB-only (fusion=rgb) checkpoint"
        )
    if sparse is not None and not sparse.exists():
        raise FileNotFoundError(f"sparse={sparse}: no such file or folder")
    if sparse is not None and not loaded.net.fusion.uses_sparse:
        log.info(
            "%s=%s has fusion=%s: sparse=%s is shown in the visualisation but not used",
            loaded.key,
            loaded.path,
            loaded.fusion,
            sparse,
        )


def output_names(stem: str, npy: bool, visualize: bool) -> list[str]:
    """The files an input ``<stem>`` writes into ``output_dir``: ``<stem>.png``, with ``npy``
    ``<stem>.npy`` and with ``visualize`` ``<stem>.viz.png``."""
    wanted = ((DEPTH_SUFFIX, True), (NPY_SUFFIX, npy), (VIZ_SUFFIX, visualize))
    return [f"{stem}{suffix}" for suffix, on in wanted if on]


def _colliding(
    images: list[Path], output_dir: Path, npy: bool, visualize: bool, read: set[Path]
) -> dict[Path, str]:
    """The images whose outputs would replace those of an image before them (in the given
    order: the first keeps its names), or a file the run reads (``read``, resolved), each with
    the one-line reason it is skipped."""
    claimed: dict[str, Path] = {}
    refused: dict[Path, str] = {}
    for path in images:
        names = output_names(path.stem, npy, visualize)
        taken = next((name for name in names if name in claimed), None)
        if taken is not None:
            other = claimed[taken]
            refused[path] = (
                f"its output {taken} would replace the {_what(taken, other.stem)} of "
                f"{other.name} (an input before it); rename one of them"
            )
            continue
        inputs = [name for name in names if (output_dir / name).resolve() in read]
        if inputs:
            refused[path] = (
                f"its output {output_dir / inputs[0]} would replace a file this run reads; "
                "choose another output_dir"
            )
            continue
        claimed.update(dict.fromkeys(names, path))
    return refused


def _files_read(images: list[Path], *folders: Path | None) -> set[Path]:
    """What a folder run reads, resolved: ``images`` and their ``<stem>.png`` in each of
    ``folders`` (sparse, ground truth) that is given."""
    companions = [_companion(folder, path) for folder in folders for path in images]
    return {path.resolve() for path in [*images, *companions] if path is not None}


def _what(name: str, stem: str) -> str:
    """What output ``name`` is of an input ``stem``: its depth PNG, depth array or
    visualisation."""
    return {DEPTH_SUFFIX: "depth PNG", NPY_SUFFIX: "depth array", VIZ_SUFFIX: "visualisation"}[
        name[len(stem) :]
    ]


def _check_companion_folders(sparse: Path | None, ground_truth: Path | None) -> None:
    """With a folder input, ``sparse`` and ``ground_truth`` are folders (or None)."""
    for key, path in (("sparse", sparse), ("ground_truth", ground_truth)):
        if path is not None and not path.is_dir():
            raise ValueError(
                f"{key}={path}: with a folder input, expected a folder of <image stem>.png "
                "depth maps"
            )


def _check_outputs_apart(output_dir: Path, *inputs: Path | None) -> None:
    """Refuse an output_dir that is an input folder: ``<stem>.png`` would replace inputs."""
    out = output_dir.expanduser().resolve()
    for path in inputs:
        if path is not None and path.is_dir() and path.resolve() == out:
            raise ValueError(
                f"output_dir={output_dir} is the input folder {path}; writing <stem>.png there "
                "would overwrite the inputs: choose another output_dir"
            )


# --------------------------------------------------------------------------- writing outputs


def _check_output_dir(output_dir: Path) -> None:
    """Creates ``output_dir`` and checks a file can be written in it, before any prediction: a
    folder that takes no files is not one input's problem.

    Raises:
        NotADirectoryError: ``output_dir`` is a file.
        OutputDirError: it cannot be created or written to (:func:`check_output_dir`).
    """
    if output_dir.exists() and not output_dir.is_dir():
        raise NotADirectoryError(f"output_dir={output_dir}: a file, expected a folder")
    check_output_dir(output_dir, needed_bytes=0)


def _write_outputs(
    output_dir: Path, frame: Frame, depth: np.ndarray, net: Any, npy: bool, visualize: bool
) -> Path:
    """Writes ``<stem>.png`` (and ``.npy``, ``.viz.png``); returns the depth PNG's path.

    The visualisation is drawn before any file is written, and when a write fails the files
    this call already wrote are removed, so the input ends with all its outputs or none.

    Raises:
        ValueError, RuntimeError: drawing the visualisation failed.
        OSError: writing a file failed.
    """
    depth_path = output_dir / f"{frame.name}{DEPTH_SUFFIX}"
    writes: list[tuple[Path, Callable[[], None]]] = [
        (depth_path, lambda: write_depth_png(depth_path, depth))
    ]
    if npy:
        array = depth.astype(np.float32)
        npy_path = output_dir / f"{frame.name}{NPY_SUFFIX}"

        def save(tmp: Path) -> None:
            np.save(tmp, array)

        writes.append((npy_path, lambda: write_atomic(npy_path, save, suffix=".npy")))
    if visualize:
        sparse = frame.sparse if frame.sparse is not None else torch.zeros_like(frame.image[:1])
        panel = depth_panel(
            frame.image,
            sparse,
            torch.from_numpy(depth),
            frame.target,
            net.min_depth,
            net.max_depth,
        )
        viz = with_colorbar(panel, net.min_depth, net.max_depth)
        viz_path = output_dir / f"{frame.name}{VIZ_SUFFIX}"
        writes.append((viz_path, lambda: write_rgb_png(viz_path, viz)))
    written: list[Path] = []
    try:
        for path, write in writes:
            write()
            written.append(path)
    except BaseException:
        for path in written:
            path.unlink(missing_ok=True)
        raise
    return depth_path


# --------------------------------------------------------------------------- the prediction loop


def _predict_frames(net: Any, frames: list[Frame], flip_tta: bool) -> list[np.ndarray]:
    """Depth (H, W) float32 metres for frames of one size, in one batch on the net's device."""
    device = next(net.parameters()).device
    images = torch.stack([f.image for f in frames]).to(device)
    sparse = None
    if net.fusion.uses_sparse:
        sparse = torch.stack([f.sparse for f in frames]).to(device)
    depth = predict_depth(net, images, sparse, flip_tta=flip_tta)
    return [d[0].float().cpu().numpy() for d in depth]


def _predict_isolated(
    net: Any, frames: list[Frame], flip_tta: bool
) -> list[np.ndarray | Exception]:
    """Each frame's depth, or the error the network raised for it.

    The frames go through as one batch; if the batch fails, each is predicted alone, so a
    failure that belongs to one frame (e.g. out of memory on a huge image) is that frame's only.
    """
    try:
        return list(_predict_frames(net, frames, flip_tta))
    except FORWARD_ERRORS as err:
        if len(frames) == 1:
            return [err]
    results: list[np.ndarray | Exception] = []
    for frame in frames:
        try:
            results += _predict_frames(net, [frame], flip_tta)
        except FORWARD_ERRORS as err:
            results.append(err)
    return results


def _describe(err: BaseException) -> str:
    """``ErrorType: first line of the message``, for a reason the error's type explains."""
    return f"{type(err).__name__}: {one_line(err)}"


def _run(
    loaded: LoadedModel,
    items: Iterable[Frame | Skipped],
    total: int,
    output_dir: Path,
    *,
    npy: bool,
    visualize: bool,
    flip_tta: bool,
    batch_size: int,
    progress: bool | None,
    description: str,
) -> PredictSummary:
    """Predicts and writes ``items``; every per-input failure becomes a skip (module docstring).

    Raises:
        ValueError: ``batch_size`` is not an integer >= 1.
        OSError: ``output_dir`` is not writable, or a write failed for want of space or
            permission.
        RuntimeError: the network failed on :data:`MAX_FAILED_IN_A_ROW` inputs in a row.
    """
    if not isinstance(batch_size, int) or batch_size < 1:
        raise ValueError(f"batch_size={batch_size}: expected an integer ≥ 1")
    net = loaded.net.eval()
    summary = PredictSummary(output_dir=Path(output_dir), total=total)
    _check_output_dir(summary.output_dir)
    batch: list[Frame] = []
    failed_in_a_row = 0

    def skip(item: Skipped) -> None:
        summary.skipped.append(item)
        log.warning("skipped %s: %s", item.source, item.reason)

    with Progress(total, description, unit="inputs", terminal=progress, logger=log) as bar:

        def flush() -> None:
            nonlocal failed_in_a_row
            results = _predict_isolated(net, batch, flip_tta)
            for frame, result in zip(batch, results, strict=True):
                if isinstance(result, Exception):
                    failed_in_a_row += 1
                    skip(Skipped(frame.source, f"prediction failed ({_describe(result)})"))
                    if failed_in_a_row >= MAX_FAILED_IN_A_ROW:
                        raise RuntimeError(
                            f"the network failed on {failed_in_a_row} inputs in a row, the last "
                            f"{frame.source} ({_describe(result)}); stopping, as this is not "
                            "about one input: check the checkpoint, device and precision"
                        ) from result
                    continue
                failed_in_a_row = 0
                try:
                    path = _write_outputs(summary.output_dir, frame, result, net, npy, visualize)
                except WRITE_ERRORS as err:
                    if isinstance(err, OSError) and err.errno in NOT_ONE_INPUT_ERRNOS:
                        raise
                    skip(Skipped(frame.source, f"writing its outputs failed ({_describe(err)})"))
                    continue
                summary.written.append(path)
            bar.advance(len(batch))
            batch.clear()

        for item in items:
            if isinstance(item, Skipped):
                skip(item)
                bar.advance(1)
                continue
            if batch and (len(batch) >= batch_size or batch[0].image.shape != item.image.shape):
                flush()
            batch.append(item)
        if batch:
            flush()
    (log.warning if summary.skipped else log.info)("%s", summary.line())
    return summary


def _reason(err: BaseException, source: str) -> str:
    """The error's message (first line) without a leading ``<source>: `` (the log line names
    it already)."""
    text = one_line(err)
    return text[len(source) + 2 :] if text.startswith(f"{source}: ") else text


def _check_limit(limit: int | None) -> None:
    if limit is not None and (not isinstance(limit, int) or limit < 1):
        raise ValueError(f"limit={limit}: expected null (everything) or an integer ≥ 1")


def _check_max_pixels(max_pixels: int | None) -> None:
    whole = isinstance(max_pixels, int) and not isinstance(max_pixels, bool)
    if max_pixels is not None and (not whole or max_pixels < 1):
        raise ValueError(f"max_pixels={max_pixels!r}: expected null (any size) or an integer ≥ 1")


# --------------------------------------------------------------------------- files, folders, splits


def predict_file(
    loaded: LoadedModel,
    image: str | os.PathLike,
    output_dir: str | os.PathLike,
    sparse: str | os.PathLike | None = None,
    ground_truth: str | os.PathLike | None = None,
    *,
    npy: bool = False,
    visualize: bool = True,
    flip_tta: bool = False,
    max_pixels: int | None = MAX_PIXELS,
) -> np.ndarray:
    """Predict one image file; returns the depth (H, W) float32 metres that was written.

    ``sparse``/``ground_truth``: a depth PNG, or a folder holding ``<image stem>.png``. Unlike a
    folder run, an input that cannot be predicted raises (naming the file) instead of being
    skipped. ``max_pixels``: the most pixels the image may have (None: any), checked before it
    is decoded.

    Raises:
        FileNotFoundError: ``image`` (or a sparse map the checkpoint needs) is missing.
        ValueError: an ``output_dir`` where an output would replace an input; a ``max_pixels``
            that is not None or an integer ≥ 1.
        DataFileError: an image that cannot be read, or of more than ``max_pixels`` pixels; a
            sparse or ground-truth map that cannot be read or is of another size.
    """
    image, output_dir = Path(image).expanduser(), Path(output_dir).expanduser()
    sparse = None if sparse is None else Path(sparse).expanduser()
    ground_truth = None if ground_truth is None else Path(ground_truth).expanduser()
    if not image.is_file():
        raise FileNotFoundError(f"input={image}: no such file")
    _check_max_pixels(max_pixels)
    _check_sparse(loaded, sparse, "a depth PNG of the same size as the image")
    targets = {(output_dir / n).resolve() for n in output_names(image.stem, npy, visualize)}
    for path in (image, sparse, ground_truth):
        if path is not None and path.resolve() in targets:
            raise ValueError(
                f"output_dir={output_dir}: writing the outputs of {image} there would overwrite "
                f"the input {path}: choose another output_dir"
            )
    uses_sparse = loaded.net.fusion.uses_sparse
    frame = _load_frame(image, sparse, ground_truth, uses_sparse, max_pixels)
    (depth,) = _predict_frames(loaded.net.eval(), [frame], flip_tta)
    _write_outputs(output_dir, frame, depth, loaded.net, npy, visualize)
    log.info("predicted 1 of 1 inputs (%s) into %s", image, output_dir)
    return depth


def predict_folder(
    loaded: LoadedModel,
    folder: str | os.PathLike,
    output_dir: str | os.PathLike,
    sparse: str | os.PathLike | None = None,
    ground_truth: str | os.PathLike | None = None,
    *,
    npy: bool = False,
    visualize: bool = True,
    flip_tta: bool = False,
    batch_size: int = 1,
    limit: int | None = None,
    progress: bool | None = None,
    max_pixels: int | None = MAX_PIXELS,
) -> PredictSummary:
    """Predict every image of ``folder`` (sorted by name; the first ``limit`` when given).

    ``sparse``/``ground_truth`` are folders of ``<image stem>.png`` depth maps. An input that
    fails (reading it, more than ``max_pixels`` pixels, predicting it, writing its outputs), or
    whose output names an input before it takes (``x.viz.png`` after ``x.png``), is logged as
    ``skipped <path>: <reason>`` and listed in the summary; the others are still written (module
    docstring, "Failures"). Images of the same size are batched ``batch_size`` at a time.
    ``progress``: a bar on stderr (True), a log line a minute (False), or None: the bar when
    stderr is a terminal, else the lines.

    Raises:
        FileNotFoundError: ``folder`` is missing.
        ValueError: a folder without images, an ``output_dir`` that is an input folder, a
            ``limit``, ``max_pixels`` or ``batch_size`` out of range.
        OSError, RuntimeError: what stops the run at once (module docstring, "Failures").
    """
    folder, output_dir = Path(folder).expanduser(), Path(output_dir).expanduser()
    sparse = None if sparse is None else Path(sparse).expanduser()
    ground_truth = None if ground_truth is None else Path(ground_truth).expanduser()
    if not folder.is_dir():
        raise FileNotFoundError(f"input={folder}: no such folder")
    _check_limit(limit)
    _check_max_pixels(max_pixels)
    _check_sparse(loaded, sparse, "a folder of <image stem>.png depth maps")
    _check_companion_folders(sparse, ground_truth)
    _check_outputs_apart(output_dir, folder, sparse, ground_truth)
    images = list_images(folder)
    if not images:
        raise ValueError(
            f"input={folder}: no images in it (expected files ending in "
            f"{', '.join(IMAGE_SUFFIXES)})"
        )
    images = images[:limit]
    needs_sparse = loaded.net.fusion.uses_sparse
    refused = _colliding(
        images, output_dir, npy, visualize, _files_read(images, sparse, ground_truth)
    )

    def items() -> Iterator[Frame | Skipped]:
        for path in images:
            if path in refused:
                yield Skipped(str(path), refused[path])
                continue
            try:
                yield _load_frame(path, sparse, ground_truth, needs_sparse, max_pixels)
            except (ValueError, OSError) as err:
                yield Skipped(str(path), _reason(err, str(path)))

    return _run(
        loaded,
        items(),
        len(images),
        output_dir,
        npy=npy,
        visualize=visualize,
        flip_tta=flip_tta,
        batch_size=batch_size,
        progress=progress,
        description=f"predict {folder.name or folder}",
    )


def predict_split(
    loaded: LoadedModel,
    split: str,
    output_dir: str | os.PathLike,
    dataset: dict | DictConfig | None = None,
    *,
    npy: bool = False,
    visualize: bool = True,
    flip_tta: bool = False,
    batch_size: int = 1,
    limit: int | None = None,
    progress: bool | None = None,
) -> PredictSummary:
    """Predict the frames of a dataset split; outputs are named ``<split>_<index:06d>``.

    ``dataset``: a dataset block (``dataset=<name>`` composed from ``conf/``); None = the one the
    checkpoint was trained on. Visualisations show the split's ground truth. Failures and
    ``progress`` as for :func:`predict_folder`; a skipped frame is named ``<split> #<index>``.
    """
    if split not in SPLITS:
        raise ValueError(f"input={SPLIT_PREFIX}{split}: expected a split of {list(SPLITS)}")
    _check_limit(limit)
    if isinstance(dataset, DictConfig):
        dataset = OmegaConf.to_container(dataset, resolve=True)
    block = dataset_config(loaded, dataset)
    reader = make_reader(block, None if dataset is not None else loaded.path, loaded.key)
    reader = reader(split=split)
    total = len(reader) if limit is None else min(limit, len(reader))
    if total == 0:
        raise ValueError(f"input={SPLIT_PREFIX}{split}: dataset={block.get('name')} has no frames")

    def items() -> Iterator[Frame | Skipped]:
        for index in range(total):
            source = f"{split} #{index}"
            try:
                item = reader[index]
            except (ValueError, OSError) as err:
                yield Skipped(source, one_line(err))
                continue
            yield Frame(
                name=f"{split}_{index:06d}",
                source=source,
                image=item["image"].float(),
                sparse=item.get("sparse"),
                target=item.get("depth"),
            )

    return _run(
        loaded,
        items(),
        total,
        Path(output_dir).expanduser(),
        npy=npy,
        visualize=visualize,
        flip_tta=flip_tta,
        batch_size=batch_size,
        progress=progress,
        description=f"predict {block.get('name')} {split}",
    )
