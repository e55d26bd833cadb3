"""A rig from the people in the scene: the cameras' poses from the keypoints of people moving
through it, with no calibration to start from and no identities (issue 63).

The intrinsics are given (the input's calibration or ``--intrinsics``); the poses are not used.

1. **Person pairs per camera pair.** In each frame every detection of camera ``a`` may be any
   detection of camera ``b`` (or the same person with left and right swapped, as detectors seen
   from behind often have them). Hypotheses of the pair's essential matrix come from the joints
   of two such candidate pairs of two frames (OpenCV's five-point RANSAC on their ~40 joints); a
   hypothesis scores the candidate pairs whose joints' median Sampson distance is below
   ``pair_px``. The best one is refitted on its pairs (USAC MAGSAC) and decomposed
   (``cv2.recoverPose``). A wrong pairing is an outlier group, not a hundred outlier points.
2. **People across cameras.** The matching pairs link detections; per frame the linked
   detections form one person (a breadth-first walk that keeps one detection per camera and the
   left/right reading that agrees with the first).
3. **Cameras one by one.** The pair with the most matched people starts the rig (camera ``a`` at
   the origin, the baseline one unit); its people are triangulated; the camera with the most
   joints on those people is posed by PnP (RANSAC), the people triangulated again, and so on.
4. **One bundle adjustment** (:func:`gt3dkit.refine.keypoints.ba_keypoints`, pycolmap, Cauchy loss)
   over every camera and every person's joints.
5. **The world** from the people: up from how they stand (the skeleton's floor joints to its up
   joints: a person's ankles to the neck), the floor from the floor joints, the scale from
   typical human bone lengths (:meth:`gt3dkit.skeletons.Skeleton.canonical`:
   adults' bones vary by some 5-7 %, and so does this scale) or from their median height when the
   user gives it, the origin at their mean position on the floor, x towards the first camera.
"""

from __future__ import annotations

import time
import warnings
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.geom.camera import project_points
from gt3dkit.geom.triangulate import normalized_points, reprojection_sq_px, triangulate_weighted
from gt3dkit.refine.clocks import Clocks, estimate_clocks, follow, synchronised
from gt3dkit.refine.common import RefineConfig, centre_similarity, transform_rig
from gt3dkit.refine.keypoints import Tracks, ba_keypoints, keypoint_residuals
from gt3dkit.refine.persons import (
    PersonViews,
    candidates,
    essential,
    normalised,
    pair_errors,
)
from gt3dkit.rig import Rig
from gt3dkit.skeletons import Skeleton, skeleton_of
from gt3dkit.types import F64, I64, JsonDict, Scene

#: Camera pairs fitted on their own (those with the most candidate person pairs); the other cameras
#: are posed on the people already in 3D (:func:`pose_by_people`).
MAX_PAIR_FITS = 10
#: RANSAC iterations of OpenCV's five-point solver within one hypothesis's two person pairs.
HYPOTHESIS_ITERS = 40
#: The focal length a camera of unknown intrinsics starts from, in its image's longer side (COLMAP's
#: default prior, 1.2).
FOCAL_START = 1.2
#: Bundle adjustments, each followed by matching the people again through the adjusted rig.
RELINK_ROUNDS = 3
#: The standing height (top of the head) of the skeletons' canonical body, metres.
_CANON_HEIGHT_M = 1.74


@dataclass(frozen=True)
class PeopleConfig:
    """Settings of :func:`calibrate_people`."""

    min_conf: float = 0.2  # joints below this confidence are not used
    pair_px: float = 3.0  # a candidate person pair matches below this median Sampson distance, px
    hypotheses: int = 150  # essential-matrix hypotheses per camera pair
    min_pairs: int = 10  # matched person pairs a camera pair needs to count
    min_joints: int = 30  # 2D-3D joints a camera needs to be posed
    height_m: float | None = None  # the people's median standing height, if known
    #: Joints left out of the geometry: a 2D detector places the hips and shoulders (and the
    #: pelvis between the hips) inside the body's outline from each view's silhouette, so each view
    #: sees a different 3D point. On Shelf's OpenPose output leaving them out brings the camera
    #: centres from 1.1-5.4 cm to 1.2-2.9 cm of Shelf's calibration (rotations 0.36-1.2 to 0.29-0.69 deg).
    skip_joints: tuple[str, ...] = ("l_hip", "r_hip", "pelvis", "l_shoulder", "r_shoulder")
    #: True: each camera's clock found too (:mod:`gt3dkit.refine.clocks`), the rig adjusted on the
    #: detections moved onto the first camera's clock.
    clocks: bool = False
    #: False: the intrinsics are not known; each camera starts from :func:`focal_from_image` and its
    #: focal length is adjusted with its pose (its distortion stays none: people's joints, a few
    #: pixels apart from view to view, do not hold a lens's distortion).
    focal_known: bool = True
    seed: int = 0


def focal_from_image(rig: Rig) -> Rig:
    """``rig`` with no intrinsics known: the focal length :data:`FOCAL_START` times the image's longer
    side, the principal point at the image's centre, no distortion (the start COLMAP takes)."""
    cams = []
    for c in rig.cameras:
        f = FOCAL_START * max(c.width, c.height)
        K = np.array([[f, 0.0, (c.width - 1) / 2], [0.0, f, (c.height - 1) / 2], [0.0, 0.0, 1.0]])
        cams.append(replace(c, K=K, dist=np.zeros(5), lens="pinhole"))
    return replace(rig, cameras=tuple(cams))


