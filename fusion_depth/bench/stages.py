"""Measuring how fast a configuration trains and infers, and this machine's limit.

The stages of ``python -m fusion_depth.bench``, each a function that measures one thing on a
composed training config (``conf/train.yaml``), and :func:`run_bench`, which runs the ones asked
for and gathers the result that ``--json`` writes:

* :func:`bench_inference`: batch-1 latency of depth in metres from an image (median and p95 over
  timed runs after warm-up); :func:`count_flops` gives the FLOPs of that forward pass
  (``torch.utils.flop_counter``) and so the GFLOP/s achieved;
* :func:`bench_training`: samples/s over full optimizer steps (forward, the real loss, backward,
  Adam) at ``data.batch_size``;
* :func:`bench_data`: the input pipeline without a model: samples/s per DataLoader worker
  (reading and collating samples as stored: uint8 images, uint16 depth maps), the conversion to
  floats and the training augmentation on the device (where training runs them, after the
  transfer), and both together;
* :func:`matmul_peak_gflops`: the matrix-product GFLOP/s of this device in the precision's dtype,
  the ceiling the model's GFLOP/s are compared with, and so the FLOP floor of a frame (its
  FLOPs at that peak), the latency no engine can beat at that precision;
* :func:`bench_prepare`: seconds per frame of each ground-truth fill method on a generated lidar
  frame, and the hours that makes for the named splits (:data:`NAMED_SPLITS`) on N cores;
* :func:`bench_engine`: batch-1 latency of the network exported by
  :func:`~fusion_depth.export.export_model` and run by its engine
  (:data:`BENCH_ENGINES`: ONNX Runtime, OpenVINO bf16/fp32 and int8, TensorRT), against the
  PyTorch path of :func:`bench_inference` (``torch``, the reference).

Times are wall seconds (:func:`time_calls`, synchronising the GPU), memory the stage's peak in
MB (:class:`PeakMemory`).
"""

from __future__ import annotations

import copy
import json
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from hydra.utils import instantiate
from lightning.fabric.utilities.apply_func import move_data_to_device
from omegaconf import DictConfig
from torch.utils.data import DataLoader
from torch.utils.flop_counter import FlopCounterMode

from fusion_depth.config.dataset_validation import check_dataset
from fusion_depth.data.cache import PreparedSplit, usable_cores
from fusion_depth.data.depth_io import DEPTH_PNG_SCALE
from fusion_depth.data.encoding import decode_sample
from fusion_depth.data.filling import colorization_reference, fill_depth
from fusion_depth.data.procedural import render_frame
from fusion_depth.export import (
    BACKENDS,
    ENGINES,
    check_export_options,
    export_model,
    load_exported,
    sidecar_path,
)
from fusion_depth.models.inference import predict_depth
from fusion_depth.runner.datamodule import DepthDataModule
from fusion_depth.runner.module import DepthModule, module_from_config
from fusion_depth.runner.run_folder import provenance
from fusion_depth.runner.speed import (
    accelerator_device,
    autocast,
    machine_info,
    resolve_precision,
    should_compile,
    speed_up,
)

STAGES = ("peak", "infer", "train", "data", "prepare")
# What a plain ``bench`` runs: ``prepare`` times ground-truth filling, not the network.
DEFAULT_STAGES = ("peak", "infer", "train", "data")
CPU = torch.device("cpu")


@dataclass(frozen=True)
class BenchEngine:
    """An engine ``bench --engines`` can time: the bench network exported to ``format`` with
    the export ``options`` (``format`` None: PyTorch itself, the reference)."""

    name: str
    format: str | None
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def key(self) -> str:
        """The name in the result's top-level keys: ``openvino-int8`` → ``openvino_int8``."""
        return self.name.replace("-", "_")


