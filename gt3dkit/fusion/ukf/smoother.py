r"""The primary estimator: the paper's per-object UKF, batched, robust, plus an RTS pass.

This module is the driver only; preparation (rows, robust per-frame fits, noise levels,
input checks) is :mod:`gt3dkit.fusion.preparation.prepare`, the measurement model
:mod:`gt3dkit.fusion.ukf.measurement`, the motion model :mod:`gt3dkit.fusion.motion` and the
filter steps :mod:`gt3dkit.fusion.ukf.sigma`.

What differs from the paper's obvious implementation (and why):

* **One stacked update per frame.** All cameras' box edges and keypoints of an object form
  one measurement vector (masked where missing or clipped); all objects of a frame are one
  batch. Information form, iterated (posterior linearisation), cubature weights.
* **Robust.** The update reweights every keypoint and box edge by its leave-one-out score
  against the prior and the *other* views (:mod:`gt3dkit.fusion.preparation.robust`), starting from
  the robust per-frame fits' verdicts, so one bad view cannot drag the state first. A
  rejected point has weight 0: it moves neither its frame nor, through the RTS pass, its
  neighbours. Every down-weighted point is reported (``TrackSet.downweighted``).
* **Weak priors.** Where the prediction says less than the frame's own views (after a gap,
  at a re-appearance, with a large process noise) the update linearises at the per-frame
  fit, not at the far-off prediction. Objects start from their first per-frame fit *with its
  covariance* (a single view's depth is as uncertain as the object's size).
* **Noise from the data.** Measurement noise from the per-frame residuals (robust, per
  joint); process noise by maximising the forward pass's likelihood with a bounded 1-D
  search on log scale (a coarse scan, then bisection and a parabola around the best value,
  several values per filter pass), so it cannot stop at a grid edge. The whole curve is in
  ``meta.json``.
* **Honest uncertainty.** When the innovations say the noise model is optimistic (NIS per
  degree of freedom above 1) every covariance is inflated by that ratio; a joint's reported
  sd is its largest axis.
* **Backward RTS pass** (offline ground truth may use the future).

Keypoints join the same state and update: each joint and its velocity (constant velocity),
measured by the projection with distortion. A person's bone lengths tie its joints together:
the lengths (and spread) come from a first pass, and a robust Gauss-Newton fit of the first
pass's smoothed joints to them gives each joint a Gaussian message (expectation propagation,
:mod:`gt3dkit.fusion.ukf.bones`) that the final pass adds to that joint's own filter, so the joints
still run as separate small filters.
"""

from __future__ import annotations

import time
from dataclasses import asdict, replace

import numpy as np

from gt3dkit.fusion.base import Capabilities
from gt3dkit.fusion.motion import StateLayout
from gt3dkit.fusion.preparation.prepare import (
    Prepared,
    axis_sd,
    ellipsoid_around,
    largest_sd,
    never_determined,
    prepare,
)
from gt3dkit.fusion.preparation.rows import Rows, nearest_same_object
from gt3dkit.fusion.ukf.blockcov import BlockCov
from gt3dkit.fusion.ukf.bones import (
    BoneLengths,
    BoneSamples,
    JointInfo,
    PersonBones,
    bone_messages,
    bone_samples,
    lengths_of,
)
from gt3dkit.fusion.ukf.config import UKFConfig
from gt3dkit.fusion.ukf.filtering import (
    initial_states,
    objects_rows,
    rerun_objects,
    run_filter,
    smoothed_weights,
)
from gt3dkit.fusion.ukf.filterrun import FilterRun
from gt3dkit.fusion.ukf.initial import Init
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.fusion.ukf.noise import NOISE_FIELDS, noise_by_likelihood, select_noise
from gt3dkit.skeletons import Skeleton
from gt3dkit.types import F64, Downweighted, JsonDict, RobustSummary, RunInfo, Scene, TrackSet


