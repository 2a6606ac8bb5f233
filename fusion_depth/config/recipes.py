"""Each model's published recipe (:class:`~fusion_depth.models.Recipe`, declared beside the
network with ``@register_model``), and each dataset's own recipe for a model
(``conf/experiment/<dataset>_<model>.yaml``), as the config options ``conf/train.yaml`` selects.

For each model ``<m>``, dataset ``<d>`` and source ``<s>`` (an option of the ``recipe_from``
group), in Hydra's config store, an option ``<s>_<d>_<m>`` of ``backbone``,
``loss``, ``optimizer``, ``scheduler`` and ``model_recipe`` (batch, epochs, augmentation and
the dataset recipe's other values):

- ``dataset`` (the default): the dataset's recipe for the model where it has one, on top of the
  model's own: the choices it switches, with the values it gives under them;
- ``model`` (``experiment=paper``): the model's own, whatever the dataset;
- ``smoke`` (``experiment=smoke``): the model's own with :data:`SMALLEST_BACKBONE` where it takes
  any encoder.

``for_<m>`` in the four groups is the model's own choice, to name on the command line
(``scheduler=for_radarnet``). ``backbone=`` and the others on the command line replace the choice,
values and all.

Why generated: Hydra allows no defaults-list override in a config selected by interpolation
("Default List Overrides are not allowed in the subtree of an interpolated config group"), and a
dataset's recipe depends on the model. So the dataset's recipe is a plain experiment file
(``override /<group>: <option>`` lines, then values), which ``experiment=<d>_<m>`` also loads as
Hydra does; here it is read as data, and each group it switches becomes that group's option, with
the values the file gives under that group. ``experiment=smoke`` switches only ``recipe_from``, a
group ``evaluate``, ``export`` and ``predict`` also have, so that they take it too.

``prepare`` reads the dataset alone, and starts without importing the networks (seconds): its
``model_recipe`` options (:func:`register_dataset_recipes`, ``prepare_<s>_<d>_<m>``) hold the
dataset recipe's values without the model's own Recipe, which concerns training alone; so
``prepare model=<m>`` prepares exactly the frames that ``train model=<m>`` reads.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from hydra.core.config_store import ConfigStore
from omegaconf import OmegaConf

from fusion_depth.config import CONF_DIR
from fusion_depth.errors import ConfigError

if TYPE_CHECKING:  # the networks are imported on use: prepare's options need none of them
    from fusion_depth.models import ModelEntry

GROUPS = ("backbone", "loss", "optimizer", "scheduler")
# experiment=smoke's encoder for a model that takes any: 4× faster a step than DenseNet-169.
SMALLEST_BACKBONE = "resnet10t"
# The recipe_from options (whose recipe fills the groups), and the prefix of prepare's.
SOURCES = ("dataset", "model", "smoke")
PREPARE_PREFIX = "prepare_"
_PROVIDER = "fusion_depth.models"
_CREATE_SCHEDULE = "fusion_depth.optim.schedules.create_schedule"


def _option_values(group: str, option: str, where: str) -> dict:
    """The values of ``conf/<group>/<option>.yaml``, unresolved.

    Raises:
        ConfigError: there is no such option, naming ``where`` it was asked for and the options.
    """
    path = Path(CONF_DIR) / group / f"{option}.yaml"
    if not path.is_file():
        options = sorted(p.stem for p in path.parent.glob("*.yaml"))
        raise ConfigError(f"{where} {group}={option!r}; expected one of {options}")
    return OmegaConf.to_container(OmegaConf.load(path), resolve=False)


def _schedule(name: str, values: dict) -> dict:
    """The scheduler option that builds schedule ``name`` by name (:func:`create_schedule`), with
    ``values`` for its arguments and null for the others."""
    from fusion_depth.optim.schedules import SCHEDULE_ARGUMENTS

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


def _run_values(entry: ModelEntry) -> dict:
    """The model's batch, epochs and augmentation, where its recipe sets them."""
    recipe = entry.recipe
    nodes = {
        "data": {"batch_size": recipe.batch_size},
        "trainer": {"max_epochs": recipe.max_epochs},
        "augment": dict(recipe.augment),
    }
    return {
        node: {key: value for key, value in keys.items() if value is not None}
        for node, keys in nodes.items()
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


def _dataset_recipe(dataset: str, name: str, config_dir: str | None) -> tuple[Path, dict] | None:
    """``experiment/<dataset>_<name>.yaml`` (in ``config_dir``, the command line's
    ``--config-dir``, or else ``conf/``) and its values, unresolved; None when there is none."""
    paths = [Path(f) / "experiment" / f"{dataset}_{name}.yaml" for f in (config_dir, CONF_DIR) if f]
    path = next((p for p in paths if p.is_file()), None)
    if path is None:
        return None
    return path, OmegaConf.to_container(OmegaConf.load(path), resolve=False)


def dataset_options(
    own: dict[str, dict], dataset: str, name: str, config_dir: str | None = None
) -> dict[str, dict]:
    """The option of each group (:data:`GROUPS` and ``model_recipe``) for ``recipe_from=dataset``:
    the model's ``own`` (its :func:`model_options` and ``model_recipe``), with
    ``experiment/<dataset>_<name>.yaml`` on top if there is one (in ``config_dir``, the command
    line's ``--config-dir``, or else ``conf/``).

    Raises:
        ConfigError: the file switches something other than a group of :data:`GROUPS`, or to a
            schedule ``conf/scheduler/`` does not have.
    """
    recipe = _dataset_recipe(dataset, name, config_dir)
    if recipe is None:
        return own
    path, values = recipe
    options = dict(own)
    for group, option in _switched(path, values).items():
        given = values.pop(group, None) or {}
        if group == "scheduler":
            where = f"{path.name}: its"
            options[group] = _schedule(option, _option_values(group, option, where) | given)
        else:
            options[group] = {"defaults": [option, "_self_"], **given}
    values.pop("defaults", None)
    options["model_recipe"] = OmegaConf.to_container(OmegaConf.merge(own["model_recipe"], values))
    return options


def dataset_recipe_values(dataset: str, name: str, config_dir: str | None = None) -> dict:
    """What ``experiment/<dataset>_<name>.yaml`` gives the ``model_recipe`` option of
    ``recipe_from=dataset`` (:func:`dataset_options`), unresolved: its values but those under
    the groups it switches (which go with the group's option) and its defaults; ``{}`` without
    such a file. The ``dataset`` node that training reads comes from here alone (a model's own
    Recipe sets its batch, epochs and augmentation).

    Raises:
        ConfigError: the file switches something other than a group of :data:`GROUPS`.
    """
    recipe = _dataset_recipe(dataset, name, config_dir)
    if recipe is None:
        return {}
    path, values = recipe
    for group in _switched(path, values):
        values.pop(group, None)
    values.pop("defaults", None)
    return values


def _names(group: str, config_dir: str | None, overrides: Sequence[str]) -> set[str]:
    """The options of ``group`` in the package's configs and ``--config-dir``, and one named by
    ``<group>=`` (an option on ``hydra.searchpath``)."""
    folders = [Path(CONF_DIR), *([Path(config_dir)] if config_dir else [])]
    names = {p.stem for folder in folders for p in (folder / group).glob("*.yaml")}
    return names | {o.partition("=")[2] for o in overrides if o.startswith(f"{group}=")}


def _dataset_names(config_dir: str | None, overrides: Sequence[str]) -> set[str]:
    """The package's datasets, those of ``--config-dir``, and one named by ``dataset=`` (a
    dataset on ``hydra.searchpath``)."""
    return _names("dataset", config_dir, overrides)


def register_dataset_recipes(config_dir: str | None = None, overrides: Sequence[str] = ()) -> None:
    """``prepare``'s ``model_recipe`` options, ``prepare_<source>_<dataset>_<model>``, in Hydra's
    config store (idempotent; ``conf/prepare.yaml`` selects them): for ``recipe_from=dataset``
    the dataset's recipe for the model (:func:`dataset_recipe_values`), for the other sources
    nothing, as training's options hold for the dataset. The networks are not imported: the
    models are the ``model`` group's options (conf/, ``--config-dir``, ``model=``).

    Raises:
        ConfigError: a dataset recipe that switches something other than a group of
            :data:`GROUPS`.
    """
    store = ConfigStore.instance()
    models = sorted(_names("model", config_dir, overrides))
    for dataset in sorted(_dataset_names(config_dir, overrides)):
        for name in models:
            recipe = dataset_recipe_values(dataset, name, config_dir)
            for source in SOURCES:
                node = recipe if source == "dataset" else {}
                option = f"{PREPARE_PREFIX}{source}_{dataset}_{name}"
                store.store(group="model_recipe", name=option, node=node, provider=_PROVIDER)


def register_model_recipes(config_dir: str | None = None, overrides: Sequence[str] = ()) -> None:
    """Every registered model's options, for each source and dataset, in Hydra's config store
    (idempotent). Commands that compose ``conf/train.yaml`` call it first (train, bench; the
    tests' compose), with the command line's ``--config-dir`` and overrides, where a dataset of
    the user's own may be. ``prepare``'s options too (:func:`register_dataset_recipes`)."""
    from fusion_depth.models import MODELS

    store = ConfigStore.instance()

    def put(group: str, option: str, node: dict) -> None:
        store.store(group=group, name=option, node=node, provider=_PROVIDER)

    register_dataset_recipes(config_dir, overrides)
    datasets = sorted(_dataset_names(config_dir, overrides))
    for name, entry in MODELS.items():
        own = model_options(name, entry)
        for group, node in own.items():
            put(group, f"for_{name}", node)
        own["model_recipe"] = _run_values(entry)
        smoke = own.copy()
        if entry.backbones is None:  # a model that takes any encoder gets the smallest
            smoke["backbone"] = {"defaults": [SMALLEST_BACKBONE, "_self_"]}
        for dataset in datasets:  # the recipe_from options (a source each)
            by_source = {
                "dataset": dataset_options(own, dataset, name, config_dir),
                "model": own,
                "smoke": smoke,
            }
            for source, options in by_source.items():
                for group, node in options.items():
                    put(group, f"{source}_{dataset}_{name}", node)
