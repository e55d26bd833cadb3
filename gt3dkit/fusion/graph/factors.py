"""The GTSAM smoother's factors and its Gauss-Newton: the constant-velocity factor whitened by
the motion model's ``Q`` (:func:`cv_whitening`), a box's factor, Huber's loss, and the
Gauss-Newton loops (the batched one of the box chains, GTSAM's own for the rest)."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from gt3dkit.fusion.motion import MotionModel, StateLayout
from gt3dkit.geom.boxkernel import box_jacobian, kernel
from gt3dkit.geom.boxrig import EVERY_CAMERA, BoxCameras, box_rig
from gt3dkit.types import F64

if TYPE_CHECKING:
    import gtsam

V = TypeVar("V")  # the values a Gauss-Newton loop moves (GTSAM's Values, or an array)
D = TypeVar("D")  # a step of them


def huber_loss(norm: F64, k: float) -> F64:
    """GTSAM's Huber loss of whitened norms: ``r^2 / 2`` within ``k``, ``k |r| - k^2 / 2`` beyond."""
    return np.where(norm <= k, 0.5 * norm**2, k * norm - 0.5 * k * k)


def huber_sqrt_weight(norm: F64, k: float) -> F64:
    """The square root of GTSAM's Huber weight (1 within ``k``, ``k / |r|`` beyond), by which its
    ``Robust`` noise model scales a factor's whitened Jacobian and residual."""
    return np.sqrt(np.where(norm <= k, 1.0, k / np.maximum(norm, 1e-300)))


def gauss_newton(error: Callable[[V], float], step: Callable[[V], D],
                 retract: Callable[[V, D, float], V], values: V, max_iterations: int,
                 rel_tol: float) -> tuple[V, int, float]:
    """Gauss-Newton with a backtracking line search (halve the step until the error falls, at
    most 10 times); stops when the error falls by less than ``rel_tol`` of itself. ``error``
    the graph's error at values, ``step`` the linearised graph's solution there, ``retract``
    values moved by a step scaled by a factor: GTSAM's graph and values
    (:func:`gtsam_gauss_newton`) or a box chain's arrays (:func:`_solve_boxes`).

    Driven from Python: with our Python factors in the graph, GTSAM's own
    ``LevenbergMarquardtOptimizer.optimize`` took 10x longer per iteration than these calls
    (1.4 s against 0.13 s on a 2 280-variable skeleton graph), and the start (the per-frame fits)
    is close enough that no damping is needed. Returns the values, the iterations and the final
    error."""
    err = error(values)
    iters = 0
    while iters < max_iterations:
        iters += 1
        delta = step(values)
        scale, new, new_err = 1.0, None, err
        for _ in range(10):
            cand = retract(values, delta, scale)
            new_err = error(cand)
            if new_err <= err:
                new = cand
                break
            scale *= 0.5
        if new is None:  # no step lowers the error: a minimum
            break
        done = err - new_err <= rel_tol * max(err, 1e-300)
        values, err = new, new_err
        if done:
            break
    return values, iters, float(err)


def gtsam_gauss_newton(g: gtsam.NonlinearFactorGraph, values: gtsam.Values, max_iterations: int,
                       rel_tol: float) -> tuple[gtsam.Values, int, float]:
    """:func:`gauss_newton` on a GTSAM nonlinear graph (its linearisation, elimination and
    retraction)."""
    return gauss_newton(g.error, lambda v: g.linearize(v).optimize(),
                         lambda v, d, k: v.retract(d if k == 1.0 else d.scale(k)),
                         values, max_iterations, rel_tol)


def cv_whitening(dts: F64, accel_sd: float, up: F64 | None, vertical_ratio: float,
                 position_sd: float = 0.0) -> F64:
    """``W (B, 6, 6)`` whitening of the constant-velocity residual ``[x_{k+1} - x_k - dt v_k ;
    v_{k+1} - v_k]`` of steps ``dts (B,)`` (``W Q W^T = I``, ``Q`` the exact discrete-time
    process noise of :class:`gt3dkit.fusion.motion.StateLayout`), one per distinct step."""
    steps, inverse = np.unique(np.asarray(dts, dtype=np.float64), return_inverse=True)
    model = MotionModel(accel_sd, 1.0, position_sd=position_sd, up=up,
                        vertical_ratio=vertical_ratio if up is not None else 1.0)
    _, Q = model.transition(StateLayout(0), steps)
    W = np.linalg.inv(np.linalg.cholesky(Q[:, :6, :6]))
    return W[inverse.reshape(-1)]


def cv_factor(lib: ModuleType, keys: list[int], dt: float, W: F64,
              loss: gtsam.noiseModel.mEstimator.Base | None = None) -> gtsam.CustomFactor:
    """Constant velocity between ``(x_k, v_k)`` and ``(x_{k+1}, v_{k+1})``: the residual
    ``[x_{k+1} - x_k - dt v_k ; v_{k+1} - v_k]`` whitened by ``W (6, 6)`` (:func:`cv_whitening`),
    unit noise model. Linear, so its Jacobians are constants."""
    I3, Z3 = np.eye(3), np.zeros((3, 3))
    blocks = [W @ np.vstack([-I3, Z3]), W @ np.vstack([-dt * I3, -I3]),
              W @ np.vstack([I3, Z3]), W @ np.vstack([Z3, I3])]

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[F64] | None) -> F64:
        ks = this.keys()
        x0, v0, x1, v1 = (v.atPoint3(ks[i]) for i in range(4))
        e = W @ np.concatenate([x1 - x0 - dt * v0, v1 - v0])
        if H is not None:
            for i in range(4):
                H[i] = blocks[i]
        return e

    unit = lib.noiseModel.Unit.Create(6)
    model = unit if loss is None else lib.noiseModel.Robust.Create(loss, unit)
    return lib.CustomFactor(model, keys, error)


def box_error(bc: BoxCameras, z: F64, m: np.ndarray, C: int
              ) -> Callable[[gtsam.CustomFactor, gtsam.Values, list[F64] | None], F64]:
    """Error function of a box factor on (centre Point3, log semi-axes Vector3); ``bc`` the
    cameras as :class:`gt3dkit.geom.boxrig.BoxCameras` (the compiled box is called directly:
    GTSAM calls this ~10 000 times per 1 000 object-frames, and the general entry point's
    argument checks were 2/3 of its time). The Jacobian is the box's analytic derivative
    (:func:`gt3dkit.geom.boxkernel.box_jacobian`, held to central differences by the tests)."""
    rig = box_rig(bc, 2)
    box, grad = np.empty((C, 4)), np.empty((C, 4, 6))
    margin = np.empty((1, C))

    def error(this: gtsam.CustomFactor, v: gtsam.Values, H: list[F64] | None) -> F64:
        ks = this.keys()
        p = np.concatenate([v.atPoint3(ks[0]), v.atVector(ks[1])])
        if H is None:
            kernel(p[None, :3].copy(), np.exp(p[None, 3:]), bc, 2, EVERY_CAMERA, box[None], margin)
        else:
            box_jacobian(p, rig, box, grad)
        e = box.reshape(-1)[m] - z
        bad = ~np.isfinite(e)
        if bad.any():
            e = np.where(bad, 1e6, e)
        if H is not None:
            Jm = grad.reshape(C * 4, 6)[m]
            Jm = np.where(np.isfinite(Jm), Jm, 0.0)
            H[0] = Jm[:, :3]
            H[1] = Jm[:, 3:]
        return e

    return error
