"""One object's solution in the GTSAM smoother (:mod:`gt3dkit.fusion.graph.smoother`), and the
graph of a box object as arrays (:func:`solve_boxes`): every factor's whitened residual and
Jacobian for all its rows at once, one ``JacobianFactor`` per row for GTSAM to eliminate."""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Literal, overload

import numpy as np

from gt3dkit.errors import EstimationError
from gt3dkit.fusion.graph.factors import cv_whitening, gauss_newton, huber_loss, huber_sqrt_weight
from gt3dkit.fusion.motion import walk_sd
from gt3dkit.fusion.preparation.prepare import Prepared, axis_sd
from gt3dkit.fusion.ukf.noise import ProcessNoise
from gt3dkit.geom.boxkernel import box_jacobian, kernel
from gt3dkit.geom.boxrig import EVERY_CAMERA, BoxCameras, box_rig
from gt3dkit.types import F64

if TYPE_CHECKING:
    import gtsam


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


@dataclass
class ObjectSolution:
    """One object's solved graph: per row its centre, log semi-axes and centre sd ``(n, 3)``, its
    joints ``(n, J, 3)`` and their largest sd ``(n, J)`` (NaN: not in the graph); the solver's
    iterations, final error and factors; the solution itself, where a retry starts (GTSAM's
    ``Values``, or a box chain's ``(n, 9)`` array); the measurements' whitened squared residuals
    (Huber-robust, error = chi2 / 2) and their count, for :func:`_discrepancy`."""

    centre: F64
    log_axes: F64
    c_sd: F64
    kpt: F64
    kpt_sd: F64
    iterations: int
    final_error: float
    factors: int
    values: gtsam.Values | F64
    meas_chi2: float
    meas_dof: float



BOX_DIM = 9  # a box object's variable per row: centre (3), velocity (3, m/step), log axes (3)


class _BoxChain:
    """The graph of one box object as arrays (see :func:`solve_boxes`): every factor's whitened
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
        # time in units of the typical step (see gt3dkit.fusion.graph.smoother.GTSAMSmoother._solve_object)
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

    @overload
    def box_residuals(self, z: F64, jacobian: Literal[True]) -> tuple[F64, F64]: ...

    @overload
    def box_residuals(self, z: F64, jacobian: Literal[False]) -> tuple[F64, None]: ...

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
        e_box, _ = self.box_residuals(z, jacobian=False)
        e_cv, e_s = self.motion_residuals(z)
        box = float(huber_loss(np.linalg.norm(e_box, axis=1), self.k_box).sum())
        prior = 0.5 * float((((z - self.prior_at) * self.prior_w) ** 2).sum())
        motion = float(huber_loss(np.linalg.norm(e_cv, axis=1), self.k_motion).sum())
        return box + prior + motion + 0.5 * float((e_s**2).sum()), box

    def linearized(self, gtsam: ModuleType, z: F64) -> gtsam.GaussianFactorGraph:
        """The graph linearised at ``z``: one ``JacobianFactor`` per row on (row, next row)
        stacking its box edges, its priors, and its steps to the next row (unit noise: rows
        whitened and robustly weighted here, ``b = -`` the residual)."""
        n, m = self.n, 4 * self.C
        e_box, J_box = self.box_residuals(z, jacobian=True)
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


def solve_boxes(gtsam: ModuleType, cfg: GTSAMConfig, pre: Prepared, mine: np.ndarray,
                 start_values: tuple[F64, np.ndarray, float], tuned: ProcessNoise, fps: float,
                 start: gtsam.Values | F64 | None = None) -> ObjectSolution:
    """One box object's graph (the factors of
    :meth:`gt3dkit.fusion.graph.smoother.GTSAMSmoother._solve_object`: a box factor per row,
    constant velocity and a log-axes random walk between rows, the weak priors; the same Huber
    losses) solved by the same Gauss-Newton with a line search, linearised in
    batches (:class:`_BoxChain`): GTSAM eliminates each linear step and gives the marginal
    covariances. A ``CustomFactor`` per box and per step called Python ~25 times per
    object-frame; this is 3-4x faster on long scenes and gives the same solution."""
    chain = _BoxChain(cfg, pre, mine, start_values, tuned, fps)
    z = start.copy() if isinstance(start, np.ndarray) else chain.start.copy()
    try:
        z, iters, err = gauss_newton(
            lambda v: chain.errors(v)[0],
            lambda v: chain.linearized(gtsam, v).optimize().vector().reshape(chain.n, BOX_DIM),
            lambda v, d, k: v + k * d, z, cfg.max_iterations, cfg.relative_error_tol)
        lin = chain.linearized(gtsam, z)
        marg = gtsam.Marginals(lin, lin.optimize())
    except RuntimeError as e:  # gtsam's IndeterminateLinearSystemException and kin
        raise singular(e, pre, mine, tuned, fps) from None
    cov = np.array([marg.marginalCovariance(k)[:3, :3] for k in range(chain.n)])
    J = pre.layout.n_joints
    return ObjectSolution(centre=z[:, :3].copy(), log_axes=z[:, 6:].copy(), c_sd=axis_sd(cov),
                          kpt=np.full((chain.n, J, 3), np.nan), kpt_sd=np.full((chain.n, J), np.nan),
                          iterations=iters, final_error=err, factors=chain.n, values=z,
                          # whitened squared residuals of the box edges (error = chi2 / 2, Huber-robust)
                          meas_chi2=2.0 * chain.errors(z)[1], meas_dof=float(chain.keep.sum()))


def singular(e: RuntimeError, pre: Prepared, mine: np.ndarray, tuned: ProcessNoise,
              fps: float) -> EstimationError:
    """GTSAM's IndeterminateLinearSystemException (and kin) on the graph of the object of rows
    ``mine``, as the one-line error the user reads."""
    first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    oid = int(pre.rows.obj_ids[pre.rows.row_o[mine[0]]])
    return EstimationError("gtsam", f"the factor graph of object {oid} is singular ({first}); "
                           f"process noise {tuned.accel_sd:.3g} m/s^2/sqrt(Hz) at {fps:g} fps: "
                           "check the frame rate, or use --estimator ukf")
