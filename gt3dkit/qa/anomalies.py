"""Annotation QA: score every input annotation against the robust estimate, flag the bad ones.

Every score is in units of the noise level the run estimated from the data (box edges per
kind, keypoints per joint and confidence) or in metres, so a noisy label set is judged by its
own standard, and every threshold is in :class:`QAConfig`. Kinds (``OUT/anomalies.csv``):

``shifted_box``      a box whose edges disagree with the estimate's tangent box (the other views);
                     where it fits another object's box in that view, the row names it
``size_outlier``     a box in the right place but much larger or smaller than the object's own
``cut_box``          a box whose edges that disagree with the estimate all fall short of it, inside
                     the box of an object nearer that camera: drawn around the visible part
                     (a detector's box, an annotator's), it ends where the nearer one begins.
                     Not an annotation error; listed so that the edges are known
``keypoint_outlier`` a keypoint far from the estimate's projection
``swapped_joints``   a left/right pair that fits the estimate exchanged in one view
``identity_split``   an id whose views place it, from this frame on, where it cannot have got to
                     since its last multi-view frame: the id is split into pieces, each estimated
                     on its own (:mod:`gt3dkit.fusion.preparation.identity`)
``world_frame``      an object standing below the floor or floating above it
``missing_view``     an object-frame seen by two or more views whose estimate projects well
                     inside another camera's image, in front of it and not covered by a nearer
                     object's projection, where that camera has annotations within two frames
                     but none of this object
``cut_edges``        a camera some of whose box edges lie inside a nearer object's box and were
                     left out, as edges at the image border are (the boxes are drawn around the
                     visible part of each person, and such edges vary clearly more than the
                     others: :mod:`gt3dkit.fusion.preparation.occlusion`); one row per camera, with counts
``time_offset``      a camera whose annotations fit the estimate clearly better when read a
                     frame or more earlier or later (an unsynchronised camera); one row per
                     camera, with the best whole-frame shift and the residual at every shift
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeAlias

import numpy as np

from gt3dkit.arrays import lookup_rows
from gt3dkit.geom.camera import project_points
from gt3dkit.geom.conics import covered_fraction, cut_edges, model_boxes
from gt3dkit.qa.view import ExchangeView, PreparedView, RowsView, SplitView
from gt3dkit.types import BOX_EDGES, F64, Scene, TrackSet


@dataclass(frozen=True)
class QAConfig:
    box_sigmas: float = 8.0  # a box edge this many noise levels off is flagged
    size_ratio: float = 1.6  # area ratio beyond which a well-placed box is a size outlier
    kpt_sigmas: float = 8.0  # a keypoint this many noise levels off is flagged
    swap_gain: float = 0.35  # swapped pair cost below this fraction of the unswapped one
    floor_tol_m: float = 0.2  # people stand on the floor when their bottoms' median is within
    below_floor_m: float = 0.3
    floating_m: float = 0.5
    inside_margin: float = 0.02  # missing_view: the box this fraction of the image inside its edges
    covered_max: float = 0.3  # ... and at most this fraction of it covered by nearer objects
    cover_depth_tol_m: float = 0.5  # ... counting as nearer those less than this much farther
    cut_depth_tol_m: float = 0.3  # cut_box: an object at least this much nearer cuts a box
    min_box_px: float = 12.0  # ... and at least this tall
    max_offset_frames: int = 3  # time_offset: shifts tried, in frames, each way
    offset_gain: float = 0.6  # flagged when the best shift's median residual is below this
    offset_sigmas: float = 2.0  # fraction of the unshifted one and the unshifted one is above
    #                             this many times the cameras' median residual


#: One flagged annotation: frame, camera ("" for all), id ("" for all), joint or "", kind,
#: score, detail (anomalies.csv's columns).
AnomalyRow: TypeAlias = tuple[int, str, int | str, int | str, str, float, str]


@dataclass
class Anomalies:
    rows: list[AnomalyRow]

    def counts(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for r in self.rows:
            out[r[4]] = out.get(r[4], 0) + 1
        return dict(sorted(out.items()))


def track_row_of(tracks: TrackSet, rows: RowsView) -> np.ndarray:
    """(R,) the row of ``tracks`` estimating each object-frame of ``rows`` (-1: none)."""
    return lookup_rows(np.stack([tracks.frame, tracks.track_id], 1),
                       np.stack([rows.frames[rows.row_t], rows.obj_ids[rows.row_o]], 1))


def _iou(a: F64, b: F64) -> F64:
    w = np.clip(np.minimum(a[..., 2], b[..., 2]) - np.maximum(a[..., 0], b[..., 0]), 0, None)
    h = np.clip(np.minimum(a[..., 3], b[..., 3]) - np.maximum(a[..., 1], b[..., 1]), 0, None)
    inter = w * h
    return inter / np.maximum(_area(a) + _area(b) - inter, 1e-9)


def _area(box: F64) -> F64:
    """``(...)`` areas of boxes ``(..., 4)`` (xmin, ymin, xmax, ymax)."""
    return (box[..., 2] - box[..., 0]) * (box[..., 3] - box[..., 1])


def find_anomalies(scene: Scene, tracks: TrackSet, pre: PreparedView, cfg: QAConfig | None = None,
                   splits: Sequence[SplitView] = (), exchanges: Sequence[ExchangeView] = ()) -> Anomalies:
    """Every flagged annotation of ``scene`` against ``tracks`` (see the module docstring), and
    each place an id was split (``splits``, :func:`gt3dkit.fusion.preparation.identity.identity_segments`)
    and each pair of ids whose labels were exchanged (``exchanges``: one row per id)."""
    cfg = cfg or QAConfig()
    rows, cams = pre.rows, pre.cams
    names = scene.rig.names
    out: list[AnomalyRow] = []
    r_of = track_row_of(tracks, rows)
    have = r_of >= 0
    idx = np.flatnonzero(have)
    # every estimated object-frame's tangent box in every camera: (n, C, 4), margin (n, C)
    box, margin = model_boxes(tracks.center_world[r_of[idx]], tracks.semi_axes[r_of[idx]], cams)
    frame_of = rows.frames[rows.row_t]
    id_of = rows.obj_ids[rows.row_o]

    _identity_rows(splits, exchanges, out)
    if pre.use_box and have.any():
        _box_rows(pre, cfg, names, idx, box, margin, frame_of, id_of, out)

    if pre.use_kpt and have.any() and tracks.kpt_world.shape[1]:
        _keypoints(scene, tracks, pre, cfg, r_of, have, frame_of, id_of, out)

    out += [(first, "", i, "", "undetermined_person", float(n),
             f"its {n} detections (frames {first}-{last}, cameras {cams}) are never seen by two cameras at "
             "once that agree: left out of the estimate") for i, first, last, n, cams in scene.left_out]
    _cut_edges(scene, pre, out)
    _world_frame(scene, tracks, cfg, out)
    _missing_views(scene, tracks, pre, cfg, out, r_of, box, margin)
    out = _with_time_offsets(scene, tracks, pre, cfg, out)
    out.sort(key=lambda x: (x[0], str(x[2]), x[1], str(x[3]), x[4]))
    return Anomalies(out)


def _identity_rows(splits: Sequence[SplitView], exchanges: Sequence[ExchangeView], out: list[AnomalyRow]
                   ) -> None:
    """The rows of each place an id was split and each pair of ids whose labels were exchanged
    (:func:`find_anomalies`)."""
    for s in splits:
        if s.given:
            out.append((s.frame_after, "", s.track_id, "", "identity_split", s.distance_m,
                        f"piece {s.segment} of this id from here, as the corrections file (segments) "
                        f"says: its {s.views_after} views place it {s.distance_m:.2f} m from where "
                        f"{s.views_before} views put it in frame {s.frame_before}"))
            continue
        out.append((s.frame_after, "", s.track_id, "", "identity_split", s.distance_m,
                    f"its {s.views_after} views place it {s.distance_m:.2f} m from where {s.views_before} "
                    f"views put it in frame {s.frame_before} ({s.speed_mps:.1f} m/s; allowed "
                    f"{s.limit_m:.2f} m): piece {s.segment} of this id from here, estimated on its own "
                    "(another person, or a mis-keyed id)"))
    for e in exchanges:
        for me, other, d, v in ((e.track_id, e.other_id, e.distance_m[0], e.views[0]),
                                (e.other_id, e.track_id, e.distance_m[1], e.views[1])):
            out.append((e.frame, "", me, "", "identity_exchange", d,
                        f"exchanged with id {other}: its {v} views place it {d:.2f} m from where id "
                        f"{other} was, and id {other} where it was; both ids are split here "
                        "(identity_split)"))


def _box_rows(pre: PreparedView, cfg: QAConfig, names: list[str], idx: np.ndarray, box: F64, margin: F64,
              frame_of: np.ndarray, id_of: np.ndarray, out: list[AnomalyRow]) -> None:
    """The flagged boxes (``cut_box``, ``size_outlier``, ``shifted_box``) of the rows ``idx`` that
    have an estimate, against its tangent boxes ``box (n, C, 4)`` at depth ``margin (n, C)``
    (:func:`find_anomalies`)."""
    rows = pre.rows
    z = rows.box_z[idx]
    usable = rows.box_mask[idx] & np.isfinite(z)
    sd = np.asarray(pre.sigma_box) * np.sqrt(pre.box_tail)  # the whole level (misfit tails in)
    zs = np.where(usable, np.abs(box - z) / sd[None, None, :], 0.0)
    score = zs.max(axis=2)  # (n, C)
    iou = _iou(box, z)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = _area(z) / _area(box)
        size = np.sqrt(np.maximum(_area(box), 1e-9))
        off = np.hypot((z[..., 0] + z[..., 2] - box[..., 0] - box[..., 2]) / 2,
                       (z[..., 1] + z[..., 3] - box[..., 1] - box[..., 3]) / 2) / size
    bad = (score > cfg.box_sigmas) & usable.any(axis=2)
    cut, by = _cut_by_nearer(bad, z, box, margin, rows.row_t[idx], cfg)
    for n, c in zip(*np.nonzero(bad), strict=True):
        r = idx[n]
        detail = (f"IoU {iou[n, c]:.2f} with the estimate's box; area ratio {ratio[n, c]:.2f}; "
                  f"largest edge residual {score[n, c]:.1f} sigma")
        off_edges = usable[n, c] & (zs[n, c] > cfg.box_sigmas)
        inward = np.sign(z[n, c] - box[n, c]) == [1, 1, -1, -1]  # the label smaller on that side
        if not (off_edges & ~(cut[n, c] & inward)).any():  # every edge off: cut short by a nearer one
            k = idx[by[n, c]]
            which = ", ".join(BOX_EDGES[e] for e in np.flatnonzero(off_edges))
            out.append((int(frame_of[r]), names[c], int(id_of[r]), "", "cut_box",
                        round(float(score[n, c]), 2),
                        f"{detail}; its edge{'s' if off_edges.sum() > 1 else ''} {which} inside the box "
                        f"of object {int(id_of[k])}, {margin[n, c] - margin[by[n, c], c]:.1f} m nearer "
                        f"this camera: the drawn box ends where the nearer object begins, not shifted"))
            continue
        other = _other_objects_box(n, c, z, box, rows.row_t[idx], iou[n, c])
        if other is not None:
            detail += (f"; it fits object {int(id_of[idx[other[0]]])}'s box in this view (IoU "
                       f"{other[1]:.2f}): that object's box under this id?")
        sized = (ratio[n, c] > cfg.size_ratio or ratio[n, c] < 1 / cfg.size_ratio) and off[n, c] < 0.25
        kind = "size_outlier" if sized else "shifted_box"
        out.append((int(frame_of[r]), names[c], int(id_of[r]), "", kind, round(float(score[n, c]), 2),
                    detail))


def _with_time_offsets(scene: Scene, tracks: TrackSet, pre: PreparedView, cfg: QAConfig,
                       out: list[AnomalyRow]) -> list[AnomalyRow]:
    """``out`` with each unsynchronised camera's row (:func:`_time_offsets`) in place of its
    per-view flags, which follow from the offset (:func:`find_anomalies`)."""
    offsets: list[AnomalyRow] = []
    _time_offsets(scene, tracks, pre, cfg, offsets)
    if offsets:  # an unsynchronised camera's views all look wrong: one row says why
        cams_off = {r[1] for r in offsets}
        per_view = ("shifted_box", "size_outlier", "missing_view", "keypoint_outlier", "swapped_joints")
        dropped = [r for r in out if r[1] in cams_off and r[4] in per_view]
        out = [r for r in out if not (r[1] in cams_off and r[4] in per_view)]
        for r in offsets:
            n = sum(1 for d in dropped if d[1] == r[1])
            out.append(r[:6] + (r[6] + (f"; {n} per-view flags of this camera left out (they follow from "
                                        "the offset)" if n else ""),))
    return out


def _cut_edges(scene: Scene, pre: PreparedView, out: list[AnomalyRow]) -> None:
    """One ``cut_edges`` row per camera with edges left out as cut by a nearer object, saying
    which: each object's frames and edge kinds (:func:`which_cut`)."""
    cut = pre.box_cut
    if cut is None:
        return
    rows = pre.rows
    for c in np.flatnonzero(cut.any(axis=(0, 2))):
        per = cut[:, c]  # (R, 4)
        boxes = per.any(axis=1)
        n_boxes = int(np.isfinite(rows.box_z[:, c, 0]).sum())
        kinds = ", ".join(f"{k} {int(n)}" for k, n in zip(BOX_EDGES, per.sum(axis=0), strict=True) if n)
        out.append((int(rows.frames[rows.row_t[np.flatnonzero(boxes)[0]]]), scene.rig.names[c], "", "",
                    "cut_edges", round(float(boxes.sum() / max(n_boxes, 1)), 3),
                    f"{int(per.sum())} edges of {int(boxes.sum())} of its {n_boxes} boxes ({kinds}) lie "
                    "inside the box of a nearer object and vary clearly more than the others: the boxes are "
                    "drawn around the visible part, so these edges say where the nearer one is; left out, as "
                    "edges at the image border are (meta.json: preparation, boxes, cut_edges). Which: "
                    + which_cut(rows.obj_ids[rows.row_o], rows.frames[rows.row_t], per,
                                _cutters(pre, int(c)))))


