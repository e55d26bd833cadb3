r"""Multi-object tracking metrics on ground-plane positions, as the paper reports them.

* MOTA, IDF1, FP, FN, IDs: ``motmetrics``' rules (:func:`gt3dkit.eval.metrics.clear_mot`).
* HOTA (Luiten et al., IJCV 2021): TrackEval's ``HOTA`` metric (its algorithm on arrays,
  :func:`hota`; the tests hold it to TrackEval), with the similarity of a
  truth and a track position ``max(0, 1 - d / cutoff)`` (the ground-plane similarity used
  for multi-view detection), averaged over TrackEval's localisation thresholds.
* OSPA(2) (Beard, Vo & Vo, "A solution for large-scale multi-object tracking", IEEE TSP
  68, 2020, eq. 9-10): no maintained Python package implements it, so it is written out
  here. For tracks ``x`` and ``y`` over the frames ``D_x ∪ D_y`` where either exists,

  .. math::
      \tilde d^{(c)}(x, y) = \frac{1}{|D_x \cup D_y|} \sum_{t \in D_x \cup D_y}
      d^{(c)}(x_t, y_t),\quad d^{(c)} = \min(c, \|x_t - y_t\|)\ \text{if both exist,}\ c
      \ \text{otherwise};

  then OSPA of order ``p`` and cut-off ``c`` between the sets of tracks,
  ``(\frac{1}{n}(\min_\pi \sum_{i \le m} \tilde d(x_i, y_{\pi(i)})^p + c^p (n - m)))^{1/p}``,
  ``m <= n``, over the whole sequence (one window). Defaults: ``c = 1`` m, ``p = 1``.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from scipy.optimize import linear_sum_assignment

from gt3dkit.eval.metrics import clear_mot, frame_pairs, ground_coords
from gt3dkit.types import F64, GroundTruth, TrackSet


def ospa2(truth_frame: np.ndarray, truth_id: np.ndarray, truth_xy: F64, est_frame: np.ndarray,
          est_id: np.ndarray, est_xy: F64, cutoff: float = 1.0, order: float = 1.0) -> float:
    """OSPA(2) between two sets of tracks (see module doc). Positions ``(N, D)``, metres.

    The track distance is the mean over the frames either track is in of the cut-off distance
    (``cutoff`` where only one of them is there), computed for one truth track against every
    estimated track at a time on frame-indexed arrays."""
    frames, f_inv = np.unique(np.concatenate([truth_frame, est_frame]), return_inverse=True)
    ft, fe = f_inv[:len(truth_frame)], f_inv[len(truth_frame):]
    tx, ti = np.unique(truth_id, return_inverse=True)
    ey, ei = np.unique(est_id, return_inverse=True)
    if not len(tx) and not len(ey):
        return 0.0
    if not len(tx) or not len(ey):
        return float(cutoff)
    F, Dm = len(frames), truth_xy.shape[1]
    X = np.full((len(tx), F, Dm), np.nan)
    X[ti, ft] = truth_xy
    Y = np.full((len(ey), F, Dm), np.nan)
    Y[ei, fe] = est_xy
    px, py = ~np.isnan(X[..., 0]), ~np.isnan(Y[..., 0])
    D = np.zeros((len(tx), len(ey)))
    for i in range(len(tx)):
        d = np.minimum(np.linalg.norm(X[i][None] - Y, axis=-1), cutoff)  # (ny, F), NaN if absent
        both = px[i][None] & py
        union = px[i][None] | py
        tot = np.where(both, d, np.where(union, cutoff, 0.0)).sum(axis=1)
        D[i] = tot / np.maximum(union.sum(axis=1), 1)
    n = max(len(tx), len(ey))
    m = min(len(tx), len(ey))
    C = D if len(tx) <= len(ey) else D.T
    r, c = linear_sum_assignment(C**order)
    cost = float(np.sum(C[r, c] ** order)) + cutoff**order * (n - m)
    return float((cost / n) ** (1.0 / order))


#: HOTA's localisation thresholds (TrackEval's ``HOTA.array_labels``)
HOTA_ALPHAS = np.arange(0.05, 0.99, 0.05)


def hota(truth_frame: np.ndarray, truth_id: np.ndarray, truth_xy: F64, est_frame: np.ndarray,
         est_id: np.ndarray, est_xy: F64, cutoff: float = 1.0) -> dict[str, float]:
    """HOTA, DetA, AssA on ground positions (similarity ``max(0, 1 - d / cutoff)``), averaged
    over :data:`HOTA_ALPHAS`: TrackEval's ``HOTA.eval_sequence`` written out on arrays.

    (1) Each truth and track identity's potential matches: per frame, the similarity over the
    union of the two rows' similarities (``s / (row sum + column sum - s)``), summed over the
    frames; the global alignment ``A = potential / (n_truth + n_track - potential)``. (2) Per
    frame, the assignment maximising ``A * s`` (Hungarian); a pair counts at threshold alpha
    when ``s >= alpha``. DetA ``= TP / (TP + FN + FP)``, AssA the TP-weighted mean of each
    matched pair's ``matches / (n_truth + n_track - matches)``, HOTA ``= sqrt(DetA AssA)``.

    Written out rather than calling TrackEval because its per-frame loop (threshold by
    threshold in Python) took 1.3 s of a 4 000-frame, 40-person evaluation, the longest part of
    ``gt3d reconstruct``'s truth report; ``tests/eval/test_metrics.py`` holds this to TrackEval
    itself on random scenes with misses, false positives and identity swaps."""
    n_a = len(HOTA_ALPHAS)
    if not len(est_id) or not len(truth_id):  # TrackEval's early return: every score 0
        return {"hota": 0.0, "deta": 0.0, "assa": 0.0}
    frames = np.union1d(np.unique(truth_frame), np.unique(est_frame))
    _, g_inv = np.unique(truth_id, return_inverse=True)
    e_ids, e_inv = np.unique(est_id, return_inverse=True)
    g_inv, e_inv = g_inv.ravel(), e_inv.ravel()
    n_g, n_e = int(g_inv.max()) + 1, len(e_ids)
    g_count = np.bincount(g_inv, minlength=n_g).astype(float)
    e_count = np.bincount(e_inv, minlength=n_e).astype(float)
    both = g_count.repeat(n_e) + np.tile(e_count, n_g)  # (n_g * n_e,) the two identities' rows
    fe = np.sort(est_frame)
    tracks_in = np.searchsorted(fe, frames, side="right") - np.searchsorted(fe, frames)  # (F,)

    def pairs() -> Iterator[tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
        """Chunks of frames (:func:`frame_pairs`; twice through, not held): the frames ``f0:f1``,
        where each frame's pairs start, the pairs' truth and track rows, similarity and id cell."""
        for f0, f1, a, b, start in frame_pairs(truth_frame, est_frame, frames):
            sim = np.maximum(0.0, 1.0 - np.linalg.norm(truth_xy[a] - est_xy[b], axis=-1) / cutoff)
            yield f0, f1, start, a, b, sim, g_inv[a] * n_e + e_inv[b]

    potential = np.zeros(n_g * n_e)
    for _, _, _, a, b, sim, cell in pairs():  # (1)
        rows = np.bincount(a, weights=sim, minlength=len(truth_frame))  # a truth row's pairs: one frame's
        cols = np.bincount(b, weights=sim, minlength=len(est_frame))
        denom = rows[a] + cols[b] - sim
        iou = np.where(denom > np.finfo(float).eps, sim / np.where(denom > 0, denom, 1.0), 0.0)
        potential += np.bincount(cell, weights=iou, minlength=n_g * n_e)
    align = potential / (both - potential)
    tp = np.zeros(n_a)
    matches = np.zeros((n_a, n_g * n_e))
    for f0, f1, start, _, _, sim, cell in pairs():  # (2)
        score = align[cell] * sim
        picked = []
        for i in range(f1 - f0):
            k0, k1 = start[i], start[i + 1]
            if k1 == k0:
                continue
            n_b = int(tracks_in[f0 + i])
            r, c = linear_sum_assignment(-score[k0:k1].reshape(-1, n_b))
            picked.append(k0 + r * n_b + c)
        if not picked:
            continue
        m = np.concatenate(picked)
        ok = sim[m][None] >= HOTA_ALPHAS[:, None] - np.finfo(float).eps  # (A, M)
        tp += ok.sum(axis=1)
        for k in range(n_a):
            matches[k] += np.bincount(cell[m[ok[k]]], minlength=n_g * n_e)
    fn, fp = len(truth_id) - tp, len(est_id) - tp
    ass = (matches * (matches / np.maximum(1.0, both - matches))).sum(axis=1) / np.maximum(1.0, tp)
    det = tp / np.maximum(1.0, tp + fn + fp)
    return {"hota": float(np.mean(np.sqrt(det * ass))), "deta": float(np.mean(det)),
            "assa": float(np.mean(ass))}


def tracking_scores(tracks: TrackSet, truth: GroundTruth, up: F64, cutoff_m: float = 1.0
                    ) -> dict[str, float | int]:
    """MOTA, IDF1, FP, FN, IDs, HOTA, DetA, AssA and OSPA(2) on ground positions."""
    g_t = ground_coords(np.nan_to_num(truth.center_world), up)
    g_e = ground_coords(tracks.center_world, up)
    out: dict[str, float | int] = dict(clear_mot(tracks, truth, up, cutoff_m))
    out.update(hota(truth.frame, truth.track_id, g_t, tracks.frame, tracks.track_id, g_e, cutoff_m))
    out["ospa2_m"] = ospa2(truth.frame, truth.track_id, g_t, tracks.frame, tracks.track_id, g_e,
                           cutoff_m, 1.0)
    return out
