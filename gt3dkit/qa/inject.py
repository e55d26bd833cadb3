"""Errors for QA checks, put into a WILDTRACK/MultiviewX-layout folder as an annotator or a
data pipeline would make them (used by ``scripts/qa_targets.py`` and the tests)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from gt3dkit.geom.conics import ellipsoid_boxes
from gt3dkit.types import Rig


def shift_box(root: Path, frame_file: int, person: int, dx_px: float) -> tuple[int, int, int]:
    """Move one view's box of the ``person``-th entry of the ``frame_file``-th annotation file
    by ``dx_px`` horizontally. Returns (frame, viewNum, personID)."""
    f = sorted((Path(root) / "annotations_positions").glob("*.json"))[frame_file]
    people = json.loads(f.read_text())
    p = people[person]
    v = next(v for v in p["views"] if v["xmin"] >= 0)
    v["xmin"] += dx_px
    v["xmax"] += dx_px
    f.write_text(json.dumps(people))
    return int(f.stem), int(v["viewNum"]), int(p["personID"])


def move_person(root: Path, rig: Rig, frame_file: int, person: int, centre_m: np.ndarray,
                semi_axes_m: np.ndarray) -> tuple[int, int]:
    """Replace every view's box of one person at one frame by the boxes of an ellipsoid
    elsewhere (a mis-keyed id). Returns (frame, personID)."""
    f = sorted((Path(root) / "annotations_positions").glob("*.json"))[frame_file]
    people = json.loads(f.read_text())
    q = people[person]
    box, _ = ellipsoid_boxes(np.asarray(centre_m)[None], np.asarray(semi_axes_m)[None], rig.world_from_body(),
                             rig.K, rig.dist, rig.R, rig.t, rig.depth_sign)
    for v in q["views"]:
        if v["xmin"] >= 0:
            b = box[0, v["viewNum"]]
            v.update(xmin=float(b[0]), ymin=float(b[1]), xmax=float(b[2]), ymax=float(b[3]))
    f.write_text(json.dumps(people))
    return int(f.stem), int(q["personID"])