def _cutters(pre: PreparedView, c: int) -> np.ndarray | None:
    """``(R, 4)`` in camera ``c`` the id of a nearer object each left-out edge lies in (-1
    elsewhere), or None where the preparation does not say."""
    by = pre.box_cut_by
    if by is None:
        return None
    rows = pre.rows
    return np.where(by[:, c] >= 0, rows.obj_ids[rows.row_o[np.maximum(by[:, c], 0)]], -1)


def which_cut(obj_id: np.ndarray, frame: np.ndarray, cut: np.ndarray, by: np.ndarray | None = None) -> str:
    """The boxes with an edge in ``cut (R, 4)`` (of the rows of objects ``obj_id (R,)`` in frames
    ``frame (R,)``), by object: its frames as runs of consecutive frames, the kinds of its cut
    edges and, given ``by (R, 4)`` (the id of a nearer object each cut edge lies in, -1 none), the
    objects they lie in: e.g. ``id 2 frames 50-57, 60 (ymax; inside id 3); id 3 frames 12 (xmin,
    ymax; inside ids 1, 4)``. Consecutive: one frame step apart, the step the most common gap
    between the frames."""
    rows = np.flatnonzero(cut.any(axis=1))
    steps = np.diff(np.unique(frame))
    step = int(np.bincount(steps).argmax()) if len(steps) else 1
    said = []
    for i in np.unique(obj_id[rows]):
        mine = rows[obj_id[rows] == i]
        f = np.sort(frame[mine])
        starts = np.flatnonzero(np.r_[True, np.diff(f) > step])
        ends = np.r_[starts[1:], len(f)] - 1
        runs = ", ".join(str(f[a]) if a == b else f"{f[a]}-{f[b]}" for a, b in zip(starts, ends, strict=True))
        kinds = ", ".join(k for k, on in zip(BOX_EDGES, cut[mine].any(axis=0), strict=True) if on)
        near = np.unique(by[mine][cut[mine] & (by[mine] >= 0)]) if by is not None else np.zeros(0)
        inside = (f"; inside id{'s' if len(near) > 1 else ''} {', '.join(str(int(n)) for n in near)}"
                  if len(near) else "")
        said.append(f"id {int(i)} frames {runs} ({kinds}{inside})")
    return "; ".join(said)


