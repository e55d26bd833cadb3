"""CMU Panoptic ``calibration_<seq>.json``: HD cameras (``type: hd``), centimetres, y down.
Read only (``K``, ``distCoef``, ``R``, ``t`` in cm, ``resolution``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.parse import json_field, read_json_field
from gt3dkit.rig import Camera, Rig

CM = 0.01


def find_calibration(root: Path) -> Path | None:
    c = sorted(Path(root).glob("calibration_*.json"))
    return c[0] if c else None


def load_rig(path: Path, cameras: list[str] | None = None, raw: bytes | None = None) -> Rig:
    """The HD cameras (``cameras``: those named only) of a Panoptic ``calibration_<seq>.json``
    (``raw``: its bytes, read already)."""
    cams_doc = (read_json_field(path, "cameras", "[...]") if raw is None else
                json_field(path, raw, "cameras", "[...]"))
    cams = []
    for i, c in enumerate(cams_doc):
        where = f"{path}: cameras[{i}]"
        try:
            if c.get("type") != "hd":
                continue
            name = str(c["name"])
            if cameras is not None and name not in cameras:
                continue
            w, h = (int(v) for v in c["resolution"])
            cams.append(Camera(name=name, width=w, height=h, K=np.asarray(c["K"], float),
                               dist=np.asarray(c["distCoef"], float).reshape(-1),
                               R=np.asarray(c["R"], float),
                               t=np.asarray(c["t"], float).reshape(3) * CM))
        except (KeyError, TypeError, ValueError, AttributeError, IndexError, OverflowError) as e:
            raise InputError(f"{where} ({c.get('name', '?') if isinstance(c, dict) else '?'})",
                             f"malformed camera ({e})") from None
    if not cams:
        want = f" among {cameras}" if cameras else ""
        raise InputError(str(path), f"no HD cameras{want} (type 'hd')")
    if cameras is not None:
        missing = sorted(set(cameras) - {c.name for c in cams})
        if missing:
            raise InputError(str(path), f"no HD camera named {missing}")
    try:
        return Rig(tuple(cams), up=np.array([0.0, -1.0, 0.0]),
                   frame_name="CMU Panoptic world (y down), centimetres converted to metres")
    except ValueError as e:
        raise InputError(str(path), str(e)) from None




def read(path: Path) -> Rig:
    """The HD cameras of a ``calibration_<seq>.json`` (or of the folder holding one)."""
    path = Path(path)
    f = find_calibration(path) if path.is_dir() else path
    if f is None:
        raise InputError(str(path), "no calibration_<seq>.json")
    return load_rig(f)
