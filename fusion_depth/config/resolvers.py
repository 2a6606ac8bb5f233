"""The ``fd.*`` OmegaConf resolvers that ``conf/`` uses, registered on ``import fusion_depth``."""

from __future__ import annotations

from omegaconf import OmegaConf

from fusion_depth.config.run_dirs import job_subdir, run_dir, sweep_dir
from fusion_depth.data import cache_dir


def register_resolvers() -> None:
    """Register the ``fd.*`` resolvers (idempotent; done on ``import fusion_depth``)."""
    OmegaConf.register_new_resolver("fd.div", lambda a, b: float(a) / float(b), replace=True)
    OmegaConf.register_new_resolver("fd.cache_dir", cache_dir, replace=True)
    # conf/hydra: run folders named after the overrides (fusion_depth.config.run_dirs)
    OmegaConf.register_new_resolver("fd.run_dir", run_dir, replace=True)
    OmegaConf.register_new_resolver("fd.job_subdir", job_subdir, replace=True)
    OmegaConf.register_new_resolver("fd.sweep_dir", sweep_dir, replace=True, use_cache=True)
