"""``python -m fusion_depth.prepare``."""

from fusion_depth.prepare.cli import main

main()
