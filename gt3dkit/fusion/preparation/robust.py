r"""Robust weights for measurements judged against the *other* views, and robust noise levels.

A measurement "point" is a group of entries that stand or fall together: a keypoint
``(u, v)`` (2 entries) or one box edge (1 entry). Each point is scored by its
*leave-one-out* (deleted, studentised) residual: the residual it would have against the
estimate made from everything else, in units of its predicted spread,

.. math::
    e_i^2 = \frac{\big(r_i / (1 - h_i)\big)^2}{D_i + p_i / (1 - h_i)},\qquad
    h_i = \frac{w_i\, p_i}{D_i},\quad p_i = (A P^+ A^\top)_{ii},

where ``r_i`` is the residual at the current estimate, ``D_i`` the entry's noise variance,
``w_i`` its current weight, ``P^+`` the posterior with it and ``A`` the (linearised)
measurement Jacobian (Sherman-Morrison: ``p_i / (1 - h_i)`` is the predictive variance
without the entry). So a bad point cannot hide by dragging the estimate towards itself,
and a point nothing else constrains (``h -> 1``) is never rejected.

Weights (per point, ``d`` entries): 1 up to the ``1 - huber_p`` quantile of
:math:`\chi^2_d`, then Huber's ``c / e`` tapered by Tukey's biweight to exactly 0 at the
``1 - reject_p`` quantile. Weight 0 = rejected: the point has no influence at all.

References: Cook & Weisberg, "Residuals and Influence in Regression" (1982), ch. 2
(deleted residuals); Huber, "Robust Statistics" (1981); Beaton & Tukey (1974).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numba
import numpy as np
from scipy.special import chdtri

from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.types import F64

drop_stale()  # before any compiled function below is called (and its cache read)

#: Rounds of trimming in :func:`robust_variance`.
TRIM_ROUNDS = 3


@dataclass(frozen=True)
class RobustConfig:
    """Thresholds as tail probabilities of the point's chi-square (noise-level relative).

    huber_p : above its ``1 - huber_p`` quantile a point is down-weighted
    reject_p : above its ``1 - reject_p`` quantile a point is rejected (weight 0)
    enabled : False = every weight 1 (plain least squares / plain UKF)
    cut_variance_ratio : a kind of box edge cut by nearer objects is left out when its median
        squared residual is at least this many times the kind's other edges'
        (:mod:`gt3dkit.fusion.preparation.occlusion`)
    """

    huber_p: float = 1e-4
    reject_p: float = 1e-7
    enabled: bool = True
    cut_variance_ratio: float = 2.5

    def __post_init__(self) -> None:
        if not 0 < self.reject_p < self.huber_p < 1:
            raise ValueError("need 0 < reject_p < huber_p < 1")
        if not self.cut_variance_ratio > 1:
            raise ValueError("need cut_variance_ratio > 1")

    def thresholds(self, dof: int) -> tuple[float, float]:
        """``(c, g)``: the down-weighting and rejection thresholds on ``e`` (not ``e^2``)."""
        return (float(np.sqrt(chi2_isf(self.huber_p, dof))),
                float(np.sqrt(chi2_isf(self.reject_p, dof))))


@lru_cache(maxsize=256)
def chi2_isf(p: float, dof: int) -> float:
    """``scipy.stats.chi2.isf(p, dof)``, cached: the filter asks for the same few quantiles
    every frame (scipy.stats spends ~0.2 ms on each call, and importing it ~1 s; the same
    function of ``scipy.special`` is used)."""
    return float(chdtri(dof, p))


def chi2_median(dof: float) -> float:
    """``scipy.stats.chi2.median(dof)``."""
    return float(chdtri(dof, 0.5))


@numba.njit(cache=True, nogil=True)
def point_weight(e2: float, c_thr: float, g_thr: float) -> float:
    """The weight in [0, 1] of a point whose squared leave-one-out score is ``e2``: 1 up to the
    threshold ``c_thr`` (in units of the score), Huber's ``c / e`` times a taper that reaches 0 at
    ``g_thr`` beyond it, 0 from there (NaN: 1). The one rule: the compiled update
    (:mod:`gt3dkit.fusion.ukf.update`) calls it per point, :func:`point_weights` per array."""
    e = math.sqrt(max(0.0 if np.isnan(e2) else e2, 0.0))
    if e >= g_thr:
        return 0.0
    if e <= c_thr:
        return 1.0
    taper = min(max(1.0 - ((e - c_thr) / (g_thr - c_thr)) ** 2, 0.0), 1.0)
    return (c_thr / max(e, 1e-300)) * taper * taper


@numba.njit(cache=True, nogil=True)
def _point_weights(e2: F64, c_thr: float, g_thr: float, out: F64) -> None:
    for k in range(e2.shape[0]):
        out[k] = point_weight(e2[k], c_thr, g_thr)


def point_weights(e2: F64, dof: int, cfg: RobustConfig) -> F64:
    """Weights ``(...)`` in [0, 1] of points with squared scores ``e2 (...)`` and ``dof`` entries:
    :func:`point_weight` at the thresholds of ``cfg`` (all 1 where it is off)."""
    if not cfg.enabled:
        return np.ones_like(e2)
    c, g = cfg.thresholds(dof)
    flat = np.ascontiguousarray(e2, dtype=np.float64).reshape(-1)
    out = np.empty(flat.shape[0])
    _point_weights(flat, float(c), float(g), out)
    return out.reshape(np.shape(e2))


def deleted_score2(r: F64, D: F64, p: F64, w: F64) -> F64:
    """Squared leave-one-out scores of entries (see the module doc); all arrays alike."""
    h = np.clip(w * p / np.maximum(D, 1e-300), 0.0, 1.0 - 1e-9)
    rl = r / (1.0 - h)
    return rl * rl / (D + p / (1.0 - h))


def median_variance(r2: F64, dof: F64, group_dof: int = 1) -> float:
    """The noise variance the median point says (``median(r2 / dof) / median(chi2_d / d)``):
    the level of the typical point, blind to the tails (:func:`robust_variance`'s start)."""
    ok = np.isfinite(r2) & (dof > 0)
    if not ok.any():
        return float("nan")
    return float(np.median(r2[ok] / dof[ok])) / (chi2_median(group_dof) / group_dof)


def robust_variance(r2: F64, dof: F64, reject_p: float = 1e-7, group_dof: int = 1) -> float:
    r"""Noise variance from residuals with a few gross errors among them.

    Parameters
    ----------
    r2 : (N,) squared residual of each point (sum over its entries), in the unit to estimate
    dof : (N,) degrees of freedom each point contributes (its entries times the fraction
        of its fit's measurements that are not used up by the fit's parameters)
    group_dof : entries per point (for the chi-square of the trimming)

    Starts from the median (``median(r2 / dof) / median(chi2_d / d)``), then drops points
    beyond the ``1 - reject_p`` quantile and takes ``sum r2 / sum dof`` of the rest; twice.
    """
    ok = np.isfinite(r2) & (dof > 0)
    r2, dof = r2[ok], dof[ok]
    if r2.size == 0 or dof.sum() <= 0:
        return float("nan")
    var = median_variance(r2, dof, group_dof)
    if not var > 0:
        var = float(r2.sum() / dof.sum())
    g2 = chi2_isf(reject_p, group_dof)
    for _ in range(TRIM_ROUNDS):
        keep = r2 / (dof / group_dof) <= g2 * var
        if not keep.any() or dof[keep].sum() <= 0:
            break
        var = float(r2[keep].sum() / dof[keep].sum())
    return var
