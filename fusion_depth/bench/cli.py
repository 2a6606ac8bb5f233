"""How fast a configuration trains and infers here, and how far that is from this machine's limit.

python -m fusion_depth.bench dataset.height=384 dataset.width=1248 --baseline --json bench.json
python -m fusion_depth.bench backbone=resnet50 fusion=concat trainer.precision=32-true
python -m fusion_depth.bench --only peak,infer --engines torch,onnxruntime,openvino,openvino-int8
python -m fusion_depth.bench --only prepare dataset.height=448 dataset.width=800 --cores 32
python -m fusion_depth.bench --only prepare --prepared ~/.cache/fusion_depth/kitti/<hash>/val

Positional arguments are Hydra overrides of the training config (``conf/train.yaml``), so the
benchmark times exactly what ``fusion_depth.train`` would run: backbone, fusion, resolution
(``dataset.height``/``width``), batch size (``data.batch_size``), precision
(``trainer.precision``), device (``trainer.accelerator``), ``model.channels_last`` and
``model.compile``. Stages:

* ``infer``: batch-1 latency of depth in metres from an image (median and p95 over timed runs
  after warm-up), the FLOPs of that forward pass (``torch.utils.flop_counter``) and the GFLOP/s
  achieved;
* ``train``: samples/s over full optimizer steps (forward, the real loss, backward, Adam) at
  ``data.batch_size``;
* ``data``: the input pipeline without a model: samples/s per DataLoader worker (reading,
  collating the uint8/uint16 samples), the conversion to floats and the training augmentation
  on the device (where training runs them, after the transfer), and both together;
* ``prepare`` (only when asked for): seconds per frame of each ground-truth fill method on a
  generated lidar frame at ``dataset.height x dataset.width``, or on the first ``--frames`` frames
  of a ``--prepared`` split folder (your own data), frames/s per worker, and the hours that makes
  for nuScenes' and KITTI's train and val splits on ``--cores`` workers;
* ``peak``: the matrix-product GFLOP/s of this device in the precision's dtype, the ceiling the
  model's GFLOP/s are compared with.

``--baseline`` times the same network in eager fp32 with contiguous memory in the same process
and prints the speed-up ratios: quote those, not absolute times from a shared machine.
``--engines`` also times the network exported to deployment engines (``onnxruntime``,
``openvino``, ``openvino-int8``, ``tensorrt``; ``torch``, the PyTorch path above, is the
reference and always timed): each is exported by ``export_model`` into a temporary folder,
verified, loaded by its engine and timed like PyTorch, and printed with its latency over the
frame's FLOP floor (its FLOPs at the ``peak`` stage's matrix-product GFLOP/s) and its speed-up
over PyTorch. The measuring functions are :mod:`fusion_depth.bench.stages`.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.errors import HydraException
from omegaconf import DictConfig

from fusion_depth.bench.stages import BENCH_ENGINES, DEFAULT_STAGES, STAGES, run_bench
from fusion_depth.config import CONF_DIR
from fusion_depth.config.arguments import argument_error, config_message
from fusion_depth.config.hydra_main import unknown_key_message
from fusion_depth.errors import ConfigError
from fusion_depth.runner.bench_record import (
    ENGINE_HEADER,
    SPEED_HEADER,
    engine_rows,
    floor_note,
    prepare_table,
    settings_line,
    speed_notes,
    speed_rows,
    spsolve_note,
)
from fusion_depth.utils.atomic import write_json_atomic
from fusion_depth.utils.console import quiet_known_noise
from fusion_depth.utils.tables import format_table

quiet_known_noise()


def compose_train_config(overrides: Sequence[str]) -> DictConfig:
    """``conf/train.yaml`` with ``overrides``; errors name the offending override (an unknown
    key in one line: :func:`fusion_depth.config.hydra_main.unknown_key_message`)."""
    from fusion_depth.config.recipes import register_model_recipes

    register_model_recipes()
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(CONF_DIR, version_base="1.3"):
            cfg = compose("train", overrides=list(overrides))
    except HydraException as err:
        unknown = unknown_key_message(err, list(overrides))
        if unknown is not None:
            raise ConfigError(unknown) from err
        raise ValueError(f"bench overrides {list(overrides)}: {err}") from err
    finally:
        GlobalHydra.instance().clear()
    return cfg


def format_result(result: dict[str, Any]) -> str:
    """The result as Markdown: a settings line, the speed table and its notes, and with several
    engines the engines table (:mod:`fusion_depth.runner.bench_record`)."""
    lines = [settings_line(result)]
    if result.get("infer") or result.get("train"):
        lines += ["", format_table(SPEED_HEADER, speed_rows(result))]
    notes = speed_notes(result)
    if notes:
        lines += ["", notes]
    if len(result.get("engines") or {}) > 1:
        lines += ["", *format_engines(result)]
    if "prepare" in result:
        header, rows, note = prepare_table(result)
        lines += ["", format_table(header, rows), "", note]
        reference = spsolve_note(result)
        if reference:
            lines.append(reference)
    return "\n".join(lines)


def format_engines(result: dict[str, Any]) -> list[str]:
    """The ``--engines`` table: each engine's batch-1 latency, its latency over the FLOP floor
    and its speed-up over PyTorch, with a line saying what the floor is."""
    return [format_table(ENGINE_HEADER, engine_rows(result)), "", floor_note(result)]


def bench_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m fusion_depth.bench`` (flags and Hydra overrides)."""
    parser = argparse.ArgumentParser(
        prog="python -m fusion_depth.bench",
        description="Time inference, training and data loading of a configuration.",
    )
    parser.add_argument(
        "overrides", nargs="*", help="Hydra overrides of conf/train.yaml (e.g. fusion=concat)"
    )
    parser.add_argument("--baseline", action="store_true", help="also time eager fp32")
    parser.add_argument(
        "--engines",
        default="torch",
        help=f"engines timing batch-1 inference, comma-separated: {','.join(BENCH_ENGINES)} "
        "(torch, the reference, always runs)",
    )
    parser.add_argument("--json", type=Path, help="write the results to this JSON file")
    parser.add_argument(
        "--only",
        default=",".join(DEFAULT_STAGES),
        help=f"stages, comma-separated: {','.join(STAGES)} (default: all but prepare)",
    )
    parser.add_argument(
        "--cores",
        type=int,
        help="--only prepare: the cores its estimates assume (default: those this process may use)",
    )
    parser.add_argument(
        "--prepared",
        type=Path,
        help="--only prepare: time the fill on the frames of this prepared split (a folder "
        "holding index.json, e.g. one prepared with dataset.fill=none) instead of a generated "
        "frame",
    )
    parser.add_argument(
        "--frames", type=int, help="--only prepare --prepared: the frames timed (default 3)"
    )
    parser.add_argument("--warmup", type=int, default=3, help="untimed calls first")
    parser.add_argument("--runs", type=int, default=20, help="timed batch-1 inferences")
    parser.add_argument("--train-steps", type=int, default=10, help="timed optimizer steps")
    parser.add_argument("--data-workers", type=int, default=1, help="DataLoader processes")
    parser.add_argument(
        "--data-batches", type=int, default=100, help="timed batches (short windows are noisy)"
    )
    parser.add_argument("--data-split", default="train", help="the split the data stage reads")
    parser.add_argument("--threads", type=int, help="torch CPU threads (default: torch's)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command on ``argv`` (default: ``sys.argv[1:]``); returns the exit status, 0.

    Bad flags, overrides or stages exit with status 2 and one line naming them (argparse).
    """
    parser = bench_parser()
    args = parser.parse_intermixed_args(argv)  # overrides may come after the flags
    counts = (
        "warmup",
        "runs",
        "train_steps",
        "data_workers",
        "data_batches",
        "threads",
        "cores",
        "frames",
    )
    for name in counts:
        value = getattr(args, name)
        minimum = 0 if name in ("warmup", "data_workers") else 1
        if value is not None and value < minimum:
            parser.error(f"--{name.replace('_', '-')}={value}: expected an integer ≥ {minimum}")
    stages = [stage for stage in args.only.split(",") if stage]
    if args.prepared is None and args.frames is not None:
        parser.error("--frames: the frames of a --prepared split; give --prepared too")
    if args.prepared is not None and "prepare" not in stages:
        parser.error(
            f"--prepared {args.prepared}: times the fill, which --only leaves out; add prepare"
        )
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        cfg = compose_train_config(args.overrides)
        result = run_bench(
            cfg,
            stages=stages,
            baseline=args.baseline,
            engines=[engine for engine in args.engines.split(",") if engine],
            warmup=args.warmup,
            runs=args.runs,
            train_steps=args.train_steps,
            data_workers=args.data_workers,
            data_batches=args.data_batches,
            data_split=args.data_split,
            prepare_cores=args.cores,
            prepared=args.prepared,
            prepare_frames=args.frames or 3,
        )
    except (ValueError, FileNotFoundError, ImportError) as err:
        argument = argument_error(err)  # a science argument: named by the key that sets it
        parser.error(str(err) if argument is None else config_message(argument, cfg=cfg))
    print(format_result(result))
    if args.json:
        write_json_atomic(args.json, result)
        print(f"\nwrote {args.json}")
    return 0