#: A flagged label that overlaps another object's estimated box at least this much (and more
#: than its own) is named as that object's box (:func:`_other_objects_box`).
OTHER_BOX_IOU = 0.5


def _other_objects_box(n: int, c: int, label: F64, box: F64, frame_ix: np.ndarray, own_iou: float
                       ) -> tuple[int, float] | None:
    """The other object of label ``n``'s frame whose estimated box in camera ``c`` the label fits
    best, with that IoU, when it is at least :data:`OTHER_BOX_IOU` and above the label's IoU with
    its own object's box (a detector's box of the nearer of two people given the farther one's
    id); else None. ``label``, ``box (n, C, 4)``, ``frame_ix (n,)`` as in :func:`find_anomalies`."""
    m = np.flatnonzero((frame_ix == frame_ix[n]) & (np.arange(len(frame_ix)) != n))
    if not m.size:
        return None
    with np.errstate(invalid="ignore"):
        v = np.nan_to_num(_iou(box[m, c], label[n, c][None]))
    k = int(np.argmax(v))
    return (int(m[k]), float(v[k])) if v[k] >= OTHER_BOX_IOU and v[k] > own_iou else None


def _cut_by_nearer(bad: np.ndarray, label: F64, box: F64, depth: F64, frame_ix: np.ndarray, cfg: QAConfig
                   ) -> tuple[np.ndarray, np.ndarray]:
    """For the flagged labels ``bad (n, C)``: which of their edges lie inside a nearer object's
    estimated box (:func:`gt3dkit.geom.conics.cut_edges`; ``label``, ``box (n, C, 4)``, ``depth
    (n, C)`` of the estimated object-frames, ``frame_ix (n,)`` their frame), ``(n, C, 4)``, and the
    index into ``n`` of the object that cuts them, ``(n, C)`` (-1: none). Only the frames with a
    flag are looked at."""
    cut = np.zeros(label.shape, bool)
    by = np.full(bad.shape, -1, dtype=np.int64)
    for f in np.unique(frame_ix[bad.any(axis=1)]):
        m = np.flatnonzero(frame_ix == f)
        c_m, w_m = cut_edges(label[m], box[m], depth[m], cfg.cut_depth_tol_m)
        cut[m], by[m] = c_m, np.where(w_m >= 0, m[np.maximum(w_m, 0)], -1)
    return cut, by


