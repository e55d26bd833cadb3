"""What every estimator starts from: rows, robust per-frame fits, noise levels, input checks.

The UKF smoother, the GTSAM smoother and the triangulation baseline all call
:func:`prepare` and nothing of each other. It

* builds the object-frame rows (:mod:`gt3dkit.fusion.preparation.rows`);
* fits every object-frame on its own, robustly: boxes by Levenberg-Marquardt with edges
  that disagree with the other views rejected (leave-one-out scores), keypoints by MSAC
  triangulation (:func:`gt3dkit.geom.triangulate.robust_triangulate`);
* estimates the noise levels from those fits' residuals, robustly (a few gross errors do
  not inflate them): one box-edge level, one keypoint level per joint (detectors are much
  worse on hips than on eyes); a keypoint's variance is its joint's divided by its
  detector confidence (a confidence is a relative weight, so ``sigma^2 / conf``: the
  weighted least-squares reading of Pose2Sim's confidence-weighted DLT);
* learns the shape prior (semi-axes) from the objects several views see well, for the
  object-frames one or two views see (depth from a single box is only as good as the
  known size of the object);
* raises :class:`InputError` for what no estimator can use (an object behind a camera that
  annotated it, keypoints that no two views agree on for a camera).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.fusion.motion import StateLayout
from gt3dkit.fusion.preparation.boxfit import PERSON_SEMI_AXES_M, BoxFit, fit_boxes
from gt3dkit.fusion.preparation.confidence import INVERSE, ConfidenceCurve, group_variances, learn_curve
from gt3dkit.fusion.preparation.crowd import CrowdLevels, crowd_levels
from gt3dkit.fusion.preparation.levels import BoxLevels, KeypointLevels, PreparationSummary
from gt3dkit.fusion.preparation.occlusion import CutEdges, cut_edges_of
from gt3dkit.fusion.preparation.robust import (
    RobustConfig,
    chi2_isf,
    deleted_score2,
    median_variance,
    point_weights,
)
from gt3dkit.fusion.preparation.rows import Rows, build_rows, nearest_same_object
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.triangulate import normalized_points, robust_triangulate, triangulation_cov
from gt3dkit.skeletons import Skeleton, skeleton_for, skeleton_of
from gt3dkit.types import BOX_EDGES, F64, I64, Scene

#: Smallest confidence used as a weight (``sigma^2 / conf``: at most 7x the sd).
CONF_FLOOR = 0.02
#: Views from which a box fit counts as well determined (learns the shape prior).
PRIOR_MIN_VIEWS = 3


@dataclass(frozen=True)
class ShapePrior:
    """Prior of an object's log semi-axes for weakly seen object-frames."""

    mean: F64  # (3,) log metres
    sd: F64  # (3,) log units
    source: str


class FrameState(NamedTuple):
    """Every row's own (per-frame) state ``x (R, n)``, its per-entry variances ``var (R, n)`` and
    the (centre, log axes) covariance ``cov6 (R, 6, 6)`` (:meth:`Prepared.frame_state`)."""

    x: F64
    var: F64
    cov6: F64


