"""gt3dkit: 3D ground truth (ellipsoids) from multi-camera 2D annotations.

Library use::

    from gt3dkit import load_scene, reconstruct
    scene = load_scene("path/to/input")          # layout detected
    tracks = reconstruct(scene)                   # UKF + RTS smoother
    tracks.center_world, tracks.semi_axes         # (M, 3) metres, input's world frame
"""

from __future__ import annotations

from gt3dkit.api import ESTIMATORS, load_scene, make_estimator, reconstruct
from gt3dkit.errors import InputError
from gt3dkit.version import __version__

__all__ = ["ESTIMATORS", "InputError", "load_scene", "make_estimator", "reconstruct",
           "__version__"]
