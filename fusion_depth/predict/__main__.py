"""``python -m fusion_depth.predict``."""

from fusion_depth.predict.cli import main

main()
