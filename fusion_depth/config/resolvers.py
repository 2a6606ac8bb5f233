"""The ``fd.*`` OmegaConf resolvers that ``conf/`` uses, registered on ``import fusion_depth``."""

from __future__ import annotations

from omegaconf import OmegaConf

from fusion_depth.data import cache_dir


def register_resolvers() -> None:
    """Register the ``fd.*`` resolvers (idempotent; done on ``import fusion_depth``)."""
    OmegaConf.register_new_resolver("fd.div", lambda a, b: float(a) / float(b), replace=True)
    OmegaConf.register_new_resolver("fd.cache_dir", cache_dir, replace=True)
    # conf/hydra: run folders named after the overrides (fusion_depth.runner.run_folder)
    OmegaConf.register_new_resolver("fd.run_dirname", _run_dirname, replace=True)
    OmegaConf.register_new_resolver(
        "fd.sweep_dirname", _sweep_dirname, replace=True, use_cache=True
    )


def _run_dirname(override_dirname: str) -> str:
    from fusion_depth.config.run_dirs import run_dirname

    return run_dirname(override_dirname)


def _sweep_dirname(config_name: str, override_dirname: str) -> str:
    from fusion_depth.config.run_dirs import sweep_dirname

    return sweep_dirname(config_name, override_dirname)
