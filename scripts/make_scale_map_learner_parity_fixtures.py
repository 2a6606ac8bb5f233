"""Parity fixtures for :mod:`fusion_depth.models.scale_map_learner`, made by running
RadarCam-Depth's authors' own code (github.com/MMOCKING/RadarCam-Depth). Nothing of their code
is copied here or into the repository: this script imports it from a checkout at run time and
keeps only what it computes.

The committed fixtures were made from commit 3762f2ffc02e8809c234b27c2bf288b557bfc27d with
torch 2.14.1, numpy 2.4.6, opencv-python-headless 4.11, Pillow and geffnet 1.0.2 on a 2-core
Xeon CPU with two threads (``fixtures.json`` records all of it; the tests compare at the
recorded thread count, since a convolution's rounding depends on it). To make them again, from
the repository root, in the project's environment::

    git clone https://github.com/MMOCKING/RadarCam-Depth CHECKOUT  # its .pth files not needed
    pip install --target EXTRA --no-deps geffnet==1.0.2
    PYTHONPATH=EXTRA python scripts/make_scale_map_learner_parity_fixtures.py CHECKOUT

(Their code also imports cv2, scipy, matplotlib, Pillow and torchvision; add
``opencv-python-headless`` to the ``pip install`` where cv2 is missing. A checkout without
the two ``.pth`` files, e.g. a sparse checkout with them marked ``skip-worktree``, will do:
nothing here reads them.)

What is substituted in their code, and nothing else:

* ``torch.hub.load("rwightman/gen-efficientnet-pytorch", "tf_efficientnet_lite3",
  pretrained=..., exportable=True)`` (their ``modules/midas/blocks.py`` line 45) cannot reach
  GitHub here. :func:`hub_load` stands in for it: it calls ``geffnet.tf_efficientnet_lite3(
  pretrained=False, exportable=...)``, the very function that repository's ``hubconf.py``
  exposes, from geffnet 1.0.2 on PyPI (the package that repository publishes; its last
  release). ``pretrained`` is forced to False (no ImageNet download): every weight is then
  overwritten with :func:`fixture_weights` anyway. Any other hub call fails.
* ``torch.utils.tensorboard`` (imported by their ``SML/sml_main.py``, line 6) is replaced by
  a stub ``SummaryWriter`` that writes nothing, since tensorboard is not installed: their
  training builds one (line 132) and logs to it only every ``n_step_per_summary`` steps, which
  is set past the one step run here.

Their network in its shipped configuration (``MidasNet_small_videpth()``, ``features=64``) has
21 M values (85 MB): too many to keep. So the weights are not stored: :func:`fixture_weights`
makes them from each key's name and shape (a fixed hash, no random generator, so any torch
makes the same bytes), scaled so that activations keep their size through the layers;
``fixtures.json`` records their SHA-256 and the test makes them again with this function. The
frames are small instead. What it does:

1. Builds their ``MidasNet_small_videpth()`` and loads :func:`fixture_weights` (strict).
2. Frame ``test``: a ZJU-like frame (720×64, cropped by their dataset to 300×64; network size
   288×64) written as their PNGs in a temporary folder and run through their ``SML_dataset``
   and ``sml_main.validate`` as ``SML/sml_run_zju.py`` runs it (eval mode, ``min_pred`` 0.1,
   ``max_pred`` 100, ``save_output=True``). It records the scaffold at full resolution (what
   their ``normalize_unit_range`` returns), the network's inputs ``x`` and ``d``, its raw
   output (``scratch.output_conv``), ``pred``, and the depth their ``save_depth`` is handed
   (the bicubic resize to 300×64, sky kept from ``mono_ga``).
3. Frame ``train``: a 40×144 frame (network size 64×288: 2.5 × 32 rounds to 2 × 32) run
   through their ``sml_main.train`` for one step with ``sml_train_zju.py``'s settings (train
   mode, ``max_pred`` 255, smooth L1, ``w_lidar`` 3). It records ``x``, ``d``, the raw output
   and ``pred`` of that step's forward (batch statistics), the resized targets, and the loss
   ``compute_loss`` returned. The same tensors then go through their ``compute_loss`` with the
   other settings it has (``losses``).
4. ``alignment``: their ``data/global_alignment.py`` ``process_scale`` on two 40×60 frames
   (one with radar points in range, one with a single one: singular), the float map it hands to
   ``save_depth``.
5. ``shipped_layout.json``: the keys and shapes of ``MidasNet_small_videpth()``'s state dict
   as their ``BaseModel.save`` writes it (read back with ``weights_only=True``), and what the
   file their training wrote holds.

Outputs in ``--out`` (default ``tests/fixtures/scale_map_learner_authors``): ``cases.pt``,
``shipped_layout.json``, ``fixtures.json``.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import subprocess
import sys
import tempfile
import types
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

AUTHORS_COMMIT = "3762f2ffc02e8809c234b27c2bf288b557bfc27d"
SEED = 0
HUB_REPO = "rwightman/gen-efficientnet-pytorch"
# Conv weights: uniform of variance GAIN / fan_in in the encoder (ReLU6 halves it), less in the
# decoder (each residual unit adds its input to what it computes); the last 1×1 conv of the
# output head is scaled so that 1 + out is negative on part of a frame (the ReLU acts).
GAIN = 2.0
DECODER_GAIN = 0.5
OUTPUT_GAIN = 1.0
OUTPUT_KEY = "scratch.output_conv.output_conv.4.weight"
# Frame "test": ZJU's 720 rows, 64 columns; frame "train": 40×144; "alignment": 40×60.
TEST_SIZE = (720, 64)
RCNET_SIZE = (300, 64)  # RC-Net writes ZJU's crop, rows 240-539
ZJU_ROWS = (240, 540)  # their SML_dataset.py lines 56-75: 720 // 3, 720 // 4 * 3
TRAIN_SIZE = (40, 144)
ALIGN_SIZE = (40, 60)
TEST_MIN_PRED, TEST_MAX_PRED = 0.1, 100.0  # sml_run_zju.py lines 77-78
TRAIN_MIN_PRED, TRAIN_MAX_PRED = 0.1, 255.0  # sml_train_zju.py lines 55-56
# compute_loss settings beyond the recipe's: (loss_func, w_smoothness, kernel, w_lidar).
LOSS_SETTINGS = {
    "recipe": ("smoothl1", 0.0, -1, 3.0),
    "l1": ("l1", 0.0, -1, 3.0),
    "l2": ("l2", 0.0, -1, 3.0),
    "no_lidar": ("smoothl1", 0.0, -1, 0.0),
    "smoothness": ("smoothl1", 0.5, -1, 3.0),
    "sobel7": ("l1", 0.5, 7, 3.0),
}


def _hashed(values: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer hash of each value (int64 arithmetic that cannot overflow)."""
    x = values & 0xFFFFFFFF
    for _ in range(2):
        x = (((x >> 16) ^ x) * 0x45D9F3B) & 0xFFFFFFFF
    return (x >> 16) ^ x


