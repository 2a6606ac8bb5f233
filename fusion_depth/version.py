"""The package version: ``fusion_depth.__version__`` and the wheel's (``pyproject.toml`` reads it
from here). Changes per version: ``docs/changelog.md``."""

__version__ = "0.2.0"