@dataclass(frozen=True)
class Prepared:
    """Rows, cameras, robust per-frame fits and noise levels (see the module doc).

    fit : per-frame box fits on the kept edges (None without boxes), weighted by
        ``sigma_box``
    box_keep : (R, C, 4) usable edges the per-frame fits kept
    fit_reliable : (R,) the per-frame box fit is a summary to trust on its own: two or more
        views and nothing rejected, or three or more views it kept whole (where the views
        disagree and few are left, which of them is wrong is for the temporal model to say)
    kpt0 : (R, J, 3) per-frame joints (NaN under 2 agreeing views); kpt0_cov (R, J, 3, 3) m^2
    kpt_keep : (R, C, J) keypoints the per-frame triangulation kept
    kpt_reliable : (R, J) the per-frame joint is a summary to trust on its own (three or more
        views kept, or two views and nothing rejected): with two views left after a
        rejection, a wrong point along the other's epipolar line looks consistent
    sigma_box : (4,) box-edge noise per edge kind (px): the typical edge's, what the filters
        weight an edge by; box_tail : the variance ratio of all edges (``info.boxes.sigma_px``,
        heavy-tailed by the model's misfit) to it, >= 1: tests and flags are made at that level;
        sigma_kpt : (J,) keypoint noise per joint (px)
    kpt_var : (R, C, J) each keypoint's variance (px^2) = sigma_kpt[j]^2 / confidence
    box_cut : (R, C, 4) the edges a nearer object cut that were left out (taken out of
        ``rows.box_mask`` as the border's; :mod:`gt3dkit.fusion.preparation.occlusion`), or None;
        box_cut_by : (R, C, 4) for each of those, the row of a nearer object it lies in (-1
        elsewhere)
    """

    rows: Rows
    cams: Cams
    layout: StateLayout
    use_box: bool
    use_kpt: bool
    fit: BoxFit | None
    box_keep: np.ndarray
    fit_reliable: np.ndarray
    kpt0: F64 | None
    kpt0_cov: F64 | None
    kpt_keep: np.ndarray
    kpt_reliable: np.ndarray
    sigma_box: F64
    sigma_kpt: F64
    kpt_var: F64
    shape_prior: ShapePrior
    skeleton: Skeleton | None
    robust: RobustConfig
    info: PreparationSummary = field(default_factory=PreparationSummary)
    box_tail: float = 1.0
    box_cut: np.ndarray | None = None  # (R, C, 4) edges a nearer object cut, left out (.occlusion)
    box_cut_by: np.ndarray | None = None  # (R, C, 4) the row of a nearer object each lies in, else -1
    box_var_scale: np.ndarray | None = None  # (R, C, 4) each edge's variance over sigma_box's (.crowd)
    #: every row's own state (:meth:`frame_state`), made with the rest (never given)
    frame: FrameState = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "frame", self._own_state())

    def frame_state(self) -> FrameState:
        """Every row's own (per-frame) state, for initialisation and linearisation (made once, as
        the preparation is: the arrays are shared, callers copy before changing them).

        Returns ``x (R, n)``, per-entry variances ``var (R, n)`` (inf where the frame says
        nothing: velocities, unseen joints) and the (centre, log axes) covariance
        ``cov6 (R, 6, 6)``. Without boxes the centre and axes are those of the ellipsoid
        around the triangulated joints (nearest frame that has some).
        """
        return self.frame

    def _own_state(self) -> FrameState:
        rows, lay = self.rows, self.layout
        R, n, J = len(rows), lay.n, lay.n_joints
        x = np.zeros((R, n))
        var = np.full((R, n), np.inf)
        cov6 = np.zeros((R, 6, 6))
        wfb = self.cams.world_from_body
        if self.fit is not None:
            x[:, lay.center], x[:, lay.log_axes] = self.fit.center_world, self.fit.log_axes
            # a frame whose own views disagree (beyond what their noise explains) is trusted less
            dof = self.fit.n_edges - 6
            chi = self.fit.rss_px2 / (self.sigma_box[0] ** 2 * self.box_tail)
            cov6 = self.fit.cov * disagreement_scale(chi, dof)[:, None, None]
        elif self.kpt0 is not None:
            c, s, _ = ellipsoid_around(self.kpt0, np.zeros(self.kpt0.shape[:2]), wfb)
            ok = np.all(np.isfinite(c), axis=1)
            near = nearest_same_object(rows, ok)
            c, s = c[near], s[near]
            x[:, lay.center], x[:, lay.log_axes] = c, np.log(s)
            cov6 = np.zeros((R, 6, 6))
            cov6[:, :3, :3] = np.eye(3) * 0.1**2
            cov6[:, 3:, 3:] = np.diag(self.shape_prior.sd**2)
        var[:, lay.center] = np.einsum("rii->ri", cov6[:, :3, :3])
        var[:, lay.log_axes] = np.einsum("rii->ri", cov6[:, 3:, 3:])
        if J:
            skel = self.skeleton or skeleton_for(J)
            canon = skel.canonical() - np.array([0.0, 0.0, PERSON_SEMI_AXES_M[2]])
            scale = np.exp(x[:, lay.log_axes]) / PERSON_SEMI_AXES_M
            placed = x[:, None, lay.center] + np.einsum("ij,rkj->rki", wfb, canon[None] * scale[:, None])
            have = (np.all(np.isfinite(self.kpt0), axis=-1) if self.kpt0 is not None
                    else np.zeros((R, J), bool))
            joints = np.where(have[..., None], np.nan_to_num(self.kpt0) if self.kpt0 is not None
                              else 0.0, placed)
            x[:, lay.joints] = joints.reshape(R, 3 * J)
            jvar = (np.einsum("rjii->rji", self.kpt0_cov) if self.kpt0_cov is not None
                    else np.full((R, J, 3), np.inf))
            var[:, lay.joints] = np.where(have[..., None], jvar, np.inf).reshape(R, 3 * J)
        return FrameState(x, var, cov6)