class UKFSmoother:
    """Forward UKF + backward RTS over all objects of a scene, one batch per frame."""

    name = "ukf"

    def __init__(self, config: UKFConfig | None = None, bones: PersonBones | None = None) -> None:
        self.config = config or UKFConfig()
        self.bones = bones  # persons' bone lengths found outside the run (gt3dkit.windows)
        self.capabilities = Capabilities(process_noise=True, bone_samples=bool(self.config.bones))

    def prepare(self, scene: Scene) -> Prepared:
        cfg = self.config
        return prepare(scene, cfg.clip_tol_px, cfg.sigma_px, cfg.kpt_sigma_px, cfg.robust_config)

    def process_noise(self, scene: Scene, pre: Prepared | None = None) -> dict[str, float]:
        """The process noise :meth:`estimate` would run ``scene`` with (the settings the config
        leaves ``None`` found by :func:`select_noise`), without the rest of the estimate: what
        :mod:`gt3dkit.windows` fixes once for all the windows of a long sequence."""
        found, _ = noise_by_likelihood(pre or self.prepare(scene), scene.fps, self.config)
        return {k: float(v) for k in NOISE_FIELDS if (v := getattr(found, k)) is not None}

    def bone_samples(self, scene: Scene, pre: Prepared | None = None) -> BoneSamples | None:
        """The first pass's bones of every row (``obj``: the person's id) that :meth:`estimate`
        would tie the joints with, without the rest of the estimate (None: it ties none): what
        the windows of a long sequence pool for one estimate of each person's bones."""
        pre = pre or self.prepare(scene)
        if not (pre.use_kpt and self.config.bones and pre.skeleton is not None):
            return None
        model, _, _, _, run = self._first_pass(scene, pre)
        s = bone_samples_of(model, first_joints(model, run), pre.skeleton)
        return replace(s, obj=model.rows.obj_ids[s.obj])

    def _first_pass(self, scene: Scene, pre: Prepared
                    ) -> tuple[Model, Init, UKFConfig, JsonDict, FilterRun]:
        """The model, start, chosen noise and its search, and the filter's and smoother's first
        pass (the views reweighted by the smoothed estimate)."""
        model = Model.of(pre)
        init = initial_states(model, self.config)
        cfg, search = select_noise(model, init, self.config, pre, scene.fps)
        run = run_filter(model, init, cfg, scene.fps, collect=True)
        if cfg.robust and model.robust_blocks:
            # second pass: the weights start from every point's verdict against the smoothed
            # estimate, which knows the future too (a bad view in an object's first frame,
            # where the forward pass had only the frame itself to judge by). Objects are
            # independent: only those with a changed verdict are run again.
            w0 = smoothed_weights(model, run.x, cfg)
            changed = objects_rows(model.rows, np.any((w0 != model.weight0) & model.mask, axis=1))
            model = replace(model, weight0=w0)
            if changed.all():  # the first pass's states go before the second's are made
                first = run.scalars()
                del run
                run = run_filter(model, init, cfg, scene.fps, collect=True).after(first)
            elif changed.any():
                run = rerun_objects(model, init, cfg, scene.fps, run, changed)
        return model, init, cfg, search, run

    def estimate(self, scene: Scene, pre: Prepared | None = None) -> TrackSet:
        t0 = time.perf_counter()
        pre = pre or self.prepare(scene)
        rows, cams, layout = pre.rows, pre.cams, pre.layout
        R = len(rows)
        model, init, cfg, search, run = self._first_pass(scene, pre)
        bone_info: JsonDict = {}
        if pre.use_kpt and cfg.bones and pre.skeleton is not None:
            # the bones' messages from the first pass's smoothed joints, added to each joint's
            # own filter run again (the views reweighted as before)
            msgs, lengths = bone_messages_of(model, cfg, run, pre.skeleton, self.bones)
            del run  # the first pass's covariances go before the second's are made
            run = run_filter(replace(model, joint_info=msgs), init, cfg, scene.fps, collect=True)
            bone_info = lengths.info(rows.obj_ids)
        x_s = run.x
        P_s: F64 | BlockCov = run.P
        nis = run.mean_nis_per_dof
        inflation = max(nis, 1.0) if cfg.inflate and np.isfinite(nis) else 1.0
        if inflation != 1.0:
            # in place: P_s is this run's own array (or its blocks)
            if isinstance(P_s, BlockCov):
                P_s *= inflation
            else:
                P_s *= inflation
        centre = x_s[:, layout.center]
        semi = np.exp(x_s[:, layout.log_axes])
        P_c, widened = widen_weak_rows(P_s[:, layout.center, layout.center], pre, scene.fps)
        centre, semi, P_c, lone_ids = single_views_as_fitted(pre, centre, semi, P_c)
        sd = axis_sd(P_c)
        kpt = np.zeros((R, 0, 3))
        kpt_sd = np.zeros((R, 0))
        if pre.use_kpt:
            kpt0 = pre.kpt0 if pre.kpt0 is not None else np.full((R, layout.n_joints, 3), np.nan)
            kpt, kpt_sd = joints_of(x_s, P_s, layout, rows, kpt0)
            if not pre.use_box:
                centre, semi, sd = ellipsoid_around(kpt, kpt_sd, cams.world_from_body)
        down = downweighted_of(model, run)
        robust = RobustSummary(bool(cfg.robust), int(np.sum(down.weight > 0)), int(np.sum(down.weight == 0)),
                               "leave-one-out score against prior + other views; weight 1 below the "
                               f"chi-square tail probability {cfg.huber_p:g}, 0 beyond {cfg.reject_p:g}")
        boxes, kpts = pre.info.boxes if pre.use_box else None, pre.info.keypoints
        params: JsonDict = {**asdict(cfg), "sigma_px": boxes.sigma_px if boxes is not None else None,
                            "sigma_px_core": boxes.sigma_px_core if boxes is not None else None,
                            "kpt_sigma_px": kpts.sigma_px if kpts is not None else None,
                            "fps": scene.fps}
        details: JsonDict = {
            **run.summary(),
            "covariance_inflation": inflation,
            "single_view_rows_widened": widened,
            "single_view_objects": {
                "ids": lone_ids,
                "note": "never seen by two box views at once: their rows are the per-frame fits "
                        "(depth from the learnt shape prior, with its spread), not the smoother's "
                        "(whose motion model would read distance from how much a walker "
                        "accelerates)"},
            "noise_search": search,
            "noise_source": {
                "sigma_px": pre.info.boxes.sigma_source if pre.info.boxes is not None else None,
                "kpt_sigma_px": kpts.sigma_source if kpts is not None else None,
                "process": ("given" if self.config.accel_sd and (self.config.joint_accel_sd
                                                                  or not pre.use_kpt)
                            else "max likelihood of the forward pass: log-spaced scan, then "
                                 "bisection and a parabola on log scale (curve in noise_search)")},
            "measurements": {"boxes": pre.use_box, "keypoints": pre.use_kpt,
                             "skeleton": pre.skeleton.name if pre.use_kpt and pre.skeleton
                             else None},
            "preparation": pre.info.as_json(),
        }
        info = RunInfo(self.name, params, time.perf_counter() - t0, robust=robust,
                       bones=bone_info or None, details=details)
        return TrackSet(
            frame=rows.frames[rows.row_t], track_id=rows.obj_ids[rows.row_o],
            center_world=centre, semi_axes=semi, center_sd=sd, n_views=rows.n_views,
            kpt_world=kpt, kpt_sd=kpt_sd, info=info, downweighted=down)


