"""The package version (also ``fusion_depth.__version__``)."""

__version__ = "0.1.0"
