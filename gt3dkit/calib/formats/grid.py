"""WILDTRACK / MultiviewX calibrations: ``calibrations/<intrinsic dir>/intr_<CAM>.xml`` (K,
distortion) and ``calibrations/extrinsic/extr_<CAM>.xml`` (rvec, tvec in the layout's units),
read and written."""

from __future__ import annotations

from pathlib import Path

import cv2

from gt3dkit.calib.model import Rig
from gt3dkit.errors import InputError
from gt3dkit.io.datasets.wildtrack import LAYOUTS, GridLayout, load_camera


def layout_of(root: Path) -> GridLayout | None:
    for g in LAYOUTS.values():
        if (Path(root) / "calibrations" / g.intrinsic_dir).is_dir():
            return g
    return None


def read(root: Path, g: GridLayout | None = None) -> Rig:
    root = Path(root)
    g = g or layout_of(root)
    if g is None:
        raise InputError(str(root), "no calibrations/intrinsic_zero or calibrations/intrinsic")
    files: dict[str, str] = {}
    cams = [c for c in (load_camera(root, g, n, files) for n in g.cameras) if c is not None]
    if not cams:
        raise InputError(str(root / "calibrations"), "no camera calibrations found")
    return Rig(tuple(cams), frame_name=f"{g.name} world (x, y on the ground, z up)")


def write(rig: Rig, root: Path, g: GridLayout) -> None:
    """The calibration files of ``rig`` in ``g``'s layout under ``root``."""
    intr = Path(root) / "calibrations" / g.intrinsic_dir
    extr = Path(root) / "calibrations" / "extrinsic"
    intr.mkdir(parents=True, exist_ok=True)
    extr.mkdir(parents=True, exist_ok=True)
    for c in rig.cameras:
        fs = cv2.FileStorage(str(intr / f"intr_{c.name}.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", c.K)
        fs.write("distortion_coefficients", c.dist.reshape(1, 5))
        fs.release()
        rvec, _ = cv2.Rodrigues(c.R)
        fs = cv2.FileStorage(str(extr / f"extr_{c.name}.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("rvec", rvec.reshape(3, 1))
        fs.write("tvec", (c.t / g.tvec_to_m).reshape(3, 1))
        fs.release()
