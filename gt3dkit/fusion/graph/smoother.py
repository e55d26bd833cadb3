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
      edges (:func:`gt3dkit.fusion.preparation.boxfit.state_boxes`), Jacobian by central differences;
    * Huber-robust noise models on every measurement; weak priors (1 m, 10 m/s, 1.0 in log
      axes) at the per-frame initial values so that nothing is left undetermined.
Solved by Gauss-Newton with a line search
(:func:`gt3dkit.fusion.graph.factors.gtsam_gauss_newton`, GTSAM's linearisation and
elimination); each output's standard deviation from GTSAM's marginal covariances. Objects with
boxes only (no keypoints) are linearised in batches instead
(:func:`gt3dkit.fusion.graph.chain.solve_boxes`: the same factors, losses and steps as arrays,
one ``JacobianFactor`` per row for GTSAM to eliminate; the tests hold it to the ``CustomFactor``
graph): Python called per factor was 3/4 of the time.

Conventions are converted here and only here: GTSAM's camera pose is ``world_from_cam``
(``Pose3(Rot3(R^T), C)``), our cameras are ``cam_from_world``.

Noise levels: measurement noise from :func:`gt3dkit.fusion.preparation.prepare.prepare` (the robust
per-frame residual levels every estimator shares; points the per-frame fits rejected get no
factor, the rest a Huber loss). Process noise of box scenes: the maximum of the model's
marginal likelihood (:func:`gt3dkit.fusion.ukf.noise.noise_by_likelihood`, the Kalman
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
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from gt3dkit.errors import EstimationError
from gt3dkit.fusion.base import Capabilities
from gt3dkit.fusion.graph.chain import GTSAMConfig, ObjectSolution, singular, solve_boxes
from gt3dkit.fusion.graph.factors import (
    box_error,
    cv_factor,
    cv_whitening,
    gtsam_gauss_newton,
)
from gt3dkit.fusion.motion import walk_sd
from gt3dkit.fusion.preparation.prepare import (
    Prepared,
    axis_sd,
    ellipsoid_around,
    never_determined,
    prepare,
)
from gt3dkit.fusion.ukf.bones import PersonBones
from gt3dkit.fusion.ukf.config import UKFConfig
from gt3dkit.fusion.ukf.noise import ProcessNoise, moment_process_noise, noise_by_likelihood
from gt3dkit.geom.boxrig import BoxCameras
from gt3dkit.geom.camera import apply_K
from gt3dkit.geom.triangulate import normalized_points
from gt3dkit.types import F64, JsonDict, RunInfo, Scene, TrackSet

if TYPE_CHECKING:
    import gtsam


def _discrepancy(results: list[ObjectSolution], tuned: ProcessNoise, step: float,
                 limit: float = 1.0) -> tuple[ProcessNoise, JsonDict]:
    r"""Morozov's discrepancy principle on the solution: the measurements' whitened squared
    residuals (Huber-robust, as the graph sees them) per measurement, ``chi^2 / m``, should not
    exceed their noise level (``limit``; the per-frame fits, with every frame's own 6 or 3
    parameters, sit at ``(m - p) / m`` below it). Above it the motion model holds the
    estimate off the data (too little process noise: the moment estimate reads a smooth
    typical frame and misses the turns): every process noise is multiplied by ``step``."""
    chi = sum(r.meas_chi2 for r in results)
    dof = sum(r.meas_dof for r in results)
    ratio = chi / max(dof, 1)
    out: JsonDict = {"measurement_chi2_per_entry": ratio, "rescaled": ratio > limit}
    if ratio <= limit:
        return tuned, out
    return ProcessNoise(tuned.accel_sd * step, tuned.shape_sd * step, tuned.joint_accel_sd * step,
                        tuned.source), out


@dataclass
class _ObjectGraph:
    """One object's nonlinear graph (:meth:`GTSAMSmoother._solve_object`): the graph, its start,
    the indices of its measurement factors and their entries, and the joints it holds."""

    g: gtsam.NonlinearFactorGraph
    vals: gtsam.Values
    meas: list[int]
    meas_dof: int
    seen_j: np.ndarray


@dataclass(frozen=True)
class _Noise:
    """The process noise the graphs start from (:meth:`GTSAMSmoother._process_noise`), the
    centre's own random walk (m/sqrt(s)), the likelihood curves of the search (None: the moment
    estimate) and whether the search set it (then the discrepancy principle does not)."""

    tuned: ProcessNoise
    position_sd: float
    curves: JsonDict | None
    by_likelihood: bool


def _gtsam() -> ModuleType:
    import gtsam

    return gtsam


class GTSAMSmoother:
    """Batch maximum a posteriori smoothing per object with GTSAM (see module doc)."""

    name = "gtsam"
    bones: PersonBones | None = None  # (no bones: Estimator.bones)

    capabilities = Capabilities()

    def __init__(self, config: GTSAMConfig | None = None) -> None:
        self.config = config or GTSAMConfig()

    def prepare(self, scene: Scene) -> Prepared:
        cfg = self.config
        return prepare(scene, cfg.clip_tol_px, cfg.sigma_px, cfg.kpt_sigma_px)

    def process_noise(self, scene: Scene, pre: Prepared | None = None) -> None:
        """None: its noise is the config's (or the UKF's likelihood maximum, found by the caller)."""
        return None

    def bone_samples(self, scene: Scene, pre: Prepared | None = None) -> None:
        """None: it ties no bones."""
        return None

    def estimate(self, scene: Scene, pre: Prepared | None = None) -> TrackSet:
        gtsam = _gtsam()
        t0 = time.perf_counter()
        pre = pre or self.prepare(scene)
        x0, var0, _ = pre.frame_state()
        x0, own = _start_values(pre, x0)
        noise = self._process_noise(pre, x0, var0, scene.fps)
        results, tuned, checks = self._solve_all(gtsam, pre, (x0, own, noise.position_sd),
                                                 _keypoint_cameras(gtsam, pre), noise, scene.fps)
        centre, semi, c_sd, kpt, kpt_sd = _assembled(pre, x0, results)
        cfg = self.config
        boxes, kpts = pre.info.boxes if pre.use_box else None, pre.info.keypoints
        stats = {"iterations": sum(r.iterations for r in results),
                 "final_error": sum((r.final_error for r in results), 0.0),
                 "factors": sum(r.factors for r in results)}
        params: JsonDict = {**asdict(cfg),
                            "sigma_px": boxes.sigma_px if boxes is not None else None,
                            "sigma_px_core": boxes.sigma_px_core if boxes is not None else None,
                            "kpt_sigma_px": kpts.sigma_px if kpts is not None else None,
                            **tuned.as_dict(), "fps": scene.fps}
        details: JsonDict = {
            "process_noise_source": tuned.source,
            "process_noise_likelihood": noise.curves, "position_sd": noise.position_sd,
            "motion_loss": f"Huber k={cfg.huber_k}" if cfg.robust_motion else "Gaussian",
            "process_noise_moment_estimate": noise.tuned.as_dict(),
            "process_noise_discrepancy": checks,
            "preparation": pre.info.as_json(),
            "optimizer": "Gauss-Newton, line search (GTSAM), one graph per object", **stats}
        info = RunInfo(self.name, params, time.perf_counter() - t0, object_frames=len(pre.rows),
                       details=details)
        rows = pre.rows
        return TrackSet(frame=rows.frames[rows.row_t], track_id=rows.obj_ids[rows.row_o],
                        center_world=centre, semi_axes=semi, center_sd=c_sd, n_views=rows.n_views,
                        kpt_world=kpt, kpt_sd=kpt_sd, info=info)

    def _process_noise(self, pre: Prepared, x0: F64, var0: F64, fps: float) -> _Noise:
        """The moment estimates from the per-frame fits, or for boxes alone (``likelihood_noise``)
        the maximum of the model's marginal likelihood; values set in the config are kept."""
        cfg = self.config
        tuned = moment_process_noise(pre, x0, var0, fps, cfg.accel_sd, cfg.shape_sd,
                                     cfg.joint_accel_sd)
        by_likelihood = cfg.likelihood_noise and pre.use_box and not pre.use_kpt and (
            cfg.accel_sd is None or cfg.shape_sd is None)
        if not by_likelihood:
            return _Noise(tuned, 0.0, None, by_likelihood=False)
        ml, curves = noise_by_likelihood(pre, fps, UKFConfig(
            sigma_px=cfg.sigma_px, accel_sd=cfg.accel_sd, shape_sd=cfg.shape_sd,
            vertical_ratio=cfg.vertical_ratio, clip_tol_px=cfg.clip_tol_px))
        tuned = ProcessNoise(ml.chosen("accel_sd"), ml.chosen("shape_sd"), tuned.joint_accel_sd,
                             "maximum of the model's marginal likelihood (the Kalman filter's "
                             "prediction-error decomposition: the UKF's noise search)")
        return _Noise(tuned, float(ml.position_sd or 0.0), curves, by_likelihood=True)

    def _solve_all(self, gtsam: ModuleType, pre: Prepared, start_values: tuple[F64, np.ndarray, float],
                   kpt: tuple[F64 | None, list[gtsam.PinholeCameraCal3_S2]], noise: _Noise, fps: float
                   ) -> tuple[list[ObjectSolution], ProcessNoise, list[JsonDict]]:
        """Every object's graph at ``noise``; where the noise was not searched nor set, solved
        again with more process noise while the discrepancy principle asks for it (each retry
        starts where the previous solution ended). Returns the solutions, the process noise
        they used and the principle's checks."""
        cfg, rows, tuned = self.config, pre.rows, noise.tuned
        checks: list[JsonDict] = []
        results: list[ObjectSolution] = []
        for attempt in range(cfg.discrepancy_steps + 1):
            results = [self._solve(gtsam, pre, np.flatnonzero(rows.row_o == o), start_values, kpt,
                                   tuned, fps, results[o].values if attempt else None)
                       for o in range(len(rows.obj_ids))]
            if attempt == cfg.discrepancy_steps or (cfg.accel_sd and cfg.joint_accel_sd) \
                    or noise.by_likelihood:
                break
            new, chk = _discrepancy(results, tuned, cfg.discrepancy_step)
            checks.append({**tuned.as_dict(), **chk})
            if not chk["rescaled"]:
                break
            tuned = new
        return results, tuned, checks

    def _solve(self, gtsam: ModuleType, pre: Prepared, mine: np.ndarray,
               start_values: tuple[F64, np.ndarray, float],
               kpt: tuple[F64 | None, list[gtsam.PinholeCameraCal3_S2]],
               tuned: ProcessNoise, fps: float, start: gtsam.Values | F64 | None = None) -> ObjectSolution:
        """One object's graph: batched for box objects
        (:func:`gt3dkit.fusion.graph.chain.solve_boxes`), GTSAM's nonlinear factors for keypoints,
        and for a box object whose batched graph GTSAM finds singular (its elimination of the
        stacked rows can be stricter than of the separate
        factors, as for an object only one camera ever sees)."""
        if not pre.use_kpt:
            try:
                return solve_boxes(gtsam, self.config, pre, mine, start_values, tuned, fps, start)
            except EstimationError:
                start = None
        return self._solve_object(gtsam, pre, mine, start_values, kpt[0], kpt[1], tuned, fps,
                                  None if isinstance(start, np.ndarray) else start)

    def _solve_object(self, gtsam: ModuleType, pre: Prepared, mine: np.ndarray,
                      start_values: tuple[F64, np.ndarray, float], und: F64 | None,
                      gcams: list[gtsam.PinholeCameraCal3_S2], tuned: ProcessNoise, fps: float,
                      start: gtsam.Values | None = None) -> ObjectSolution:
        """One object's graph of GTSAM's nonlinear factors (:meth:`_object_graph`), solved from
        its start or from ``start`` (a previous solution)."""
        cfg = self.config
        x0 = start_values[0]
        layout, sym = pre.layout, gtsam.symbol
        J, n_rows = layout.n_joints, len(mine)
        og = self._object_graph(gtsam, pre, mine, start_values, und, gcams, tuned, fps)
        g = og.g
        try:
            result, iters, final = gtsam_gauss_newton(g, og.vals if start is None else start,
                                                      cfg.max_iterations, cfg.relative_error_tol)
            marg = gtsam.Marginals(g, result)
        except RuntimeError as e:  # gtsam's IndeterminateLinearSystemException and kin
            raise singular(e, pre, mine, tuned, fps) from None
        out = ObjectSolution(
            centre=x0[mine][:, layout.center].copy(), log_axes=x0[mine][:, layout.log_axes].copy(),
            c_sd=np.full((n_rows, 3), np.nan),
            kpt=x0[mine][:, layout.joints].reshape(n_rows, J, 3).copy(),
            kpt_sd=np.full((n_rows, J), np.nan),
            iterations=iters, final_error=final, factors=int(g.size()), values=result,
            meas_chi2=2.0 * sum(g.at(i).error(result) for i in og.meas), meas_dof=float(og.meas_dof))
        if pre.use_box:
            for k in range(n_rows):
                out.log_axes[k] = result.atVector(sym("s", k))
                out.centre[k] = result.atPoint3(sym("c", k * 32))
                out.c_sd[k] = axis_sd(marg.marginalCovariance(sym("c", k * 32)))
        for j in np.flatnonzero(og.seen_j):
            for k in range(n_rows):
                key = sym("p", k * 32 + int(j))
                out.kpt[k, j] = result.atPoint3(key)
                out.kpt_sd[k, j] = np.sqrt(np.linalg.eigvalsh(marg.marginalCovariance(key))[-1])
        return out

    def _object_graph(self, gtsam: ModuleType, pre: Prepared, mine: np.ndarray,
                      start_values: tuple[F64, np.ndarray, float], und: F64 | None,
                      gcams: list[gtsam.PinholeCameraCal3_S2], tuned: ProcessNoise, fps: float
                      ) -> _ObjectGraph:
        """The object of rows ``mine``: its variables at their start, weak priors, the motion
        factors and a robust factor per box and per keypoint (the module doc)."""
        cfg = self.config
        # (R, n) start; (R,) rows whose own views placed them (weak prior); the centre's own
        # random walk (m/sqrt(s), gt3dkit.fusion.motion)
        x0, own, position_sd = start_values
        rows, cams, layout = pre.rows, pre.cams, pre.layout
        use_box, use_kpt = pre.use_box, pre.use_kpt
        J = layout.n_joints
        g = gtsam.NonlinearFactorGraph()
        vals = gtsam.Values()
        sym = gtsam.symbol
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
        blocks += [("p", int(j), tuned.joint_accel_sd) for j in np.flatnonzero(seen_j)]
        blocks = [(ch, j, q * tau**1.5) for ch, j, q in blocks]  # m/s^2/sqrt(Hz) -> per step
        pos_step = walk_sd(position_sd, tau)  # m/sqrt(s) -> per step
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
                g.add(cv_factor(gtsam, [sym(ch, k * 32 + j), sym(vch, k * 32 + j),
                                        sym(ch, (k + 1) * 32 + j), sym(vch, (k + 1) * 32 + j)],
                                float(dt), W[k], motion_loss))
        meas, meas_dof = _measurement_factors(gtsam, g, pre, mine, und, gcams, huber, huber_box)
        return _ObjectGraph(g, vals, meas, meas_dof, seen_j)


def _measurement_factors(gtsam: ModuleType, g: gtsam.NonlinearFactorGraph, pre: Prepared,
                         mine: np.ndarray, und: F64 | None, gcams: list[gtsam.PinholeCameraCal3_S2],
                         huber: gtsam.noiseModel.mEstimator.Base,
                         huber_box: gtsam.noiseModel.mEstimator.Base) -> tuple[list[int], int]:
    """A robust factor per usable box (its edges) and per kept keypoint of the rows ``mine``, added
    to ``g``; the indices of the factors added and their measurement entries."""
    rows, cams, sigma_box, sym = pre.rows, pre.cams, pre.sigma_box, gtsam.symbol
    C = len(cams.K)
    meas: list[int] = []
    meas_dof = 0
    if pre.use_box:
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
                                     box_error(bc, z, m, C)))
    if pre.use_kpt and und is not None:
        for k, r in enumerate(mine):
            cc, jj = np.nonzero(np.isfinite(und[r][..., 0]) & pre.kpt_keep[r])
            for c, j in zip(cc, jj, strict=True):
                noise_k = gtsam.noiseModel.Robust.Create(huber, gtsam.noiseModel.Isotropic.Sigma(
                    2, float(np.sqrt(pre.kpt_var[r, c, j]))))
                meas.append(int(g.size()))
                meas_dof += 2
                g.add(gtsam.TriangulationFactorCal3_S2(gcams[c], und[r, c, j], noise_k,
                                                       sym("p", k * 32 + int(j))))
    return meas, meas_dof