def prepare(scene: Scene, clip_tol_px: float = 1.0, sigma_px: float | None = None,
            kpt_sigma_px: float | None = None, robust: RobustConfig | None = None) -> Prepared:
    """Rows, robust per-frame fits, noise levels and input checks (see the module doc)."""
    robust = robust or RobustConfig()
    rows = build_rows(scene, clip_tol_px)
    cams = Cams.of(scene.rig, scene.box_model)
    J = scene.obs.n_joints
    use_box = bool(np.isfinite(rows.box_z).any())
    use_kpt = J > 0 and bool(np.isfinite(rows.kpt_z).any())
    boxes_found: BoxLevels | None = None
    kpts_found: KeypointLevels | None = None
    skel = None
    if J:
        skel = skeleton_of(scene) or skeleton_for(J)
    fit = None
    box_keep = np.zeros((len(rows), len(cams.K), 4), bool)
    reliable = np.zeros(len(rows), bool)
    sigma_box = np.ones(4)
    cuts = crowd = None
    prior = ShapePrior(np.log(PERSON_SEMI_AXES_M), np.full(3, 0.25), "person size (no boxes)")
    if use_box:
        fit, box_keep, sigma_box, prior, boxes_found, cuts, crowd = _robust_box_fits(
            scene, rows, cams, robust, sigma_px)
        views = rows.box_mask.any(axis=2)
        whole = (views & np.all(box_keep | ~rows.box_mask, axis=2)).sum(axis=1)
        none_rejected = ~np.any(rows.box_mask & ~box_keep, axis=(1, 2))
        reliable = fit.ok & (((views.sum(axis=1) >= 2) & none_rejected) | (whole >= 3))
    kpt0 = kpt0_cov = None
    kpt_keep = np.zeros((len(rows), len(cams.K), J), bool)
    kpt_reliable = np.zeros((len(rows), J), bool)
    sigma_kpt = np.ones(J)
    kpt_var = np.ones((len(rows), len(cams.K), J))
    if use_kpt:
        kpt0, kpt0_cov, kpt_keep, sigma_kpt, curve, kpts_found = _robust_keypoints(scene, rows, cams, robust,
                                                                                   kpt_sigma_px)
        n_in = kpt_keep.sum(axis=1)
        n_seen = np.isfinite(rows.kpt_z[..., 0]).sum(axis=1)
        kpt_reliable = np.isfinite(kpt0[..., 0]) & ((n_in >= 3) | ((n_in == 2) & (n_seen == 2)))
        conf = np.maximum(rows.kpt_conf, CONF_FLOOR)
        kpt_var = sigma_kpt[None, None, :] ** 2 * curve(conf)
        if not use_box:
            prior = ShapePrior(np.log(PERSON_SEMI_AXES_M), np.full(3, 0.25),
                               "person size around the joints")
            _check_determined(scene, rows, kpt0)
    return Prepared(rows=rows, cams=cams, layout=StateLayout(J if use_kpt else 0), use_box=use_box,
                    use_kpt=use_kpt, fit=fit, box_keep=box_keep, fit_reliable=reliable, kpt0=kpt0,
                    kpt0_cov=kpt0_cov, kpt_keep=kpt_keep, kpt_reliable=kpt_reliable, sigma_box=sigma_box,
                    sigma_kpt=sigma_kpt, kpt_var=kpt_var, shape_prior=prior, skeleton=skel, robust=robust,
                    info=PreparationSummary(boxes_found, kpts_found),
                    box_tail=float(boxes_found.tail_variance_ratio) if boxes_found is not None else 1.0,
                    box_cut=cuts.dropped if cuts is not None else None,
                    box_cut_by=np.where(cuts.dropped, cuts.by, -1) if cuts is not None else None,
                    box_var_scale=crowd.scale() if crowd is not None else None)


def disagreement_scale(chi2_sum: F64, dof: F64, tail_p: float = 0.01) -> F64:
    """Covariance scale of a fit from its residual chi-square: the reduced chi-square where
    it lies beyond the ``1 - tail_p`` quantile (the views disagree more than their noise
    explains), else 1. Scaling by ``max(reduced, 1)`` everywhere would bias every covariance
    up (most of all with 1 dof)."""
    from scipy.special import chdtri  # = scipy.stats.chi2.isf(p, d), without importing stats

    d = np.maximum(np.asarray(dof, dtype=np.float64), 1.0)
    red = np.asarray(chi2_sum, dtype=np.float64) / d
    out = np.where((np.asarray(dof) > 0) & (chi2_sum > chdtri(d, tail_p)), red, 1.0)
    return np.where(np.isfinite(out), out, 1.0)


