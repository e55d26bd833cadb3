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
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from gt3dkit.arrays import lookup_rows
from gt3dkit.types import F64, GroundTruth, TrackSet


def match_rows(tracks: TrackSet, truth: GroundTruth) -> tuple[np.ndarray, np.ndarray]:
    """Indices ``(i_track, i_truth)`` of rows with the same (frame, id), in the tracks' order."""
    at = lookup_rows(np.c_[truth.frame, truth.track_id].astype(np.int64),
                     np.c_[tracks.frame, tracks.track_id].astype(np.int64))
    it = np.flatnonzero(at >= 0)
    return it, at[it]


#: Pairs of rows :func:`frame_pairs` hands out at once (their arrays a few MB: a 4 000-frame,
#: 40-person truth report peaked 120 MB above its inputs with 2**20, nothing above with 2**17).
PAIRS_PER_CHUNK = 1 << 17


def frame_pairs(frame_a: np.ndarray, frame_b: np.ndarray, frames: np.ndarray, max_pairs: int = PAIRS_PER_CHUNK
                ) -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray]]:
    """Every pair of a row of table ``a`` and a row of table ``b`` in the same frame, for the
    sorted frame numbers ``frames``, in chunks of whole frames of about ``max_pairs`` pairs:
    yields ``(f0, f1, ia, ib, start)``, the frames ``frames[f0:f1]``, the pairs' rows ``(P,)`` in
    ``a`` and in ``b`` (frame by frame; within a frame ``a``'s rows in table order, each with
    ``b``'s rows in table order: the frame's ``(n_a, n_b)`` block, row-major) and ``start (f1 -
    f0 + 1,)`` where each frame's pairs begin. One sort per table instead of a scan per frame."""
    oa, ob = np.argsort(frame_a, kind="stable"), np.argsort(frame_b, kind="stable")
    fa, fb = np.asarray(frame_a)[oa], np.asarray(frame_b)[ob]
    lo_a, lo_b = np.searchsorted(fa, frames), np.searchsorted(fb, frames)
    n_a = np.searchsorted(fa, frames, side="right") - lo_a
    n_b = np.searchsorted(fb, frames, side="right") - lo_b
    n_pair = n_a * n_b
    end = np.cumsum(n_pair)
    f0 = 0
    while f0 < len(frames):
        base = end[f0] - n_pair[f0]
        f1 = max(int(np.searchsorted(end, base + max_pairs, side="right")), f0 + 1)
        start = np.concatenate([[0], end[f0:f1] - base])
        of = np.repeat(np.arange(f0, f1), n_pair[f0:f1])
        k = np.arange(start[-1]) - start[of - f0]  # the pair's place in its frame's block
        yield f0, f1, oa[lo_a[of] + k // n_b[of]], ob[lo_b[of] + k % n_b[of]], start
        f0 = f1


def _pair_counts(tracks: TrackSet, truth: GroundTruth, g_e: F64, g_t: F64, max_dist_m: float
                 ) -> tuple[F64, np.ndarray, np.ndarray]:
    """``count (n_track_ids, n_truth_ids)``: the frames in which a track and a truth identity are
    within ``max_dist_m`` of each other (ground positions ``g_e, g_t``); and the two id lists."""
    ids, ti = np.unique(tracks.track_id, return_inverse=True)
    tids, gi = np.unique(truth.track_id, return_inverse=True)
    ti, gi = ti.ravel(), gi.ravel()
    count = np.zeros(len(ids) * len(tids))
    frames = np.intersect1d(tracks.frame, truth.frame)
    for _, _, a, b, _ in frame_pairs(tracks.frame, truth.frame, frames):
        near = np.linalg.norm(g_e[a] - g_t[b], axis=1) <= max_dist_m
        count += np.bincount(ti[a[near]] * len(tids) + gi[b[near]], minlength=len(count))
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
    count, ids, tids = _pair_counts(tracks, truth, ground_coords(tracks.center_world, up),
                                    ground_coords(centre, up), max_dist_m)
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


def box_errors(tracks: TrackSet, truth: GroundTruth, up: F64, max_dist_m: float = 1.0,
               mot: dict[str, Any] | None = None) -> BoxErrors:
    """Errors of matched rows and :func:`clear_mot` (``mot``: its result when already computed,
    e.g. by :func:`gt3dkit.eval.tracking.tracking_scores` with the same arguments)."""
    it, ig = match_rows(tracks, truth)
    c_est, c_tru = tracks.center_world[it], truth.center_world[ig]
    g_est = ground_coords(c_est, up)
    g_tru = ground_coords(np.nan_to_num(c_tru), up)
    ground = np.linalg.norm(g_est - g_tru, axis=1)
    centre = np.linalg.norm(c_est - c_tru, axis=1)
    s_est, s_tru = tracks.semi_axes[it], truth.semi_axes[ig]
    height = np.abs(2 * s_est[:, 2] - 2 * s_tru[:, 2])
    radius = np.abs(s_est[:, :2].mean(1) - s_tru[:, :2].mean(1))
    keys = ("mota", "idf1", "fp", "fn", "ids")
    mot = {k: mot[k] for k in keys} if mot is not None else clear_mot(tracks, truth, up, max_dist_m)
    return BoxErrors(
        rows_truth=len(truth.frame), rows_matched=len(ig),
        coverage=len(np.unique(ig)) / max(len(truth.frame), 1),
        ground_mean_m=_nanmean(ground),
        ground_median_m=float(np.median(ground)) if ground.size else float("nan"),
        centre_mean_m=_nanmean(centre), height_mean_m=_nanmean(height),
        radius_mean_m=_nanmean(radius), **mot)


def clear_mot(tracks: TrackSet, truth: GroundTruth, up: F64, max_dist_m: float = 1.0
              ) -> dict[str, float | int]:
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
    within reach (Ristani et al. 2016).

    Written out rather than calling motmetrics because its accumulator builds pandas frames
    per frame: its import and updates were ~0.8 s of every 400-frame evaluation (most of a box
    reconstruction's evaluation); ``tests/eval/test_metrics.py`` holds this to motmetrics itself on
    random scenes with misses, false positives and identity swaps.
    """
    from scipy.optimize import linear_sum_assignment

    g_t = ground_coords(np.nan_to_num(truth.center_world), up)
    g_e = ground_coords(tracks.center_world, up)
    ot = np.argsort(truth.frame, kind="stable")
    oe = np.argsort(tracks.frame, kind="stable")
    ft, fe = truth.frame[ot], tracks.frame[oe]
    frames = np.union1d(ft, fe)
    lo_t, hi_t = np.searchsorted(ft, frames), np.searchsorted(ft, frames, side="right")
    lo_e, hi_e = np.searchsorted(fe, frames), np.searchsorted(fe, frames, side="right")
    max_d2 = max_dist_m**2
    last: dict[int, int] = {}  # truth id -> the track it was last matched to
    fp = fn = ids = 0
    for a, b, c, d in zip(lo_t, hi_t, lo_e, hi_e, strict=True):
        gi, hi = ot[a:b], oe[c:d]
        o, h = truth.track_id[gi].tolist(), tracks.track_id[hi].tolist()
        om, hm = np.zeros(len(o), bool), np.zeros(len(h), bool)
        if o and h:
            d2 = np.sum((g_t[gi][:, None] - g_e[hi][None]) ** 2, axis=-1)
            d2[d2 > max_d2] = np.nan
            col = {t: j for j, t in enumerate(h)}
            for i, oid in enumerate(o):  # (1) carry the previous matches forward
                j = col.get(last[oid], -1) if oid in last else -1
                if j >= 0 and not hm[j] and np.isfinite(d2[i, j]):
                    om[i] = hm[j] = True
            rest = d2[~om][:, ~hm]
            if np.isfinite(rest).any():  # (2) the rest, most pairs first, then least distance
                valid = np.isfinite(rest)
                big = 2 * min(rest.shape) * (np.abs(rest[valid]).max() + 1) + 1
                r, cc = linear_sum_assignment(np.where(valid, rest, big))
                ri, ci = np.flatnonzero(~om)[r], np.flatnonzero(~hm)[cc]
                for i, j in zip(ri.tolist(), ci.tolist(), strict=True):
                    if not np.isfinite(d2[i, j]):
                        continue
                    if o[i] in last and last[o[i]] != h[j]:
                        ids += 1
                    last[o[i]] = h[j]
                    om[i] = hm[j] = True
        fn += int((~om).sum())
        fp += int((~hm).sum())
    n_truth, n_est = len(truth.frame), len(tracks.frame)
    count, _, _ = _pair_counts(tracks, truth, g_e, g_t, max_dist_m)
    idtp = 0.0
    if count.size:
        r, c = linear_sum_assignment(-count)
        idtp = float(count[r, c].sum())
    return {"mota": 1.0 - (fn + fp + ids) / n_truth if n_truth else float("nan"),
            "idf1": 2 * idtp / (n_truth + n_est) if n_truth + n_est else float("nan"),
            "fp": fp, "fn": fn, "ids": ids}
