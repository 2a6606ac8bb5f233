"""``scheduler=cosine``: linear warm-up then cosine decay, stepped per optimizer step over the
run's steps; the paper's ``scheduler=step`` stays per epoch; ``create_schedule`` builds either by
name (model=densedepth's default, which follows a dataset's recipe)."""

from __future__ import annotations

import functools
import inspect
import math
import re
import shlex
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
from helpers import compose_config
from hydra.utils import instantiate
from omegaconf import OmegaConf

from fusion_depth.config import SWEEPS_DIR, validate_config
from fusion_depth.errors import ConfigError
from fusion_depth.optim.schedules import (
    SCHEDULE_ARGUMENTS,
    SCHEDULES,
    Constant,
    WarmupCosine,
    create_schedule,
    schedule_arguments,
    schedule_interval,
)


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


@pytest.mark.slow
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


def _optimizer() -> torch.optim.Optimizer:
    return torch.optim.SGD([torch.zeros(1, requires_grad=True)], lr=1.0)


def test_create_schedule_builds_the_named_schedule_with_its_own_arguments() -> None:
    step = create_schedule(_optimizer(), "step", step_size=2, gamma=0.5)
    assert isinstance(step, torch.optim.lr_scheduler.StepLR)
    lrs = []
    for _ in range(5):  # per epoch
        lrs.append(step.optimizer.param_groups[0]["lr"])
        step.optimizer.step()
        step.step()
    assert lrs == pytest.approx([1.0, 1.0, 0.5, 0.5, 0.25])
    cosine = create_schedule(_optimizer(), "cosine", total_steps=10, warmup_fraction=0.2)
    assert isinstance(cosine, WarmupCosine)
    assert (cosine.total_steps, cosine.warmup_steps, cosine.final_lr_ratio) == (10, 2, 0.01)
    constant = create_schedule(_optimizer(), "constant")
    assert isinstance(constant, Constant)
    assert set(SCHEDULES) == {"step", "cosine", "constant"}


@pytest.mark.parametrize(
    "name,kwargs,match",
    [
        ("onecycle", {}, r"^name='onecycle': unknown schedule; expected one of step"),
        ("cosine", {"total_steps": 5, "step_size": 3}, r"the cosine schedule takes no step_size"),
        ("step", {"step_size": 3, "warmup_fraction": 0.1}, r"step schedule takes no warmup_f"),
        ("step", {"gamma": 0.5}, r"^step_size: the step schedule needs it; it is null"),
    ],
)
def test_create_schedule_refuses_an_unknown_name_or_the_other_schedules_argument(
    name, kwargs, match
) -> None:
    with pytest.raises(ValueError, match=match):
        create_schedule(_optimizer(), name, **kwargs)


def test_the_interval_follows_the_name_a_partial_gives() -> None:
    assert schedule_interval(functools.partial(create_schedule, name="cosine")) == "step"
    assert schedule_interval(functools.partial(create_schedule, name="step")) == "epoch"
    assert schedule_interval(functools.partial(WarmupCosine, warmup_fraction=0.1)) == "step"
    assert schedule_interval(torch.optim.lr_scheduler.StepLR) == "epoch"


@pytest.mark.slow
def test_the_recipe_names_its_schedule_and_the_command_line_adjusts_it(make_config) -> None:
    """model=densedepth's default schedule is the recipe's (cosine) on the built-in dataset and
    the paper's StepLR elsewhere; either takes its own arguments from the command line, and an
    argument of the other schedule fails at config time, naming it."""
    tuned = make_config("scheduler.warmup_fraction=0.1")
    assert (tuned.scheduler.name, tuned.scheduler.warmup_fraction) == ("cosine", 0.1)
    validate_config(tuned)
    smoke = make_config("experiment=smoke", "scheduler.step_size=3")  # the model's own: the paper's
    assert (smoke.scheduler.name, smoke.scheduler.step_size, smoke.scheduler.gamma) == (
        "step",
        3,
        0.2,
    )
    validate_config(smoke)
    module = instantiate(smoke.model, _convert_="all")
    scheduler = module.configure_optimizers()["lr_scheduler"]["scheduler"]
    assert isinstance(scheduler, torch.optim.lr_scheduler.StepLR) and scheduler.step_size == 3
    with pytest.raises(ConfigError, match=r"scheduler.step_size=3: the cosine schedule takes no"):
        validate_config(make_config("scheduler.step_size=3"))
    with pytest.raises(ConfigError, match=r"scheduler.name='bogus': unknown schedule"):
        validate_config(make_config("scheduler.name=bogus"))
    with pytest.raises(ConfigError, match=r"scheduler.warmup_fraction=1.5: expected a share"):
        validate_config(make_config("scheduler.warmup_fraction=1.5"))
    with pytest.raises(ConfigError, match=r"scheduler.step_size: the step schedule needs it"):
        validate_config(make_config("experiment=smoke", "scheduler.step_size=null"))
    # A schedule chosen by group keeps its own arguments required.
    with pytest.raises(ConfigError, match=r"scheduler.step_size=null: expected an integer ≥ 1"):
        validate_config(make_config("scheduler=step", "scheduler.step_size=null"))


