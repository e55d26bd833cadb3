r"""Multi-object tracking metrics on ground-plane positions, as the paper reports them.

* MOTA, IDF1, FP, FN, IDs: ``motmetrics``' rules (:func:`gt3dkit.eval.metrics.clear_mot`).
* HOTA (Luiten et al., IJCV 2021): TrackEval's ``HOTA`` metric, with the similarity of a
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

import numpy as np
from scipy.optimize import linear_sum_assignment

from gt3dkit.eval.metrics import clear_mot, ground_coords
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


def hota(truth_frame: np.ndarray, truth_id: np.ndarray, truth_xy: F64, est_frame: np.ndarray,
         est_id: np.ndarray, est_xy: F64, cutoff: float = 1.0) -> dict[str, float]:
    """HOTA, DetA, AssA with TrackEval on ground positions (similarity ``1 - d/cutoff``)."""
    from trackeval.metrics import HOTA

    frames = np.union1d(np.unique(truth_frame), np.unique(est_frame))
    g_ids, g_inv = np.unique(truth_id, return_inverse=True)
    e_ids, e_inv = np.unique(est_id, return_inverse=True)
    data: dict[str, object] = {"num_timesteps": len(frames), "num_gt_ids": len(g_ids),
                               "num_tracker_ids": len(e_ids), "num_gt_dets": len(truth_id),
                               "num_tracker_dets": len(est_id), "gt_ids": [],
                               "tracker_ids": [], "similarity_scores": []}
    for f in frames:
        gi = np.flatnonzero(truth_frame == f)
        ei = np.flatnonzero(est_frame == f)
        d = np.linalg.norm(truth_xy[gi][:, None] - est_xy[ei][None], axis=-1)
        data["gt_ids"].append(g_inv[gi])  # type: ignore[attr-defined]
        data["tracker_ids"].append(e_inv[ei])  # type: ignore[attr-defined]
        data["similarity_scores"].append(np.maximum(0.0, 1.0 - d / cutoff))  # type: ignore[attr-defined]
    res = HOTA({"PRINT_CONFIG": False}).eval_sequence(data)
    return {"hota": float(np.mean(res["HOTA"])), "deta": float(np.mean(res["DetA"])),
            "assa": float(np.mean(res["AssA"]))}


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
