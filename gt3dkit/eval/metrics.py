"""Errors of tracks against a scene's truth.

Definitions (metres):

* centre error: 3D distance between estimated and true ellipsoid centres;
* ground error: distance between the centres projected on the ground plane
  (the plane orthogonal to ``up``) - the only error for WILDTRACK/MultiviewX
  positionIDs, which give the ground position alone;
* height error: ``|2c - 2c_true|``, the object's full vertical extent;
* radius error: ``|(a+b)/2 - (a_true+b_true)/2|``, the mean horizontal semi-axis;
* coverage: truth rows with an estimate;
* MOTA / IDF1 / FP / FN / IDs by ``motmetrics``' rules (CLEAR MOT, Bernardin & Stiefelhagen
  2008; IDF1, Ristani et al. 2016; :func:`clear_mot`) on ground positions, a match within 1 m.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple, Protocol

import numpy as np

from gt3dkit.arrays import lookup_rows
from gt3dkit.types import F64, I64, GroundTruth, TrackSet


class FrameIds(Protocol):
    """Rows keyed by (frame, id): a :class:`TrackSet` or a :class:`GroundTruth`."""

    @property
    def frame(self) -> I64: ...

    @property
    def track_id(self) -> I64: ...


def match_rows(tracks: FrameIds, truth: FrameIds) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i_track, i_truth)`` of rows with the same (frame, id), in the tracks' order."""
    at = lookup_rows(np.c_[truth.frame, truth.track_id].astype(np.int64),
                     np.c_[tracks.frame, tracks.track_id].astype(np.int64))
    it = np.flatnonzero(at >= 0)
    return it, at[it]


#: Candidate pairs :func:`near_pairs` expands at once (their arrays a few tens of MB at most).
CANDIDATES_PER_CHUNK = 1 << 20


class NearPairs(NamedTuple):
    """Pairs of a row of table ``a`` and a row of table ``b`` in the same frame (:func:`near_pairs`):
    their rows ``(P,)`` and distance ``(P,)``, metres."""

    a: np.ndarray
    b: np.ndarray
    d: F64

    @staticmethod
    def concat(parts: list[NearPairs]) -> NearPairs:
        """``parts`` one after another (none: no pair)."""
        if not parts:
            return NearPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
        return NearPairs(*(np.concatenate(x) for x in zip(*parts, strict=True)))