def person_views(scene: Scene, cfg: PeopleConfig) -> PersonViews:
    o, rig = scene.obs, (scene.rig if cfg.focal_known else focal_from_image(scene.rig))
    if o.kpt_uv_px is None or scene.skeleton is None:
        raise InputError(scene.root or "input", "no keypoints: this makes a rig from people's joints "
                                                "(from boxes: gt3dkit.refine.boxpeople)")
    xy = normalized_points(o.kpt_uv_px, rig.K[o.cam][:, None], rig.dist[o.cam][:, None])
    ok = np.isfinite(xy[..., 0])
    if o.kpt_conf is not None:
        ok &= np.nan_to_num(o.kpt_conf) >= cfg.min_conf
    skel = skeleton_of(scene)
    if skel is None:
        raise InputError(str(scene.root), "the people's rig needs keypoints")
    ok[:, [k for k, n in enumerate(skel.joints) if n in cfg.skip_joints]] = False
    return PersonViews(np.where(ok[..., None], xy, np.nan), ok, o.cam.astype(np.int64),
                       o.frame.astype(np.int64), o.kpt_uv_px, skel.mirror(), rig.K[:, 0, 0].copy())


# ----------------------------------------------------------------------------- camera pairs


#: How often a hypothesis reads a candidate's joints with left and right swapped (detectors swap
#: them in a minority of views: seen from behind, or sideways).
SWAPPED_SHARE = 0.15


def hypotheses_needed(inliers: float, confidence: float = 0.999) -> int:
    """RANSAC's adaptive count (Fischler & Bolles 1981; Hartley & Zisserman 4.7.1) for samples of
    two candidates, each in its right reading, with ``inliers`` the share of candidates that
    match: ``log(1 - confidence) / log(1 - ((1 - SWAPPED_SHARE) w)^2)``, at least 20."""
    w = (1 - SWAPPED_SHARE) * min(max(inliers, 1e-6), 1.0)
    return max(20, int(np.ceil(np.log(1 - confidence) / np.log(max(1 - w * w, 1e-12)))))


@dataclass
class TwoFrameSamples:
    """Samples of two candidates (indices into ``frames``, each candidate's frame) from two
    frames, as many as RANSAC's adaptive count asks once a hypothesis is :meth:`found` (at most
    ``limit``)."""

    frames: I64
    limit: int
    rng: np.random.Generator
    needed: int = field(init=False)

    def __post_init__(self) -> None:
        self.needed = self.limit

    def __iter__(self) -> Iterator[I64]:
        tried = 0
        while tried < self.needed:
            tried += 1
            k = self.rng.choice(len(self.frames), 2, replace=False)
            if self.frames[k[0]] != self.frames[k[1]]:
                yield k

    def found(self, share: float) -> None:
        """The best hypothesis so far matches ``share`` of the candidates."""
        self.needed = min(self.limit, hypotheses_needed(share))


@dataclass(frozen=True)
class PairFit:
    """Camera ``b``'s pose relative to ``a`` (``X_b = R X_a + t``, ``|t| = 1``) and the matched
    person pairs ``links (L, 3)``: detection in ``a``, detection in ``b``, 1 where ``b``'s joints
    read with left and right swapped."""

    a: int
    b: int
    R: F64
    t: F64
    links: I64
    candidates: int


def fit_pair(pv: PersonViews, a: int, b: int, cfg: PeopleConfig, rng: np.random.Generator) -> PairFit | None:
    """Camera ``b`` relative to ``a`` from their person pairs (module docstring, step 1); None
    where fewer than ``min_pairs`` pairs match."""
    import cv2

    P = candidates(pv, a, b)
    if len(P) < cfg.min_pairs:
        return None
    f_px = float(np.sqrt(pv.f_px[a] * pv.f_px[b]))
    frames = pv.frame[P[:, 0]]
    score_on = P if len(P) <= 400 else P[rng.choice(len(P), 400, replace=False)]
    best, best_E = -1, None
    samples = TwoFrameSamples(frames, cfg.hypotheses, rng)
    for k in samples:
        flip = rng.uniform(size=2) < SWAPPED_SHARE
        parts1: list[F64] = []
        parts2: list[F64] = []
        for q, fl in zip(k, flip, strict=True):
            x2 = pv.xy[P[q, 1]][pv.mirror] if fl else pv.xy[P[q, 1]]
            m = pv.ok[P[q, 0]] & np.isfinite(x2[:, 0])
            parts1.append(pv.xy[P[q, 0]][m])
            parts2.append(x2[m])
        p1a, p2a = np.concatenate(parts1), np.concatenate(parts2)
        if len(p1a) < 10:
            continue
        E, _ = cv2.findEssentialMat(p1a, p2a, np.eye(3), method=cv2.RANSAC, prob=0.99,
                                    threshold=cfg.pair_px / f_px, maxIters=HYPOTHESIS_ITERS)
        if E is None:
            continue
        E3 = np.asarray(E[:3], dtype=np.float64)
        score = int((pair_errors(pv, E3, score_on, f_px)[0] < cfg.pair_px).sum())
        if score > best:
            best, best_E = score, E3
            samples.found(score / len(score_on))
    if best_E is None:
        return None
    err, flip = pair_errors(pv, best_E, P, f_px)
    good = err < cfg.pair_px
    if good.sum() < cfg.min_pairs:
        return None
    p1, p2 = _joint_pairs(pv, P[good], flip[good])
    E, inl = cv2.findEssentialMat(p1, p2, np.eye(3), method=cv2.USAC_MAGSAC, prob=0.9999,
                                  threshold=cfg.pair_px / f_px)
    if E is None:
        return None
    E3 = np.asarray(E[:3], dtype=np.float64)
    _, R, t, _ = cv2.recoverPose(E3, p1, p2, np.eye(3), mask=inl.copy())
    err, flip = pair_errors(pv, E3, P, f_px)
    good = err < cfg.pair_px
    links = np.column_stack([P[good], flip[good].astype(np.int64)])
    return PairFit(a, b, np.asarray(R, dtype=np.float64), np.asarray(t, dtype=np.float64).reshape(3),
                   _one_per_detection(links, err[good]), len(P))


