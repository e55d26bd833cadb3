"""gt3dkit: 3D ground truth (ellipsoids) from multi-camera 2D annotations.

Library use::

    from gt3dkit import load_scene, reconstruct
    scene = load_scene("path/to/input")          # layout detected
    tracks = reconstruct(scene)                   # UKF + RTS smoother
    tracks.center_world, tracks.semi_axes         # (M, 3) metres, input's world frame

The names below load :mod:`gt3dkit.api` when first used (PEP 562, as SciPy's and scikit-image's
lazy submodules do), so that importing a light part of the package (:mod:`gt3dkit.cli` before
it connects to a Dask scheduler, :mod:`gt3dkit.version` on a worker) loads no compiled kernels.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from gt3dkit.errors import InputError
from gt3dkit.version import __version__

if TYPE_CHECKING:
    from gt3dkit.api import ESTIMATORS, load_scene, make_estimator, reconstruct

__all__ = ["ESTIMATORS", "InputError", "load_scene", "make_estimator", "reconstruct",
           "__version__"]

#: The names :mod:`gt3dkit.api` gives the package, loaded on first use.
_FROM_API = ("ESTIMATORS", "load_scene", "make_estimator", "reconstruct")


def __getattr__(name: str) -> Any:
    if name in _FROM_API:
        return getattr(importlib.import_module("gt3dkit.api"), name)
    raise AttributeError(f"module 'gt3dkit' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
