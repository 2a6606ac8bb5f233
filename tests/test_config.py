"""The composed configs: paper defaults, every group choice, and early, named errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
from helpers import compose_config
from hydra.errors import ConfigCompositionException, MissingConfigException
from hydra.utils import instantiate
from omegaconf import OmegaConf
from omegaconf.errors import MissingMandatoryValue

from fusion_depth.config import validate_config
from fusion_depth.optim.schedules import WarmupCosine

REPO = Path(__file__).resolve().parents[1]


# The paper's recipe (Siddiqui et al., Sec. III-B and IV), key by key, with the built-in
# dataset's frame counts and size of its earlier default.
PAPER_RECIPE = {
    "optimizer._target_": "torch.optim.Adam",
    "optimizer.lr": 1e-4,
    "optimizer.betas": [0.9, 0.999],
    "optimizer.weight_decay": 0.0,
    "scheduler._target_": "torch.optim.lr_scheduler.StepLR",
    "scheduler.step_size": 7,
    "scheduler.gamma": 0.2,
    "data.batch_size": 2,
    "trainer.max_epochs": 20,
    "trainer.limit_train_batches": None,
    "trainer.accumulate_grad_batches": 1,
    "trainer.gradient_clip_val": None,
    "backbone.name": "densenet169",
    "model.net.backbone_taps": "paper",
    "loss.pixel": "l1",
    "loss.w_ssim": 1.0,
    "loss.w_edge": 1.0,
    "loss.w_pixel": 1.0,
    "augment.flip_p": 0.5,
    "augment.color_p": 0.5,
    "augment.brightness": [0.75, 1.25],
    "augment.contrast": [0.9, 1.1],
    "fusion.mode": "rgb",
    "dataset.num_train": 160,
    "dataset.num_val": 40,
    "dataset.num_test": 250,
    "dataset.height": 64,
    "dataset.width": 192,
}


def _flat(cfg, resolve: bool = True) -> dict:
    """Every leaf of ``cfg`` (interpolations resolved unless ``resolve=False``) as
    ``{"a.b.c": value}``."""
    out = {}

    def walk(node, prefix: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(value, f"{prefix}{key}.")
        else:
            out[prefix[:-1]] = node

    walk(OmegaConf.to_container(cfg, resolve=resolve), "")
    return out


def test_experiment_paper_is_the_papers_recipe_key_by_key(make_config) -> None:
    paper = _flat(make_config("experiment=paper"))
    for key, value in PAPER_RECIPE.items():
        assert paper[key] == value, key
    assert paper["backbone.pretrained"] is False  # built-in dataset: no ImageNet download
    assert not any(key.startswith("recipe.") for key in paper)
    # Every key the built-in dataset's own recipe changes is one the paper's recipe pins.
    default = make_config()
    builtin, raw = _flat(default), _flat(default, resolve=False)
    changed = {k for k in paper.keys() | builtin.keys() if paper.get(k) != builtin.get(k)}
    changed -= {"paths.output_dir"}  # named after the overrides

    def copied(key: str) -> bool:  # the key, or a node above it, interpolates another key
        parts = key.split(".")
        return any(
            str(raw.get(".".join(parts[:n]), "")).startswith("${") for n in range(1, len(parts) + 1)
        )

    changed = {k for k in changed if not copied(k)}
    # The paper's schedule (StepLR) pins the scheduler node whole: it has no warm-up to set.
    changed = {k for k in changed if not (k.startswith("scheduler.") and k not in paper)}
    assert changed <= set(PAPER_RECIPE), sorted(changed - set(PAPER_RECIPE))


def test_the_builtin_dataset_trains_with_its_own_recipe_by_default(make_config) -> None:
    default = make_config()
    cfg = _flat(default)
    assert cfg["backbone.name"] == "resnet10t"
    assert (cfg["optimizer.lr"], cfg["data.batch_size"]) == (3e-3, 16)
    assert (cfg["trainer.max_epochs"], cfg["trainer.limit_train_batches"]) == (22, 125)
    assert cfg["scheduler.name"] == "cosine"
    assert (cfg["scheduler.warmup_fraction"], cfg["scheduler.final_lr_ratio"]) == (0.02, 0.01)
    assert (cfg["scheduler.step_size"], cfg["scheduler.gamma"]) == (None, None)
    assert (cfg["loss.w_ssim"], cfg["loss.w_edge"], cfg["loss.w_pixel"]) == (1.87, 1.14, 0.43)
    assert cfg["dataset.num_train"] == 6400
    # Instantiated, the recipe is the network and schedule the config names.
    model = instantiate(default.model, _convert_="all")
    assert model.net.encoder.name == "resnet10t"
    model._trainer = SimpleNamespace(estimated_stepping_batches=22 * 125)  # Lightning's count
    schedule = model.configure_optimizers()["lr_scheduler"]
    assert schedule["interval"] == "step"
    assert isinstance(schedule["scheduler"], WarmupCosine)
    assert (schedule["scheduler"].total_steps, schedule["scheduler"].warmup_steps) == (2750, 55)


def test_a_choice_on_the_command_line_beats_the_recipe(make_config) -> None:
    """The recipe adjusts only the default choices: an explicit backbone=, loss= or scheduler=
    gets that config's own values, not the recipe's."""
    cfg = _flat(make_config("backbone=densenet169", "loss=l1", "scheduler=step"))
    assert cfg["backbone.name"] == "densenet169"
    assert (cfg["scheduler.step_size"], cfg["scheduler.gamma"]) == (7, 0.2)
    assert (cfg["loss.w_ssim"], cfg["loss.w_edge"], cfg["loss.w_pixel"]) == (1.0, 1.0, 1.0)
    cosine = _flat(make_config("scheduler=cosine"))
    assert cosine["scheduler._target_"] == "fusion_depth.optim.schedules.WarmupCosine"
    assert "scheduler.step_size" not in cosine
    # Other models on the built-in dataset get their own recipe for it (RadarNet: Adam 3e-2,
    # batch 8), never the built-in dataset's DenseDepth recipe (its encoder or loss weights).
    radarnet = _flat(make_config("model=radarnet", "fusion=concat"))
    assert (radarnet["optimizer.lr"], radarnet["data.batch_size"]) == (3e-2, 8)
    assert (radarnet["loss.w_ssim"], radarnet["loss.w_edge"], radarnet["loss.w_pixel"]) == (0, 0, 1)
    assert radarnet["backbone.name"] == "resnet18"


def test_a_dataset_recipe_is_an_experiment_file_and_smoke_takes_a_small_encoder(
    make_config,
) -> None:
    """The built-in dataset's recipe (conf/experiment/procedural_densedepth.yaml) loads as a plain
    Hydra experiment too, with the choices the default run makes from it; experiment=smoke trains
    DenseDepth on ResNet-10-T and RadarNet on its own encoder unless backbone= says otherwise."""
    default = _flat(make_config())
    explicit = _flat(make_config("experiment=procedural_densedepth"))
    same = ("backbone.name", "loss.w_ssim", "loss.w_pixel", "optimizer.lr", "dataset.num_train")
    for key in same:
        assert explicit[key] == default[key], key
    assert explicit["scheduler.warmup_fraction"] == default["scheduler.warmup_fraction"] == 0.02
    assert _flat(make_config("experiment=smoke"))["backbone.name"] == "resnet10t"
    radarnet = _flat(make_config("experiment=smoke", "model=radarnet", "fusion=concat"))
    assert radarnet["backbone.name"] == "resnet18"
    smoke = _flat(make_config("experiment=smoke", "backbone=densenet169"))
    assert smoke["backbone.name"] == "densenet169"


def test_top_view_trains_the_papers_30_epochs_unless_smoke_or_asked(make_config) -> None:
    topview = ("dataset=topview", "dataset.root=/t")
    assert _flat(make_config(*topview))["trainer.max_epochs"] == 30
    assert _flat(make_config(*topview, "experiment=paper"))["trainer.max_epochs"] == 30
    assert _flat(make_config(*topview, "experiment=smoke"))["trainer.max_epochs"] == 2
    assert _flat(make_config(*topview, "trainer.max_epochs=5"))["trainer.max_epochs"] == 5
    assert _flat(make_config("experiment=paper"))["trainer.max_epochs"] == 20


def test_real_datasets_train_with_the_papers_recipe(make_config) -> None:
    cfg = _flat(make_config("dataset=kitti", "dataset.root=/k", "dataset.raw_root=/r"))
    for key, value in PAPER_RECIPE.items():
        if not key.startswith(("dataset.", "scheduler.")):
            assert cfg[key] == value, key
    # model=densedepth's default schedule names the paper's StepLR (create_schedule, so that the
    # built-in dataset's recipe can name another).
    assert cfg["scheduler._target_"] == "fusion_depth.optim.schedules.create_schedule"
    assert (cfg["scheduler.name"], cfg["scheduler.step_size"], cfg["scheduler.gamma"]) == (
        "step",
        PAPER_RECIPE["scheduler.step_size"],
        PAPER_RECIPE["scheduler.gamma"],
    )
    assert (cfg["scheduler.warmup_fraction"], cfg["scheduler.final_lr_ratio"]) == (None, None)
    assert cfg["backbone.pretrained"] is True  # ImageNet weights, as the paper


@pytest.mark.parametrize(
    "group,choice,key,value",
    [
        ("fusion", "concat", "fusion.mode", "concat"),
        ("fusion", "add", "fusion.mode", "add"),
        ("loss", "l2", "loss.pixel", "l2"),
        ("loss", "berhu", "loss.pixel", "berhu"),
        ("backbone", "resnet50", "backbone.name", "resnet50"),
        ("logger", "csv", "logger._target_", "fusion_depth.runner.loggers.csv_logger"),
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
    model._trainer = SimpleNamespace(estimated_stepping_batches=100)  # the recipe's per-step lr
    optimizer = model.configure_optimizers()["optimizer"]
    assert optimizer.defaults["lr"] == cfg.optimizer.lr


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


@pytest.mark.slow
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


# What a training run reads is set by the dataset group, the model's dataset recipe
# (conf/experiment/<dataset>_<model>.yaml), an experiment and the command line.
AS_TRAINED = {
    "default": [],  # the built-in dataset's recipe for densedepth: a 6,400-frame pool
    "paper": ["experiment=paper"],  # the model's own recipe: the dataset group's pool
    "nuscenes_radarnet": ["dataset=nuscenes", "dataset.root=DATA", "model=radarnet"],
    "command_line_wins": ["model=sparse_to_dense", "dataset.num_train=320"],
}


@pytest.mark.parametrize("overrides", AS_TRAINED.values(), ids=AS_TRAINED.keys())
def test_prepare_prepares_the_dataset_training_reads(overrides, tmp_path, monkeypatch) -> None:
    """``prepare model=<m>`` (or ``experiment=``) composes the dataset block that ``train`` with
    the same overrides reads: here, and with prepare's options alone, as its command registers
    them without importing a network (the store's training options set aside)."""
    from hydra.core.config_store import ConfigStore

    def dataset(command: str) -> dict:
        cfg = compose_config(overrides, tmp_path / command, config_name=command)
        return OmegaConf.to_container(cfg.dataset, resolve=True)

    trained = dataset("train")
    assert dataset("prepare") == trained
    from fusion_depth.config.recipes import register_dataset_recipes

    monkeypatch.setitem(ConfigStore.instance().repo, "model_recipe", {})
    register_dataset_recipes(overrides=overrides)
    assert dataset("prepare") == trained


@pytest.mark.slow
def test_the_prepare_command_composes_the_dataset_training_reads(tmp_path: Path) -> None:
    overrides = AS_TRAINED["nuscenes_radarnet"]
    result = subprocess.run(
        [sys.executable, "-m", "fusion_depth.prepare", *overrides, "--cfg", "job", "--resolve"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    prepared = OmegaConf.create(result.stdout).dataset
    trained = compose_config(overrides, tmp_path / "train").dataset
    assert OmegaConf.to_container(prepared) == OmegaConf.to_container(trained, resolve=True)