def _keypoints(scene: Scene, tracks: TrackSet, pre: PreparedView, cfg: QAConfig, r_of: np.ndarray,
               have: np.ndarray, frame_of: np.ndarray, id_of: np.ndarray,
               out: list[AnomalyRow]) -> None:
    rows, cams = pre.rows, pre.cams
    names = scene.rig.names
    skel = pre.skeleton  # the preparation's (the scene's own, or the one its joints' count names)
    joints = skel.joints if skel is not None else ()
    ix = {j: i for i, j in enumerate(joints)}
    pairs = [(ix[a], ix[b]) for a, b in skel.left_right] if skel is not None else []
    idx = np.flatnonzero(have)
    X = tracks.kpt_world[r_of[idx]]  # (n, J, 3)
    uv, _ = project_points(X, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)  # (n, J, C, 2)
    uv = np.swapaxes(uv, 1, 2)  # (n, C, J, 2)
    z = rows.kpt_z[idx]  # (n, C, J, 2)
    sd = np.sqrt(pre.kpt_var[idx])  # (n, C, J)
    err = np.linalg.norm(uv - z, axis=-1)  # (n, C, J)
    score = err / sd
    bad = np.isfinite(score) & (score > cfg.kpt_sigmas)
    for i, j in pairs:  # swapped pairs: one row instead of two outliers
        swapped = np.linalg.norm(uv[:, :, i] - z[:, :, j], axis=-1) + np.linalg.norm(uv[:, :, j] - z[:, :, i],
                                                                                      axis=-1)
        plain = err[:, :, i] + err[:, :, j]
        sw = (bad[:, :, i] | bad[:, :, j]) & np.isfinite(swapped) & (swapped < cfg.swap_gain * plain)
        for n, c in zip(*np.nonzero(sw), strict=True):
            r = idx[n]
            out.append((int(frame_of[r]), names[c], int(id_of[r]), int(i), "swapped_joints",
                        round(float(max(score[n, c, i], score[n, c, j])), 2),
                        f"{joints[i]} and {joints[j]} exchanged: {plain[n, c]:.1f} px apart as labelled, "
                        f"{swapped[n, c]:.1f} px exchanged"))
        bad[:, :, i] &= ~sw
        bad[:, :, j] &= ~sw
    for n, c, j in zip(*np.nonzero(bad), strict=True):
        r = idx[n]
        out.append((int(frame_of[r]), names[c], int(id_of[r]), int(j), "keypoint_outlier",
                    round(float(score[n, c, j]), 2),
                    f"{err[n, c, j]:.1f} px from the estimate's projection ({score[n, c, j]:.1f} sigma)"
                    + _at_other_joint(uv[n, c], z[n, c, j], float(err[n, c, j]), j, joints)))