def check_in_front(scene: Scene, rows: Rows, fit: BoxFit, cams: Cams) -> None:
    """Raise :class:`InputError` for a box whose object the other views place behind that
    camera: a fit that lands behind one of its own cameras is refitted without each of its boxes
    in turn, and the error names a camera ``v`` whose object the fit without ``v``'s box places in
    front of every other camera that sees it (two or more: one view's depth is the shape prior's)
    and behind ``v`` (a camera facing away from the scene), those other views fitting it as the
    typical object-frame's views do (:data:`IN_FRONT_AGREE`), or a camera with at least half of its
    boxes behind it. Elsewhere (two views, one of them a sliver of a person almost hidden by a
    nearer one, the other cut by the image border) the views do not place the object at all and
    the robust steps decide."""
    seen = (rows.obs_row >= 0) & np.all(np.isfinite(rows.box_z), axis=-1)
    bad = seen & fit.ok[:, None] & ~(fit.margin > 0)
    most = bad.sum(axis=0) >= 0.5 * np.maximum(seen.sum(axis=0), 1)  # (C,) a camera facing away
    doubt = np.flatnonzero(bad.any(axis=1) & ~(bad & most[None, :]).any(axis=1))
    if doubt.size:  # every (row, view) of those rows refitted without that view, in one batch
        r, v = np.nonzero(seen[doubt])
        r = doubt[r]
        k = np.arange(len(r))
        mask = rows.box_mask[r].copy()
        mask[k, v] = False
        again = fit_boxes(rows.box_z[r], mask, cams)
        front = (again.margin > 0) | ~seen[r]
        behind_v = ~front[k, v]
        front[k, v] = True
        # the other views must agree on the place they give it: their refit fits them as the
        # typical object-frame's fit fits its boxes (boxes cut by nearer people can place it
        # metres off, behind a camera that does see it)
        agree = _rms_px(again) <= IN_FRONT_AGREE * np.nanmedian(_rms_px(fit))
        blamed = (seen[r].sum(axis=1) >= 3) & again.ok & front.all(axis=1) & behind_v & agree
        bad[doubt] = False
        bad[r[blamed], v[blamed]] = True
    if bad.any():
        r, c = np.argwhere(bad)[0]
        where = scene.obs.origin[rows.obs_row[r, c]]
        raise InputError(where, f"the object of this box is behind camera "
                                f"{scene.rig.cameras[c].name} (the other views place it at "
                                f"{np.round(fit.center_world[r], 2).tolist()} m): "
                                f"box and calibration disagree")


#: A refit whose boxes' rms residual is above this many times the typical object-frame's does not
#: place its object well enough to say a camera sees it from behind (:func:`check_in_front`).
IN_FRONT_AGREE = 3.0


def _rms_px(fit: BoxFit) -> F64:
    """``(R,)`` each fit's rms edge residual (px) over its used edges (NaN: none)."""
    r = fit.residual_px
    ok = np.isfinite(r)
    n = ok.sum(axis=(1, 2))
    sq = (np.where(ok, r, 0.0) ** 2).sum(axis=(1, 2))
    return np.where(n > 0, np.sqrt(sq / np.maximum(n, 1)), np.nan)


def _merge_fit(fit: BoxFit, sel: np.ndarray, sub: BoxFit) -> BoxFit:
    """``fit`` with rows ``sel`` replaced by ``sub``."""
    out = {}
    for k in fit.__dataclass_fields__:
        a = getattr(fit, k).copy()
        a[sel] = getattr(sub, k)
        out[k] = a
    return BoxFit(**out)


def _edge_residuals(fit: BoxFit, keep: np.ndarray) -> tuple[F64, F64, np.ndarray]:
    """The kept edges' squared residuals ``(R, C, 4)`` (0 where unused), each edge's degrees of
    freedom (its share of its fit's edges minus 6) and which edges are used."""
    n = np.maximum(fit.n_edges, 1.0)
    share = np.clip((fit.n_edges - 6) / n, 0.0, 1.0)  # each edge's share of the row's dof
    use = keep & (share[:, None, None] > 0) & np.isfinite(fit.residual_px)
    r2 = np.where(use, fit.residual_px, 0.0) ** 2
    return r2, np.broadcast_to(share[:, None, None], keep.shape), use


def _core_sigma(fit: BoxFit, keep: np.ndarray) -> float:
    """The box-edge noise sd (px) of the typical edge
    (:func:`gt3dkit.fusion.preparation.robust.median_variance` of the kept edges' residuals)."""
    r2, dof, use = _edge_residuals(fit, keep)
    v = median_variance(r2[use], dof[use])
    return float(np.sqrt(max(v, 0.1**2))) if np.isfinite(v) else float("nan")


