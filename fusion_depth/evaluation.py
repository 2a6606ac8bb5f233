"""The evaluation protocol and the record it produces, shared by ``train`` (test stage) and
``evaluate``: the ``eval`` config group, the breakdown tables, ``metrics.json`` and
``per_image.csv``.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from fusion_depth.inference import UPSAMPLING
from fusion_depth.metrics import METRIC_KEYS, DepthMetrics
from fusion_depth.runs import METRICS_FILE, PER_IMAGE_FILE, write_json_atomic, write_text_atomic
from fusion_depth.speed import cpu_model
from fusion_depth.tables import format_table

# (metric key, column header) of the printed tables, in the paper's order plus MAE.
TABLE_COLUMNS = (
    ("rmse", "RMSE"),
    ("abs_rel", "ARD"),
    ("sq_rel", "SRD"),
    ("mae", "MAE"),
    ("delta1", "δ1"),
    ("delta2", "δ2"),
    ("delta3", "δ3"),
)


@dataclass(frozen=True)
class EvalProtocol:
    """How predictions are scored (the ``eval`` config group; see ``conf/eval/default.yaml``)."""

    min_depth: float
    max_depth: tuple[float, ...]
    crop: str = "none"
    averaging: str = "per_image"
    flip_tta: bool = False
    upsample: str = "bilinear"
    bin_width: float | None = 10.0

    @classmethod
    def from_config(
        cls, cfg: Mapping[str, Any] | None, min_depth: float, max_depth: float
    ) -> EvalProtocol:
        """The protocol of an ``eval`` block; null depth limits take the model's range."""
        cfg = dict(cfg or {})
        caps = cfg.get("max_depth")
        caps = [max_depth] if caps is None else caps
        caps = [caps] if isinstance(caps, int | float) else list(caps)
        bin_width = cfg.get("bin_width", 10.0)
        if bin_width is not None and not bin_width > 0:
            raise ValueError(f"eval.bin_width={bin_width}: expected a positive number or null")
        if cfg.get("upsample", "bilinear") not in UPSAMPLING:
            raise ValueError(
                f"eval.upsample={cfg['upsample']!r}: expected one of {list(UPSAMPLING)}"
            )
        protocol = cls(
            min_depth=float(cfg["min_depth"] if cfg.get("min_depth") is not None else min_depth),
            max_depth=tuple(sorted(float(c) for c in caps)),
            crop=cfg.get("crop", "none"),
            averaging=cfg.get("averaging", "per_image"),
            flip_tta=bool(cfg.get("flip_tta", False)),
            upsample=cfg.get("upsample", "bilinear"),
            bin_width=None if bin_width is None else float(bin_width),
        )
        protocol.metrics()  # validates the depth range, crop and averaging names
        return protocol

    @property
    def distance_bins(self) -> list[float] | None:
        """Bin edges 0, w, 2w, ... up to the headline cap (the last bin may be narrower)."""
        if self.bin_width is None:
            return None
        cap = self.max_depth[-1]
        edges = [float(x) for x in np.arange(0.0, cap, self.bin_width)]
        return [*edges, cap]

    def metrics(self, conditions: Sequence[str] | None = None) -> DepthMetrics:
        """A fresh DepthMetrics scoring by this protocol."""
        return DepthMetrics(
            min_depth=self.min_depth,
            max_depth=list(self.max_depth),
            conditions=list(conditions) if conditions else None,
            averaging=self.averaging,
            crop=self.crop,
            distance_bins=self.distance_bins,
        )

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["max_depth"] = list(self.max_depth)
        out["distance_bins"] = self.distance_bins
        return out


def device_name(device: torch.device | str) -> str:
    """A readable name of the device inference ran on (GPU model or CPU model and cores)."""
    device = torch.device(device)
    if device.type == "cuda":
        return f"cuda: {torch.cuda.get_device_name(device)}"
    return f"cpu: {cpu_model()} ({torch.get_num_threads()} threads)"


def latency_summary(
    per_frame_s: Sequence[float], device: torch.device | str, batch_size: int, size: tuple
) -> dict[str, Any]:
    """Mean and p95 of the per-frame latency of each batch; the first batch (warm-up: lazy
    initialisation, cudnn autotuning) is left out when there are others."""
    times = list(per_frame_s[1:] if len(per_frame_s) > 1 else per_frame_s)
    return {
        "mean_s": float(np.mean(times)) if times else None,
        "p95_s": float(np.percentile(times, 95)) if times else None,
        "num_batches": len(times),
        "batch_size": batch_size,
        "input_size": list(size),
        "device": device_name(device),
    }


