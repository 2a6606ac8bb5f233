"""The checks a config must pass before any work, together: :func:`validate_config`."""

from __future__ import annotations

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from fusion_depth.config.keys import check_known_keys
from fusion_depth.config.values import check_values
from fusion_depth.errors import ConfigError, MissingValueError


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