def test_create_schedule_takes_every_named_schedules_arguments() -> None:
    """A schedule added to the table without its arguments in create_schedule would fail here
    rather than in a config."""
    takes = set(inspect.signature(create_schedule).parameters)
    for name in SCHEDULES:
        assert set(schedule_arguments(name)) <= set(SCHEDULE_ARGUMENTS) <= takes, name


def test_a_cosine_schedule_saved_mid_run_resumes_on_the_same_learning_rates(tmp_path) -> None:
    """The recipe's per-step schedule goes into last.ckpt as plain data (loaded with
    weights_only=True, as checkpoints are) and continues exactly where it stopped."""
    first = create_schedule(_optimizer(), "cosine", total_steps=12, warmup_fraction=0.25)
    before = _lrs(first, 5)
    torch.save(first.state_dict(), tmp_path / "schedule.pt")
    second = create_schedule(_optimizer(), "cosine", total_steps=12, warmup_fraction=0.25)
    second.load_state_dict(torch.load(tmp_path / "schedule.pt", weights_only=True))
    second.optimizer.param_groups[0]["lr"] = second.get_last_lr()[0]  # as Lightning restores it
    after = _lrs(second, 7)
    reference = _lrs(
        create_schedule(_optimizer(), "cosine", total_steps=12, warmup_fraction=0.25), 12
    )
    assert before[:5] + after == pytest.approx(reference)


def _lr_by_epoch(cfg, epochs: int) -> list[float]:
    """The learning rate of each epoch under ``cfg``'s optimizer and schedule, as built."""
    optimizer = instantiate(cfg.optimizer)(params=[torch.nn.Parameter(torch.zeros(1))])
    scheduler = instantiate(cfg.scheduler)(optimizer=optimizer)
    rates = []
    for _ in range(epochs):
        rates.append(optimizer.param_groups[0]["lr"])
        optimizer.step()
        scheduler.step()
    return rates


