"""The evaluation protocol and what it measures, shared by ``train`` (test stage) and
``evaluate``: the ``eval`` config group (:class:`EvalProtocol`: depth caps, crop, averaging,
flip TTA, upsampling, distance bins), a test stage's :class:`EvaluationResult` (metric tables,
per-image records, latency), ``per_image.csv`` and the printed and W&B tables. The run record
that holds the results, ``metrics.json``, is :mod:`fusion_depth.runner.record`'s.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Collection, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from fusion_depth.errors import ArgumentError, ConfigError
from fusion_depth.metrics.depth import (
    AVERAGING,
    EVAL_CROPS,
    METRIC_KEYS,
    QUANTIZATIONS,
    RELATIVE_TO,
    TABLE_METRICS,
    UNITS,
    DepthMetrics,
    metric_header,
    metric_in_units,
)
from fusion_depth.models.inference import UPSAMPLING
from fusion_depth.runner.speed import cpu_model
from fusion_depth.utils.atomic import write_text_atomic
from fusion_depth.utils.config_values import ABSENT, config_value
from fusion_depth.utils.schema import BOOLEAN, Rule, Schema, is_number, one_of
from fusion_depth.utils.tables import format_table

RESOLUTIONS: tuple[str, ...] = ("network", "full")
"""Where the ground truth is scored: the network's frames (the prediction resized to them), or
``full``: the dataset's own resolution where a reader keeps it as points (``depth_points``,
nuScenes' val and test), the prediction read there bilinearly
(:func:`~fusion_depth.models.inference.depth_at_points`); a reader that keeps none is scored on
its frames as they are."""

BEFORE_PRESETS: dict[str, Any] = {
    "preset": "paper",
    "clamp": True,
    "relative_to": "ground_truth",
    "units": "m",
    "metrics": list(TABLE_METRICS),
    "quantize": "none",
    "resolution": "network",
}
"""The protocol keys added with or after the presets, with the values that score as every
protocol written before them did: a record or run config without them means these."""


def protocol_differences(
    a: Mapping[str, Any] | None, b: Mapping[str, Any] | None, ignore: Collection[str] = ()
) -> list[tuple[str, Any, Any]]:
    """``(key, value in a, value in b)`` for each key two recorded protocols (metrics.json's
    ``protocol``) score differently by, sorted; ``ignore``d keys left out. A key a protocol
    written before the presets lacks means its :data:`BEFORE_PRESETS` value."""
    a, b = a or {}, b or {}
    differences = []
    for key in sorted((set(a) | set(b)) - set(ignore)):
        x, y = (p.get(key, BEFORE_PRESETS.get(key)) for p in (a, b))
        if x != y:
            differences.append((key, x, y))
    return differences


@dataclass(frozen=True)
class EvalProtocol:
    """How predictions are scored: the ``eval`` config group, one preset per published protocol
    (``conf/eval/<preset>.yaml``, see docs/guides/evaluation.md).

    ``preset`` names it; ``clamp`` says whether predictions are clamped to ``[min_depth,
    cap]`` before scoring; ``quantize`` how they are read first
    (:data:`~fusion_depth.metrics.depth.QUANTIZATIONS`); ``resolution`` where the ground truth
    is (:data:`RESOLUTIONS`); ``relative_to`` what ARD and SRD
    divide by; ``units`` and ``metrics`` are the printed tables' units and columns, in the
    reference's order (metrics.json always holds every metric, in metres and 1/km).
    """

    min_depth: float
    max_depth: tuple[float, ...]
    crop: str = "none"
    averaging: str = "per_image"
    flip_tta: bool = False
    upsample: str = "bilinear"
    bin_width: float | None = 10.0
    preset: str = "paper"
    clamp: bool = True
    relative_to: str = "ground_truth"
    units: str = "m"
    metrics: tuple[str, ...] = TABLE_METRICS
    quantize: str = "none"
    resolution: str = "network"

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
        if cfg.get("units", "m") not in UNITS:
            raise ValueError(f"eval.units={cfg['units']!r}: expected one of {list(UNITS)}")
        metrics = tuple(cfg.get("metrics") or TABLE_METRICS)
        unknown = [k for k in metrics if k not in METRIC_KEYS]
        if unknown:
            raise ValueError(
                f"eval.metrics: unknown metric {unknown[0]!r} (expected some of "
                f"{', '.join(METRIC_KEYS)})"
            )
        protocol = cls(
            min_depth=float(cfg["min_depth"] if cfg.get("min_depth") is not None else min_depth),
            max_depth=tuple(sorted(float(c) for c in caps)),
            crop=cfg.get("crop", "none"),
            averaging=cfg.get("averaging", "per_image"),
            flip_tta=bool(cfg.get("flip_tta", False)),
            upsample=cfg.get("upsample", "bilinear"),
            bin_width=None if bin_width is None else float(bin_width),
            preset=str(cfg.get("preset", "paper")),
            clamp=bool(cfg.get("clamp", True)),
            relative_to=cfg.get("relative_to", "ground_truth"),
            units=cfg.get("units", "m"),
            metrics=metrics,
            quantize=cfg.get("quantize", "none"),
            resolution=cfg.get("resolution", "network"),
        )
        if protocol.resolution not in RESOLUTIONS:
            raise ValueError(
                f"eval.resolution={protocol.resolution!r}: expected one of {list(RESOLUTIONS)}"
            )
        if protocol.resolution == "full" and (
            protocol.upsample,
            protocol.crop,
            protocol.quantize,
        ) != ("bilinear", "none", "none"):
            raise ValueError(
                "eval.resolution=full reads the prediction bilinearly at the full-resolution "
                "points: expected eval.upsample=bilinear, eval.crop=none and eval.quantize=none, "
                f"got {protocol.upsample}, {protocol.crop} and {protocol.quantize}"
            )
        try:
            protocol.scorer()  # validates the depth range, crop and averaging names
        except ArgumentError as err:  # the metrics name their argument: here, the eval block's
            raise ConfigError(err.naming(lambda argument: f"eval.{argument}")) from None
        return protocol

    @property
    def distance_bins(self) -> list[float] | None:
        """Bin edges 0, w, 2w, ... up to the headline cap (the last bin may be narrower)."""
        if self.bin_width is None:
            return None
        cap = self.max_depth[-1]
        edges = [float(x) for x in np.arange(0.0, cap, self.bin_width)]
        return [*edges, cap]

    def scorer(self, conditions: Sequence[str] | None = None) -> DepthMetrics:
        """A fresh DepthMetrics scoring by this protocol."""
        return DepthMetrics(
            min_depth=self.min_depth,
            max_depth=list(self.max_depth),
            conditions=list(conditions) if conditions else None,
            averaging=self.averaging,
            crop=self.crop,
            distance_bins=self.distance_bins,
            clamp=self.clamp,
            relative_to=self.relative_to,
            quantize=self.quantize,
        )

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["max_depth"] = list(self.max_depth)
        out["metrics"] = list(self.metrics)
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


@dataclass(frozen=True)
class EvaluationResult:
    """What one test stage measured (:meth:`fusion_depth.runner.module.DepthModule.run_test`).

    Each metrics dict holds every key of :data:`~fusion_depth.metrics.depth.METRIC_KEYS` (RMSE and
    MAE in metres) plus ``num_images`` and ``num_pixels``; groups without a scored image are
    left out (see :meth:`fusion_depth.metrics.depth.DepthMetrics.results`).
    """

    protocol: EvalProtocol  # how the predictions were scored
    overall: dict[str, float]  # the headline: every scored image, within the largest cap
    by_condition: dict[str, dict[str, float]]  # per weather/light condition
    by_distance: dict[str, dict[str, float]]  # per distance bin, "0-10" (m), ...
    by_cap: dict[str, dict[str, float]]  # per depth cap, "80" (m), ...
    per_image: list[dict[str, Any]]  # one row per scored image, by index (per_image.csv's)
    latency: dict[str, Any]  # per-frame inference latency (:func:`latency_summary`)

    @classmethod
    def from_metrics(
        cls, protocol: EvalProtocol, metrics: DepthMetrics, latency: dict[str, Any]
    ) -> EvaluationResult:
        """The result of ``metrics`` (a DepthMetrics that scored the whole split)."""
        tables = metrics.results()
        return cls(
            protocol=protocol,
            overall=tables["overall"],
            by_condition=tables["by_condition"],
            by_distance=tables["by_distance"],
            by_cap=tables["by_cap"],
            per_image=metrics.per_image(),
            latency=latency,
        )


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


def results_tables(result: EvaluationResult) -> str:
    """Markdown tables of a test stage's result: per condition, per distance bin, per cap, and
    the latency line. Columns are the protocol's ``metrics`` in its ``units``."""
    protocol = result.protocol

    def rows(groups: Mapping[str, Mapping[str, float]]) -> list[list[str]]:
        return [
            [
                name,
                *(f"{metric_in_units(k, m[k], protocol.units):.3f}" for k in protocol.metrics),
                str(m["num_images"]),
                str(m["num_pixels"]),
            ]
            for name, m in groups.items()
        ]

    header = [metric_header(k, protocol.units) for k in protocol.metrics] + ["Images", "Pixels"]
    head_cap = f"{protocol.max_depth[-1]:g}"
    parts = [
        format_table(["Condition", *header], rows({"all": result.overall, **result.by_condition}))
    ]
    if result.by_distance:
        parts.append(
            format_table([f"Distance (m, cap {head_cap})", *header], rows(result.by_distance))
        )
    if len(result.by_cap) > 1:
        parts.append(
            format_table(
                ["Cap (m)", *header], rows({f"< {k}": v for k, v in result.by_cap.items()})
            )
        )
    latency = result.latency or {}
    if latency.get("mean_s") is not None:
        parts.append(
            f"Inference latency per frame ({latency['input_size'][0]}x{latency['input_size'][1]}, "
            f"batch {latency['batch_size']}, {latency['device']}): mean "
            f"{latency['mean_s'] * 1000:.1f} ms, p95 {latency['p95_s'] * 1000:.1f} ms"
        )
    return "\n\n".join(parts)


