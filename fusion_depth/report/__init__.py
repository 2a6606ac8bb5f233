"""``python -m fusion_depth.report``: the tables, paired comparisons and plots of a sweep (see
:mod:`fusion_depth.report.cli` for the options).

One module per concern: :mod:`.groups` (grouping runs, tables), :mod:`.compare` (paired
comparisons), :mod:`.by_model` (``--by model``: per model, with differences between models),
:mod:`.plots` (bar charts), :mod:`.cli` (the command line and W&B upload).
"""

from fusion_depth.report.by_model import build_model_report, default_baseline
from fusion_depth.report.cli import log_wandb, main, table_cells
from fusion_depth.report.compare import (
    COMPARE_KEYS,
    Comparison,
    PerImage,
    build_comparison_table,
    compare_groups,
    compare_to_baseline,
    load_per_image,
    paired_differences,
    per_image_path,
)
from fusion_depth.report.groups import (
    ALL,
    BY_SECTIONS,
    HARD_CONDITIONS,
    Preset,
    build_by_table,
    build_table,
    by_column_stats,
    check_format_versions,
    group_runs,
    key_label,
    runs_preset,
)
from fusion_depth.report.plots import (
    PLOT_METRICS,
    plot_by,
    plot_comparisons,
    plot_groups,
    read_figure_description,
)

__all__ = [
    "ALL",
    "BY_SECTIONS",
    "Preset",
    "build_by_table",
    "build_table",
    "by_column_stats",
    "check_format_versions",
    "group_runs",
    "HARD_CONDITIONS",
    "key_label",
    "runs_preset",
    "build_model_report",
    "default_baseline",
    "COMPARE_KEYS",
    "Comparison",
    "PerImage",
    "build_comparison_table",
    "compare_groups",
    "compare_to_baseline",
    "load_per_image",
    "paired_differences",
    "per_image_path",
    "PLOT_METRICS",
    "plot_by",
    "plot_comparisons",
    "plot_groups",
    "read_figure_description",
    "log_wandb",
    "main",
    "table_cells",
]
