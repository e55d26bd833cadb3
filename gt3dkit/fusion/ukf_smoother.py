r"""The primary estimator: the paper's per-object UKF, batched, plus an unscented RTS pass.

What differs from the paper's obvious implementation (and why):

* **One stacked update per frame.** All cameras' box edges of an object form one
  measurement vector (masked where missing or clipped), instead of one sequential
  update per camera; all objects of a frame are one batch.
* **Cubature weights** (``alpha=1, beta=0, kappa=0``): no negative weight, so the
  predicted covariances are PSD by construction; any repair is counted in ``info``.
* **Initialisation already close:** each object starts at the per-frame
  least-squares fit of its first frame (itself started from the paper's ground-plane
  homography), not at the homography point.
* **Noise that matches the input:** the edge noise ``sigma_px`` defaults to the
  residual RMS of the per-frame fits (with degrees of freedom), e.g. 0.29 px for
  boxes rounded to whole pixels.
* **Backward RTS pass** (offline ground truth may use the future).

Keypoints (issue 4) join the same state and the same update: each joint and its
velocity (constant velocity), measured by the ordinary projection with distortion.
Joints start from per-frame DLT triangulation where two views see them and from the
canonical pose scaled into the ellipsoid otherwise. A person's bone lengths are
tied together by pseudo-measurements ``|p_i - p_j| = L_b`` whose lengths (and
spread) come from a first pass without them. With many cameras x joints the update
runs in information form (:func:`gt3dkit.fusion.ukf.ukf_update_information`).
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np

from gt3dkit.errors import InputError
from gt3dkit.fusion.boxfit import PERSON_SEMI_AXES_M, BoxFit, auto_sigma_px, box_model, fit_boxes
from gt3dkit.fusion.motion import StateLayout
from gt3dkit.fusion.rows import Rows, build_rows
from gt3dkit.fusion.ukf import (
    SigmaWeights,
    predict_linear,
    rts_step,
    ukf_update,
    ukf_update_information,
)
from gt3dkit.geom.camera import Cams, project_points
from gt3dkit.geom.triangulate import normalized_points, triangulate_dlt
from gt3dkit.skeletons import SKELETONS, Skeleton, skeleton_for
from gt3dkit.types import F64, Scene, TrackSet


@dataclass(frozen=True)
class UKFConfig:
    """Settings of :class:`UKFSmoother` (units in the names). ``None`` = from the data.

    sigma_px : box-edge noise; ``None`` = residual RMS of the per-frame fits
    accel_sd : white-acceleration noise of the centre, m/s^2/sqrt(Hz); ``None`` = the
        value of ``accel_grid`` with the highest forward-pass likelihood of the data
    vertical_ratio : the vertical acceleration noise is this times ``accel_sd``
    shape_sd : random-walk noise of the log semi-axes, 1/sqrt(s); ``None`` = chosen with
        ``accel_sd`` by likelihood from ``shape_grid``
    kpt_sigma_px : keypoint noise; ``None`` = reprojection RMS of the DLT points
    joint_accel_sd : white-acceleration noise of the joints; ``None`` = by likelihood
        from ``joint_accel_grid``
    bones : tie each person's bone lengths together (second pass)
    bone_sd_m : sd of the bone-length pseudo-measurement; ``None`` = the robust spread
        of that bone's length over the first pass, at least ``bone_sd_floor_m``
    init_pos_sd_m, init_vel_sd_mps, init_shape_sd, init_joint_sd_m, init_canon_sd_m :
        initial standard deviations (joints from DLT / from the canonical pose)
    clip_tol_px : edges this close to the image border count as clipped
    iterations : passes of the iterated (posterior-linearisation) update
    information_form_min_m : measurement length from which the update runs in
        information form
    smooth : run the backward RTS pass
    """

    sigma_px: float | None = None
    accel_sd: float | None = None
    accel_grid: tuple[float, ...] = (0.03, 0.1, 0.3, 1.0, 3.0)
    vertical_ratio: float = 0.1
    shape_sd: float | None = None
    shape_grid: tuple[float, ...] = (0.0002, 0.005, 0.05)
    kpt_sigma_px: float | None = None
    joint_accel_sd: float | None = None
    joint_accel_grid: tuple[float, ...] = (0.3, 1.0, 3.0, 10.0)
    bones: bool = True
    bone_sd_m: float | None = None
    bone_sd_floor_m: float = 0.001
    init_pos_sd_m: float = 0.05
    init_vel_sd_mps: float = 1.5
    init_shape_sd: float = 0.1
    init_joint_sd_m: float = 0.02
    init_canon_sd_m: float = 0.15
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float = 0.0
    clip_tol_px: float = 1.0
    iterations: int = 3
    information_form_min_m: int = 200
    smooth: bool = True

    def __post_init__(self) -> None:
        for k, v in asdict(self).items():
            if isinstance(v, float) and not np.isfinite(v):
                raise ValueError(f"UKFConfig.{k} must be finite, got {v}")
        for k in ("sigma_px", "kpt_sigma_px", "bone_sd_m", "accel_sd", "shape_sd",
                  "joint_accel_sd"):
            v = getattr(self, k)
            if v is not None and v <= 0:
                raise ValueError(f"UKFConfig.{k} must be positive, got {v}")
        if self.iterations < 1:
            raise ValueError("UKFConfig.iterations must be >= 1")


def check_in_front(scene: Scene, rows: Rows, fit: BoxFit) -> None:
    """Raise :class:`InputError` for a box whose object lies behind that camera."""
    seen = (rows.obs_row >= 0) & np.all(np.isfinite(rows.box_z), axis=-1)
    bad = seen & fit.ok[:, None] & ~(fit.margin > 0)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        where = scene.obs.origin[rows.obs_row[r, c]]
        raise InputError(where, f"the object of this box is behind camera "
                                f"{scene.rig.cameras[c].name} (the other views place it at "
                                f"{np.round(fit.center_world[r], 2).tolist()} m): "
                                f"box and calibration disagree")


@dataclass(frozen=True)
class Prepared:
    """What every estimator starts from: rows, cameras, per-frame fits and noise levels.

    fit : per-frame box fits (None without boxes); kpt0 : (R, J, 3) per-frame DLT joints
    (None without keypoints); sigma_box / sigma_kpt : measurement noise (px), given or
    estimated from the per-frame residuals.
    """

    rows: Rows
    cams: Cams
    layout: StateLayout
    use_box: bool
    use_kpt: bool
    fit: BoxFit | None
    kpt0: F64 | None
    sigma_box: float
    sigma_kpt: float

    def model(self, scene: Scene, cfg: UKFConfig) -> Model:
        """The stacked filter model with initial states from ``cfg``'s initial sds."""
        x0, p0 = initial_states(scene, self.rows, self.cams, self.layout, self.fit, self.kpt0, cfg)
        return stacked_model(self.rows, self.cams, self.layout, self.use_box, self.use_kpt,
                             self.sigma_box, self.sigma_kpt, x0, p0, self.kpt0,
                             cfg.init_joint_sd_m)


