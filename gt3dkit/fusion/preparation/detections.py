"""People from per-frame keypoint detections without identities (OpenPose, a COCO detector):
:func:`associate_detections` groups each frame's detections across cameras by how well they
triangulate, and links the groups over time; the result is an
:class:`gt3dkit.fusion.preparation.associate.Association` like the tracklets' (``association.csv``)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.preparation.associate import Association, AssociationRow, finish_association
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.triangulate import normalized_points, triangulate_dlt
from gt3dkit.types import F64, I64, Observations, Scene


@dataclass(frozen=True)
class DetectionConfig:
    """Per-frame detections (no ids) -> people."""

    max_reproj_px: float = 25.0  # two detections are one person when their common joints,
    #                              triangulated from the two views, reproject this close (median)
    min_joints: int = 4  # common confident joints needed to compare two detections
    min_conf: float = 0.3
    max_speed_mps: float = 4.0  # a person's centroid moves at most this fast between frames
    link_margin_m: float = 0.3
    max_gap_s: float = 1.0  # a person unseen longer than this is a new track when seen again


#: The notes of the detections left out (``association.csv``): no second view confirms the
#: detection, or a camera's second detection of a person (:func:`_one_per_person`).
UNCONFIRMED = "no second view confirms it: left out"
SECOND_DETECTION = "a second detection of a person in this camera: left out"

#: Detection pairs whose costs are computed at once (:func:`pair_costs`): ``(pairs, J, 4, 4)`` arrays.
PAIR_CHUNK = 8192


def frame_pairs(frame: np.ndarray, cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Every pair of rows ``a < b`` of one frame and different cameras, frame by frame, in row
    order (``frame (N,)`` sorted, ``cam (N,)``): ``(P,)`` each."""
    out_a, out_b = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]])
    ends = np.r_[starts[1:], len(frame)]
    for n in np.unique(ends - starts):  # frames with n rows together
        lo = starts[(ends - starts) == n]
        i, j = np.triu_indices(int(n), 1)
        out_a.append((lo[:, None] + i).reshape(-1))
        out_b.append((lo[:, None] + j).reshape(-1))
    a, b = np.concatenate(out_a), np.concatenate(out_b)
    order = np.lexsort((b, a))
    a, b = a[order], b[order]
    keep = cam[a] != cam[b]
    return a[keep], b[keep]


def pair_costs(xy: F64, a: np.ndarray, b: np.ndarray, cam: np.ndarray, Pw: F64, f_px: F64,
               min_joints: int) -> F64:
    r"""For each pair of detections ``a, b (P,)`` (rows of ``xy (N, J, 2)``, undistorted normalised
    joints, NaN = not confident, seen by the cameras ``cam (N,)`` whose ``[R | t]`` are ``Pw (C, 3,
    4)`` and focal lengths ``f_px (C,)``): the median over the joints both saw of the two-view
    reprojection error (px, the RMS of the two views) after triangulating each joint from the two
    views (DLT, the rows of :func:`gt3dkit.geom.triangulate.triangulate_dlt`); ``inf`` with fewer
    than ``min_joints`` such joints, NaN where an error is undefined. ``(P,)``, in chunks of
    :data:`PAIR_CHUNK` pairs."""
    out = np.full(len(a), np.inf)
    for lo in range(0, len(a), PAIR_CHUNK):
        s = slice(lo, lo + PAIR_CHUNK)
        xa, xb = xy[a[s]], xy[b[s]]
        ok = np.isfinite(xa).all(axis=-1) & np.isfinite(xb).all(axis=-1)  # (p, J)
        n = ok.sum(axis=1)
        use = n >= min_joints
        if not use.any():
            continue
        ok, n = ok[use], n[use]
        x2 = np.stack([xa[use], xb[use]], axis=2)  # (p, J, 2 views, 2)
        x2 = np.where(ok[..., None, None], x2, 0.0)
        views = np.stack([cam[a[s]], cam[b[s]]], 1)[use]  # (p, 2)
        proj = Pw[views][:, None]  # (p, 1, 2, 3, 4) the two views' projection matrices
        rows_x = x2[..., 0, None] * proj[..., 2, :] - proj[..., 0, :]  # (p, J, 2, 4)
        rows_y = x2[..., 1, None] * proj[..., 2, :] - proj[..., 1, :]
        A = np.concatenate([rows_x, rows_y], axis=2)
        # A's smallest right singular vector: the eigenvector of A^T A's smallest eigenvalue
        # (a batched 4x4 eigh is 5x faster than the SVD; the same point to rounding)
        Xh = np.linalg.eigh(np.swapaxes(A, -1, -2) @ A)[1][..., 0]
        X = Xh[..., :3] / Xh[..., 3:]  # (p, J, 3)
        Xc = np.einsum("pvij,pnj->pnvi", proj[:, 0, :, :, :3], X) + proj[:, 0, None, :, :, 3]  # (p, J, 2, 3)
        z = Xc[..., 2]
        d = Xc[..., :2] / z[..., None] - x2
        e2 = np.where(z > 0, np.sum(d * d, axis=-1) * f_px[views][:, None] ** 2, np.inf)
        e = np.sqrt(np.nanmean(e2, axis=-1))  # (p, J)
        out[np.flatnonzero(use) + lo] = _masked_median(e, ok, n)
    return out


