"""Object-frame rows: the dense, batched form every estimator works on.

An object has a row for every frame of the scene's frame grid from its first to
its last annotation (also where no camera sees it). Rows are sorted by frame, then
object, so the rows of one frame are one contiguous slice: a filter steps all
objects of a frame as one batch.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from gt3dkit.types import B8, F64, I64, Scene


def usable_edges(box_xyxy_px: F64, wh: F64, clip_tol_px: float) -> B8:
    """Which box edges carry information.

    An edge within ``clip_tol_px`` of the image border (or beyond it) may have been
    clipped by the border: it only says the object reaches at least that far, so it
    is masked.

    Parameters
    ----------
    box_xyxy_px : (..., C, 4) float64, NaN = no box
    wh : (C, 2) image width and height

    Returns
    -------
    (..., C, 4) bool
    """
    lo = box_xyxy_px[..., :2] > clip_tol_px
    hi = box_xyxy_px[..., 2:] < (wh - 1.0 - clip_tol_px)
    return np.concatenate([lo, hi], axis=-1) & np.isfinite(box_xyxy_px)


@dataclass(frozen=True)
class Rows:
    """Attributes (``R`` rows, ``T`` frames, ``O`` objects, ``C`` cameras, ``J`` joints).

    frames : (T,) frame numbers; obj_ids : (O,) object ids
    row_t, row_o : (R,) frame index, object index
    prev_row, next_row : (R,) the same object's row in the previous/next frame, -1 at ends
    t_start : (T+1,) rows of frame t are ``t_start[t]:t_start[t+1]``
    box_z : (R, C, 4) boxes (NaN missing); box_mask : (R, C, 4) usable edges
    kpt_z : (R, C, J, 2) keypoints (NaN missing)
    kpt_conf : (R, C, J) detector confidence in (0, 1] (1 where the input gives none)
    obs_row : (R, C) row of ``scene.obs`` or -1
    seen_at : (R, C) when each view was taken, in frames after its row's frame (a camera on its
        own clock, :attr:`gt3dkit.types.Observations.frame_offset`; 0 where none or no view)
    """

    frames: I64
    obj_ids: I64
    row_t: I64
    row_o: I64
    prev_row: I64
    next_row: I64
    t_start: I64
    box_z: F64
    box_mask: B8
    kpt_z: F64
    kpt_conf: F64
    obs_row: I64
    seen_at: F64

    @functools.cached_property
    def n_views(self) -> I64:
        """(R,) cameras with an annotation of each row (computed once: QA asks per row)."""
        return (self.obs_row >= 0).sum(axis=1)

    def __len__(self) -> int:
        return len(self.row_t)


def build_rows(scene: Scene, clip_tol_px: float = 1.0) -> Rows:
    obs = scene.obs
    frames = np.asarray(scene.frames, dtype=np.int64)
    t_of = np.searchsorted(frames, obs.frame)
    obj_ids, o_of = np.unique(obs.track_id, return_inverse=True)
    O, T, C = len(obj_ids), len(frames), len(scene.rig.cameras)
    first = np.full(O, T, dtype=np.int64)
    last = np.full(O, -1, dtype=np.int64)
    np.minimum.at(first, o_of, t_of)
    np.maximum.at(last, o_of, t_of)
    alive = (np.arange(T)[:, None] >= first[None, :]) & (np.arange(T)[:, None] <= last[None, :])
    row_t, row_o = np.nonzero(alive)  # sorted by t then o
    R = len(row_t)
    row_of = np.full((T, O), -1, dtype=np.int64)
    row_of[row_t, row_o] = np.arange(R)
    prev_row = np.where(row_t > 0, row_of[np.maximum(row_t - 1, 0), row_o], -1)
    prev_row[row_t == 0] = -1
    next_row = np.where(row_t < T - 1, row_of[np.minimum(row_t + 1, T - 1), row_o], -1)
    next_row[row_t == T - 1] = -1
    t_start = np.searchsorted(row_t, np.arange(T + 1))
    r_of = row_of[t_of, o_of]
    J = obs.n_joints
    box_z = np.full((R, C, 4), np.nan)
    kpt_z = np.full((R, C, J, 2), np.nan)
    obs_row = np.full((R, C), -1, dtype=np.int64)
    box_z[r_of, obs.cam] = obs.box_xyxy_px
    kpt_z[r_of, obs.cam] = obs.kpt_uv_px
    kpt_conf = np.ones((R, C, J))
    if obs.kpt_conf is not None:
        kpt_conf[r_of, obs.cam] = np.where(np.isfinite(obs.kpt_conf), obs.kpt_conf, 1.0)
    obs_row[r_of, obs.cam] = np.arange(len(obs))
    seen_at = np.zeros((R, C))
    if obs.frame_offset is not None:
        seen_at[r_of, obs.cam] = obs.frame_offset
    box_mask = usable_edges(box_z, scene.rig.wh, clip_tol_px)
    return Rows(frames=frames, obj_ids=obj_ids, row_t=row_t, row_o=row_o, prev_row=prev_row,
                next_row=next_row, t_start=t_start, box_z=box_z, box_mask=box_mask,
                kpt_z=kpt_z, kpt_conf=kpt_conf, obs_row=obs_row, seen_at=seen_at)


def replicate_rows(rows: Rows, sel: np.ndarray, copies: int) -> tuple[Rows, I64, I64]:
    """``copies`` independent copies of the rows ``sel`` as one set of rows (copy ``k`` of
    object ``o`` is object ``k * O + o``; a row whose neighbour is not in ``sel`` has none).

    Returns the new rows, ``src (R',)`` the original row of each new row and ``copy (R',)``
    its copy. Used to run one filter pass for several noise settings at once.
    """
    O, n = len(rows.obj_ids), len(sel)
    kk = np.repeat(np.arange(copies), n)
    rr = np.tile(sel, copies)
    tt = rows.row_t[rr]
    oo = rows.row_o[rr] + kk * O
    order = np.lexsort((oo, tt))  # by frame, then object: the layout build_rows makes
    pos = np.empty(copies * n, dtype=np.int64)
    pos[order] = np.arange(copies * n)
    in_sel = np.full(len(rows), -1, dtype=np.int64)
    in_sel[sel] = np.arange(n)

    def link(other: I64) -> I64:  # a neighbour outside ``sel`` is no neighbour
        j = np.where(other[rr] >= 0, in_sel[np.maximum(other[rr], 0)], -1)
        return np.where(j >= 0, pos[kk * n + np.maximum(j, 0)], -1)[order]

    src = rr[order]
    new = Rows(frames=rows.frames, obj_ids=np.tile(rows.obj_ids, copies), row_t=tt[order],
               row_o=oo[order], prev_row=link(rows.prev_row), next_row=link(rows.next_row),
               t_start=np.searchsorted(tt[order], np.arange(len(rows.frames) + 1)),
               box_z=rows.box_z[src], box_mask=rows.box_mask[src], kpt_z=rows.kpt_z[src],
               kpt_conf=rows.kpt_conf[src], obs_row=rows.obs_row[src], seen_at=rows.seen_at[src])
    return new, src, kk[order]


def nearest_same_object(rows: Rows, ok: np.ndarray) -> np.ndarray:
    """(R,) for each row the nearest row (in frames) of the same object where ``ok``; the row
    itself where ok. Rows of objects with no ok row map to themselves."""
    R = len(rows)
    out = np.arange(R)
    order = np.lexsort((rows.row_t, rows.row_o))
    o_sorted = rows.row_o[order]
    starts = np.flatnonzero(np.r_[True, o_sorted[1:] != o_sorted[:-1]])
    ends = np.r_[starts[1:], R]
    for a, b in zip(starts, ends, strict=True):
        mine = order[a:b]
        good = mine[ok[mine]]
        if good.size == 0 or good.size == mine.size:
            continue
        d = np.abs(rows.row_t[good][None, :] - rows.row_t[mine][:, None])
        out[mine] = good[np.argmin(d, axis=1)]
    return out


def regrouped(rows: Rows, new_id: I64) -> tuple[Rows, I64]:
    """The rows :func:`build_rows` makes of the same annotations under other ids, laid out from
    these (the same frames; every annotated object-frame under one new id): ``new_id (R,)`` each
    annotated row's new id (unannotated rows' are not read). A new object's rows span its first
    to its last annotated frame (rows of the old object between two of its new ones, where no
    camera saw it, have none). Returns the rows and each one's row here ``(R',)``."""
    T = len(rows.frames)
    seen = np.flatnonzero((rows.obs_row >= 0).any(axis=1))
    ids, inv = np.unique(new_id[seen], return_inverse=True)
    N = len(ids)
    first = np.full(N, T, np.int64)
    last = np.full(N, -1, np.int64)
    np.minimum.at(first, inv, rows.row_t[seen])
    np.maximum.at(last, inv, rows.row_t[seen])
    old = np.zeros(N, np.int64)
    old[inv] = rows.row_o[seen]  # each new object's old one
    row_of = np.full((T, len(rows.obj_ids)), -1, np.int64)
    row_of[rows.row_t, rows.row_o] = np.arange(len(rows))
    span = last - first + 1
    n_of = np.repeat(np.arange(N), span)
    t_of = np.repeat(first, span) + np.arange(span.sum()) - np.repeat(np.cumsum(span) - span, span)
    order = np.lexsort((n_of, t_of))  # by frame, then object: build_rows' layout
    row_t, row_o = t_of[order], n_of[order]
    src = row_of[row_t, old[row_o]]
    R = len(row_t)
    new_of = np.full((T, N), -1, np.int64)
    new_of[row_t, row_o] = np.arange(R)
    prev_row = np.where(row_t > 0, new_of[np.maximum(row_t - 1, 0), row_o], -1)
    next_row = np.where(row_t < T - 1, new_of[np.minimum(row_t + 1, T - 1), row_o], -1)
    return Rows(frames=rows.frames, obj_ids=ids.astype(np.int64), row_t=row_t, row_o=row_o, prev_row=prev_row,
                next_row=next_row, t_start=np.searchsorted(row_t, np.arange(T + 1)), box_z=rows.box_z[src],
                box_mask=rows.box_mask[src], kpt_z=rows.kpt_z[src], kpt_conf=rows.kpt_conf[src],
                obs_row=rows.obs_row[src], seen_at=rows.seen_at[src]), src
