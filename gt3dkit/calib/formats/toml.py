"""Anipose / Pose2Sim calibration TOML (read and write)::

    [cam_0]
    name = "cam0"
    size = [1920, 1080]
    matrix = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]
    distortions = [k1, k2, p1, p2, k3]   # 4 or 5 (OpenCV order); a fisheye's k1 k2 k3 k4
    rotation = [rx, ry, rz]              # Rodrigues vector, cam_from_world
    translation = [tx, ty, tz]           # cam_from_world, metres (Pose2Sim; Anipose: board units)
    fisheye = false                      # true: OpenCV's fisheye model (aniposelib's FisheyeCamera)

    [metadata]
    ...

Read with the standard library's ``tomllib``; written by hand (the format is a handful of
arrays; a TOML writer would be a dependency for that). A fisheye camera (``fisheye = true``) is
read and written as aniposelib's ``FisheyeCamera`` is: four ``distortions``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.parse import load_toml
from gt3dkit.rig import Camera, Rig

# cv2 is imported in the functions that use it: 26 MB and 30 ms that a run whose calibration is
# not Pose2Sim's never needs

_KEYS = ("size", "matrix", "distortions", "rotation", "translation")


def read(path: Path) -> Rig:
    import cv2
    path = Path(path)
    doc = load_toml(path)
    cams = []
    for key, c in doc.items():
        if key == "metadata" or not isinstance(c, dict):
            continue
        where = f"{path}: [{key}]"
        missing = [k for k in _KEYS if k not in c]
        if missing:
            raise InputError(where, f"missing {', '.join(missing)}")
        fisheye = c.get("fisheye", False)
        if not isinstance(fisheye, bool):
            raise InputError(where, f"fisheye must be true or false, not {fisheye!r}")
        try:
            w, h = (int(v) for v in c["size"])
            rvec = np.asarray(c["rotation"], dtype=np.float64).reshape(3, 1)
            if not np.all(np.isfinite(rvec)):
                raise ValueError("rotation has non-finite values")
            R, _ = cv2.Rodrigues(rvec)
            cams.append(Camera(name=str(c.get("name", key)), width=w, height=h,
                               K=np.asarray(c["matrix"], dtype=np.float64),
                               dist=np.asarray(c["distortions"], dtype=np.float64).reshape(-1),
                               R=np.asarray(R, dtype=np.float64),
                               t=np.asarray(c["translation"], dtype=np.float64).reshape(-1),
                               lens="fisheye" if fisheye else "pinhole"))
        except (TypeError, ValueError, OverflowError) as e:
            raise InputError(where, f"malformed camera ({e})") from None
    if not cams:
        raise InputError(str(path), "no [cam_N] tables")
    try:
        return Rig(tuple(cams), frame_name=f"world frame of {path.name}")
    except ValueError as e:
        raise InputError(str(path), str(e)) from None


def _num(v: float) -> str:
    if not math.isfinite(v):
        raise ValueError(f"cannot write {v} to TOML")
    return repr(float(v))


def _arr(a: np.ndarray) -> str:
    a = np.asarray(a, dtype=np.float64)
    if a.ndim == 1:
        return "[ " + ", ".join(_num(v) for v in a) + ",]"
    return "[ " + ", ".join(_arr(r) for r in a) + ",]"


def write(rig: Rig, path: Path) -> None:
    """``rig`` as an Anipose/Pose2Sim TOML (translation in metres)."""
    import cv2
    lines = []
    for i, c in enumerate(rig.cameras):
        rvec = cv2.Rodrigues(c.R)[0].reshape(3)
        fisheye = c.lens == "fisheye"
        lines += [f"[cam_{i}]", f'name = "{c.name}"', f"size = [ {c.width}, {c.height},]",
                  f"matrix = {_arr(c.K)}", f"distortions = {_arr(c.coefficients)}",
                  f"rotation = {_arr(rvec)}", f"translation = {_arr(c.t)}",
                  f"fisheye = {'true' if fisheye else 'false'}", ""]
    lines += ["[metadata]", "adjusted = false", "error = 0.0", 'units = "m"', 'written_by = "gt3dkit"', ""]
    Path(path).write_text("\n".join(lines))