#: Rows of consecutive frames whose pairs are costed together (:func:`_consistent_pairs`).
FRAME_ROWS = 4096


FramePairs = tuple[int, np.ndarray, list[tuple[float, int, int]], set[tuple[int, int]]]


def _consistent_pairs(obs: Observations, xy: F64, Pw: F64, f_px: F64, cfg: DetectionConfig
                      ) -> Iterator[FramePairs]:
    """Per frame (in order): its rows, its pairs of views within ``cfg.max_reproj_px``,
    ``(cost, a, b)``: the pairs with ``2 * cfg.min_joints`` confident joints in common or more
    first, then the rest, each best first (:func:`pair_costs`, over runs of whole frames of
    about :data:`FRAME_ROWS` rows: a long recording's pairs are never all held at once). A pair
    of a few joints (a partial skeleton: a leg) agrees with many more detections than it should
    and, grouped first, kept a whole detection of that person from the person's other views
    (real Shelf, frame 6: a leg in one view took the person's view in another into a second id);
    and the pairs compared (``cfg.min_joints`` in common) and beyond ``cfg.max_reproj_px``."""
    frames, start = np.unique(obs.frame, return_index=True)
    end = np.r_[start[1:], len(obs.frame)]
    seen = np.isfinite(xy[..., 0])  # (N, J) the confident joints
    k = 0
    while k < len(frames):
        k1 = max(int(np.searchsorted(start, start[k] + FRAME_ROWS, side="right")), k + 1)
        lo, hi = int(start[k]), int(end[k1 - 1])
        a, b = frame_pairs(obs.frame[lo:hi], obs.cam[lo:hi])
        a, b = a + lo, b + lo
        cost = pair_costs(xy, a, b, obs.cam, Pw, f_px, cfg.min_joints)
        common = (seen[a] & seen[b]).sum(axis=1)
        good = cost <= cfg.max_reproj_px
        against = ~good & (common >= cfg.min_joints)  # compared, and they disagree
        at = np.asarray(np.searchsorted(a, np.r_[start[k:k1], hi]))  # each frame's pairs
        for q in range(k, k1):
            s = np.arange(at[q - k], at[q - k + 1])
            g = s[good[s]]
            weak = common[g] < 2 * cfg.min_joints  # a few joints in common
            order = g[np.lexsort((b[g], a[g], cost[g], weak))]  # the well-supported pairs first
            bad = s[against[s]]
            yield (int(frames[q]), np.arange(start[q], end[q]),
                   list(zip(cost[order].tolist(), a[order].tolist(), b[order].tolist(), strict=True)),
                   set(zip(a[bad].tolist(), b[bad].tolist(), strict=True)))
        k = k1


