"""RadarNet's checkpoint rule (:class:`MajorityCheckpoint`): the validations it keeps are those
its reference code keeps, a run tests and records the kept one, and the rule's state survives a
resume and refuses a hostile one."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from fusion_depth.runner.callbacks import MajorityCheckpoint
from fusion_depth.runner.hparams_search import objective
from fusion_depth.runner.record import RunRecord
from fusion_depth.runner.resume import check_resume_state
from fusion_depth.utils.checkpoint_file import CheckpointError

RADARNET = {"val/mae": 1e-5, "val/rmse": 1e-5, "val/imae": 0.01, "val/irmse": 0.01}


def _radarnets_kept_steps(rows: list[tuple[float, float, float, float]]) -> list[int]:
    """A line-by-line copy of RadarNet's ``fusionnet_main.py`` ``validate`` tail: MAE and RMSE
    in millimetres, iMAE and iRMSE in 1/km, each rounded to 2 decimals."""
    best = {"mae": np.inf, "rmse": np.inf, "imae": np.inf, "irmse": np.inf}
    kept = []
    for step, (mae, rmse, imae, irmse) in enumerate(rows):
        n_improve = 0
        if np.round(mae, 2) <= np.round(best["mae"], 2):
            n_improve = n_improve + 1
        if np.round(rmse, 2) <= np.round(best["rmse"], 2):
            n_improve = n_improve + 1
        if np.round(imae, 2) <= np.round(best["imae"], 2):
            n_improve = n_improve + 1
        if np.round(irmse, 2) <= np.round(best["irmse"], 2):
            n_improve = n_improve + 1
        if n_improve > 2:
            best = {"mae": mae, "rmse": rmse, "imae": imae, "irmse": irmse}
            kept.append(step)
    return kept


def _trainer(metrics: dict[str, float]) -> SimpleNamespace:
    return SimpleNamespace(
        callback_metrics={k: torch.tensor(v) for k, v in metrics.items()},
        strategy=SimpleNamespace(reduce_boolean_decision=lambda decision: decision),
    )


def test_it_keeps_the_validations_radarnet_keeps() -> None:
    rng = np.random.default_rng(0)
    # a slowly improving run with noise, and values on the rounding boundary: ties count as
    # no worse, as RadarNet's <= of rounded values does
    rows = []
    level = np.array([2100.0, 4300.0, 9.0, 16.0])
    for _ in range(300):
        level = level * rng.uniform(0.985, 1.01, 4)
        rows.append(tuple(np.round(level, rng.integers(1, 4))))
    rule = MajorityCheckpoint(metrics=RADARNET, at_least=3, monitor="val/rmse")
    kept = []
    for step, (mae, rmse, imae, irmse) in enumerate(rows):
        logged = {
            "val/mae": mae / 1000,
            "val/rmse": rmse / 1000,
            "val/imae": imae,
            "val/irmse": irmse,
        }
        if rule.check_monitor_top_k(_trainer(logged), torch.tensor(rmse / 1000)):
            kept.append(step)
    expected = _radarnets_kept_steps(rows)
    assert kept == expected
    assert 20 < len(kept) < 280  # the rule decides: neither every step nor none


def test_a_non_finite_validation_is_never_kept() -> None:
    rule = MajorityCheckpoint(metrics=RADARNET, at_least=3, monitor="val/rmse")
    good = {"val/mae": 2.0, "val/rmse": 4.0, "val/imae": 9.0, "val/irmse": 16.0}
    assert rule.check_monitor_top_k(_trainer(good), torch.tensor(4.0))
    nan = {**good, "val/rmse": float("nan"), "val/mae": 1.0, "val/imae": 1.0}
    assert not rule.check_monitor_top_k(_trainer(nan), torch.tensor(float("nan")))
    assert rule.kept_metrics == good


@pytest.mark.parametrize(
    ("metrics", "at_least", "match"),
    [({}, 1, "metrics"), ({"val/rmse": 0.0}, 1, "resolution"), (RADARNET, 5, "at_least=5")],
)
def test_a_rule_that_cannot_decide_is_refused(metrics, at_least, match) -> None:
    with pytest.raises(ValueError, match=match):
        MajorityCheckpoint(metrics=metrics, at_least=at_least, monitor="val/rmse")


def test_a_run_tests_and_records_the_validation_the_rule_kept(make_config) -> None:
    """Four validations; the kept checkpoint is the one the rule picks from the logged values,
    the record's best RMSE is its, and the objective reads its metrics."""
    from fusion_depth.train.fit import train

    cfg = make_config("experiment=smoke", "logger=none", "trainer.max_epochs=4")
    rule = {"val/mae": 1e-5, "val/rmse": 1e-5, "val/abs_rel": 1e-4, "val/sq_rel": 1e-4}
    with open_dict(cfg):
        cfg.callbacks.model_checkpoint._target_ = "fusion_depth.runner.callbacks.MajorityCheckpoint"
        cfg.callbacks.model_checkpoint.metrics = rule
        cfg.callbacks.model_checkpoint.at_least = 2
    train(cfg)
    out = Path(cfg.paths.output_dir)
    record = RunRecord.from_json(json.loads((out / "metrics.json").read_text()))
    history = record.validation
    assert len(history) == 4
    replay = MajorityCheckpoint(metrics=rule, at_least=2, monitor="val/rmse")
    kept = None
    for entry in history:
        values = {k: entry[k.removeprefix("val/")] for k in rule}
        if replay.keeps(values):
            replay.kept_metrics, kept = values, entry
    assert kept is not None
    assert record.best_val_rmse == pytest.approx(kept["rmse"], rel=1e-6)
    saved = sorted((out / "checkpoints").glob("epoch*.ckpt"))
    assert [p.name[:8] for p in saved] == [f"epoch{kept['epoch']:03d}"]
    assert objective(record, "val_abs_rel") == kept["abs_rel"]


