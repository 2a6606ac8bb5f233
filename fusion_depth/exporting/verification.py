"""Checking an exported model against PyTorch: the depth it gives must be PyTorch's."""

from __future__ import annotations

import numpy as np
import torch

TOLERANCE = 1e-3  # largest relative difference |exported - PyTorch| / PyTorch accepted by verify


class ExportError(RuntimeError):
    """The export ran but its result is not usable (e.g. it disagrees with PyTorch)."""


def compare_depth(
    exported: np.ndarray, reference: torch.Tensor, tolerance: float, what: str
) -> dict[str, float]:
    """Max absolute (m) and relative difference of ``exported`` depth (B, 1, H, W) metres from
    PyTorch's ``reference``.

    Raises:
        ExportError: the shapes differ, or the relative difference is over ``tolerance`` (or
            NaN); the message names ``what`` (the runtime that ran the exported model).
    """
    expected = reference.numpy()
    if exported.shape != expected.shape:
        raise ExportError(
            f"{what}: output shape {tuple(exported.shape)}, PyTorch's is {tuple(expected.shape)}"
        )
    diff = np.abs(exported.astype(np.float64) - expected)
    max_abs = float(diff.max())
    max_rel = float((diff / np.abs(expected)).max())  # depth ≥ min_depth > 0
    if not max_rel <= tolerance:  # NaN fails too
        raise ExportError(
            f"{what}: depth differs from PyTorch's by up to {max_abs:.3g} m ({max_rel:.3g} "
            f"relative), more than tolerance={tolerance:g}; the exported model is not faithful "
            "(nothing was written)"
        )
    return {"max_abs_diff_m": max_abs, "max_rel_diff": max_rel}
