"""``hparams_search=optuna``: a smoke study killed during a trial and started again ends with all
its trials, the best configuration written and a retrain command that composes; a failing trial
is recorded as failed and the study goes on; trials return a validation metric, never a test
one."""

from __future__ import annotations

import json
import math
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import optuna
import pytest
from helpers import run_module
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf
from optuna.trial import TrialState

from fusion_depth.config import CONF_DIR, SWEEPS_DIR, check_config_values
from fusion_depth.config.hydra_main import register_sweeps
from fusion_depth.errors import ConfigError
from fusion_depth.runner.hparams_search import (
    BEST_FILE,
    INTERRUPTED,
    SearchSummary,
    check_search,
    metric_key,
    objective,
    retrain_command,
)
from fusion_depth.runner.record import RunRecord
from fusion_depth.runner.resume import RunLockedError

STUDY = "fusion_depth"  # conf/hparams_search/optuna.yaml: hydra.sweeper.study_name


def _search_args(sweep_dir: Path, n_trials: int, *extra: str) -> list[str]:
    return [
        "fusion_depth.train",
        "-m",
        "hparams_search=optuna",
        "experiment=smoke",
        "logger=none",
        "trainer.max_epochs=1",
        *extra,
        f"hydra.sweeper.n_trials={n_trials}",
        f"hydra.sweep.dir={sweep_dir}",
    ]


def _study(sweep_dir: Path) -> optuna.Study:
    return optuna.load_study(study_name=STUDY, storage=f"sqlite:///{sweep_dir}/optuna.db")


def _retrain_line(stdout: str) -> str:
    (line,) = [s.strip() for s in stdout.splitlines() if s.strip().startswith("python -m")]
    return line


def _compose_retrain(line: str):
    """The retrain command's config, composed as the command would compose its first job."""
    words = shlex.split(line)
    assert words[:4] == ["python", "-m", "fusion_depth.train", "-m"], line
    overrides = OverridesParser.create().parse_overrides(words[4:])
    seeds = next(o for o in overrides if o.key_or_group == "seed")
    assert list(seeds.sweep_string_iterator()) == ["42", "43", "44"]
    single = [
        f"{o.get_key_element()}={next(iter(o.sweep_string_iterator()))}"
        if o.is_sweep_override()
        else o.input_line
        for o in overrides
    ]
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(CONF_DIR, version_base="1.3"):
            cfg = compose("train", overrides=single, return_hydra_config=True)
    finally:
        GlobalHydra.instance().clear()
    check_config_values(cfg)
    return cfg


