"""The composed configs: paper defaults, every group choice, and early, named errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from hydra.errors import ConfigCompositionException, MissingConfigException
from hydra.utils import instantiate
from omegaconf.errors import MissingMandatoryValue

from fusion_depth.config import validate_config

REPO = Path(__file__).resolve().parents[1]


def test_defaults_reproduce_the_paper_setup(make_config) -> None:
    cfg = make_config()
    assert (cfg.fusion.mode, cfg.loss.pixel, cfg.backbone.name, cfg.dataset.name) == (
        "rgb",
        "l1",
        "densenet169",
        "procedural",
    )
    assert cfg.optimizer._target_ == "torch.optim.Adam"
    assert cfg.optimizer.lr == 1e-4 and list(cfg.optimizer.betas) == [0.9, 0.999]
    assert cfg.data.batch_size == 2 and cfg.trainer.max_epochs == 20
    assert (cfg.scheduler.step_size, cfg.scheduler.gamma) == (7, 0.2)
    assert list(cfg.augment.brightness) == [0.75, 1.25] and list(cfg.augment.contrast) == [0.9, 1.1]
    assert cfg.augment.flip_p == 0.5 and cfg.augment.color_p == 0.5
    assert (cfg.loss.w_ssim, cfg.loss.w_edge, cfg.loss.w_pixel) == (1.0, 1.0, 1.0)
    assert cfg.backbone.pretrained is False  # built-in dataset: from scratch, no network


@pytest.mark.parametrize(
    "group,choice,key,value",
    [
        ("fusion", "concat", "fusion.mode", "concat"),
        ("fusion", "add", "fusion.mode", "add"),
        ("loss", "l2", "loss.pixel", "l2"),
        ("loss", "berhu", "loss.pixel", "berhu"),
        ("backbone", "resnet50", "backbone.name", "resnet50"),
        ("logger", "csv", "logger._target_", "fusion_depth.loggers.csv_logger"),
        ("logger", "none", "logger._target_", None),
    ],
)
def test_group_choices_compose(make_config, group, choice, key, value) -> None:
    cfg = make_config(f"{group}={choice}")
    node = cfg
    for part in key.split("."):
        node = node[part]
    assert node == value


def test_model_and_loss_instantiate_from_config(make_config) -> None:
    cfg = make_config("fusion=add", "loss=berhu", "backbone=resnet50")
    model = instantiate(cfg.model, _convert_="all")
    assert model.net.fusion.mode == "add" and model.loss.pixel == "berhu"
    assert model.loss.max_val == pytest.approx(cfg.dataset.depth_scale / cfg.dataset.min_depth)
    optimizer = model.configure_optimizers()["optimizer"]
    assert optimizer.defaults["lr"] == 1e-4


def test_wrong_choice_names_group_and_options(make_config) -> None:
    with pytest.raises((MissingConfigException, ConfigCompositionException)) as err:
        make_config("fusion=sum")
    message = str(err.value)
    assert "fusion" in message and "sum" in message
    assert all(option in message for option in ("rgb", "concat", "add"))


@pytest.mark.parametrize(
    "override,match",
    [
        ("dataset.height=50", "dataset.height=50"),
        ("dataset.width=0", "dataset.width=0"),
        ("dataset.min_depth=90", "min_depth"),
        ("data.batch_size=0", "data.batch_size=0"),
    ],
)
def test_invalid_values_fail_naming_the_key(make_config, override, match) -> None:
    with pytest.raises(ValueError, match=match):
        validate_config(make_config(override))


def test_missing_required_value_fails(make_config) -> None:
    with pytest.raises(MissingMandatoryValue, match="backbone.name"):
        validate_config(make_config("backbone.name=???"))


def test_cli_rejects_bad_choice_before_touching_data(tmp_path: Path) -> None:
    env = {**os.environ, "FUSION_DEPTH_CACHE": str(tmp_path / "cache")}
    result = subprocess.run(
        [sys.executable, "-m", "fusion_depth.train", "loss=huber", f"hydra.run.dir={tmp_path}/run"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode != 0
    assert "loss" in result.stderr and "berhu" in result.stderr
    assert not (tmp_path / "cache").exists()