# The engines of ``bench --engines``, by name. What is timed is what users deploy: the file
# export_model writes, run by its engine from the runtime's table (ENGINES). INT8 calibrates
# on synthetic frames: the bench network has random weights, so latency, not accuracy, is
# measured there.
BENCH_ENGINES: dict[str, BenchEngine] = {
    engine.name: engine
    for engine in (
        BenchEngine("torch", None),
        BenchEngine("onnxruntime", "onnx"),
        BenchEngine("openvino", "openvino", {"precision": "auto"}),
        BenchEngine("openvino-int8", "openvino", {"precision": "auto", "quantize": "int8"}),
        BenchEngine("tensorrt", "tensorrt", {"precision": "fp16"}),
    )
}
CALIBRATION_FRAMES = 8  # synthetic frames an int8 engine calibrates on
# Top-level keys of every result, for scripts comparing runs (with --baseline also
# baseline_infer_latency_s_median, baseline_train_samples_per_s and the speed-ups).
SUMMARY_KEYS = (
    "infer_latency_s_median",
    "infer_latency_s_p95",
    "train_samples_per_s",
    "data_samples_per_s_per_worker",
    "peak_memory_mb",
    "achieved_gflops",
    "peak_gflops",
)
_MATMUL_DTYPES = {"32-true": torch.float32, "bf16-mixed": torch.bfloat16, "16-mixed": torch.float16}


class PeakMemory:
    """Peak memory of one stage: GPU max allocated, or the process's peak resident set (Linux
    resets it through ``/proc/self/clear_refs``; elsewhere it is the process's lifetime peak)."""

    def __init__(self, device: torch.device) -> None:
        self.device = device

    def reset(self) -> None:
        if self.device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(self.device)
            return
        try:
            Path("/proc/self/clear_refs").write_text("5")
        except OSError:
            pass

    def read_mb(self) -> float:
        if self.device.type == "cuda":
            return torch.cuda.max_memory_allocated(self.device) / 2**20
        try:
            for line in Path("/proc/self/status").read_text().splitlines():
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
        except OSError:
            pass
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_calls(fn: Callable[[], Any], device: torch.device, warmup: int, runs: int) -> list[float]:
    """Wall seconds of ``runs`` calls of ``fn`` after ``warmup`` untimed ones."""
    for _ in range(warmup):
        fn()
    _synchronize(device)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        _synchronize(device)
        times.append(time.perf_counter() - start)
    return times


def count_flops(fn: Callable[[], Any]) -> int:
    """FLOPs of one call of ``fn`` (multiply-adds count two), from the operators it runs."""
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return int(counter.get_total_flops())


def matmul_peak_gflops(
    precision: str, device: torch.device, size: int | None = None, runs: int = 5
) -> float:
    """The best GFLOP/s of a square matrix product in the precision's compute dtype: what a
    convolution network can at most reach on this device."""
    dtype = _MATMUL_DTYPES[precision]
    size = size or (8192 if device.type == "cuda" else 2048)
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(size, size, generator=generator).to(device, dtype)
    b = torch.randn(size, size, generator=generator).to(device, dtype)
    times = time_calls(lambda: torch.mm(a, b), device, warmup=2, runs=runs)
    return 2 * size**3 / min(times) / 1e9


def synthetic_batch(
    cfg: DictConfig, batch_size: int, device: torch.device, seed: int = 0
) -> dict[str, torch.Tensor]:
    """A batch shaped like the dataset's: image in [0, 1], ~2 % sparse returns, dense depth."""
    generator = torch.Generator().manual_seed(seed)
    height, width = cfg.dataset.height, cfg.dataset.width
    low, high = float(cfg.dataset.min_depth), float(cfg.dataset.max_depth)
    shape = (batch_size, 1, height, width)
    depth = low + (high - low) * torch.rand(shape, generator=generator)
    returns = torch.rand(shape, generator=generator) < 0.02
    return {
        "image": torch.rand((batch_size, 3, height, width), generator=generator).to(device),
        "sparse": torch.where(returns, depth, torch.zeros_like(depth)).to(device),
        "depth": depth.to(device),
    }


def _percentile(times: Sequence[float], q: float) -> float:
    return float(np.percentile(np.asarray(times), q))