def _masked_median(e: F64, ok: np.ndarray, n: np.ndarray) -> F64:
    """``(p,)`` the median of each row of ``e (p, J)`` over its ``ok`` entries (``n (p,)`` of them,
    at least one): NaN where one of them is NaN, as ``np.median``."""
    srt = np.sort(np.where(ok, e, np.inf), axis=1)  # the ok entries first (NaN after every inf)
    r = np.arange(len(e))
    lo, hi = srt[r, (n - 1) // 2], srt[r, n // 2]
    med = np.where(n % 2 == 1, lo, (lo + hi) / 2.0)
    return np.where(np.any(ok & np.isnan(e), axis=1), np.nan, med)


def _flat(v: F64, up: F64) -> float:
    """|v| on the floor plane (the component along ``up`` removed)."""
    return float(np.linalg.norm(v - (v @ up) * up))


def _frame_groups(rows: np.ndarray, pairs: list[tuple[float, int, int]], against: set[tuple[int, int]],
                  cam: I64, xy: F64, cams: Cams) -> tuple[list[tuple[list[int], F64, float]], list[int]]:
    """One frame's detections ``rows`` grouped greedily by their consistent ``pairs`` (in the
    order given; one detection per camera; no two detections of a group compared and found to
    disagree, ``against``: two views with too few joints in common to compare, a partial
    skeleton and a view of the other side, neither join nor part a group;
    :func:`_one_per_person`): per group of two or more views its members, the median of its
    triangulated joints (m) and its pairs' mean cost (px); and the detections left out as a
    camera's second of a person."""
    cost_of = {(a, b): c for c, a, b in pairs}
    group = {int(r): {int(r)} for r in rows}
    for _, a, b in pairs:
        ga, gb = group[a], group[b]
        if ga is gb:
            continue
        if {cam[r] for r in ga} & {cam[r] for r in gb}:
            continue
        if any((min(r, q), max(r, q)) in against for r in ga for q in gb):
            continue
        merged = ga | gb
        for r in merged:
            group[r] = merged
    groups, dropped = _one_per_person(list({id(g): g for g in group.values()}.values()), cost_of, cam,
                                      np.isfinite(xy[..., 0]))
    found = []
    for g in groups:
        if len(g) < 2:
            continue
        members = sorted(g)
        cs = [cams.take(np.array([cam[r] for r in members]))]
        X, _ = triangulate_dlt(np.stack([xy[r] for r in members], axis=1), cs[0].R, cs[0].t)
        if not np.isfinite(X).all(axis=1).any():
            continue
        centroid = np.nanmedian(X[np.isfinite(X).all(axis=1)], axis=0)
        pc = [cost_of[(min(r, q), max(r, q))] for r in members for q in members
              if r < q and (min(r, q), max(r, q)) in cost_of]
        found.append((members, centroid, float(np.mean(pc))))
    return found, dropped


def _one_per_person(groups: list[set[int]], cost_of: dict[tuple[int, int], float], cam: I64,
                    seen: np.ndarray, shared_joints: int = 2) -> tuple[list[set[int]], list[int]]:
    """The groups with every two that are one person split by a detector merged. OpenPose can
    find one person in a view as two skeletons (the upper body and the legs), and the
    one-detection-per-camera rule then makes two groups of that person. Two groups are one
    person when, in every camera they share, their two detections have at most
    ``shared_joints`` joints in common (``seen (N, J)``: the confident joints; two people's
    skeletons share most), and most pairs of their detections in different cameras (two at
    least, half of them) are consistent (two people a step apart have none: their views do not
    triangulate together; a partial skeleton may lack the joints to compare with one view). The
    merged group keeps the larger group's detections and the other's in cameras it lacks; the
    other's in the shared cameras are left out (returned)."""
    def consistent(a: set[int], b: set[int]) -> bool:
        parts = all((seen[r] & seen[q]).sum() <= shared_joints for r in a for q in b if cam[r] == cam[q])
        cross = [(min(r, q), max(r, q)) for r in a for q in b if cam[r] != cam[q]]
        agree = sum(k in cost_of for k in cross)
        return parts and agree >= 2 and 2 * agree >= len(cross)

    groups = list(groups)
    dropped: list[int] = []
    k = 0
    while k < len(groups):
        cams_k = {int(cam[r]) for r in groups[k]}
        m = next((m for m in range(k + 1, len(groups))
                  if cams_k & {int(cam[r]) for r in groups[m]} and consistent(groups[k], groups[m])), None)
        if m is None:
            k += 1
            continue
        a, b = groups[k], groups.pop(m)
        if len(b) > len(a):  # the larger group keeps its views (the merged one keeps a's place)
            a, b = b, a
        have = {int(cam[r]) for r in a}
        dropped += [r for r in b if int(cam[r]) in have]
        groups[k] = a | {r for r in b if int(cam[r]) not in have}
    return groups, dropped


@dataclass
class _Track:
    """A person linked over frames: its id, the last frame it was seen in, its centroid there."""

    id: int
    frame: int
    X: F64


def _linked(tracks: list[_Track], found: list[tuple[list[int], F64, float]], f: int, scene: Scene,
            cfg: DetectionConfig) -> dict[int, _Track]:
    """The tracks alive at frame ``f`` (seen within ``cfg.max_gap_s``) each group of ``found``
    continues: the assignment of least floor-plane distance between a track's last centroid and
    a group's, gated by a walking speed."""
    from scipy.optimize import linear_sum_assignment

    alive = [t for t in tracks if (f - t.frame) / scene.fps <= cfg.max_gap_s]
    taken: dict[int, _Track] = {}
    if alive and found:
        # on the floor plane: the joints a frame sees move a median centroid up and down
        D = np.array([[_flat(t.X - g[1], scene.rig.up) for g in found] for t in alive])
        gate = np.array([cfg.max_speed_mps * (f - t.frame) / scene.fps + cfg.link_margin_m
                         for t in alive])
        D = np.where(D <= gate[:, None], D, 1e9)
        ri, ci = linear_sum_assignment(D)
        for i, j in zip(ri, ci, strict=True):
            if D[i, j] < 1e9:
                taken[j] = alive[i]
    return taken


def associate_detections(scene: Scene, cfg: DetectionConfig | None = None,
                         overrides: dict[tuple[str, int, int | None], int] | None = None) -> Association:
    """People from per-frame keypoint detections without identities (OpenPose): per frame,
    detections of different cameras whose confident joints triangulate consistently (the
    two-view reprojection error) are grouped greedily, best pair first, one detection per
    camera, every pair of a group consistent; groups of two or more views are triangulated and
    linked over time by their centroid on the floor plane (Hungarian, gated by a walking speed);
    detections no second view confirms are left out (their row has global id -1)."""
    cfg = cfg or DetectionConfig()
    obs = scene.obs
    names = scene.rig.names
    cams = Cams.of(scene.rig)
    f_px = cams.K[:, 0, 0]
    conf = obs.kpt_conf if obs.kpt_conf is not None else np.ones(obs.kpt_uv_px.shape[:2])
    kp = np.where((conf >= cfg.min_conf)[..., None], obs.kpt_uv_px, np.nan)
    xy = np.full(kp.shape, np.nan)
    for c in np.unique(obs.cam):
        m = obs.cam == c
        xy[m] = normalized_points(kp[m][:, :, None, :], cams.K[c:c + 1], cams.dist[c:c + 1])[:, :, 0]
    gid = np.full(len(obs), -1, dtype=np.int64)
    gconf = np.full(len(obs), np.nan)
    twice = np.zeros(len(obs), bool)  # a camera's second detection of a person
    tracks: list[_Track] = []
    next_id = 0
    with np.errstate(all="ignore"):
        Pw = np.concatenate([cams.R, cams.t[:, :, None]], axis=2)  # (C, 3, 4)
        for f, rows, pairs, against in _consistent_pairs(obs, xy, Pw, f_px, cfg):
            found, dropped = _frame_groups(rows, pairs, against, obs.cam, xy, cams)
            twice[dropped] = True
            taken = _linked(tracks, found, f, scene, cfg)
            for j, (members, centroid, pc) in enumerate(found):
                t = taken.get(j)
                if t is None:
                    t = _Track(next_id, f, centroid)
                    tracks.append(t)
                    next_id += 1
                t.frame, t.X = f, centroid
                gid[members] = t.id
                gconf[members] = float(np.clip(1 - pc / cfg.max_reproj_px, 0, 1))
    rows_out: list[AssociationRow] = []
    for r in range(len(obs)):
        rows_out.append((names[int(obs.cam[r])], int(obs.track_id[r]), int(obs.frame[r]), int(gid[r]),
                         float(gconf[r]), 1, np.nan,
                         "" if gid[r] >= 0 else SECOND_DETECTION if twice[r] else UNCONFIRMED))
    return finish_association(rows_out, overrides)
