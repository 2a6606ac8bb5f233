"""OmegaConf resolvers used by ``conf/``, the checks a config must pass before any work, and the
output-directory check. The errors they raise are in :mod:`fusion_depth.errors`; the redaction of
secrets from what a run writes is :mod:`fusion_depth.redaction`."""

from __future__ import annotations

import difflib
import importlib.util
import inspect
import os
import re
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from fusion_depth.data import cache_dir
from fusion_depth.errors import (
    ConfigError,
    MissingDependencyError,
    MissingValueError,
    OutputDirError,
)

# --- resolvers --------------------------------------------------------------------------------


def _shipped(name: str) -> str:
    """A folder that sits at the repository's top level and ships inside the package: the
    installed copy (``fusion_depth/<name>``) or, in a checkout, the repository's own."""
    package = Path(__file__).resolve().parent
    installed = package / name
    return str(installed if installed.is_dir() else package.parent / name)


# The Hydra configs every entry point composes, and the ready-made sweep configs.
CONF_DIR = _shipped("conf")
SWEEPS_DIR = _shipped("sweeps")


def register_resolvers() -> None:
    """Register the ``fd.*`` resolvers (idempotent; done on ``import fusion_depth``)."""
    OmegaConf.register_new_resolver("fd.div", lambda a, b: float(a) / float(b), replace=True)
    OmegaConf.register_new_resolver("fd.cache_dir", cache_dir, replace=True)
    # conf/hydra: run folders named after the overrides (fusion_depth.runs)
    OmegaConf.register_new_resolver("fd.run_dirname", _run_dirname, replace=True)
    OmegaConf.register_new_resolver(
        "fd.sweep_dirname", _sweep_dirname, replace=True, use_cache=True
    )


def _run_dirname(override_dirname: str) -> str:
    from fusion_depth.runs import run_dirname

    return run_dirname(override_dirname)


def _sweep_dirname(config_name: str, override_dirname: str) -> str:
    from fusion_depth.runs import sweep_dirname

    return sweep_dirname(config_name, override_dirname)


# --- value checks -----------------------------------------------------------------------------

_ABSENT = object()


