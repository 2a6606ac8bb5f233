"""Learning-rate schedules stepped per optimizer step (``scheduler=cosine``).

The paper's schedule, ``scheduler=step`` (torch's ``StepLR``), is stepped per epoch. A schedule
here declares ``interval = "step"`` and takes ``total_steps``, which the module passes: the
run's optimizer steps (``trainer.estimated_stepping_batches``), so it follows ``max_epochs``,
``limit_train_batches`` and gradient accumulation without being told.
"""

from __future__ import annotations

import math

import torch
from torch.optim.lr_scheduler import LambdaLR


class WarmupCosine(LambdaLR):
    """Linear warm-up from ~0 to the optimizer's learning rate over the first
    ``warmup_fraction`` of ``total_steps``, then cosine decay to ``final_lr_ratio`` times it
    (Goyal et al. 2017 warm-up; Loshchilov & Hutter 2017, SGDR, without restarts).

    Args:
        optimizer: its ``lr`` is the peak.
        total_steps: optimizer steps of the whole run (≥ 1).
        warmup_fraction: share of ``total_steps`` spent warming up, in [0, 1).
        final_lr_ratio: learning rate at the last step over the peak, in [0, 1].

    Raises:
        ValueError: an argument out of range, naming it.
    """

    interval = "step"  # stepped after every optimizer step, not every epoch

    def __init__(
        self,
        optimizer: torch.optim.Optimizer,
        total_steps: int,
        warmup_fraction: float = 0.05,
        final_lr_ratio: float = 0.01,
    ) -> None:
        if not (isinstance(total_steps, int) and total_steps >= 1):
            raise ValueError(f"scheduler total_steps={total_steps!r}: expected an integer ≥ 1")
        if not 0 <= warmup_fraction < 1:
            raise ValueError(
                f"scheduler.warmup_fraction={warmup_fraction!r}: expected a share in [0, 1)"
            )
        if not 0 <= final_lr_ratio <= 1:
            raise ValueError(
                f"scheduler.final_lr_ratio={final_lr_ratio!r}: expected a ratio in [0, 1]"
            )
        self.total_steps = total_steps
        self.warmup_steps = int(round(warmup_fraction * total_steps))
        self.final_lr_ratio = final_lr_ratio
        super().__init__(optimizer, self.factor)

    def factor(self, step: int) -> float:
        """The learning rate after ``step`` optimizer steps, over the peak."""
        if step < self.warmup_steps:
            return (step + 1) / (self.warmup_steps + 1)
        span = max(1, self.total_steps - self.warmup_steps)
        progress = min(1.0, (step - self.warmup_steps) / span)
        cosine = 0.5 * (1 + math.cos(math.pi * progress))
        return self.final_lr_ratio + (1 - self.final_lr_ratio) * cosine
