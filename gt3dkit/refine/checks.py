"""Checks of a rig that need the annotations (``gt3d calib show`` with an input)."""

from __future__ import annotations

import numpy as np

from gt3dkit.fusion.preparation.prepare import prepare
from gt3dkit.types import Scene


def scene_warnings(scene: Scene) -> list[str]:
    """Warnings that need the annotations: where the people are, who sees them."""
    w = []
    pre = prepare(scene)
    x0, _, _ = pre.frame_state()
    centre = x0[:, pre.layout.center]
    centre = centre[np.isfinite(centre).all(axis=1)]
    rig = scene.rig
    for c in rig.cameras:
        if centre.size and not np.any((centre - c.center_world) @ (c.depth_sign * c.R[2]) > 0):
            w.append(f"camera {c.name}: no annotated object lies in front of it: its pose is wrong "
                     "(or it is mirrored)")
    if pre.kpt0 is not None:
        h = pre.kpt0 @ rig.up  # (R, J) heights
        lo, hi = np.nanmin(np.where(np.isfinite(h), h, np.inf), axis=1), \
            np.nanmax(np.where(np.isfinite(h), h, -np.inf), axis=1)
        ok = np.isfinite(lo) & np.isfinite(hi)
        if ok.any():
            feet, heads = float(np.median(lo[ok])), float(np.median(hi[ok]))
            if feet < -0.3:
                w.append(f"people's lowest joints sit {-feet:.2f} m below the floor (median): up, "
                         "the floor or the world's handedness is wrong")
            if heads > 3.0:
                w.append(f"people's highest joints are {heads:.2f} m above the floor (median): up or "
                         "the floor is wrong, or the scale")
    return w