def _joint_pairs(pv: PersonViews, P: I64, flip: np.ndarray) -> tuple[F64, F64]:
    x1 = pv.xy[P[:, 0]]
    x2 = np.where(flip[:, None, None], pv.xy[P[:, 1]][:, pv.mirror], pv.xy[P[:, 1]])
    m = np.isfinite(x1[..., 0]) & np.isfinite(x2[..., 0])
    return x1[m], x2[m]


def _one_per_detection(links: I64, err: F64) -> I64:
    """The links with each detection in at most one (the best first)."""
    used_a: set[int] = set()
    used_b: set[int] = set()
    keep = []
    for k in np.argsort(err, kind="stable"):
        i, j = int(links[k, 0]), int(links[k, 1])
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            keep.append(k)
    return links[np.sort(np.array(keep, dtype=np.int64))]


def rig_links(pv: PersonViews, rig: Rig, cfg: PeopleConfig) -> list[PairFit]:
    """Every camera pair's person pairs through ``rig``'s relative poses (its essential matrices)."""
    out = []
    C = len(rig.cameras)
    for a in range(C):
        for b in range(a + 1, C):
            P = candidates(pv, a, b)
            if not len(P):
                continue
            E = essential(rig, a, b)
            R = rig.R[b] @ rig.R[a].T
            t = rig.t[b] - R @ rig.t[a]
            err, flip = pair_errors(pv, E, P, float(np.sqrt(pv.f_px[a] * pv.f_px[b])))
            good = err < cfg.pair_px
            links = np.column_stack([P[good], flip[good].astype(np.int64)])
            out.append(PairFit(a, b, R, t, _one_per_detection(links, err[good]), len(P)))
    return out


# ----------------------------------------------------------------------------- people


def people_of(pv: PersonViews, fits: list[PairFit]) -> tuple[I64, np.ndarray]:
    """Each detection's person (-1: none; module docstring, step 2) and whether it reads with left
    and right swapped relative to its person."""
    N = len(pv.cam)
    adj: list[list[tuple[int, int]]] = [[] for _ in range(N)]
    for fit in fits:
        for i, j, fl in fit.links:
            adj[int(i)].append((int(j), int(fl)))
            adj[int(j)].append((int(i), int(fl)))
    person, flip = np.full(N, -1, np.int64), np.zeros(N, bool)
    order = np.argsort([-len(x) for x in adj], kind="stable")
    n = 0
    for s in order:
        if person[s] >= 0 or not adj[s]:
            continue
        cams = {int(pv.cam[s])}
        person[s], flip[s] = n, False
        queue = deque([int(s)])
        while queue:
            i = queue.popleft()
            for j, fl in adj[i]:
                if person[j] >= 0 or int(pv.cam[j]) in cams:
                    continue
                person[j], flip[j] = n, bool(flip[i]) ^ bool(fl)
                cams.add(int(pv.cam[j]))
                queue.append(j)
        n += 1
    return person, flip


def _oriented(pv: PersonViews, flip: np.ndarray) -> F64:
    """(N, J, 2) every detection's joints in its person's left/right reading."""
    return np.where(flip[:, None, None], pv.xy[:, pv.mirror], pv.xy)


def triangulate_people(pv: PersonViews, person: I64, flip: np.ndarray, R: F64, t: F64,
                       placed: np.ndarray) -> F64:
    """(n_people, J, 3) each person's joints from the placed cameras (NaN: fewer than 2 views)."""
    n, C, J = int(person.max()) + 1, len(placed), pv.xy.shape[1]
    xy = np.full((n, J, C, 2), np.nan)
    m = (person >= 0) & placed[pv.cam]
    xy[person[m], :, pv.cam[m]] = _oriented(pv, flip)[m]
    w = np.isfinite(xy[..., 0]).astype(np.float64)
    X = triangulate_weighted(np.nan_to_num(xy).reshape(n * J, C, 2), R, t, w.reshape(n * J, C))
    return X.reshape(n, J, 3)