def _at_other_joint(uv: F64, label: F64, err: float, j: int, joints: tuple[str, ...]) -> str:
    """Where an outlying label of joint ``j`` (``err`` px from its own projection) lies at most
    half as far from another joint's projection (``uv (J, 2)``, the estimate's joints in that
    view): a clause naming that joint (a labeller or a model that put one joint on another, a
    far-side haunch on the near one); else empty."""
    d = np.linalg.norm(uv - label, axis=-1)
    d[j] = np.inf
    k = int(np.argmin(np.nan_to_num(d, nan=np.inf)))
    if not (np.isfinite(d[k]) and d[k] <= 0.5 * err):
        return ""
    return f"; {d[k]:.1f} px from {joints[k]}'s: labelled at {joints[k]}?"


def _world_frame(scene: Scene, tracks: TrackSet, cfg: QAConfig, out: list[AnomalyRow]) -> None:
    """Objects under the floor or floating, where the people of the scene stand on the floor."""
    up = scene.rig.up
    if tracks.kpt_world.shape[1] and np.isfinite(tracks.kpt_world).any():
        h = np.where(np.isfinite(tracks.kpt_world[..., 0]), tracks.kpt_world @ up, np.inf)
        bottom = h.min(axis=1)
    else:
        bottom = tracks.center_world @ up - tracks.semi_axes[:, 2]
    ok = np.isfinite(bottom)
    if not ok.any() or abs(float(np.median(bottom[ok]))) > cfg.floor_tol_m:
        return  # the scene's people do not stand on z = 0 along up: no floor to judge by
    for i in np.unique(tracks.track_id):
        m = ok & (tracks.track_id == i)
        if not m.any():
            continue
        b = float(np.median(bottom[m]))
        if b < -cfg.below_floor_m or b > cfg.floating_m:
            f = int(tracks.frame[m][0])
            out.append((f, "", int(i), "", "world_frame", round(abs(b), 3),
                        f"stands {abs(b):.2f} m {'below' if b < 0 else 'above'} the floor (median "
                        "over its frames)"))


