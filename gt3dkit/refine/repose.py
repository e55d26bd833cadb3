"""A camera whose calibration fits no other camera's (a copied or outdated one: the association
leaves every one of its detections out), posed again on the people the other cameras place.

Its detections are paired with the people estimated in the same frames (every detection with
every person: the wrong pairs are outliers), joint by joint; OpenCV's PnP in RANSAC (EPnP on the
camera's own intrinsics, then Levenberg-Marquardt on the inliers) poses it, for each focal length
a golden-section search tries (a copied camera has another camera's lens: anipose's shared
session's ``side`` holds ``top``'s 965 px where a board finds 769). The focal length kept is the
one of least truncated reprojection cost over every pair (MSAC); the principal point and the distortion stay
the calibration's. ``--refine-calib`` then adjusts the whole rig (:mod:`gt3dkit.refine.keypoints`).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.rig import Camera, Rig
from gt3dkit.types import F64, JsonDict, Observations, TrackSet

#: RANSAC's inlier distance (px) and the least inliers that pose a camera
INLIER_PX = 8.0
MIN_INLIERS = 30
#: the focal lengths searched, as a share of the calibration's
FOCAL_RANGE = (0.5, 2.0)


def correspondences(obs: Observations, cam: int, tracks: TrackSet) -> tuple[F64, F64]:
    """``(N, 3)`` world points (m) and ``(N, 2)`` pixels of camera ``cam``: each of its keypoint
    detections against every person estimated in its frame, joint by joint."""
    X: list[F64] = []
    uv: list[F64] = []
    mine = np.flatnonzero(obs.cam == cam)
    for f in np.unique(obs.frame[mine]):
        people = tracks.kpt_world[tracks.frame == f]  # (P, J, 3)
        for r in mine[obs.frame[mine] == f]:
            for p in people:
                ok = np.isfinite(p[:, 0]) & np.isfinite(obs.kpt_uv_px[r, :, 0])
                X.append(p[ok])
                uv.append(obs.kpt_uv_px[r][ok])
    if not X:
        return np.zeros((0, 3)), np.zeros((0, 2))
    return np.concatenate(X), np.concatenate(uv)


def _posed(cam: Camera, f_px: float, X: F64, uv: F64) -> tuple[float, F64, F64, np.ndarray]:
    """The truncated cost (MSAC: the mean over every pair of its squared reprojection error,
    capped at :data:`INLIER_PX`), ``R (3, 3)``, ``t (3,)`` and the inliers of ``cam`` posed with
    focal length ``f_px`` (inf where PnP finds too few inliers)."""
    import cv2

    K = cam.K.copy()
    K[0, 0], K[1, 1] = f_px, f_px * cam.K[1, 1] / cam.K[0, 0]
    try:  # a focal length whose lens model folds inside the image is no camera
        dataclasses.replace(cam, K=K)
    except ValueError:
        return math.inf, np.eye(3), np.zeros(3), np.zeros(0, np.int64)
    dist = cam.coefficients
    obj, img = X.astype(np.float64), uv.astype(np.float64)
    cv2.setRNGSeed(0)  # RANSAC's draws: the same pose every run
    ok, rv, tv, inl = cv2.solvePnPRansac(obj, img, K, dist, iterationsCount=1000, reprojectionError=INLIER_PX,
                                         flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None or len(inl) < MIN_INLIERS:
        return math.inf, np.eye(3), np.zeros(3), np.zeros(0, np.int64)
    i = inl.reshape(-1)
    rv, tv = cv2.solvePnPRefineLM(obj[i], img[i], K, dist, rv, tv)
    p, _ = cv2.projectPoints(obj, rv, tv, K, dist)
    e = np.linalg.norm(p.reshape(-1, 2) - img, axis=1)
    err = float(np.mean(np.minimum(e, INLIER_PX) ** 2))
    i = np.flatnonzero(e < INLIER_PX)
    R = np.asarray(cv2.Rodrigues(rv)[0], dtype=np.float64)
    return err, R, np.asarray(tv, dtype=np.float64).reshape(3), i


def reposed(rig: Rig, name: str, X: F64, uv: F64) -> tuple[Rig, JsonDict]:
    """``rig`` with camera ``name`` posed on the world points ``X (N, 3)`` it sees at ``uv (N, 2)``
    (:func:`correspondences`), its focal length searched (golden section on the truncated cost of
    :func:`_posed`, over :data:`FOCAL_RANGE` of its own); and what was found, for ``meta.json``
    (the median reprojection before over every pair, after over the inliers).
    InputError where too few points agree (the camera sees none of the people the others do)."""
    cam = rig.cameras[rig.index(name)]
    f0 = float(cam.K[0, 0])
    before = _median_px(cam, X, uv)
    lo, hi = np.log(FOCAL_RANGE[0] * f0), np.log(FOCAL_RANGE[1] * f0)
    seen: dict[float, float] = {}

    def cost(log_f: float) -> float:
        if log_f not in seen:
            seen[log_f] = _posed(cam, float(np.exp(log_f)), X, uv)[0]
        return seen[log_f]

    g = (math.sqrt(5) - 1) / 2
    a, b = lo + (1 - g) * (hi - lo), lo + g * (hi - lo)
    for _ in range(24):  # to 0.1 % of the focal length
        if cost(a) <= cost(b):
            hi, b = b, a
            a = lo + (1 - g) * (hi - lo)
        else:
            lo, a = a, b
            b = lo + g * (hi - lo)
    best = min(seen, key=lambda k: seen[k])
    f = float(np.exp(best))
    err, R, t, inl = _posed(cam, f, X, uv)
    if not math.isfinite(err) or len(inl) < MIN_INLIERS:
        raise InputError(f"camera {name}", f"cannot be posed again: fewer than {MIN_INLIERS} of its "
                                           "keypoints agree with the people the other cameras place")
    K = cam.K.copy()
    K[0, 0], K[1, 1] = f, f * cam.K[1, 1] / cam.K[0, 0]
    new = dataclasses.replace(cam, K=K, R=R, t=t)
    cams = tuple(new if c.name == name else c for c in rig.cameras)
    after = _median_px(new, X[inl], uv[inl])
    report: JsonDict = {"median_px_before": round(before, 3), "median_px_after": round(after, 3),
                        "inliers": int(len(inl)), "pairs": int(len(X)), "focal_px_before": round(f0, 2),
                        "focal_px": round(f, 2)}
    return dataclasses.replace(rig, cameras=cams), report


def _median_px(cam: Camera, X: F64, uv: F64) -> float:
    """Median reprojection (px) of ``X`` through ``cam`` as it is."""
    import cv2

    if not len(X):
        return math.nan
    rv = cv2.Rodrigues(cam.R)[0]
    p, _ = cv2.projectPoints(X.astype(np.float64), rv, cam.t.astype(np.float64), cam.K, cam.coefficients)
    return float(np.median(np.linalg.norm(p.reshape(-1, 2) - uv, axis=1)))
