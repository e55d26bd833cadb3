"""The native layout: ``cameras.json`` + ``boxes.csv`` (and ``truth.csv`` if present).

``cameras.json``::

    {"up": [0, 0, 1], "fps": 10,
     "cameras": [{"name", "width", "height", "K": 3x3, "dist": [k1, k2, p1, p2, k3],
                  "R": 3x3, "t": [3]}]}

``R``, ``t`` are ``cam_from_world``, ``t`` in metres. ``fps`` is optional (default 10).

``boxes.csv``: header ``frame,camera,id,xmin,ymin,xmax,ymax``; pixels of the distorted image.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.io.datasets.common import RowBuilder, sha256
from gt3dkit.io.datasets.wildtrack import read_truth_csv
from gt3dkit.types import Camera, Rig, Scene

BOX_COLUMNS = ("frame", "camera", "id", "xmin", "ymin", "xmax", "ymax")
DEFAULT_FPS = 10.0


def load_cameras(path: Path) -> tuple[Rig, float]:
    try:
        doc = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(str(path), f"malformed JSON ({e})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), list):
        raise InputError(str(path), 'expected {"up": [...], "cameras": [...]}')
    cams = []
    for i, c in enumerate(doc["cameras"]):
        where = f"{path}: cameras[{i}]"
        try:
            where = f"{path}: camera {c['name']!r}"
            cams.append(_camera(c))
        except (KeyError, TypeError) as e:
            raise InputError(where, f"missing or malformed field {e}") from None
        except ValueError as e:
            raise InputError(where, str(e)) from None
    try:
        rig = Rig(tuple(cams), up=np.asarray(doc.get("up", [0, 0, 1]), dtype=np.float64),
                  frame_name=f"input world frame of {Path(path).name}")
    except (ValueError, TypeError) as e:
        raise InputError(str(path), str(e)) from None
    fps = float(doc.get("fps", DEFAULT_FPS))
    if not fps > 0:
        raise InputError(str(path), f"fps must be positive, got {fps}")
    return rig, fps


def _camera(c: dict[str, Any]) -> Camera:
    return Camera(name=str(c["name"]), width=int(c["width"]), height=int(c["height"]),
                  K=np.asarray(c["K"], dtype=np.float64),
                  dist=np.asarray(c.get("dist", [0, 0, 0, 0, 0]), dtype=np.float64),
                  R=np.asarray(c["R"], dtype=np.float64), t=np.asarray(c["t"], dtype=np.float64))


def read_csv_rows(path: Path, columns: tuple[str, ...]) -> list[tuple[int, dict[str, str]]]:
    """Rows of a CSV with the given leading header; (line number, row)."""
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None or tuple(h.strip() for h in header[: len(columns)]) != columns:
                raise InputError(str(path), f"expected header {','.join(columns)}, got {header}")
            out = []
            for line, row in enumerate(reader, start=2):
                if not row or all(not x.strip() for x in row):
                    continue
                if len(row) < len(columns):
                    raise InputError(f"{path}: line {line}",
                                     f"expected {len(columns)} fields, got {len(row)}")
                out.append((line, dict(zip(columns, (x.strip() for x in row), strict=False))))
            return out
    except UnicodeDecodeError as e:
        raise InputError(str(path), f"not a text CSV file ({e})") from None


def camera_index(rig: Rig, name: str, where: str) -> int:
    try:
        return rig.index(name)
    except KeyError:
        raise InputError(where, f"unknown camera {name!r} (cameras.json has {rig.names})") from None


def load(root: Path, n_joints: int = 0) -> Scene:
    root = Path(root)
    files: dict[str, str] = {}
    cam_path = root / "cameras.json"
    rig, fps = load_cameras(cam_path)
    files["cameras.json"] = sha256(cam_path)
    rb = RowBuilder(n_joints=n_joints)
    box_path = root / "boxes.csv"
    if box_path.exists():
        files["boxes.csv"] = sha256(box_path)
        for line, r in read_csv_rows(box_path, BOX_COLUMNS):
            where = f"{box_path}: line {line}"
            try:
                frame, tid = int(r["frame"]), int(r["id"])
                box = [float(r[k]) for k in ("xmin", "ymin", "xmax", "ymax")]
            except ValueError as e:
                raise InputError(where, f"malformed value ({e})") from None
            cam = camera_index(rig, r["camera"], where)
            rb.add_box(frame, cam, tid, box, where)
    obs = rb.build()
    if len(obs) == 0:
        raise InputError(str(root), "no annotations (boxes.csv is missing or empty)")
    truth = read_truth_csv(root / "truth.csv", files, root) if (root / "truth.csv").exists() else None
    frames = np.unique(obs.frame)
    return Scene(rig=rig, obs=obs, layout="native", fps=fps, frames=frames, truth=truth,
                 files=files, root=str(root))
