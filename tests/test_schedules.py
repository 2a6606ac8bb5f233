"""``scheduler=cosine``: linear warm-up then cosine decay, stepped per optimizer step over the
run's steps; the paper's ``scheduler=step`` stays per epoch."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
import torch
from hydra.utils import instantiate

from fusion_depth.config import validate_config
from fusion_depth.errors import ConfigError
from fusion_depth.schedules import WarmupCosine


def _lrs(scheduler: torch.optim.lr_scheduler.LRScheduler, steps: int) -> list[float]:
    optimizer = scheduler.optimizer
    lrs = []
    for _ in range(steps):
        lrs.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    return lrs + [optimizer.param_groups[0]["lr"]]


def test_warmup_then_cosine_to_the_final_ratio() -> None:
    optimizer = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    lrs = _lrs(WarmupCosine(optimizer, total_steps=10, warmup_fraction=0.2, final_lr_ratio=0.1), 10)
    assert lrs[:3] == pytest.approx([1 / 3, 2 / 3, 1.0])  # 2 warm-up steps, then the peak
    progress = 4 / 8  # step 6: half-way through the 8 decay steps
    assert lrs[6] == pytest.approx(0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * progress)))
    assert lrs[10] == pytest.approx(0.1)  # the last step's learning rate
    assert all(a >= b for a, b in zip(lrs[2:], lrs[3:], strict=False))  # never rises after


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"total_steps": 0}, "total_steps=0"),
        ({"total_steps": 5, "warmup_fraction": 1.0}, "warmup_fraction=1.0"),
        ({"total_steps": 5, "final_lr_ratio": -0.1}, "final_lr_ratio=-0.1"),
    ],
)
def test_bad_arguments_are_named(kwargs, match) -> None:
    optimizer = torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)
    with pytest.raises(ValueError, match=match):
        WarmupCosine(optimizer, **kwargs)


def test_the_module_steps_it_per_optimizer_step_over_the_runs_steps(make_config) -> None:
    cfg = make_config(
        "experiment=smoke",
        "scheduler=cosine",
        "scheduler.warmup_fraction=0.25",
        "optimizer.lr=0.001",
    )
    module = instantiate(cfg.model, _convert_="all")
    module._trainer = SimpleNamespace(estimated_stepping_batches=8)  # what Lightning computes
    configured = module.configure_optimizers()
    assert configured["lr_scheduler"]["interval"] == "step"
    lrs = _lrs(configured["lr_scheduler"]["scheduler"], 8)
    assert max(lrs) == pytest.approx(1e-3) and lrs.index(max(lrs)) == 2
    assert lrs[-1] == pytest.approx(1e-3 * cfg.scheduler.final_lr_ratio)
    # The paper's StepLR stays per epoch.
    paper = instantiate(make_config("experiment=smoke").model, _convert_="all")
    assert paper.configure_optimizers()["lr_scheduler"]["interval"] == "epoch"


def test_out_of_range_settings_fail_at_config_time(make_config) -> None:
    with pytest.raises(ConfigError, match=r"scheduler.warmup_fraction=1.5: expected a share"):
        validate_config(make_config("scheduler=cosine", "scheduler.warmup_fraction=1.5"))