@pytest.mark.slow
def test_a_killed_study_started_again_ends_with_all_its_trials(tmp_path) -> None:
    sweep_dir = tmp_path / "search"
    args = _search_args(sweep_dir, 3)
    with open(tmp_path / "first.log", "w") as out:
        process = subprocess.Popen(
            [sys.executable, "-m", *args],
            cwd=tmp_path,
            env=dict(os.environ),
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            # Killed once the first trial has finished and the second has started.
            deadline = time.monotonic() + 600
            while time.monotonic() < deadline and process.poll() is None:
                started = list(sweep_dir.glob("*/.hydra/overrides.yaml"))
                finished = list(sweep_dir.glob("*/metrics.json"))
                if len(started) >= 2 and len(finished) == 1:
                    break
                time.sleep(0.05)
            assert process.poll() is None, (tmp_path / "first.log").read_text()[-3000:]
        finally:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    states = [t.state for t in _study(sweep_dir).trials]
    assert states == [TrialState.COMPLETE, TrialState.RUNNING]
    interrupted = _study(sweep_dir).trials[1].params

    done = run_module(args, cwd=tmp_path, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "1 of 3 trials done, 1 interrupted trial(s) run again; 2 to go" in done.stdout

    trials = _study(sweep_dir).trials
    complete = [t for t in trials if t.state == TrialState.COMPLETE]
    assert len(complete) == 3 and all(math.isfinite(t.value) for t in complete)
    (failed,) = [t for t in trials if t.state != TrialState.COMPLETE]
    assert failed.state == TrialState.FAIL and failed.user_attrs[INTERRUPTED] is True
    # The interrupted values ran again, in the interrupted run's folder.
    assert [t.params for t in complete].count(interrupted) == 1
    assert len(list(sweep_dir.glob("*/.hydra/overrides.yaml"))) == 3
    assert len(list(sweep_dir.glob("*/metrics.json"))) == 3

    best = OmegaConf.to_container(OmegaConf.load(sweep_dir / BEST_FILE))
    winner = min(complete, key=lambda t: t.value)
    assert best["best_trial"] == winner.number and best["best_value"] == winner.value
    assert best["best_params"] == winner.params
    assert best["trials"] == {"complete": 3, "fail": 1}
    assert best["optimized_metric"] == "val_rmse"
    # Each trial returned its best validation RMSE, not a test metric.
    record = RunRecord.from_json(json.loads((Path(best["run_dir"]) / "metrics.json").read_text()))
    assert winner.value == pytest.approx(record.best_val_rmse, rel=1e-5)
    assert winner.value != record.test["rmse"]

    line = _retrain_line(done.stdout)
    assert line == best["retrain"]
    cfg = _compose_retrain(line)
    assert cfg.hydra.sweeper._target_ == "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
    assert cfg.loss.pixel == "berhu" and cfg.fusion.mode == "concat"
    assert cfg.trainer.max_epochs == 1 and cfg.dataset.num_train == 8  # experiment=smoke
    assert cfg.optimizer.lr == winner.params["optimizer.lr"]
    for key in ("w_ssim", "w_edge", "w_pixel", "berhu_threshold"):
        assert cfg.loss[key] == winner.params[f"loss.{key}"]
    assert cfg.model.net.sparse_encoding == winner.params["model.net.sparse_encoding"]


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
def test_a_failing_trial_is_recorded_as_failed_and_the_study_goes_on(tmp_path) -> None:
    sweep_dir = tmp_path / "search"
    sweep_dir.mkdir()
    # The first trial gets an encoding no network has (it fails the config checks), the
    # second a real one.
    study = optuna.create_study(
        study_name=STUDY, storage=f"sqlite:///{sweep_dir}/optuna.db", direction="minimize"
    )
    study.enqueue_trial({"model.net.sparse_encoding": "bogus"})
    study.enqueue_trial({"model.net.sparse_encoding": "log"})
    args = _search_args(sweep_dir, 2, "model.net.sparse_encoding=choice(log,bogus)")
    done = run_module(args, cwd=tmp_path, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    first, second = _study(sweep_dir).trials
    assert first.state == TrialState.FAIL
    assert second.state == TrialState.COMPLETE and math.isfinite(second.value)
    (failure,) = sweep_dir.glob("*/failure.json")
    assert "sparse_encoding=bogus" in failure.read_text()
    summary = done.stdout[done.stdout.index("Search summary") :]
    assert "trial 0    fail" in summary and "model.net.sparse_encoding=bogus: expected" in summary
    assert "2 trials: 1 fail, 1 complete (2 wanted)" in summary
    assert "Best: trial 1" in summary


def _record(validation: list[dict], best: float | None = None) -> RunRecord:
    return RunRecord(validation=validation, best_val_rmse=best, test={"rmse": 0.5})


def test_the_objective_is_a_validation_metric_at_the_kept_checkpoint() -> None:
    record = _record(
        [
            {"epoch": 0, "rmse": 3.0, "abs_rel": 0.3, "delta1": 0.5},
            {"epoch": 1, "rmse": 2.0, "abs_rel": 0.4, "delta1": 0.6},
            {"epoch": 2, "rmse": 2.0, "abs_rel": 0.1, "delta1": 0.7},  # not better: not kept
            {"epoch": 3, "rmse": float("nan"), "abs_rel": 0.0, "delta1": 0.9},
        ]
    )
    assert objective(record) == 2.0
    assert objective(record, "val_abs_rel") == 0.4
    assert objective(record, "val_delta1") == 0.6
    # a rule of several metrics kept epoch 2, whose RMSE (float32) the record gives
    assert objective(_record(record.validation, best=2.0000001), "val_abs_rel") == 0.4
    kept_later = [*record.validation[:2], {**record.validation[2], "rmse": 2.5}]
    assert objective(_record(kept_later, best=2.5000001), "val_abs_rel") == 0.1
    assert objective(_record([], best=1.5)) == 1.5  # an older record: no validation history
    assert objective(_record([], best=float("inf"))) is None  # a failed trial, not a value
    assert objective(None) is None


@pytest.mark.parametrize("name", ["test_rmse", "rmse", "val_nope", None, 3])
def test_a_test_or_unknown_metric_is_refused_in_one_line(name) -> None:
    with pytest.raises(ConfigError, match=r"^optimized_metric=.*expected a validation metric"):
        metric_key(name)


def _search_config(*overrides: str, preset: str = "optuna"):
    """``train`` with ``hparams_search=<preset>``, or the search reproduction sweeps/<preset>."""
    GlobalHydra.instance().clear()
    register_sweeps()
    reproduction = (Path(SWEEPS_DIR) / f"{preset}.yaml").is_file()
    try:
        with initialize_config_dir(CONF_DIR, version_base="1.3"):
            return compose(
                preset if reproduction else "train",
                overrides=[*([] if reproduction else [f"hparams_search={preset}"]), *overrides],
                return_hydra_config=True,
            )
    finally:
        GlobalHydra.instance().clear()


# The built-in dataset's recipe searches and the budget every trial of each trains with:
# (encoder, batch size, epochs, batches per epoch), a (key, value) of the schedule's config that
# makes it the warm-up + cosine one, and keys that must be searched.
RECIPE_SEARCHES = {
    "procedural_recipe_search": (
        ("resnet18", 8, 15, 100),
        ("_target_", "fusion_depth.optim.schedules.WarmupCosine"),
        {"optimizer.lr", "dataset.num_train"},
    ),
    "procedural_recipe_search_19_epochs": (
        ("resnet10t", 16, 19, 125),
        ("name", "cosine"),
        {"optimizer.lr", "loss.w_pixel"},
    ),
}


@pytest.mark.parametrize("preset", sorted(RECIPE_SEARCHES))
def test_the_built_in_recipe_search_gives_every_trial_the_same_budget(preset: str) -> None:
    """sweeps/procedural_recipe_search(_19_epochs): each corner of its space composes, passes the
    config checks and trains with the fixed budget (so a trial's cost does not depend on its
    values)."""
    budget_expected, schedule, must_search = RECIPE_SEARCHES[preset]
    params = _search_config(preset=preset).hydra.sweeper.params
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()])
    fixed = [o.input_line for o in parsed if not o.is_sweep_override()]
    searched = [o for o in parsed if o.is_sweep_override()]
    assert {o.key_or_group for o in searched} >= must_search
    for corner in (0, -1):  # every searched value at its low end, then at its high end
        values = []
        for override in searched:
            sweep = override.value()
            if hasattr(sweep, "list"):  # choice(...)
                values.append(f"{override.key_or_group}={sweep.list[corner]}")
            else:  # interval(...), possibly tagged log
                bound = sweep.start if corner == 0 else sweep.end
                values.append(f"{override.key_or_group}={bound}")
        cfg = _search_config(*fixed, *values, preset=preset)
        check_config_values(cfg)
        for value in values:  # each value reached the run's config
            key, _, text = value.partition("=")
            assert float(OmegaConf.select(cfg, key)) == pytest.approx(float(text)), value
        budget = (
            cfg.backbone.name,
            cfg.data.batch_size,
            cfg.trainer.max_epochs,
            cfg.trainer.limit_train_batches,
        )
        assert budget == budget_expected
        assert cfg.scheduler[schedule[0]] == schedule[1]


def test_the_preset_composes_with_the_config_checks_and_a_direction_must_fit_the_metric() -> None:
    cfg = _search_config()
    check_config_values(cfg)
    assert cfg.optimized_metric == "val_rmse"
    assert cfg.hydra.sweeper.storage == f"sqlite:///{cfg.hydra.sweep.dir}/optuna.db"
    params = cfg.hydra.sweeper.params
    assert params["loss"] == "berhu" and params["fusion"] == "concat"
    # every searched key is a key of the composed config
    for key in params:
        assert "." not in key or OmegaConf.select(cfg, key) is not None, key
    assert check_search(cfg) == ("val_rmse", "minimize")
    assert check_search(
        _search_config("optimized_metric=val_delta1", "hydra.sweeper.direction=maximize")
    )
    with pytest.raises(ConfigError, match="val_delta1 is better higher"):
        check_search(_search_config("optimized_metric=val_delta1"))


def test_the_retrain_command_leaves_out_the_search_and_quotes_for_the_shell() -> None:
    command = retrain_command(
        ["hparams_search=optuna", "seed=7", "loss=berhu", "dataset.root=/data/my runs"]
    )
    assert shlex.split(command) == [
        "python", "-m", "fusion_depth.train", "-m", "loss=berhu", "dataset.root=/data/my runs",
        "seed=42,43,44",
    ]  # fmt: skip


@pytest.mark.filterwarnings("ignore::optuna.exceptions.ExperimentalWarning")
def test_a_stored_study_continues_to_its_total_and_runs_an_interrupted_trial_again(
    tmp_path,
) -> None:
    sweep_dir = tmp_path / "search"
    cfg = _search_config(f"hydra.sweep.dir={sweep_dir}", "hydra.sweeper.n_trials=5")
    sweep_dir.mkdir()
    study = optuna.create_study(study_name=STUDY, storage=cfg.hydra.sweeper.storage)
    study.optimize(lambda t: t.suggest_float("optimizer.lr", 1e-5, 1e-3, log=True), n_trials=2)
    running = study.ask()  # its process died
    lr = running.suggest_float("optimizer.lr", 1e-5, 1e-3, log=True)

    callback = SearchSummary()
    callback.on_multirun_start(cfg)
    try:
        assert cfg.hydra.sweeper.n_trials == 3  # 5 in all, 2 done
        with pytest.raises(RunLockedError):  # one search process per study
            SearchSummary().on_multirun_start(_search_config(f"hydra.sweep.dir={sweep_dir}"))
    finally:
        callback._lock.__exit__(None, None, None)
    trials = _study(sweep_dir).trials
    assert trials[2].state == TrialState.FAIL and trials[2].user_attrs == {INTERRUPTED: True}
    assert trials[3].state == TrialState.WAITING
    assert trials[3].system_attrs["fixed_params"] == {"optimizer.lr": lr}


@pytest.mark.slow
def test_a_study_whose_trials_all_fail_ends_in_one_line(tmp_path) -> None:
    # Every trial fails the config checks: the sweeper's request for the best trial then
    # fails inside Optuna, which the user reads as one line, not Optuna's traceback.
    sweep_dir = tmp_path / "search"
    done = run_module(
        _search_args(sweep_dir, 2, "model.net.sparse_encoding=bogus"), cwd=tmp_path, timeout=600
    )
    assert done.returncode == 1
    assert "Traceback" not in done.stderr, done.stderr[-3000:]
    assert "hparams_search: no trial of the study completed" in done.stderr
    assert len(list(sweep_dir.glob("*/failure.json"))) == 2
    assert all(t.state == TrialState.FAIL for t in _study(sweep_dir).trials)