def _show(value: Any) -> str:
    """A value as it is written on the command line (``null``, ``true``, ``[1, 2]``, ``x``)."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, list | tuple | ListConfig):
        return "[" + ", ".join(_show(v) for v in value) + "]"
    return str(value)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _get(cfg: DictConfig, key: str) -> Any:
    """The resolved value at ``key``, or ``_ABSENT``; a ``???`` value raises
    MissingMandatoryValue (turned into a one-line error by :func:`validate_config`)."""
    value = OmegaConf.select(cfg, key, default=_ABSENT, throw_on_missing=True)
    if isinstance(value, DictConfig | ListConfig):
        return OmegaConf.to_container(value, resolve=True)
    return value


def _require(cfg: DictConfig, key: str, ok: Callable[[Any], bool], expected: str) -> None:
    """``key`` (when present) must satisfy ``ok``; else a ConfigError ``key=value: expected …``."""
    value = _get(cfg, key)
    if value is not _ABSENT and not ok(value):
        raise ConfigError(f"{key}={_show(value)}: expected {expected}")


def _one_of(*allowed: Any) -> tuple[Callable[[Any], bool], str]:
    names = ", ".join(_show(a) for a in allowed)

    def ok(value: Any) -> bool:
        return any(type(value) is type(a) and value == a for a in allowed)

    return ok, f"one of {names}"


def check_dataset(ds: DictConfig, fusion: str) -> None:
    """A dataset block the network can take, with ``fusion`` (its input mode) allowed on it."""
    for key in ("height", "width"):
        value = ds[key]
        if not _is_int(value) or value <= 0 or value % 32:
            raise ConfigError(
                f"dataset.{key}={_show(value)}: expected a positive multiple of 32 "
                "(the encoder downsamples by 32)"
            )
    for key in ("min_depth", "max_depth", "depth_scale"):
        if not _is_number(ds[key]) or not ds[key] > 0:
            raise ConfigError(f"dataset.{key}={_show(ds[key])}: expected a positive number")
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
    from fusion_depth.models.encoder import ENCODER_SPECS
    from fusion_depth.models.fusion import FUSION_MODES, SPARSE_ENCODINGS
    from fusion_depth.resume import RESUME_MODES
    from fusion_depth.speed import COMPILE_MODES, PRECISIONS

    _require(cfg, "fusion.mode", *_one_of(*FUSION_MODES))
    _require(cfg, "loss.pixel", *_one_of(*PIXEL_LOSSES))
    _require(cfg, "backbone.name", *_one_of(*sorted(ENCODER_SPECS)))
    _require(cfg, "backbone.pretrained", *_one_of(True, False))
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
        lambda v: v is None
        or positive_int(v)
        or (isinstance(v, float) and 0 < v <= 1)
        or isinstance(v, str | dict),
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
        lambda v: isinstance(v, list) and len(v) == 2 and all(
            _is_number(b) and 0 <= b < 1 for b in v
        ),
        "[beta1, beta2], each in [0, 1)",
    )
    _require(cfg, "optimizer.eps", positive_number, "a number > 0")
    _require(cfg, "optimizer.weight_decay", nonneg_number, "a number ≥ 0")
    _require(cfg, "optimizer.momentum", nonneg_number, "a number ≥ 0")
    _require(cfg, "scheduler.step_size", positive_int, "an integer ≥ 1 (epochs)")
    _require(cfg, "scheduler.gamma", positive_number, "a factor > 0")
    _require(cfg, "callbacks.progress_log.every_s", positive_number, "seconds > 0")

    _require(cfg, "model.net.fusion", *_one_of(*FUSION_MODES))
    _require(cfg, "model.net.backbone", *_one_of(*sorted(ENCODER_SPECS)))
    _require(cfg, "model.net.sparse_encoding", *_one_of(*SPARSE_ENCODINGS))
    _require(cfg, "model.compile", *_one_of(True, False, "auto"))
    _require(cfg, "model.compile_mode", *_one_of(*COMPILE_MODES))
    _require(cfg, "model.channels_last", *_one_of(True, False))
    _require(cfg, "model.on_nonfinite_loss", *_one_of(*NONFINITE_ACTIONS))
    _require(cfg, "model.max_nonfinite_skips", nonneg_int, "an integer ≥ 0")
    _require(cfg, "model.num_val_panels", nonneg_int, "an integer ≥ 0")

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


# --- unknown keys -----------------------------------------------------------------------------

# Nodes without a ``_target_`` whose keys are one callable's arguments: data → the datamodule
# (``DepthDataModule(reader=..., **cfg.data)``), eval → the evaluation protocol.
PLAIN_CONSUMERS: dict[str, str] = {
    "data": "fusion_depth.data.datamodule.DepthDataModule",
    "eval": "fusion_depth.evaluation.EvalProtocol",
}
# Arguments the code passes itself, per node: not config keys (a value would clash with the
# code's or be overridden by it).
PASSED_BY_CODE: dict[str, dict[str, str]] = {
    "trainer": {
        "callbacks": "fusion_depth.train builds them from the callbacks group",
        "logger": "fusion_depth.train builds it from the logger group",
        "plugins": "fusion_depth.train sets its checkpoint writer",
    },
    "data": {
        "reader": "fusion_depth.train builds it from dataset.reader",
        "seed": "fusion_depth.train passes the run's seed",
    },
    "dataset.reader": {
        "split": "the datamodule builds each split",
        "on_error": "fusion_depth.prepare skips broken frames, training stops at the first",
    },
    "optimizer": {"params": "the module passes its parameters"},
    "scheduler": {"optimizer": "the module passes its optimizer"},
}
# Keys fusion_depth.train reads directly although no config file may define them, so a
# ``+key=value`` override of them is not an unknown key.
READ_BY_CODE = ("resume", "sweep.skip_done", "dataset.fusions", "dataset.requires")
_RESERVED = re.compile(r"^_\w+_$")  # Hydra's _target_, _partial_, _convert_, _recursive_, _args_
_REFERENCE = re.compile(r"\$\{(\.*)([A-Za-z_][\w-]*(?:(?:\.[\w-]+)|(?:\[[^\]]*\]))*)\}")


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


def unknown_key_error(key: str, allowed: list[str], note: str = "") -> ConfigError:
    """``key: unknown key (did you mean …?); expected one of …``, one line."""
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], allowed, n=1)
    notes = [n for n in (note, f"did you mean {close[0]}?" if close else "") if n]
    hint = f" ({'; '.join(notes)})" if notes else ""
    expected = f"one of {', '.join(sorted(allowed))}" if allowed else "no keys here"
    return ConfigError(f"{key}: unknown key{hint}; expected {expected}")


def _parameters(target: Any) -> dict[str, inspect.Parameter] | None:
    """The keyword arguments ``target`` takes; None when it takes ``**kwargs`` (or has no
    signature to read), so any key may be right."""
    try:
        signature = inspect.signature(target)
    except (TypeError, ValueError):
        return None
    params = {}
    for name, param in signature.parameters.items():
        if param.kind is inspect.Parameter.VAR_KEYWORD:
            return None
        if param.kind in (param.POSITIONAL_OR_KEYWORD, param.KEYWORD_ONLY):
            params[name] = param
    return params


def target_accepts(node: Any, key: str) -> bool:
    """Whether ``node`` (a config node) has a ``_target_`` that takes the argument ``key``."""
    from hydra.utils import get_object

    target = node.get("_target_") if isinstance(node, DictConfig) else None
    if not isinstance(target, str):
        return False
    try:
        params = _parameters(get_object(target))
    except Exception:  # noqa: BLE001 - an unimportable target accepts nothing we can tell
        return False
    return params is None or key in params


def _import_target(target: str, key: str) -> Any:
    from hydra.utils import get_object

    try:
        return get_object(target)
    except Exception as err:  # noqa: BLE001 - any failure means the target cannot be built
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{key}={target}: cannot be imported ({first})") from None


def _check_node(node: Mapping, path: str, target: Any) -> None:
    """Every key of ``node`` (Hydra's ``_x_`` keys aside) must be an argument of ``target``
    that the code does not pass itself."""
    params = _parameters(target)
    if params is None:
        return
    by_code = PASSED_BY_CODE.get(path, {})
    allowed = [name for name in params if name not in by_code]
    for key in node:
        if not isinstance(key, str) or _RESERVED.match(key):
            continue
        if key in by_code:
            raise ConfigError(f"{_join(path, key)}: not a config key ({by_code[key]})")
        if key not in allowed:
            raise unknown_key_error(_join(path, key), allowed)


def _walk(node: Any, path: str = "") -> Iterator[tuple[str, Mapping]]:
    """(path, dict) of every mapping in a plain (unresolved) config, depth first."""
    if isinstance(node, Mapping):
        yield path, node
        for key, value in node.items():
            yield from _walk(value, _join(path, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield from _walk(value, f"{path}[{i}]")


def _strings(node: Any, path: str = "") -> Iterator[tuple[str, str]]:
    """(path of the containing node, string) of every string value in a plain config."""
    if isinstance(node, Mapping):
        for key, value in node.items():
            if isinstance(value, str):
                yield path, value
            else:
                yield from _strings(value, _join(path, key))
    elif isinstance(node, list):
        for value in node:
            if isinstance(value, str):
                yield path, value
            else:
                yield from _strings(value, path)


def _references(*configs: Any) -> set[str]:
    """The config keys that interpolations (``${a.b}``, also nested in resolver calls) read."""
    found = set()
    for config in configs:
        for node_path, text in _strings(config):
            for dots, key in _REFERENCE.findall(text):
                key = re.sub(r"\[[^\]]*\]", "", key)
                if dots:  # relative: one dot is the containing node, each further one its parent
                    base = node_path.split(".") if node_path else []
                    base = base[: max(len(base) - (len(dots) - 1), 0)]
                    key = ".".join([*base, key])
                found.add(key)
    return found


def _is_config_group(name: str) -> bool:
    """Whether ``name`` is a config group on the running app's search path (``+experiment=x``
    adds a group, ``+seedx=1`` a key)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return False
    for source in HydraConfig.get().runtime.config_sources:
        try:
            if source.schema == "file" and (Path(source.path) / name).is_dir():
                return True
            if source.schema == "pkg":
                from importlib.resources import files

                if files(source.path.replace("/", ".")).joinpath(name).is_dir():
                    return True
            if source.schema == "structured":
                from hydra.core.config_store import ConfigStore

                repo = ConfigStore.instance().repo
                for part in name.split("/"):
                    repo = repo[part]
                if isinstance(repo, dict):
                    return True
        except (KeyError, ModuleNotFoundError, OSError, TypeError):
            continue
    return False