def single_views_as_fitted(pre: Prepared, centre: F64, semi: F64, P_c: F64
                           ) -> tuple[F64, F64, F64, list[int]]:
    """The smoothed ``centre, semi (R, 3)`` and centre covariances ``P_c (R, 3, 3)`` with the rows
    of objects no two box views ever see at once (:func:`single_view_rows`) taken from their
    per-frame fits (depth from the shape prior, with its spread); and those objects' ids."""
    if not pre.use_box or pre.fit is None:
        return centre, semi, P_c, []
    lone = single_view_rows(pre)
    if not lone.any():
        return centre, semi, P_c, []
    centre, semi, P_c = centre.copy(), semi.copy(), P_c.copy()
    centre[lone] = pre.fit.center_world[lone]
    semi[lone] = np.exp(pre.fit.log_axes[lone])
    P_c[lone] = pre.fit.cov[lone][:, :3, :3]
    rows = pre.rows
    return centre, semi, P_c, sorted({int(i) for i in rows.obj_ids[rows.row_o[lone]]})


def widen_weak_rows(P_c: F64, pre: Prepared, fps: float, support_s: float = 1.0
                    ) -> tuple[F64, int]:
    """Centre covariances ``(R, 3, 3)`` of object-frames seen by one box view, far (more than
    ``support_s``) from any frame of the object that two views see, widened to at least their
    own per-frame fit's spread along its weakest direction (the viewing ray).

    One view fixes the direction to the object, not its distance: that comes from the shape
    prior, and a smoother also reads it from the motion model (a nearer, smaller walker
    accelerates less), which is no evidence of distance. So where no multi-view frame is
    near, the reported spread along the ray is not allowed below what the box and the shape
    prior alone say. Returns the covariances and how many rows were widened.
    """
    if pre.fit is None:
        return P_c, 0
    rows = pre.rows
    nv = np.all(np.isfinite(rows.box_z), axis=-1).sum(axis=1)
    multi = nv >= 2
    t_s = rows.frames[rows.row_t] / fps
    near = nearest_same_object(rows, multi)
    dist = np.where(multi[near], np.abs(t_s - t_s[near]), np.inf)
    weak = (nv == 1) & (dist > support_s) & pre.fit.ok
    if not weak.any():
        return P_c, 0
    cf = pre.fit.cov[weak][:, :3, :3]
    w, V = np.linalg.eigh(cf)
    d = V[..., -1]  # (K, 3) weakest direction of the single-view fit
    lam = w[..., -1]
    P = P_c.copy()
    cur = np.einsum("ki,kij,kj->k", d, P[weak], d)
    P[weak] += np.maximum(lam - cur, 0.0)[:, None, None] * d[:, :, None] * d[:, None, :]
    return P, int(weak.sum())


