r"""The primary estimator: the paper's per-object UKF, batched, robust, plus an RTS pass.

This module is the driver only; preparation (rows, robust per-frame fits, noise levels,
input checks) is :mod:`gt3dkit.fusion.prepare`, the measurement model
:mod:`gt3dkit.fusion.measurement`, the motion model :mod:`gt3dkit.fusion.motion` and the
filter steps :mod:`gt3dkit.fusion.ukf`.

What differs from the paper's obvious implementation (and why):

* **One stacked update per frame.** All cameras' box edges and keypoints of an object form
  one measurement vector (masked where missing or clipped); all objects of a frame are one
  batch. Information form, iterated (posterior linearisation), cubature weights.
* **Robust.** The update reweights every keypoint and box edge by its leave-one-out score
  against the prior and the *other* views (:mod:`gt3dkit.fusion.robust`), starting from
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
:mod:`gt3dkit.fusion.bones`) that the final pass adds to that joint's own filter, so the joints
still run as separate small filters.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from functools import partial
from typing import Any

import numpy as np

from gt3dkit.fusion.bones import (
    BoneLengths,
    BoneSamples,
    JointInfo,
    PersonBones,
    bone_messages,
    bone_samples,
    lengths_of,
)
from gt3dkit.fusion.boxupdate import LinearisedSearch, applies_to_model, run_boxes
from gt3dkit.fusion.filterrun import FilterRun
from gt3dkit.fusion.initial import InitialCov, rows_of
from gt3dkit.fusion.jointupdate import run_joints
from gt3dkit.fusion.measurement import Model
from gt3dkit.fusion.prepare import (
    Prepared,
    axis_sd,
    ellipsoid_around,
    largest_sd,
    moment_process_noise,
    nearest_same_object,
    never_determined,
    prepare,
)
from gt3dkit.fusion.robust import RobustConfig, point_weights
from gt3dkit.fusion.rows import replicate_rows
from gt3dkit.skeletons import Skeleton
from gt3dkit.types import F64, Downweighted, Scene, TrackSet

#: The provisional robust pass that fixes the noise search's weights runs at this multiple of
#: the moment estimates of the process noise.
PROVISIONAL_LOOSENESS = 3.0
#: ... and a shape noise of at least this (the moment estimate of a shape that the per-frame
#: noise hides is its floor, which would hold every box to a rigid shape).
PROVISIONAL_MIN_SHAPE_SD = 0.05
#: The noise search (and its provisional pass) runs on whole objects up to this many
#: object-frames: the likelihood of two or three noise levels needs no more.
SEARCH_OBJECT_FRAMES = 2500
#: Covariance bytes the values one pass of the noise search runs at once may hold (estimated).
SEARCH_PASS_BYTES = 1e9
#: Rounds of coordinate ascent between the centre's acceleration and position noise at most.
ASCENT_ROUNDS = 3
#: The fields :func:`select_noise` finds (the others are the caller's).
NOISE_FIELDS = ("accel_sd", "shape_sd", "joint_accel_sd", "position_sd")


@dataclass(frozen=True)
class UKFConfig:
    """Settings of :class:`UKFSmoother` (units in the names). ``None`` = from the data.

    sigma_px : box-edge noise; ``None`` = robust residual level of the per-frame fits
    accel_sd : white-acceleration noise of the centre, m/s^2/sqrt(Hz); ``None`` = maximum
        likelihood of the forward pass within ``accel_bounds``
    position_sd : random walk of the centre's position on top of it, m/sqrt(s)
        (:mod:`gt3dkit.fusion.motion`: labels placed frame by frame depart from a smooth path);
        ``None`` = maximum likelihood within ``position_bounds`` (boxes; 0 without boxes)
    vertical_ratio : the vertical acceleration noise is this times ``accel_sd``
    shape_sd : random-walk noise of the log semi-axes, 1/sqrt(s); ``None`` = maximum
        likelihood within ``shape_bounds``
    kpt_sigma_px : keypoint noise (all joints); ``None`` = per joint, from the data
    joint_accel_sd : white-acceleration noise of the joints; ``None`` = maximum likelihood
        within ``joint_accel_bounds``
    robust : down-weight / reject measurements the other views disagree with
    huber_p, reject_p : tail probabilities where down-weighting starts / rejection is total
    bones : tie each person's bone lengths together (messages from the first pass's joints to
        the final pass, :mod:`gt3dkit.fusion.bones`)
    bone_sd_m : sd of a bone's length about its fitted value; ``None`` = the spread of that
        bone's length over the first pass, at least ``bone_sd_floor_m``
    init_vel_sd_mps : initial velocity sd; init_canon_sd_m : initial sd of a joint placed
        from the canonical pose (no two views agree on it in the object's first frame): half a
        person's height, since the pose is scaled from the joints the frame did place (a knee
        placed from a head and shoulders was 0.85 m off; at 0.15 m its first views faded the
        prediction, velocity too, and the joint's filter diverged)
    clip_tol_px : edges this close to the image border count as clipped
    iterations : passes of the iterated, reweighted update
    inflate : inflate covariances by the NIS per degree of freedom when above 1
    smooth : run the backward RTS pass
    search_linearised : boxes only: the noise search's passes use the boxes' regression about the
        provisional smoothed estimate, fixed per row (:class:`gt3dkit.fusion.boxupdate.LinearisedSearch`,
        a linear filter per value); ``False``: each pass re-linearises at every prediction
    """

    sigma_px: float | None = None
    accel_sd: float | None = None
    accel_bounds: tuple[float, float] = (0.01, 100.0)
    position_sd: float | None = None
    position_bounds: tuple[float, float] = (1e-3, 1.0)
    vertical_ratio: float = 0.1
    shape_sd: float | None = None
    shape_bounds: tuple[float, float] = (1e-5, 0.3)
    kpt_sigma_px: float | None = None
    joint_accel_sd: float | None = None
    joint_accel_bounds: tuple[float, float] = (0.03, 100.0)
    robust: bool = True
    huber_p: float = 1e-4
    reject_p: float = 1e-7
    bones: bool = True
    bone_sd_m: float | None = None
    bone_sd_floor_m: float = 0.001
    init_vel_sd_mps: float = 1.5
    init_canon_sd_m: float = 0.5
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float = 0.0
    clip_tol_px: float = 1.0
    iterations: int = 4
    inflate: bool = True
    smooth: bool = True
    search_linearised: bool = True

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if isinstance(v, float) and not np.isfinite(v):
                raise ValueError(f"UKFConfig.{k} must be finite, got {v}")
        for k in ("sigma_px", "kpt_sigma_px", "bone_sd_m", "accel_sd", "shape_sd",
                  "joint_accel_sd", "position_sd"):
            v = getattr(self, k)
            if v is not None and v <= 0:
                raise ValueError(f"UKFConfig.{k} must be positive, got {v}")
        for k in ("accel_bounds", "shape_bounds", "joint_accel_bounds", "position_bounds"):
            lo, hi = getattr(self, k)
            if not 0 < lo < hi:
                raise ValueError(f"UKFConfig.{k} must be 0 < lo < hi, got {(lo, hi)}")
        if self.iterations < 1:
            raise ValueError("UKFConfig.iterations must be >= 1")
        RobustConfig(self.huber_p, self.reject_p)

    @property
    def robust_config(self) -> RobustConfig:
        return RobustConfig(self.huber_p, self.reject_p, enabled=self.robust)


class UKFSmoother:
    """Forward UKF + backward RTS over all objects of a scene, one batch per frame."""

    name = "ukf"

    def __init__(self, config: UKFConfig | None = None, bones: PersonBones | None = None) -> None:
        self.config = config or UKFConfig()
        self.bones = bones  # persons' bone lengths found outside the run (gt3dkit.windows)

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
                    ) -> tuple[Model, Init, UKFConfig, dict[str, Any], FilterRun]:
        """The model, start, chosen noise and its search, and the filter's and smoother's first
        pass (the views reweighted by the smoothed estimate)."""
        model = Model.of(pre)
        init = initial_states(model, self.config)
        cfg, search = select_noise(model, init, self.config, pre, scene.fps)
        pre.memo[_noise_key(self.config, scene.fps)] = (cfg, search)  # for GTSAM on this preparation
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
                run = None
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
        bone_info: dict[str, Any] = {}
        if pre.use_kpt and cfg.bones and pre.skeleton is not None:
            # the bones' messages from the first pass's smoothed joints, added to each joint's
            # own filter run again (the views reweighted as before)
            msgs, lengths = bone_messages_of(model, cfg, run, pre.skeleton, self.bones)
            run = None  # the first pass's covariances go before the second's are made
            run = run_filter(replace(model, joint_info=msgs), init, cfg, scene.fps, collect=True)
            bone_info = lengths.info(rows.obj_ids)
        x_s, P_s = run.x, run.P
        nis = run.mean_nis_per_dof
        inflation = max(nis, 1.0) if cfg.inflate and np.isfinite(nis) else 1.0
        if inflation != 1.0:
            P_s *= inflation  # in place: P_s is this run's own array
        centre = x_s[:, layout.center]
        semi = np.exp(x_s[:, layout.log_axes])
        P_c, widened = widen_weak_rows(P_s[:, layout.center, layout.center], pre, scene.fps)
        lone_ids: list[int] = []
        if pre.use_box and pre.fit is not None:
            lone = single_view_rows(pre)
            if lone.any():
                centre, semi, P_c = centre.copy(), semi.copy(), P_c.copy()
                centre[lone] = pre.fit.center_world[lone]
                semi[lone] = np.exp(pre.fit.log_axes[lone])
                P_c[lone] = pre.fit.cov[lone][:, :3, :3]
                lone_ids = sorted({int(i) for i in rows.obj_ids[rows.row_o[lone]]})
        sd = axis_sd(P_c)
        kpt = np.zeros((R, 0, 3))
        kpt_sd = np.zeros((R, 0))
        if pre.use_kpt:
            kpt, kpt_sd = joints_of(x_s, P_s, layout, rows, pre.kpt0)
            if not pre.use_box:
                centre, semi, sd = ellipsoid_around(kpt, kpt_sd, cams.world_from_body)
        down = downweighted_of(model, run)
        info: dict[str, Any] = {
            "estimator": self.name,
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
                "sigma_px": pre.info.get("boxes", {}).get("sigma_source"),
                "kpt_sigma_px": pre.info.get("keypoints", {}).get("sigma_source"),
                "process": ("given" if self.config.accel_sd and (self.config.joint_accel_sd
                                                                  or not pre.use_kpt)
                            else "max likelihood of the forward pass: log-spaced scan, then "
                                 "bisection and a parabola on log scale (curve in noise_search)")},
            "params": {**asdict(cfg), "sigma_px": pre.info["boxes"]["sigma_px"] if pre.use_box else None,
                       "sigma_px_core": pre.info["boxes"]["sigma_px_core"] if pre.use_box else None,
                       "kpt_sigma_px": pre.info.get("keypoints", {}).get("sigma_px"),
                       "fps": scene.fps},
            "measurements": {"boxes": pre.use_box, "keypoints": pre.use_kpt,
                             "skeleton": pre.skeleton.name if pre.use_kpt and pre.skeleton
                             else None},
            "preparation": pre.info,
            "robust": {"enabled": cfg.robust, "downweighted": int(np.sum(down.weight > 0)),
                       "rejected": int(np.sum(down.weight == 0)),
                       "rule": "leave-one-out score against prior + other views; weight 1 "
                               f"below the chi-square tail probability {cfg.huber_p:g}, 0 "
                               f"beyond {cfg.reject_p:g}"},
            **({"bones": bone_info} if bone_info else {}),
            "seconds": time.perf_counter() - t0,
        }
        return TrackSet(
            frame=rows.frames[rows.row_t], track_id=rows.obj_ids[rows.row_o],
            center_world=centre, semi_axes=semi, center_sd=sd, n_views=rows.n_views,
            kpt_world=kpt, kpt_sd=kpt_sd, info=info, downweighted=down)


def objects_rows(rows: Any, hit: np.ndarray) -> np.ndarray:
    """(R,) every row of the objects that have a row in ``hit (R,)``."""
    obj = np.zeros(len(rows.obj_ids), bool)
    obj[rows.row_o[hit]] = True
    return obj[rows.row_o]


def smoothed_weights(model: Model, x_s: F64, cfg: UKFConfig) -> F64:
    """(R, m) weights of every measurement judged by its residual at the smoothed estimate
    ``x_s (R, n)`` in units of its noise (:func:`gt3dkit.fusion.robust.point_weights`), 1
    outside the robust blocks. The smoothed state rests on many frames, so its own spread
    is left out of the score (a slightly stricter test)."""
    w = np.ones_like(model.z)
    zhat = model.h(x_s[:, None, :])[:, 0, :]
    r = np.where(model.mask & np.isfinite(zhat), model.z - zhat, 0.0)
    e2 = r * r / (model.var * model.test_variance())
    B = len(x_s)
    for sl, d in model.robust_blocks:
        e2b = e2[:, sl].reshape(B, -1, d).sum(axis=2)
        w[:, sl] = np.repeat(point_weights(e2b, d, cfg.robust_config), d, axis=1)
    return np.where(model.mask, w, 1.0)


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


@dataclass(frozen=True)
class Init:
    """Initial state ``x0 (R, n)`` and covariance ``P0 (R, n, n)`` of every row (used where
    an object starts): the row's own per-frame fit with its covariance. ``P0`` an array or
    one made when indexed (:class:`InitialCov`)."""

    x0: F64
    P0: Any


def initial_states(model: Model, cfg: UKFConfig) -> Init:
    lay = model.layout
    x0 = model.x_frame.copy()
    v = model.var_frame.copy()
    v[:, lay.velocity] = cfg.init_vel_sd_mps**2
    if lay.n_joints:
        v[:, lay.joint_velocity] = cfg.init_vel_sd_mps**2
        j = v[:, lay.joints]
        v[:, lay.joints] = np.where(np.isfinite(j), j, cfg.init_canon_sd_m**2)
    v = np.where(np.isfinite(v), v, 1.0)
    c6 = model.cov6_frame
    ok = np.all(np.isfinite(c6), axis=(1, 2))
    dims = np.r_[np.arange(lay.center.start, lay.center.stop),
                 np.arange(lay.log_axes.start, lay.log_axes.stop)]
    return Init(x0, InitialCov(v, c6, ok, dims))


def maximise_log(f: Any, lo: float, hi: float, n_scan: int, rounds: int = 2
                 ) -> tuple[float, dict[float, float]]:
    """Maximiser of a smooth ``f`` over ``[lo, hi]`` on log scale, evaluated in batches:
    ``f(values) -> logliks`` takes a list. A log-spaced scan of ``n_scan`` values, then
    ``rounds`` of bisection (the log-midpoints to the best value's neighbours, two values per
    batch; the last batch adds the vertex of the parabola in ``log q`` through the best three).
    Returns the best value evaluated and every evaluation ``{value: f}``."""
    seen: dict[float, float] = {}

    def evaluate(values: list[float]) -> None:
        new = [v for v in values if v not in seen]
        if new:
            for v, ll in zip(new, f(new), strict=True):
                seen[v] = float(ll) if np.isfinite(ll) else -np.inf

    def vertex() -> list[float]:
        """The vertex of the parabola in log q through the best value and its neighbours."""
        vs = sorted(seen)
        ll = np.array([seen[v] for v in vs])
        k = int(np.argmax(ll))
        if k == 0 or k == len(vs) - 1 or not np.all(np.isfinite(ll[k - 1:k + 2])):
            return []
        u = np.log(vs[k - 1:k + 2])
        c2, c1, _ = np.polyfit(u, ll[k - 1:k + 2], 2)
        return [float(np.exp(np.clip(-c1 / (2 * c2), u[0], u[2])))] if c2 < 0 else []

    evaluate([float(v) for v in np.geomspace(lo, hi, n_scan)])
    for r in range(rounds):
        vs = sorted(seen)
        k = int(np.argmax([seen[v] for v in vs]))
        cand = [float(np.sqrt(vs[k] * vs[j])) for j in (k - 1, k + 1) if 0 <= j < len(vs)]
        evaluate(cand + (vertex() if r == rounds - 1 else []))
    best = max(seen, key=lambda v: seen[v])
    return best, seen


def select_noise(model: Model, init: Init, cfg: UKFConfig, pre: Prepared, fps: float
                 ) -> tuple[UKFConfig, dict[str, Any]]:
    """Process noise by maximum likelihood of the forward pass (no smoothing, no bones).

    The likelihood must not be bent by outliers, and a single pass cannot reweight: so a
    first robust pass (forward and RTS), at provisional values (the moment estimates from the
    per-frame fits, :func:`gt3dkit.fusion.prepare.moment_process_noise`), fixes every
    measurement's weight by its residual at that smoothed estimate, and the search's single
    passes use those weights. The search runs on at most ``SEARCH_OBJECT_FRAMES`` object-frames
    (:func:`search_rows`). Values set in
    ``cfg`` are kept; the others are found in turn (``accel_sd``, then ``shape_sd`` with boxes,
    then ``joint_accel_sd`` with keypoints) by :func:`maximise_log`. Returns the tuned config
    and, per searched parameter, the likelihood curve (``value, loglik``, sorted).
    """
    curves: dict[str, Any] = {}
    use_box, use_kpt = pre.use_box, pre.use_kpt
    x_f, v_f, _ = pre.frame_state()
    prov = moment_process_noise(pre, x_f, v_f, fps, cfg.accel_sd, cfg.shape_sd,
                                cfg.joint_accel_sd)
    # looser than the moment estimates: the provisional pass is to catch what the other
    # views contradict, not to hold the data to a prior that may be too tight
    loose = PROVISIONAL_LOOSENESS
    start = replace(cfg, accel_sd=cfg.accel_sd or loose * prov.accel_sd,
                    shape_sd=cfg.shape_sd or max(loose * prov.shape_sd, PROVISIONAL_MIN_SHAPE_SD),
                    joint_accel_sd=cfg.joint_accel_sd or loose * prov.joint_accel_sd)
    weights = model.weight0
    on = search_rows(model.rows, SEARCH_OBJECT_FRAMES)
    if on is not None:
        curves["subsample"] = {
            "objects": int(len(np.unique(model.rows.row_o[on]))), "object_frames": int(on.sum()),
            "note": f"the search runs on whole objects drawn at random (seed 0) up to "
                    f"{SEARCH_OBJECT_FRAMES} object-frames: two noise levels need no more"}
    searching = (cfg.accel_sd is None or cfg.shape_sd is None or (use_kpt and cfg.joint_accel_sd is None))
    linear = searching and cfg.search_linearised and use_box and not use_kpt
    if linear:  # boxes only
        linear = applies_to_model(model)
    if searching and (cfg.robust or linear):
        # every point judged against the provisional *smoothed* estimate, as the second pass
        # judges them: a bad view in an object's first frames, which a forward pass cannot
        # tell yet, would otherwise bend the motion model's likelihood
        # the provisional pass's covariances are read by the linearised box search only
        prov_runner = partial(run_joints, covariances=False) if not linear and \
            backend_for(model) == "joints" else run_filter
        prov_run = prov_runner(model, init, start, fps, on=on)
        x_prov, P_prov = prov_run.x, prov_run.P
        if cfg.robust:
            weights = smoothed_weights(model, x_prov, start)
        curves["provisional"] = {**prov.as_dict(), "source": prov.source,
                                 "use": ("a robust pass at these values, smoothed, fixes the weights"
                                         if cfg.robust else "a pass at these values, smoothed")
                                 + (" and the boxes' linearisation" if linear else "")}
    lin = None
    if linear:
        lin = LinearisedSearch(model, init, start, fps, x_prov, P_prov, weights, on)
    search_model = replace(model, weight0=weights)  # one pass each: no reweighting
    sel = np.flatnonzero(on) if on is not None else np.arange(len(model.rows))

    # several values in one pass (copies of the objects), as far as SEARCH_PASS_BYTES of the
    # whole state's covariances would allow. With joints their separate small filters hold
    # about a third of that, and only their likelihoods are read: the whole state's covariances
    # are not put back together (``covariances=False``), so the search stays well
    # inside the budget
    per_pass = max(1, int(SEARCH_PASS_BYTES // (6 * 8 * model.layout.n ** 2 * max(len(sel), 1))))
    runner = run_filter if backend_for(model) == "objects" else partial(run_joints, covariances=False)

    def search(name: str, c: UKFConfig, bounds: tuple[float, float], n_scan: int) -> UKFConfig:
        def logliks(values: list[float]) -> list[float]:
            if lin is not None:  # boxes: the regression fixed per row, a linear pass per value
                return lin.logliks([{"accel_sd": c.accel_sd, "shape_sd": c.shape_sd,
                                     "position_sd": c.position_sd or 0.0, name: v} for v in values])
            out: list[float] = []
            for i in range(0, len(values), per_pass):
                part = values[i:i + per_pass]
                rows_k, src, copy = replicate_rows(model.rows, sel, len(part))
                run = runner(search_model.take(rows_k, src), Init(init.x0[src], rows_of(init.P0, src)),
                             replace(c, smooth=False, iterations=1), fps, fade=False,
                             noise_rows={name: np.asarray(part)[copy]})
                out += list(np.bincount(copy, weights=run.loglik_rows, minlength=len(part)))
            return out

        best, seen = maximise_log(logliks, *bounds, n_scan)
        curves[name] = [{"value": v, "loglik": ll} for v, ll in sorted(seen.items())]
        return replace(c, **{name: best})

    given = cfg
    cfg = start
    if use_box and given.accel_sd is None:
        cfg = search("accel_sd", cfg, cfg.accel_bounds, 5)
    if use_box and given.position_sd is None:
        cfg = search("position_sd", cfg, cfg.position_bounds, 4)
        for _ in range(ASCENT_ROUNDS if given.accel_sd is None else 0):
            # the two trade off (a jittery label set is explained by either): coordinate ascent
            was = (cfg.accel_sd, cfg.position_sd)
            cfg = search("position_sd", search("accel_sd", cfg, cfg.accel_bounds, 5), cfg.position_bounds, 4)
            if np.allclose(np.log([cfg.accel_sd, cfg.position_sd]), np.log(was), atol=0.05):
                break
    if use_box and given.shape_sd is None:
        cfg = search("shape_sd", cfg, cfg.shape_bounds, 4)
    if use_kpt and given.joint_accel_sd is None:
        cfg = search("joint_accel_sd", cfg, cfg.joint_accel_bounds, 4)
    if not use_box and given.accel_sd is None:
        cfg = replace(cfg, accel_sd=cfg.joint_accel_sd)
    return cfg, curves


def noise_by_likelihood(pre: Prepared, fps: float, cfg: UKFConfig) -> tuple[UKFConfig, dict[str, Any]]:
    """:func:`select_noise` of a preparation: the process noise (the values ``cfg`` leaves
    ``None``) that maximises the marginal likelihood of the state-space model, by the Kalman
    filter's prediction-error decomposition; what the GTSAM smoother's graph is tuned by too
    (the same model, solved another way)."""
    key = _noise_key(cfg, fps)
    if key not in pre.memo:  # the UKF of this preparation may have found it already
        model = Model.of(pre)
        pre.memo[key] = select_noise(model, initial_states(model, cfg), cfg, pre, fps)
    found, curves = pre.memo[key]
    return replace(found, **{k: v for k, v in asdict(cfg).items() if k not in NOISE_FIELDS}), curves


def _noise_key(cfg: UKFConfig, fps: float) -> tuple[Any, ...]:
    """Where :func:`noise_by_likelihood` keeps its result in ``Prepared.memo``."""
    return ("noise_by_likelihood", cfg, fps)


def search_rows(rows: Any, budget: int, seed: int = 0) -> np.ndarray | None:
    """(R,) the rows of whole objects, drawn in a seeded random order until they hold
    ``budget`` object-frames (:func:`drawn_objects`); ``None`` (all rows) when the scene has no
    more than that. (Windows of the sequence with every object in them were tried: per pass they
    were no faster, the batches grew as the frames shrank, and a shape's random walk showed less.)"""
    if len(rows) <= budget:
        return None
    return drawn_objects(np.bincount(rows.row_o, minlength=len(rows.obj_ids)), budget, seed)[rows.row_o]


def drawn_objects(count: np.ndarray, budget: int, seed: int = 0) -> np.ndarray:
    """``(O,)`` which objects the noise search runs on, of objects with ``count (O,)``
    object-frames each: in a random order (``seed``) until they hold ``budget`` of them."""
    order = np.random.default_rng(seed).permutation(len(count))
    take = order[: int(np.searchsorted(np.cumsum(count[order]), budget)) + 1]
    obj = np.zeros(len(count), bool)
    obj[take] = True
    return obj


def joints_of(x_s: F64, P_s: F64, layout: Any, rows: Any, kpt0: F64) -> tuple[F64, F64]:
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
    assert W is not None and S2 is not None and RES is not None
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
    """:func:`gt3dkit.fusion.bones.bone_samples` of a first pass's :func:`first_joints`
    ``first``; ``obj``: each row's person index."""
    joints, cov, seen = first
    rows = model.rows
    return bone_samples(rows.row_o, rows.frames[rows.row_t], seen.sum(axis=1) >= 2, joints, cov, skel)


def bone_messages_of(model: Model, cfg: UKFConfig, run: FilterRun, skel: Skeleton,
                     fixed: PersonBones | None = None) -> tuple[JointInfo, BoneLengths]:
    """The bones' messages to every joint of every row (:mod:`gt3dkit.fusion.bones`) and each
    person's bone lengths, from a first pass ``run`` (split: independent joints); the persons
    ``fixed`` holds take its lengths."""
    rows = model.rows
    first = first_joints(model, run)
    lengths = lengths_of(bone_samples_of(model, first, skel), np.arange(len(rows.obj_ids)),
                         cfg.bone_sd_floor_m, cfg.bone_sd_m)
    if fixed is not None:
        lengths = fixed.applied(lengths, rows.obj_ids)
    joints, cov, seen = first
    bones = skel.bones
    zb = lengths.length[rows.row_o]
    # a bone ties a joint to a measured one: where neither end has a view in a frame it would
    # only couple two extrapolations (and bend both along a sphere far from any evidence)
    seen1 = seen.any(axis=1)
    mb = np.isfinite(zb) & (seen1[:, bones[:, 0]] | seen1[:, bones[:, 1]])
    msgs = bone_messages(joints, cov, bones, np.nan_to_num(zb), lengths.sd[rows.row_o] ** 2, mb,
                         cfg.robust_config if cfg.robust else None)
    return msgs, lengths


def rerun_objects(model: Model, init: Init, cfg: UKFConfig, fps: float, run: FilterRun, on: np.ndarray
                  ) -> FilterRun:
    """``run`` with the rows ``on (R,)`` (whole objects) run again: by the frames' filter their
    covariances are written into ``run``'s own (no second array of every row's)."""
    if backend_for(model) == "joints":
        return run.merged(run_joints(model, init, cfg, fps, True, True, on, None, into=run.P), on)
    return run.merged(run_filter(model, init, cfg, fps, collect=True, on=on), on)


def run_filter(model: Model, init: Init, cfg: UKFConfig, fps: float, collect: bool = False,
               fade: bool = True, on: np.ndarray | None = None,
               noise_rows: dict[str, F64] | None = None) -> FilterRun:
    """Forward UKF, then (optionally) RTS, by the backend that serves the model
    (:func:`backend_for`): a :class:`gt3dkit.fusion.filterrun.FilterRun`; with ``collect`` it
    holds the final weights, scores and residuals ``(R, m)``. ``fade`` lets the frame's own
    views weaken a contradicted prediction (the fading rule of :mod:`gt3dkit.fusion.kalman`); the
    noise search runs
    without it, so that its likelihood judges the motion model as it is. ``on (R,)`` runs the
    rows of some objects only (whole objects: each object's filter is independent of the
    others); the other rows' outputs are zero and their statistics absent
    (:meth:`FilterRun.merged` combines runs). ``noise_rows`` gives some of ``accel_sd``,
    ``shape_sd``, ``joint_accel_sd`` per row ``(R,)`` instead of ``cfg``'s (the noise search runs
    several values at once)."""
    if cfg.accel_sd is None or cfg.shape_sd is None:
        raise ValueError("run_filter needs numeric accel_sd and shape_sd")
    return BACKENDS[backend_for(model)](model, init, cfg, fps, collect, fade, on, noise_rows)


def backend_for(model: Model) -> str:
    """The filter that runs ``model``: ``"objects"`` (a boxes-only model: every object's rows as
    one compiled chain, objects in parallel, :func:`gt3dkit.fusion.boxupdate.run_boxes`) or
    ``"joints"`` (a model with joints: every joint of every person as a compiled chain, the
    ellipsoid by the boxes' chains, :func:`gt3dkit.fusion.jointupdate.run_joints`). The tests hold
    both to a filter over the frame grid (``tests/oracles_frames.py``), which calls the same
    steps."""
    return "joints" if model.layout.n_joints else "objects"


BACKENDS = {"objects": run_boxes, "joints": run_joints}
