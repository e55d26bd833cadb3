"""The package version (one place: the package, its outputs' meta.json and pyproject agree)."""

__version__ = "0.1.0"
