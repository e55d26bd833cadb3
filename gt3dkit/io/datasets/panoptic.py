"""CMU Panoptic: ``calibration_<seq>.json`` + ``hdPose3d_stage1_coco19/body3DScene_<frame>.json``.

Panoptic has no 2D annotations, so this loader follows the paper's protocol: the 3D
joints (confidence >= ``min_conf``) are projected into the HD cameras with lens
distortion; joints behind a camera or outside its image are dropped. The estimators
see only those 2D points; the 3D joints are the truth.

Units: the files are in centimetres; everything here is metres. World +y points
down (gravity), so ``up = [0, -1, 0]``. Frame numbers are HD frames at 29.97 fps.
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.calib.formats.panoptic import find_calibration, load_rig
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import project_points
from gt3dkit.parse import json_field, parse_frame, parse_int, read_hashed
from gt3dkit.skeletons import SKELETONS
from gt3dkit.types import (
    MAX_WORLD_M,
    GroundTruth,
    JsonValue,
    Observations,
    Origins,
    Rig,
    Scene,
    SkeletonScene,
)

CM = 0.01
FPS = 29.97
POSE_DIR = "hdPose3d_stage1_coco19"


def load_with(root: Path, options: Mapping[str, JsonValue]) -> Scene:
    """:func:`load` with its keyword ``options`` as a scene's ``load_options`` keep them (JSON:
    ``cameras`` a list of names, the others numbers)."""
    unknown = sorted(set(options) - {"cameras", "noise_px", "seed", "min_conf"})
    if unknown:
        raise InputError(str(root), f"unknown panoptic options {unknown}")
    cams = options.get("cameras")
    if cams is not None and (isinstance(cams, str) or not isinstance(cams, Sequence)):
        raise InputError("--cameras", f"expected a list of camera names, got {cams!r}")

    def number(key: str, default: float) -> float:
        v = options.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int | float):
            raise InputError(key, f"must be a number, got {v!r}")
        return float(v)

    return load(root, None if cams is None else [str(c) for c in cams], number("noise_px", 0.0),
                parse_int("seed", options.get("seed", 0), "seed"), number("min_conf", 0.1))


def load(root: Path, cameras: list[str] | None = None, noise_px: float = 0.0, seed: int = 0,
         min_conf: float = 0.1) -> Scene:
    """Load a Panoptic sequence folder and make its 2D observations (see module doc).

    Parameters
    ----------
    cameras : HD camera names to use (default: all HD cameras)
    noise_px : standard deviation of Gaussian noise added to every 2D point
    seed : seed of that noise
    min_conf : joints below this confidence are neither observed nor scored
    """
    root = Path(root)
    if not (np.isfinite(noise_px) and noise_px >= 0):
        raise InputError("noise_px", f"must be >= 0 and finite, got {noise_px}")
    calib = find_calibration(root)
    if calib is None:
        raise InputError(str(root), "no calibration_<seq>.json")
    raw, digest = read_hashed(calib)  # read once: hashed, then parsed
    files = {calib.name: digest}
    rig = load_rig(calib, cameras, raw)
    if cameras is not None and len(rig.cameras) < 2:
        raise InputError("--cameras", f"{', '.join(c.name for c in rig.cameras)}: one camera; keypoints need "
                                      "two or more to place a joint (name at least two HD cameras)")
    pose_files = sorted((root / POSE_DIR).glob("body3DScene_*.json"))
    if not pose_files:
        raise InputError(str(root / POSE_DIR), "no body3DScene_<frame>.json files")
    skel = SKELETONS["coco19"]
    J = skel.n_joints
    t_frame, t_id, t_joints = [], [], []
    for p in pose_files:
        m = re.fullmatch(r"body3DScene_(\d+)\.json", p.name)
        if m is None:
            raise InputError(str(p), "file name is not body3DScene_<frame>.json")
        raw, digest = read_hashed(p)  # the file opened once: its bytes parsed and hashed
        bodies = json_field(p, raw, "bodies", "[...]")
        if not isinstance(bodies, list):
            raise InputError(f"{p}: bodies", "expected a list of bodies")
        frame = parse_frame(str(p), m.group(1))
        files[f"{POSE_DIR}/{p.name}"] = digest
        for i, b in enumerate(bodies):
            if not (isinstance(b, dict) and "id" in b and "joints19" in b):
                raise InputError(f"{p}: bodies[{i}]", "expected {id, joints19}")
            bid = parse_int(f"{p}: bodies[{i}]", b["id"], "id")
            try:
                j = np.asarray(b["joints19"], dtype=np.float64)
            except (TypeError, ValueError, OverflowError):
                raise InputError(f"{p}: body {bid}", "joints19 must be a list of numbers") from None
            if j.shape != (4 * J,):
                raise InputError(f"{p}: body {bid}", f"joints19 has {j.size} values, expected {4 * J}")
            if not np.all(np.isfinite(j)):
                raise InputError(f"{p}: body {bid}", "joints19 has non-finite values")
            if np.abs(j).max() > MAX_WORLD_M / CM:
                raise InputError(f"{p}: body {bid}", f"joints19 has a value beyond {MAX_WORLD_M / CM:g} cm")
            j = j.reshape(J, 4)
            X = np.where((j[:, 3] >= min_conf)[:, None], j[:, :3] * CM, np.nan)
            t_frame.append(frame)
            t_id.append(bid)
            t_joints.append(X)
    frames = np.array(t_frame, dtype=np.int64)
    ids = np.array(t_id, dtype=np.int64)
    X = np.array(t_joints).reshape(-1, J, 3)
    if not np.isfinite(X).any():
        raise InputError(str(root / POSE_DIR), f"joints19: every joint's confidence (each fourth value) is "
                                               f"below {min_conf:g}, the least a joint is kept with "
                                               f"({len(ids)} bodies in {len(pose_files)} files): no joint "
                                               "to reconstruct")
    pairs, counts = unique_rows(np.stack([frames, ids], 1), return_counts=True)
    if (counts > 1).any():
        bad = pairs[counts > 1][0]
        raise InputError(f"{root / POSE_DIR}/body3DScene_{bad[0]:08d}.json",
                         f"body {bad[1]} appears twice")
    truth = GroundTruth(frame=frames, track_id=ids, center_world=np.full((len(ids), 3), np.nan),
                        semi_axes=np.full((len(ids), 3), np.nan), kpt_world=X,
                        source="Panoptic hdPose3d_stage1_coco19 joints")
    obs = project_observations(rig, frames, ids, X, noise_px, seed,
                               origin=[f"body3DScene_{f:08d}.json: body {i}"
                                       for f, i in zip(frames, ids, strict=True)])
    return Scene(rig=rig, obs=obs, layout="panoptic", fps=FPS,
                 frames=np.unique(frames), truth=truth, skeleton="coco19", files=files,
                 root=str(root))


def project_observations(rig: Rig, frames: np.ndarray, ids: np.ndarray, X_world: np.ndarray,
                         noise_px: float, seed: int, origin: list[str]) -> Observations:
    """2D keypoints of 3D joints ``(M, J, 3)`` in every camera; drops behind/outside points.

    Returns one observation row per (pose, camera) that sees at least one joint.
    """
    M, J, _ = X_world.shape
    uv, depth = project_points(X_world, rig.K, rig.dist, rig.R, rig.t, rig.depth_sign)  # (M,J,C,2)
    if noise_px > 0:
        uv = uv + np.random.default_rng(seed).normal(scale=noise_px, size=uv.shape)
    wh = rig.wh
    inside = (depth > 0) & np.all((uv >= 0) & (uv <= wh - 1), axis=-1)
    uv = np.where(inside[..., None], uv, np.nan)
    uv = np.moveaxis(uv, 2, 1)  # (M, C, J, 2)
    keep = np.isfinite(uv[..., 0]).any(axis=2)  # (M, C)
    m_i, c_i = np.nonzero(keep)
    return Observations(frame=frames[m_i], cam=c_i, track_id=ids[m_i],
                        box_xyxy_px=np.full((len(m_i), 4), np.nan), kpt_uv_px=uv[m_i, c_i],
                        origin=Origins.of(f"{origin[m]}, camera {rig.cameras[c].name}"
                                          for m, c in zip(m_i, c_i, strict=True)))


def write(sim: SkeletonScene, tmp: Path) -> None:
    """A simulated coco19 skeleton scene as a CMU Panoptic sequence in ``tmp``
    (``calibration_sim.json`` in cm + ``body3DScene`` files; :func:`load` makes the 2D points,
    so ``uv``, noise and missing points are not written)."""
    if sim.skeleton != "coco19":
        raise ValueError("the Panoptic layout holds coco19 skeletons")
    cams = [{"name": c.name, "type": "hd", "resolution": [c.width, c.height],
             "panel": 0, "node": i, "K": c.K.tolist(), "distCoef": c.dist.tolist(),
             "R": c.R.tolist(), "t": (c.t[:, None] * 100).tolist()}
            for i, c in enumerate(sim.rig.cameras)]
    cams.append({"name": "01_01", "type": "vga", "resolution": [640, 480], "panel": 1,
                 "node": 1, "K": np.eye(3).tolist(), "distCoef": [0] * 5,
                 "R": np.eye(3).tolist(), "t": [[0], [0], [300]]})
    (tmp / "calibration_sim.json").write_text(json.dumps(
        {"calibDataSource": "gt3dkit simulate", "cameras": cams}))
    d = tmp / "hdPose3d_stage1_coco19"
    d.mkdir()
    for f in sim.frames:
        bodies = []
        for a in np.flatnonzero(sim.truth_frame == f):
            j = np.concatenate([sim.kpt_world[a] * 100, np.ones((len(sim.kpt_world[a]), 1))],
                               axis=1)
            bodies.append({"id": int(sim.truth_id[a]), "joints19": j.reshape(-1).round(4).tolist()})
        (d / f"body3DScene_{int(f):08d}.json").write_text(json.dumps(
            {"version": 0.7, "univTime": float(f), "fpsType": "hd_29_97", "bodies": bodies}))
