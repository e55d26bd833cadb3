"""What the refinement procedures share: settings, result, similarity alignment of rigs, pose
changes, the held-out folds, a rig's digest."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, replace

import numpy as np

from gt3dkit.calib.formats.native import cameras_doc
from gt3dkit.errors import InputError
from gt3dkit.rig import Camera, Rig
from gt3dkit.types import F64, JsonDict


@dataclass(frozen=True)
class RefineConfig:
    refine_intrinsics: bool = False  # focal length and distortion too (principal point never)
    refine_distortion: bool = True  # with refine_intrinsics: the distortion too (False: the focal only)
    folds: int = 2  # time blocks for the held-out check
    # Held-out reprojection must drop by this fraction in every fold. A refit always lowers it
    # somewhat by fitting the detector's or the box model's own biases, consistently over
    # time, so held-out frames do not expose it: from the true calibration of the real
    # MultiviewX subset, box refinement lowers held-out residuals by 10-35 % while moving the
    # cameras 2-3 cm / 0.1-0.2 degrees (and the ground error from 10.5 to 17 mm). A camera is
    # refined only where refining at least halves its held-out error: its input pose is then
    # clearly inconsistent with the others.
    min_gain: float = 0.5
    min_points: int = 15  # observations a camera needs in a fit
    loss_scale: float = 2.0  # Cauchy scale in units of the keypoint noise
    max_iterations: int = 100


@dataclass
class RefineResult:
    rig: Rig
    report: JsonDict = field(default_factory=dict)


# ----------------------------------------------------------------------------- geometry


def umeyama(src: F64, dst: F64) -> tuple[float, F64, F64]:
    """Similarity ``dst ~ s R src + t`` (least squares, Umeyama 1991) of (N, 3) points."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var) if var > 0 else 1.0
    return s, R, mu_d - s * R @ mu_s


def transform_rig(rig: Rig, s: float, Rw: F64, tw: F64) -> Rig:
    """The rig in the world ``X' = s Rw X + tw`` (cameras keep their images)."""
    cams = []
    for c in rig.cameras:
        R2 = c.R @ Rw.T
        cams.append(replace(c, R=R2, t=s * c.t - R2 @ tw))
    return Rig(tuple(cams), up=rig.up, frame_name=rig.frame_name)


def centre_similarity(rig: Rig, given: Rig) -> tuple[float, F64, F64] | None:
    """The similarity ``X_given = s R X + t`` that best maps ``rig``'s camera centres onto those of
    the cameras of the same names in ``given`` (:func:`umeyama`); None where they share fewer than
    three cameras or ``given`` has no poses to map onto (its centres within 1 cm of each other:
    intrinsics only)."""
    names = [n for n in rig.names if n in given.names]
    src = np.array([rig.cameras[rig.index(n)].center_world for n in names]).reshape(-1, 3)
    dst = np.array([given.cameras[given.index(n)].center_world for n in names]).reshape(-1, 3)
    if len(names) < 3 or np.ptp(dst, axis=0).max() < 0.01:
        return None
    return umeyama(src, dst)


def align_to(rig: Rig, ref: Rig) -> tuple[Rig, dict[str, float]]:
    """``rig`` moved onto ``ref`` by the similarity that best maps its camera centres."""
    src = np.array([c.center_world for c in rig.cameras])
    dst = np.array([c.center_world for c in ref.cameras])
    s, R, t = umeyama(src, dst)
    return transform_rig(rig, s, R, t), {"scale": s, "rotation_deg": _angle_deg(R)}


def _angle_deg(R: F64) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


def pose_change(a: Camera, b: Camera) -> tuple[float, float]:
    """(centre distance m, rotation angle degrees) between two poses of a camera."""
    return float(np.linalg.norm(a.center_world - b.center_world)), _angle_deg(a.R @ b.R.T)


#: A refined camera that turned by more than this (degrees), or moved by more than this share of
#: its distance to what it sees, was re-posed rather than refined (a refinement corrects a bump
#: or a drift: cm and tenths of a degree); the run says so (:func:`large_moves`).
LARGE_TURN_DEG = 5.0
LARGE_SHIFT_SHARE = 0.1


def large_moves(before: Rig, after: Rig, refined: np.ndarray, points_world: F64) -> list[str]:
    """What to say of the ``refined (C,)`` cameras that ``after`` moved by more than a refinement
    (:data:`LARGE_TURN_DEG`, :data:`LARGE_SHIFT_SHARE` of the median distance to
    ``points_world (P, 3)``): a small or far subject leaves a camera's pose free to swing about it
    while the held-out frames, of the same subject, agree with the swing."""
    out = []
    pts = points_world[np.all(np.isfinite(points_world), axis=1)]
    for c, (a, b) in enumerate(zip(before.cameras, after.cameras, strict=True)):
        if not refined[c]:
            continue
        moved_m, turned = pose_change(a, b)
        dist = float(np.median(np.linalg.norm(pts - a.center_world, axis=1))) if len(pts) else np.inf
        if turned > LARGE_TURN_DEG or moved_m > LARGE_SHIFT_SHARE * dist:
            out.append(f"camera {a.name}: refining turned it {turned:.1f} degrees and moved it "
                       f"{moved_m:.3g} m ({moved_m / dist:.0%} of its distance to what it sees): more "
                       "than a refinement. "
                       "A subject this small in its view may not fix its pose: check it against a board "
                       "calibration (gt3d calib board) before trusting it")
    return out


def check_enough(rig: Rig, n_obs: np.ndarray, cfg: RefineConfig, what: str) -> None:
    """:class:`InputError` when no camera has the observations a held-out check needs."""
    need = cfg.folds * cfg.min_points
    if not (n_obs >= need).any():
        worst = ", ".join(f"{c.name} {int(n)}" for c, n in zip(rig.cameras, n_obs, strict=True))
        raise InputError("calib refine", f"too few correspondences to refine any camera: {what} per "
                                         f"camera: {worst} (need {need})")


def time_blocks(times: np.ndarray, folds: int) -> np.ndarray:
    """Fold index (0..folds-1) of each time: contiguous blocks of the sorted unique frames."""
    u = np.unique(times)
    edges = u[np.linspace(0, len(u), folds + 1).astype(int)[1:-1]]
    return np.searchsorted(edges, times, side="right")


def rig_digest(rig: Rig) -> str:
    """SHA-256 of a rig's cameras.json document (what identifies a calibration in meta.json)."""
    return hashlib.sha256(json.dumps(cameras_doc(rig, None), sort_keys=True).encode()).hexdigest()