def near_pairs(frame_a: np.ndarray, xy_a: F64, frame_b: np.ndarray, xy_b: F64, cutoff: float) -> NearPairs:
    """Every pair of a row of table ``a`` and a row of table ``b`` in the same frame whose
    positions (``(N, D)``, metres) are at most ``cutoff`` apart, with their distance (the norm
    of ``xy_a[a] - xy_b[b]``): grouped by frame in frame order, ``a``'s rows in table order
    within a frame and each one's ``b`` rows in table order. So the pairs of tables cut into
    parts of consecutive frames, each part's found on its own, are the whole tables' pairs in
    the same order (:class:`gt3dkit.eval.tracking.TrackingTally`). Rows with a non-finite
    position pair with none.

    A sweep, not every pair of a frame: ``b``'s rows are sorted by frame and by the coordinate
    that spreads most, and each ``a`` row meets only the ``b`` rows of its frame within
    ``cutoff`` along that coordinate (a superset, then the exact distance). For 26 people a
    frame, 4 000 frames, that was 5 candidates a row instead of 26."""
    xy_a, xy_b = np.asarray(xy_a, float), np.asarray(xy_b, float)
    frame_a, frame_b = np.asarray(frame_a), np.asarray(frame_b)
    ok_a = np.flatnonzero(np.isfinite(xy_a).all(axis=1))
    ok_b = np.flatnonzero(np.isfinite(xy_b).all(axis=1))
    if not len(ok_a) or not len(ok_b):
        return NearPairs(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    ok_a = ok_a[np.argsort(frame_a[ok_a], kind="stable")]  # a's rows by frame, in table order
    lo = np.minimum(xy_a[ok_a].min(axis=0), xy_b[ok_b].min(axis=0))
    axis = int(np.argmax(np.maximum(xy_a[ok_a].max(axis=0), xy_b[ok_b].max(axis=0)) - lo))
    frames = np.union1d(frame_a[ok_a], frame_b[ok_b])
    x_a, x_b = xy_a[ok_a, axis] - lo[axis], xy_b[ok_b, axis] - lo[axis]
    width = float(max(x_a.max(), x_b.max())) + 2.0 * cutoff + 1.0  # the frames' keys never overlap
    key_b = np.searchsorted(frames, frame_b[ok_b]) * width + x_b
    ob = np.argsort(key_b, kind="stable")
    ok_b, key_b = ok_b[ob], key_b[ob]
    key_a = np.searchsorted(frames, frame_a[ok_a]) * width + x_a
    pad = cutoff + 1e-9 * (1.0 + float(np.abs(key_b).max()))  # the keys' rounding: a superset
    start = np.searchsorted(key_b, key_a - pad)
    count = np.searchsorted(key_b, key_a + pad, side="right") - start
    out: list[tuple[np.ndarray, np.ndarray, F64]] = []
    ends = np.cumsum(count)
    k = 0
    while k < len(ok_a):  # chunks of a's rows of about CANDIDATES_PER_CHUNK candidates
        base = ends[k] - count[k]
        k1 = max(int(np.searchsorted(ends, base + CANDIDATES_PER_CHUNK, side="right")), k + 1)
        ia = np.repeat(np.arange(k, k1), count[k:k1])
        ra, rb = ok_a[ia], ok_b[start[ia] + np.arange(len(ia)) - (ends[ia] - count[ia] - base)]
        sq = (xy_a[ra, 0] - xy_b[rb, 0]) ** 2  # as np.linalg.norm sums them
        for c in range(1, xy_a.shape[1]):
            sq += (xy_a[ra, c] - xy_b[rb, c]) ** 2
        d = np.sqrt(sq)
        keep = np.flatnonzero((d <= cutoff) & (frame_a[ra] == frame_b[rb]))
        keep = keep[np.lexsort((rb[keep], ia[keep]))]  # each a row's b rows in table order
        out.append((ra[keep], rb[keep], d[keep]))
        k = k1
    return NearPairs(*(np.concatenate(x) for x in zip(*out, strict=True)))


def frame_blocks(frame: np.ndarray, frames: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A table's rows by frame, for the sorted frame numbers ``frames (F,)``: ``order (N,)`` the
    rows sorted by frame (stable: table order within a frame), ``lo, hi (F,)`` each frame's
    rows ``order[lo:hi]``, and ``pos (N,)`` each row's place among its frame's rows."""
    order = np.argsort(frame, kind="stable")
    f = np.asarray(frame)[order]
    pos = np.empty(len(order), np.int64)
    pos[order] = np.arange(len(order)) - np.searchsorted(f, f)
    return order, np.searchsorted(f, frames), np.searchsorted(f, frames, side="right"), pos


def pair_counts(est_id: np.ndarray, truth_id: np.ndarray, pairs: NearPairs, max_dist_m: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count (n_track_ids, n_truth_ids)``: the frames in which a track and a truth identity are
    within ``max_dist_m`` of each other (``pairs``: the truth's rows ``a`` and the tracks' ``b``
    within at least that, :func:`near_pairs`); and the two id lists."""
    ids, ti = np.unique(est_id, return_inverse=True)
    tids, gi = np.unique(truth_id, return_inverse=True)
    b, a, d = pairs
    near = d <= max_dist_m
    count = np.bincount(ti.ravel()[a[near]] * len(tids) + gi.ravel()[b[near]], minlength=len(ids) * len(tids))
    return count.reshape(len(ids), len(tids)), ids, tids


def ids_to_truth(tracks: TrackSet, truth: GroundTruth, up: F64, max_dist_m: float = 1.0) -> dict[int, int]:
    """Each estimated id's truth id, when the ids are gt3dkit's own (cross-view association):
    the one-to-one assignment maximising the frames in which the two are within ``max_dist_m``
    on the ground plane (IDF1's global identity matching, Ristani et al. 2016)."""
    from scipy.optimize import linear_sum_assignment

    centre = truth.center_world
    if not np.isfinite(centre).any() and truth.kpt_world.shape[1]:  # keypoint truth: the joints' mean
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            centre = np.nanmean(truth.kpt_world, axis=1)
    g_t = ground_coords(centre, up)
    pairs = near_pairs(truth.frame, g_t, tracks.frame, ground_coords(tracks.center_world, up), max_dist_m)
    count, ids, tids = pair_counts(tracks.track_id, truth.track_id, pairs, max_dist_m)
    r, c = linear_sum_assignment(-count)
    return {int(ids[i]): int(tids[j]) for i, j in zip(r, c, strict=True) if count[i, j] > 0}


def relabel_to_truth(tracks: TrackSet, truth: GroundTruth, up: F64, max_dist_m: float = 1.0) -> TrackSet:
    """``tracks`` with its ids replaced by the truth ids :func:`ids_to_truth` assigns (ids left
    unmatched get new ids above every truth id)."""
    import dataclasses

    m = ids_to_truth(tracks, truth, up, max_dist_m)
    top = int(max(np.max(truth.track_id, initial=0), np.max(tracks.track_id, initial=0))) + 1
    extra = {int(i): top + k for k, i in enumerate(sorted(set(np.unique(tracks.track_id).tolist()) - set(m)))}
    new = np.array([m.get(int(i), extra.get(int(i))) for i in tracks.track_id], dtype=np.int64)
    return dataclasses.replace(tracks, track_id=new)


def ground_coords(X: F64, up: F64) -> F64:
    """(N, 3) -> (N, 3) with the component along ``up`` removed."""
    return X - np.outer(X @ up, up)


@dataclass(frozen=True)
class BoxErrors:
    rows_truth: int
    rows_matched: int
    coverage: float
    ground_mean_m: float
    ground_median_m: float
    centre_mean_m: float  # NaN when the truth has no vertical coordinate
    height_mean_m: float
    radius_mean_m: float
    mota: float
    idf1: float
    fp: int
    fn: int
    ids: int

    def as_dict(self) -> dict[str, float | int]:
        return dict(self.__dict__)


def _nanmean(x: F64) -> float:
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else float("nan")


@dataclass(frozen=True)
class RowErrors:
    """The errors of the track rows that have a truth row of the same frame and id
    (:func:`row_errors`): each one's truth row ``truth_row (K,)``, and its ground, centre,
    height and radius errors ``(K,)``, metres, in the tracks' row order."""

    truth_row: np.ndarray
    ground: F64
    centre: F64
    height: F64
    radius: F64

    @staticmethod
    def concat(parts: list[RowErrors]) -> RowErrors:
        """``parts`` one after another (none: no row)."""
        if not parts:
            return RowErrors(np.zeros(0, np.int64), *(np.zeros(0) for _ in range(4)))
        return RowErrors(*(np.concatenate([getattr(p, f) for p in parts]) for f in
                           ("truth_row", "ground", "centre", "height", "radius")))


def row_errors(tracks: TrackSet, truth: GroundTruth, up: F64) -> RowErrors:
    """The errors of each row of ``tracks`` that ``truth`` has a row of (the same frame and id)."""
    it, ig = match_rows(tracks, truth)
    c_est, c_tru = tracks.center_world[it], truth.center_world[ig]
    g_est = ground_coords(c_est, up)
    g_tru = ground_coords(np.nan_to_num(c_tru), up)
    s_est, s_tru = tracks.semi_axes[it], truth.semi_axes[ig]
    return RowErrors(ig, np.linalg.norm(g_est - g_tru, axis=1), np.linalg.norm(c_est - c_tru, axis=1),
                     np.abs(2 * s_est[:, 2] - 2 * s_tru[:, 2]),
                     np.abs(s_est[:, :2].mean(1) - s_tru[:, :2].mean(1)))


def box_errors(tracks: TrackSet, truth: GroundTruth, up: F64, max_dist_m: float = 1.0,
               mot: Mapping[str, float | int] | None = None) -> BoxErrors:
    """Errors of matched rows and :func:`clear_mot` (``mot``: its result when already computed,
    e.g. by :func:`gt3dkit.eval.tracking.tracking_scores` with the same arguments)."""
    mot = mot if mot is not None else clear_mot(tracks, truth, up, max_dist_m)
    e = row_errors(tracks, truth, up)
    return errors_of(e, len(np.unique(e.truth_row)), len(truth.frame), mot)


def errors_of(e: RowErrors, covered: int, n_truth: int, mot: Mapping[str, float | int]) -> BoxErrors:
    """:class:`BoxErrors` of the matched rows' errors ``e``, ``covered`` of the truth's
    ``n_truth`` rows with an estimate, with :func:`clear_mot`'s scores ``mot``."""
    ground = e.ground
    return BoxErrors(
        rows_truth=n_truth, rows_matched=len(e.truth_row),
        coverage=covered / max(n_truth, 1),
        ground_mean_m=_nanmean(ground),
        ground_median_m=float(np.median(ground)) if ground.size else float("nan"),
        centre_mean_m=_nanmean(e.centre), height_mean_m=_nanmean(e.height),
        radius_mean_m=_nanmean(e.radius), mota=float(mot["mota"]), idf1=float(mot["idf1"]),
        fp=int(mot["fp"]), fn=int(mot["fn"]), ids=int(mot["ids"]))


def _match_frame(d2: F64, o: I64, h: I64, last: I64, col: I64, om: np.ndarray, hm: np.ndarray) -> int:
    """One frame of :func:`clear_mot`: its truths ``o`` and tracks ``h`` (indices of the ids),
    their squared distances ``d2`` (NaN: out of reach). Each truth keeps the track it was last
    matched to (``last``, updated) where within reach, the rest are assigned; ``om``, ``hm``
    mark the matched truths and tracks (``col``: a scratch map, left all -1). Returns the
    identity switches."""
    from scipy.optimize import linear_sum_assignment

    switches = 0
    col[h] = np.arange(len(h))  # (1) carry the previous matches forward
    j = np.where(last[o] >= 0, col[np.maximum(last[o], 0)], -1)
    col[h] = -1
    i = np.flatnonzero(j >= 0)
    i = i[np.isfinite(d2[i, j[i]])]
    hm[j[i]] = True
    if hm.sum() < len(i):  # a track two truths last had: the first truth's, in order
        _, first = np.unique(j[i], return_index=True)
        i = np.sort(i[first])
    om[i] = True
    rest = d2[~om][:, ~hm]
    if np.isfinite(rest).any():  # (2) the rest, most pairs first, then least distance
        valid = np.isfinite(rest)
        big = 2 * min(rest.shape) * (np.abs(rest[valid]).max() + 1) + 1
        r, cc = linear_sum_assignment(np.where(valid, rest, big))
        ri, ci = np.flatnonzero(~om)[r], np.flatnonzero(~hm)[cc]
        for a, b in zip(ri.tolist(), ci.tolist(), strict=True):
            if not np.isfinite(d2[a, b]):
                continue
            if last[o[a]] >= 0 and last[o[a]] != h[b]:
                switches += 1
            last[o[a]] = h[b]
            om[a] = hm[b] = True
    return switches


def clear_mot(tracks: TrackSet, truth: GroundTruth, up: F64, max_dist_m: float = 1.0,
              pairs: NearPairs | None = None) -> dict[str, float | int]:
    """MOTA, IDF1, FP, FN, IDs on ground positions, a truth and a track paired when within
    ``max_dist_m``: the event rules of py-motmetrics (``MOTAccumulator.update`` and its ID
    measures, Heindl et al.), written out on arrays.

    Per frame: (1) each truth object keeps the track it was last matched to, if that track is
    there and within reach; (2) the rest are assigned to minimise the total squared distance
    among the most pairs within reach (motmetrics' scipy solver: out-of-reach pairs cost more
    than any set of real pairs); a truth object matched to another track than its last one is
    an identity switch; (3) unmatched truths are misses, unmatched tracks false positives.
    MOTA ``= 1 - (FN + FP + IDs) / truths``. IDF1 ``= 2 IDTP / (truths + tracks)``, IDTP the
    frames of the one-to-one pairing of truth and track identities that share the most frames
    within reach (Ristani et al. 2016). Only the pairs within reach are looked at
    (:func:`near_pairs`; ``pairs``: the truth's and the tracks' within at least ``max_dist_m``,
    when known), each frame's distance matrix built from them.

    Written out rather than calling motmetrics because its accumulator builds pandas frames
    per frame: its import and updates were ~0.8 s of every 400-frame evaluation (most of a box
    reconstruction's evaluation); ``tests/eval/test_metrics.py`` holds this to motmetrics itself on
    random scenes with misses, false positives and identity swaps.
    """
    g_t = ground_coords(np.nan_to_num(truth.center_world), up)
    g_e = ground_coords(tracks.center_world, up)
    # the pairs within reach: a hair beyond it found, then motmetrics' own test (MotCounts.block)
    if pairs is None:
        pairs = near_pairs(truth.frame, g_t, tracks.frame, g_e, max_dist_m * (1.0 + 1e-9))
    _, t_idx = np.unique(truth.track_id, return_inverse=True)
    _, e_idx = np.unique(tracks.track_id, return_inverse=True)
    counts = MotCounts(int(t_idx.max(initial=-1)) + 1)
    counts.block(truth.frame, t_idx.ravel(), g_t, tracks.frame, e_idx.ravel(), g_e, pairs, max_dist_m)
    return counts.scores(len(truth.frame), len(tracks.frame),
                         idtp(pair_counts(tracks.track_id, truth.track_id, pairs, max_dist_m)[0]))


def idtp(count: F64) -> float:
    """IDF1's true positives: the frames of the one-to-one pairing of track and truth identities
    (``count (tracks, truths)``: the frames each pair is within reach) that share the most."""
    from scipy.optimize import linear_sum_assignment

    if not count.size:
        return 0.0
    r, c = linear_sum_assignment(-count)
    return float(count[r, c].sum())


class MotCounts:
    """CLEAR-MOT's counts over frames that come in blocks in frame order (:func:`clear_mot`: one
    block; :class:`gt3dkit.eval.tracking.TrackingTally`: a long sequence's windows as they
    finish): the misses, false positives and identity switches so far, and each truth
    identity's last track (``last``, by the tracks' identity codes), from which the next block
    goes on: the same counts however the frames are cut."""

    def __init__(self, n_truth_ids: int) -> None:
        self.last = np.full(n_truth_ids, -1)  # truth id -> the track (its code) it was last matched to
        self.col = np.zeros(0, np.int64)  # a frame's track -> its column (-1: not in the frame)
        self.fp = self.fn = self.ids = 0

    def block(self, t_frame: np.ndarray, t_idx: np.ndarray, g_t: F64, e_frame: np.ndarray, e_idx: np.ndarray,
              g_e: F64, pairs: NearPairs, max_dist_m: float) -> None:
        """The frames of the truth rows ``(frame, identity index, ground position)`` and track rows
        ``(frame, identity code, ground position)`` given, all after the previous blocks' frames,
        with their :func:`near_pairs` (``a`` the truth rows, ``b`` the tracks', within at least
        ``max_dist_m``)."""
        if len(e_idx) and e_idx.max() >= len(self.col):  # codes never seen: their columns
            self.col = np.r_[self.col, np.full(int(e_idx.max()) + 1 - len(self.col), -1)]
        frames = np.union1d(t_frame, e_frame)
        ot, lo_t, hi_t, pos_t = frame_blocks(t_frame, frames)
        oe, lo_e, hi_e, pos_e = frame_blocks(e_frame, frames)
        # motmetrics' own test on the squared distance of the two ground positions, as its
        # distance matrix has it
        pt, pe = pairs.a, pairs.b
        d2p = np.sum((g_t[pt] - g_e[pe]) ** 2, axis=-1)
        near = d2p <= max_dist_m**2
        pt, pe, d2p = pt[near], pe[near], d2p[near]
        p_lo = np.searchsorted(np.searchsorted(frames, t_frame[pt]), np.arange(len(frames) + 1))
        for f in range(len(frames)):
            gi, hi = ot[lo_t[f]:hi_t[f]], oe[lo_e[f]:hi_e[f]]
            om, hm = np.zeros(len(gi), bool), np.zeros(len(hi), bool)
            k0, k1 = p_lo[f], p_lo[f + 1]
            if k1 > k0:
                d2 = np.full((len(gi), len(hi)), np.nan)
                d2[pos_t[pt[k0:k1]], pos_e[pe[k0:k1]]] = d2p[k0:k1]
                self.ids += _match_frame(d2, t_idx[gi], e_idx[hi], self.last, self.col, om, hm)
            self.fn += int((~om).sum())
            self.fp += int((~hm).sum())

    def scores(self, n_truth: int, n_est: int, idtp: float) -> dict[str, float | int]:
        """MOTA, IDF1, FP, FN, IDs of the blocks so far: ``n_truth`` and ``n_est`` rows, IDF1's
        true positives ``idtp`` (:func:`idtp`)."""
        fn, fp, ids = self.fn, self.fp, self.ids
        return {"mota": 1.0 - (fn + fp + ids) / n_truth if n_truth else float("nan"),
                "idf1": 2 * idtp / (n_truth + n_est) if n_truth + n_est else float("nan"),
                "fp": fp, "fn": fn, "ids": ids}
