"""Cross-view identity association: per-camera tracklets -> global identities.

Per-camera annotation tasks (MOT files, CVAT tasks) number people per camera. A *tracklet* is
one (camera, local id); its geometry per frame is where a box's bottom-centre ray meets the
floor (up . X = 0, the plane every layout's people stand on), i.e. the ground homography the
UKF initialises with. Tracklets are merged greedily, closest first (average linkage: the median
over the frames both see of the distance between the two clusters' mean ground points), while

* the median distance is at most :attr:`AssocConfig.max_ground_m` over at least
  :attr:`AssocConfig.min_common_frames` common frames, and
* a cluster never holds two tracklets of one camera that overlap in time (one person is one
  box per view), so two people walking side by side stay two.

Tracklets no other view confirms stay their own (single-view) identities; bystanders seen by
one camera are therefore separate people, never merged into the subject. Boxes whose bottom
edge touches the image border carry no ground point (the feet are cut off): a tracklet made of
those joins the cluster whose vertical axis the rays through its box centres pass closest to,
when that is within :attr:`AssocConfig.max_axis_m` and clearly the best.

The mapping is :class:`Association` (``association.csv``: ``camera,local_id,global_id,
confidence,frames,median_m,note``); a user's edited copy passed back (``--association FILE``)
overrides the rows it lists.
"""

from __future__ import annotations

import csv
import dataclasses
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TypeAlias

import numpy as np

from gt3dkit.arrays import unique_rows
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import Cams, pixel_rays, project_points
from gt3dkit.parse import parse_frame, parse_int, read_csv_rows
from gt3dkit.skeletons import skeleton_of
from gt3dkit.types import F64, I64, Observations, Scene

COLUMNS = ("camera", "local_id", "frame", "global_id", "confidence", "frames", "median_m", "note")


@dataclass(frozen=True)
class AssocConfig:
    max_ground_m: float = 0.8  # clusters this far apart (median over common frames) stay apart
    min_common_frames: int = 2
    border_px: float = 2.0  # a box bottom this close to the image edge has no ground point
    min_ray_sin: float = 0.17  # ... nor one whose ray meets the floor at less than 10 degrees
    min_camera_m: float = 0.3  # ... nor one seen by a camera less than this high above the floor
    max_axis_m: float = 0.4  # a track without ground points joins the cluster whose vertical axis
    #                          its box-centre rays pass this close to (and twice closer than any other)


#: One row of an association (:class:`Association`).
AssociationRow: TypeAlias = tuple[str, int, int | None, int, float, int, float, str]
#: The user's global ids by (camera name, local id, frame or None).
Overrides: TypeAlias = dict[tuple[str, int, int | None], int]


@dataclass(frozen=True)
class Association:
    """rows: (camera name, local id, frame (per-frame detections) or None (a per-camera track),
    global id (-1: left out), confidence in [0, 1] (NaN: single view), frames annotated, median
    ground distance to the rest of its cluster in m (NaN), note)."""

    rows: tuple[AssociationRow, ...]

    def mapping(self) -> dict[tuple[str, int, int | None], int]:
        return {(r[0], r[1], r[2]): r[3] for r in self.rows}

    def write(self, path: Path) -> None:
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(COLUMNS)
            for r in self.rows:
                w.writerow([r[0], r[1], "" if r[2] is None else r[2], r[3],
                            "" if not np.isfinite(r[4]) else f"{r[4]:.3f}", r[5],
                            "" if not np.isfinite(r[6]) else f"{r[6]:.3f}", r[7]])

    def summary(self) -> str:
        kept = [r for r in self.rows if r[3] >= 0]
        g = {r[3] for r in kept}
        if any(r[2] is not None for r in self.rows):
            out = len(self.rows) - len(kept)
            return (f"{len(self.rows)} detections -> {len(g)} people"
                    + (f" ({out} left out: seen by one camera only, or a camera's second detection of a "
                       "person)" if out else ""))
        single = len(g - {r[3] for r in kept if np.isfinite(r[4])})
        return (f"{len(self.rows)} per-camera tracks -> {len(g)} people ({single} seen by one camera "
                "only)")


