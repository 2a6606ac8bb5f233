"""Checking an exported model against PyTorch: the depth it gives must be PyTorch's, within the
tolerance of the precision it computes in.

``verify`` runs the file on a random input and computes the relative difference ``|exported -
PyTorch| / PyTorch`` of every pixel. :data:`TOLERANCES` (docs/guides/export.md, with the
measurements behind them) bounds, per precision, the statistic :data:`CHECKED` names: fp32
files agree to rounding, so their largest difference is bounded tightly; bf16 keeps 8 bits of
mantissa, so its largest difference gets a looser bound, and fp16 (11 bits, TensorRT on a GPU)
the same one, not measured yet (no GPU here); an int8 file is judged by its accuracy
on data (``measure_accuracy``), and on the random input only its mean difference is bounded,
loosely: a sanity check that catches a broken file (a wrong scale, a collapsed range), not a
measure of its accuracy.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from fusion_depth.errors import UserError

TOLERANCE = 1e-3  # fp32: the default tolerance, as it always was
# What a file computes in → the default tolerance (relative), and the statistic it bounds.
# fp16 keeps 3 more mantissa bits than bf16, so bf16's bound holds for it with room to spare.
TOLERANCES: dict[str, float] = {"fp32": TOLERANCE, "bf16": 0.1, "fp16": 0.1, "int8": 0.5}
CHECKED: dict[str, str] = {
    "fp32": "max_rel_diff",
    "bf16": "max_rel_diff",
    "fp16": "max_rel_diff",
    "int8": "mean_rel_diff",
}


class ExportError(RuntimeError, UserError):
    """The export ran but its result is not usable (it disagrees with PyTorch, or it costs
    more accuracy than allowed); the message is one line and nothing was written."""


def unreadable(what: str, err: BaseException) -> ExportError:
    """The :class:`ExportError` for a file its runtime cannot read back: ``<what>: <the first
    line of err>`` (runtimes' messages run to many lines)."""
    text = str(err).strip()
    return ExportError(f"{what}: {text.splitlines()[0] if text else type(err).__name__}")


def compare_depth(
    exported: np.ndarray,
    reference: torch.Tensor,
    tolerance: float,
    what: str,
    checked: str = "max_rel_diff",
) -> dict[str, Any]:
    """Max absolute (m), max relative and mean relative difference of ``exported`` depth
    (B, 1, H, W) metres from PyTorch's ``reference``, with ``tolerance`` applied to the one
    ``checked`` names (``max_rel_diff`` or ``mean_rel_diff``, :data:`CHECKED`).

    Raises:
        ExportError: the shapes differ, or the checked difference is over ``tolerance`` (or
            NaN); the message names ``what`` (the runtime that ran the exported model).
    """
    expected = reference.numpy()
    if exported.shape != expected.shape:
        raise ExportError(
            f"{what}: output shape {tuple(exported.shape)}, PyTorch's is {tuple(expected.shape)}"
        )
    diff = np.abs(exported.astype(np.float64) - expected)
    relative = diff / np.abs(expected)  # depth ≥ min_depth > 0
    max_abs, max_rel, mean_rel = float(diff.max()), float(relative.max()), float(relative.mean())
    if checked == "mean_rel_diff":
        by, value = f"{mean_rel:.3g} relative on average (up to {max_abs:.3g} m)", mean_rel
    else:
        by, value = f"up to {max_abs:.3g} m ({max_rel:.3g} relative)", max_rel
    if not value <= tolerance:  # NaN fails too
        raise ExportError(
            f"{what}: depth differs from PyTorch's by {by}, more than tolerance={tolerance:g}; "
            "the exported model is not faithful (nothing was written)"
        )
    return {
        "max_abs_diff_m": max_abs,
        "max_rel_diff": max_rel,
        "mean_rel_diff": mean_rel,
        "checked": checked,
        "tolerance": float(tolerance),
    }
