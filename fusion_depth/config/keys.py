"""Unknown keys: every key of a config is read by something (a target's argument, an
interpolation, or the code itself); one-line errors naming the key and the close matches."""

from __future__ import annotations

import difflib
import functools
import inspect
import re
from collections.abc import Collection, Iterator, Mapping
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from fusion_depth.errors import ArgumentError, ConfigError
from fusion_depth.utils.overrides import show

# Nodes without a ``_target_`` whose keys are one callable's arguments: data → the datamodule
# (``DepthDataModule(reader=..., **cfg.data)``), eval → the evaluation protocol.
PLAIN_CONSUMERS: dict[str, str] = {
    "data": "fusion_depth.runner.datamodule.DepthDataModule",
    "eval": "fusion_depth.runner.protocol.EvalProtocol",
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
    "scheduler": {
        "optimizer": "the module passes its optimizer",
        "total_steps": "the module passes the run's optimizer steps",
    },
}
# Keys fusion_depth.train reads directly although no config file may define them, so a
# ``+key=value`` override of them is not an unknown key.
READ_BY_CODE = ("resume", "sweep.skip_done", "dataset.fusions", "dataset.requires")
_MODEL_REGISTRY = "fusion_depth.models._registry"  # its create_model takes the model's keys
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


def _is_model_factory(target: Any) -> bool:
    """Whether ``target`` is :func:`fusion_depth.models.create_model`. The model registry is
    imported only for a target from it: it imports timm (seconds), and ``prepare``, which checks
    only its dataset, does without."""
    if getattr(target, "__module__", None) != _MODEL_REGISTRY:
        return False
    from fusion_depth.models._registry import create_model

    return target is create_model


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


def check_known_keys(cfg: DictConfig, only: Collection[str] | None = None) -> None:
    """Every key is read by something: the keys of a ``_target_`` node are the arguments of
    its target (unless it takes ``**kwargs``), those of ``data`` and ``eval`` the arguments of
    the datamodule and the evaluation protocol, and a key added with ``+key=value`` elsewhere
    must be read by an interpolation (or by train itself, :data:`READ_BY_CODE`). Hydra rejects
    ``key=value`` for an unknown key, but it accepts ``+key=value``, which would otherwise fail
    deep inside instantiate or be ignored in silence.

    ``only`` (top-level keys, e.g. ``("dataset", "prepare")``) checks those nodes alone, for a
    command that reads nothing else (``prepare``); it imports only their targets.

    Raises:
        ConfigError: the first unknown key, in one line naming it and the keys that exist.
    """
    plain = OmegaConf.to_container(cfg, resolve=False)
    checked: list[str] = []  # nodes whose keys are checked against a signature
    for path, node in _walk(plain):
        if only is not None and path.split(".")[0].split("[")[0] not in only:
            continue
        if "_target_" in node:
            target = OmegaConf.select(cfg, _join(path, "_target_"))
            if target is None:  # e.g. logger=none
                continue
            if not isinstance(target, str):
                raise ConfigError(f"{_join(path, '_target_')}={show(target)}: expected a name")
            built = _import_target(target, _join(path, "_target_"))
            if _is_model_factory(built):  # the keys are the named model's arguments
                from fusion_depth.models._registry import model_class

                try:
                    built = model_class(OmegaConf.select(cfg, _join(path, "name")))
                except ArgumentError as err:
                    raise ConfigError(err.naming(functools.partial(_join, path))) from None
                node = {k: v for k, v in node.items() if k != "name"}
            _check_node(node, path, built)
            checked.append(path)
    for path, target in PLAIN_CONSUMERS.items():
        node = plain.get(path) if only is None or path in only else None
        if isinstance(node, Mapping):
            _check_node(node, path, _import_target(target, path))
            checked.append(path)

    added = [k for k in _added_keys() if only is None or k.split(".")[0] in only]
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