def prepare(scene: Scene, clip_tol_px: float = 1.0, sigma_px: float | None = None,
            kpt_sigma_px: float | None = None) -> Prepared:
    """Rows, cameras, per-frame box fits / DLT joints, input checks and noise levels."""
    rows = build_rows(scene, clip_tol_px)
    cams = Cams.of(scene.rig)
    J = scene.obs.n_joints
    use_box = bool(np.isfinite(rows.box_z).any())
    use_kpt = J > 0 and bool(np.isfinite(rows.kpt_z).any())
    fit, kpt0 = None, None
    sigma_box = sigma_kpt = 1.0
    if use_box:
        fit = fit_boxes(rows.box_z, rows.box_mask, cams)
        check_in_front(scene, rows, fit)
        sigma_box = sigma_px if sigma_px is not None else auto_sigma_px(fit)
    if use_kpt:
        kpt0, rms = triangulate_rows(scene, rows, cams)
        sigma_kpt = kpt_sigma_px if kpt_sigma_px is not None else max(rms, 0.05)
    return Prepared(rows, cams, StateLayout(J if use_kpt else 0), use_box, use_kpt, fit, kpt0,
                    sigma_box, sigma_kpt)


@dataclass
class Model:
    """Everything one filter run needs: rows, cameras, stacked measurements, initial states.

    Measurement vector of a row: ``[box edges (C*4) | keypoints (C*J*2) | bones (K)]``,
    each block present only when the scene has it.
    """

    rows: Rows
    cams: Cams
    layout: StateLayout
    use_box: bool
    z: F64  # (R, m)
    mask: np.ndarray  # (R, m) bool
    var: F64  # (R, m) measurement variances
    x0: F64  # (R, n) initial state where an object starts
    p0_diag: F64  # (R, n) initial variances
    kpt_hint: F64 | None = None  # (R, J, 3) triangulated joints (NaN under 2 views)
    hint_sd_m: float = 0.02
    bones: np.ndarray | None = None  # (K, 2)

    def linearisation_point(self, r: np.ndarray, x: F64, P: F64) -> tuple[F64 | None, F64 | None]:
        """Where the first update pass linearises: the prior, except for joints the filter
        has lost (sd above 5x ``hint_sd_m``) that this frame triangulates: those at the
        triangulated point with sd ``hint_sd_m``, uncorrelated."""
        if self.kpt_hint is None:
            return None, None
        J = self.layout.n_joints
        sl = self.layout.joints
        var = np.diagonal(P, axis1=1, axis2=2)[:, sl].reshape(len(r), J, 3).max(axis=2)
        hint = self.kpt_hint[r]
        lost = (var > (5 * self.hint_sd_m) ** 2) & np.all(np.isfinite(hint), axis=2)
        if not lost.any():
            return None, None
        dims = (sl.start + 3 * np.argwhere(lost)[:, 1][:, None] + np.arange(3)).reshape(-1)
        b = np.repeat(np.argwhere(lost)[:, 0], 3)
        xl = x.copy()
        xl[b, dims] = hint[lost].reshape(-1)
        Pl = P.copy()
        Pl[b, dims, :] = 0.0
        Pl[b, :, dims] = 0.0
        Pl[b, dims, dims] = self.hint_sd_m**2
        return xl, Pl

    def h(self, X: F64) -> F64:
        """(B, S, n) -> (B, S, m) predicted measurements of all sigma points."""
        B, S = X.shape[:2]
        C, J = len(self.cams.K), self.layout.n_joints
        parts = []
        if self.use_box:
            parts.append(box_model(X[..., 0:3], X[..., 6:9], self.cams).reshape(B, S, C * 4))
        if J:
            P3 = X[..., self.layout.joints].reshape(B, S, J, 3)
            uv, _ = project_points(P3, self.cams.K, self.cams.dist, self.cams.R, self.cams.t,
                                   self.cams.depth_sign)  # (B,S,J,C,2)
            parts.append(np.swapaxes(uv, 2, 3).reshape(B, S, C * J * 2))
            if self.bones is not None:
                d = P3[..., self.bones[:, 0], :] - P3[..., self.bones[:, 1], :]
                parts.append(np.linalg.norm(d, axis=-1))
        return np.concatenate(parts, axis=-1)