def _pose_camera(pv: PersonViews, person: I64, flip: np.ndarray, X: F64, c: int, cfg: PeopleConfig
                 ) -> tuple[F64, F64, int] | None:
    """Camera ``c``'s cam_from_world (R, t) by PnP RANSAC on its people's triangulated joints, and
    the joints it used; None with fewer than ``min_joints``."""
    import cv2

    m = (pv.cam == c) & (person >= 0)
    if not m.any():
        return None
    X3 = X[person[m]]  # (n, J, 3)
    x2 = _oriented(pv, flip)[m]
    ok = np.isfinite(X3[..., 0]) & np.isfinite(x2[..., 0])
    if ok.sum() < cfg.min_joints:
        return None
    got, rv, tv, inl = cv2.solvePnPRansac(X3[ok], x2[ok], np.eye(3), None, iterationsCount=500,
                                          reprojectionError=2 * cfg.pair_px / pv.f_px[c],
                                          flags=cv2.SOLVEPNP_EPNP)
    if not got or inl is None or len(inl) < cfg.min_joints:
        return None
    i = inl.reshape(-1)
    rv, tv = cv2.solvePnPRefineLM(X3[ok][i], x2[ok][i], np.eye(3), None, rv, tv)
    return (np.asarray(cv2.Rodrigues(rv)[0], dtype=np.float64), np.asarray(tv, dtype=np.float64).reshape(3),
            int(len(i)))


def _reprojection_px(X: F64, xy: F64, R: F64, t: F64, f_px: float) -> F64:
    """Per candidate the median distance (px) between its joints ``xy (P, J, 2)`` (normalised) and
    the points ``X (P, J, 3)`` seen through ``R, t``; inf where none is seen."""
    e2 = reprojection_sq_px(X, xy[..., None, :], R[None], t[None], np.array([f_px]))[..., 0]
    d = np.where(np.isfinite(e2), np.sqrt(e2), np.nan)  # a joint behind the camera: not seen
    with np.errstate(all="ignore"):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            med = np.nanmedian(d, axis=1)
    return np.nan_to_num(med, nan=np.inf)


@dataclass(frozen=True)
class CameraByPeople:
    """A camera posed on the people already in 3D: cam_from_world ``R, t``, the joints used, and
    which of its detections are which person (``det``, ``person``, ``flip``)."""

    R: F64
    t: F64
    joints: int
    det: I64
    person: I64
    flip: np.ndarray


def pose_by_people(pv: PersonViews, person: I64, X: F64, c: int, cfg: PeopleConfig,
                   rng: np.random.Generator) -> CameraByPeople | None:
    """Camera ``c`` posed on the people in 3D ``X (n, J, 3)`` without knowing which of its
    detections is whom: hypotheses from two (detection, person) candidates of two frames (PnP on
    their joints), scored by the candidates that reproject within ``2 pair_px``; the best refitted
    on one candidate per detection and per person (PnP RANSAC, then Levenberg-Marquardt)."""
    import cv2

    people = np.flatnonzero(np.isfinite(X[..., 0]).sum(1) >= 6)
    if not len(people):
        return None
    frame_of = np.full(len(X), -1, np.int64)
    has = person >= 0
    frame_of[person[has]] = pv.frame[has]
    dets = np.flatnonzero(pv.cam == c)
    pf = frame_of[people]
    order = np.argsort(pf, kind="stable")
    lo = np.searchsorted(pf[order], pv.frame[dets], "left")
    hi = np.searchsorted(pf[order], pv.frame[dets], "right")
    pairs = [(d, people[order[k]]) for d, a, b in zip(dets, lo, hi, strict=True) for k in range(a, b)]
    cand = np.array(pairs, dtype=np.int64).reshape(-1, 2)
    if len(cand) < 2:
        return None
    f_px, thr = float(pv.f_px[c]), 2 * cfg.pair_px
    xy, xym = pv.xy[cand[:, 0]], pv.xy[cand[:, 0]][:, pv.mirror]
    X3 = X[cand[:, 1]]
    score_on = np.arange(len(cand)) if len(cand) <= 400 else rng.choice(len(cand), 400, replace=False)
    best, best_rt = -1, None
    samples = TwoFrameSamples(pv.frame[cand[:, 0]], cfg.hypotheses, rng)
    for k in samples:
        obj, img = [], []
        for q in k:
            x2 = xym[q] if rng.uniform() < SWAPPED_SHARE else xy[q]
            m = np.isfinite(X3[q][:, 0]) & np.isfinite(x2[:, 0])
            obj.append(X3[q][m])
            img.append(x2[m])
        o3, i2 = np.concatenate(obj), np.concatenate(img)
        if len(o3) < 8:
            continue
        got, rv, tv, _ = cv2.solvePnPRansac(o3, i2, np.eye(3), None, iterationsCount=HYPOTHESIS_ITERS,
                                            reprojectionError=thr / f_px, flags=cv2.SOLVEPNP_EPNP)
        if not got:
            continue
        Rh = np.asarray(cv2.Rodrigues(rv)[0], dtype=np.float64)
        th = np.asarray(tv, dtype=np.float64).reshape(3)
        e = np.minimum(_reprojection_px(X3[score_on], xy[score_on], Rh, th, f_px),
                       _reprojection_px(X3[score_on], xym[score_on], Rh, th, f_px))
        score = int((e < thr).sum())
        if score > best:
            best, best_rt = score, (Rh, th)
            samples.found(score / len(score_on))
    if best_rt is None:
        return None
    e0 = _reprojection_px(X3, xy, *best_rt, f_px)
    e1 = _reprojection_px(X3, xym, *best_rt, f_px)
    err, fl = np.minimum(e0, e1), e1 < e0
    good = np.flatnonzero(err < thr)
    links = _one_per_detection(np.column_stack([cand[good], fl[good].astype(np.int64)]), err[good])
    if not len(links):
        return None
    x2 = np.where(links[:, 2, None, None].astype(bool), pv.xy[links[:, 0]][:, pv.mirror], pv.xy[links[:, 0]])
    o3 = X[links[:, 1]]
    ok = np.isfinite(o3[..., 0]) & np.isfinite(x2[..., 0])
    if ok.sum() < cfg.min_joints:
        return None
    got, rv, tv, inl = cv2.solvePnPRansac(o3[ok], x2[ok], np.eye(3), None, iterationsCount=500,
                                          reprojectionError=thr / f_px, flags=cv2.SOLVEPNP_EPNP)
    if not got or inl is None or len(inl) < cfg.min_joints:
        return None
    i = inl.reshape(-1)
    rv, tv = cv2.solvePnPRefineLM(o3[ok][i], x2[ok][i], np.eye(3), None, rv, tv)
    return CameraByPeople(np.asarray(cv2.Rodrigues(rv)[0], dtype=np.float64),
                          np.asarray(tv, dtype=np.float64).reshape(3), int(len(i)), links[:, 0], links[:, 1],
                          links[:, 2].astype(bool))