def bench_inference(
    net: torch.nn.Module,
    cfg: DictConfig,
    device: torch.device,
    precision: str,
    warmup: int,
    runs: int,
    memory: PeakMemory,
) -> dict[str, float]:
    """Batch-1 latency of :func:`predict_depth` (depth in metres at the input size). For a
    network with a frozen prior (``prior=``) also the prior's latency alone and the network's on
    top of a given prior (``prior_latency_s_median``, ``head_latency_s_median``): a foundation
    prior comes trained and may run elsewhere, so the two are read apart."""
    batch = synthetic_batch(cfg, 1, device)
    net.eval()

    def infer(**given: torch.Tensor) -> torch.Tensor:
        with torch.inference_mode(), autocast(precision, device):
            return predict_depth(net, batch["image"], batch["sparse"], **given)

    memory.reset()
    times = time_calls(infer, device, warmup, runs)
    out = {
        "latency_s_median": _percentile(times, 50),
        "latency_s_p95": _percentile(times, 95),
        "runs": runs,
        "peak_memory_mb": memory.read_mb(),
    }
    prior = getattr(net, "prior", None)
    if prior is not None:

        def run_prior() -> torch.Tensor:
            with torch.inference_mode(), autocast(precision, device):
                return prior(batch["image"])

        out["prior_latency_s_median"] = _percentile(time_calls(run_prior, device, warmup, runs), 50)
        given = run_prior().float()
        head = time_calls(lambda: infer(prior=given), device, warmup, runs)
        out["head_latency_s_median"] = _percentile(head, 50)
    return out


def bench_training(
    module: DepthModule,
    cfg: DictConfig,
    device: torch.device,
    precision: str,
    warmup: int,
    steps: int,
    memory: PeakMemory,
) -> dict[str, float]:
    """Samples/s over full optimizer steps with the run's loss and optimizer."""
    batch_size = int(cfg.data.batch_size)
    batch = synthetic_batch(cfg, batch_size, device)
    module.train()
    optimizer = module.build_optimizer()
    scaler = torch.amp.GradScaler(device.type, enabled=precision == "16-mixed")

    def step() -> None:
        with autocast(precision, device):
            loss = module.step_losses(batch)["loss"]
        scaler.scale(loss).backward()
        scaler.step(optimizer)
        scaler.update()
        optimizer.zero_grad(set_to_none=True)

    memory.reset()
    times = time_calls(step, device, warmup, steps)
    return {
        "samples_per_s": batch_size / float(np.median(times)),
        "step_s_median": float(np.median(times)),
        "batch_size": batch_size,
        "steps": steps,
        "peak_memory_mb": memory.read_mb(),
    }


def _timed_batches(
    loader: DataLoader, batches: int, device: torch.device, work: Callable[[dict], Any]
) -> float:
    """Seconds for ``batches`` batches of ``loader`` moved to ``device`` and given to ``work``,
    the first batch (worker start-up) not counted; the loader is cycled if it is shorter."""
    seen, start = -1, 0.0
    while seen < batches:
        for batch in loader:
            work(move_data_to_device(batch, device))
            if seen < 0:
                _synchronize(device)
                start = time.perf_counter()
            seen += 1
            if seen == batches:
                break
    _synchronize(device)
    return time.perf_counter() - start


def bench_data(
    cfg: DictConfig, device: torch.device, workers: int, batches: int, split: str
) -> dict[str, float]:
    """The input pipeline without a model. Workers read samples in their encoded form (uint8
    image, uint16 depth maps) and collate them; on ``device`` the batch is converted to floats
    (:func:`~fusion_depth.data.encoding.decode_sample`) and augmented, as in training, where
    both run after the transfer. Timed: the loader alone (per worker: the total divided by
    ``max(workers, 1)``), the conversion and augmentation alone (``augment_samples_per_s``),
    and everything in one loop."""
    datamodule = DepthDataModule(
        reader=instantiate(cfg.dataset.reader),
        num_workers=workers,
        pin_memory=device.type == "cuda",
    )
    augment = instantiate(cfg.model.augmentation).to(device)

    def augmentation(batch: dict) -> dict:
        return augment(decode_sample(batch))

    batch_size = int(cfg.data.batch_size)
    loader = datamodule.loader(split, shuffle=True, batch_size=batch_size)
    if len(loader) == 0:
        raise ValueError(
            f"data: split {split!r} has {len(datamodule.dataset(split))} samples, fewer than "
            f"data.batch_size={batch_size}"
        )
    samples = batches * batch_size
    loading = samples / _timed_batches(loader, batches, device, lambda batch: None)
    pipeline = samples / _timed_batches(loader, batches, device, augmentation)
    batch = move_data_to_device(next(iter(loader)), device)
    times = time_calls(lambda: augmentation(batch), device, warmup=1, runs=batches)
    return {
        "samples_per_s_per_worker": loading / max(workers, 1),
        "loader_samples_per_s": loading,
        "augment_samples_per_s": batch_size / float(np.median(times)),
        "pipeline_samples_per_s": pipeline,
        "workers": workers,
        "batches": batches,
        "split": split,
        "dataset": str(cfg.dataset.name),
        "augment_device": str(device),
    }