class UKFSmoother:
    """Forward UKF + backward RTS over all objects of a scene, one batch per frame."""

    name = "ukf"

    def __init__(self, config: UKFConfig | None = None) -> None:
        self.config = config or UKFConfig()

    def estimate(self, scene: Scene) -> TrackSet:
        cfg = self.config
        t0 = time.perf_counter()
        pre = prepare(scene, cfg.clip_tol_px, cfg.sigma_px, cfg.kpt_sigma_px)
        rows, cams, layout, use_box, use_kpt = (pre.rows, pre.cams, pre.layout, pre.use_box,
                                                pre.use_kpt)
        sigma_box, sigma_kpt = pre.sigma_box, pre.sigma_kpt
        R, J = len(rows), layout.n_joints
        info: dict[str, Any] = {"estimator": self.name}
        model = pre.model(scene, cfg)
        cfg, loglik = select_noise(model, cfg, self.config, use_box, use_kpt, scene.fps)
        x_s, P_s, run_info = run_filter(model, cfg, scene.fps)
        bone_info: dict[str, Any] = {}
        if use_kpt and cfg.bones:
            skel = SKELETONS[scene.skeleton] if scene.skeleton else skeleton_for(J)
            x_s, P_s, run_info, bone_info = rerun_with_bones(model, cfg, scene.fps, x_s, P_s, skel)
        info.update(run_info)
        info["noise_loglik"] = loglik
        centre = x_s[:, layout.center]
        semi = np.exp(x_s[:, layout.log_axes])
        sd = np.sqrt(np.einsum("rii->ri", P_s[:, :3, :3]))
        kpt = np.zeros((R, 0, 3))
        kpt_sd = np.zeros((R, 0))
        if use_kpt:
            kpt, kpt_sd = joints_of(x_s, P_s, layout, rows)
            if not use_box:
                centre, semi, sd = ellipsoid_around(kpt, kpt_sd, cams.world_from_body)
        info.update({
            "params": {**asdict(cfg), "sigma_px": sigma_box if use_box else None,
                       "kpt_sigma_px": sigma_kpt if use_kpt else None, "fps": scene.fps},
            "measurements": {"boxes": use_box, "keypoints": use_kpt,
                             "skeleton": scene.skeleton if use_kpt else None},
            "noise_source": {"sigma_px": "given" if self.config.sigma_px else "per-frame fit residuals",
                             "kpt_sigma_px": ("given" if self.config.kpt_sigma_px
                                              else "DLT reprojection RMS"),
                             "process": "max likelihood over the grids where not given"},
            **({"bones": bone_info} if bone_info else {}),
            "seconds": time.perf_counter() - t0,
        })
        return TrackSet(
            frame=rows.frames[rows.row_t], track_id=rows.obj_ids[rows.row_o],
            center_world=centre, semi_axes=semi, center_sd=sd, n_views=rows.n_views,
            kpt_world=kpt, kpt_sd=kpt_sd, info=info)


