"""``python -m fusion_depth.predict``: depth maps for new images or a dataset split
(:mod:`.cli`; the files it reads and writes: :mod:`.files`)."""

from fusion_depth.predict.cli import main

__all__ = ["main"]
