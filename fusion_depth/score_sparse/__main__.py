"""``python -m fusion_depth.score_sparse``."""

from fusion_depth.score_sparse.cli import main

main()