def stacked_model(rows: Rows, cams: Cams, layout: StateLayout, use_box: bool, use_kpt: bool,
                  sigma_box: float, sigma_kpt: float, x0: F64, p0: F64, kpt0: F64 | None,
                  hint_sd_m: float) -> Model:
    """The filter's stacked measurements ``[boxes | keypoints]`` with masks and variances."""
    R, C = len(rows), len(cams.K)
    J = layout.n_joints
    zs, masks, vars_ = [], [], []
    if use_box:
        zs.append(rows.box_z.reshape(R, C * 4))
        masks.append(rows.box_mask.reshape(R, C * 4))
        vars_.append(np.full((R, C * 4), sigma_box**2))
    if use_kpt:
        zk = rows.kpt_z.reshape(R, C * J * 2)
        zs.append(zk)
        masks.append(np.isfinite(zk))
        vars_.append(np.full((R, C * J * 2), sigma_kpt**2))
    mask = np.concatenate(masks, 1)
    return Model(rows, cams, layout, use_box, np.where(mask, np.concatenate(zs, 1), 0.0), mask,
                 np.concatenate(vars_, 1), x0, p0, kpt_hint=kpt0, hint_sd_m=hint_sd_m)


def select_noise(model: Model, cfg: UKFConfig, given: UKFConfig, use_box: bool, use_kpt: bool,
                 fps: float, shape_grid: tuple[float, ...] | None = None
                 ) -> tuple[UKFConfig, list[dict[str, float | None]]]:
    """Process noise by maximum likelihood of the forward pass (no smoothing, no bones).

    Values set in ``given`` are kept; the others are chosen from the config's grids:
    ``accel_sd`` x ``shape_sd`` with boxes, then ``joint_accel_sd`` with keypoints.
    Returns the tuned config and every grid point's log-likelihood.
    """
    loglik: list[dict[str, float | None]] = []

    def score(c: UKFConfig) -> float:
        ll = run_filter(model, replace(c, smooth=False, iterations=1), fps)[2]["loglik"]
        loglik.append({"accel_sd": c.accel_sd, "shape_sd": c.shape_sd,
                       "joint_accel_sd": c.joint_accel_sd, "loglik": ll})
        return float(ll)

    sgrid = shape_grid or cfg.shape_grid
    cfg = replace(cfg, accel_sd=cfg.accel_sd or cfg.accel_grid[len(cfg.accel_grid) // 2],
                  shape_sd=cfg.shape_sd or sgrid[0],
                  joint_accel_sd=cfg.joint_accel_sd or cfg.joint_accel_grid[1])
    if use_box and (given.accel_sd is None or given.shape_sd is None):
        qs = cfg.accel_grid if given.accel_sd is None else (cfg.accel_sd,)
        ss = sgrid if given.shape_sd is None else (cfg.shape_sd,)
        best = max(((q, sh) for q in qs for sh in ss),
                   key=lambda k: score(replace(cfg, accel_sd=k[0], shape_sd=k[1])))
        cfg = replace(cfg, accel_sd=best[0], shape_sd=best[1])
    if use_kpt and given.joint_accel_sd is None:
        ja = max(cfg.joint_accel_grid, key=lambda q: score(replace(cfg, joint_accel_sd=q)))
        cfg = replace(cfg, joint_accel_sd=ja)
    return cfg, loglik


def never_seen(rows: Rows, n_joints: int) -> np.ndarray:
    """(R, J) joints whose object never showed them in any view of any frame."""
    seen = np.isfinite(rows.kpt_z[..., 0]).any(axis=1)  # (R, J)
    ever = np.zeros((len(rows.obj_ids), n_joints), bool)
    np.logical_or.at(ever, rows.row_o, seen)
    return ~ever[rows.row_o]


def triangulate_rows(scene: Scene, rows: Rows, cams: Cams) -> tuple[F64, float]:
    """DLT of every row's joints (R, J, 3) (NaN under 2 views) and the reprojection RMS (px).

    Raises :class:`InputError` when a triangulated joint lies behind a camera that saw it.
    """
    R, C, J = rows.kpt_z.shape[:3]
    xy = normalized_points(np.swapaxes(rows.kpt_z, 1, 2).reshape(R * J, C, 2), cams.K, cams.dist)
    X, nv = triangulate_dlt(xy, cams.R, cams.t)
    uv, depth = project_points(X, cams.K, cams.dist, cams.R, cams.t, cams.depth_sign)
    obs = np.swapaxes(rows.kpt_z, 1, 2).reshape(R * J, C, 2)
    seen = np.isfinite(obs[..., 0]) & np.isfinite(X[:, :1])
    behind = seen & ~(depth > 0)
    if behind.any():
        k, c = np.argwhere(behind)[0]
        r, j = divmod(int(k), J)
        raise InputError(scene.obs.origin[rows.obs_row[r, c]],
                         f"joint {j} triangulates behind camera {scene.rig.cameras[c].name}: "
                         f"keypoints and calibration disagree")
    res = np.where(seen[..., None], uv - obs, 0.0)
    dof = float(np.sum(2 * seen.sum(axis=1)[nv >= 3] - 3))
    rss = float(np.sum(res[nv >= 3] ** 2))
    rms = float(np.sqrt(rss / dof)) if dof > 0 else 1.0
    return X.reshape(R, J, 3), rms


def initial_states(scene: Scene, rows: Rows, cams: Cams, layout: StateLayout, fit: BoxFit | None,
                   kpt0: F64 | None, cfg: UKFConfig) -> tuple[F64, F64]:
    """Initial state and variances ``(R, n)`` for every row (used where an object starts)."""
    R, n, J = len(rows), layout.n, layout.n_joints
    x0 = np.zeros((R, n))
    p0 = np.zeros((R, n))
    wfb = cams.world_from_body
    if fit is not None:
        x0[:, 0:3], x0[:, 6:9] = fit.center_world, fit.log_axes
    elif kpt0 is not None:
        c, s, _ = ellipsoid_around(kpt0, np.zeros(kpt0.shape[:2]), wfb)
        ok = np.all(np.isfinite(c), axis=1)
        # rows with no triangulated joint borrow the nearest row of the same object that has one
        for o in np.unique(rows.row_o[~ok]):
            mine = np.flatnonzero(rows.row_o == o)
            good = mine[ok[mine]]
            if good.size == 0:
                first = scene.obs.origin[int(rows.obs_row[mine][rows.obs_row[mine] >= 0][0])]
                raise InputError(first, f"object {int(rows.obj_ids[o])} is never seen by two "
                                        "cameras at once: its 3D position is undetermined "
                                        "from keypoints alone")
            near = good[np.argmin(np.abs(rows.row_t[good][None, :] - rows.row_t[mine][:, None]),
                                  axis=1)]
            c[mine], s[mine] = c[near], s[near]
        x0[:, 0:3], x0[:, 6:9] = c, np.log(s)
    p0[:, 0:3] = cfg.init_pos_sd_m**2
    p0[:, 3:6] = cfg.init_vel_sd_mps**2
    p0[:, 6:9] = cfg.init_shape_sd**2
    if J:
        skel = SKELETONS[scene.skeleton] if scene.skeleton else skeleton_for(J)
        canon = skel.canonical() - np.array([0.0, 0.0, PERSON_SEMI_AXES_M[2]])
        scale = np.exp(x0[:, 6:9]) / PERSON_SEMI_AXES_M  # (R, 3)
        placed = x0[:, None, 0:3] + np.einsum("ij,rkj->rki", wfb, canon[None] * scale[:, None])
        have = np.all(np.isfinite(kpt0), axis=-1) if kpt0 is not None else np.zeros((R, J), bool)
        joints = np.where(have[..., None], np.nan_to_num(kpt0) if kpt0 is not None else 0, placed)
        x0[:, layout.joints] = joints.reshape(R, 3 * J)
        var = np.where(have, cfg.init_joint_sd_m**2, cfg.init_canon_sd_m**2)
        p0[:, layout.joints] = np.repeat(var, 3, axis=1)
        p0[:, layout.joint_velocity] = cfg.init_vel_sd_mps**2
    return x0, p0


def ellipsoid_around(kpt: F64, kpt_sd: F64, world_from_body: F64, pad_m: float = 0.1
                     ) -> tuple[F64, F64, F64]:
    """Axis-aligned (body frame) ellipsoid around each row's joints ``(R, J, 3)``.

    Centre = middle of the joints' extent, semi-axes = half extent + ``pad_m`` (limbs have
    thickness); centre sd = RMS of the joints' sd. NaN where a row has no finite joint.
    """
    body = np.einsum("ji,rkj->rki", world_from_body, kpt)  # body coordinates
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows stay NaN
        lo, hi = np.nanmin(body, axis=1), np.nanmax(body, axis=1)
        sd = np.sqrt(np.nanmean(kpt_sd**2, axis=1))
    centre = np.einsum("ij,rj->ri", world_from_body, (lo + hi) / 2)
    semi = (hi - lo) / 2 + pad_m
    return centre, semi, np.repeat(sd[:, None], 3, axis=1)


def joints_of(x_s: F64, P_s: F64, layout: StateLayout, rows: Rows) -> tuple[F64, F64]:
    """Joints ``(R, J, 3)`` and their sd ``(R, J)``; NaN for joints an object never showed."""
    R, J = len(rows), layout.n_joints
    kpt = x_s[:, layout.joints].reshape(R, J, 3)
    var = np.einsum("rii->ri", P_s[:, layout.joints, layout.joints]).reshape(R, J, 3)
    sd = np.sqrt(var.mean(axis=2))
    never = never_seen(rows, J)
    kpt[never] = np.nan
    sd[never] = np.nan
    return kpt, sd


def rerun_with_bones(model: Model, cfg: UKFConfig, fps: float, x_s: F64, P_s: F64,
                     skel: Skeleton) -> tuple[F64, F64, dict[str, Any], dict[str, Any]]:
    r"""Second pass with bone-length pseudo-measurements ``|p_i - p_j| = L_b`` per person.

    ``L_b`` is the median of the first pass's smoothed lengths over the person's frames
    where two or more views saw both joints. The pseudo-measurement's sd is the bone's
    *true* variability: the variance of those lengths minus the mean variance the
    first pass's own uncertainty explains (``u^T (P_ii + P_jj - P_ij - P_ji) u``), floored
    at ``bone_sd_floor_m``; or ``cfg.bone_sd_m`` when given. So a rigid skeleton is held
    rigid, while a bone whose length really varies (or that the truth does not hold
    constant) is left almost free.
    """
    rows, layout = model.rows, model.layout
    R, J = len(rows), layout.n_joints
    bones = skel.bones
    P3 = x_s[:, layout.joints].reshape(R, J, 3)
    d = P3[:, bones[:, 0]] - P3[:, bones[:, 1]]  # (R, K, 3)
    length = np.linalg.norm(d, axis=-1)
    u = d / np.maximum(length[..., None], 1e-9)
    j0 = layout.joints.start + 3 * bones[:, 0, None] + np.arange(3)  # (K, 3)
    j1 = layout.joints.start + 3 * bones[:, 1, None] + np.arange(3)
    Pd = (P_s[:, j0[:, :, None], j0[:, None, :]] + P_s[:, j1[:, :, None], j1[:, None, :]]
          - P_s[:, j0[:, :, None], j1[:, None, :]] - P_s[:, j1[:, :, None], j0[:, None, :]])
    var_est = np.einsum("rki,rkij,rkj->rk", u, Pd, u)
    seen2 = np.isfinite(rows.kpt_z[..., 0]).sum(axis=1) >= 2  # (R, J)
    both = seen2[:, bones[:, 0]] & seen2[:, bones[:, 1]]
    O, K = len(rows.obj_ids), len(bones)
    L = np.full((O, K), np.nan)
    sd = np.full((O, K), np.nan)
    for o in range(O):
        mine = rows.row_o == o
        for k in range(K):
            sel = mine & both[:, k]
            v = length[sel, k]
            if v.size:
                L[o, k] = np.median(v)
                if v.size > 2:
                    # plain (not robust) variance: a bone the data show changing, even in a
                    # few frames, must not be forced rigid
                    spread = float(np.var(v, ddof=1))
                    sd[o, k] = np.sqrt(max(spread - float(np.mean(var_est[sel, k])), 0.0))
    if cfg.bone_sd_m is not None:
        sd = np.full_like(sd, cfg.bone_sd_m)
    sd = np.maximum(np.nan_to_num(sd, nan=0.05), cfg.bone_sd_floor_m)
    zb = L[rows.row_o]
    mb = np.isfinite(zb)
    bmodel = replace(model, z=np.concatenate([model.z, np.nan_to_num(zb)], 1),
                     mask=np.concatenate([model.mask, mb], 1),
                     var=np.concatenate([model.var, sd[rows.row_o] ** 2], 1), bones=bones)
    x2, P2, info = run_filter(bmodel, cfg, fps)
    names = [f"{skel.joints[a]}-{skel.joints[b]}" for a, b in bones]
    per_person = {
        str(int(rows.obj_ids[o])): {
            names[k]: {"length": None if not np.isfinite(L[o, k]) else round(float(L[o, k]), 5),
                       "sd": round(float(sd[o, k]), 5)}
            for k in range(K)}
        for o in range(O)}
    return x2, P2, info, {"skeleton": skel.name, "units": "m", "per_person": per_person}


def run_filter(model: Model, cfg: UKFConfig, fps: float) -> tuple[F64, F64, dict[str, Any]]:
    """Forward UKF over the frame grid, then (optionally) RTS. Returns ``(R, n)``, ``(R, n, n)``."""
    rows, cams, layout = model.rows, model.cams, model.layout
    n, R = layout.n, len(rows)
    if cfg.accel_sd is None or cfg.shape_sd is None:
        raise ValueError("run_filter needs numeric accel_sd and shape_sd")
    w = SigmaWeights(n, cfg.alpha, cfg.beta, cfg.kappa)
    update = (ukf_update_information if model.z.shape[1] >= cfg.information_form_min_m
              else ukf_update)
    x_p = np.zeros((R, n))
    P_p = np.zeros((R, n, n))
    x_f = np.zeros((R, n))
    P_f = np.zeros((R, n, n))
    frame_s = rows.frames / fps

    def transition(dt: F64) -> tuple[F64, F64]:
        return layout.transition(dt, cfg.accel_sd, cfg.shape_sd, cfg.joint_accel_sd,  # type: ignore[arg-type]
                                 up=cams.up, vertical_ratio=cfg.vertical_ratio)

    stats = {"repaired": 0, "nis": 0.0, "dof": 0, "loglik": 0.0}
    for t in range(len(rows.frames)):
        r = np.arange(rows.t_start[t], rows.t_start[t + 1])
        if len(r) == 0:
            continue
        prev = rows.prev_row[r]
        new = prev < 0
        if new.any():
            rn = r[new]
            x_p[rn] = model.x0[rn]
            P_p[rn] = model.p0_diag[rn][:, :, None] * np.eye(n)
        if (~new).any():
            ro, po = r[~new], prev[~new]
            F, Q = transition(frame_s[t] - frame_s[rows.row_t[po]])
            x_p[ro], P_p[ro] = predict_linear(x_f[po], P_f[po], F, Q)
        xl, Pl = model.linearisation_point(r, x_p[r], P_p[r])
        x_f[r], P_f[r], inf = update(x_p[r], P_p[r], model.z[r], model.mask[r], model.var[r],
                                     model.h, w, cfg.iterations, xl, Pl)
        for k in stats:
            stats[k] += inf[k]
    x_s, P_s = x_f.copy(), P_f.copy()
    if cfg.smooth:
        for t in range(len(rows.frames) - 2, -1, -1):
            r = np.arange(rows.t_start[t], rows.t_start[t + 1])
            r = r[rows.next_row[r] >= 0]
            if len(r) == 0:
                continue
            nr = rows.next_row[r]
            F, _ = transition(np.full(len(r), frame_s[t + 1] - frame_s[t]))
            x_s[r], P_s[r] = rts_step(x_f[r], P_f[r], x_p[nr], P_p[nr], x_s[nr], P_s[nr], F)
    info: dict[str, Any] = {
        "pd_repairs": int(stats["repaired"]),
        "mean_nis_per_dof": float(stats["nis"]) / max(int(stats["dof"]), 1),
        "object_frames": R,
        "loglik": float(stats["loglik"]),
        "update_form": "information" if update is ukf_update_information else "covariance",
    }
    return x_s, P_s, info
