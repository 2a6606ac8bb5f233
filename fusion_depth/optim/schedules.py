"""Learning-rate schedules: the paper's per-epoch ``StepLR`` (``scheduler=step``), the per-step
:class:`WarmupCosine` (``scheduler=cosine``), :class:`Constant` (RadarNet's), and
:func:`create_schedule`, which builds any of them by name (``scheduler=for_<model>``, so that a
model or a dataset's recipe can name its schedule).

A schedule here declares ``interval = "step"`` and takes ``total_steps``, which the module
passes: the run's optimizer steps (``trainer.estimated_stepping_batches``), so it follows
``max_epochs``, ``limit_train_batches`` and gradient accumulation without being told.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch.optim.lr_scheduler import LambdaLR, LRScheduler, StepLR

from fusion_depth.errors import ArgumentError


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
        ArgumentError: an argument out of range, naming it.
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
            raise ValueError(f"total_steps={total_steps!r}: expected an integer ≥ 1")
        if not 0 <= warmup_fraction < 1:
            raise ArgumentError(
                f"{{warmup_fraction}}={warmup_fraction!r}: expected a share in [0, 1)",
                "warmup_fraction",
                owner=WarmupCosine,
            )
        if not 0 <= final_lr_ratio <= 1:
            raise ArgumentError(
                f"{{final_lr_ratio}}={final_lr_ratio!r}: expected a ratio in [0, 1]",
                "final_lr_ratio",
                owner=WarmupCosine,
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


# The schedules a config may name (create_schedule's ``name``): the paper's StepLR, stepped per
# epoch, and the warm-up + cosine one, stepped per optimizer step.
def _unchanged(epoch: int) -> float:
    return 1.0


class Constant(LambdaLR):
    """The optimizer's learning rate throughout: RadarNet's reference schedule (one rate for all
    of ``--learning_schedule``, nesl/radar-camera-fusion-depth, src/fusionnet_main.py lines
    332-341, with bash/train_fusionnet_nuscenes.sh's single rate).

    Args:
        optimizer: its ``lr`` is the rate.
    """

    def __init__(self, optimizer: torch.optim.Optimizer) -> None:
        super().__init__(optimizer, _unchanged)


SCHEDULES: dict[str, type[LRScheduler]] = {
    "step": StepLR,
    "cosine": WarmupCosine,
    "constant": Constant,
}
# Arguments the module passes itself, never a config's.
_PASSED_BY_MODULE = ("self", "optimizer", "total_steps", "last_epoch")
# Every schedule's config arguments, which create_schedule takes (None: unset).
SCHEDULE_ARGUMENTS = ("step_size", "gamma", "warmup_fraction", "final_lr_ratio")


def schedule_class(name: str) -> type[LRScheduler]:
    """The schedule called ``name`` in :data:`SCHEDULES`.

    Raises:
        ArgumentError: an unknown name, listing the known ones.
    """
    if name not in SCHEDULES:
        raise ArgumentError(
            f"{{name}}={name!r}: unknown schedule; expected one of {', '.join(SCHEDULES)}",
            "name",
            owner=schedule_class,
        )
    return SCHEDULES[name]


def schedule_arguments(name: str) -> list[str]:
    """The arguments a config may give schedule ``name`` (those the module passes left out)."""
    params = inspect.signature(schedule_class(name)).parameters
    return [p for p in params if p not in _PASSED_BY_MODULE]


def check_schedule_arguments(name: str, arguments: Mapping[str, Any]) -> None:
    """``arguments`` that are set (not None) must be schedule ``name``'s own, and those it
    requires must be set.

    Raises:
        ArgumentError: an unknown name, a set argument the schedule does not take, or a
            required one unset, naming it.
    """
    allowed = schedule_arguments(name)
    for key, value in arguments.items():
        if value is not None and key not in allowed:
            raise ArgumentError(
                f"{{{key}}}={value!r}: the {name} schedule takes no {key} "
                f"(its arguments: {', '.join(allowed)}); set it to null",
                key,
                owner=check_schedule_arguments,
            )
    params = inspect.signature(schedule_class(name)).parameters
    for key in allowed:
        if params[key].default is inspect.Parameter.empty and arguments.get(key) is None:
            raise ArgumentError(
                f"{{{key}}}: the {name} schedule needs it; it is null",
                key,
                owner=check_schedule_arguments,
            )


def create_schedule(
    optimizer: torch.optim.Optimizer,
    name: str = "step",
    total_steps: int | None = None,
    step_size: int | None = None,
    gamma: float | None = None,
    warmup_fraction: float | None = None,
    final_lr_ratio: float | None = None,
) -> LRScheduler:
    """Schedule ``name`` (:data:`SCHEDULES`) over ``optimizer``, built with the arguments that
    are set; the others must be None.

    A model's or dataset recipe's schedule (``scheduler=<recipe_from>_<dataset>_<model>``, made by
    :mod:`fusion_depth.config.recipes`) is built through this: the schedule is named, looked up
    here, never imported.

    Args:
        optimizer: the run's optimizer; its ``lr`` is the peak.
        name: ``step`` (torch's StepLR, per epoch) or ``cosine`` (:class:`WarmupCosine`, per
            optimizer step).
        total_steps: the run's optimizer steps (the module passes it to a per-step schedule).
        step_size: StepLR's: lr × ``gamma`` every ``step_size`` epochs.
        gamma: StepLR's factor.
        warmup_fraction: :class:`WarmupCosine`'s (None: its default).
        final_lr_ratio: :class:`WarmupCosine`'s (None: its default).

    Raises:
        ArgumentError: an unknown name, or a set argument the named schedule does not take.
    """
    arguments = {
        "step_size": step_size,
        "gamma": gamma,
        "warmup_fraction": warmup_fraction,
        "final_lr_ratio": final_lr_ratio,
    }
    check_schedule_arguments(name, arguments)
    cls = schedule_class(name)
    given = {key: value for key, value in arguments.items() if value is not None}
    if getattr(cls, "interval", "epoch") == "step":
        given["total_steps"] = total_steps
    return cls(optimizer, **given)


def schedule_interval(factory: Callable[..., Any]) -> str:
    """``"step"`` or ``"epoch"``: how often the schedule a factory builds (a class, or a
    ``functools.partial`` as Hydra's ``_partial_: true`` makes, also of :func:`create_schedule`)
    is stepped, so that the module knows whether to pass ``total_steps``."""
    keywords: dict[str, Any] = {}
    while isinstance(factory, functools.partial):
        keywords = {**factory.keywords, **keywords}
        factory = factory.func
    if factory is create_schedule:
        factory = schedule_class(keywords.get("name", "step"))
    return getattr(factory, "interval", "epoch")
