"""``python -m fusion_depth.train``."""

from fusion_depth.train.cli import main

main()
