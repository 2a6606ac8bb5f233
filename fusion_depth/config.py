"""OmegaConf resolvers used by ``conf/`` and the checks a config must pass before any work."""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from omegaconf import DictConfig, OmegaConf


def _cache_dir() -> str:
    """Where generated/prepared datasets live: $FUSION_DEPTH_CACHE or ~/.cache/fusion_depth."""
    return str(Path(os.environ.get("FUSION_DEPTH_CACHE", "~/.cache/fusion_depth")).expanduser())


def register_resolvers() -> None:
    """Register the ``fd.*`` resolvers (idempotent; done on ``import fusion_depth``)."""
    OmegaConf.register_new_resolver("fd.div", lambda a, b: float(a) / float(b), replace=True)
    OmegaConf.register_new_resolver("fd.cache_dir", _cache_dir, replace=True)


def check_dataset(ds: DictConfig, fusion: str) -> None:
    """A dataset block the network can take, with ``fusion`` (its input mode) allowed on it."""
    for key in ("height", "width"):
        value = ds[key]
        if not isinstance(value, int) or value <= 0 or value % 32:
            raise ValueError(
                f"dataset.{key}={value}: expected a positive multiple of 32 "
                "(the encoder downsamples by 32)"
            )
    if not 0 < ds.min_depth < ds.max_depth:
        raise ValueError(
            f"dataset.min_depth={ds.min_depth}, dataset.max_depth={ds.max_depth}: "
            "expected 0 < min_depth < max_depth"
        )
    needs = ds.get("requires")
    if needs is not None and importlib.util.find_spec(needs.module) is None:
        raise ImportError(
            f"dataset={ds.name} needs {needs.package} (module {needs.module!r}), which is not "
            f"installed: {needs.install}"
        )
    allowed = ds.get("fusions")
    if allowed is not None and fusion not in allowed:
        raise ValueError(
            f"fusion={fusion}: dataset={ds.name} has no sparse sensor input, so only "
            f"fusion={'/'.join(allowed)} is possible (dataset.fusions)"
        )


def validate_config(cfg: DictConfig) -> dict:
    """Fail before touching data: missing values, and values the network cannot take.

    Hydra already rejects unknown group choices with the list of options; this catches
    ``???`` values anywhere and the numeric constraints, each naming the key. Returns the
    resolved config as plain data.
    """
    resolved = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
    check_dataset(cfg.dataset, cfg.fusion.mode)
    if cfg.data.batch_size < 1:
        raise ValueError(f"data.batch_size={cfg.data.batch_size}: expected an integer ≥ 1")
    return resolved
