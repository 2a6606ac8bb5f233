"""The checks of :func:`~fusion_depth.config.validate_config` that concern the dataset alone,
for ``prepare``, which reads nothing else (and its own ``prepare`` node); and the one-line form
both give OmegaConf's errors.

This module imports only the data layer, so ``python -m fusion_depth.prepare`` starts without
the models (timm) and the trainer (Lightning): with several workers, their seconds of import
were a fixed cost that no number of workers shortens.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

from fusion_depth.config.keys import check_known_keys
from fusion_depth.data.base import check_dataset
from fusion_depth.errors import ConfigError


class MissingValueError(MissingMandatoryValue, ConfigError):
    """A ``???`` value that must be set (still an OmegaConf MissingMandatoryValue)."""


@contextmanager
def one_line_errors() -> Iterator[None]:
    """OmegaConf's errors inside, as one-line errors naming the key: a ``???`` value as
    :class:`MissingValueError` (saying how to set it), any other as
    :class:`~fusion_depth.errors.ConfigError`."""
    try:
        yield
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


def validate_dataset_config(cfg: DictConfig) -> dict:
    """Fail before touching data, as :func:`~fusion_depth.config.validate_config` does, for the
    ``dataset`` node alone: missing values, the dataset's values
    (:func:`fusion_depth.data.base.check_dataset`, against ``fusion.mode``), and unknown keys of
    ``dataset`` and ``prepare`` (:func:`~fusion_depth.config.keys.check_known_keys`). The rest of
    the config is training's; ``train`` checks it.

    Returns:
        The resolved ``dataset`` node as plain data.

    Raises:
        MissingValueError: a ``???`` value under ``dataset`` (e.g. ``dataset.root``).
        ConfigError: a bad value or an unknown key, in one line naming it.
        MissingDependencyError: the dataset needs a package that is not installed.
    """
    with one_line_errors():
        OmegaConf.to_container(cfg.dataset, resolve=False, throw_on_missing=True)
        check_dataset(cfg.dataset, cfg.fusion.mode)
        check_known_keys(cfg, only=("dataset", "prepare"))
        return OmegaConf.to_container(cfg.dataset, resolve=True, throw_on_missing=True)