def check_engines(engines: Sequence[str], device: torch.device) -> list[BenchEngine]:
    """The engines of ``--engines`` (``torch`` first, always: it is the reference), checked
    before anything is timed.

    Raises:
        ValueError: an unknown name, or ``tensorrt`` on a device that is not a CUDA GPU.
        ImportError: a package (or the GPU) an engine needs is missing (one line naming it).
    """
    unknown = [name for name in engines if name not in BENCH_ENGINES]
    if unknown:
        raise ValueError(
            f"--engines {','.join(unknown)}: expected some of {','.join(BENCH_ENGINES)}"
        )
    chosen = [BENCH_ENGINES["torch"]]
    chosen += [BENCH_ENGINES[name] for name in dict.fromkeys(engines) if name != "torch"]
    for engine in chosen[1:]:
        backend = BACKENDS[engine.format]
        ENGINES[backend.engine].require()
        check_export_options(engine.format, None, None, None, True, **engine.options)
        if backend.engine == "tensorrt" and device.type != "cuda":
            raise ValueError(
                f"--engines {engine.name}: times a GPU engine against PyTorch on the same GPU, "
                f"but this benchmark runs on {device}; pass trainer.accelerator=gpu"
            )
    return chosen


def bench_engine(
    engine: BenchEngine,
    net: torch.nn.Module,
    cfg: DictConfig,
    device: torch.device,
    warmup: int,
    runs: int,
    memory: PeakMemory,
) -> dict[str, Any]:
    """Batch-1 latency of ``net`` exported by :func:`export_model` as ``engine`` asks (into a
    temporary folder, verified against PyTorch as every export is) and loaded by its engine
    (:func:`~fusion_depth.export.load_exported`), timed as :func:`bench_inference` times
    PyTorch: the same call on the same synthetic frame. An int8 engine calibrates on
    :data:`CALIBRATION_FRAMES` synthetic frames."""
    height, width = int(cfg.dataset.height), int(cfg.dataset.width)
    backend = BACKENDS[engine.format]
    options = dict(engine.options)
    if options.get("quantize"):
        frames = [
            synthetic_batch(cfg, 1, torch.device("cpu"), seed=1 + i)
            for i in range(CALIBRATION_FRAMES)
        ]
        names = ["image", "sparse"] if net.fusion.uses_sparse else ["image"]
        options["calibration"] = [tuple(frame[name] for name in names) for frame in frames]
    with tempfile.TemporaryDirectory() as folder:
        start = time.perf_counter()
        path = export_model(
            net,
            engine.format,
            Path(folder) / f"model{backend.suffix}",
            height,
            width,
            measure_accuracy=False,
            **options,
        )
        export_s = time.perf_counter() - start
        verified = json.loads(sidecar_path(path).read_text())["verified"]
        exported = load_exported(path).net
        timed = bench_inference(exported, cfg, device, "32-true", warmup, runs, memory)
    return {
        **timed,
        "format": engine.format,
        "computes": exported.runner.computes,
        "runtime": exported.runner.description,
        "export_s": export_s,
        "verified_max_rel_diff": verified["max_rel_diff"],
        "verified_mean_rel_diff": verified["mean_rel_diff"],
    }


def build_module(cfg: DictConfig, device: torch.device) -> DepthModule:
    """The run's LightningModule (random weights: speed does not depend on them)."""
    cfg = copy.deepcopy(cfg)
    cfg.backbone.pretrained = False
    cfg.backbone.weights = None
    torch.manual_seed(int(cfg.seed))
    return module_from_config(cfg).to(device)


