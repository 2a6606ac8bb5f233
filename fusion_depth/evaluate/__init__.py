"""``python -m fusion_depth.evaluate``: score a checkpoint, a folder of runs or an exported model
file without training (:mod:`.cli`)."""

from fusion_depth.evaluate.cli import main

__all__ = ["main"]