# ----------------------------------------------------------------------------- the calibration


@dataclass(frozen=True)
class PeopleCalibration:
    rig: Rig  # every camera, in the people's world
    report: JsonDict
    tracks: Tracks  # the people's joints the last adjustment used (camera indices into ``rig``)
    warnings: tuple[str, ...] = ()  # cameras placed poorly, by their sd
    clocks: Clocks | None = None  # each camera's clock (PeopleConfig.clocks)


@dataclass
class Placement:
    """Steps 1-3 of the module docstring: each camera's pose ``R (C, 3, 3)``, ``t (C, 3)`` and
    whether it was ``placed (C,)``, the joints each was posed on, every detection's ``person`` and
    ``flip``, the camera pairs fitted and the first (the rig's start)."""

    R: F64
    t: F64
    placed: np.ndarray
    joints_used: dict[int, int]
    person: I64
    flip: np.ndarray
    fits: list[PairFit]
    first: PairFit


def place_cameras(pv: PersonViews, rig: Rig, cfg: PeopleConfig, rng: np.random.Generator, where: str
                  ) -> Placement:
    """Camera pairs fitted, people linked across cameras, cameras posed one by one (module
    docstring, steps 1-3); :class:`InputError` naming a camera that cannot be placed."""
    C = len(rig.cameras)
    by_count = sorted(((len(candidates(pv, a, b)), a, b) for a in range(C) for b in range(a + 1, C)),
                      reverse=True)
    fits = [f for _, a, b in by_count[:MAX_PAIR_FITS] if (f := fit_pair(pv, a, b, cfg, rng)) is not None]
    if not fits:
        raise InputError(where, "no two cameras share enough people to be placed "
                         f"(each camera pair needs {cfg.min_pairs} person pairs whose joints agree)")
    person, flip = people_of(pv, fits)
    first = max(fits, key=lambda f: len(f.links))
    R, t = np.tile(np.eye(3), (C, 1, 1)), np.zeros((C, 3))
    R[first.b], t[first.b] = first.R, first.t
    placed = np.zeros(C, bool)
    placed[[first.a, first.b]] = True
    joints_used = {first.a: 0, first.b: 0}
    while not placed.all():
        X = triangulate_people(pv, person, flip, R, t, placed)
        tries: dict[int, CameraByPeople] = {}
        for cam in np.flatnonzero(~placed).tolist():
            posed = _pose_camera(pv, person, flip, X, cam, cfg)
            if posed is not None:
                tries[cam] = CameraByPeople(*posed, np.zeros(0, np.int64), np.zeros(0, np.int64),
                                            np.zeros(0, bool))
            elif (got := pose_by_people(pv, person, X, cam, cfg, rng)) is not None:
                tries[cam] = got
        if not tries:
            break
        most = max(r.joints for r in tries.values())
        for c, r in tries.items():  # every camera posed on at least half the joints of the best
            if r.joints >= 0.5 * most:
                R[c], t[c], joints_used[c] = r.R, r.t, r.joints
                person[r.det], flip[r.det] = r.person, r.flip
                placed[c] = True
    if not placed.all():
        c = int(np.flatnonzero(~placed)[0])
        n = int((pv.cam == c).sum())
        linked = int(((pv.cam == c) & (person >= 0)).sum())
        raise InputError(f"{where}: camera {rig.cameras[c].name}",
                         f"cannot be placed: {n} detections, {linked} of them matched to a person the "
                         f"placed cameras saw, fewer than {cfg.min_joints} joints agreeing with them "
                         "(too few people or frames shared with the other cameras)")
    return Placement(R, t, placed, joints_used, person, flip, fits, first)