def _missing_views(scene: Scene, tracks: TrackSet, pre: PreparedView, cfg: QAConfig, out: list[AnomalyRow],
                   r_of: np.ndarray, box: F64, margin: F64) -> None:
    """``r_of`` (R,) :func:`track_row_of`; ``box``,
    ``margin`` the tangent boxes of the rows ``r_of >= 0`` in every camera."""
    rows, cams = pre.rows, pre.cams
    names = scene.rig.names
    ok = r_of >= 0  # every estimated object can hide another; only those seen twice are judged
    if not (ok & (rows.n_views >= 2)).any():
        return
    idx = np.flatnonzero(ok)
    centres = np.stack([c.center_world for c in scene.rig.cameras])  # (C, 3)
    depth = np.linalg.norm(tracks.center_world[r_of[idx]][:, None, :] - centres[None], axis=-1)
    depth = np.where(margin > 0, depth, np.nan)
    W, H = cams.wh[:, 0], cams.wh[:, 1]
    m = cfg.inside_margin * np.maximum(W, H)
    inside = (margin > 0) & (box[..., 0] > m) & (box[..., 1] > m) & (box[..., 2] < W - m) \
        & (box[..., 3] < H - m) & (box[..., 3] - box[..., 1] > cfg.min_box_px) \
        & (box[..., 2] > box[..., 0]) & np.isfinite(box).all(-1)  # a folded projection is no box
    unannotated = rows.obs_row[idx] < 0  # (n, C)
    cand = inside & unannotated & (rows.n_views[idx] >= 2)[:, None]
    if not cand.any():
        return
    t_of = rows.row_t[idx]
    # the camera annotates something within 2 frames (else that stretch is not annotated there)
    cam_frame = np.zeros((len(rows.frames), len(names)), bool)
    np.logical_or.at(cam_frame, rows.row_t, rows.obs_row >= 0)
    near = cam_frame.copy()
    for k in (1, 2):
        near[k:] |= cam_frame[:-k]
        near[:-k] |= cam_frame[k:]
    cand &= near[t_of]
    # every object of the frame can cover: use all rows of that frame with an estimate
    for t in np.unique(t_of[cand.any(axis=1)]):
        sel = np.flatnonzero(t_of == t)
        cov = covered_fraction(box[sel], depth[sel], cfg.cover_depth_tol_m)
        for k, c in zip(*np.nonzero(cand[sel] & (cov <= cfg.covered_max)), strict=True):
            n = sel[k]
            r = idx[n]
            b = box[n, c]
            out.append((int(rows.frames[t]), names[c], int(rows.obj_ids[rows.row_o[r]]), "", "missing_view",
                        round(float(1 - cov[k, c]), 2),
                        f"seen by {int(rows.n_views[r])} other views; projects to "
                        f"({b[0]:.0f}, {b[1]:.0f})-({b[2]:.0f}, {b[3]:.0f}) px inside the image, "
                        f"{100 * cov[k, c]:.0f}% covered by nearer objects, not annotated"))


