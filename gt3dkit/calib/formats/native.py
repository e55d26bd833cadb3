"""Native ``cameras.json`` (read and write)::

    {"up": [0, 0, 1], "fps": 10, "skeleton": "coco19",
     "cameras": [{"name", "width", "height", "K": 3x3, "dist": [k1, k2, p1, p2, k3],
                  "R": 3x3, "t": [3]}]}

``R``, ``t`` are ``cam_from_world``, ``t`` in metres; ``fps``, ``skeleton`` optional.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.parse import json_of, load_json, parse_float, parse_int
from gt3dkit.rig import Camera, Rig
from gt3dkit.skeletons import SKELETONS
from gt3dkit.types import JsonDict, JsonValue

#: Frame rates accepted in cameras.json and by --fps: one frame per 17 minutes .. 1 MHz.
FPS_RANGE = (1e-3, 1e6)


def load_cameras(path: Path, raw: bytes | None = None) -> tuple[Rig, float | None, str | None]:
    """Rig, fps (None when the file gives none) and skeleton name of a ``cameras.json`` (``raw``:
    its bytes, read already)."""
    doc = load_json(path) if raw is None else json_of(path, raw)
    rig = rig_of_doc(doc, path)
    if doc.get("fps") is None:
        return rig, None, _skeleton_of(doc, path)
    fps = parse_float(f"{path}: fps", doc["fps"], "fps")
    if not FPS_RANGE[0] <= fps <= FPS_RANGE[1]:
        raise InputError(f"{path}: fps", f"must be in [{FPS_RANGE[0]:g}, {FPS_RANGE[1]:g}], got {fps:g}")
    return rig, fps, _skeleton_of(doc, path)


def rig_of_doc(doc: JsonValue, path: Path | str) -> Rig:
    """The rig of a ``cameras.json`` document (as :func:`cameras_doc` writes it); ``path``
    names it in errors."""
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), list):
        raise InputError(str(path), 'expected {"up": [...], "cameras": [...]}')
    cams = []
    for i, c in enumerate(doc["cameras"]):
        where = f"{path}: cameras[{i}]"
        try:
            where = f"{path}: camera {str(c['name'])!r}"
            cams.append(_camera(c))
        except (KeyError, TypeError, IndexError) as e:
            raise InputError(where, f"missing or malformed field {e}") from None
        except (ValueError, OverflowError) as e:
            raise InputError(where, str(e)) from None
    try:
        rig = Rig(tuple(cams), up=np.asarray(doc.get("up", [0, 0, 1]), dtype=np.float64),
                  frame_name=f"input world frame of {Path(path).name}")
    except (ValueError, TypeError, OverflowError) as e:
        raise InputError(f"{path}: {'up' if cams else 'cameras'}", str(e)) from None
    return rig


def _skeleton_of(doc: JsonDict, path: Path) -> str | None:
    skel = doc.get("skeleton")
    known = isinstance(skel, str) and (skel in SKELETONS or skel.endswith(".toml"))
    if skel is not None and not known:
        raise InputError(str(path), f"unknown skeleton {skel!r} (known: {', '.join(SKELETONS)}; or a "
                                    "skeleton file beside it, .toml)")
    return skel if skel is None else str(skel)


def cameras_doc(rig: Rig, fps: float | None, **extra: JsonValue) -> JsonDict:
    """The ``cameras.json`` document of a rig (what :func:`load_cameras` reads back)."""
    return {"up": rig.up.tolist(), "fps": fps, **extra,
            "cameras": [{"name": c.name, "width": c.width, "height": c.height, "K": c.K.tolist(),
                         "dist": c.coefficients.tolist(),
                         "R": c.R.tolist(), "t": c.t.tolist(),
                         **({"lens": c.lens} if c.lens != "pinhole" else {}),
                         **({"depth_sign": -1} if c.depth_sign < 0 else {})}
                        for c in rig.cameras]}


def _camera(c: JsonDict) -> Camera:
    size = [parse_int("", c[k], k, 1, 100_000) for k in ("width", "height")]
    sign = c.get("depth_sign", 1.0)
    if not isinstance(sign, int | float | str):
        raise TypeError("depth_sign")
    return Camera(name=str(c["name"]), width=size[0], height=size[1],
                  K=np.asarray(c["K"], dtype=np.float64),
                  dist=np.asarray(c.get("dist", [0, 0, 0, 0, 0]), dtype=np.float64),
                  R=np.asarray(c["R"], dtype=np.float64), t=np.asarray(c["t"], dtype=np.float64),
                  depth_sign=float(sign), lens=str(c.get("lens", "pinhole")))


def read(path: Path) -> Rig:
    """The rig of a ``cameras.json``."""
    return load_cameras(path)[0]


def write(rig: Rig, path: Path, fps: float | None = None, **extra: JsonValue) -> None:
    """Write ``rig`` as ``cameras.json`` (``fps`` and ``extra`` keys if given)."""
    import json

    doc = cameras_doc(rig, fps, **extra)
    if fps is None:
        doc.pop("fps")
    Path(path).write_text(json.dumps(doc, indent=1))
