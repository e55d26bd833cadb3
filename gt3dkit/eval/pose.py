"""3D pose metrics as VoxelPose defines them for CMU Panoptic.

Tu, Wang & Zeng, "VoxelPose", ECCV 2020, ``lib/dataset/panoptic.py`` (``evaluate``,
``_eval_list_to_ap``, ``_eval_list_to_mpjpe``, ``_eval_list_to_recall``): every predicted
pose is matched to the truth pose of its frame with the lowest MPJPE (mean over the
truth's valid joints); predictions are sorted by score; a prediction is a true positive
at threshold ``d`` if its MPJPE is below ``d`` and its truth pose is not matched yet.
AP is the area under the precision envelope (VOC style); MPJPE is the mean over the
true positives at 500 mm; recall@500 the fraction of truth poses with a prediction
within 500 mm. Millimetres in, millimetres out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.eval.metrics import match_rows
from gt3dkit.types import F64, GroundTruth, TrackSet


@dataclass(frozen=True)
class PoseScores:
    mpjpe_mm: float
    ap: dict[int, float]  # threshold (mm) -> AP in [0, 1]
    recall_500: float
    poses_truth: int
    poses_predicted: int

    def as_dict(self) -> dict[str, float | int]:
        d: dict[str, float | int] = {"mpjpe_mm": self.mpjpe_mm, "recall_500": self.recall_500,
                                     "poses_truth": self.poses_truth,
                                     "poses_predicted": self.poses_predicted}
        d.update({f"ap_{k}": v for k, v in self.ap.items()})
        return d


def _ap(mpjpe: F64, gt_id: np.ndarray, score: F64, total_gt: int, thr: float) -> float:
    order = np.argsort(-score, kind="stable")
    tp = np.zeros(len(order))
    seen: set[int] = set()
    for k, i in enumerate(order):
        if mpjpe[i] < thr and int(gt_id[i]) not in seen:
            tp[k] = 1
            seen.add(int(gt_id[i]))
    fp = 1 - tp
    tp, fp = np.cumsum(tp), np.cumsum(fp)
    recall = tp / (total_gt + 1e-5)
    prec = tp / (tp + fp + 1e-5)
    for n in range(len(prec) - 2, -1, -1):
        prec[n] = max(prec[n], prec[n + 1])
    prec = np.concatenate(([0.0], prec, [0.0]))
    recall = np.concatenate(([0.0], recall, [1.0]))
    idx = np.flatnonzero(recall[1:] != recall[:-1])
    return float(np.sum((recall[idx + 1] - recall[idx]) * prec[idx + 1]))


def pose_scores(pred_frame: np.ndarray, pred_kpt_mm: F64, pred_score: F64,
                truth_frame: np.ndarray, truth_kpt_mm: F64,
                thresholds: tuple[int, ...] = (25, 50, 100, 150)) -> PoseScores:
    """VoxelPose metrics.

    Parameters
    ----------
    pred_frame : (P,), pred_kpt_mm : (P, J, 3), pred_score : (P,)
    truth_frame : (G,), truth_kpt_mm : (G, J, 3) with NaN for joints without truth
    """
    mp, gid, sc = [], [], []
    for i in range(len(pred_frame)):
        cand = np.flatnonzero(truth_frame == pred_frame[i])
        if cand.size == 0:
            mp.append(np.inf)
            gid.append(-1 - i)
            sc.append(pred_score[i])
            continue
        d = np.linalg.norm(pred_kpt_mm[i][None] - truth_kpt_mm[cand], axis=-1)  # (c, J)
        valid = np.isfinite(d)
        with np.errstate(invalid="ignore"):
            per = np.where(valid.any(1), np.nansum(d, 1) / np.maximum(valid.sum(1), 1), np.inf)
        k = int(np.argmin(per))
        mp.append(per[k])
        gid.append(int(cand[k]))
        sc.append(pred_score[i])
    mpjpe = np.array(mp, dtype=np.float64)
    gt_id = np.array(gid, dtype=np.int64)
    score = np.array(sc, dtype=np.float64)
    G = len(truth_frame)
    ap = {t: _ap(mpjpe, gt_id, score, G, float(t)) for t in thresholds}
    order = np.argsort(-score, kind="stable")
    used: set[int] = set()
    tps = []
    for i in order:
        if mpjpe[i] < 500 and int(gt_id[i]) not in used:
            tps.append(mpjpe[i])
            used.add(int(gt_id[i]))
    recall = len({int(g) for g, m in zip(gt_id, mpjpe, strict=True) if m < 500 and g >= 0}) / max(G, 1)
    return PoseScores(mpjpe_mm=float(np.mean(tps)) if tps else float("inf"), ap=ap,
                      recall_500=recall, poses_truth=G, poses_predicted=len(pred_frame))


def score_tracks(tracks: TrackSet, truth: GroundTruth, joints: np.ndarray | None = None
                 ) -> PoseScores:
    """VoxelPose metrics of a reconstruction's keypoints (metres) against truth (metres).

    ``joints`` selects the scored joints (e.g. the 15 body joints). Predictions score
    ``1 / (1 + mean joint sd)`` so that the most certain poses rank first.
    """
    sel = slice(None) if joints is None else joints
    pk = tracks.kpt_world[:, sel] * 1000
    tk = truth.kpt_world[:, sel] * 1000
    with np.errstate(invalid="ignore"):
        sd = tracks.kpt_sd[:, sel]
        n = np.isfinite(sd).sum(axis=1)
        mean_sd = np.where(n > 0, np.where(np.isfinite(sd), sd, 0.0).sum(axis=1) / np.maximum(n, 1), 1e3)
        score = 1.0 / (1.0 + mean_sd)
    keep = np.isfinite(pk).any(axis=(1, 2))
    return pose_scores(tracks.frame[keep], pk[keep], score[keep], truth.frame, tk)


def mpjpe_by_id(tracks: TrackSet, truth: GroundTruth, joints: np.ndarray | None = None
                ) -> tuple[float, int, int]:
    """Mean joint error (mm) over rows matched by (frame, id), and poses matched / in truth."""
    it, ig = match_rows(tracks, truth)
    sel = slice(None) if joints is None else joints
    d = np.linalg.norm(tracks.kpt_world[it][:, sel] - truth.kpt_world[ig][:, sel], axis=-1)
    ok = np.isfinite(truth.kpt_world[ig][:, sel]).all(axis=-1)
    return float(np.mean(d[ok]) * 1000) if ok.any() else float("nan"), len(ig), len(truth.frame)