def _edge_sigmas(fit: BoxFit, keep: np.ndarray, robust: RobustConfig) -> tuple[F64, F64]:
    """Box-edge noise sd (px) from the kept edges' residuals (dof: edges minus 6 per
    object-frame): ``(4,)`` the one level every edge is weighted with, and ``(4,)`` each edge
    kind's own level (a diagnostic). The kinds differ on real labels (a person's feet make
    a sharp bottom edge, swinging arms ragged side edges), but weighting them apart was
    worse against MultiviewX's ground positions (16.4 vs 12.1 mm): the differences are the
    ellipsoid model's misfit, not noise, and the sharpest edge is not the truest."""
    r2, dof, use = _edge_residuals(fit, keep)
    glob, out = group_variances(r2, dof, use, np.arange(4), 4, robust.reject_p, 1)
    out = np.where(np.isfinite(out) & (out > 0), out, 1.0)
    g = glob if np.isfinite(glob) and glob > 0 else 1.0
    return np.full(4, np.sqrt(max(g, 0.1**2))), np.sqrt(np.maximum(out, 0.1**2))


def _shape_prior(fit: BoxFit, views: np.ndarray) -> ShapePrior:
    """The shape prior of weakly seen object-frames: the median and robust spread of the log
    semi-axes of the fits of object-frames at least :data:`PRIOR_MIN_VIEWS` cameras see
    (``views (R,)``), or a person's size where fewer than 5 are."""
    good = fit.ok & (views >= PRIOR_MIN_VIEWS)
    if good.sum() >= 5:
        la = fit.log_axes[good]
        med = np.median(la, axis=0)
        sd = np.clip(1.4826 * np.median(np.abs(la - med), axis=0), 0.05, 1.0)
        return ShapePrior(med, sd, f"median and spread of {int(good.sum())} object-frames "
                                   f"seen by >= {PRIOR_MIN_VIEWS} cameras")
    return ShapePrior(np.log(PERSON_SEMI_AXES_M), np.full(3, 0.25),
                      "person size (too few object-frames seen by 3+ cameras)")


def _robust_box_fits(scene: Scene, rows: Rows, cams: Cams, robust: RobustConfig,
                     sigma_px: float | None
                     ) -> tuple[BoxFit, np.ndarray, F64, ShapePrior, BoxLevels, CutEdges | None,
                                CrowdLevels | None]:
    """Per-frame box fits weighted by per-edge noise; edges rejected by their leave-one-out
    score; edges cut by a nearer object left out where they mislead (``rows.box_mask`` updated;
    the cut edges where some were left out, or None); shape prior for weakly seen object-frames;
    the crowding bands' levels (:mod:`gt3dkit.fusion.preparation.crowd`; None where the noise is
    given)."""
    keep = rows.box_mask.copy()
    fit = fit_boxes(rows.box_z, keep, cams)
    check_in_front(scene, rows, fit, cams)

    def sigmas(f: BoxFit) -> F64:
        return np.full(4, float(sigma_px)) if sigma_px is not None else _edge_sigmas(f, keep,
                                                                                      robust)[0]

    def params(f: BoxFit, sel: np.ndarray | slice = slice(None)) -> F64:
        return np.concatenate([f.center_world[sel], f.log_axes[sel]], 1)

    sig = sigmas(fit)
    # one noise level for every edge: the unit-weight fit is the weighted one, its covariance
    # scaled (the weak log-axes prior aside)
    fit = replace(fit, cov=fit.cov * sig[0] ** 2)
    for _ in range(2 if robust.enabled else 0):
        r = np.nan_to_num(fit.residual_px)
        var = np.broadcast_to(sig**2, r.shape)
        e2 = deleted_score2(r, var, np.nan_to_num(fit.leverage) * var, np.ones_like(r))
        bad = keep & (point_weights(e2, 1, robust) == 0)
        if not bad.any():
            break
        keep = keep & ~bad
        sel = bad.any(axis=(1, 2))
        fit = _merge_fit(fit, sel, fit_boxes(rows.box_z[sel], keep[sel], cams, sig,
                                             p0=params(fit, sel)))
        sig = sigmas(fit)
    # edges a nearer object cut, where the data say they mislead (gt3dkit.fusion.preparation.occlusion): left
    # out as the border's are
    cuts = None
    if robust.enabled:
        level = _core_sigma(fit, keep)
        cuts = cut_edges_of(rows, cams, fit, keep, level if np.isfinite(level) else float(sig[0]),
                            robust.cut_variance_ratio)
        if cuts.dropped.any():
            rows.box_mask[cuts.dropped] = False
            keep = keep & ~cuts.dropped
            sel = np.asarray(cuts.dropped.any(axis=(1, 2)))
            fit = _merge_fit(fit, sel, fit_boxes(rows.box_z[sel], keep[sel], cams, sig, p0=params(fit, sel)))
    nv = np.all(np.isfinite(rows.box_z), axis=-1).sum(axis=1)
    prior = _shape_prior(fit, nv)
    weak = fit.ok & (nv < PRIOR_MIN_VIEWS)
    if weak.any():
        fit = _merge_fit(fit, weak, fit_boxes(rows.box_z[weak], keep[weak], cams, sig,
                                              prior_log_axes=prior.mean, prior_sd=prior.sd,
                                              p0=params(fit, weak)))
    # the filters weight an edge by the typical edge's noise; the tails beyond it (a person is
    # not an ellipsoid's tangent box: side edges 2-6 px off where the feet are within 0.5 px)
    # are the model's misfit, not outliers: their tests are made at the whole level
    core = float(sig[0]) if sigma_px is not None else _core_sigma(fit, keep)
    core = min(core, float(sig[0])) if np.isfinite(core) else float(sig[0])
    tail = (float(sig[0]) / core) ** 2
    crowd = crowd_levels(rows, *_edge_residuals(fit, keep), robust.reject_p) if sigma_px is None else None
    info = BoxLevels(
        scene.box_model, scene.box_model_px, float(sig[0]), core, tail,
        dict(zip(BOX_EDGES, _edge_sigmas(fit, keep, robust)[1].round(4).tolist(), strict=True)),
        "given" if sigma_px is not None else
        "robust residual level of the per-frame fits (kept edges, with dof); the filters weight "
        "each edge by sigma_px_core (the median edge's level) and test it against sigma_px",
        int((rows.box_mask & ~keep).sum()), cuts.as_json() if cuts is not None else None,
        int(rows.box_mask.sum()),
        {"semi_axes_m": np.exp(prior.mean).round(4).tolist(), "log_sd": prior.sd.round(4).tolist(),
         "source": prior.source}, crowd.as_json() if crowd is not None else None)
    left_out = cuts if cuts is not None and cuts.dropped.any() else None
    return fit, keep, np.full(4, core), prior, info, left_out, crowd


