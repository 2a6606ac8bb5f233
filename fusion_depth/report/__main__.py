"""``python -m fusion_depth.report``."""

import sys

from fusion_depth.report.cli import main

sys.exit(main())
