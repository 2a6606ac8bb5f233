"""What entry points print: third-party notices users cannot act on are silenced here, once."""

from __future__ import annotations

import logging
import warnings


class _DropTips(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.getMessage()).startswith("💡 Tip")


def quiet_known_noise() -> None:
    """Hide Lightning's product tips and two warnings about its own internals (idempotent)."""
    # The augmentation hook is meant to live on the module, and the pytree notice is Lightning's
    # own use of a deprecated torch API.
    warnings.filterwarnings("ignore", message=".*overridden `on_after_batch_transfer`.*")
    warnings.filterwarnings(
        "ignore", message=".*isinstance\\(treespec, LeafSpec\\)` is deprecated.*"
    )
    logger = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    if not any(isinstance(f, _DropTips) for f in logger.filters):
        logger.addFilter(_DropTips())