def _keypoint_cameras(gtsam: ModuleType, pre: Prepared
                      ) -> tuple[F64 | None, list[gtsam.PinholeCameraCal3_S2]]:
    """The undistorted pixels of every keypoint ``(R, C, J, 2)`` (None without keypoints: GTSAM's
    pinhole with ``Cal3_S2`` has no distortion) and the cameras as GTSAM's pinholes."""
    rows, cams = pre.rows, pre.cams
    und = None
    if pre.use_kpt:
        und = apply_K(normalized_points(rows.kpt_z, cams.K[:, None], cams.dist[:, None]),
                      cams.K[:, None])  # (R, C, J, 2)
    cal = [gtsam.Cal3_S2(k[0, 0], k[1, 1], k[0, 1], k[0, 2], k[1, 2]) for k in cams.K]
    gcams = [gtsam.PinholeCameraCal3_S2(
        gtsam.Pose3(gtsam.Rot3(r.T), -r.T @ t), cal[c])
        for c, (r, t) in enumerate(zip(cams.R, cams.t, strict=True))]
    return und, gcams


def _assembled(pre: Prepared, x0: F64, results: list[ObjectSolution]
               ) -> tuple[F64, F64, F64, F64, F64]:
    """Every row's centre, semi-axes and centre sd ``(R, 3)``, joints ``(R, J, 3)`` and their sd
    ``(R, J)`` from the objects' solutions (joints never placed by two views, or whose every
    point was rejected: NaN; without boxes the ellipsoid around the joints)."""
    rows, layout, use_kpt = pre.rows, pre.layout, pre.use_kpt
    R, J = len(rows), layout.n_joints
    centre = x0[:, layout.center].copy()
    log_axes = x0[:, layout.log_axes].copy()
    c_sd = np.full((R, 3), np.nan)
    kpt = x0[:, layout.joints].reshape(R, J if use_kpt else 0, 3).copy()
    kpt_sd = np.full(kpt.shape[:2], np.nan)
    for o, res in enumerate(results):
        mine = np.flatnonzero(rows.row_o == o)  # sorted by frame
        centre[mine], log_axes[mine], c_sd[mine] = res.centre, res.log_axes, res.c_sd
        if use_kpt:
            kpt[mine], kpt_sd[mine] = res.kpt, res.kpt_sd
    semi = np.exp(log_axes)
    if use_kpt:
        # never placed by two views, or every point of it rejected: no estimate (x0 is only a guess)
        kpt0 = pre.kpt0 if pre.kpt0 is not None else np.full(kpt.shape, np.nan)
        nv = never_determined(rows, kpt0) | ~np.isfinite(kpt_sd)
        kpt[nv], kpt_sd[nv] = np.nan, np.nan
        if not pre.use_box:
            centre, semi, c_sd = ellipsoid_around(kpt, kpt_sd, pre.cams.world_from_body)
    return centre, semi, c_sd, kpt, kpt_sd


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
