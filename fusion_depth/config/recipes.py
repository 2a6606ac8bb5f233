"""Each model's published recipe (:class:`~fusion_depth.models.Recipe`, declared beside the
network with ``@register_model``) as the config options ``model=<name>`` selects: for each model
``<name>``, ``backbone/for_<name>``, ``loss/for_<name>``, ``optimizer/for_<name>`` and
``scheduler/for_<name>`` in Hydra's config store, and ``model_recipe/<name>`` (its batch and
epochs). ``conf/train.yaml`` picks ``for_${model}`` in each group, so ``backbone=``, ``loss=``,
``optimizer=`` or ``scheduler=`` on the command line replaces the model's choice, values and all.

A dataset's own recipe for a model (``conf/experiment/<dataset>_<model>.yaml``, which the
defaults select by interpolation) may name the encoder (for a model that takes any), the pixel
loss and its weights, and the schedule under ``recipe:``; the options here read those values and
fall back to the model's. Hydra allows no defaults-list override in a config selected by
interpolation ("Default List Overrides are not allowed in the subtree of an interpolated config
group"), which is why a dataset's recipe gives values rather than choices.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from fusion_depth.config import CONF_DIR
from fusion_depth.errors import ConfigError
from fusion_depth.models import MODELS, ModelEntry
from fusion_depth.optim.schedules import SCHEDULE_ARGUMENTS

# The loss keys a dataset's recipe may set, and where it sets them (under ``recipe:``).
_LOSS_KEYS = {
    "pixel": "pixel_loss",
    "w_ssim": "loss_weights.ssim",
    "w_edge": "loss_weights.edge",
    "w_pixel": "loss_weights.pixel",
}
_PROVIDER = "fusion_depth.models"


def _select(key: str, default: Any) -> str:
    """The interpolation that reads ``recipe.<key>``, or ``default`` when it is not set."""
    return f"${{oc.select:recipe.{key},{'null' if default is None else default}}}"


def recipe_options(name: str, entry: ModelEntry) -> dict[str, dict]:
    """The config options of ``entry``'s recipe, by ``<group>``: each a node with a defaults
    list naming the group's option and the values that replace that option's.

    Raises:
        ConfigError: the recipe names a loss that ``conf/loss/`` does not have (the other groups'
            options are checked by Hydra when the config is composed).
    """
    recipe = entry.recipe
    backbone: dict[str, Any] = {"defaults": [recipe.backbone, "_self_"]}
    if entry.backbones is None:  # a model that takes any encoder takes a dataset's
        backbone["name"] = _select("backbone", recipe.backbone)
    loss_file = Path(CONF_DIR) / "loss" / f"{recipe.loss}.yaml"
    if not loss_file.is_file():
        options = sorted(p.stem for p in loss_file.parent.glob("*.yaml"))
        raise ConfigError(
            f"model={name}: its Recipe's loss={recipe.loss!r}; expected one of {options}"
        )
    loss_values = OmegaConf.load(loss_file)
    loss = {"defaults": [recipe.loss, "_self_"]}
    loss |= {key: _select(at, loss_values[key]) for key, at in _LOSS_KEYS.items()}
    schedule = {
        "_target_": "fusion_depth.optim.schedules.create_schedule",
        "_partial_": True,
        "name": _select("schedule.name", recipe.schedule),
    }
    for key in SCHEDULE_ARGUMENTS:
        schedule[key] = _select(f"schedule.{key}", recipe.schedule_args.get(key))
    options = {
        "backbone": backbone,
        "loss": loss,
        "optimizer": {"defaults": [recipe.optimizer, "_self_"], **recipe.optimizer_args},
        "scheduler": schedule,
    }
    data, trainer = {"batch_size": recipe.batch_size}, {"max_epochs": recipe.max_epochs}
    length = {"data": data, "trainer": trainer}
    options["model_recipe"] = {
        node: {key: value for key, value in keys.items() if value is not None}
        for node, keys in length.items()
        if any(value is not None for value in keys.values())
    }
    return options


def register_model_recipes() -> None:
    """Every registered model's recipe options in Hydra's config store (idempotent). Commands
    that compose ``conf/train.yaml`` call it first (train, bench; the tests' compose)."""
    store = ConfigStore.instance()
    for name, entry in MODELS.items():
        for group, node in recipe_options(name, entry).items():
            option = name if group == "model_recipe" else f"for_{name}"
            store.store(group=group, name=option, node=node, provider=_PROVIDER)