def calibrate_people(scene: Scene, cfg: PeopleConfig | None = None) -> PeopleCalibration:
    """The poses of ``scene``'s cameras from its people (module docstring)."""
    cfg = cfg or PeopleConfig()
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    pv = person_views(scene, cfg)
    rig = scene.rig if cfg.focal_known else focal_from_image(scene.rig)
    pl = place_cameras(pv, rig, cfg, rng, scene.root or "input")
    R, t, placed, joints_used, person, flip = pl.R, pl.t, pl.placed, pl.joints_used, pl.person, pl.flip
    fits, first = pl.fits, pl.first
    keep = np.flatnonzero(placed)
    cams = tuple(replace(rig.cameras[c], R=R[c], t=t[c]) for c in keep)
    start = Rig(cams, up=rig.up, frame_name="people")
    # 4. bundle adjustments over the placed cameras and every person's joints; after each, the
    # people matched again through the adjusted rig (every pair's geometry now known)
    on = placed[pv.cam]
    pv_on = PersonViews(pv.xy[on], pv.ok[on], np.searchsorted(keep, pv.cam[on]), pv.frame[on], pv.uv[on],
                        pv.mirror, pv.f_px[keep])
    rounds = RELINK_ROUNDS if cfg.focal_known else 2 * RELINK_ROUNDS
    rig_ba, pv_on, person_on, flip_on = adjust(pv_on, person[on], flip[on], start, cfg, rounds)
    clocks: Clocks | None = None
    if cfg.clocks:
        # the clocks through this rig, the detections moved onto the first camera's clock and the
        # rig adjusted again on them; the clocks again through the adjusted rig
        succ, _ = follow(pv_on)
        sync = synchronised(pv_on, succ, estimate_clocks(pv_on, rig_ba).late_frames)
        p_s, f_s = people_of(sync, rig_links(sync, rig_ba, cfg))
        rig_ba, sync, person_on, flip_on = adjust(sync, p_s, f_s, rig_ba, cfg, RELINK_ROUNDS)
        clocks = estimate_clocks(replace(pv_on, xy=normalised(pv_on, rig_ba), f_px=rig_ba.K[:, 0, 0].copy()),
                                 rig_ba)
        pv_on = sync
    X = triangulate_people(pv_on, person_on, flip_on, rig_ba.R, rig_ba.t, np.ones(len(keep), bool))
    tracks, joint_of = _tracks(pv_on, person_on, flip_on, X, rig_ba, cfg)
    person = person_on
    # 5. the world
    skel = skeleton_of(scene)
    assert skel is not None  # person_views refused a scene without keypoints
    s, Rw, tw, world = people_world(X, skel, rig_ba, cfg)
    out = transform_rig(rig_ba, s, Rw, tw)
    out = Rig(out.cameras, up=np.array([0.0, 0.0, 1.0]), frame_name=str(world["frame"]))
    res = keypoint_residuals(rig_ba, tracks)
    c_sd, r_sd = pose_sd(rig_ba, tracks, joint_of)
    c_sd *= s  # into metres
    report: JsonDict = {
        "seconds": time.perf_counter() - t0,
        "camera_pairs": [{"cameras": [rig.cameras[f.a].name, rig.cameras[f.b].name],
                          "person_pairs": int(len(f.links)), "candidates": f.candidates} for f in fits],
        "people": int(person.max()) + 1,
        "tracks": int(len(tracks.X0)),
        "reprojection_median_px": float(np.median(res)),
        "start_pair": [rig.cameras[first.a].name, rig.cameras[first.b].name],
        "world": world,
        "cameras": {rig.cameras[c].name: {
            "joints_posed_on": joints_used.get(int(c), 0),
            "centre_sd_m": float(c_sd[k]), "rotation_sd_deg": float(r_sd[k]),
            "median_px": float(np.median(res[tracks.cam == k])) if (tracks.cam == k).any() else None}
            for k, c in enumerate(keep)},
    }
    if clocks is not None:
        report["clocks"] = clocks.report()
    given = against_given(out, scene.rig)
    if given is not None:
        report["against_input_calibration"] = given
    return PeopleCalibration(out, report, tracks, poorly_placed(out, c_sd, r_sd), clocks)


def adjust(pv: PersonViews, person: I64, flip: np.ndarray, rig: Rig, cfg: PeopleConfig, rounds: int
           ) -> tuple[Rig, PersonViews, I64, np.ndarray]:
    """``rounds`` bundle adjustments of ``rig`` on its people's joints (module docstring, step 4),
    the people matched again after each through the adjusted rig; with the focal length unknown,
    the joints' rays through the adjusted intrinsics. Returns the rig, the views, the people."""
    ba_cfg = RefineConfig(refine_intrinsics=not cfg.focal_known, refine_distortion=False)
    every = np.ones(len(rig.cameras), bool)
    for _ in range(rounds):
        X = triangulate_people(pv, person, flip, rig.R, rig.t, every)
        tracks, _ = _tracks(pv, person, flip, X, rig, cfg)
        sigma = float(np.median(keypoint_residuals(rig, tracks)))
        rig = ba_keypoints(rig, tracks, every, ba_cfg, max(sigma, 0.5))
        if not cfg.focal_known:
            pv = replace(pv, xy=normalised(pv, rig), f_px=rig.K[:, 0, 0].copy())
        person, flip = people_of(pv, rig_links(pv, rig, cfg))
    return rig, pv, person, flip