def test_each_model_brings_its_published_recipe(make_config) -> None:
    """model=sparse_to_dense trains as sparse-to-dense.pytorch's main.py does (SGD 0.01, momentum
    0.9, weight decay 1e-4, lr_init * 0.1 ** (epoch // 5), batch 8, 15 epochs); model=radarnet as
    the FusionNet script (Adam 1e-3, no decay, one rate, batch 16, 450 epochs). Each is composed
    on a recorded dataset (KITTI, CARLA): the built-in dataset has its own recipe for each (the
    test below)."""
    s2d = make_config(
        "model=sparse_to_dense", "dataset=kitti", "dataset.root=/k", "dataset.raw_root=/r"
    )
    validate_config(s2d)
    optimizer = instantiate(s2d.optimizer)(params=[torch.nn.Parameter(torch.zeros(1))])
    assert isinstance(optimizer, torch.optim.SGD)
    group = optimizer.param_groups[0]
    assert (group["momentum"], group["weight_decay"], group["nesterov"]) == (0.9, 1e-4, False)
    expected = [0.01 * 0.1 ** (epoch // 5) for epoch in range(15)]
    assert _lr_by_epoch(s2d, 15) == pytest.approx(expected)
    assert (s2d.data.batch_size, s2d.trainer.max_epochs) == (8, 15)

    radarnet = make_config("model=radarnet", "fusion=concat", "dataset=carla", "dataset.root=/c")
    validate_config(radarnet)
    assert instantiate(radarnet.optimizer)(
        params=[torch.nn.Parameter(torch.zeros(1))]
    ).__class__ is (torch.optim.Adam)
    assert _lr_by_epoch(radarnet, 12) == pytest.approx([1e-3] * 12)
    assert radarnet.optimizer.weight_decay == 0.0
    assert (radarnet.data.batch_size, radarnet.trainer.max_epochs) == (16, 450)


def _reference_command(sweep: str) -> list[str]:
    """The overrides of the search sweep's reference trial, as its header prints them: the
    ``python -m fusion_depth.train --config-name <sweep> -m`` command that names a scheduler."""
    text = Path(SWEEPS_DIR, f"{sweep}.yaml").read_text()
    header = "\n".join(
        line.removeprefix("#").strip() for line in text.splitlines() if line.startswith("#")
    ).replace("\\\n", " ")
    commands = [c for c in header.splitlines() if c.startswith("python -m fusion_depth.train")]
    (command,) = [c for c in commands if re.search(r"\bscheduler=", c)]
    given = shlex.split(command, comments=True)
    given = given[given.index("--config-name") + 3 :]  # after "--config-name <sweep> -m"
    # the sweeper's values for the keys not given (each a single value in these sweeps)
    params = OmegaConf.create(text).hydra.sweeper.params
    keys = {override.partition("=")[0] for override in given}
    return [*given, *(f"{key}={value}" for key, value in params.items() if key not in keys)]


@pytest.mark.parametrize(
    "sweep,optimizer_class,epochs,expected",
    [
        (  # sparse-to-dense.pytorch's main.py: lr_init * 0.1 ** (epoch // 5), lr_init 0.01
            "procedural_recipe_search_sparse_to_dense",
            torch.optim.SGD,
            15,
            [0.01 * 0.1 ** (epoch // 5) for epoch in range(15)],
        ),
        ("procedural_recipe_search_radarnet", torch.optim.Adam, 4, [1e-3] * 4),  # one rate
    ],
)
def test_a_searchs_reference_trial_trains_with_its_authors_schedule(
    packaged_sweeps, tmp_path, sweep, optimizer_class, epochs, expected
) -> None:
    """The command a search sweep's header gives for its reference trial composes, on the
    built-in dataset, to the authors' schedule, not the built-in recipe's warm-up + cosine
    (there, ``scheduler=for_<model>`` names the recipe's)."""
    cfg = compose_config(_reference_command(sweep), tmp_path / "run", config_name=sweep)
    validate_config(cfg)
    optimizer = instantiate(cfg.optimizer)(params=[torch.nn.Parameter(torch.zeros(1))])
    assert type(optimizer) is optimizer_class
    assert cfg.trainer.max_epochs == epochs
    assert _lr_by_epoch(cfg, epochs) == pytest.approx(expected)


@pytest.mark.parametrize(
    "model,optimizer_class,hyperparameters,epochs,batches",
    [
        ("sparse_to_dense", torch.optim.SGD, {"momentum": 0.9, "weight_decay": 1e-4}, 30, 100),
        ("radarnet", torch.optim.Adam, {"weight_decay": 0.0}, 10, 40),
    ],
)
def test_the_built_in_dataset_brings_each_model_its_own_recipe(
    make_config, model, optimizer_class, hyperparameters, epochs, batches
) -> None:
    """conf/experiment/procedural_<model>.yaml: the authors' optimizer (Sparse-to-Dense's SGD with
    momentum 0.9 and weight decay 1e-4, RadarNet's Adam without decay) at the searched peak 3e-2,
    5 % warm-up then cosine to 1 %, batch 8 from a 6,400-frame pool, for the default run's wall
    time (docs/results/methods.md)."""
    cfg = make_config(f"model={model}", "fusion=concat")
    validate_config(cfg)
    optimizer = instantiate(cfg.optimizer)(params=[torch.nn.Parameter(torch.zeros(1))])
    assert type(optimizer) is optimizer_class
    group = optimizer.param_groups[0]
    assert {key: group[key] for key in hyperparameters} == hyperparameters
    assert group["lr"] == 3e-2
    trainer = cfg.trainer
    assert (cfg.data.batch_size, trainer.max_epochs, trainer.limit_train_batches) == (
        8,
        epochs,
        batches,
    )
    assert cfg.dataset.num_train == 6400
    rates = _lrs(instantiate(cfg.scheduler)(optimizer, total_steps=1000), 1000)
    assert rates[0] < 3e-2 * 0.05 and max(rates) == pytest.approx(3e-2)
    assert rates.index(max(rates)) in range(49, 51)  # the peak after 5 % of the steps
    assert rates[-1] == pytest.approx(3e-4, rel=0.05)  # decays to 1 % of the peak


@pytest.mark.parametrize("model", ["densedepth", "sparse_to_dense", "radarnet"])
def test_experiment_paper_puts_every_model_under_the_papers_recipe(make_config, model) -> None:
    cfg = make_config(f"model={model}", "fusion=concat", "experiment=paper")
    validate_config(cfg)
    optimizer = instantiate(cfg.optimizer)(params=[torch.nn.Parameter(torch.zeros(1))])
    assert type(optimizer) is torch.optim.Adam and optimizer.param_groups[0]["lr"] == 1e-4
    assert _lr_by_epoch(cfg, 15) == pytest.approx([1e-4 * 0.2 ** (e // 7) for e in range(15)])
    assert (cfg.data.batch_size, cfg.trainer.max_epochs) == (2, 20)


def test_the_command_line_and_a_datasets_recipe_win_over_a_models(make_config) -> None:
    cfg = make_config(
        "model=sparse_to_dense", "optimizer=adamw", "data.batch_size=4", "trainer.max_epochs=3"
    )
    validate_config(cfg)
    optimizer = instantiate(cfg.optimizer)(params=[torch.nn.Parameter(torch.zeros(1))])
    assert type(optimizer) is torch.optim.AdamW
    assert (cfg.data.batch_size, cfg.trainer.max_epochs) == (4, 3)
    default = make_config()  # model=densedepth on the built-in dataset: its own recipe
    assert (default.optimizer.lr, default.scheduler.name) == (3e-3, "cosine")
    assert (default.data.batch_size, default.trainer.max_epochs) == (16, 22)
