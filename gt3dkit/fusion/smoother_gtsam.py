r"""A second, independent estimator: one GTSAM factor graph per object over all its frames.

Variables (per object)
    ``c_k`` (Point3) ellipsoid centre, ``v_k`` (Point3) its velocity and ``s_k`` (Vector3)
    log semi-axes at every frame row; for keypoints ``p_{k,j}`` (Point3) and
    ``w_{k,j}`` (Point3) velocity of each joint the object ever shows.
Factors
    * constant velocity between consecutive rows (``CustomFactor``, linear, exact
      discrete-time ``Q`` of :class:`gt3dkit.fusion.motion.StateLayout`), and a random walk
      of the log semi-axes (``BetweenFactorVector``), as in the UKF;
    * one ``TriangulationFactorCal3_S2`` per 2D keypoint: GTSAM's projection factor with the
      calibrated camera; the keypoint is undistorted first (GTSAM's ``Cal3DS2`` has no ``k3``);
    * one ``CustomFactor`` per box whose error is the tangent-box residual of its usable
      edges (:func:`gt3dkit.fusion.boxfit.box_model`), Jacobian by central differences;
    * Huber-robust noise models on every measurement; weak priors (1 m, 10 m/s, 1.0 in log
      axes) at the per-frame initial values so that nothing is left undetermined.
Solved by Gauss-Newton with a line search (:func:`_gtsam_gauss_newton`, GTSAM's linearisation and
elimination); each output's standard deviation from GTSAM's marginal covariances. Objects with
boxes only (no keypoints) are linearised in batches instead (:func:`_solve_boxes`: the same
factors, losses and steps as arrays, one ``JacobianFactor`` per row for GTSAM to eliminate; the
tests hold it to the ``CustomFactor`` graph): Python called per factor was 3/4 of the time.

Conventions are converted here and only here: GTSAM's camera pose is ``world_from_cam``
(``Pose3(Rot3(R^T), C)``), our cameras are ``cam_from_world``.

Noise levels: measurement noise from :func:`gt3dkit.fusion.prepare.prepare` (the robust
per-frame residual levels every estimator shares; points the per-frame fits rejected get no
factor, the rest a Huber loss). Process noise of box scenes: the maximum of the model's
marginal likelihood (:func:`gt3dkit.fusion.noise.noise_by_likelihood`, the Kalman
filter's prediction-error decomposition of the same state-space model; the graph then solves it
another way, as one batch). The moment estimates from the per-frame fits it used before
(:func:`moment_process_noise`, raised by Morozov's discrepancy principle) fit neither real set:
38 mm on MultiviewX and 49 mm on WILDTRACK where the likelihood's values give 10.7 and 17.3 mm.
Keypoint scenes keep them (``likelihood_noise`` applies to boxes). The motion factors carry the
measurements' Huber loss too (``robust_motion``): people stop and turn between two annotations,
and a Gaussian motion factor then held the track off the views by decimetres. Rows no view
saw start between their object's placed rows, with no prior (:func:`_start_values`).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from gt3dkit.errors import EstimationError
from gt3dkit.fusion.gtsam_factors import (
    _box_error,
    _cv_factor,
    _gauss_newton,
    _gtsam_gauss_newton,
    cv_whitening,
    huber_loss,
    huber_sqrt_weight,
)
from gt3dkit.fusion.motion import walk_sd
from gt3dkit.fusion.noise import ProcessNoise, moment_process_noise, noise_by_likelihood
from gt3dkit.fusion.prepare import (
    Prepared,
    axis_sd,
    ellipsoid_around,
    never_determined,
    prepare,
)
from gt3dkit.fusion.ukf_config import UKFConfig
from gt3dkit.geom.boxkernel import EVERY_CAMERA, BoxCameras, box_jacobian, box_rig, kernel
from gt3dkit.geom.camera import apply_K
from gt3dkit.geom.triangulate import normalized_points
from gt3dkit.types import F64, Scene, TrackSet


def _discrepancy(results: list[dict[str, Any]], tuned: ProcessNoise, step: float,
                 limit: float = 1.0) -> tuple[ProcessNoise, dict[str, Any]]:
    r"""Morozov's discrepancy principle on the solution: the measurements' whitened squared
    residuals (Huber-robust, as the graph sees them) per measurement, ``chi^2 / m``, should not
    exceed their noise level (``limit``; the per-frame fits, with every frame's own 6 or 3
    parameters, sit at ``(m - p) / m`` below it). Above it the motion model holds the
    estimate off the data (too little process noise: the moment estimate reads a smooth
    typical frame and misses the turns): every process noise is multiplied by ``step``."""
    chi = sum(r["meas"][0] for r in results)
    dof = sum(r["meas"][1] for r in results)
    ratio = chi / max(dof, 1)
    out: dict[str, Any] = {"measurement_chi2_per_entry": ratio, "rescaled": ratio > limit}
    if ratio <= limit:
        return tuned, out
    return ProcessNoise(tuned.accel_sd * step, tuned.shape_sd * step, tuned.joint_accel_sd * step,
                        tuned.source), out


@dataclass(frozen=True)
class GTSAMConfig:
    """Settings of :class:`GTSAMSmoother`. ``None`` = from the data (as the UKF does)."""

    sigma_px: float | None = None
    kpt_sigma_px: float | None = None
    accel_sd: float | None = None
    shape_sd: float | None = None
    joint_accel_sd: float | None = None
    vertical_ratio: float = 0.1
    huber_k: float = 1.345
    clip_tol_px: float = 1.0
    max_iterations: int = 100
    # stop when an iteration lowers the error by a smaller fraction (on WILDTRACK, 1e-6 moved no
    # centre by more than 0.06 of its sd, in twice the time)
    relative_error_tol: float = 1e-4
    discrepancy_steps: int = 3
    discrepancy_step: float = 3.0
    likelihood_noise: bool = True
    robust_motion: bool = True


def _gtsam() -> Any:
    import gtsam

    return gtsam


class GTSAMSmoother:
    """Batch maximum a posteriori smoothing per object with GTSAM (see module doc)."""

    name = "gtsam"

    def __init__(self, config: GTSAMConfig | None = None) -> None:
        self.config = config or GTSAMConfig()

    def prepare(self, scene: Scene) -> Prepared:
        cfg = self.config
        return prepare(scene, cfg.clip_tol_px, cfg.sigma_px, cfg.kpt_sigma_px)

    def estimate(self, scene: Scene, pre: Prepared | None = None) -> TrackSet:
        gtsam = _gtsam()
        cfg = self.config
        t0 = time.perf_counter()
        pre = pre or self.prepare(scene)
        rows, cams, layout, use_box, use_kpt = (pre.rows, pre.cams, pre.layout, pre.use_box,
                                                pre.use_kpt)
        R, J = len(rows), layout.n_joints
        x0, var0, _ = pre.frame_state()
        x0, own = _start_values(pre, x0)
        tuned = moment_process_noise(pre, x0, var0, scene.fps, cfg.accel_sd, cfg.shape_sd,
                                     cfg.joint_accel_sd)
        position_sd, curves = 0.0, None
        by_likelihood = cfg.likelihood_noise and use_box and not use_kpt and (cfg.accel_sd is None
                                                                           or cfg.shape_sd is None)
        if by_likelihood:
            ml, curves = noise_by_likelihood(pre, scene.fps, UKFConfig(
                sigma_px=cfg.sigma_px, accel_sd=cfg.accel_sd, shape_sd=cfg.shape_sd,
                vertical_ratio=cfg.vertical_ratio, clip_tol_px=cfg.clip_tol_px))
            tuned = ProcessNoise(float(ml.accel_sd), float(ml.shape_sd), tuned.joint_accel_sd,
                                 "maximum of the model's marginal likelihood (the Kalman filter's "
                                 "prediction-error decomposition: the UKF's noise search)")
            position_sd = float(ml.position_sd or 0.0)
        centre = x0[:, layout.center].copy()
        log_axes = x0[:, layout.log_axes].copy()
        c_sd = np.full((R, 3), np.nan)
        kpt = x0[:, layout.joints].reshape(R, J if use_kpt else 0, 3).copy()
        kpt_sd = np.full(kpt.shape[:2], np.nan)
        stats = {"iterations": 0, "final_error": 0.0, "factors": 0}
        # undistorted pixels of every keypoint (GTSAM's pinhole with Cal3_S2)
        und = None
        if use_kpt:
            und = apply_K(normalized_points(rows.kpt_z, cams.K[:, None], cams.dist[:, None]),
                          cams.K[:, None])  # (R, C, J, 2)
        cal = [gtsam.Cal3_S2(k[0, 0], k[1, 1], k[0, 1], k[0, 2], k[1, 2]) for k in cams.K]
        gcams = [gtsam.PinholeCameraCal3_S2(
            gtsam.Pose3(gtsam.Rot3(r.T), -r.T @ t), cal[c])
            for c, (r, t) in enumerate(zip(cams.R, cams.t, strict=True))]
        moment = tuned
        checks: list[dict[str, Any]] = []
        results: list[dict[str, Any]] = []
        for attempt in range(cfg.discrepancy_steps + 1):
            # a retry with more process noise starts where the previous solution ended
            results = [self._solve(gtsam, pre, np.flatnonzero(rows.row_o == o),
                                   (x0, own, position_sd), (und, gcams), tuned, scene.fps,
                                   results[o]["values"] if attempt else None)
                       for o in range(len(rows.obj_ids))]
            if attempt == cfg.discrepancy_steps or (cfg.accel_sd and cfg.joint_accel_sd) \
                    or by_likelihood:
                break
            new, chk = _discrepancy(results, tuned, cfg.discrepancy_step)
            checks.append({**tuned.as_dict(), **chk})
            if not chk["rescaled"]:
                break
            tuned = new
        for o, res in enumerate(results):
            mine = np.flatnonzero(rows.row_o == o)  # sorted by frame
            for k in stats:
                stats[k] += res["stats"][k]
            centre[mine], log_axes[mine], c_sd[mine] = res["centre"], res["log_axes"], res["c_sd"]
            if use_kpt:
                kpt[mine], kpt_sd[mine] = res["kpt"], res["kpt_sd"]
        semi = np.exp(log_axes)
        if use_kpt:
            # never placed by two views, or every point of it rejected: no estimate (x0 is only a guess)
            nv = never_determined(rows, pre.kpt0) | ~np.isfinite(kpt_sd)
            kpt[nv], kpt_sd[nv] = np.nan, np.nan
            if not use_box:
                centre, semi, c_sd = ellipsoid_around(kpt, kpt_sd, cams.world_from_body)
        info = {"estimator": self.name,
                "params": {**asdict(cfg),
                           "sigma_px": pre.info["boxes"]["sigma_px"] if use_box else None,
                           "sigma_px_core": pre.info["boxes"]["sigma_px_core"] if use_box else None,
                           "kpt_sigma_px": pre.info.get("keypoints", {}).get("sigma_px"),
                           **tuned.as_dict(), "fps": scene.fps},
                "process_noise_source": tuned.source,
                "process_noise_likelihood": curves, "position_sd": position_sd,
                "motion_loss": f"Huber k={cfg.huber_k}" if cfg.robust_motion else "Gaussian",
                "process_noise_moment_estimate": moment.as_dict(),
                "process_noise_discrepancy": checks,
                "preparation": pre.info,
                "optimizer": "Gauss-Newton, line search (GTSAM), one graph per object", **stats,
                "object_frames": R, "seconds": time.perf_counter() - t0}
        return TrackSet(frame=rows.frames[rows.row_t], track_id=rows.obj_ids[rows.row_o],
                        center_world=centre, semi_axes=semi, center_sd=c_sd, n_views=rows.n_views,
                        kpt_world=kpt, kpt_sd=kpt_sd, info=info)

    def _solve(self, gtsam: Any, pre: Prepared, mine: np.ndarray,
               start_values: tuple[F64, np.ndarray, float], kpt: tuple[F64 | None, list[Any]],
               tuned: ProcessNoise, fps: float, start: Any = None) -> dict[str, Any]:
        """One object's graph: batched for box objects (:func:`_solve_boxes`), GTSAM's
        nonlinear factors for keypoints, and for a box object whose batched graph GTSAM finds
        singular (its elimination of the stacked rows can be stricter than of the separate
        factors, as for an object only one camera ever sees)."""
        if not pre.use_kpt:
            try:
                return _solve_boxes(gtsam, self.config, pre, mine, start_values, tuned, fps, start)
            except EstimationError:
                start = None
        return self._solve_object(gtsam, pre, mine, start_values, kpt[0], kpt[1], tuned, fps,
                                  None if isinstance(start, np.ndarray) else start)

    def _solve_object(self, gtsam: Any, pre: Prepared, mine: np.ndarray,
                      start_values: tuple[F64, np.ndarray, float], und: F64 | None, gcams: list[Any],
                      tuned: ProcessNoise, fps: float, start: Any = None) -> dict[str, Any]:
        cfg = self.config
        # (R, n) start; (R,) rows whose own views placed them (weak prior); the centre's own
        # random walk (m/sqrt(s), gt3dkit.fusion.motion)
        x0, own, position_sd = start_values
        rows, cams, layout = pre.rows, pre.cams, pre.layout
        use_box, use_kpt, sigma_box = pre.use_box, pre.use_kpt, pre.sigma_box
        C = len(cams.K)
        J = layout.n_joints
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        sym = gtsam.symbol
        n_rows = len(mine)
        huber = gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_k)
        # box edges are weighted by the typical edge's noise and give way beyond the whole level
        huber_box = gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_k * np.sqrt(pre.box_tail))
        # the motion too has heavy tails: people stop and turn between two annotations, and a
        # Gaussian motion factor would then outvote the views (the boxes' Huber loss gives way)
        motion_loss = huber if cfg.robust_motion else None
        weak3 = gtsam.noiseModel.Isotropic.Sigma(3, 1.0)
        frame_s = rows.frames[rows.row_t[mine]] / fps
        # Time in units of the typical step (velocities in m/step): the graph's conditioning
        # then does not depend on the frame rate (at 1e5 fps, seconds make it singular).
        # Positions, shapes and their noise are the same in any time unit.
        dts = np.diff(frame_s)
        tau = float(np.median(dts)) if dts.size else 1.0
        dts = dts / tau
        weakv = gtsam.noiseModel.Isotropic.Sigma(3, 10.0 * tau)  # 10 m/s
        seen_j = np.zeros(J, bool)
        if use_kpt and und is not None:
            seen_j = (np.isfinite(und[mine][..., 0]) & pre.kpt_keep[mine]).any(axis=(0, 1))
        blocks: list[tuple[str, int, float]] = []  # (symbol char, joint, accel_sd)
        if use_box:
            blocks.append(("c", 0, tuned.accel_sd))
            la = layout.log_axes
            for k, r in enumerate(mine):
                vals.insert(sym("s", k), x0[r, la].copy())
                if own[r]:
                    g.add(gtsam.PriorFactorVector(sym("s", k), x0[r, la].copy(),
                                                  gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
            for k, dt in enumerate(dts):
                g.add(gtsam.BetweenFactorVector(
                    sym("s", k), sym("s", k + 1), np.zeros(3),
                    gtsam.noiseModel.Isotropic.Sigma(3, walk_sd(tuned.shape_sd, dt * tau))))
        for j in np.flatnonzero(seen_j):
            blocks.append(("p", int(j), tuned.joint_accel_sd))
        blocks = [(ch, j, q * tau**1.5) for ch, j, q in blocks]  # m/s^2/sqrt(Hz) -> per step
        pos_step = walk_sd(position_sd, tau)  # m/sqrt(s) -> per step
        meas: list[int] = []
        meas_dof = 0
        for ch, j, q in blocks:
            vch = "v" if ch == "c" else "w"
            for k, r in enumerate(mine):
                if ch == "c":
                    init = x0[r, layout.center]
                else:
                    init = x0[r, layout.joints.start + 3 * j: layout.joints.start + 3 * j + 3]
                kx, kv = sym(ch, k * 32 + j), sym(vch, k * 32 + j)
                vals.insert(kx, np.asarray(init, dtype=np.float64).copy())
                vals.insert(kv, np.zeros(3))
                if own[r] or ch != "c":
                    g.add(gtsam.PriorFactorPoint3(kx, np.asarray(init, float).copy(), weak3))
                g.add(gtsam.PriorFactorPoint3(kv, np.zeros(3), weakv))
            W = cv_whitening(dts, q, cams.up if ch == "c" else None, cfg.vertical_ratio,
                             pos_step if ch == "c" else 0.0)
            for k, dt in enumerate(dts):
                g.add(_cv_factor(gtsam, [sym(ch, k * 32 + j), sym(vch, k * 32 + j),
                                         sym(ch, (k + 1) * 32 + j), sym(vch, (k + 1) * 32 + j)],
                                 float(dt), W[k], motion_loss))
        if use_box:
            bc = BoxCameras.of(cams)
            for k, r in enumerate(mine):
                m = pre.box_keep[r].reshape(-1)
                if not m.any():
                    continue
                z = rows.box_z[r].reshape(-1)[m]
                noise = gtsam.noiseModel.Robust.Create(
                    huber_box, gtsam.noiseModel.Diagonal.Sigmas(np.tile(sigma_box, C)[m]))
                meas.append(int(g.size()))
                meas_dof += int(m.sum())
                g.add(gtsam.CustomFactor(noise, [sym("c", k * 32), sym("s", k)],
                                         _box_error(bc, z, m, C)))
        if use_kpt and und is not None:
            for k, r in enumerate(mine):
                cc, jj = np.nonzero(np.isfinite(und[r][..., 0]) & pre.kpt_keep[r])
                for c, j in zip(cc, jj, strict=True):
                    noise_k = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(
                        2, float(np.sqrt(pre.kpt_var[r, c, j]))))
                    meas.append(int(g.size()))
                    meas_dof += 2
                    g.add(gtsam.TriangulationFactorCal3_S2(gcams[c], und[r, c, j], noise_k,
                                                           sym("p", k * 32 + int(j))))
        try:
            result, iters, final = _gtsam_gauss_newton(g, vals if start is None else start,
                                                       cfg.max_iterations, cfg.relative_error_tol)
            marg = gtsam.Marginals(g, result)
        except RuntimeError as e:  # gtsam's IndeterminateLinearSystemException and kin
            raise _singular(e, pre, mine, tuned, fps) from None
        out: dict[str, Any] = {
            "centre": x0[mine][:, layout.center].copy(), "log_axes": x0[mine][:, layout.log_axes].copy(),
            "c_sd": np.full((n_rows, 3), np.nan),
            "kpt": x0[mine][:, layout.joints].reshape(n_rows, J, 3).copy(),
            "kpt_sd": np.full((n_rows, J), np.nan),
            "stats": {"iterations": iters, "final_error": final,
                      "factors": int(g.size())},
            "values": result,
            # whitened squared residuals of the measurements (error = chi2 / 2, Huber-robust)
            "meas": (2.0 * sum(g.at(i).error(result) for i in meas), float(meas_dof)),
        }
        if use_box:
            for k in range(n_rows):
                out["log_axes"][k] = result.atVector(sym("s", k))
                out["centre"][k] = result.atPoint3(sym("c", k * 32))
                out["c_sd"][k] = axis_sd(marg.marginalCovariance(sym("c", k * 32)))
        for j in np.flatnonzero(seen_j):
            for k in range(n_rows):
                key = sym("p", k * 32 + int(j))
                out["kpt"][k, j] = result.atPoint3(key)
                out["kpt_sd"][k, j] = np.sqrt(np.linalg.eigvalsh(marg.marginalCovariance(key))[-1])
        return out


BOX_DIM = 9  # a box object's variable per row: centre (3), velocity (3, m/step), log axes (3)


class _BoxChain:
    """The graph of one box object as arrays (see :func:`_solve_boxes`): every factor's whitened
    residual and Jacobian computed for all its rows at once, the robust weights as GTSAM's
    ``Robust`` noise model applies them (one Huber weight per factor, from its whitened norm)."""

    def __init__(self, cfg: GTSAMConfig, pre: Prepared, mine: np.ndarray,
                 start_values: tuple[F64, np.ndarray, float], tuned: ProcessNoise, fps: float) -> None:
        x0, own, position_sd = start_values
        rows, cams, lay = pre.rows, pre.cams, pre.layout
        n, C = len(mine), len(cams.K)
        self.n, self.C = n, C
        self.bc = BoxCameras.of(cams)
        self.rig = box_rig(self.bc, 2)
        self.keep = pre.box_keep[mine].reshape(n, 4 * C)  # (n, 4C) usable edges
        self.z = np.where(self.keep, rows.box_z[mine].reshape(n, 4 * C), 0.0)
        self.inv_sd = np.tile(1.0 / np.asarray(pre.sigma_box, float), C)  # (4C,)
        self.k_box = cfg.huber_k * np.sqrt(pre.box_tail)
        self.k_motion = cfg.huber_k if cfg.robust_motion else np.inf
        # time in units of the typical step (see GTSAMSmoother._solve_object)
        dts = np.diff(rows.frames[rows.row_t[mine]] / fps)
        tau = float(np.median(dts)) if dts.size else 1.0
        self.dts = dts / tau
        self.W = cv_whitening(self.dts, tuned.accel_sd * tau**1.5, cams.up, cfg.vertical_ratio,
                              walk_sd(position_sd, tau))  # (n-1, 6, 6)
        self.inv_shape_sd = 1.0 / walk_sd(tuned.shape_sd, self.dts * tau)  # (n-1,)
        # weak priors: centre (1 m) and log axes (1.0) where the row's own views placed it,
        # velocity (10 m/s) everywhere
        self.prior_at = np.c_[x0[mine][:, lay.center], np.zeros((n, 3)), x0[mine][:, lay.log_axes]]
        own_m = own[mine].astype(np.float64)[:, None]
        self.prior_w = np.c_[own_m.repeat(3, 1), np.full((n, 3), 1.0 / (10.0 * tau)),
                             own_m.repeat(3, 1)]  # (n, 9) inverse sds (0: no prior)
        I3 = np.eye(3)
        # d[x_{k+1} - x_k - dt v_k ; v_{k+1} - v_k] / d(c_k, v_k) and / d(c_{k+1}, v_{k+1})
        from_k = np.zeros((len(self.dts), 6, 6))
        from_k[:, :3, :3], from_k[:, 3:, 3:] = -I3, -I3
        from_k[:, :3, 3:] = -self.dts[:, None, None] * I3
        self.A_from = self.W @ from_k
        self.start = self.prior_at.copy()

    def box_residuals(self, z: F64, jacobian: bool) -> tuple[F64, F64 | None]:
        """``(n, 4C)`` whitened box-edge residuals (0 where no edge; 1e6 where the box is
        undefined, as the factor said) and ``(n, 4C, 6)`` their derivatives by centre and log
        axes (:func:`gt3dkit.geom.boxkernel.box_jacobian`) when ``jacobian``."""
        n, C = self.n, self.C
        box = np.empty((n, C, 4))
        grad = None
        if jacobian:
            grad = np.empty((n, C, 4, 6))
            p = np.ascontiguousarray(np.c_[z[:, :3], z[:, 6:]])
            for k in range(n):
                box_jacobian(p[k], self.rig, box[k], grad[k])
        else:
            kernel(np.ascontiguousarray(z[:, :3]), np.exp(z[:, 6:]), self.bc, 2, EVERY_CAMERA,
                   box, np.empty((n, C)))
        e = box.reshape(n, 4 * C) - self.z
        e = np.where(np.isfinite(e), e, 1e6) * self.inv_sd
        e = np.where(self.keep, e, 0.0)
        if grad is None:
            return e, None
        J = grad.reshape(n, 4 * C, 6) * self.inv_sd[:, None]
        J = np.where(self.keep[..., None] & np.isfinite(J), J, 0.0)
        return e, J

    def motion_residuals(self, z: F64) -> tuple[F64, F64]:
        """``(n-1, 6)`` whitened constant-velocity residuals and ``(n-1, 3)`` log-axes steps."""
        c, v, s = z[:, :3], z[:, 3:6], z[:, 6:]
        d = np.c_[c[1:] - c[:-1] - self.dts[:, None] * v[:-1], v[1:] - v[:-1]]
        return np.einsum("kij,kj->ki", self.W, d), (s[1:] - s[:-1]) * self.inv_shape_sd[:, None]

    def errors(self, z: F64) -> tuple[float, float]:
        """The graph's error at ``z (n, 9)`` (as GTSAM's: half the Gaussian factors' squared
        whitened norms, the Huber loss of the robust ones) and that of the box factors alone."""
        e_box, _ = self.box_residuals(z, False)
        e_cv, e_s = self.motion_residuals(z)
        box = float(huber_loss(np.linalg.norm(e_box, axis=1), self.k_box).sum())
        prior = 0.5 * float((((z - self.prior_at) * self.prior_w) ** 2).sum())
        motion = float(huber_loss(np.linalg.norm(e_cv, axis=1), self.k_motion).sum())
        return box + prior + motion + 0.5 * float((e_s**2).sum()), box

    def linearized(self, gtsam: Any, z: F64) -> Any:
        """The graph linearised at ``z``: one ``JacobianFactor`` per row on (row, next row)
        stacking its box edges, its priors, and its steps to the next row (unit noise: rows
        whitened and robustly weighted here, ``b = -`` the residual)."""
        n, m = self.n, 4 * self.C
        e_box, J_box = self.box_residuals(z, True)
        e_cv, e_s = self.motion_residuals(z)
        w_box = huber_sqrt_weight(np.linalg.norm(e_box, axis=1), self.k_box)[:, None]
        w_cv = huber_sqrt_weight(np.linalg.norm(e_cv, axis=1), self.k_motion)[:, None]
        rows = m + 2 * BOX_DIM
        A1, A2, b = np.zeros((n, rows, BOX_DIM)), np.zeros((n, rows, BOX_DIM)), np.zeros((n, rows))
        A1[:, :m, :3] = J_box[..., :3] * w_box[..., None]
        A1[:, :m, 6:] = J_box[..., 3:] * w_box[..., None]
        b[:, :m] = -e_box * w_box
        diag = np.arange(BOX_DIM)
        A1[:, m + diag, diag] = self.prior_w
        b[:, m:m + BOX_DIM] = -(z - self.prior_at) * self.prior_w
        o = m + BOX_DIM
        A1[:-1, o:o + 6, :6] = self.A_from * w_cv[..., None]
        A2[:-1, o:o + 6, :6] = self.W * w_cv[..., None]
        b[:-1, o:o + 6] = -e_cv * w_cv
        A1[:-1, o + 6 + np.arange(3), 6 + np.arange(3)] = -self.inv_shape_sd[:, None]
        A2[:-1, o + 6 + np.arange(3), 6 + np.arange(3)] = self.inv_shape_sd[:, None]
        b[:-1, o + 6:] = -e_s
        g = gtsam.GaussianFactorGraph()
        unit = gtsam.noiseModel.Unit.Create(rows)
        for k in range(n - 1):
            g.add(gtsam.JacobianFactor(k, A1[k], k + 1, A2[k], b[k], unit))
        g.add(gtsam.JacobianFactor(n - 1, A1[-1], b[-1], unit))
        return g


def _solve_boxes(gtsam: Any, cfg: GTSAMConfig, pre: Prepared, mine: np.ndarray,
                 start_values: tuple[F64, np.ndarray, float], tuned: ProcessNoise, fps: float,
                 start: F64 | None = None) -> dict[str, Any]:
    """One box object's graph (the factors of :meth:`GTSAMSmoother._solve_object`: a box factor
    per row, constant velocity and a log-axes random walk between rows, the weak priors; the
    same Huber losses) solved by the same Gauss-Newton with a line search, linearised in
    batches (:class:`_BoxChain`): GTSAM eliminates each linear step and gives the marginal
    covariances. A ``CustomFactor`` per box and per step called Python ~25 times per
    object-frame; this is 3-4x faster on long scenes and gives the same solution."""
    chain = _BoxChain(cfg, pre, mine, start_values, tuned, fps)
    z = start.copy() if isinstance(start, np.ndarray) else chain.start.copy()
    try:
        z, iters, err = _gauss_newton(
            lambda v: chain.errors(v)[0],
            lambda v: chain.linearized(gtsam, v).optimize().vector().reshape(chain.n, BOX_DIM),
            lambda v, d, k: v + k * d, z, cfg.max_iterations, cfg.relative_error_tol)
        lin = chain.linearized(gtsam, z)
        marg = gtsam.Marginals(lin, lin.optimize())
    except RuntimeError as e:  # gtsam's IndeterminateLinearSystemException and kin
        raise _singular(e, pre, mine, tuned, fps) from None
    cov = np.array([marg.marginalCovariance(k)[:3, :3] for k in range(chain.n)])
    J = pre.layout.n_joints
    return {"centre": z[:, :3].copy(), "log_axes": z[:, 6:].copy(), "c_sd": axis_sd(cov),
            "kpt": np.full((chain.n, J, 3), np.nan), "kpt_sd": np.full((chain.n, J), np.nan),
            "stats": {"iterations": iters, "final_error": err, "factors": chain.n},
            "values": z,
            # whitened squared residuals of the box edges (error = chi2 / 2, Huber-robust)
            "meas": (2.0 * chain.errors(z)[1], float(chain.keep.sum()))}


def _start_values(pre: Prepared, x0: F64) -> tuple[F64, np.ndarray]:
    """The graph's start: every row's own per-frame fit where its views placed it (``own (R,)``:
    those rows also get the weak priors); a row no view saw (a gap in its annotations) starts
    on the line between its object's nearest placed rows (centre and log axes), with no prior:
    the per-frame state there is a placeholder (the origin), and a prior on it pulled the
    track towards the origin, metres off on real WILDTRACK."""
    rows, lay = pre.rows, pre.layout
    own = rows.n_views > 0
    if pre.fit is not None:
        own &= pre.fit.ok
    x0 = x0.copy()
    t = rows.frames[rows.row_t].astype(np.float64)
    dims = lay.ellipsoid_dims
    for o in np.unique(rows.row_o[~own]):
        mine = rows.row_o == o
        have, need = np.flatnonzero(mine & own), np.flatnonzero(mine & ~own)
        if not len(have):
            continue
        for d in dims:
            x0[need, d] = np.interp(t[need], t[have], x0[have, d])
    return x0, own


def _singular(e: RuntimeError, pre: Prepared, mine: np.ndarray, tuned: ProcessNoise,
              fps: float) -> EstimationError:
    """GTSAM's IndeterminateLinearSystemException (and kin) on the graph of the object of rows
    ``mine``, as the one-line error the user reads."""
    first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    oid = int(pre.rows.obj_ids[pre.rows.row_o[mine[0]]])
    return EstimationError("gtsam", f"the factor graph of object {oid} is singular ({first}); "
                           f"process noise {tuned.accel_sd:.3g} m/s^2/sqrt(Hz) at {fps:g} fps: "
                           "check the frame rate, or use --estimator ukf")