def single_view_rows(pre: Prepared) -> np.ndarray:
    """(R,) rows with a box view of objects that no two box views ever see at once."""
    rows = pre.rows
    if pre.fit is None:
        return np.zeros(len(rows), bool)
    nv = np.all(np.isfinite(rows.box_z), axis=-1).sum(axis=1)
    multi = np.zeros(len(rows.obj_ids), bool)
    np.logical_or.at(multi, rows.row_o, nv >= 2)
    return ~multi[rows.row_o] & (nv >= 1) & pre.fit.ok


def joints_of(x_s: F64, P_s: F64 | BlockCov, layout: StateLayout, rows: Rows, kpt0: F64) -> tuple[F64, F64]:
    """Joints ``(R, J, 3)`` and their largest-axis sd ``(R, J)``; NaN for joints an object's
    views never placed (``kpt0 (R, J, 3)``: the per-frame triangulation; :func:`never_determined`)."""
    R, J = len(rows), layout.n_joints
    kpt = x_s[:, layout.joints].reshape(R, J, 3).copy()
    idx = layout.joints.start + 3 * np.arange(J)[:, None] + np.arange(3)  # (J, 3)
    cov = P_s[:, idx[:, :, None], idx[:, None, :]]  # (R, J, 3, 3)
    sd = largest_sd(cov)
    never = never_determined(rows, kpt0)
    kpt[never] = np.nan
    sd[never] = np.nan
    return kpt, sd


