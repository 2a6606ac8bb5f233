"""How fast a configuration trains and infers here, and how far that is from this machine's limit.

python -m fusion_depth.bench dataset.height=384 dataset.width=1248 --baseline --json bench.json
python -m fusion_depth.bench backbone=resnet50 fusion=concat trainer.precision=32-true
python -m fusion_depth.bench --only peak,infer --engines torch,onnxruntime,openvino,openvino-int8

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

from fusion_depth.bench.stages import BENCH_ENGINES, STAGES, run_bench
from fusion_depth.config import CONF_DIR
from fusion_depth.config.hydra_main import unknown_key_message
from fusion_depth.errors import ConfigError
from fusion_depth.utils.atomic import write_json_atomic
from fusion_depth.utils.console import quiet_known_noise

quiet_known_noise()


def compose_train_config(overrides: Sequence[str]) -> DictConfig:
    """``conf/train.yaml`` with ``overrides``; errors name the offending override (an unknown
    key in one line: :func:`fusion_depth.config.hydra_main.unknown_key_message`)."""
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


def _fmt(value: float | None, digits: int = 3) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def _ratio(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}×"


def format_table(result: dict[str, Any]) -> str:
    """The result as a markdown table with a settings line above it."""
    s, machine = result["settings"], result["machine"]
    where = machine["gpu"] or f"{machine['cpu']}, {machine['torch_threads']} threads"
    lines = [
        f"{s['backbone']} · fusion={s['fusion']} · {s['height']}×{s['width']} · "
        f"train batch {s['batch_size']} · {s['device']} ({where})",
        "",
        "| run | infer median (s) | infer p95 (s) | infer GFLOP/s | of matmul peak "
        "| train samples/s | train GFLOP/s | peak memory (MB) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    peak = result.get("peak_gflops")
    infer_flops = result.get("infer_gflop_per_frame")
    train_flops = result.get("train_gflop_per_step")

    def row(name: str, infer: dict | None, train: dict | None, peak_gflops: float | None) -> str:
        latency = infer["latency_s_median"] if infer else None
        gflops = infer_flops / latency if infer_flops and latency else None
        share = f"{100 * gflops / peak_gflops:.0f} %" if gflops and peak_gflops else "–"
        train_gflops = train_flops / train["step_s_median"] if train and train_flops else None
        memory = max((d["peak_memory_mb"] for d in (infer, train) if d), default=None)
        return (
            f"| {name} | {_fmt(latency)} | {_fmt(infer and infer['latency_s_p95'])} "
            f"| {_fmt(gflops, 1)} | {share} | {_fmt(train and train['samples_per_s'], 2)} "
            f"| {_fmt(train_gflops, 1)} | {_fmt(memory, 0)} |"
        )

    speed = f"{s['precision']}{', channels-last' if s['channels_last'] else ''}"
    speed += f", compiled ({s['compile_mode']})" if s["compile"] else ", eager"
    lines.append(row(speed, result.get("infer"), result.get("train"), peak))
    if "baseline_infer" in result or "baseline_train" in result:
        lines.append(
            row(
                "32-true, eager, contiguous (baseline)",
                result.get("baseline_infer"),
                result.get("baseline_train"),
                result.get("baseline_peak_gflops"),
            )
        )
        lines.append(
            f"| speed-up | {_ratio(result.get('infer_speedup'))} | | | "
            f"| {_ratio(result.get('train_speedup'))} | | |"
        )
    notes = []
    if peak:
        notes.append(f"matrix-product peak {peak:.0f} GFLOP/s ({s['precision']})")
    if result.get("baseline_peak_gflops"):
        notes.append(f"{result['baseline_peak_gflops']:.0f} GFLOP/s (fp32)")
    if infer_flops:
        notes.append(f"{infer_flops:.1f} GFLOP per frame")
    if train_flops:
        notes.append(f"{train_flops:.1f} GFLOP per training step")
    if "data" in result:
        d = result["data"]
        notes.append(
            f"data ({d['dataset']} {d['split']}): {d['samples_per_s_per_worker']:.1f} samples/s "
            f"per loader worker ({d['workers']}), to floats + augmentation on "
            f"{d['augment_device']} {d['augment_samples_per_s']:.1f} samples/s, together "
            f"{d['pipeline_samples_per_s']:.1f} samples/s"
        )
    if notes:
        lines += ["", "; ".join(notes)]
    engines = result.get("engines") or {}
    if len(engines) > 1:
        lines += ["", *format_engines(result)]
    return "\n".join(lines)


def format_engines(result: dict[str, Any]) -> list[str]:
    """The ``--engines`` table: each engine's batch-1 latency, its latency over the FLOP floor
    and its speed-up over PyTorch, with a line saying what the floor is."""
    lines = [
        "| engine | computes in | batch-1 latency, median (p95) | latency / FLOP floor "
        "| speed-up over torch | export (s) |",
        "|---|---|---|---|---|---|",
    ]
    for name, e in result["engines"].items():
        floor = e["latency_over_floor"]
        lines.append(
            f"| {name} | {e['computes']} | {_fmt(e['latency_s_median'])} s "
            f"({_fmt(e['latency_s_p95'])}) | {_ratio(floor)} | {_ratio(e['speedup'])} "
            f"| {_fmt(e.get('export_s'), 0)} |"
        )
    floor_s, peak = result.get("infer_floor_s"), result.get("peak_gflops")
    if floor_s:
        lines += [
            "",
            f"FLOP floor {floor_s:.3f} s: {result['infer_gflop_per_frame']:.1f} GFLOP per frame at "
            f"the {result['settings']['precision']} matrix-product peak, {peak:.0f} GFLOP/s "
            "(latency / floor 1.00× = at the floor)",
        ]
    else:
        lines += ["", "no FLOP floor: the peak stage did not run (--only peak,infer)"]
    return lines


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
        "--only", default=",".join(STAGES), help=f"stages, comma-separated: {','.join(STAGES)}"
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
    for name in ("warmup", "runs", "train_steps", "data_workers", "data_batches", "threads"):
        value = getattr(args, name)
        minimum = 0 if name in ("warmup", "data_workers") else 1
        if value is not None and value < minimum:
            parser.error(f"--{name.replace('_', '-')}={value}: expected an integer ≥ {minimum}")
    if args.threads:
        torch.set_num_threads(args.threads)
    try:
        cfg = compose_train_config(args.overrides)
        result = run_bench(
            cfg,
            stages=[stage for stage in args.only.split(",") if stage],
            baseline=args.baseline,
            engines=[engine for engine in args.engines.split(",") if engine],
            warmup=args.warmup,
            runs=args.runs,
            train_steps=args.train_steps,
            data_workers=args.data_workers,
            data_batches=args.data_batches,
            data_split=args.data_split,
        )
    except (ValueError, FileNotFoundError, ImportError) as err:
        parser.error(str(err))
    print(format_table(result))
    if args.json:
        write_json_atomic(args.json, result)
        print(f"\nwrote {args.json}")
    return 0
