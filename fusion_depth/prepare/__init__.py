"""``python -m fusion_depth.prepare``: build a dataset's prepared cache before training
(:mod:`.cli`; the cache itself: :mod:`fusion_depth.data.cache`)."""

from fusion_depth.prepare.cli import main

__all__ = ["main"]