def wandb_tables(result: EvaluationResult) -> dict[str, tuple[list[str], list[list]]]:
    """The breakdowns as (columns, rows) for W&B Tables, keyed by their dashboard name."""
    columns = ["group", *METRIC_KEYS, "num_images", "num_pixels"]

    def table(groups: Mapping[str, Mapping[str, float]]) -> tuple[list[str], list[list]]:
        rows = [
            [name, *(g[k] for k in METRIC_KEYS), g["num_images"], g["num_pixels"]]
            for name, g in groups.items()
        ]
        return columns, rows

    tables = {"test/by_condition": table({"all": result.overall, **result.by_condition})}
    if result.by_distance:
        tables["test/by_distance"] = table(result.by_distance)
    if result.by_cap:
        tables["test/by_cap"] = table(result.by_cap)
    return tables


def log_to_loggers(loggers: Sequence[Any], result: EvaluationResult) -> None:
    """Send the breakdown tables to every W&B logger (other loggers get the flat metrics from
    the module's ``log_dict``)."""
    from lightning.pytorch.loggers import WandbLogger

    for logger in loggers:
        if isinstance(logger, WandbLogger):
            for key, (columns, rows) in wandb_tables(result).items():
                logger.log_table(key=key, columns=columns, data=rows)


def config_schema(cfg: DictConfig) -> Schema:
    """The ``eval`` group's values (:class:`EvalProtocol`'s arguments;
    fusion_depth.utils.schema). Each depth cap must lie above the minimum depth scored: the
    protocol's own, or the dataset's."""
    floor = config_value(cfg, "eval.min_depth")
    floor = cfg.dataset.min_depth if floor in (None, ABSENT) else floor
    positive_metres = Rule(lambda v: is_number(v) and v > 0, "a positive number of metres")
    # Without clamping, min_depth 0 scores every target above 0 (RadarNet's gt > 0).
    clamp = config_value(cfg, "eval.clamp") is not False
    min_depth = positive_metres if clamp else Rule(lambda v: is_number(v) and v >= 0, "0 or more")
    return {
        "eval.preset": Rule(lambda v: isinstance(v, str) and v != "", "the preset's name"),
        "eval.clamp": BOOLEAN,
        "eval.relative_to": one_of(*RELATIVE_TO),
        "eval.units": one_of(*UNITS),
        "eval.metrics": Rule(
            lambda v: isinstance(v, list) and v and all(k in METRIC_KEYS for k in v),
            f"a list of metrics from {', '.join(METRIC_KEYS)}",
        ),
        "eval.crop": one_of(*EVAL_CROPS),
        "eval.averaging": one_of(*AVERAGING),
        "eval.upsample": one_of(*UPSAMPLING),
        "eval.quantize": one_of(*QUANTIZATIONS),
        "eval.resolution": one_of(*RESOLUTIONS),
        "eval.flip_tta": BOOLEAN,
        "eval.bin_width": positive_metres.or_null("no distance breakdown"),
        "eval.min_depth": min_depth.or_null("dataset.min_depth"),
        "eval.max_depth": Rule(
            lambda v: (
                v is None
                or (is_number(v) and v > floor)
                or (isinstance(v, list) and v and all(is_number(c) and c > floor for c in v))
            ),
            f"a cap or a list of caps in metres, each above the minimum depth {floor}, or null "
            "(dataset.max_depth)",
        ),
    }
