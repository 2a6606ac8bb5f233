"""Each model's published recipe (:class:`~fusion_depth.models.Recipe`, declared beside the
network with ``@register_model``), and each dataset's own recipe for a model
(``conf/experiment/<dataset>_<model>.yaml``), as the config options ``conf/train.yaml`` selects.

For each model ``<m>`` and dataset ``<d>``, in Hydra's config store:

- ``backbone``, ``loss``, ``optimizer``, ``scheduler``: ``for_<m>`` (the model's own choice and
  values) and ``for_<d>_<m>`` (the same, with the choices the dataset's recipe switches);
  ``backbone/smallest_for_<m>``: :data:`SMALLEST_BACKBONE` for a model that takes any encoder,
  else its own (``experiment=smoke``).
- ``model_recipe``: ``<m>`` (the model's batch and epochs) and ``<d>_<m>`` (those, then the
  dataset recipe's other values).

``conf/train.yaml`` picks ``for_${dataset}_${model}`` in each group, so ``backbone=`` and the
others on the command line replace that choice, values and all; an experiment returns to the
model's own with ``override /<group>: for_${model}`` (``experiment=paper``).

Why generated: Hydra allows no defaults-list override in a config selected by interpolation
("Default List Overrides are not allowed in the subtree of an interpolated config group"), and a
dataset's recipe depends on the model. So the dataset's recipe is a plain experiment file
(``override /<group>: <option>`` lines, then values), which ``experiment=<d>_<m>`` also loads as
Hydra does; here it is read as data, and each group it switches becomes that group's
``for_<d>_<m>`` option, with the values the file gives under that group.
"""

from __future__ import annotations

from pathlib import Path

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from fusion_depth.config import CONF_DIR
from fusion_depth.errors import ConfigError
from fusion_depth.models import MODELS, ModelEntry
from fusion_depth.optim.schedules import SCHEDULE_ARGUMENTS

GROUPS = ("backbone", "loss", "optimizer", "scheduler")
# experiment=smoke's encoder for a model that takes any: 4× faster a step than DenseNet-169.
SMALLEST_BACKBONE = "resnet10t"
_PROVIDER = "fusion_depth.models"
_CREATE_SCHEDULE = "fusion_depth.optim.schedules.create_schedule"


def _option_values(group: str, option: str, where: str) -> dict:
    """The values of ``conf/<group>/<option>.yaml``, unresolved.

    Raises:
        ConfigError: there is no such option, naming ``where`` it was asked for and the options.
    """
    path = Path(CONF_DIR) / group / f"{option}.yaml"
    if not path.is_file():
        options = sorted(p.stem for p in path.parent.glob("*.yaml") if "for_" not in p.stem)
        raise ConfigError(f"{where} {group}={option!r}; expected one of {options}")
    return OmegaConf.to_container(OmegaConf.load(path), resolve=False)


def _schedule(name: str, values: dict) -> dict:
    """The scheduler option that builds schedule ``name`` by name (:func:`create_schedule`), with
    ``values`` for its arguments and null for the others."""
    arguments = {key: values.get(key) for key in SCHEDULE_ARGUMENTS}
    return {"_target_": _CREATE_SCHEDULE, "_partial_": True, "name": name, **arguments}


def model_options(name: str, entry: ModelEntry) -> dict[str, dict]:
    """The model's own option of each group (:data:`GROUPS`), as the node stored there.

    Raises:
        ConfigError: the recipe names a loss that ``conf/loss/`` does not have (the other
            groups' options are checked by Hydra when the config is composed).
    """
    recipe = entry.recipe
    _option_values("loss", recipe.loss, f"model={name}: its Recipe's")
    return {
        "backbone": {"defaults": [recipe.backbone, "_self_"]},
        "loss": {"defaults": [recipe.loss, "_self_"]},
        "optimizer": {"defaults": [recipe.optimizer, "_self_"], **recipe.optimizer_args},
        "scheduler": _schedule(recipe.schedule, dict(recipe.schedule_args)),
    }


def _length(entry: ModelEntry) -> dict:
    """The model's batch and epochs, where its recipe sets them."""
    data, trainer = {"batch_size": entry.recipe.batch_size}, {"max_epochs": entry.recipe.max_epochs}
    return {
        node: {key: value for key, value in keys.items() if value is not None}
        for node, keys in {"data": data, "trainer": trainer}.items()
        if any(value is not None for value in keys.values())
    }


def _switched(path: Path, values: dict) -> dict[str, str]:
    """The groups a dataset recipe switches (``override /<group>: <option>``), by group.

    Raises:
        ConfigError: a defaults entry that switches no group of :data:`GROUPS`.
    """
    switched = {}
    for item in values.get("defaults", []):
        ((key, option),) = item.items() if isinstance(item, dict) and len(item) == 1 else ((0, 0),)
        group = str(key).removeprefix("override /")
        if group not in GROUPS or not isinstance(option, str):
            raise ConfigError(
                f"{path.name}: defaults entry {item!r}; a dataset's recipe may only have "
                f"'override /<group>: <option>' entries, <group> one of {list(GROUPS)}"
            )
        switched[group] = option
    return switched


def dataset_options(dataset: str, name: str, entry: ModelEntry) -> dict[str, dict]:
    """The options ``for_<dataset>_<name>`` of each group and the ``model_recipe`` node, from the
    model's own and ``conf/experiment/<dataset>_<name>.yaml`` if there is one."""
    options = model_options(name, entry)
    length = _length(entry)
    path = Path(CONF_DIR) / "experiment" / f"{dataset}_{name}.yaml"
    if path.is_file():
        values = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
        for group, option in _switched(path, values).items():
            given = values.pop(group, None) or {}
            if group == "scheduler":
                where = f"{path.name}: its"
                options[group] = _schedule(option, _option_values(group, option, where) | given)
            else:
                options[group] = {"defaults": [option, "_self_"], **given}
        values.pop("defaults", None)
        length = OmegaConf.to_container(OmegaConf.merge(length, values))
    return options | {"model_recipe": length}


def _dataset_names() -> list[str]:
    return sorted(p.stem for p in (Path(CONF_DIR) / "dataset").glob("*.yaml"))


def register_model_recipes() -> None:
    """Every registered model's options, alone and with each dataset, in Hydra's config store
    (idempotent). Commands that compose ``conf/train.yaml`` call it first (train, bench; the
    tests' compose)."""
    store = ConfigStore.instance()

    def put(group: str, option: str, node: dict) -> None:
        store.store(group=group, name=option, node=node, provider=_PROVIDER)

    for name, entry in MODELS.items():
        for group, node in model_options(name, entry).items():
            put(group, f"for_{name}", node)
        put("model_recipe", name, _length(entry))
        smallest = entry.recipe.backbone if entry.backbones else SMALLEST_BACKBONE
        put("backbone", f"smallest_for_{name}", {"defaults": [smallest, "_self_"]})
        for dataset in _dataset_names():
            for group, node in dataset_options(dataset, name, entry).items():
                option = f"{dataset}_{name}" if group == "model_recipe" else f"for_{dataset}_{name}"
                put(group, option, node)
