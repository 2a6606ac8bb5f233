"""The values the network, the trainer and the data pipeline can take, each checked (when the key
is present) before anything is built; errors are one line naming the key."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from fusion_depth.config.show import show
from fusion_depth.errors import ConfigError, MissingDependencyError
from fusion_depth.schedules import SCHEDULE_ARGUMENTS, check_schedule_arguments

_ABSENT = object()


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _get(cfg: DictConfig, key: str) -> Any:
    """The resolved value at ``key``, or ``_ABSENT``; a ``???`` value raises
    MissingMandatoryValue (turned into a one-line error by
    :func:`~fusion_depth.config.validation.validate_config`)."""
    value = OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=True)
    if isinstance(value, DictConfig | ListConfig):
        return OmegaConf.to_container(value, resolve=True)
    return value


def _require(cfg: DictConfig, key: str, ok: Callable[[Any], bool], expected: str) -> None:
    """``key`` (when present) must satisfy ``ok``; else a ConfigError ``key=value: expected …``."""
    value = _get(cfg, key)
    if value is not _ABSENT and not ok(value):
        raise ConfigError(f"{key}={show(value)}: expected {expected}")


def _one_of(*allowed: Any) -> tuple[Callable[[Any], bool], str]:
    names = ", ".join(show(a) for a in allowed)

    def ok(value: Any) -> bool:
        return any(type(value) is type(a) and value == a for a in allowed)

    return ok, f"one of {names}"


def check_dataset(ds: DictConfig, fusion: str) -> None:
    """A dataset block the network can take, with ``fusion`` (its input mode) allowed on it."""
    from fusion_depth.data.base import check_size

    try:
        check_size(ds.height, ds.width)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    for key in ("min_depth", "max_depth", "depth_scale"):
        if not _is_number(ds[key]) or not ds[key] > 0:
            raise ConfigError(f"dataset.{key}={show(ds[key])}: expected a positive number")
    if not 0 < ds.min_depth < ds.max_depth:
        raise ConfigError(
            f"dataset.min_depth={ds.min_depth}, dataset.max_depth={ds.max_depth}: "
            "expected 0 < min_depth < max_depth"
        )
    needs = ds.get("requires")
    if needs is not None and importlib.util.find_spec(needs.module) is None:
        raise MissingDependencyError(
            f"dataset={ds.name} needs {needs.package} (module {needs.module!r}), which is not "
            f"installed: {needs.install}"
        )
    allowed = ds.get("fusions")
    if allowed is not None and fusion not in allowed:
        raise ConfigError(
            f"fusion={fusion}: dataset={ds.name} has no sparse sensor input, so only "
            f"fusion={'/'.join(allowed)} is possible (dataset.fusions)"
        )


def check_model(cfg: DictConfig) -> None:
    """The chosen network (``model.net.name``, a key of the model table) takes the chosen fusion
    mode, encoder and dataset; a refusal names the model and the value it cannot take."""
    from fusion_depth.models import model_entry

    name = _get(cfg, "model.net.name")
    if name is _ABSENT:
        return
    try:
        entry = model_entry(name)
    except ValueError as err:
        raise ConfigError(str(err)) from None
    checks = (
        ("fusion", _get(cfg, "model.net.fusion"), entry.fusions),
        ("backbone", _get(cfg, "model.net.backbone"), entry.backbones),
        ("dataset.sensor", _get(cfg, "dataset.sensor"), entry.sensors),
    )
    for key, value, allowed in checks:
        if value is not _ABSENT and allowed is not None and value not in allowed:
            dataset = f" (dataset={cfg.dataset.name})" if key == "dataset.sensor" else ""
            raise ConfigError(
                f"model={name} cannot take {key}={show(value)}{dataset}: it takes "
                f"{key}={'/'.join(allowed)} ({entry.paper})"
            )


def check_backbone(cfg: DictConfig) -> None:
    """``backbone.name`` and ``model.net.backbone``: an encoder the network can build with its
    taps (``backbone.taps``/``model.net.backbone_taps``: ``paper``, the default, takes the
    paper's backbones; ``pyramid``, ``backbone=timm``, any timm model name, with a did-you-mean).
    Whether a timm model has a usable feature pyramid is only known once it is built."""
    from fusion_depth.models.encoder import TAPS, check_backbone_name

    taps = "paper"  # a network without backbone_taps takes the backbone group's (check_model)
    for name_key, taps_key in (
        ("backbone.name", "backbone.taps"),
        ("model.net.backbone", "model.net.backbone_taps"),
    ):
        _require(cfg, taps_key, *_one_of(*TAPS))
        name, value = _get(cfg, name_key), _get(cfg, taps_key)
        taps = taps if value is _ABSENT else value
        if name is _ABSENT:
            continue
        try:
            check_backbone_name(name, taps, key=name_key)
        except ValueError as err:
            raise ConfigError(str(err)) from None


def check_bottleneck(cfg: DictConfig) -> None:
    """A training batch must hold more than one value per channel at the encoder's bottleneck
    (1/32 of the input): batch norm in training mode cannot normalise a single value, so batch 1
    at 32×32 would fail inside the first training step."""
    batch = _get(cfg, "data.batch_size")
    height, width = cfg.dataset.height, cfg.dataset.width
    if _is_int(batch) and batch * (height // 32) * (width // 32) < 2:
        raise ConfigError(
            f"data.batch_size={batch} with dataset.height={height}, dataset.width={width}: the "
            "encoder's bottleneck (1/32 of the input) is 1×1, and batch norm needs more than one "
            "value per channel to train; use data.batch_size=2 or a height or width of 64"
        )


def check_values(cfg: DictConfig) -> None:
    """The values the network, the trainer and the data pipeline can take, each checked (when
    the key is present) before anything is built; errors are one line naming the key."""
    from fusion_depth.data import SPLITS
    from fusion_depth.inference import UPSAMPLING
    from fusion_depth.losses import NONFINITE_ACTIONS, PIXEL_LOSSES
    from fusion_depth.metrics import AVERAGING, EVAL_CROPS
    from fusion_depth.models.fusion import FUSION_MODES, SPARSE_ENCODINGS
    from fusion_depth.resume import RESUME_MODES
    from fusion_depth.speed import COMPILE_MODES, PRECISIONS

    _require(cfg, "fusion.mode", *_one_of(*FUSION_MODES))
    _require(cfg, "loss.pixel", *_one_of(*PIXEL_LOSSES))
    check_backbone(cfg)
    _require(cfg, "backbone.pretrained", *_one_of(True, False))
    # A fusion mode no model takes is named alone; then the model check, before the dataset's
    # own checks, so a model that needs a sensor the dataset lacks is refused naming both
    # (model=radarnet on a camera-only dataset).
    _require(cfg, "model.net.fusion", *_one_of(*FUSION_MODES))
    check_model(cfg)
    check_dataset(cfg.dataset, cfg.fusion.mode)
    _require(cfg, "seed", _is_int, "an integer")

    def positive_int(v: Any) -> bool:
        return _is_int(v) and v >= 1

    def nonneg_int(v: Any) -> bool:
        return _is_int(v) and v >= 0

    def probability(v: Any) -> bool:
        return _is_number(v) and 0 <= v <= 1

    def factor_range(v: Any) -> bool:
        return (
            isinstance(v, list)
            and len(v) == 2
            and all(_is_number(x) for x in v)
            and 0 < v[0] <= v[1]
        )

    def nonneg_number(v: Any) -> bool:
        return _is_number(v) and v >= 0

    _require(cfg, "data.batch_size", positive_int, "an integer ≥ 1")
    check_bottleneck(cfg)
    _require(
        cfg,
        "data.eval_batch_size",
        lambda v: v is None or positive_int(v),
        "an integer ≥ 1, or null (data.batch_size)",
    )
    _require(
        cfg,
        "data.num_workers",
        lambda v: v == "auto" or nonneg_int(v),
        "auto or an integer ≥ 0",
    )
    for key in ("data.pin_memory", "data.persistent_workers"):
        _require(cfg, key, *_one_of(None, True, False))
    _require(cfg, "data.test_split", *_one_of(*SPLITS))

    _require(cfg, "augment.flip_p", probability, "a probability in [0, 1]")
    _require(cfg, "augment.color_p", probability, "a probability in [0, 1]")
    for key in ("augment.brightness", "augment.contrast"):
        _require(cfg, key, factor_range, "[low, high] factors with 0 < low ≤ high")
    for key in ("loss.w_ssim", "loss.w_edge", "loss.w_pixel"):
        _require(cfg, key, nonneg_number, "a number ≥ 0")
    _require(cfg, "loss.berhu_threshold", lambda v: _is_number(v) and v > 0, "a number > 0")

    _require(
        cfg,
        "trainer.max_epochs",
        lambda v: v is None or (_is_int(v) and v == -1) or positive_int(v),
        "an integer ≥ 1, -1 (no epoch limit: trainer.max_steps or max_time stops the run) or "
        "null (Lightning's default: 1000 unless trainer.max_steps is set)",
    )
    _require(cfg, "trainer.precision", *_one_of(*PRECISIONS))
    _require(cfg, "trainer.accumulate_grad_batches", positive_int, "an integer ≥ 1")
    _require(
        cfg,
        "trainer.max_steps",
        lambda v: _is_int(v) and v >= -1,
        "an integer ≥ 1, or -1 (no step limit)",
    )
    _require(
        cfg,
        "trainer.gradient_clip_val",
        lambda v: v is None or nonneg_number(v),
        "a number ≥ 0, or null (no clipping)",
    )
    _require(
        cfg,
        "trainer.val_check_interval",
        lambda v: (
            v is None
            or positive_int(v)
            or (isinstance(v, float) and 0 < v <= 1)
            or isinstance(v, str | dict)
        ),
        "null (once per epoch), a fraction of the epoch in (0, 1], or a number of batches ≥ 1",
    )

    # The optimizer's and scheduler's arguments (torch.optim.Adam, StepLR; the keys any other
    # choice shares are checked alike), before torch's own checks deep inside training.
    def positive_number(v: Any) -> bool:
        return _is_number(v) and v > 0

    _require(cfg, "optimizer.lr", positive_number, "a learning rate > 0")
    _require(
        cfg,
        "optimizer.betas",
        lambda v: (
            isinstance(v, list) and len(v) == 2 and all(_is_number(b) and 0 <= b < 1 for b in v)
        ),
        "[beta1, beta2], each in [0, 1)",
    )
    _require(cfg, "optimizer.eps", positive_number, "a number > 0")
    _require(cfg, "optimizer.weight_decay", nonneg_number, "a number ≥ 0")
    _require(cfg, "optimizer.momentum", nonneg_number, "a number ≥ 0")

    # A schedule's arguments; with fusion_depth.schedules.create_schedule (scheduler=
    # for_densedepth) only those of the schedule it names are set, the others are null.
    by_name = _get(cfg, "scheduler._target_") == "fusion_depth.schedules.create_schedule"

    def unset_or(ok: Callable[[Any], bool]) -> Callable[[Any], bool]:
        return (lambda v: v is None or ok(v)) if by_name else ok

    _require(cfg, "scheduler.step_size", unset_or(positive_int), "an integer ≥ 1 (epochs)")
    _require(cfg, "scheduler.gamma", unset_or(positive_number), "a factor > 0")
    _require(
        cfg,
        "scheduler.warmup_fraction",
        unset_or(lambda v: _is_number(v) and 0 <= v < 1),
        "a share in [0, 1)",
    )
    _require(
        cfg,
        "scheduler.final_lr_ratio",
        unset_or(lambda v: _is_number(v) and 0 <= v <= 1),
        "a ratio in [0, 1]",
    )
    if by_name:
        scheduler = OmegaConf.to_container(cfg.scheduler, resolve=True)
        try:  # a key that is no schedule's argument is check_known_keys' to name
            check_schedule_arguments(
                scheduler.get("name", "step"),
                {k: v for k, v in scheduler.items() if k in SCHEDULE_ARGUMENTS},
            )
        except ValueError as err:
            raise ConfigError(str(err)) from None
    _require(cfg, "callbacks.progress_log.every_s", positive_number, "seconds > 0")

    _require(cfg, "model.net.sparse_encoding", *_one_of(*SPARSE_ENCODINGS))
    _require(cfg, "model.compile", *_one_of(True, False, "auto"))
    _require(cfg, "model.compile_mode", *_one_of(*COMPILE_MODES))
    _require(cfg, "model.channels_last", *_one_of(True, False))
    _require(cfg, "model.on_nonfinite_loss", *_one_of(*NONFINITE_ACTIONS))
    _require(cfg, "model.max_nonfinite_skips", nonneg_int, "an integer ≥ 0")
    _require(cfg, "model.num_val_panels", nonneg_int, "an integer ≥ 0")
    _require(cfg, "model.num_test_panels", nonneg_int, "an integer ≥ 0")

    _require(cfg, "eval.crop", *_one_of(*EVAL_CROPS))
    _require(cfg, "eval.averaging", *_one_of(*AVERAGING))
    _require(cfg, "eval.upsample", *_one_of(*UPSAMPLING))
    _require(cfg, "eval.flip_tta", *_one_of(True, False))
    _require(
        cfg,
        "eval.bin_width",
        lambda v: v is None or (_is_number(v) and v > 0),
        "a positive number of metres, or null (no distance breakdown)",
    )
    _require(
        cfg,
        "eval.min_depth",
        lambda v: v is None or (_is_number(v) and v > 0),
        "a positive number of metres, or null (dataset.min_depth)",
    )
    floor = _get(cfg, "eval.min_depth")
    floor = cfg.dataset.min_depth if floor in (None, _ABSENT) else floor
    _require(
        cfg,
        "eval.max_depth",
        lambda v: (
            v is None
            or (_is_number(v) and v > floor)
            or (isinstance(v, list) and v and all(_is_number(c) and c > floor for c in v))
        ),
        f"a cap or a list of caps in metres, each above the minimum depth {floor}, or null "
        "(dataset.max_depth)",
    )

    # read by fusion_depth.train itself (fusion_depth.resume)
    _require(cfg, "resume", *_one_of(*RESUME_MODES))
    _require(cfg, "sweep.skip_done", *_one_of(True, False))