def run_bench(
    cfg: DictConfig,
    stages: Sequence[str] = STAGES,
    baseline: bool = False,
    engines: Sequence[str] = ("torch",),
    warmup: int = 3,
    runs: int = 20,
    train_steps: int = 10,
    data_workers: int = 1,
    data_batches: int = 100,
    data_split: str = "train",
    prepare_cores: int | None = None,
    prepared: str | Path | None = None,
    prepare_frames: int = 3,
) -> dict[str, Any]:
    """Every requested stage for the config; the result is what ``--json`` writes.

    ``prepare`` (:func:`bench_prepare`) fills a generated lidar frame at ``dataset.height x
    dataset.width``, or the first ``prepare_frames`` frames of the ``prepared`` split folder,
    with each method and estimates hours for the named splits on ``prepare_cores`` workers
    (default: every core this process may use).

    ``engines`` (:data:`BENCH_ENGINES`) other than ``torch`` are timed in the infer stage after
    PyTorch, each as ``engines[<name>]`` and the top-level ``<key>_infer_latency_s_median`` and
    ``<key>_speedup`` (PyTorch's latency over the engine's; ``<key>`` is the name with ``-`` as
    ``_``), with ``latency_over_floor``: the latency over the frame's FLOP floor
    (``infer_floor_s``, its FLOPs at the ``peak`` stage's matrix-product GFLOP/s).
    """
    device, chosen = _check_request(cfg, stages, engines)
    if prepared is not None and "prepare" in stages:
        PreparedSplit(Path(prepared).expanduser())  # a wrong folder fails before any stage runs
    precision = resolve_precision(cfg.trainer.precision, device)
    compiled = should_compile(cfg.model.compile, device)
    memory = PeakMemory(device)
    settings = _settings(cfg, device, precision, compiled, warmup, runs, train_steps)
    result: dict[str, Any] = {
        "settings": settings,
        "machine": machine_info(device),
        "versions": provenance(),
    }
    result.update(dict.fromkeys(SUMMARY_KEYS))  # None where a stage was not run
    if "peak" in stages:
        result["peak_gflops"] = matmul_peak_gflops(precision, device)
        if baseline:
            result["baseline_peak_gflops"] = matmul_peak_gflops("32-true", device)
    if "infer" in stages or "train" in stages:
        _bench_model(result, cfg, stages, chosen, baseline, device, settings, memory)
    if "data" in stages:
        data = bench_data(cfg, device, data_workers, data_batches, data_split)
        result["data"] = data
        result["data_samples_per_s_per_worker"] = data["samples_per_s_per_worker"]
    if "prepare" in stages:
        height, width = int(cfg.dataset.height), int(cfg.dataset.width)
        result["prepare"] = bench_prepare(
            height,
            width,
            prepare_cores or usable_cores(),
            prepared=prepared,
            frames=prepare_frames,
        )
    return result


# Frames of the splits people prepare, for ``--only prepare``'s estimates: nuScenes v1.0-trainval
# keyframes of the train and val scenes (Caesar et al., CVPR 2020: 28,130 and 6,019), and the
# KITTI depth-completion train and val sets, both cameras (Uhrig et al., 3DV 2017: 85,898 and
# 6,852).
NAMED_SPLITS: dict[str, int] = {
    "nuscenes train": 28_130,
    "nuscenes val": 6_019,
    "kitti-dc train": 85_898,
    "kitti-dc val": 6_852,
}


