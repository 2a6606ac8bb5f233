"""``python -m fusion_depth.bench``: how fast a configuration trains and infers here
(:mod:`.cli`; the measuring stages: :mod:`.stages`)."""

from fusion_depth.bench.cli import main

__all__ = ["main"]
