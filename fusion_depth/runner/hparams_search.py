"""Hyperparameter search (``hparams_search=optuna``, ``conf/hparams_search/optuna.yaml``):
what a trial returns, restarting a study, and the report at its end.

Hydra's Optuna sweeper asks the study for a trial's values, launches a training run with them
as overrides, and tells the study what the run returned: :func:`objective` of its record, the
config's ``optimized_metric`` (a validation metric; a search never looks at test metrics). A run
that fails returns nothing, which the sweeper records as a failed trial; the study goes on.

:class:`SearchSummary` is the sweep's Hydra callback (it replaces
:class:`~fusion_depth.runner.sweep_summary.SweepSummary`):

* **Before the first trial** it checks the metric and the direction, takes the sweep folder's
  lock (one search process per study) and, when the study exists already, continues it:
  ``hydra.sweeper.n_trials`` is the study's total, so it is lowered to the trials still missing,
  and a trial left running by a process that died is recorded as failed (user attribute
  ``interrupted``) and its values are queued to run again, in the same run folder, which
  resumes from its last checkpoint. (This callback is the one hook that runs before the sweeper
  is built from the config; a sweeper of our own would have to live in ``hydra_plugins``.)
* **At the end** it prints one line per trial and the best one, writes ``best_params.yaml`` to
  the sweep folder (next to the sweeper's own ``optimization_results.yaml``) and prints the
  command that retrains the best configuration with three seeds.
"""

from __future__ import annotations

import logging
import math
import shlex
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, ListConfig, OmegaConf, open_dict, read_write

from fusion_depth.errors import ConfigError
from fusion_depth.metrics.depth import HIGHER_IS_BETTER, METRIC_KEYS
from fusion_depth.runner.record import RunRecord
from fusion_depth.runner.resume import RunLock
from fusion_depth.runner.sweep_summary import SweepSummary, summarize_sweep
from fusion_depth.utils.atomic import write_json_atomic, write_text_atomic
from fusion_depth.utils.overrides import show

log = logging.getLogger(__name__)

METRIC_PREFIX = "val_"
DEFAULT_METRIC = "val_rmse"
BEST_FILE = "best_params.yaml"
RETRAIN_SEEDS = (42, 43, 44)
INTERRUPTED = "interrupted"  # user attribute of a trial whose process died while it ran
# Overrides a retrain leaves out: the search preset (it would search again), the seed (the
# retrain sets three) and what a run returns to a sweeper.
_NOT_RETRAINED = ("hparams_search", "seed", "optimized_metric")


# --- what a trial returns ---------------------------------------------------------------------


def metric_key(optimized_metric: Any) -> str:
    """The metric (a :data:`~fusion_depth.metrics.depth.METRIC_KEYS` key) that ``optimized_metric``
    (``val_<metric>``) names.

    Raises:
        ConfigError: not ``val_`` and a metric key (a test metric above all).
    """
    name = optimized_metric if isinstance(optimized_metric, str) else ""
    key = name.removeprefix(METRIC_PREFIX)
    if not name.startswith(METRIC_PREFIX) or key not in METRIC_KEYS:
        options = ", ".join(METRIC_PREFIX + k for k in METRIC_KEYS)
        raise ConfigError(
            f"optimized_metric={show(optimized_metric)}: expected a validation metric, one of "
            f"{options} (a search never optimises a test metric)"
        )
    return key


def objective(record: RunRecord | None, optimized_metric: str = DEFAULT_METRIC) -> float | None:
    """What a run returns to a sweeper: ``optimized_metric`` (``val_<metric>``) at the
    validation whose checkpoint the run keeps and tests: the one with the lowest RMSE, or under
    a rule of several metrics (:class:`~fusion_depth.runner.callbacks.MajorityCheckpoint`) the
    one whose RMSE the record gives as the kept checkpoint's (for ``val_rmse``: that RMSE). None
    when there is none, or it is not finite (a sweeper records that trial as failed), and on the
    ranks that do not test."""
    key = metric_key(optimized_metric)
    if record is None:
        return None
    scored = [
        entry
        for entry in record.validation or []
        if _finite(entry.get("rmse")) and _finite(entry.get(key))
    ]
    best = record.best_val_rmse  # logged in float32: equal to its validation's to 1e-6
    kept = [e for e in scored if _finite(best) and abs(e["rmse"] - best) <= 1e-6 * abs(best)]
    if kept:
        value = kept[0][key]  # the first with the kept RMSE: Lightning keeps the first best
    elif scored:
        value = min(scored, key=lambda entry: entry["rmse"])[key]  # the first best, as kept
    elif key == "rmse":  # a record without the validation history
        value = record.best_val_rmse
    else:
        value = None
    return float(value) if _finite(value) else None


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