def generated_lidar_frame(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """A street frame of the built-in generator at ``height x width`` with its lidar map
    (image uint8 (H, W, 3), sparse float32 (H, W) metres, 0 = no return): what ``--only
    prepare`` fills when it has no data of the user's."""
    image, _, sparse = render_frame(0, "train", 0, height, width, 82.0, "day", "lidar")
    return image, sparse


def prepared_frames(split_dir: str | Path, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The first ``count`` frames of a prepared split as ``fill_depth`` gets them when the split
    is prepared: image uint8 (H, W, 3) and measured depth float32 (H, W) metres, 0 = none, cut
    to the frame's own pixels where the cache padded it (its ``frame_box``). ``--only prepare
    --prepared`` times the fill on these, so the estimate is for the user's own frames.

    Raises:
        FileNotFoundError: ``split_dir`` holds no prepared split (no ``index.json``).
        DataFileError: a damaged file of the split, naming it.
    """
    split = PreparedSplit(Path(split_dir).expanduser())
    frames = []
    for index in range(min(count, len(split))):
        sample = split.encoded_sample(index)
        image = sample["image"].permute(1, 2, 0).numpy()
        depth = sample["depth"][0].numpy().astype(np.float32) / DEPTH_PNG_SCALE
        if "frame_box" in sample:  # (top, left, height, width) of the frame in the sample
            top, left, frame_h, frame_w = (int(v) for v in sample["frame_box"])
            rows = slice(max(top, 0), min(top + frame_h, depth.shape[0]))
            cols = slice(max(left, 0), min(left + frame_w, depth.shape[1]))
            image, depth = image[rows, cols], depth[rows, cols]
        frames.append((np.ascontiguousarray(image), depth))
    return frames


def _against_spsolve(
    image: np.ndarray, depth: np.ndarray, ours: np.ndarray, ours_s: float
) -> dict[str, Any]:
    """SciPy's default solve of the colorization system of ``depth`` (a frame with a measured
    pixel) against the solver's fill ``ours``, which took ``ours_s`` seconds: its seconds, the
    speed-up and the largest difference in metres, on this machine, not on the one the docs
    name."""
    # SciPy's imports, untimed, on a patch holding a measured pixel (a frame's corner is often
    # sky, which fills at once); SuperLU keeps nothing from one solve to the next.
    row, col = (int(v) for v in np.argwhere(depth > 0)[0])
    patch = np.s_[max(row - 16, 0) : row + 16, max(col - 16, 0) : col + 16]
    colorization_reference(depth[patch], image[patch])
    reference: list[np.ndarray] = []
    spsolve_s = time_calls(
        lambda: reference.append(colorization_reference(depth, image)), CPU, 0, 1
    )[0]
    return {
        "s_per_frame": spsolve_s,
        "speedup": spsolve_s / ours_s if ours_s > 0 else None,
        "max_difference_m": float(np.abs(ours - reference[0]).max()),
    }


def bench_prepare(
    height: int,
    width: int,
    cores: int,
    methods: Sequence[str] = ("none", "linear", "colorization"),  # linear_hull costs as linear
    runs: int = 1,
    prepared: str | Path | None = None,
    frames: int = 3,
) -> dict[str, Any]:
    """Seconds per frame of each ground-truth fill method (:func:`fill_depth`, the cost that
    dominates preparing a frame), one worker; frames per second per worker; and the hours each
    of :data:`NAMED_SPLITS` takes to fill on ``cores`` workers (``prepare.workers``), assuming
    the frames divide evenly.

    The frames are the first ``frames`` of the ``prepared`` split folder
    (:func:`prepared_frames`: the user's data, filled as prepare fills it; each timed once, the
    median kept), or else one generated ``height x width`` lidar frame timed ``runs`` times.
    Each method first fills the first frame once, untimed, as a prepare worker has after its
    first frame of a size. The colorization row also holds SciPy's ``spsolve`` of the first
    frame's system (:func:`colorization_reference`, timed once after its imports): its seconds,
    the speed-up and the largest difference between the two fills.

    Raises:
        FileNotFoundError, DataFileError: ``prepared`` is not a readable prepared split.
        ValueError: ``prepared`` has no frame.
    """
    if prepared is None:
        image, sparse = generated_lidar_frame(height, width)
        inputs, source = [(image, sparse)] * runs, "generated"
    else:
        inputs, source = prepared_frames(prepared, frames), str(prepared)
        if not inputs:
            raise ValueError(f"--prepared {prepared}: the split has no frame to time")
        height, width = inputs[0][1].shape
    methods_out: dict[str, Any] = {}
    image, depth = inputs[0]
    first: dict[str, tuple[np.ndarray, float]] = {}  # each method's fill of the first frame
    for method in methods:
        # One untimed fill of the first frame: the solver's imports, its plan for this frame
        # size and its first use of memory, which a prepare pays once per worker and size.
        fill_depth(depth, image, method)
        filled: list[np.ndarray] = []
        seconds = [
            time_calls(
                lambda m=method, i=i, d=d, out=filled: out.append(fill_depth(d, i, m)), CPU, 0, 1
            )[0]
            for i, d in inputs
        ]
        first[method] = filled[0], seconds[0]
        per_frame = float(np.median(seconds))
        methods_out[method] = {
            "s_per_frame": per_frame,
            "frames_per_s_per_worker": 1.0 / per_frame if per_frame > 0 else None,
            "hours": {
                split: frames * per_frame / cores / 3600 for split, frames in NAMED_SPLITS.items()
            },
        }
    if "colorization" in first and (depth > 0).any():
        ours, ours_s = first["colorization"]
        methods_out["colorization"]["spsolve"] = _against_spsolve(image, depth, ours, ours_s)
    return {
        "source": source,
        "frames": len(inputs) if prepared is not None else 1,
        "height": height,
        "width": width,
        "measured_fraction": float(np.mean([(d > 0).mean() for _, d in inputs])),
        "cores": cores,
        "methods": methods_out,
    }


def _check_request(
    cfg: DictConfig, stages: Sequence[str], engines: Sequence[str]
) -> tuple[torch.device, list[BenchEngine]]:
    """The device and the checked engines of a bench request, refused before anything runs."""
    unknown = sorted(set(stages) - set(STAGES))
    if unknown:
        raise ValueError(f"--only {','.join(unknown)}: expected some of {list(STAGES)}")
    check_dataset(cfg.dataset, cfg.fusion.mode)
    device = accelerator_device(cfg.trainer.accelerator)
    chosen = check_engines(engines, device)
    if len(chosen) > 1 and "infer" not in stages:
        raise ValueError(
            f"--engines {','.join(e.name for e in chosen[1:])}: times batch-1 inference, "
            "which --only leaves out; add infer"
        )
    return device, chosen


def _settings(
    cfg: DictConfig,
    device: torch.device,
    precision: str,
    compiled: bool,
    warmup: int,
    runs: int,
    train_steps: int,
) -> dict[str, Any]:
    """The result's ``settings``: what was measured, and how; the stages read them from here."""
    return {
        "backbone": str(cfg.backbone.name),
        "fusion": str(cfg.fusion.mode),
        "height": int(cfg.dataset.height),
        "width": int(cfg.dataset.width),
        "batch_size": int(cfg.data.batch_size),
        "precision": precision,
        "channels_last": bool(cfg.model.channels_last),
        "compile": compiled,
        "compile_mode": str(cfg.model.compile_mode) if compiled else None,
        "cudnn_benchmark": bool(cfg.trainer.get("benchmark")),
        "device": str(device),
        "warmup": warmup,
        "runs": runs,
        "train_steps": train_steps,
    }


def _bench_model(
    result: dict[str, Any],
    cfg: DictConfig,
    stages: Sequence[str],
    chosen: Sequence[BenchEngine],
    baseline: bool,
    device: torch.device,
    settings: dict[str, Any],
    memory: PeakMemory,
) -> None:
    """The infer and train stages asked for, on one module built for both, into ``result``."""
    module = build_module(cfg, device)
    # FLOPs of the eager network, before compilation hides its operators from the counter.
    if "infer" in stages:
        infer_flops = _infer_flops(module.net, cfg, device)
        result["infer_gflop_per_frame"] = infer_flops / 1e9
    if "train" in stages:
        train_flops = _train_flops(module, cfg, device)
        result["train_gflop_per_step"] = train_flops / 1e9
    reference = copy.deepcopy(module) if baseline else None
    # The eager network the engines export (before channels-last and compilation).
    to_export = copy.deepcopy(module.net).cpu() if len(chosen) > 1 else None
    channels_last, compiled = settings["channels_last"], settings["compile"]
    speed_up(module.net, channels_last, compiled, device, cfg.model.compile_mode)
    if "infer" in stages:
        _bench_infer(result, module, reference, infer_flops, cfg, device, settings, memory)
        _bench_engines(result, chosen, to_export, cfg, device, settings, memory)
    if "train" in stages:
        _bench_train(result, module, reference, train_flops, cfg, device, settings, memory)
    peaks = [result.get(k, {}).get("peak_memory_mb") for k in ("infer", "train")]
    result["peak_memory_mb"] = max((p for p in peaks if p is not None), default=None)


def _infer_flops(net: torch.nn.Module, cfg: DictConfig, device: torch.device) -> int:
    """FLOPs of a batch-1 :func:`predict_depth` of ``net`` (left in eval mode)."""
    batch = synthetic_batch(cfg, 1, device)
    with torch.no_grad():
        net.eval()
        return count_flops(lambda: predict_depth(net, **_inputs(batch)))


def _train_flops(module: DepthModule, cfg: DictConfig, device: torch.device) -> int:
    """FLOPs of a training step's loss and backward at ``data.batch_size`` (gradients cleared)."""
    batch = synthetic_batch(cfg, int(cfg.data.batch_size), device)
    module.train()
    flops = count_flops(lambda: module.step_losses(batch)["loss"].backward())
    module.zero_grad(set_to_none=True)
    return flops


def _bench_infer(
    result: dict[str, Any],
    module: DepthModule,
    reference: DepthModule | None,
    flops: int,
    cfg: DictConfig,
    device: torch.device,
    settings: dict[str, Any],
    memory: PeakMemory,
) -> None:
    """The infer stage's PyTorch latency (and the fp32 ``reference``'s), into ``result``."""
    warmup, runs = settings["warmup"], settings["runs"]
    torch.backends.cudnn.benchmark = settings["cudnn_benchmark"]
    infer = bench_inference(module.net, cfg, device, settings["precision"], warmup, runs, memory)
    result["infer"] = infer
    result["infer_latency_s_median"] = infer["latency_s_median"]
    result["infer_latency_s_p95"] = infer["latency_s_p95"]
    result["achieved_gflops"] = flops / infer["latency_s_median"] / 1e9
    if reference is not None:
        # The baseline is PyTorch's defaults: fp32, no cuDNN autotuning.
        torch.backends.cudnn.benchmark = False
        base = bench_inference(reference.net, cfg, device, "32-true", warmup, runs, memory)
        result["baseline_infer"] = base
        result["baseline_infer_latency_s_median"] = base["latency_s_median"]
        result["baseline_infer_latency_s_p95"] = base["latency_s_p95"]
        result["infer_speedup"] = base["latency_s_median"] / infer["latency_s_median"]


def _bench_engines(
    result: dict[str, Any],
    chosen: Sequence[BenchEngine],
    net: torch.nn.Module | None,
    cfg: DictConfig,
    device: torch.device,
    settings: dict[str, Any],
    memory: PeakMemory,
) -> None:
    """``result["engines"]``: PyTorch's latency, then each other engine's on ``net`` exported."""
    computes = settings["precision"] + (", channels-last" if settings["channels_last"] else "")
    result["engines"] = {"torch": {**result["infer"], "computes": computes}}
    for engine in chosen[1:]:
        result["engines"][engine.name] = bench_engine(
            engine, net, cfg, device, settings["warmup"], settings["runs"], memory
        )
    _engine_summary(result, chosen)


def _bench_train(
    result: dict[str, Any],
    module: DepthModule,
    reference: DepthModule | None,
    flops: int,
    cfg: DictConfig,
    device: torch.device,
    settings: dict[str, Any],
    memory: PeakMemory,
) -> None:
    """The train stage's samples/s (and the fp32 ``reference``'s), into ``result``."""
    warmup, steps = settings["warmup"], settings["train_steps"]
    torch.backends.cudnn.benchmark = settings["cudnn_benchmark"]
    train = bench_training(module, cfg, device, settings["precision"], warmup, steps, memory)
    result["train"] = train
    result["train_samples_per_s"] = train["samples_per_s"]
    result["train_achieved_gflops"] = flops / train["step_s_median"] / 1e9
    if reference is not None:
        # The baseline is PyTorch's defaults: fp32, no cuDNN autotuning.
        torch.backends.cudnn.benchmark = False
        base = bench_training(reference, cfg, device, "32-true", warmup, steps, memory)
        result["baseline_train"] = base
        result["baseline_train_samples_per_s"] = base["samples_per_s"]
        result["train_speedup"] = train["samples_per_s"] / base["samples_per_s"]


def _engine_summary(result: dict[str, Any], chosen: Sequence[BenchEngine]) -> None:
    """Each engine's speed-up over PyTorch (``torch``) and latency over the FLOP floor, into
    ``result["engines"][<name>]`` and the top-level ``<key>_...`` keys."""
    peak = result.get("peak_gflops")
    floor = result["infer_gflop_per_frame"] / peak if peak else None
    result["infer_floor_s"] = floor
    for engine in chosen:
        entry = result["engines"][engine.name]
        latency = entry["latency_s_median"]
        entry["speedup"] = result["infer_latency_s_median"] / latency
        entry["latency_over_floor"] = latency / floor if floor else None
        result[f"{engine.key}_infer_latency_s_median"] = latency
        result[f"{engine.key}_speedup"] = entry["speedup"]


def _inputs(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    return {"image": batch["image"], "sparse": batch["sparse"]}