def box_or_keypoint_box(box: F64, kpt: F64) -> F64:
    """(N, 4) each row's box, or where it has none the box around its keypoints (NaN if
    fewer than 3)."""
    out = box.copy()
    need = ~np.isfinite(box).all(axis=1)
    if need.any() and kpt.shape[1]:
        k = kpt[need]
        n = np.isfinite(k[..., 0]).sum(axis=1)
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            kb = np.stack([np.nanmin(k[..., 0], axis=1), np.nanmin(k[..., 1], axis=1),
                           np.nanmax(k[..., 0], axis=1), np.nanmax(k[..., 1], axis=1)], axis=1)
        out[need] = np.where((n >= 3)[:, None], kb, np.nan)
    return out


def _box_foot(scene: Scene, box: F64) -> F64:
    """(N, 2) the point of each box on the image direction of world-down through its centre
    (the bottom centre for an upright camera; the top for one mounted upside down)."""
    obs = scene.obs
    cams = Cams.of(scene.rig)
    out = np.full((len(obs), 2), np.nan)
    ok = np.isfinite(box).all(axis=1)
    for c in np.unique(obs.cam[ok]):
        m = np.flatnonzero(ok & (obs.cam == c))
        ctr = np.stack([(box[m, 0] + box[m, 2]) / 2, (box[m, 1] + box[m, 3]) / 2], axis=1)
        sub = cams.take(np.array([c]))
        o, d = pixel_rays(ctr[:, None, :], sub.K, sub.dist, sub.R, sub.t, sub.depth_sign)
        X = o[0] + 5.0 * d[:, 0]  # a point on the ray, 5 m out
        uv, _ = project_points(np.stack([X, X - 0.5 * cams.up]), sub.K, sub.dist, sub.R, sub.t,
                               sub.depth_sign)
        v = uv[1, :, 0] - uv[0, :, 0]  # (n, 2) image direction of world-down
        v /= np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
        half = np.stack([(box[m, 2] - box[m, 0]) / 2, (box[m, 3] - box[m, 1]) / 2], axis=1)
        # from the centre along v to the box's edge
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.min(np.where(np.abs(v) > 1e-9, half / np.abs(v), np.inf), axis=1)
        out[m] = ctr + s[:, None] * v
    return out


def ground_points(scene: Scene, cfg: AssocConfig) -> F64:
    """(N, 3) where each observation's foot pixel (a box's bottom centre, else the mean of its
    ankle/heel/toe keypoints) ray meets the floor (NaN: none, at the image's bottom border, ray
    parallel to or away from the floor)."""
    obs = scene.obs
    cams = Cams.of(scene.rig)
    out = np.full((len(obs), 3), np.nan)
    b = obs.box_xyxy_px
    foot = _box_foot(scene, b)  # where the box meets the person's axis on the floor side
    skel = skeleton_of(scene)
    if obs.n_joints and skel is not None:  # the mean of the foot joints seen, when there are
        js = [i for i, j in enumerate(skel.joints)
              if j.split("_", 1)[-1] in ("ankle", "heel", "big_toe", "small_toe")]
        if js:
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                kf = np.nanmean(obs.kpt_uv_px[:, js], axis=1)
            # a pose without its feet: its box (often the keypoints' extent) ends at the knees
            posed = np.isfinite(obs.kpt_uv_px[..., 0]).sum(axis=1) >= 3
            foot[posed] = kf[posed]
    ok = np.isfinite(foot).all(axis=1) & (foot[:, 1] < cams.wh[obs.cam, 1] - cfg.border_px)
    for c in np.unique(obs.cam[ok]):
        m = np.flatnonzero(ok & (obs.cam == c))
        uv = foot[m][:, None, :]
        sub = cams.take(np.array([c]))
        origin, d = pixel_rays(uv, sub.K, sub.dist, sub.R, sub.t, sub.depth_sign)
        o, d = origin[0], d[:, 0]
        den = d @ cams.up
        with np.errstate(divide="ignore", invalid="ignore"):
            s = -(o @ cams.up) / den
        # a camera near or under the floor, or a ray grazing it, places feet metres off
        good = np.isfinite(s) & (s > 0) & (-den > cfg.min_ray_sin) & (o @ cams.up > cfg.min_camera_m)
        out[m[good]] = o + s[good, None] * d[good]
    return out