# --- the retrain command ----------------------------------------------------------------------


def _override_key(override: str) -> str:
    return override.partition("=")[0].lstrip("+~")


def retrain_command(
    overrides: Sequence[str], seeds: Sequence[int] = RETRAIN_SEEDS, config_name: str = "train"
) -> str:
    """``python -m fusion_depth.train -m <overrides> seed=42,43,44``: a trial's overrides as a
    sweep over ``seeds``, without the search preset; shell-quoted where needed."""
    kept = [o for o in overrides if _override_key(o) not in _NOT_RETRAINED]
    name = [] if config_name in ("", "train") else ["--config-name", config_name]
    seed = "seed=" + ",".join(str(s) for s in seeds)
    return shlex.join(["python", "-m", "fusion_depth.train", *name, "-m", *kept, seed])


def trial_overrides(params: Mapping[str, Any], fixed: Mapping[str, Any]) -> list[str]:
    """The overrides the Optuna sweeper launches a trial with (``key=value``, as it formats
    them): the fixed ones, then the searched ones."""
    merged = {**{k: v for k, v in fixed.items() if k != INTERRUPTED}, **params}
    return [f"{k}={v}" for k, v in merged.items()]


def fixed_overrides(config: DictConfig) -> dict[str, Any]:
    """The values the sweeper sets in every trial (``hydra.sweeper.params`` and command-line
    overrides that sweep nothing; the command line wins), as it parses them."""
    params = config.hydra.sweeper.get("params") or {}
    lines = [f"{k}={v}" for k, v in params.items()]
    lines += list(config.hydra.overrides.task)
    fixed: dict[str, Any] = {}
    for override in OverridesParser.create().parse_overrides(lines):
        key = override.get_key_element()
        if override.is_sweep_override():
            fixed.pop(key, None)
        else:
            fixed[key] = override.value()
    return fixed


# --- the study --------------------------------------------------------------------------------


def _direction(config: DictConfig) -> str:
    """``hydra.sweeper.direction`` as ``minimize`` or ``maximize``.

    Raises:
        ConfigError: several directions (a multi-objective study), or another word.
    """
    direction = config.hydra.sweeper.get("direction", "minimize")
    if isinstance(direction, ListConfig | list):
        if len(direction) != 1:
            raise ConfigError(
                f"hydra.sweeper.direction={show(direction)}: expected minimize or maximize (a "
                "run returns one metric, optimized_metric)"
            )
        direction = direction[0]
    name = str(getattr(direction, "name", direction))
    if name not in ("minimize", "maximize"):
        raise ConfigError(f"hydra.sweeper.direction={name}: expected minimize or maximize")
    return name


def check_search(config: DictConfig) -> tuple[str, str]:
    """(optimized_metric, direction) of a search, checked before its first trial.

    Raises:
        ConfigError: a metric that is not a validation metric, several directions, or a
            direction that would look for the worst model (``val_delta1`` minimised).
    """
    metric = config.get("optimized_metric", DEFAULT_METRIC)
    key = metric_key(metric)
    direction = _direction(config)
    better = "maximize" if HIGHER_IS_BETTER[key] else "minimize"
    if direction != better:
        raise ConfigError(
            f"hydra.sweeper.direction={direction}: {metric} is better "
            f"{'higher' if better == 'maximize' else 'lower'}; use hydra.sweeper.direction="
            f"{better}"
        )
    return metric, direction


