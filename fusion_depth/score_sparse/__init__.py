"""``python -m fusion_depth.score_sparse``: a split's sparse input scored as if it were the
prediction (:mod:`.cli`)."""

from fusion_depth.score_sparse.cli import main

__all__ = ["main"]
