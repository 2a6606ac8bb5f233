"""``python -m fusion_depth.train``: train one configuration (or a sweep with ``-m``), test its
best checkpoint, write ``metrics.json`` and ``per_image.csv`` (:mod:`.cli`; the run itself:
:mod:`.fit`)."""

from fusion_depth.train.cli import main

__all__ = ["main"]