def evaluation_record(
    results: Mapping[str, Any], protocol: EvalProtocol, split: str, latency: Mapping | None
) -> dict[str, Any]:
    """The evaluation part of ``metrics.json`` (``test`` holds the scored split's headline)."""
    return {
        "split": split,
        "protocol": protocol.as_dict(),
        "test": results["overall"],
        "test_by_condition": results["by_condition"],
        "test_by_distance": results["by_distance"],
        "test_by_cap": results["by_cap"],
        "latency": dict(latency) if latency else None,
        "per_image_file": PER_IMAGE_FILE,
    }


def write_per_image(path: str | os.PathLike, rows: Sequence[Mapping[str, Any]]) -> None:
    """``per_image.csv``: index, condition, num_pixels and every metric, one row per image."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["index", "condition", "num_pixels", *METRIC_KEYS])
    for row in rows:
        writer.writerow(
            [row["index"], row["condition"], row["num_pixels"]]
            + [repr(float(row[k])) for k in METRIC_KEYS]
        )
    write_text_atomic(path, out.getvalue())


def _rows(groups: Mapping[str, Mapping[str, float]]) -> list[list[str]]:
    return [
        [
            name,
            *(f"{m[k]:.3f}" for k, _ in TABLE_COLUMNS),
            str(m["num_images"]),
            str(m["num_pixels"]),
        ]
        for name, m in groups.items()
    ]


def results_tables(record: Mapping[str, Any]) -> str:
    """Markdown tables of an evaluation record: per condition, per distance bin, per cap."""

    header = [name for _, name in TABLE_COLUMNS] + ["Images", "Pixels"]
    caps = record["protocol"]["max_depth"]
    head_cap = f"{caps[-1]:g}"
    parts = [
        format_table(
            ["Condition", *header],
            _rows({"all": record["test"], **record["test_by_condition"]}),
        )
    ]
    if record.get("test_by_distance"):
        parts.append(
            format_table(
                [f"Distance (m, cap {head_cap})", *header], _rows(record["test_by_distance"])
            )
        )
    if len(record.get("test_by_cap", {})) > 1:
        parts.append(
            format_table(
                ["Cap (m)", *header], _rows({f"< {k}": v for k, v in record["test_by_cap"].items()})
            )
        )
    latency = record.get("latency") or {}
    if latency.get("mean_s") is not None:
        parts.append(
            f"Inference latency per frame ({latency['input_size'][0]}x{latency['input_size'][1]}, "
            f"batch {latency['batch_size']}, {latency['device']}): mean "
            f"{latency['mean_s'] * 1000:.1f} ms, p95 {latency['p95_s'] * 1000:.1f} ms"
        )
    return "\n\n".join(parts)


def wandb_tables(record: Mapping[str, Any]) -> dict[str, tuple[list[str], list[list]]]:
    """The breakdowns as (columns, rows) for W&B Tables, keyed by their dashboard name."""
    columns = ["group", *METRIC_KEYS, "num_images", "num_pixels"]

    def table(groups: Mapping[str, Mapping[str, float]]) -> tuple[list[str], list[list]]:
        rows = [
            [name, *(g[k] for k in METRIC_KEYS), g["num_images"], g["num_pixels"]]
            for name, g in groups.items()
        ]
        return columns, rows

    tables = {"test/by_condition": table({"all": record["test"], **record["test_by_condition"]})}
    if record.get("test_by_distance"):
        tables["test/by_distance"] = table(record["test_by_distance"])
    if record.get("test_by_cap"):
        tables["test/by_cap"] = table(record["test_by_cap"])
    return tables


def log_to_loggers(loggers: Sequence[Any], record: Mapping[str, Any]) -> None:
    """Send the breakdown tables to every W&B logger (other loggers get the flat metrics from
    the module's ``log_dict``)."""
    from lightning.pytorch.loggers import WandbLogger

    for logger in loggers:
        if isinstance(logger, WandbLogger):
            for key, (columns, rows) in wandb_tables(record).items():
                logger.log_table(key=key, columns=columns, data=rows)


def publish_results(
    output_dir: str | os.PathLike,
    results: Mapping[str, Any],
    rows: Sequence[Mapping[str, Any]],
    loggers: Sequence[Any],
    title: str,
) -> Path:
    """Send the breakdowns to W&B, write ``per_image.csv`` then ``metrics.json`` (last, so its
    presence means the run is complete), and print ``title`` with the tables."""
    log_to_loggers(loggers, results)
    output_dir = Path(output_dir)
    write_per_image(output_dir / PER_IMAGE_FILE, rows)
    path = output_dir / METRICS_FILE
    write_json_atomic(path, results)
    print(f"\n{title}:\n{results_tables(results)}\nWritten to {path}", flush=True)
    return path
