"""``gt3d calib show``: a table per camera and warnings for what users get wrong.

Checks of a calibration alone (the floor is the plane through the world origin orthogonal
to ``up``, where calibration boards lie): a camera below the floor; a camera that looks away
from the floor point under the rig's middle while the others look at it; every camera
looking upwards (a mirrored or upside-down world: up is the wrong way); a focal length
outside 0.2 .. 20 image widths; a principal point outside the middle half of the image; a
rotation re-orthonormalised beyond float round-off. With the annotations
(``scene``): a camera in front of which no annotated object lies, and people whose lowest
joints sit well below the floor or whose highest are above 3 m (up or the floor is wrong).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gt3dkit.rig import Rig
from gt3dkit.types import F64


class CameraRow(NamedTuple):
    """One camera of ``gt3d calib show``'s table: its centre (m), height along up (m), optical axis
    in the world and how far it looks up (deg), intrinsics (px), lens and its coefficients, image
    size (px) and how far its rotation was from orthonormal."""

    camera: str
    centre_m: F64
    height_m: float
    view_dir: F64
    tilt_deg: float
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    lens: str
    dist: F64
    size: tuple[int, int]
    r_deviation: float


def camera_table(rig: Rig) -> list[CameraRow]:
    out = []
    for c in rig.cameras:
        look = c.depth_sign * c.R[2]  # optical axis in the world
        out.append(CameraRow(c.name, c.center_world, float(c.center_world @ rig.up), look,
                             float(np.degrees(np.arcsin(np.clip(look @ rig.up, -1, 1)))),
                             float(c.K[0, 0]), float(c.K[1, 1]), float(c.K[0, 2]), float(c.K[1, 2]),
                             c.lens, c.coefficients, (c.width, c.height), float(c.r_deviation)))
    return out


#: cameras further apart than this (the median over the pairs, in the calibration's units read as
#: metres) are more likely a rig calibrated in millimetres or centimetres
FAR_APART_M = 100.0


def far_apart(rig: Rig) -> str | None:
    """A warning where the cameras stand implausibly far apart for metres (None: they do not)."""
    centres = np.array([c.center_world for c in rig.cameras]).reshape(-1, 3)
    if len(centres) < 2:
        return None
    a, b = np.triu_indices(len(centres), 1)
    apart = float(np.median(np.linalg.norm(centres[a] - centres[b], axis=-1)))
    if not apart > FAR_APART_M:
        return None
    return (f"the cameras stand {apart:.0f} m apart (median over the pairs), the calibration read as "
            "metres: is it in millimetres or centimetres? (--calib-units mm|cm)")


def rig_warnings(rig: Rig) -> list[str]:
    w = []
    tab = camera_table(rig)
    below = [t.camera for t in tab if t.height_m < -0.05]
    if below:
        w.append(f"cameras below the floor (height along up < 0): {', '.join(below)}: up is the wrong "
                 "way, or the world is mirrored")
    if len(tab) > 1 and all(t.tilt_deg > 5 for t in tab):
        w.append("every camera looks upwards: up is the wrong way, or the world is mirrored")
    centres = np.array([c.center_world for c in rig.cameras])
    mid = centres.mean(0)
    mid = mid - (mid @ rig.up) * rig.up  # on the floor under the rig's middle
    away = [c.name for c in rig.cameras
            if (c.depth_sign * c.R[2]) @ (mid - c.center_world) < 0]
    if away and len(away) < len(rig.cameras):
        w.append(f"cameras looking away from the middle of the rig: {', '.join(away)}")
    for c in rig.cameras:
        size = max(c.width, c.height)
        if not 0.2 * size <= c.K[0, 0] <= 20 * size or not 0.2 * size <= c.K[1, 1] <= 20 * size:
            w.append(f"camera {c.name}: focal length {c.K[0, 0]:.0f}/{c.K[1, 1]:.0f} px is outside "
                     f"0.2 .. 20 image sizes ({size} px): a wrong unit or image size?")
        cx_ok = 0.25 * c.width <= c.K[0, 2] <= 0.75 * c.width
        if not (cx_ok and 0.25 * c.height <= c.K[1, 2] <= 0.75 * c.height):
            w.append(f"camera {c.name}: principal point ({c.K[0, 2]:.0f}, {c.K[1, 2]:.0f}) is outside the "
                     f"middle half of its {c.width}x{c.height} image: a wrong image size?")
        if c.valid_radius_px is not None:
            k = np.round(c.coefficients, 4).tolist()
            w.append(f"camera {c.name}: its {c.lens} lens model (dist {k}) turns back "
                     f"{c.valid_radius_px:.0f} px from the principal point, before the image's corners: "
                     "observations beyond that radius are left out")
        if c.r_deviation > 1e-6:
            w.append(f"camera {c.name}: R was not orthonormal (max |R R^T - I| = {c.r_deviation:.2g}); "
                     "re-orthonormalised")
    w += copied_cameras(rig)
    return w


def copied_cameras(rig: Rig) -> list[str]:
    """Cameras at the same place looking the same way (within 1 mm and 0.01 degree): one was
    copied over the other, since two cameras cannot share a lens."""
    out = []
    for i, a in enumerate(rig.cameras):
        for b in rig.cameras[i + 1:]:
            dc = float(np.linalg.norm(a.center_world - b.center_world))
            ang = float(np.degrees(np.arccos(np.clip((np.trace(a.R.T @ b.R) - 1) / 2, -1, 1))))
            if dc < 1e-3 and ang < 0.01:
                same_k = bool(np.allclose(a.K, b.K) and np.allclose(a.dist, b.dist))
                out.append(f"cameras {a.name} and {b.name} have the same pose{' and lens' if same_k else ''} "
                           f"({dc * 1e3:.2g} mm, {ang:.2g} degrees apart): one is a copy of the other; "
                           "check the calibration against the annotations (gt3d calib show INPUT) or "
                           "calibrate again (gt3d calib board)")
    return out