def _added_keys() -> list[str]:
    """Keys the command line added with ``+key=value`` (``+`` fails on an existing key, so
    these are exactly the keys no config file defines); config-group additions left out."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.core.override_parser.overrides_parser import OverridesParser

    if not HydraConfig.initialized():
        return []
    overrides = OverridesParser.create().parse_overrides(list(HydraConfig.get().overrides.task))
    return [
        o.key_or_group
        for o in overrides
        if o.is_add() and o.package is None and not _is_config_group(o.key_or_group)
    ]


def check_known_keys(cfg: DictConfig) -> None:
    """Every key is read by something: the keys of a ``_target_`` node are the arguments of
    its target (unless it takes ``**kwargs``), those of ``data`` and ``eval`` the arguments of
    the datamodule and the evaluation protocol, and a key added with ``+key=value`` elsewhere
    must be read by an interpolation (or by train itself, :data:`READ_BY_CODE`). Hydra rejects
    ``key=value`` for an unknown key, but it accepts ``+key=value``, which would otherwise fail
    deep inside instantiate or be ignored in silence."""
    plain = OmegaConf.to_container(cfg, resolve=False)
    checked: list[str] = []  # nodes whose keys are checked against a signature
    for path, node in _walk(plain):
        if "_target_" in node:
            target = OmegaConf.select(cfg, _join(path, "_target_"))
            if target is None:  # e.g. logger=none
                continue
            if not isinstance(target, str):
                raise ConfigError(f"{_join(path, '_target_')}={_show(target)}: expected a name")
            _check_node(node, path, _import_target(target, _join(path, "_target_")))
            checked.append(path)
    for path, target in PLAIN_CONSUMERS.items():
        node = plain.get(path)
        if isinstance(node, Mapping):
            _check_node(node, path, _import_target(target, path))
            checked.append(path)

    added = _added_keys()
    if not added:
        return
    from hydra.core.hydra_config import HydraConfig

    hydra_cfg = OmegaConf.to_container(HydraConfig.get(), resolve=False)
    read = _references(plain, {"hydra": hydra_cfg})
    for key in added:
        if any(key.startswith(f"{c}.") for c in checked if c):
            continue  # checked above against its node's signature
        if isinstance(OmegaConf.select(cfg, key, throw_on_resolution_failure=False), DictConfig):
            continue  # a whole node (e.g. a new callback): its _target_ is checked above
        if key in READ_BY_CODE or any(
            r == key or r.startswith(f"{key}.") or key.startswith(f"{r}.") for r in read
        ):
            continue
        parent, _, _ = key.rpartition(".")
        siblings = OmegaConf.select(cfg, parent) if parent else cfg
        allowed = [
            k
            for k in (siblings.keys() if isinstance(siblings, DictConfig) else [])
            if isinstance(k, str) and _join(parent, k) not in added
        ]
        raise unknown_key_error(key, allowed, "nothing reads it")


def validate_config(cfg: DictConfig) -> dict:
    """Fail before touching data: unknown keys, missing values, and values the network cannot
    take, each a one-line error naming the key (Hydra prints it without a traceback).

    Hydra already rejects unknown group choices with the list of options. Returns the resolved
    config as plain data.
    """
    try:
        OmegaConf.to_container(cfg, resolve=False, throw_on_missing=True)  # ??? values first
        check_values(cfg)  # before importing targets: a missing optional package is named
        check_known_keys(cfg)
        return OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    except MissingValueError:
        raise
    except MissingMandatoryValue as err:
        key = err.full_key or "?"
        raise MissingValueError(
            f"{key}: missing value (???); set it on the command line: {key}=..."
        ) from None
    except OmegaConfBaseException as err:
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise ConfigError(f"{err.full_key or 'config'}: {first}") from None


# --- output directory -------------------------------------------------------------------------

MB = 1_000_000


def check_output_dir(path: str | os.PathLike, needed_bytes: int) -> None:
    """Fail before training unless ``path`` can be created and written to and its file system
    has ``needed_bytes`` free (see :func:`checkpoint_bytes`); one-line OutputDirError."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=".write-check-", dir=path)
        try:
            os.write(fd, b"ok")
        finally:
            os.close(fd)
            os.unlink(name)
    except OSError as err:
        reason = err.strerror or type(err).__name__
        raise OutputDirError(f"output directory {path}: not writable ({reason})") from None
    free = shutil.disk_usage(path).free
    if free < needed_bytes:
        raise OutputDirError(
            f"output directory {path}: {free / MB:.0f} MB free, the run needs about "
            f"{needed_bytes / MB:.0f} MB for its checkpoints; free some space or choose another "
            "directory (hydra.run.dir=... / hydra.sweep.dir=...)"
        )


def checkpoint_bytes(model: Any, optimizer_states: int = 2) -> int:
    """The size of one full Lightning checkpoint of ``model`` (an ``nn.Module``): its
    parameters once for the weights and ``optimizer_states`` more times for the optimizer's
    per-parameter state (Adam: 2), plus its buffers. Metadata adds little."""
    params = sum(p.numel() * p.element_size() for p in model.parameters())
    buffers = sum(b.numel() * b.element_size() for b in model.buffers())
    return int(params * (1 + optimizer_states) + buffers)