def against_given(rig: Rig, given: Rig) -> JsonDict | None:
    """``rig`` beside the ``given`` one (the input's calibration): after the similarity that best
    maps the camera centres (Umeyama), each camera's centre distance (m) and rotation (deg), and
    the similarity's scale; None where the given rig has no poses to compare (its centres within
    1 cm of each other: intrinsics only)."""
    found = centre_similarity(rig, given)
    if found is None:
        return None
    s, R, t = found
    E = np.array([c.center_world for c in rig.cameras])
    T = np.array([given.cameras[given.index(c.name)].center_world for c in rig.cameras])
    centre = np.linalg.norm((s * (R @ E.T)).T + t - T, axis=1)
    per_camera: dict[str, JsonDict] = {}
    out: JsonDict = {"scale_given_over_found": float(s), "cameras": per_camera}
    for c, d in zip(rig.cameras, centre, strict=True):
        Rg = given.cameras[given.index(c.name)].R
        ang = float(np.degrees(np.arccos(np.clip((np.trace((c.R @ R.T).T @ Rg) - 1) / 2, -1, 1))))
        per_camera[c.name] = {"centre_m": float(d), "rotation_deg": ang}
    return out


def poorly_placed(rig: Rig, centre_sd_m: F64, rotation_sd_deg: F64) -> tuple[str, ...]:
    """Warnings for cameras whose centre or rotation sd is 3 times the rig's median and beyond 1 cm
    or 0.1 degree (fewer people, or people only at one side of its view)."""
    out = []
    mc, mr = float(np.nanmedian(centre_sd_m)), float(np.nanmedian(rotation_sd_deg))
    for cam, c, r in zip(rig.cameras, centre_sd_m, rotation_sd_deg, strict=True):
        if (c > 3 * mc and c > 0.01) or (r > 3 * mr and r > 0.1) or not (np.isfinite(c) and np.isfinite(r)):
            out.append(f"camera {cam.name}: placed poorly (centre sd {100 * c:.1f} cm, rotation sd "
                       f"{r:.2f} deg; the rig's median {100 * mc:.1f} cm, {mr:.2f} deg): few people in its "
                       "view, or all at one side of it")
    return tuple(out)


def _tracks(pv: PersonViews, person: I64, flip: np.ndarray, X: F64, rig: Rig, cfg: PeopleConfig
            ) -> tuple[Tracks, I64]:
    """Every person's joint seen by two or more cameras as a track, observations more than
    ``4 pair_px`` off their joint left out; and each observation's joint."""
    m = person >= 0
    idx = np.flatnonzero(m)
    uv = np.where(flip[idx, None, None], pv.uv[idx][:, pv.mirror], pv.uv[idx])  # (n, J, 2) px
    ok = np.where(flip[idx, None], pv.ok[idx][:, pv.mirror], pv.ok[idx])
    Xd = X[person[idx]]  # (n, J, 3)
    proj, _ = project_points(Xd, rig.K, rig.dist, rig.R, rig.t, rig.depth_sign)  # (n, J, C, 2)
    cams = pv.cam[idx]
    pj = proj[np.arange(len(idx)), :, cams]  # (n, J, 2)
    err = np.linalg.norm(pj - uv, axis=-1)
    use = ok & np.isfinite(Xd[..., 0]) & (err < 4 * cfg.pair_px)
    n, j = np.nonzero(use)
    key = person[idx][n] * X.shape[1] + j
    pts, point = np.unique(key, return_inverse=True)
    count = np.bincount(point)
    keep_pt = count >= 2
    sel = keep_pt[point]
    new = np.cumsum(keep_pt) - 1
    X0 = X.reshape(-1, 3)[pts[keep_pt]]
    times = np.zeros(len(X0), np.int64)
    return Tracks(X0, times, new[point[sel]], cams[n[sel]], uv[n[sel], j[sel]]), j[sel]


