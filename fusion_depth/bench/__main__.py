"""``python -m fusion_depth.bench``."""

import sys

from fusion_depth.bench.cli import main

sys.exit(main())