def _axis_distances(scene: Scene, tl: np.ndarray, t_of: np.ndarray, T: int, F: int
                    ) -> Callable[[int, F64], F64]:
    """A function (tracklet, (F, 3) ground points of a cluster) -> (F,) horizontal distance (m)
    between the ray through the tracklet's box centre and the cluster's vertical axis."""
    obs = scene.obs
    cams = Cams.of(scene.rig)
    o = np.full((T, F, 3), np.nan)
    d = np.full((T, F, 3), np.nan)
    b = box_or_keypoint_box(obs.box_xyxy_px, obs.kpt_uv_px)
    ok = np.isfinite(b).all(axis=1)
    for c in np.unique(obs.cam[ok]):
        m = np.flatnonzero(ok & (obs.cam == c))
        uv = np.stack([(b[m, 0] + b[m, 2]) / 2, (b[m, 1] + b[m, 3]) / 2], axis=1)[:, None, :]
        sub = cams.take(np.array([c]))
        origin, dirs = pixel_rays(uv, sub.K, sub.dist, sub.R, sub.t, sub.depth_sign)
        o[tl[m], t_of[m]] = origin[0]
        d[tl[m], t_of[m]] = dirs[:, 0]
    up = cams.up

    def dist(t: int, ground: F64) -> F64:
        n = np.cross(d[t], up)  # (F, 3): normal of the plane holding the ray and the up direction
        nn = np.linalg.norm(n, axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.abs(np.einsum("fi,fi->f", ground - o[t], n)) / nn

    return dist


@dataclass
class _Clusters:
    """Tracklets being merged into people: per cluster (indexed by a tracklet of it) the sum and
    the count of its members' ground points per frame ``(T, F, 3)``, ``(T, F)``, the cameras and
    frames it occupies ``(T, C, F)`` and whether it remains ``(T,)``; each tracklet's cluster."""

    sums: F64
    weight: F64
    occ: np.ndarray
    alive: np.ndarray
    member: I64


def _merge_on_ground(cl: _Clusters, cfg: AssocConfig) -> None:
    """Merge the closest two clusters (median ground distance over their common frames, never
    two that share a camera and frame) while within ``cfg.max_ground_m``."""
    sums, weight, occ, alive, member = cl.sums, cl.weight, cl.occ, cl.alive, cl.member
    T = len(member)

    def costs(a: int) -> F64:
        mean_a = sums[a] / np.maximum(weight[a], 1e-12)[:, None]
        mean = sums / np.maximum(weight, 1e-12)[..., None]
        both = (weight[a] > 0)[None] & (weight > 0)
        d = np.where(both, np.linalg.norm(mean - mean_a[None], axis=-1), np.nan)
        n = both.sum(axis=1)
        with np.errstate(all="ignore"):
            med = np.nanmedian(np.where(n[:, None] > 0, d, 0.0), axis=1)
        # a track seen in one frame only can still be placed (from that one frame)
        have = (weight > 0).sum(axis=1)
        need = np.minimum(cfg.min_common_frames, np.minimum(have[a], have))
        bad = (n < np.maximum(need, 1)) | ~alive | (occ & occ[a][None]).any(axis=(1, 2))
        med[bad] = np.inf
        med[a] = np.inf
        return med

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        cost = np.stack([costs(a) for a in range(T)]) if T else np.zeros((0, 0))
        while T > 1:
            a, b = np.unravel_index(int(np.argmin(cost)), cost.shape)
            if not cost[a, b] <= cfg.max_ground_m:
                break
            sums[a] += sums[b]
            weight[a] += weight[b]
            occ[a] |= occ[b]
            alive[b] = False
            member[member == b] = a
            cost[b, :] = cost[:, b] = np.inf
            cost[a] = costs(int(a))
            cost[:, a] = cost[a]


def _join_by_axis(cl: _Clusters, axis_d: Callable[[int, F64], F64], cfg: AssocConfig) -> None:
    """Every tracklet still alone (its foot points may be off, a foot ray grazing the floor)
    joined to the cluster whose vertical axis its box-centre rays pass closest to
    (``axis_d``), when that is within ``cfg.max_axis_m`` and clearly the best."""
    sums, weight, occ, alive, member = cl.sums, cl.weight, cl.occ, cl.alive, cl.member
    T = len(member)
    cut = np.flatnonzero(alive & (np.bincount(member, minlength=T) == 1))
    for t in cut:
        if member[t] != t or (member == t).sum() > 1:
            continue
        cand = []
        for k in np.flatnonzero(alive & (weight.sum(axis=1) >= cfg.min_common_frames)
                                & (np.bincount(member, minlength=T) > 1)):
            if k == t or (occ[k] & occ[t]).any():
                continue
            mean = sums[k] / np.maximum(weight[k], 1e-12)[:, None]
            d = axis_d(int(t), mean)
            if np.isfinite(d).sum() >= cfg.min_common_frames:
                cand.append((float(np.nanmedian(d)), int(k)))
        cand.sort()
        if cand and cand[0][0] <= cfg.max_axis_m and (len(cand) == 1 or cand[1][0] > 2 * cand[0][0]):
            joined = cand[0][1]
            occ[joined] |= occ[t]
            alive[t] = False
            member[member == t] = joined


def _median_to_rest(traj: F64, t: int, others: list[int]) -> float:
    """The median ground distance of tracklet ``t``'s points ``traj (T, F, 3)`` to the mean of
    the ``others`` of its cluster over their common frames (NaN: none)."""
    if not others:
        return np.nan
    rest = np.nansum([np.nan_to_num(traj[u]) for u in others], axis=0)
    cnt = np.sum([np.isfinite(traj[u][:, 0]) for u in others], axis=0)
    both = (cnt > 0) & np.isfinite(traj[t][:, 0])
    if not both.any():
        return np.nan
    return float(np.median(np.linalg.norm(traj[t][both] - rest[both] / cnt[both, None], axis=1)))


def associate(scene: Scene, cfg: AssocConfig | None = None,
              overrides: Overrides | None = None) -> Association:
    """Global identities for the per-camera ids of ``scene.obs`` (see the module docstring)."""
    cfg = cfg or AssocConfig()
    obs = scene.obs
    names = scene.rig.names
    keys, tl = unique_rows(np.stack([obs.cam, obs.track_id], axis=1), return_inverse=True)
    tl = tl.ravel()
    frames, t_of = np.unique(obs.frame, return_inverse=True)
    T, F, C = len(keys), len(frames), len(names)
    g = ground_points(scene, cfg)
    traj = np.full((T, F, 3), np.nan)
    traj[tl, t_of] = g
    occ = np.zeros((T, C, F), bool)
    occ[tl, obs.cam, t_of] = True
    n_frames = occ.any(axis=1).sum(axis=1)
    weight = np.isfinite(traj[..., 0]).astype(float)  # (K, F) members with a ground point
    cl = _Clusters(np.nan_to_num(traj) * weight[..., None], weight, occ, np.ones(T, bool), np.arange(T))
    _merge_on_ground(cl, cfg)
    # tracklets with (almost) no ground point (feet cut off by the image's bottom edge: someone
    # close to the camera) or still alone: joined to the cluster whose vertical axis their
    # box-centre rays pass closest to, when that is clearly the best
    _join_by_axis(cl, _axis_distances(scene, tl, t_of, T, F), cfg)
    member = cl.member
    # per tracklet: median distance to the rest of its cluster (its confidence)
    clusters = np.unique(member)
    order = sorted(clusters, key=lambda k: (int(np.flatnonzero(occ[k].any(axis=0))[0])
                                            if occ[k].any() else F, int(k)))
    gid = {int(k): i for i, k in enumerate(order)}
    rows: list[AssociationRow] = []
    for t in range(T):
        k = int(member[t])
        others = [int(u) for u in np.flatnonzero(member == k) if u != t]
        med = _median_to_rest(traj, t, others)
        conf = float(np.clip(1 - med / cfg.max_ground_m, 0, 1)) if np.isfinite(med) else (
            1.0 if others else np.nan)
        note = "" if others else "seen by this camera only (single view)"
        rows.append((names[int(keys[t, 0])], int(keys[t, 1]), None, gid[k], conf, int(n_frames[t]), med,
                     note))
    return finish_association(rows, overrides)


def finish_association(rows: list[AssociationRow], overrides: Overrides | None) -> Association:
    """The association of ``rows`` (:data:`COLUMNS`), the user's ``overrides`` applied, sorted by
    global id (the left-out, -1, last), frame, camera and local id."""
    if overrides:
        known = {(r[0], r[1], r[2]) for r in rows}
        for key in overrides:
            if key not in known:
                raise InputError("--association", f"camera {key[0]} has no local id {key[1]}"
                                 + (f" in frame {key[2]}" if key[2] is not None else ""))
        note = "set by the association file"
        rows = [(r[0], r[1], r[2], overrides[(r[0], r[1], r[2])], r[4], r[5], r[6], note)
                if (r[0], r[1], r[2]) in overrides else r for r in rows]
    return Association(tuple(sorted(rows, key=lambda r: (r[3] < 0, r[3], -1 if r[2] is None else r[2], r[0],
                                                         r[1]))))


def apply_association(scene: Scene, assoc: Association) -> Scene:
    """``scene`` with every observation's id replaced by its global id; two boxes of one
    global id in one (frame, camera) are an error naming both tracks."""
    obs = scene.obs
    m = assoc.mapping()
    names = scene.rig.names
    per_frame = any(r[2] is not None for r in assoc.rows)
    new = np.array([m.get((names[int(c)], int(i), int(f) if per_frame else None), -1)
                    for f, c, i in zip(obs.frame, obs.cam, obs.track_id, strict=True)], dtype=np.int64)
    if (new < 0).any():  # left out (detections no second view confirms)
        scene = dataclasses.replace(scene, obs=obs.select(new >= 0))
        obs, new = scene.obs, new[new >= 0]
    key = np.stack([obs.frame, obs.cam, new], axis=1)
    u, first, counts = unique_rows(key, return_index=True, return_counts=True)
    if (counts > 1).any():
        k = int(np.flatnonzero(counts > 1)[0])
        f, c, gi = (int(v) for v in u[k])
        both = np.flatnonzero((key == u[k]).all(axis=1))
        raise InputError(obs.origin[both[1]], f"frame {f}, camera {names[c]}: local ids "
                         f"{sorted(int(obs.track_id[b]) for b in both)} are both global id {gi} "
                         "(see the association file)")
    order = np.lexsort((new, obs.cam, obs.frame))
    o2 = Observations(frame=obs.frame[order], cam=obs.cam[order], track_id=new[order],
                      box_xyxy_px=obs.box_xyxy_px[order], kpt_uv_px=obs.kpt_uv_px[order],
                      origin=obs.origin.take(order),
                      kpt_conf=None if obs.kpt_conf is None else obs.kpt_conf[order],
                      frame_offset=None if obs.frame_offset is None else obs.frame_offset[order])
    return dataclasses.replace(scene, obs=o2)


def read_overrides(path: Path, names: Sequence[str]) -> Overrides:
    """An edited ``association.csv`` (``camera,local_id,frame,global_id`` first, ``frame``
    empty for per-camera tracks; other columns ignored): the rows a user fixed."""
    out: dict[tuple[str, int, int | None], int] = {}
    for line, r in read_csv_rows(Path(path), ("camera", "local_id", "frame", "global_id"), warnings=[]):
        where = f"{path}: line {line}"
        if r["camera"] not in names:
            raise InputError(where, f"unknown camera {r['camera']!r} (the input has {', '.join(names)})")
        key = (r["camera"], parse_int(where, r["local_id"], "local_id"),
               parse_frame(where, r["frame"]) if r["frame"] else None)
        if key in out:
            raise InputError(where, f"second row for camera {key[0]} local id {key[1]}")
        out[key] = parse_int(where, r["global_id"], "global_id")
    return out