def _robust_keypoints(scene: Scene, rows: Rows, cams: Cams, robust: RobustConfig,
                      kpt_sigma_px: float | None
                      ) -> tuple[F64, F64, np.ndarray, F64, ConfidenceCurve, KeypointLevels]:
    """Per-frame robust triangulation of every joint, per-joint noise, input checks."""
    R, C, J = rows.kpt_z.shape[:3]
    obs = np.swapaxes(rows.kpt_z, 1, 2).reshape(R * J, C, 2)
    xy = normalized_points(obs, cams.K, cams.dist)
    f = cams.K[:, [0, 1], [0, 1]].mean(axis=1)
    conf = np.swapaxes(np.maximum(rows.kpt_conf, CONF_FLOOR), 1, 2).reshape(R * J, C)
    seen = np.isfinite(obs[..., 0])
    diag = float(np.median(np.hypot(cams.wh[:, 0], cams.wh[:, 1])))
    g2 = chi2_isf(robust.reject_p, 2)
    joint_of = np.tile(np.arange(J), R)

    def joint_sigmas(e2: F64, keep: np.ndarray) -> tuple[F64, float, ConfidenceCurve]:
        """The joints' levels (sd, px, at full confidence), the overall one and the curve."""
        n_in = keep.sum(axis=1)
        share = np.clip((2 * n_in - 3) / np.maximum(2 * n_in, 1), 0.0, 1.0)
        dof = np.broadcast_to((2 * share)[:, None], keep.shape)
        use = keep & (n_in[:, None] >= 3)
        curve, level = learn_curve(np.where(keep, e2, np.nan), dof, use, conf, joint_of[:, None], J,
                                   robust.reject_p)
        glob, _ = group_variances(np.where(keep, e2 / curve(conf), np.nan), dof, use, joint_of[:, None], J,
                                  robust.reject_p, 2)
        glob = glob if np.isfinite(glob) and glob > 0 else 1.0
        level = np.where(np.isfinite(level) & (level > 0), level, glob)
        return np.sqrt(np.maximum(level, 0.05**2)), float(np.sqrt(max(glob, 0.05**2))), curve

    thr1 = max(0.015 * diag, 4.0) if robust.enabled else np.inf
    X, keep, e2 = robust_triangulate(xy, cams.R, cams.t, f, thr1, 1.0 / conf, cams.depth_sign)
    _check_keypoints_in_front(scene, rows, e2, seen, X, J)
    if kpt_sigma_px is not None:
        sig_j = np.full(J, float(kpt_sigma_px))
        sig = float(kpt_sigma_px)
        curve = INVERSE
    else:
        sig_j, sig, curve = joint_sigmas(e2, keep)
    if robust.enabled:
        scale = (sig_j[joint_of] / sig)[:, None] ** 2 * curve(conf)
        X, keep, e2 = robust_triangulate(xy, cams.R, cams.t, f, float(np.sqrt(g2)) * sig, scale,
                                         cams.depth_sign)
        if kpt_sigma_px is None:
            sig_j, sig, curve = joint_sigmas(e2, keep)
    w = np.where(keep, 1.0 / (sig_j[joint_of][:, None] ** 2 * curve(conf)), 0.0)
    cov = triangulation_cov(np.nan_to_num(X), cams.R, cams.t, f, w)
    # a point whose views disagree beyond what their noise explains is trusted less
    n_in = keep.sum(axis=1)
    chi = np.sum(np.where(keep, e2, 0.0) * w, axis=1)
    cov = cov * disagreement_scale(chi, 2 * n_in - 3)[:, None, None]
    cov[~np.all(np.isfinite(X), axis=1)] = np.inf
    kept = np.swapaxes(keep.reshape(R, J, C), 1, 2)
    info = KeypointLevels(
        sig, sig_j.round(4).tolist(),
        "given" if kpt_sigma_px is not None else
        "robust reprojection level of the per-frame triangulation (kept points, with dof)",
        int(seen.sum()), int((seen & ~keep).sum()),
        curve.info() if scene.obs.kpt_conf is not None else "none given")
    return (X.reshape(R, J, 3), cov.reshape(R, J, 3, 3), kept, sig_j, curve, info)