def _uniform(key: str, base: torch.Tensor, count: int, seed: int) -> torch.Tensor:
    """``count`` values in [-1, 1), float32: the hash of the hashed indices ``base`` (the
    hash of 0, 1, ...) mixed with the CRC-32 of ``key``."""
    salt = zlib.crc32(f"{seed}:{key}".encode())
    x = _hashed(base[:count] ^ salt)
    return (x.to(torch.float64) / 2**31 - 1.0).to(torch.float32)


def fixture_weights(layout: Mapping[str, Sequence[int]], seed: int = SEED) -> dict[str, Any]:
    """The fixtures' weights for a state dict of keys and shapes (their network's).

    Each tensor is :func:`_uniform` of its key, shaped. Batch norms (a key whose module has a
    ``running_mean``): weight ``1 + 0.25 u``, bias ``0.1 u``, running mean ``0.1 u``, running
    variance ``1 + 0.5 u``; ``num_batches_tracked`` 0. Conv weights ``u · sqrt(3 · GAIN /
    fan_in)`` (:data:`DECODER_GAIN` in ``scratch``, :data:`OUTPUT_GAIN` for its last one);
    conv biases ``0.1 u``."""
    state: dict[str, Any] = {}
    base = _hashed(torch.arange(max(math.prod(shape) for shape in layout.values())))
    for key, shape in layout.items():
        shape = tuple(shape)
        if key.endswith("num_batches_tracked"):
            state[key] = torch.zeros(shape, dtype=torch.int64)
            continue
        u = _uniform(key, base, math.prod(shape), seed).reshape(shape)
        module, name = key.rsplit(".", 1)
        if f"{module}.running_mean" in layout:
            scale, shift = {
                "weight": (0.25, 1.0),
                "bias": (0.1, 0.0),
                "running_mean": (0.1, 0.0),
                "running_var": (0.5, 1.0),
            }[name]
            state[key] = u * scale + shift
        elif name == "bias":
            state[key] = u * 0.1
        else:
            gain = GAIN
            if key.startswith("scratch."):
                gain = OUTPUT_GAIN if key == OUTPUT_KEY else DECODER_GAIN
            scale = math.sqrt(3.0 * gain / (math.prod(shape) // shape[0]))
            state[key] = u * torch.tensor(scale, dtype=torch.float32)
    return state


def weights_digest(state: Mapping[str, torch.Tensor]) -> str:
    """SHA-256 of the tensors' bytes, in key order."""
    digest = hashlib.sha256()
    for key in sorted(state):
        digest.update(key.encode())
        digest.update(state[key].contiguous().numpy().tobytes())
    return digest.hexdigest()


HUB_CALLS: list[dict[str, Any]] = []


def hub_load(repo: str, model: str, *args: Any, **kwargs: Any) -> Any:
    """Stands in for ``torch.hub.load`` (module docstring): geffnet's own ``model`` function,
    the one the hub repository's ``hubconf.py`` exposes, without ImageNet weights."""
    import geffnet

    if repo != HUB_REPO or args:
        raise RuntimeError(f"unexpected torch.hub.load({repo!r}, {model!r}, *{args})")
    HUB_CALLS.append({"repo": repo, "model": model, **kwargs})
    return getattr(geffnet, model)(**{**kwargs, "pretrained": False})


class _SummaryWriter:
    """The stub of ``torch.utils.tensorboard.SummaryWriter`` (module docstring)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        pass

    def __getattr__(self, name: str) -> Any:
        return lambda *args, **kwargs: None


def import_authors(checkout: Path) -> dict[str, Any]:
    """Their modules, imported from the checkout, with :func:`hub_load` and the stub writer."""
    sys.path.insert(0, str(checkout))
    tensorboard = types.ModuleType("torch.utils.tensorboard")
    tensorboard.SummaryWriter = _SummaryWriter
    sys.modules["torch.utils.tensorboard"] = tensorboard
    torch.hub.load = hub_load
    import data.global_alignment as global_alignment
    import modules.midas.midas_net_custom as midas_net_custom
    import SML.sml_main as sml_main
    import utils.loss as loss

    return {
        "sml_main": sml_main,
        "net_module": midas_net_custom,
        "global_alignment": global_alignment,
        "loss": loss,
    }


@contextlib.contextmanager
def _patched(module: Any, **values: Any) -> Iterator[None]:
    """``module``'s attributes set to ``values`` for the duration."""
    before = {name: getattr(module, name) for name in values}
    for name, value in values.items():
        setattr(module, name, value)
    try:
        yield
    finally:
        for name, value in before.items():
            setattr(module, name, value)


def _write_png(path: Path, metres: np.ndarray) -> np.ndarray:
    """A depth map as their PNGs hold it (``uint16(z · 256)``); returns the codes."""
    from PIL import Image

    codes = np.clip(np.round(metres * 256.0), 0, 65535).astype(np.uint16)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(codes).save(path)
    return codes


def _write_image(path: Path, generator: np.random.Generator, size: tuple[int, int]) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(generator.integers(0, 256, (*size, 3), dtype=np.uint8)).save(path)


def _aligned_depth(
    generator: np.random.Generator, size: tuple[int, int], rows: tuple[int, int]
) -> np.ndarray:
    """A monocular depth in metres over ``size``, shaped for the rows ``rows`` the network
    sees (ZJU's crop): far at their top (up to 250 m: sky past 200 m and past ``max_pred``),
    near at their bottom (under 2 m), noisy, and a patch of 0.05 m (under ``min_pred``)."""
    top, bottom = rows
    t = np.clip((np.arange(size[0]) - top) / (bottom - 1 - top), 0.0, 1.0)[:, None]
    depth = np.exp(np.log(250.0) * (1 - t) + np.log(1.2) * t) * (
        1 + 0.15 * np.sin(np.arange(size[1])[None, :] / 5.0)
    )
    depth = depth * generator.uniform(0.9, 1.1, size)
    depth[bottom - 6 : bottom, :10] = 0.05
    return np.clip(depth, 0.05, 255.0)


def _quasi_dense(generator: np.random.Generator, size: tuple[int, int], bands: int) -> np.ndarray:
    """RC-Net-like quasi-dense depth: whole-metre bands of columns over the lower rows, 0
    elsewhere, and a band at 85 m (past the 80 m their SML counts)."""
    rows, columns = size
    depth = np.zeros(size)
    for i in range(bands):
        left = int(generator.integers(0, columns - 6))
        width = int(generator.integers(3, 10))
        top = int(generator.integers(rows // 3, rows - 4))
        depth[top:, left : left + width] = 85.0 if i == 0 else float(generator.integers(2, 70))
    return depth


def _lidar(generator: np.random.Generator, size: tuple[int, int], share: float) -> np.ndarray:
    depth = generator.uniform(1.0, 90.0, size)
    return np.where(generator.random(size) < share, depth, 0.0)


def _frame_files(
    root: Path,
    generator: np.random.Generator,
    size: tuple[int, int],
    rcnet_size: tuple[int, int],
    rows: tuple[int, int],
) -> dict[str, Any]:
    """One frame in their folders (``sml_train_zju.py`` lines 11-16): image, radar_png, gt
    (``gt_interp``), sparse gt, RC-Net's depth, ``mono_ga``; returns paths and PNG codes."""
    paths = {
        name: root / name / "frame.png"
        for name in ("image", "radar", "gt", "sparse_gt", "rcnet", "mono_ga")
    }
    _write_image(paths["image"], generator, size)
    codes = {
        "radar": _write_png(paths["radar"], _lidar(generator, size, 0.01)),
        "gt": _write_png(paths["gt"], _lidar(generator, size, 0.6)),
        "sparse_gt": _write_png(paths["sparse_gt"], _lidar(generator, size, 0.1)),
        "rcnet": _write_png(paths["rcnet"], _quasi_dense(generator, rcnet_size, 7)),
        "mono_ga": _write_png(paths["mono_ga"], _aligned_depth(generator, size, rows)),
    }
    return {"paths": {k: [str(v)] for k, v in paths.items()}, "codes": codes}


class Recorder:
    """Stands in for their network's ``forward`` (the first call) and keeps its inputs, its
    raw output (``scratch.output_conv``'s) and its results."""

    def __init__(self, net: Any) -> None:
        self.net, self.forward_of, self.seen = net, net.forward, {}
        net.scratch.output_conv.register_forward_hook(self._out)

    def _out(self, module: Any, inputs: Any, output: torch.Tensor) -> None:
        self.seen.setdefault("out", output.detach().clone())

    def __call__(self, x: torch.Tensor, d: torch.Tensor) -> Any:
        first = "x" not in self.seen
        if first:
            self.seen.update(x=x.detach().clone(), d=d.detach().clone())
        pred, scales = self.forward_of(x, d)
        if first:
            self.seen.update(pred=pred.detach().clone(), scales=scales.detach().clone())
        return pred, scales


def their_net(authors: dict[str, Any], weights: Mapping[str, torch.Tensor], **kwargs: Any) -> Any:
    """Their ``MidasNet_small_videpth(**kwargs)`` with the fixture weights, recorded."""
    net = authors["net_module"].MidasNet_small_videpth(**kwargs)
    net.load_state_dict(weights, strict=True)
    net.forward = Recorder(net)
    return net


def test_frame(authors: dict[str, Any], weights: Mapping, generator: np.random.Generator) -> dict:
    """Frame ``test`` (step 2): their ``validate`` as ``sml_run_zju.py`` calls it."""
    sml_main = authors["sml_main"]
    net = their_net(authors, weights, min_pred=TEST_MIN_PRED, max_pred=TEST_MAX_PRED).eval()
    saved, scaffolds = [], []
    normalize = sml_main.utils.normalize_unit_range

    def record_scaffold(data: np.ndarray) -> np.ndarray:
        scaffolds.append(normalize(data))
        return scaffolds[-1]

    with tempfile.TemporaryDirectory() as folder:
        files = _frame_files(Path(folder), generator, TEST_SIZE, RCNET_SIZE, ZJU_ROWS)
        paths = files["paths"]
        with (
            _patched(sml_main.utils, normalize_unit_range=record_scaffold),
            _patched(
                sml_main.data_utils,
                save_depth=lambda z, path: saved.append(z.copy()),
                save_color_depth=lambda z, path: None,
            ),
            torch.no_grad(),
        ):
            sml_main.validate(
                image_paths=paths["image"],
                radar_paths=paths["radar"],
                gt_paths=paths["sparse_gt"],
                sparse_gt_paths=paths["sparse_gt"],
                rcnet_paths=paths["rcnet"],
                mono_ga_paths=paths["mono_ga"],
                best_results={
                    "mae": np.inf,
                    "rmse": np.inf,
                    "imae": np.inf,
                    "irmse": np.inf,
                    "abs_rel": np.inf,
                    "sq_rel": np.inf,
                    "delta1": 0,
                    "step": -1,
                },
                ScaleMapLearner=net,
                step=6000,
                min_radar_valid_depth=0.0,
                max_radar_valid_depth=80.0,
                min_eval_depth=0.0,
                max_eval_depth=80.0,
                output_path=folder,
                log_path=str(Path(folder) / "results.txt"),
                save_output=True,
            )
    (scaffold,) = scaffolds
    (depth,) = saved
    codes = files["codes"]
    return {
        "rcnet_png": torch.from_numpy(codes["rcnet"].astype(np.int32)),
        "mono_ga_png": torch.from_numpy(codes["mono_ga"].astype(np.int32)),
        "scaffold": torch.from_numpy(scaffold),
        "depth": torch.from_numpy(depth),
        **{k: net.forward.seen[k] for k in ("x", "d", "out", "pred")},
    }


def train_frame(authors: dict[str, Any], weights: Mapping, generator: np.random.Generator) -> dict:
    """Frame ``train`` (step 3): one step of their ``train`` with the recipe's settings."""
    sml_main = authors["sml_main"]
    nets, losses = [], []
    compute_loss = sml_main.compute_loss

    def build(**kwargs: Any) -> Any:
        nets.append(their_net(authors, weights, **kwargs))
        return nets[-1]

    def record_loss(**kwargs: Any) -> Any:
        loss, info = compute_loss(**kwargs)
        inputs = {k: v.detach().clone() for k, v in kwargs.items() if torch.is_tensor(v)}
        losses.append({"inputs": inputs, "loss": loss.detach().clone(), "info": dict(info)})
        return loss, info

    with tempfile.TemporaryDirectory() as folder:
        files = _frame_files(Path(folder), generator, TRAIN_SIZE, TRAIN_SIZE, (0, TRAIN_SIZE[0]))
        paths = files["paths"]
        with _patched(sml_main, MidasNet_small_videpth=build, compute_loss=record_loss):
            sml_main.train(
                train_image_paths=paths["image"],
                train_radar_paths=paths["radar"],
                train_gt_paths=paths["gt"],
                train_sparse_gt_paths=paths["sparse_gt"],
                train_rcnet_paths=paths["rcnet"],
                train_mono_ga_paths=paths["mono_ga"],
                learning_rates=[2e-4],
                learning_schedule=[1],
                batch_size=12,
                n_step_per_summary=10**9,
                n_step_per_checkpoint=10**9,
                loss_func="smoothl1",
                w_smoothness=0.0,
                w_weight_decay=0.0,
                loss_smoothness_kernel_size=-1,
                w_lidar_loss=3.0,
                ground_truth_outlier_removal_kernel_size=-1,
                ground_truth_outlier_removal_threshold=1.5,
                ground_truth_dilation_kernel_size=-1,
                restore_path="",
                min_pred_depth=TRAIN_MIN_PRED,
                max_pred_depth=TRAIN_MAX_PRED,
                min_radar_valid_depth=0.0,
                max_radar_valid_depth=80.0,
                checkpoint_dirpath=str(Path(folder) / "log"),
            )
        written = sorted(p.name for p in (Path(folder) / "log").glob("*.pth"))
        saved = torch.load(Path(folder) / "log" / written[0], weights_only=True)
    (net,) = nets
    (step,) = losses
    codes = files["codes"]
    inputs = step["inputs"]
    return {
        **{f"{k}_png": torch.from_numpy(codes[k].astype(np.int32)) for k in codes if k != "radar"},
        **{k: net.forward.seen[k] for k in ("x", "d", "out", "pred")},
        "gt": inputs["ground_truth"],
        "sparse_gt": inputs["lidar_map"],
        "output_depth": inputs["output_depth"],
        "loss": step["loss"],
        "loss_supervised": torch.as_tensor(step["info"]["loss_supervised"]).detach(),
        "loss_lidar": torch.as_tensor(step["info"]["loss_lidar"]).detach(),
        "written": {"files": written, "type": type(saved).__name__, "keys": len(saved)},
    }


def other_losses(authors: dict[str, Any], train: dict) -> dict[str, dict[str, float]]:
    """Their ``compute_loss`` on the training step's tensors with :data:`LOSS_SETTINGS`."""
    compute_loss = authors["loss"].compute_loss
    output = train["output_depth"]
    image = 1.0 / train["d"]  # sml_main.py line 229: the aligned depth is their "image"
    gt, lidar = train["gt"], train["sparse_gt"]
    values = {}
    for name, (func, w_smoothness, kernel, w_lidar) in LOSS_SETTINGS.items():
        loss, info = compute_loss(
            image=image,
            output_depth=output,
            ground_truth=gt,
            lidar_map=lidar,
            loss_func=func,
            w_smoothness=w_smoothness,
            loss_smoothness_kernel_size=kernel,
            validity_map_loss_smoothness=torch.where(gt > 0, 0.0, 1.0),
            w_lidar_loss=w_lidar,
        )
        values[name] = {k: float(v) for k, v in info.items()}
    return values


def _saver(saved: list) -> Any:
    """A ``data_utils.save_depth`` that keeps the map it is handed in ``saved``."""
    return lambda z, path: saved.append(z.copy())


def alignment_frames(authors: dict[str, Any], generator: np.random.Generator) -> dict:
    """``alignment`` (step 4): their ``process_scale`` on two frames."""
    module = authors["global_alignment"]
    frames = {}
    for name, points in (("fit", 0.05), ("singular", None)):
        saved = []
        with tempfile.TemporaryDirectory() as folder:
            root = Path(folder)
            relative = generator.uniform(0.5, 30.0, ALIGN_SIZE)
            radar = np.where(
                generator.random(ALIGN_SIZE) < (points or 0.0),
                1.3 * relative + generator.uniform(-3.0, 3.0, ALIGN_SIZE),
                0.0,
            )
            if points is None:
                radar[5, 7] = 30.0
            radar[0, :3] = (1.5, 80.0, 100.0)  # below, at and past the range: not used
            mono_codes = _write_png(root / "mono" / "frame.png", relative)
            radar_codes = _write_png(root / "radar" / "frame.png", radar)
            save = _saver(saved)
            with _patched(module.data_utils, save_depth=save):
                module.process_scale(
                    str(root / "radar"), str(root / "mono"), "frame.png", save_path=folder
                )
        frames[name] = {
            "mono_png": torch.from_numpy(mono_codes.astype(np.int32)),
            "radar_png": torch.from_numpy(radar_codes.astype(np.int32)),
            "aligned": torch.from_numpy(saved[0]),
        }
    return frames


def shipped_layout(authors: dict[str, Any]) -> dict[str, Any]:
    """Their ``MidasNet_small_videpth()`` as ``BaseModel.save`` writes it, read back with
    ``weights_only=True``: the file's type and the network's keys and shapes."""
    net = authors["net_module"].MidasNet_small_videpth()
    with tempfile.TemporaryDirectory() as folder:
        net.save(str(Path(folder) / "model-6000.pth"))
        loaded = torch.load(Path(folder) / "model-6000.pth", weights_only=True)
    return {
        "type": type(loaded).__name__,
        "network": {k: list(t.shape) for k, t in loaded.items()},
        "int64": sorted(k for k, t in loaded.items() if t.dtype == torch.int64),
    }


def git_commit(checkout: Path) -> str:
    """The checkout's commit; refuses one with local changes (a checkout without the .pth
    files, marked skip-worktree, counts as clean)."""
    done = subprocess.run(
        ["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    if done.returncode:
        sys.exit(f"{checkout}: not a git checkout of the authors' repository (git rev-parse)")
    dirty = subprocess.run(
        ["git", "-C", str(checkout), "status", "--porcelain", "--untracked-files=no"],
        capture_output=True,
        text=True,
    ).stdout.strip()
    if dirty:
        sys.exit(f"{checkout}: has local changes; the fixtures must come from a commit")
    return done.stdout.strip()


def _cpu() -> str:
    """The CPU's model name (Linux), which with the thread count decides how convs round."""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        return "unknown"
    names = [line.split(":", 1)[1].strip() for line in lines if line.startswith("model name")]
    return names[0] if names else "unknown"


def _versions() -> dict[str, str]:
    from importlib.metadata import version

    packages = ("torch", "numpy", "opencv-python-headless", "pillow", "scipy", "geffnet")
    return {name: version(name) for name in packages}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkout", type=Path, help="a git checkout of the authors' repository")
    parser.add_argument(
        "--out", type=Path, default=Path("tests/fixtures/scale_map_learner_authors")
    )
    args = parser.parse_args()
    commit = git_commit(args.checkout)
    out = args.out.resolve()
    authors = import_authors(args.checkout.resolve())
    layout = shipped_layout(authors)
    weights = fixture_weights(layout["network"])
    generator = np.random.default_rng(SEED)
    cases: dict[str, Any] = {"test": test_frame(authors, weights, generator)}
    cases["train"] = train_frame(authors, weights, generator)
    written = cases["train"].pop("written")
    cases["alignment"] = alignment_frames(authors, generator)
    losses = other_losses(authors, cases["train"])
    del cases["train"]["output_depth"]  # 1 / pred, as their loop computes it
    out.mkdir(parents=True, exist_ok=True)
    torch.save(cases, out / "cases.pt")
    made = {
        "authors_commit": commit,
        "made_by": "scripts/make_scale_map_learner_parity_fixtures.py",
    }
    shipped = {**made, "checkpoint": layout, "their_training_wrote": written}
    (out / "shipped_layout.json").write_text(json.dumps(shipped, separators=(",", ":")) + "\n")
    record = {
        **made,
        **_versions(),
        "threads": torch.get_num_threads(),
        "cpu": _cpu(),
        "seed": SEED,
        "weights_sha256": weights_digest(weights),
        "hub_calls": HUB_CALLS,
        "hub_substitute": "geffnet.<model>(pretrained=False, exportable=...) for torch.hub.load",
        "test_pred_bounds_m": [TEST_MIN_PRED, TEST_MAX_PRED],
        "train_pred_bounds_m": [TRAIN_MIN_PRED, TRAIN_MAX_PRED],
        "losses": {
            name: {"settings": list(LOSS_SETTINGS[name]), **value} for name, value in losses.items()
        },
    }
    (out / "fixtures.json").write_text(json.dumps(record, indent=1) + "\n")
    for name in ("test", "train"):
        out_ = cases[name]["out"]
        print(
            f"{name}: out {float(out_.mean()):.3g} ± {float(out_.std()):.3g}, "
            f"{float((out_ < -1).float().mean()):.0%} under -1"
        )
    print(f"train loss {float(cases['train']['loss']):.4g}; other losses {losses}")


if __name__ == "__main__":
    main()
