"""``python -m fusion_depth.export``."""

from fusion_depth.export.cli import main

main()