def _quiet_optuna() -> None:
    """Optuna's and Alembic's (its schema migrations') info lines off: Alembic logs one per
    plugin it sets up when the storage is first opened."""
    logging.getLogger("alembic").setLevel(logging.WARNING)
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)


def _load_study(storage: str, study_name: str) -> Any:
    """The study, or None when the storage has none of that name."""
    import optuna

    try:
        return optuna.load_study(study_name=study_name, storage=storage)
    except KeyError:
        return None


def continue_study(storage: str, study_name: str) -> tuple[int, int]:
    """Make a stored study ready to go on: each trial still marked running (its process died)
    is recorded as failed with the user attribute ``interrupted`` and its values are queued to
    run again. Returns (trials done, trials interrupted now); done counts the finished trials
    other than interrupted ones, and is 0 for a study that does not exist yet."""
    _quiet_optuna()
    from optuna.exceptions import ExperimentalWarning
    from optuna.trial import TrialState

    study = _load_study(storage, study_name)
    if study is None:
        return 0, 0
    stale = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
    for trial in stale:
        study._storage.set_trial_user_attr(trial._trial_id, INTERRUPTED, True)
        study._storage.set_trial_state(trial._trial_id, TrialState.FAIL)
        with warnings.catch_warnings():  # optuna 2.10 calls enqueue_trial experimental
            warnings.simplefilter("ignore", ExperimentalWarning)
            study.enqueue_trial(dict(trial.params))  # the same values: the same run folder
    done = sum(
        1
        for t in study.get_trials(deepcopy=False)
        if t.state.is_finished() and not t.user_attrs.get(INTERRUPTED)
    )
    return done, len(stale)


class SearchSummary(SweepSummary):
    """The Hydra callback of ``hparams_search=optuna`` (see the module docstring): continues a
    stored study before the first trial, and reports the best trial at the end."""

    def __init__(self) -> None:
        self._lock: RunLock | None = None
        self._n_trials: int | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Check the search, lock the sweep folder and continue a stored study: the sweeper,
        built from ``config`` right after this, then runs only the missing trials."""
        check_search(config)
        _quiet_optuna()
        sweeper = config.hydra.sweeper
        sweep_dir = Path(config.hydra.sweep.dir)
        sweep_dir.mkdir(parents=True, exist_ok=True)  # SQLite creates the file, not its folder
        self._lock = RunLock(sweep_dir).__enter__()  # held until the end or the process's exit
        self._n_trials = int(sweeper.n_trials)
        storage, name = sweeper.get("storage"), sweeper.get("study_name")
        if storage is None or name is None:
            return
        done, interrupted = continue_study(str(storage), str(name))
        if not done and not interrupted:
            return
        to_go = max(self._n_trials - done, 0)
        with read_write(sweeper), open_dict(sweeper):
            sweeper.n_trials = to_go
        again = f", {interrupted} interrupted trial(s) run again" if interrupted else ""
        print(
            f"Continuing study {name} ({storage}): {done} of {self._n_trials} trials "
            f"done{again}; {to_go} to go",
            flush=True,
        )

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Print the trials and the best one, write ``best_params.yaml`` and the sweep's
        ``sweep_summary.json``; exit 1 when no trial completed."""
        sweep_dir = Path(config.hydra.sweep.dir)
        try:
            jobs = summarize_sweep(sweep_dir)
            write_json_atomic(sweep_dir / "sweep_summary.json", jobs)
            report = search_report(config, jobs, self._n_trials)
        finally:
            if self._lock is not None:
                self._lock.__exit__(None, None, None)
                self._lock = None
        print("\n".join(report["lines"]), flush=True)
        if report["best"] is None:
            raise SystemExit(1)
        write_text_atomic(sweep_dir / BEST_FILE, OmegaConf.to_yaml(report["best"]))


