"""Errors put into inputs for the QA and robustness checks (the tests and ``scripts/qa_targets.py``,
``scripts/robust_targets.py``): a box moved or a person moved in a WILDTRACK/MultiviewX-layout
folder as an annotator or a data pipeline would, and a detector's errors injected into a loaded
keypoint scene. Test helpers: they are not part of the package."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.geom.conics import ellipsoid_boxes
from gt3dkit.sim import Errors, detector_errors
from gt3dkit.types import Observations, Rig, Scene


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


def corrupt_keypoints(scene: Scene, errors: Errors, seed: int = 0
                      ) -> tuple[Scene, tuple[tuple[int, str, int, str, str, str], ...]]:
    """A loaded keypoint scene (e.g. real CMU Panoptic) with detector ``errors`` injected.

    The same errors as the skeleton simulator makes, on any :class:`Scene`'s keypoints; the
    returned scene carries confidences. Returns the scene and the injected errors.
    """
    obs = scene.obs
    if obs.n_joints == 0 or scene.skeleton is None:
        raise ValueError("corrupt_keypoints needs a keypoint scene with a named skeleton")
    keys, m_of = unique_rows(np.stack([obs.frame, obs.track_id], 1), return_inverse=True)
    m_of = m_of.reshape(-1)
    C, J = len(scene.rig.cameras), obs.n_joints
    uv = np.full((len(keys), C, J, 2), np.nan)
    uv[m_of, obs.cam] = obs.kpt_uv_px
    uv2, conf, injected = detector_errors(uv, scene.rig, scene.skeleton, keys[:, 0], keys[:, 1],
                                           np.asarray(scene.frames), errors,
                                           np.random.default_rng([seed, 1]))
    kpt = uv2[m_of, obs.cam]
    c = conf[m_of, obs.cam]
    keep = np.isfinite(kpt[..., 0]).any(axis=1)
    new = Observations(obs.frame, obs.cam, obs.track_id, obs.box_xyxy_px, kpt, obs.origin,
                       np.where(np.isfinite(kpt[..., 0]), c, np.nan)).select(keep)
    return dataclasses.replace(scene, obs=new), tuple(injected)
