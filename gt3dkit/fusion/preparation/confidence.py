"""What a detector's confidence says about a keypoint's pixel noise, learned from the data.

A detector's confidence (OpenPose's heatmap peak, a COCO score) orders its keypoints by how
sure it was, but in no known unit. The rule ``variance = sigma_joint^2 / confidence`` (the
weighted least squares reading of Pose2Sim's confidence-weighted DLT) fixes that unit by
assumption. On real OpenPose output it is far off: on Shelf's first half, the per-frame
triangulation's residuals of one joint grow ~9x in variance from the most confident eighth of
the detections to the least confident (``1/conf`` predicts ~2x).

:func:`learn_curve` measures it instead: the variance of a keypoint is ``sigma_joint^2 *
factor(confidence)``, the factor a non-increasing step curve over confidence bins (equal
counts), learnt with the joints' levels by alternating robust variances of the per-frame
fits' residuals (each point's degrees of freedom counted as for the joints' levels). Nothing
here reads a truth. Where the input gives no confidences (all 1), or too few points for the
bins, the curve is ``1/conf``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.preparation.robust import robust_variance
from gt3dkit.types import F64, JsonDict

#: Confidence bins of the learnt curve (equal counts of kept points).
BINS = 8
#: Kept points per bin below which the curve is not learnt.
MIN_PER_BIN = 200
#: Rounds of the alternation (joint levels, then bin factors); measured on Shelf: the exponent
#: of a power-law fit to the factors settles within 1 % in 3.
ROUNDS = 3


@dataclass(frozen=True)
class ConfidenceCurve:
    """``factor(conf)``: a keypoint's variance over its joint's level, by confidence.

    knots : (B,) the bins' median confidences, increasing; factors : (B,) the variance factor
    there, non-increasing, 1 at the most confident bin (a joint's level is its sd there);
    between knots a power law (log factor linear in log confidence), below the first knot the
    first segment's power law continued (the least confident bin's median is not its least
    confident point), constant above the last. ``knots`` empty: ``1 / conf``.
    """

    knots: F64
    factors: F64
    source: str

    def __call__(self, conf: F64) -> F64:
        c = np.asarray(conf, dtype=np.float64)
        if not len(self.knots):
            return 1.0 / c
        lc, lk, lf = np.log(c), np.log(self.knots), np.log(self.factors)
        inside = np.interp(lc, lk, lf)
        slope = (lf[1] - lf[0]) / (lk[1] - lk[0])  # below the first knot: the first segment's power law
        return np.exp(np.where(lc < lk[0], lf[0] + slope * (lc - lk[0]), inside))

    def info(self) -> JsonDict:
        """For ``meta.json`` and the report: the table of the curve and where it came from."""
        return {"rule": "variance = sigma_joint^2 * factor(confidence)", "source": self.source,
                "confidence": self.knots.round(4).tolist(), "factor": self.factors.round(4).tolist()}


INVERSE = ConfidenceCurve(np.zeros(0), np.zeros(0), "1/confidence (assumed: no confidences to learn from)")


def learn_curve(r2: F64, dof: F64, use: np.ndarray, conf: F64, joint: np.ndarray, n_joints: int,
                reject_p: float) -> tuple[ConfidenceCurve, F64]:
    """The curve and the joints' levels ``(J,)`` (variances, px^2) from the per-frame fits'
    squared residuals ``r2``, each point's degrees of freedom ``dof``, the points to use ``use``,
    their confidences ``conf`` and joints ``joint`` (all the same shape; 2 entries per point).
    :data:`INVERSE` (and the levels under it) where the confidences cannot be binned."""
    joint = np.broadcast_to(joint, use.shape)
    c = conf[use]
    edges = np.quantile(c, np.linspace(0.0, 1.0, BINS + 1)) if c.size else np.zeros(0)
    if c.size < BINS * MIN_PER_BIN or not np.all(np.diff(edges) > 0):
        return INVERSE, _levels(r2 * conf, dof, use, joint, n_joints, reject_p)
    bin_of = np.clip(np.searchsorted(edges, conf, side="right") - 1, 0, BINS - 1)
    knots = np.array([np.median(c[bin_of[use] == b]) for b in range(BINS)])
    factors = 1.0 / knots  # the assumed rule, to start from
    for _ in range(ROUNDS):
        level = _levels(r2 / factors[bin_of], dof, use, joint, n_joints, reject_p)
        scaled = r2 / level[joint]
        factors = np.array([robust_variance(scaled[use & (bin_of == b)], dof[use & (bin_of == b)],
                                            reject_p, 2) for b in range(BINS)])
        factors = np.maximum.accumulate(factors[::-1])[::-1]  # less sure is never less noisy
        factors = factors / factors[-1]
    level = _levels(r2 / factors[bin_of], dof, use, joint, n_joints, reject_p)
    return ConfidenceCurve(knots, factors, "learnt from the per-frame triangulation's residuals "
                                           f"({BINS} confidence bins of equal counts)"), level


def group_variances(r2: F64, dof: F64, use: np.ndarray, group: np.ndarray, n_groups: int,
                    reject_p: float, group_dof: int, min_points: int = 30) -> tuple[float, F64]:
    """:func:`gt3dkit.fusion.preparation.robust.robust_variance` of all used points and of each group
    (``group`` broadcasts against ``use``) with at least ``min_points``; a group with fewer, or
    with no finite positive estimate, gets the overall one."""
    group = np.broadcast_to(group, use.shape)
    glob = robust_variance(r2[use], dof[use], reject_p, group_dof)
    out = np.full(n_groups, glob)
    for g in range(n_groups):
        u = use & (group == g)
        if u.sum() >= min_points:
            v = robust_variance(r2[u], dof[u], reject_p, group_dof)
            if np.isfinite(v) and v > 0:
                out[g] = v
    return glob, out


def _levels(r2: F64, dof: F64, use: np.ndarray, joint: np.ndarray, n_joints: int,
            reject_p: float) -> F64:
    """(J,) each joint's robust variance of ``r2`` (:func:`group_variances`)."""
    return group_variances(r2, dof, use, joint, n_joints, reject_p, 2)[1]