def test_the_rule_state_survives_a_resume_and_a_hostile_one_is_refused(tmp_path) -> None:
    rule = MajorityCheckpoint(metrics=RADARNET, at_least=3, monitor="val/rmse", dirpath=tmp_path)
    good = {"val/mae": 2.0, "val/rmse": 4.0, "val/imae": 9.0, "val/irmse": 16.0}
    rule.check_monitor_top_k(_trainer(good), torch.tensor(4.0))
    resumed = MajorityCheckpoint(metrics=RADARNET, at_least=3, monitor="val/rmse", dirpath=tmp_path)
    resumed.load_state_dict(rule.state_dict())
    assert resumed.kept_metrics == good
    worse = {k: v * 1.1 for k, v in good.items()}
    assert not resumed.check_monitor_top_k(_trainer(worse), torch.tensor(4.4))
    state = {"callbacks": {"MajorityCheckpoint": {**rule.state_dict(), "kept_metrics": "rm -rf"}}}
    with pytest.raises(CheckpointError, match=r"kept_metrics is not metric values"):
        check_resume_state(state, tmp_path / "last.ckpt")


def test_a_moved_run_folder_keeps_its_kept_checkpoint(tmp_path) -> None:
    """Lightning restores only the best path when the folder moved; the rule restores the kept
    file's place in the new folder and its score, so the next kept one replaces it."""
    old, new = tmp_path / "old" / "checkpoints", tmp_path / "new" / "checkpoints"
    rule = MajorityCheckpoint(metrics=RADARNET, at_least=3, monitor="val/rmse", dirpath=old)
    state = {
        **rule.state_dict(),
        "best_model_path": str(old / "epoch003-rmse4.0000.ckpt"),
        "best_model_score": torch.tensor(4.0),
        "kept_metrics": {"val/mae": 2.0, "val/rmse": 4.0, "val/imae": 9.0, "val/irmse": 16.0},
    }
    moved = MajorityCheckpoint(metrics=RADARNET, at_least=3, monitor="val/rmse", dirpath=new)
    with pytest.warns(UserWarning, match="dirpath has changed"):
        moved.load_state_dict(state)
    here = str(new / "epoch003-rmse4.0000.ckpt")
    assert moved.best_model_path == here and moved.best_k_models == {here: torch.tensor(4.0)}
    assert moved.kept_metrics["val/rmse"] == 4.0


def test_without_metrics_it_is_lightnings_rule() -> None:
    """metrics=null (callbacks.model_checkpoint.metrics=null): by the monitor alone."""
    rule = MajorityCheckpoint(metrics=None, at_least=3, monitor="val/rmse")
    assert rule.check_monitor_top_k(_trainer({}), torch.tensor(4.0))  # the first: kept
    rule.best_k_models = {"a.ckpt": torch.tensor(4.0)}
    rule.kth_best_model_path = "a.ckpt"
    assert not rule.check_monitor_top_k(_trainer({}), torch.tensor(4.5))
    assert rule.check_monitor_top_k(_trainer({}), torch.tensor(3.5))
    assert rule.kept_metrics == {}