def offset_residuals(tracks: TrackSet, pre: PreparedView, max_shift: int) -> tuple[np.ndarray, F64]:
    """Per camera and shift s in -max_shift..max_shift frames, the median residual (px) of
    that camera's annotations against the estimate ``s`` frame steps later: (shifts,
    (C, S) medians, NaN where too few pairs)."""
    rows, cams = pre.rows, pre.cams
    C = len(cams.K)
    shifts = np.arange(-max_shift, max_shift + 1)
    med = np.full((C, len(shifts)), np.nan)
    track_keys = np.stack([tracks.frame, tracks.track_id], 1)
    frames = rows.frames
    for k, s in enumerate(shifts):
        t2 = rows.row_t + s
        valid = (t2 >= 0) & (t2 < len(frames))
        r_of = np.full(len(rows), -1, dtype=np.int64)
        r_of[valid] = lookup_rows(track_keys,
                                  np.stack([frames[t2[valid]], rows.obj_ids[rows.row_o[valid]]], 1))
        idx = np.flatnonzero(r_of >= 0)
        if not len(idx):
            continue
        parts = []
        if pre.use_box:
            box, _ = model_boxes(tracks.center_world[r_of[idx]], tracks.semi_axes[r_of[idx]], cams)
            e = np.where(rows.box_mask[idx], np.abs(box - rows.box_z[idx]), np.nan)
            parts.append(e)
        if pre.use_kpt and tracks.kpt_world.shape[1]:
            uv, _ = project_points(tracks.kpt_world[r_of[idx]], cams.K, cams.dist, cams.R, cams.t,
                                   cams.depth_sign)
            parts.append(np.linalg.norm(np.swapaxes(uv, 1, 2) - rows.kpt_z[idx], axis=-1))
        e = np.concatenate(parts, axis=2)  # (n, C, m)
        for c in range(C):
            v = e[:, c].ravel()
            v = v[np.isfinite(v)]
            if v.size >= 20:
                med[c, k] = float(np.median(v))
    return shifts, med


def _time_offsets(scene: Scene, tracks: TrackSet, pre: PreparedView, cfg: QAConfig,
                  out: list[AnomalyRow]) -> None:
    if len(pre.rows.frames) < 2 * cfg.max_offset_frames + 3 or cfg.max_offset_frames < 1:
        return
    shifts, med = offset_residuals(tracks, pre, cfg.max_offset_frames)
    zero = int(np.flatnonzero(shifts == 0)[0])
    # the residual level of the cameras as given (the noise levels the run estimated include
    # an unsynchronised camera's misfit, so they are not the reference)
    noise = float(np.nanmedian(med[:, zero])) if np.isfinite(med[:, zero]).any() else np.inf
    names = scene.rig.names
    first = int(pre.rows.frames[0])
    for c in range(len(names)):
        m = med[c]
        if not np.isfinite(m[zero]) or not np.isfinite(m).sum() >= 3:
            continue
        best = int(np.nanargmin(m))
        if best == zero or not (m[best] < cfg.offset_gain * m[zero] and m[zero] > cfg.offset_sigmas * noise):
            continue
        off = int(shifts[best])
        step = float(np.median(np.diff(pre.rows.frames)))
        out.append((first, names[c], "", "", "time_offset", round(float(m[zero] / m[best]), 2),
                    f"its annotations fit the estimate best {off:+d} frame steps later "
                    f"({off * step / scene.fps:+.3f} s): "
                    f"median residual {m[zero]:.1f} px as given, {m[best]:.1f} px shifted "
                    f"(per shift {', '.join(f'{s:+d}: {v:.1f}' for s, v in zip(shifts, m, strict=True))})"))
