"""``python -m fusion_depth.evaluate``."""

from fusion_depth.evaluate.cli import main

main()
