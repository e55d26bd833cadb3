"""A rig from people's boxes (issue 63, the harder case): the cameras' poses from the boxes of
people whose ids the input gives across cameras (WILDTRACK's, MOTChallenge's after association),
with no calibration to start from. The intrinsics are given.

A box is two points: the middle of its bottom edge (where the person stands) and of its top edge
(the top of the head). They are not the projections of two fixed 3D points (a box is the outline
of a body, and its bottom edge is the lowest point of the feet's outline from that view), so the
rig they give is a start; what a box really constrains is its tangency, which the box refinement
(:mod:`gt3dkit.refine.boxes`, the exact tangent box of the ellipsoid) can take further.

1. **Points**: each box's two points, left out where the box touches the image's border (a cut
   box's edge is the border's). Each (frame, id) seen by two cameras is a correspondence of two
   points.
2. **Pairs**: per camera pair the essential matrix on its correspondences (OpenCV's five-point
   RANSAC, USAC MAGSAC) and its pose; the pair with the most inliers starts the rig.
3. **Cameras one by one**: the people's points triangulated from the posed cameras, the camera
   seeing most of them posed by PnP (RANSAC), and so on.
4. **One bundle adjustment** (:func:`gt3dkit.refine.keypoints.ba_keypoints`, pycolmap, Cauchy loss)
   over every camera and every person-frame's two points, rounds of it dropping points off by more
   than four times the median.
5. **The world**: up from feet to head (median), the floor through the feet, the scale from the
   people's median height (``height_m``: 1.7 m unless the user gives it; adults' heights vary by
   some 4 %, and so does this scale), the origin at their mean position on the floor, x towards the
   first camera.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import cv2
import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.geom.triangulate import normalized_points, triangulate_weighted
from gt3dkit.refine.common import RefineConfig, transform_rig
from gt3dkit.refine.keypoints import Tracks, ba_keypoints, keypoint_residuals
from gt3dkit.refine.people import PeopleCalibration, against_given, poorly_placed, pose_sd
from gt3dkit.rig import Rig
from gt3dkit.types import F64, I64, JsonDict, Scene

#: A box edge within this of the image's border (px) may be the border's: the box's point left out.
BORDER_PX = 2.0
#: The people's feet span a floor (its plane is up) where their spread across it is this much
#: smaller than along it.
FLAT = 0.2
#: The people's feet and heads in one plane (all walking along one line) within this share of their
#: spread along it: the rig is not determined (a plane's points leave the essential matrix ambiguous).
ON_A_PLANE = 0.03
#: The camera sds' jackknife leaves out one of this many groups of the people at a time.
SD_GROUPS = 10


@dataclass(frozen=True)
class BoxPeopleConfig:
    height_m: float = 1.7  # the people's median height (top of the box to its bottom), metres
    ransac_px: float = 4.0  # the essential matrix's and PnP's inlier threshold, px
    min_people: int = 20  # person-frames a camera needs in common with the posed ones
    ba_rounds: int = 3


@dataclass(frozen=True)
class BoxPoints:
    """Per annotated box ``(N,)``: its camera, frame and id, its two points ``uv (N, 2, 2)`` px (feet,
    head) and their rays ``xy (N, 2, 2)`` (normalised, undistorted; NaN where the box is cut)."""

    cam: I64
    frame: I64
    track: I64
    uv: F64
    xy: F64


def box_points(scene: Scene) -> BoxPoints:
    o, rig = scene.obs, scene.rig
    has = o.has_box
    b = o.box_xyxy_px[has]
    cam = o.cam[has]
    wh = rig.wh[cam]
    inside = (b[:, 0] > BORDER_PX) & (b[:, 1] > BORDER_PX) & (b[:, 2] < wh[:, 0] - 1 - BORDER_PX) & \
        (b[:, 3] < wh[:, 1] - 1 - BORDER_PX)
    cx = 0.5 * (b[:, 0] + b[:, 2])
    uv = np.stack([np.stack([cx, b[:, 3]], -1), np.stack([cx, b[:, 1]], -1)], 1)  # (N, 2, 2): feet, head
    uv[~inside] = np.nan
    xy = normalized_points(uv, rig.K[cam][:, None], rig.dist[cam][:, None])
    return BoxPoints(cam, o.frame[has], o.track_id[has], uv, xy)


def _key(p: BoxPoints) -> I64:
    return p.track.astype(np.int64) * (1 << 32) + p.frame


def _pair(p: BoxPoints, a: int, b: int) -> tuple[I64, I64]:
    """The boxes of cameras ``a`` and ``b`` of the same (frame, id), both whole."""
    ia = np.flatnonzero((p.cam == a) & np.isfinite(p.xy[:, 0, 0]))
    ib = np.flatnonzero((p.cam == b) & np.isfinite(p.xy[:, 0, 0]))
    _, ja, jb = np.intersect1d(_key(p)[ia], _key(p)[ib], return_indices=True)
    return ia[ja], ib[jb]


def _pair_pose(p: BoxPoints, a: int, b: int, f_px: float, cfg: BoxPeopleConfig) -> tuple[int, F64, F64]:
    """Inliers, ``R, t`` of camera ``b`` against ``a`` (``|t| = 1``) from their correspondences."""
    ia, ib = _pair(p, a, b)
    if len(ia) < cfg.min_people:
        return 0, np.eye(3), np.zeros(3)
    x1, x2 = p.xy[ia].reshape(-1, 2), p.xy[ib].reshape(-1, 2)
    E, mask = cv2.findEssentialMat(x1, x2, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999,
                                   threshold=cfg.ransac_px / f_px)
    if E is None or E.shape != (3, 3):
        return 0, np.eye(3), np.zeros(3)
    n, R, t, _ = cv2.recoverPose(E, x1, x2, np.eye(3), mask=mask)
    return int(n), np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).reshape(3)


def _triangulate(p: BoxPoints, R: F64, t: F64, posed: np.ndarray) -> tuple[I64, F64]:
    """Each (frame, id)'s two points from the posed cameras' whole boxes: keys ``(P,)``, ``X (P, 2, 3)``."""
    keys, inv = np.unique(_key(p), return_inverse=True)
    C = len(posed)
    xy = np.zeros((len(keys), C, 2, 2))
    w = np.zeros((len(keys), C))
    ok = posed[p.cam] & np.isfinite(p.xy[:, 0, 0])
    xy[inv[ok], p.cam[ok]] = p.xy[ok]
    w[inv[ok], p.cam[ok]] = 1.0
    X = np.stack([triangulate_weighted(xy[:, :, k], R, t, w) for k in range(2)], 1)
    return keys, X


def _pnp(p: BoxPoints, keys: I64, X: F64, c: int, f_px: float, cfg: BoxPeopleConfig) -> tuple[int, F64, F64]:
    ic = np.flatnonzero((p.cam == c) & np.isfinite(p.xy[:, 0, 0]))
    at = np.searchsorted(keys, _key(p)[ic])
    at = np.clip(at, 0, len(keys) - 1)
    found = (keys[at] == _key(p)[ic]) & np.all(np.isfinite(X[at]), axis=(1, 2))
    if found.sum() < cfg.min_people:
        return 0, np.eye(3), np.zeros(3)
    obj = X[at[found]].reshape(-1, 3)
    img = p.xy[ic[found]].reshape(-1, 2)
    ok, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, np.eye(3), None, iterationsCount=2000,
                                             reprojectionError=cfg.ransac_px / f_px, confidence=0.9999,
                                             flags=cv2.SOLVEPNP_EPNP)
    if not ok or inl is None:
        return 0, np.eye(3), np.zeros(3)
    ok, rvec, tvec = cv2.solvePnP(obj[inl[:, 0]], img[inl[:, 0]], np.eye(3), None, rvec, tvec,
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
    return (int(len(inl)), np.asarray(cv2.Rodrigues(rvec)[0], dtype=np.float64),
            np.asarray(tvec, dtype=np.float64).reshape(3))


@dataclass(frozen=True)
class Placed:
    """The cameras placed one by one (module docstring, steps 2-3): their poses ``R (C, 3, 3)``, ``t
    (C, 3)`` (the first at the origin, the start pair's baseline one unit), the order they were placed
    in, and each camera pair's inlier points (a whole box gives two)."""

    R: F64
    t: F64
    order: list[int]
    pair_inliers: dict[tuple[int, int], int]


def place_cameras(p: BoxPoints, rig: Rig, cfg: BoxPeopleConfig, where: str) -> Placed:
    """Steps 2-3 of the module docstring, or :class:`InputError` naming a camera that cannot be
    placed, or everyone's points in one plane."""
    C = len(rig.cameras)
    f = rig.K[:, 0, 0]
    fits = {(a, b): _pair_pose(p, a, b, float(np.sqrt(f[a] * f[b])), cfg)
            for a in range(C) for b in range(a + 1, C)}
    (a, b), (n, Rab, tab) = max(fits.items(), key=lambda kv: kv[1][0])
    if n < cfg.min_people:
        raise InputError(where, f"no two cameras share {cfg.min_people} whole boxes of the same people: "
                                "no rig can be started")
    R, t = np.tile(np.eye(3), (C, 1, 1)), np.zeros((C, 3))
    R[b], t[b] = Rab, tab
    posed = np.zeros(C, bool)
    posed[[a, b]] = True
    order = [a, b]
    while not posed.all():
        keys, X = _triangulate(p, R, t, posed)
        left = np.flatnonzero(~posed).tolist()
        c, (n, Rc, tc) = max(((c, _pnp(p, keys, X, c, float(f[c]), cfg)) for c in left),
                             key=lambda kv: kv[1][0])
        if n < cfg.min_people:
            missing = [rig.cameras[k].name for k in np.flatnonzero(~posed)]
            raise InputError(", ".join(missing), f"shares at most {n} whole boxes of people with the posed "
                                                 f"cameras (needs {cfg.min_people}): cannot be placed")
        R[c], t[c] = Rc, tc
        posed[c] = True
        order.append(int(c))
    _, X = _triangulate(p, R, t, posed)
    pts = X.reshape(-1, 3)[np.isfinite(X.reshape(-1, 3)).all(1)]
    sv = np.linalg.svd(pts - np.median(pts, axis=0), compute_uv=False)
    if sv[2] < ON_A_PLANE * sv[1]:
        raise InputError("people", "everyone's feet and heads lie in one plane (on one line across the "
                                   f"floor; spread {sv[2] / sv[1]:.3f} of their spread along it): the "
                                   "cameras' poses are not determined by them")
    return Placed(R, t, order, {k: int(v[0]) for k, v in fits.items()})


def adjusted(p: BoxPoints, start: Rig, cfg: BoxPeopleConfig) -> Rig:
    """Step 4 of the module docstring: ``cfg.ba_rounds`` pycolmap adjustments of every camera and
    point, each dropping the points off by more than four times the median."""
    out = start
    every = np.ones(len(start.cameras), bool)
    ba_cfg = RefineConfig(refine_intrinsics=False, refine_distortion=False)
    for _ in range(cfg.ba_rounds):
        keys, X = _triangulate(p, out.R, out.t, every)
        tracks = _tracks(p, keys, X, out)
        r = keypoint_residuals(out, tracks)
        sigma = float(np.median(r))
        keep = np.ones(len(tracks.X0), bool)
        keep[np.unique(tracks.point[r > 4 * sigma])] = False
        out = ba_keypoints(out, tracks.subset(keep), every, ba_cfg, max(sigma, 0.5))
    return out


def calibrate_boxes(scene: Scene, cfg: BoxPeopleConfig | None = None) -> PeopleCalibration:
    """The rig of ``scene``'s cameras from its people's boxes (module docstring); its intrinsics
    are the scene's, its poses are not used."""
    cfg = cfg or BoxPeopleConfig()
    t0 = time.perf_counter()
    rig = scene.rig
    C = len(rig.cameras)
    p = box_points(scene)
    placed = place_cameras(p, rig, cfg, scene.root or "input")
    start = replace(rig, cameras=tuple(replace(cam, R=placed.R[k], t=placed.t[k])
                                       for k, cam in enumerate(rig.cameras)))
    out = adjusted(p, start, cfg)
    keys, X = _triangulate(p, out.R, out.t, np.ones(C, bool))
    tracks = _tracks(p, keys, X, out)
    res = keypoint_residuals(out, tracks)
    # the sds: a jackknife over ten groups of the people (a person's boxes share their body's outline),
    # and over the two points (the feet's and the head's: each a point of the outline, not of the
    # body, and misplaced by its own amount from each view); the larger
    c_sd, r_sd = pose_sd(out, tracks, (keys[tracks.point // 2] >> 32) % SD_GROUPS)
    c_sd2, r_sd2 = pose_sd(out, tracks, tracks.point % 2, min_kinds=2)
    c_sd, r_sd = np.fmax(c_sd, c_sd2), np.fmax(r_sd, r_sd2)
    s, Rw, tw, world = box_world(X, out, cfg)
    c_sd *= s
    final = replace(transform_rig(out, s, Rw, tw), up=np.array([0.0, 0.0, 1.0]),
                    frame_name=str(world["frame"]))
    a, b = placed.order[:2]
    report: JsonDict = {
        "seconds": time.perf_counter() - t0, "from": "boxes",
        "camera_pairs": [{"cameras": [rig.names[i], rig.names[j]], "inlier_points": v}
                         for (i, j), v in placed.pair_inliers.items()],
        "people": int(len(keys)), "tracks": int(len(tracks.X0)),
        "reprojection_median_px": float(np.median(res)), "start_pair": [rig.names[a], rig.names[b]],
        "order": [rig.names[k] for k in placed.order], "world": world,
        "cameras": {rig.names[c]: {"centre_sd_m": float(c_sd[c]), "rotation_sd_deg": float(r_sd[c]),
                                   "median_px": float(np.median(res[tracks.cam == c]))
                                   if (tracks.cam == c).any() else None} for c in range(C)}}
    given = against_given(final, rig)
    if given is not None:
        report["against_input_calibration"] = given
    return PeopleCalibration(final, report, tracks, poorly_placed(final, c_sd, r_sd))


def _tracks(p: BoxPoints, keys: I64, X: F64, rig: Rig) -> Tracks:
    """Each (frame, id)'s two triangulated points seen by two or more whole boxes, as tracks."""
    at = np.clip(np.searchsorted(keys, _key(p)), 0, len(keys) - 1)
    ok = (keys[at] == _key(p)) & np.isfinite(p.uv[:, 0, 0])
    n = np.flatnonzero(ok)
    pt = np.repeat(at[n] * 2, 2) + np.tile([0, 1], len(n))  # (2n,) point of each observation
    uv = p.uv[n].reshape(-1, 2)
    cam = np.repeat(p.cam[n], 2)
    Xf = X.reshape(-1, 3)
    good = np.isfinite(Xf[pt]).all(-1)
    pts, point = np.unique(pt[good], return_inverse=True)
    count = np.bincount(point)
    keep = count >= 2
    sel = keep[point]
    new = np.cumsum(keep) - 1
    return Tracks(Xf[pts[keep]], np.zeros(int(keep.sum()), np.int64), new[point[sel]], cam[good][sel],
                  uv[good][sel])


def box_world(X: F64, rig: Rig, cfg: BoxPeopleConfig) -> tuple[float, F64, F64, JsonDict]:
    """The similarity ``X' = s Rw X + tw`` into the people's world (module docstring, step 5) of
    their feet and heads ``X (P, 2, 3)``."""
    v = X[:, 1] - X[:, 0]
    ok = np.all(np.isfinite(v), axis=1)
    if ok.sum() < 10:
        raise InputError("people", f"{int(ok.sum())} people with both feet and head placed: too few to find "
                                   "up")
    h = np.linalg.norm(v[ok], axis=1)
    u = v[ok] / h[:, None]
    up = np.median(u, axis=0)
    up /= np.linalg.norm(up)
    # people walking over a floor wider than they are tall: its plane through their feet is the
    # better vertical (a box's bottom and top are its outline's, leaning with the view)
    feet = X[ok, 0]
    sv, vecs = np.linalg.svd(feet - np.median(feet, axis=0), full_matrices=False)[1:]
    how_up = "from their feet to their heads"
    if sv[2] < FLAT * sv[1]:
        up = vecs[2] * np.sign(vecs[2] @ up)
        how_up = "the plane through their feet"
    height = float(np.median(v[ok] @ up))
    scale = cfg.height_m / height
    floor = float(np.median(feet @ up))
    centre = feet.mean(0)
    centre = centre - (centre @ up - floor) * up
    cam0 = rig.cameras[0].center_world - centre
    x = cam0 - (cam0 @ up) * up
    x /= np.linalg.norm(x)
    Rw = np.stack([x, np.cross(up, x), up])
    tw = -scale * Rw @ centre
    return scale, Rw, tw, {
        "frame": f"the people's world: z up ({how_up}), z = 0 the floor (their feet), "
                 f"origin their mean position on it, x towards the first camera; metres from their median "
                 f"height, {cfg.height_m} m", "people_frames": int(ok.sum())}