def _check_keypoints_in_front(scene: Scene, rows: Rows, e2: F64, seen: np.ndarray, X: F64,
                              J: int) -> None:
    """A camera whose keypoints lie behind it wherever the other views place the joint."""
    determined = np.all(np.isfinite(X), axis=1)[:, None] & seen
    behind = determined & np.isinf(e2)
    n_det = determined.sum(axis=0)
    n_behind = behind.sum(axis=0)
    bad = np.flatnonzero((n_behind > 0) & (n_behind * 2 >= n_det))
    if bad.size:
        c = int(bad[0])
        k = int(np.flatnonzero(behind[:, c])[0])
        r, j = divmod(k, J)
        raise InputError(scene.obs.origin[rows.obs_row[r, c]],
                         f"joint {j} triangulates behind camera {scene.rig.cameras[c].name} "
                         f"(as do {int(n_behind[c])} of the {int(n_det[c])} joints it saw that "
                         f"other views place): keypoints and calibration disagree")


def _undetermined(rows: Rows, kpt0: F64) -> np.ndarray:
    """Keypoints only: the objects ``(O,)`` no two views ever agree on (no 3D position)."""
    have = np.isfinite(kpt0[..., 0]).any(axis=1)  # (R,)
    ever = np.zeros(len(rows.obj_ids), bool)
    np.logical_or.at(ever, rows.row_o, have)
    return ~ever


def _check_determined(scene: Scene, rows: Rows, kpt0: F64) -> None:
    """Keypoints only: an object no two views ever agree on has no 3D position (an error naming
    its id and its first keypoint: the user's own ids name a person the data cannot place)."""
    bad = _undetermined(rows, kpt0)
    if bad.any():
        o = int(np.flatnonzero(bad)[0])
        r, c = np.argwhere((rows.row_o == o)[:, None] & (rows.obs_row >= 0))[0]
        first = scene.obs.origin[int(rows.obs_row[r, c])]
        cams = sorted({scene.rig.names[int(k)] for k in np.flatnonzero((rows.obs_row[rows.row_o == o] >= 0)
                                                                         .any(axis=0))})
        raise InputError(first, f"id {int(rows.obj_ids[o])} is never seen by two cameras at once (that "
                                f"agree; it is seen by {', '.join(cams)}): its 3D position is undetermined "
                                f"from keypoints alone: give it a second view, or leave id "
                                f"{int(rows.obj_ids[o])} out")