def _trial_rows(study: Any, jobs: list[dict]) -> list[dict]:
    """One row per trial of ``study``: number, state, value, searched values, overrides, run
    folder and error (matched with the sweep's job folders by their overrides)."""
    by_overrides = {frozenset(j["overrides"]): j for j in jobs}
    rows = []
    for trial in study.get_trials(deepcopy=False):
        overrides = trial_overrides(trial.params, trial.user_attrs)
        job = by_overrides.get(frozenset(overrides), {})
        state = trial.state.name.lower()
        if trial.user_attrs.get(INTERRUPTED):
            error = "interrupted (its values were queued to run again)"
        else:
            error = job.get("error")
        rows.append(
            {
                "number": trial.number,
                "state": state,
                "value": trial.value if state == "complete" else None,
                "params": dict(trial.params),
                "overrides": overrides,
                "run_dir": job.get("dir"),
                "error": error,
            }
        )
    return rows


def _rows_without_storage(config: DictConfig, jobs: list[dict]) -> list[dict]:
    """The best trial alone, from the sweeper's ``optimization_results.yaml`` (a study kept in
    memory, ``hydra.sweeper.storage=null``, is gone when the sweep ends)."""
    results = Path(config.hydra.sweep.dir) / "optimization_results.yaml"
    if not results.is_file():
        return []
    best = OmegaConf.to_container(OmegaConf.load(results))
    params = best.get("best_params") or {}
    overrides = trial_overrides(params, fixed_overrides(config))
    job = {frozenset(j["overrides"]): j for j in jobs}.get(frozenset(overrides), {})
    return [
        {
            "number": None,
            "state": "complete",
            "value": best.get("best_value"),
            "params": params,
            "overrides": overrides,
            "run_dir": job.get("dir"),
            "error": None,
        }
    ]


def search_report(config: DictConfig, jobs: list[dict], n_trials: int | None) -> dict:
    """The end-of-search report: ``lines`` to print, and ``best`` (what ``best_params.yaml``
    holds; None when no trial completed)."""
    metric, direction = check_search(config)
    sweeper = config.hydra.sweeper
    storage, name = sweeper.get("storage"), sweeper.get("study_name")
    _quiet_optuna()
    study = _load_study(str(storage), str(name)) if storage and name else None
    rows = _trial_rows(study, jobs) if study is not None else _rows_without_storage(config, jobs)
    sweep_dir = config.hydra.sweep.dir
    lines = [f"Search summary ({sweep_dir}), study {name}, {metric} ({direction}):"]
    for row in rows:
        value = f"{row['value']:.4f}" if row["value"] is not None else "-"
        searched = " ".join(f"{k}={v}" for k, v in row["params"].items())
        detail = f"  {row['error']}" if row["error"] else ""
        number = "best" if row["number"] is None else row["number"]
        lines.append(f"  trial {number:<4} {row['state']:<8} {value:>10}  {searched}{detail}")
    counts: dict[str, int] = {}
    for row in rows:
        counts[row["state"]] = counts.get(row["state"], 0) + 1
    tally = ", ".join(f"{n} {state}" for state, n in counts.items())
    wanted = f" ({n_trials} wanted)" if n_trials is not None else ""
    lines.append(f"{len(rows)} trials: {tally or 'none'}{wanted}")
    complete = [r for r in rows if r["state"] == "complete" and r["value"] is not None]
    if not complete:
        lines.append("No trial completed: there is no best configuration")
        return {"lines": lines, "best": None}
    pick = max if direction == "maximize" else min
    best = pick(complete, key=lambda r: r["value"])
    command = retrain_command(best["overrides"], config_name=config.hydra.job.config_name)
    best_file = Path(sweep_dir) / BEST_FILE
    lines.append(
        f"Best: trial {'?' if best['number'] is None else best['number']}, "
        f"{metric} {best['value']:.4f}"
    )
    lines += [f"  {k}: {v}" for k, v in best["params"].items()]
    if best["run_dir"]:
        lines.append(f"  run: {best['run_dir']}")
    lines.append(f"Written to {best_file}. Retrain it with three seeds:")
    lines.append(f"  {command}")
    record = {
        "study": None if name is None else str(name),
        "storage": None if storage is None else str(storage),
        "optimized_metric": metric,
        "direction": direction,
        "n_trials": n_trials,
        "trials": counts,
        "best_trial": best["number"],
        "best_value": best["value"],
        "best_params": best["params"],
        "overrides": best["overrides"],
        "run_dir": best["run_dir"],
        "retrain": command,
    }
    return {"lines": lines, "best": record}
