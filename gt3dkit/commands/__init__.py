"""The commands of ``gt3d`` (one module each, or a few related ones together); :mod:`gt3dkit.cli` only
parses the command line and calls them."""
