"""The config checks that read several keys at once (the rest are the ``ARGUMENT_RULES`` tables
beside the code, :mod:`fusion_depth.utils.schema`): the encoder and its taps, the network against
the fusion mode, encoder and dataset it is given, the batch against the encoder's bottleneck, and
the schedule's arguments. Each reads the config and asks the science code, which takes plain
arguments, then names the key in one line."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, OmegaConf

from fusion_depth.config.arguments import config_message
from fusion_depth.errors import ArgumentError, ConfigError
from fusion_depth.models._registry import MODELS, check_model_takes, model_class
from fusion_depth.models.encoder import TAPS, check_backbone_name
from fusion_depth.optim import schedules
from fusion_depth.optim.schedules import SCHEDULE_ARGUMENTS, check_schedule_arguments
from fusion_depth.utils.config_values import ABSENT, check_schema, config_value
from fusion_depth.utils.schema import POSITIVE, POSITIVE_INT, Rule, is_int, is_number, one_of


def check_backbone(cfg: DictConfig) -> None:
    """``backbone.name`` and ``model.net.backbone``: an encoder the network can build with its
    taps (``backbone.taps``/``model.net.backbone_taps``: ``paper``, the default, takes the
    paper's backbones; ``pyramid``, ``backbone=timm``, any timm model name, with a did-you-mean).
    Whether a timm model has a usable feature pyramid is only known once it is built.

    Raises:
        ConfigError: a taps value or backbone name the network cannot build, naming the key.
    """
    taps = "paper"  # a network without backbone_taps takes the backbone group's (check_model)
    model = config_value(cfg, "model.net.name")
    own = None  # the encoders a network builds itself (prior_correction's learner): check_model's
    if isinstance(model, str) and model in MODELS:
        own = MODELS[model].backbones
    for name_key, taps_key in (
        ("backbone.name", "backbone.taps"),
        ("model.net.backbone", "model.net.backbone_taps"),
    ):
        check_schema(cfg, {taps_key: one_of(*TAPS)})
        name, value = config_value(cfg, name_key), config_value(cfg, taps_key)
        taps = taps if value is ABSENT else value
        if name is ABSENT or (own is not None and name in own):
            continue
        try:
            check_backbone_name(name, taps)
        except ArgumentError as err:
            keys = {"name": name_key, "taps": taps_key}
            raise ConfigError(config_message(err, keys)) from None


def check_bottleneck(cfg: DictConfig) -> None:
    """A training crop (``augment.crop``) fits in the dataset's frames, and a training batch
    holds more than one value per channel at the encoder's bottleneck (1/32 of the input, the
    crop where there is one): batch norm in training mode cannot normalise a single value, so
    batch 1 at 32×32 would fail inside the first training step.

    Raises:
        ConfigError: naming ``augment.crop``, or ``data.batch_size`` and the training size.
    """
    batch = config_value(cfg, "data.batch_size")
    height, width = cfg.dataset.height, cfg.dataset.width
    crop = config_value(cfg, "augment.crop")
    size = f"dataset.height={height}, dataset.width={width}"
    if isinstance(crop, list) and len(crop) == 2 and all(is_int(x) for x in crop):
        if crop[0] > height or crop[1] > width:
            raise ConfigError(
                f"augment.crop={crop}: larger than the frames ({size}); expected at most "
                f"[{height}, {width}]"
            )
        height, width = crop
        size = f"augment.crop={crop}"
    if is_int(batch) and batch * (height // 32) * (width // 32) < 2:
        raise ConfigError(
            f"data.batch_size={batch} with {size}: the "
            "encoder's bottleneck (1/32 of the input) is 1×1, and batch norm needs more than one "
            "value per channel to train; use data.batch_size=2 or a height or width of 64"
        )


def check_scheduler(cfg: DictConfig) -> None:
    """The ``scheduler`` group's values (fusion_depth.utils.schema). With
    :func:`create_schedule` (a recipe's ``scheduler=<recipe_from>_<dataset>_<model>``) only the
    arguments of the schedule it names are set, the others are null, and those it names must be
    that schedule's.

    Raises:
        ConfigError: naming the key and what it accepts.
    """
    by_name = config_value(cfg, "scheduler._target_") == f"{schedules.__name__}.create_schedule"

    def rule(ok: Callable[[Any], bool], expected: str) -> Rule:
        return Rule((lambda v: v is None or ok(v)) if by_name else ok, expected)

    check_schema(
        cfg,
        {
            "scheduler.step_size": rule(POSITIVE_INT.ok, "an integer ≥ 1 (epochs)"),
            "scheduler.gamma": rule(POSITIVE.ok, "a factor > 0"),
            "scheduler.warmup_fraction": rule(
                lambda v: is_number(v) and 0 <= v < 1, "a share in [0, 1)"
            ),
            "scheduler.final_lr_ratio": rule(
                lambda v: is_number(v) and 0 <= v <= 1, "a ratio in [0, 1]"
            ),
        },
    )
    if by_name:
        scheduler = OmegaConf.to_container(cfg.scheduler, resolve=True)
        try:  # a key that is no schedule's argument is check_known_keys' to name
            check_schedule_arguments(
                scheduler.get("name", "step"),
                {k: v for k, v in scheduler.items() if k in SCHEDULE_ARGUMENTS},
            )
        except ArgumentError as err:
            raise ConfigError(config_message(err)) from None


# Where the arguments of check_model_takes are set (its messages name the groups:
# fusion_depth.config.arguments).
_MODEL_TAKES = {
    "fusion": "model.net.fusion",
    "backbone": "model.net.backbone",
    "sensor": "dataset.sensor",
    "prior": "prior.name",
}


def check_model(cfg: DictConfig) -> None:
    """The chosen network (``model.net.name``, a key of the model table) takes the chosen fusion
    mode, encoder and dataset, and its own arguments pass the rules its class declares
    (``ARGUMENT_RULES``: argument → :class:`~fusion_depth.utils.schema.Rule`).

    Raises:
        ConfigError: naming the model and the value it cannot take.
    """
    name = config_value(cfg, "model.net.name")
    if name is ABSENT:
        return
    given = {argument: config_value(cfg, key) for argument, key in _MODEL_TAKES.items()}
    try:
        check_model_takes(name, **{a: None if v is ABSENT else v for a, v in given.items()})
    except ArgumentError as err:
        message = config_message(err)
        if err.arguments == ("sensor",):  # say which dataset lacks it
            message = message.replace(": it takes", f" (dataset={cfg.dataset.name}): it takes", 1)
        raise ConfigError(message) from None
    # What the network's own arguments accept, declared on its class (fusion_depth.utils.schema)
    rules = getattr(model_class(name), "ARGUMENT_RULES", {})
    check_schema(cfg, {f"model.net.{argument}": rule for argument, rule in rules.items()})