def downweighted_of(model: Model, run: FilterRun) -> Downweighted:
    """The measurements the final forward pass down-weighted or rejected (``run`` collected)."""
    rows = model.rows
    J = model.layout.n_joints
    W, S2, RES = run.weights, run.score2, run.residual
    if W is None or S2 is None or RES is None:
        raise ValueError("downweighted_of needs a run that collected its weights (collect=True)")
    parts: list[tuple[np.ndarray, ...]] = []
    for sl, d in model.robust_blocks:
        w = W[:, sl][:, ::d]
        m = model.mask[:, sl][:, ::d]
        s = np.sqrt(S2[:, sl][:, ::d])
        res = np.sqrt((RES[:, sl] ** 2).reshape(len(rows), -1, d).sum(axis=2))
        r, k = np.nonzero(m & (w < 1.0))
        if d == 1:  # box edges: k = c * 4 + edge
            cam, joint, edge = k // 4, np.full(len(k), -1), k % 4
        else:  # keypoints: k = c * J + j
            cam, joint, edge = k // J, k % J, np.full(len(k), -1)
        parts.append((r, cam, joint, edge, w[r, k], res[r, k], s[r, k]))
    if not parts:
        e = np.zeros(0, dtype=np.int64)
        return Downweighted(e, e, e, e, e, np.zeros(0), np.zeros(0), np.zeros(0))
    r, cam, joint, edge, w, res, s = (np.concatenate(p) for p in zip(*parts, strict=True))
    return Downweighted(frame=rows.frames[rows.row_t[r]], cam=cam.astype(np.int64),
                        track_id=rows.obj_ids[rows.row_o[r]], joint=joint.astype(np.int64),
                        edge=edge.astype(np.int64), weight=w, residual_px=res, score=s)


def first_joints(model: Model, run: FilterRun) -> tuple[F64, F64, np.ndarray]:
    """A first pass's (split: independent joints) smoothed joints ``(R, J, 3)``, their
    covariances ``(R, J, 3, 3)`` and which views saw each ``(R, C, J)``."""
    rows, lay = model.rows, model.layout
    joints = run.x[:, lay.joints].reshape(len(rows), lay.n_joints, 3)
    idx = lay.joint_dims(np.arange(lay.n_joints))
    return joints, run.P[:, idx[:, :, None], idx[:, None, :]], np.isfinite(rows.kpt_z[..., 0])


def bone_samples_of(model: Model, first: tuple[F64, F64, np.ndarray], skel: Skeleton) -> BoneSamples:
    """:func:`gt3dkit.fusion.ukf.bones.bone_samples` of a first pass's :func:`first_joints`
    ``first``; ``obj``: each row's person index."""
    joints, cov, seen = first
    rows = model.rows
    return bone_samples(rows.row_o, rows.frames[rows.row_t], seen.sum(axis=1) >= 2, joints, cov, skel)


def bone_messages_of(model: Model, cfg: UKFConfig, run: FilterRun, skel: Skeleton,
                     fixed: PersonBones | None = None) -> tuple[JointInfo, BoneLengths]:
    """The bones' messages to every joint of every row (:mod:`gt3dkit.fusion.ukf.bones`) and each
    person's bone lengths, from a first pass ``run`` (split: independent joints); the persons
    ``fixed`` holds take its lengths."""
    rows = model.rows
    first = first_joints(model, run)
    lengths = lengths_of(bone_samples_of(model, first, skel), np.arange(len(rows.obj_ids)),
                         cfg.bone_sd_floor_m, cfg.bone_sd_m)
    if fixed is not None:
        lengths = fixed.applied(lengths, rows.obj_ids)
    joints, cov, seen = first
    bones = skel.ties  # the bones, and the pairs of each rigid group
    zb = lengths.length[rows.row_o]
    # a bone ties a joint to a measured one: where neither end has a view in a frame it would
    # only couple two extrapolations (and bend both along a sphere far from any evidence)
    seen1 = np.asarray(seen.any(axis=1))
    mb = np.isfinite(zb) & (seen1[:, bones[:, 0]] | seen1[:, bones[:, 1]])
    msgs = bone_messages(joints, cov, bones, np.nan_to_num(zb), lengths.sd[rows.row_o] ** 2, mb,
                         cfg.robust_config if cfg.robust else None)
    return msgs, lengths


