"""Secrets never reach what a run writes: secret-looking values (``*api_key*``, ``*token*``,
``*password*``, … in config keys, overrides or the environment) are replaced by ``***`` in
configs, overrides and Hydra's own ``.hydra/`` files."""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, ListConfig, OmegaConf

from fusion_depth.utils.atomic import write_text_atomic

REDACTED = "***"
_SECRET_WORDS = (
    "api_key",
    "apikey",
    "token",
    "secret",
    "password",
    "passwd",
    "passphrase",
    "credential",
    "credentials",
    "private_key",
    "access_key",
)
_SECRET_NAME = re.compile(
    r"(?<![a-z0-9])(" + "|".join(re.escape(w) for w in _SECRET_WORDS) + r")(?![a-z0-9])"
)
# key=value inside free text (a comma-joined override_dirname, an argv line)
_ASSIGNMENT = re.compile(r"([A-Za-z0-9_.\-/@+~]+)=([^\s,;&'\"]*)")


def is_secret_name(name: str) -> bool:
    """Whether a key or variable name looks like it holds a secret (``api_key``, ``apiKey``,
    ``WANDB_API_KEY``, ``hf_token``, ``db.password``, ``client_secret``, ``credentials``, …)."""
    snake = re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", name).lower().replace("-", "_")
    return _SECRET_NAME.search(snake) is not None


def _secret_env_values() -> list[str]:
    """Values of secret-named environment variables (WANDB_API_KEY, HF_TOKEN, …), longest
    first, so one that found its way into a string is still redacted."""
    values = {v for k, v in os.environ.items() if is_secret_name(k) and len(v) >= 8}
    return sorted(values, key=len, reverse=True)


def _redact_text(text: str, env_values: list[str]) -> str:
    for value in env_values:
        text = text.replace(value, REDACTED)
    return _ASSIGNMENT.sub(
        lambda m: f"{m[1]}={REDACTED}" if is_secret_name(m[1]) and m[2] else m[0], text
    )


def _redact_override(override: str, env_values: list[str]) -> str:
    key, sep, value = override.partition("=")
    if sep and is_secret_name(key) and value:
        return f"{key}={REDACTED}"
    return _redact_text(override, env_values)


def _redact(data: Any, env_values: list[str]) -> Any:
    if isinstance(data, DictConfig | ListConfig):
        data = OmegaConf.to_container(data, resolve=False)
    if isinstance(data, Mapping):
        out = {}
        for key, value in data.items():
            secret = isinstance(key, str) and is_secret_name(key)
            if secret and value not in (None, "", {}, []):
                out[key] = REDACTED
            else:
                out[key] = _redact(value, env_values)
        return out
    if isinstance(data, list | tuple):
        return [
            _redact_override(v, env_values) if isinstance(v, str) else _redact(v, env_values)
            for v in data
        ]
    if isinstance(data, str):
        return _redact_text(data, env_values)
    return data


def redact_secrets(data: Any) -> Any:
    """A copy of nested dicts/lists (or an OmegaConf config) with secrets replaced by ``***``:
    the values of secret-named keys, ``key=value`` strings with such keys (override lists,
    override_dirname), and the values of secret-named environment variables wherever they
    appear. Everything else is returned as it was (lists stay lists, tuples become lists)."""
    return _redact(data, _secret_env_values())


def redact_overrides(overrides: list[str]) -> list[str]:
    """Hydra overrides with the value of every secret-named key replaced: ``+x.api_key=abc`` →
    ``+x.api_key=***`` (also ``++``/``~`` forms; secret environment values anywhere)."""
    env_values = _secret_env_values()
    return [_redact_override(str(o), env_values) for o in overrides]


HYDRA_FILES = ("config.yaml", "overrides.yaml", "hydra.yaml")
MULTIRUN_FILE = "multirun.yaml"


def redact_yaml_file(path: str | os.PathLike) -> bool:
    """Redact a YAML file in place (atomically), only if something in it needs it; returns
    whether it was rewritten. A missing file is left alone."""
    path = Path(path)
    if not path.is_file():
        return False
    data = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    redacted = redact_secrets(data)
    if redacted == data:
        return False
    write_text_atomic(path, OmegaConf.to_yaml(OmegaConf.create(redacted)))
    return True


def redact_hydra_files(output_dir: str | os.PathLike, subdir: str | None = ".hydra") -> None:
    """Redact Hydra's own records of the run (``<output_dir>/<subdir>/{config,overrides,
    hydra}.yaml``, written before the task function runs) in place; a file is rewritten,
    atomically, only if something in it needed redacting. ``subdir`` is
    ``hydra.output_subdir`` (null: Hydra wrote nothing)."""
    if subdir is None:
        return
    for name in HYDRA_FILES:
        redact_yaml_file(Path(output_dir) / subdir / name)


class RedactSecrets(Callback):
    """Hydra callback (``hydra.callbacks``) that redacts secrets from the files Hydra writes:
    a job's ``.hydra/*.yaml`` as soon as they are written (``on_job_start`` runs right after,
    before the task function), and a sweep's ``multirun.yaml``. Works for every entry point
    that uses ``conf/hydra``.

    A secret reaches them through a legitimate override such as
    ``+hydra.job.env_set.WANDB_API_KEY=...`` (hydra.yaml records it twice).
    """

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        hydra_cfg = config.hydra
        redact_hydra_files(hydra_cfg.runtime.output_dir, hydra_cfg.output_subdir)
        if hydra_cfg.mode == RunMode.MULTIRUN:
            redact_yaml_file(Path(hydra_cfg.sweep.dir) / MULTIRUN_FILE)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        redact_yaml_file(Path(config.hydra.sweep.dir) / MULTIRUN_FILE)