def undetermined_objects(scene: Scene, robust: RobustConfig | None = None) -> I64:
    """The ids of a keypoints-only scene that no two views ever agree on (what :func:`prepare`
    refuses): the per-frame robust triangulation of :func:`prepare`, nothing else."""
    rows = build_rows(scene)
    if scene.obs.n_joints == 0 or np.isfinite(rows.box_z).any() or not np.isfinite(rows.kpt_z).any():
        return np.zeros(0, np.int64)
    kpt0 = _robust_keypoints(scene, rows, Cams.of(scene.rig, scene.box_model), robust or RobustConfig(),
                             None)[0]
    return np.asarray(rows.obj_ids[_undetermined(rows, kpt0)], dtype=np.int64)


def never_determined(rows: Rows, kpt0: F64) -> np.ndarray:
    """(R, J) joints whose object's views never placed them in any frame (no two views agreeing:
    ``kpt0 (R, J, 3)``, the per-frame triangulation, never finite): one view alone gives a ray,
    not a point; the estimate there would be the canonical pose's guess along it."""
    return _never(rows, np.isfinite(kpt0[..., 0]), kpt0.shape[1])


def _never(rows: Rows, have: np.ndarray, n_joints: int) -> np.ndarray:
    ever = np.zeros((len(rows.obj_ids), n_joints), bool)
    np.logical_or.at(ever, rows.row_o, have)
    return ~ever[rows.row_o]


def ellipsoid_around(kpt: F64, kpt_sd: F64, world_from_body: F64, pad_m: float = 0.1,
                     known_sd_m: float = 0.1) -> tuple[F64, F64, F64]:
    """Axis-aligned (body frame) ellipsoid around each row's joints ``(R, J, 3)``.

    Centre = middle of the extent of the joints the row knows (sd at most ``known_sd_m``, or
    3x the row's median joint sd if that is larger; all joints where none is known), semi-axes =
    half extent + ``pad_m`` (limbs have thickness); centre sd = RMS of those joints' sd. A joint
    no view has seen for a while is an extrapolation with a metre-sized sd: it must not stretch
    the person's ellipsoid (on the real Panoptic data two unseen ears, extrapolated below the
    floor, dragged a person's centre 1.5 m down). NaN where a row has no finite joint.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows stay NaN
        limit = np.maximum(known_sd_m, 3 * np.nanmedian(kpt_sd, axis=1))  # (R,)
    known = np.isfinite(kpt_sd) & (kpt_sd <= limit[:, None])
    use = np.where(np.asarray(known.any(axis=1))[:, None], known, True)
    kpt = np.where(use[..., None], kpt, np.nan)
    kpt_sd = np.where(use, kpt_sd, np.nan)
    body = np.einsum("ji,rkj->rki", world_from_body, kpt)  # body coordinates
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows stay NaN
        lo, hi = np.nanmin(body, axis=1), np.nanmax(body, axis=1)
        sd = np.sqrt(np.nanmean(kpt_sd**2, axis=1))
    centre = np.einsum("ij,rj->ri", world_from_body, (lo + hi) / 2)
    semi = (hi - lo) / 2 + pad_m
    return centre, semi, np.repeat(sd[:, None], 3, axis=1)


def axis_sd(cov: F64) -> F64:
    r"""``(..., 3, 3)`` covariances -> ``(..., 3)`` per-axis sds that are safe to use one axis
    at a time: the marginal sds widened by the largest eigenvalue ``k`` of the correlation
    matrix, ``sd_i = sqrt(k Sigma_ii)``.

    Then ``sum_i (e_i / sd_i)^2 <= e^T Sigma^{-1} e`` for every error ``e``, so the per-axis
    check a user makes is at least as often passed as a chi-square with 3 dof says. The
    marginal sds alone would fail it where the axes are correlated (one camera: the whole
    error lies along its ray and is counted in every axis). ``k`` is 1 for uncorrelated axes.
    """
    var = np.einsum("...ii->...i", cov)
    out = np.full(var.shape, np.nan)
    ok = np.all(np.isfinite(cov), axis=(-1, -2)) & np.all(var > 0, axis=-1)
    if ok.any():
        d = np.sqrt(var[ok])
        corr = cov[ok] / (d[..., :, None] * d[..., None, :])
        k = np.linalg.eigvalsh(corr)[..., -1]
        out[ok] = d * np.sqrt(np.maximum(k, 1.0))[..., None]
    return out


def largest_sd(cov: F64) -> F64:
    """``(..., 3, 3)`` covariances -> ``(...)`` square root of the largest eigenvalue."""
    out = np.full(cov.shape[:-2], np.nan)
    ok = np.all(np.isfinite(cov), axis=(-1, -2))
    if ok.any():
        out[ok] = np.sqrt(np.maximum(np.linalg.eigvalsh(cov[ok])[..., -1], 0.0))
    return out