def pose_sd(rig: Rig, tracks: Tracks, joint: I64, min_kinds: int = 5) -> tuple[F64, F64]:
    """Per camera the sd of its centre (rig units) and of its rotation (deg), the people's joints
    held where they were triangulated: a jackknife over the joint types (its pose fitted again
    without each in turn; Efron & Stein 1981). A detector places each joint type with a bias of
    its own in each view (an elbow on the sleeve's edge, an ankle on the shoe), the same in every
    frame: thousands of observations of ~15 joint types are ~15 independent errors, which a
    per-observation ``s^2 (J^T J)^-1`` would count as thousands (on Shelf it gives 0.1 cm where the
    camera is 1-3 cm from Shelf's calibration). NaN with fewer than ``min_kinds`` joint types seen."""
    from scipy.optimize import least_squares  # heavy to import (scipy): only where it runs
    from scipy.spatial.transform import Rotation

    C = len(rig.cameras)
    c_sd, r_sd = np.full(C, np.nan), np.full(C, np.nan)
    for c, cam in enumerate(rig.cameras):
        m = tracks.cam == c
        kinds = np.unique(joint[m])
        if len(kinds) < min_kinds:
            continue
        X, uv, jt = tracks.X0[tracks.point[m]], tracks.uv[m], joint[m]

        def resid(p: F64, X: F64, uv: F64, c: int = c) -> F64:
            R = Rotation.from_rotvec(p[:3]).as_matrix()
            px, _ = project_points(X, rig.K[c : c + 1], rig.dist[c : c + 1], R[None], p[None, 3:])
            return np.nan_to_num((px[:, 0] - uv).reshape(-1), nan=0.0)

        p0 = np.r_[Rotation.from_matrix(cam.R).as_rotvec(), cam.t]
        fits = []
        for k in kinds:
            use = jt != k
            fits.append(least_squares(resid, p0, args=(X[use], uv[use]), loss="soft_l1", f_scale=3.0).x)
        P = np.array(fits)  # (K, 6)
        n = len(P)
        rot = Rotation.from_rotvec(P[:, :3]) * Rotation.from_rotvec(p0[:3]).inv()
        dr = rot.as_rotvec()  # (K, 3) small turns from the full fit
        ctr = np.array([-Rotation.from_rotvec(p[:3]).as_matrix().T @ p[3:] for p in P])
        r_sd[c] = float(np.degrees(np.sqrt((n - 1) / n * np.sum((dr - dr.mean(0)) ** 2) / 3)))
        c_sd[c] = float(np.sqrt((n - 1) / n * np.sum((ctr - ctr.mean(0)) ** 2) / 3))
    return c_sd, r_sd


def people_world(X: F64, sk: Skeleton, rig: Rig, cfg: PeopleConfig) -> tuple[float, F64, F64, JsonDict]:
    """The similarity ``X' = s Rw X + tw`` into the people's world (module docstring, step 5) of
    their joints ``X (n, J, 3)`` of the skeleton ``sk``, and what it rests on. Up and the floor
    are the skeleton's (its file's ``up`` and ``floor`` joints)."""
    ix = {j: i for i, j in enumerate(sk.joints)}

    def mid(*names: str) -> F64:
        pts = [X[:, ix[n]] for n in names if n in ix]
        if not pts:
            return np.full((len(X), 3), np.nan)
        with warnings.catch_warnings():  # a person with none of them seen: NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            return np.nanmean(np.stack(pts), axis=0)

    top_name = next((n for n in sk.up if n not in cfg.skip_joints), None)
    on_floor = [n for n in sk.floor if n not in cfg.skip_joints]
    if top_name is None or not on_floor:
        raise InputError("--skeleton", f"{sk.name} names no joints that point up and none on the floor (a "
                                       "skeleton file's up and floor): a rig from people needs them to "
                                       "find up and the floor")
    top = mid(top_name)
    feet = mid(*on_floor)
    v = top - feet
    v = v[np.all(np.isfinite(v), axis=1)]
    if len(v) < 10:
        raise InputError("people", f"{len(v)} people with both {top_name} and their floor joints seen: "
                                   "too few to find up")
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    up = np.median(v, axis=0)
    up /= np.linalg.norm(up)
    canon = sk.canonical()
    floor_h = float(np.mean(canon[[ix[n] for n in on_floor], 2]))  # the floor joints' canonical height
    bones = sk.bones
    meas = np.linalg.norm(X[:, bones[:, 0]] - X[:, bones[:, 1]], axis=-1)  # (n, K)
    ref = np.linalg.norm(canon[bones[:, 0]] - canon[bones[:, 1]], axis=-1)  # (K,)
    if cfg.height_m is not None:
        # the canonical body's neck-to-ankle height over its standing height, times theirs
        stand = (canon[ix[top_name], 2] - floor_h) / _CANON_HEIGHT_M
        scale = float(cfg.height_m * stand / np.nanmedian((top - feet) @ up))
        how = f"the people's median height, {cfg.height_m} m (--height)"
    else:
        ratio = ref[None, :] / meas
        use = (ref > 0.15) & np.isfinite(ratio).any(0)
        scale = float(np.nanmedian(ratio[:, use]))
        how = ("typical adult bone lengths (the skeleton's canonical body): median over "
               f"{int(np.isfinite(ratio[:, use]).sum())} bones seen")
    # floor: the ankles' height in the canonical body below their median height
    heights = np.concatenate([X[:, ix[n]] @ up for n in on_floor])
    floor = float(np.nanmedian(heights)) - floor_h / scale
    centre = np.nanmean(feet, axis=0)
    centre = centre - (centre @ up - floor) * up
    cam0 = rig.cameras[0].center_world - centre
    x = cam0 - (cam0 @ up) * up
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    Rw = np.stack([x, y, up])  # world_from_people rows
    tw = -scale * Rw @ centre
    return scale, Rw, tw, {
        "frame": "the people's world: z up (from how they stand), z = 0 the floor (their ankles), "
                 "origin their mean position on it, x towards the first camera; metres from " + how,
        "scale_from": how, "people_frames": int(len(v)),
    }

