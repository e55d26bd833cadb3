"""The package version (one place: the package, its outputs' meta.json and pyproject agree)."""

__version__ = "0.1.0"


def installed() -> str:
    """The version of gt3dkit the process running this has: on each Dask worker, the check that
    it runs the client's (:func:`gt3dkit.windows.cluster.connect_scheduler`; a worker without
    gt3dkit fails to load this function). This module imports nothing, so the check loads nothing
    heavy on a worker that is busy loading its kernels."""
    return __version__
