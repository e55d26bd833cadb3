r"""The keypoint filter as compiled chains: every (person, joint) its own filter of six entries.

A joint's projections depend on its own three coordinates, the motion model moves it by its own
velocity and nothing in the initial covariance ties it to another joint or to the ellipsoid: the
covariance of a person's stacked ``9 + 6J`` state stays block-diagonal, and its filter is one
small filter per joint (its position and velocity, 6 entries) and one for the ellipsoid, exactly
(but for when the iterated update stops: each part on its own, within the update's convergence
tolerance); for 19 joints, 123-entry matrices (one inverse is 1.9 Mflop) become 20 small ones.
:func:`run_joints` runs the ellipsoid's by the boxes' compiled chains
(:func:`gt3dkit.fusion.ukf.boxupdate.run_boxes`; with
keypoints alone nothing measures it and it stays the rows' initial state) and every joint's as a
compiled chain along the person's rows, the joints of all persons dealt over
:func:`gt3dkit.threads.compiled_threads` threads. The steps are the package's own: the prediction
and RTS step of :mod:`gt3dkit.fusion.ukf.kalman`, the iterated robust update of
:mod:`gt3dkit.fusion.ukf.update`; what is new here is the joint's sigma-point regression
(:func:`point_regression`, the projection with distortion of :mod:`gt3dkit.geom.boxkernel`), the
joint's steps in the one filter loop (:class:`JointChain`, :mod:`gt3dkit.fusion.ukf.filterloop`), its
fading and linearisation point (:func:`_fade`, :func:`_linearisation`) and the bones'
information (:func:`add_info`). The filter over the frame grid in ``tests/oracles_frames.py``
(split or whole) is the reference the tests hold it to: the same result within the iterated
update's convergence tolerance (a part stops iterating on its own entries' spread, not on the
stacked state's).
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import numba
import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.motion import SPACE, StateLayout, joint_step
from gt3dkit.fusion.preparation.robust import RobustConfig, chi2_isf
from gt3dkit.fusion.ukf.blockcov import BlockCov
from gt3dkit.fusion.ukf.boxupdate import object_chains, regress, run_boxes, sigma_points
from gt3dkit.fusion.ukf.config import NoiseRows, UKFConfig
from gt3dkit.fusion.ukf.filterloop import Chains, backward_chain, forward_chain, register
from gt3dkit.fusion.ukf.filterrun import FilterRun
from gt3dkit.fusion.ukf.initial import Init, InitialCov
from gt3dkit.fusion.ukf.kalman import fade_factor, predict_row, rts_row
from gt3dkit.fusion.ukf.rowsmodel import RowsModel
from gt3dkit.fusion.ukf.sigma import Block, Robust, SigmaWeights, block_columns
from gt3dkit.fusion.ukf.update import (
    Columns,
    Current,
    Measured,
    Posterior,
    Prior,
    Regression,
    Scores,
    pass_row,
    prior_factor,
    statistics,
)
from gt3dkit.geom.boxkernel import world_pixel
from gt3dkit.geom.boxrig import BoxRig
from gt3dkit.threads import run_split
from gt3dkit.types import F64, I64

#: Entries of a joint's filter: its position, then its velocity (m, m/s).
N = 2 * SPACE


class PointSigma(NamedTuple):
    """The sigma-point rule of a joint's position (3 entries), or of its position and velocity (6:
    views taken off their rows' frames, :func:`point_regression`): weights ``Wm, Wc`` (without the
    centre point where the rule gives it no weight) and the points' ``scale``."""

    Wm: F64
    Wc: F64
    scale: float


class JointModel(NamedTuple):
    """What every joint's update shares: the sigma rule, the cameras (:class:`BoxRig` rows), the
    ``2 C`` columns of a joint's views (:class:`gt3dkit.fusion.ukf.update.Columns`), the iterated
    update's passes at most, whether it reweights, whether predictions fade and at which
    chi-square(3) ``limit``."""

    sigma: PointSigma
    rig: BoxRig
    cols: Columns
    iterations: int
    robust: bool
    fade: bool
    limit: float


class JointData(NamedTuple):
    """Per row and joint: the views ``z (R, J, C, 2)`` px, which are present ``mask``, their
    variances ``var`` and start weights ``w0`` (the same shape); the per-frame joint ``x_frame (R,
    J, 3)`` with its variances ``var_frame (R, J, 3)`` (inf: unreliable) and covariance ``cov_frame
    (R, J, 3, 3)`` (inf: may not fade a prediction); the bones' information ``info (R, J, 3, 3)``,
    ``eta (R, J, 3)`` (``(0, ...)``: none); each row's joint acceleration noise ``q (R,)``; when
    each view was taken ``seen_s (R, C)``, seconds after its row's time (``(0, C)``: every view
    at its row's time)."""

    z: F64
    mask: np.ndarray
    var: F64
    w0: F64
    x_frame: F64
    var_frame: F64
    cov_frame: F64
    info: F64
    eta: F64
    q: F64
    seen_s: F64


class JointStart(NamedTuple):
    """Each chain's first row ``row (K,)``, its joint ``joint (K,)`` and its initial state ``x0 (K,
    6)`` and covariance ``P0 (K, 6, 6)``."""

    row: I64
    joint: I64
    x0: F64
    P0: F64


class JointOut(NamedTuple):
    """Per row and joint: the filtered (then smoothed) ``x (R, J, 6)``, ``P (R, J, 6, 6)``, the
    prediction ``x_p, P_p`` (the same shapes), whether it was faded ``faded (R, J)``, the update's
    ``stats (R, J, 5)`` (NIS, dof, log-likelihood, passes, repairs) and per view entry the final
    ``weights``, squared leave-one-out ``score2`` and residual ``resid`` ``(R, J, C, 2)``."""

    x: F64
    P: F64
    x_p: F64
    P_p: F64
    faded: np.ndarray
    stats: F64
    weights: F64
    score2: F64
    resid: F64


@numba.njit(cache=True, nogil=True)
def point_regression(xj: F64, Pj: F64, meas: Measured, sig: PointSigma, rig: BoxRig, seen_s: F64,
                     lin: Regression) -> int:
    r"""Statistical linear regression of a joint's views (``meas``: ``(2 C,)``, camera by camera
    ``u, v``) on the sigma points of ``N(xj (6,), Pj (6, 6))``, into ``lin``: as the reference
    ``block_regression`` (``tests/oracles_frames.py``) of the joint's block (a view is used where
    present and every sigma point is in front of its camera). The points span the position's
    marginal, or, where ``lin`` has six columns, the position and velocity: camera ``c``'s view
    was taken ``seen_s[c]`` seconds after the row's time and sees the joint where the motion model
    moves it by then,

    .. math::
        z_c = h_c(p + \delta_c v) + e,

    the constant-velocity prediction to the view's own time (the process noise over
    ``|\delta_c|`` of at most half a frame, ``q^2 \delta^3 / 3`` per axis, is left out: a
    thousandth of a pixel at 30 fps). Returns 1 if the marginal's factor needed a repair."""
    C = rig.cam.shape[0]
    m = 2 * C
    S = sig.Wm.shape[0]
    d = lin.At.shape[1]
    Pb = np.empty((d, d))
    X = np.empty((S, d))
    Z = np.empty((S, m))
    dims = np.arange(d)
    repaired = sigma_points(xj, Pj, dims, sig.scale, Pb, X)
    for c in range(C):
        if not (meas.mask[2 * c] or meas.mask[2 * c + 1]):
            continue
        q = rig.cam[c]
        dt = seen_s[c] if d > SPACE else 0.0
        for s in range(S):
            if dt != 0.0:  # a joint's state: its position, then its velocity (SPACE entries each)
                v = SPACE
                Z[s, 2 * c], Z[s, 2 * c + 1] = world_pixel(X[s, 0] + dt * X[s, v], X[s, 1] + dt * X[s, v + 1],
                                                           X[s, 2] + dt * X[s, v + 2], q)
            else:
                Z[s, 2 * c], Z[s, 2 * c + 1] = world_pixel(X[s, 0], X[s, 1], X[s, 2], q)
    regress(X, Z, xj, dims, sig.Wm, sig.Wc, Pb, meas, 0, lin)
    return repaired


@numba.njit(cache=True, nogil=True)
def add_info(x: F64, P: F64, lam: F64, eta: F64) -> None:
    r"""A joint's state ``x (6,)``, ``P (6, 6)`` with the information ``lam (3, 3)``, ``eta (3,)`` on
    its position added in place (the reference ``add_joint_info`` (``tests/oracles_frames.py``) of one joint):
    ``P^+ = P - U M U^T``, ``M = \Lambda (I + C \Lambda)^{-1}``, ``x^+ = x + P^+ E^T (\eta -
    \Lambda E x)``."""
    A = np.empty((SPACE, SPACE))  # I + lam C
    for i in range(SPACE):
        for j in range(SPACE):
            s = 1.0 if i == j else 0.0
            for k in range(SPACE):
                s += lam[i, k] * P[k, j]
            A[i, j] = s
    Mt = np.empty((SPACE, SPACE))
    _solve3(A, lam, Mt)  # M^T = (I + lam C)^-1 lam
    M = np.empty((SPACE, SPACE))
    for i in range(SPACE):
        for j in range(SPACE):
            M[i, j] = 0.5 * (Mt[j, i] + Mt[i, j])
    UM = np.empty((N, SPACE))
    for i in range(N):
        for j in range(SPACE):
            s = 0.0
            for k in range(SPACE):
                s += P[i, k] * M[k, j]
            UM[i, j] = s
    Pn = np.empty((N, N))
    for i in range(N):
        for j in range(N):
            s = 0.0
            for k in range(SPACE):
                s += UM[i, k] * P[j, k]
            Pn[i, j] = P[i, j] - s
    for i in range(N):
        for j in range(i + 1):
            v = 0.5 * (Pn[i, j] + Pn[j, i])
            P[i, j] = v
            P[j, i] = v
    innov = np.empty(SPACE)
    for a in range(SPACE):
        s = eta[a]
        for b in range(SPACE):
            s -= lam[a, b] * x[b]
        innov[a] = s
    for i in range(N):
        s = 0.0
        for a in range(SPACE):
            s += P[i, a] * innov[a]
        x[i] += s


@numba.njit(cache=True, nogil=True)
def _solve3(A: F64, B: F64, X: F64) -> None:
    """``X = A^{-1} B`` for a general ``A (3, 3)`` (its adjugate); ``B, X (3, 3)``."""
    c00 = A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1]
    c01 = A[1, 2] * A[2, 0] - A[1, 0] * A[2, 2]
    c02 = A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0]
    det = A[0, 0] * c00 + A[0, 1] * c01 + A[0, 2] * c02
    inv = np.empty((3, 3))
    inv[0, 0], inv[1, 0], inv[2, 0] = c00 / det, c01 / det, c02 / det
    inv[0, 1] = (A[0, 2] * A[2, 1] - A[0, 1] * A[2, 2]) / det
    inv[1, 1] = (A[0, 0] * A[2, 2] - A[0, 2] * A[2, 0]) / det
    inv[2, 1] = (A[0, 1] * A[2, 0] - A[0, 0] * A[2, 1]) / det
    inv[0, 2] = (A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]) / det
    inv[1, 2] = (A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]) / det
    inv[2, 2] = (A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]) / det
    for i in range(SPACE):
        for j in range(SPACE):
            X[i, j] = inv[i, 0] * B[0, j] + inv[i, 1] * B[1, j] + inv[i, 2] * B[2, j]


@numba.njit(cache=True, nogil=True)
def update_joint(r: int, j: int, xl: F64, Pl: F64, data: JointData, jm: JointModel, out: JointOut) -> None:
    """The iterated, robust update (:func:`gt3dkit.fusion.ukf.update.pass_row`) of joint ``j`` of row
    ``r`` from its prediction ``out.x_p, out.P_p``, the first pass linearised at ``xl, Pl``; then
    the bones' information; into ``out``."""
    C = data.z.shape[2]
    m = 2 * C
    d = jm.cols.dims.shape[1]
    seen = data.seen_s[r] if data.seen_s.shape[0] else np.zeros(C)
    LP, Pinv = np.empty((N, N)), np.empty((N, N))
    prior_factor(out.P_p[r, j], LP, Pinv)
    prior = Prior(out.x_p[r, j], Pinv, LP)
    meas = Measured(data.z[r, j].reshape(m), data.mask[r, j].reshape(m), data.var[r, j].reshape(m))
    cur = Current(xl.copy(), Pl.copy(), data.w0[r, j].reshape(m).copy(), np.empty(m))
    lin = Regression(np.zeros(m, np.bool_), np.zeros((m, d)), np.zeros(m), np.ones(m))
    post = Posterior(np.empty(N), np.empty((N, N)), np.empty((N, N)), np.empty((N, N)), np.empty(N),
                     np.zeros(m), np.zeros(m))
    scores = Scores(np.zeros(m), np.zeros(m))
    repaired = 0
    it = 0
    for it in range(jm.iterations):
        repaired += point_regression(cur.xj, cur.Pj, meas, jm.sigma, jm.rig, seen, lin)
        done, rep = pass_row(it, it == jm.iterations - 1, jm.robust, prior, lin, jm.cols, cur, post, scores)
        repaired += rep
        if done:
            break
    quad, dof, ll = statistics(prior, lin, cur.wt, post)
    st = out.stats[r, j]
    st[0], st[1], st[2], st[3], st[4] = quad, dof, ll, it + 1, repaired
    w, s2, rs = out.weights[r, j].reshape(m), out.score2[r, j].reshape(m), out.resid[r, j].reshape(m)
    for k in range(m):
        w[k] = cur.wt[k] if meas.mask[k] else 1.0
        s2[k] = scores.score2[k]
        rs[k] = scores.resid[k]
    out.x[r, j] = post.x
    out.P[r, j] = post.P
    if data.info.shape[0]:
        lam = data.info[r, j]
        if np.any(lam != 0.0):
            add_info(out.x[r, j], out.P[r, j], lam, data.eta[r, j])


class JointChain(NamedTuple):
    """The joint kind's bundle for :mod:`gt3dkit.fusion.ukf.filterloop` (the element ``e`` of a step:
    the chain's index into ``start``): the chains, the chains' starts, the joints' data and
    model, the outputs, and work arrays ``F, Q (6, 6)`` and the linearisation point ``xl (6,),
    Pl (6, 6)``."""

    chains: Chains
    start: JointStart
    data: JointData
    jm: JointModel
    out: JointOut
    F: F64
    Q: F64
    xl: F64
    Pl: F64


@numba.njit(cache=True, nogil=True)
def _start(ctx: JointChain, e: int, r: int) -> None:
    j = ctx.start.joint[e]
    ctx.out.x_p[r, j] = ctx.start.x0[e]
    ctx.out.P_p[r, j] = ctx.start.P0[e]


@numba.njit(cache=True, nogil=True)
def _predict(ctx: JointChain, e: int, r: int, prev: int, f: float) -> None:
    """Joint ``j``'s prediction of row ``r`` from row ``prev``'s filtered state, its process noise
    scaled by ``f`` (``f Q f``)."""
    j, out, F, Q = ctx.start.joint[e], ctx.out, ctx.F, ctx.Q
    joint_step(ctx.chains.t_s[r] - ctx.chains.t_s[prev], ctx.data.q[r], F, Q)
    if f != 1.0:
        for a in range(N):
            for b in range(N):
                Q[a, b] = f * Q[a, b] * f
    predict_row(out.x[prev, j], out.P[prev, j], F, Q, out.x_p[r, j], out.P_p[r, j])


@numba.njit(cache=True, nogil=True)
def _fades(ctx: JointChain, e: int, r: int) -> bool:
    return ctx.jm.fade


@numba.njit(cache=True, nogil=True)
def _fade(ctx: JointChain, e: int, r: int) -> float:
    """:func:`gt3dkit.fusion.ukf.kalman.fade_factor` of the joint's prediction in row ``r`` against
    the frame's own joint."""
    j, data, out = ctx.start.joint[e], ctx.data, ctx.out
    d = np.empty(SPACE)
    S = np.empty((SPACE, SPACE))
    for a in range(SPACE):
        d[a] = data.x_frame[r, j, a] - out.x_p[r, j, a]
        for b in range(SPACE):
            S[a, b] = out.P_p[r, j, a, b] + data.cov_frame[r, j, a, b]
    return fade_factor(d, S, ctx.jm.limit)


@numba.njit(cache=True, nogil=True)
def _faded(ctx: JointChain, e: int, r: int, f: float) -> None:
    j = ctx.start.joint[e]
    if f != 1.0:
        P = ctx.out.P_p[r, j]
        for a in range(N):
            for b in range(N):
                P[a, b] = f * P[a, b] * f
    ctx.out.faded[r, j] = True


@numba.njit(cache=True, nogil=True)
def _measured(ctx: JointChain, e: int, r: int) -> bool:
    j, data = ctx.start.joint[e], ctx.data
    for c in range(data.mask.shape[2]):
        if data.mask[r, j, c, 0] or data.mask[r, j, c, 1]:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _keep(ctx: JointChain, e: int, r: int) -> None:
    j = ctx.start.joint[e]
    ctx.out.x[r, j] = ctx.out.x_p[r, j]
    ctx.out.P[r, j] = ctx.out.P_p[r, j]


@numba.njit(cache=True, nogil=True)
def _update(ctx: JointChain, e: int, r: int) -> None:
    j = ctx.start.joint[e]
    _linearisation(r, j, ctx.data, ctx.out, ctx.xl, ctx.Pl)
    update_joint(r, j, ctx.xl, ctx.Pl, ctx.data, ctx.jm, ctx.out)


@numba.njit(cache=True, nogil=True)
def _smooth(ctx: JointChain, e: int, r: int, nxt: int) -> None:
    j, out, F, Q = ctx.start.joint[e], ctx.out, ctx.F, ctx.Q
    joint_step(ctx.chains.t_s[nxt] - ctx.chains.t_s[r], ctx.data.q[r], F, Q)
    rts_row(out.x[r, j], out.P[r, j], out.x_p[nxt, j], out.P_p[nxt, j], out.x[nxt, j], out.P[nxt, j],
            F, out.x[r, j], out.P[r, j])


register(JointChain, start=_start, predict=_predict, fades=_fades, fade=_fade, faded=_faded,
         measured=_measured, keep=_keep, update=_update, smooth=_smooth)


@numba.njit(cache=True, nogil=True)
def _linearisation(r: int, j: int, data: JointData, out: JointOut, xl: F64, Pl: F64) -> None:
    """Where joint ``j`` of row ``r`` linearises first: its prediction, unless the prediction's
    position spread (trace) exceeds
    the frame's own joint's; then that joint, with its variances, decorrelated from the velocity."""
    xl[:] = out.x_p[r, j]
    Pl[:, :] = out.P_p[r, j]
    vj = Pl[0, 0] + Pl[1, 1] + Pl[2, 2]
    vf = data.var_frame[r, j, 0] + data.var_frame[r, j, 1] + data.var_frame[r, j, 2]
    if not (np.isfinite(vf) and vj > vf):
        return
    for a in range(SPACE):
        xl[a] = data.x_frame[r, j, a]
        for b in range(N):
            Pl[a, b] = 0.0
            Pl[b, a] = 0.0
    for a in range(SPACE):
        Pl[a, a] = data.var_frame[r, j, a]


def joint_chain(start: JointStart, chains: Chains, data: JointData, jm: JointModel, out: JointOut
                ) -> JointChain:
    """The bundle of a run, with its own work arrays (one per thread)."""
    return JointChain(chains, start, data, jm, out, np.empty((N, N)), np.empty((N, N)), np.empty(N),
                      np.empty((N, N)))


@numba.njit(cache=True, nogil=True)
def forward(chain: I64, ctx: JointChain) -> None:
    """Forward filter (:func:`gt3dkit.fusion.ukf.filterloop.forward_chain`) of the chains ``chain``
    (indices into ``ctx.start``): each joint along its person's rows."""
    for k in chain:
        forward_chain(ctx, k, ctx.start.row[k])


@numba.njit(cache=True, nogil=True)
def backward(chain: I64, last: I64, ctx: JointChain) -> None:
    """RTS smoother (:func:`gt3dkit.fusion.ukf.filterloop.backward_chain`) of the chains ``chain``
    (indices into ``ctx.start``) from their persons' last rows ``last (K,)`` back:
    ``ctx.out.x, ctx.out.P`` filtered on entry, smoothed on exit."""
    for k in chain:
        backward_chain(ctx, k, last[k])


def covariance_entries(n_joints: int) -> int:
    """Covariance entries a row of a person with ``n_joints`` joints is budgeted by the windows
    (:func:`gt3dkit.windows.plan.state_bytes`): ``J + 1`` parts of the ellipsoid and one joint
    (``StateLayout(1)``, 15 entries) each, as the per-joint filters were first held."""
    return (n_joints + 1) * StateLayout(1).n ** 2


def point_sigma(alpha: float, beta: float, kappa: float, d: int = SPACE) -> PointSigma:
    """The :class:`PointSigma` of a joint's position (``d = 3``), or position and velocity (6),
    under the scaled unscented rule."""
    sw = SigmaWeights(d, alpha, beta, kappa)
    Wm, Wc = sw.Wm, sw.Wc
    if Wm[0] == 0.0 and Wc[0] == 0.0:  # the cubature rule gives the centre no weight
        Wm, Wc = Wm[1:], Wc[1:]
    return PointSigma(contiguous(Wm), contiguous(Wc), float(np.sqrt(sw.n + sw.lam)))


def joint_columns(C: int, robust: RobustConfig | None, d: int = SPACE) -> Columns:
    """The :class:`gt3dkit.fusion.ukf.update.Columns` of one joint's ``2 C`` views (on its three
    coordinates, or ``d = 6``: its position and velocity; points of two entries judged by
    ``robust``, a :class:`gt3dkit.fusion.preparation.robust.RobustConfig`, or never reweighted: None)."""
    blk = Block(np.arange(d)[None], np.arange(2 * C)[None], None)
    rule = Robust(robust, ((slice(0, 2 * C), 2),)) if robust is not None else None
    return block_columns([blk], 2 * C, rule)


def _per_joint(a: F64, R: int, C: int, J: int, at: int) -> F64:
    """The keypoint columns ``at:`` of ``a (R, m)`` as ``(R, J, C, 2)`` (contiguous)."""
    return contiguous(a[:, at:].reshape(R, C, J, 2).transpose(0, 2, 1, 3), a.dtype)


def boxes_part(model: RowsModel) -> RowsModel:
    """The boxes-only model of ``model``'s ellipsoid (its box columns, the state's first 9
    entries): what :func:`gt3dkit.fusion.ukf.boxupdate.run_boxes` runs."""
    E = StateLayout(0).n
    mb = model.n_box_columns
    blocks = tuple(b for b in model.robust_blocks if b[0].stop <= mb)
    return replace(model, layout=StateLayout(0), z=model.z[:, :mb], mask=model.mask[:, :mb],
                   var=model.var[:, :mb], weight0=model.weight0[:, :mb], robust_blocks=blocks,
                   x_frame=model.x_frame[:, :E],
                   var_frame=model.var_frame[:, :E], kpt_cov_frame=None, joint_info=None)


def run_joints(model: RowsModel, init: Init, cfg: UKFConfig, fps: float, collect: bool = False,
               fade: bool = True, on: np.ndarray | None = None, noise_rows: NoiseRows | None = None,
               covariances: bool = True, into: BlockCov | F64 | None = None) -> FilterRun:
    """The filter (and RTS) of a model with joints as compiled chains (the module doc): the
    arguments and outputs of :func:`gt3dkit.fusion.ukf.filtering.run_filter`; ``covariances=False``
    leaves ``P`` out (``(R, 0, 0)``), ``into`` takes the covariances of the rows ``on`` (the others
    left as they are) and is the run's ``P``."""
    rows, lay = model.rows, model.layout
    R, J, C = len(rows), lay.n_joints, len(model.cams.K)
    if not J:
        return run_boxes(model, init, cfg, fps, collect=collect, fade=fade, on=on, noise_rows=noise_rows)
    jd = np.concatenate([lay.joint_dims(np.arange(J)), lay.joint_dims(np.arange(J)) + SPACE * J], axis=1)
    chains, first, last = object_chains(model, fps, on)
    per = noise_rows or {}
    q = per.get("joint_accel_sd", cfg.joint_accel_sd if cfg.joint_accel_sd is not None else cfg.accel_sd)
    at = model.n_box_columns
    timed = bool(np.any(rows.seen_at != 0.0))
    info = model.joint_info
    kcov = model.kpt_cov_frame
    data = JointData(
        _per_joint(model.z, R, C, J, at), _per_joint(model.mask, R, C, J, at),
        _per_joint(model.var, R, C, J, at), _per_joint(model.weight0, R, C, J, at),
        contiguous(model.x_frame[:, lay.joints].reshape(R, J, SPACE)),
        contiguous(model.var_frame[:, lay.joints].reshape(R, J, SPACE)),
        contiguous(np.full((1, 1, 1, 1), np.inf) if kcov is None else kcov),
        contiguous(np.zeros((0, J, SPACE, SPACE)) if info is None else info.info),
        contiguous(np.zeros((0, J, SPACE)) if info is None else info.eta),
        contiguous(np.broadcast_to(np.asarray(q, dtype=np.float64), (R,))),
        contiguous(rows.seen_at / fps if timed else np.zeros((0, C))))
    robust = cfg.robust_config if cfg.robust and model.robust_blocks else None
    d = N if timed else SPACE  # views off their rows' frames: regressed on the velocity too
    cols = joint_columns(C, robust, d)
    jm = JointModel(point_sigma(cfg.alpha, cfg.beta, cfg.kappa, d), model.box_rig, cols, int(cfg.iterations),
                    bool(np.any(cols.size > 0)), bool(fade) and kcov is not None,
                    float(chi2_isf(1e-3, SPACE)))
    objs = np.flatnonzero(first >= 0)
    srow = first[objs]
    K = len(objs) * J
    start = JointStart(contiguous(np.repeat(srow, J), np.int64),
                       contiguous(np.tile(np.arange(J), len(objs)), np.int64),
                       contiguous(init.x0[srow][:, jd].reshape(K, N)),
                       contiguous(np.asarray(init.P0[srow[:, None, None, None], jd[None, :, :, None],
                                                     jd[None, :, None, :]]).reshape(K, N, N)))
    out = JointOut(np.zeros((R, J, N)), np.zeros((R, J, N, N)), np.zeros((R, J, N)), np.zeros((R, J, N, N)),
                   np.zeros((R, J), bool), np.zeros((R, J, 5)), np.ones((R, J, C, 2)), np.zeros((R, J, C, 2)),
                   np.zeros((R, J, C, 2)))
    # the chains dealt alternately over the threads (each person's joints split between them)
    size = np.bincount(rows.row_o, minlength=len(rows.obj_ids))[objs]
    order = np.argsort(np.repeat(-size, J), kind="stable")
    parts = [np.sort(order[i::2]).astype(np.int64) for i in range(2)] if K > 1 else \
        [np.arange(K, dtype=np.int64)]

    def fwd(a: int, b: int) -> None:
        for p in parts[a:b]:
            forward(p, joint_chain(start, chains, data, jm, out))

    run_split(fwd, len(parts))
    if cfg.smooth:
        ends = contiguous(np.repeat(last[objs], J), np.int64)

        def bwd(a: int, b: int) -> None:
            for p in parts[a:b]:
                backward(p, ends, joint_chain(start, chains, data, jm, out))

        run_split(bwd, len(parts))
    run = RunChoice(collect, fade, on, noise_rows, covariances, into)
    return _assembled(model, init, cfg, fps, run, chains, out, jd)


class RunChoice(NamedTuple):
    """How :func:`run_joints` was asked to run (its keyword arguments, handed on whole)."""

    collect: bool
    fade: bool
    on: np.ndarray | None
    noise_rows: NoiseRows | None
    covariances: bool
    into: BlockCov | F64 | None


def _assembled(model: RowsModel, init: Init, cfg: UKFConfig, fps: float, run: RunChoice, chains: Chains,
               out: JointOut, jd: I64) -> FilterRun:
    """The run of ``model``'s rows from the joints' chains ``out`` and the ellipsoid's run (the
    boxes', or the rows' initial state without boxes)."""
    collect, fade, on, noise_rows, covariances, into = run
    rows, lay = model.rows, model.layout
    R, J, C = len(rows), lay.n_joints, len(model.cams.K)
    E = StateLayout(0).n
    ran = chains.run
    jran = ran[:, None] & (out.stats[:, :, 3] > 0)  # (R, J)
    box = None
    if model.use_box:
        ell = boxes_part(model)
        box = run_boxes(ell, replace(init, x0=init.x0[:, :E], P0=_leading(init.P0, E)), cfg, fps,
                        collect=collect, fade=fade, on=on, noise_rows=noise_rows)
    x = np.zeros((R, lay.n))
    x[:, :E] = box.x if box is not None else init.x0[:, :E]
    x[:, jd.reshape(-1)] = out.x.reshape(R, J * N)
    x[~ran] = 0.0
    P: BlockCov | F64 = np.zeros((R, 0, 0))
    if covariances:
        ell_cov = np.asarray(box.P) if box is not None else np.asarray(_leading(init.P0, E)[np.arange(R)])
        P = BlockCov(lay.n, [(np.arange(E)[None], ell_cov[:, None]), (jd, out.P)]).rows_that_ran(ran, into)
    st = np.where(jran[:, :, None], out.stats, 0.0)

    def summed(k: int, boxes: F64 | None) -> F64:
        v = st[:, :, k].sum(axis=1)
        return v + boxes if boxes is not None else v

    nis = summed(0, box.nis if box is not None else None)
    dof = summed(1, box.dof if box is not None else None)
    ll = summed(2, box.loglik_rows if box is not None else None)

    def entries(a: F64, boxes: F64 | None) -> F64 | None:
        if not collect:
            return None
        kp = np.where(jran[:, :, None, None], a, 0.0).transpose(0, 2, 1, 3).reshape(R, 2 * C * J)
        return np.concatenate([boxes, kp], axis=1) if boxes is not None else kp

    passes = st[:, :, 3][jran]
    return FilterRun(
        x, P, nis, dof, ll,
        entries(out.weights, box.weights if box is not None else None),
        entries(out.score2, box.score2 if box is not None else None),
        entries(out.resid, box.residual if box is not None else None),
        pd_repairs=int(st[:, :, 4].sum()) + (box.pd_repairs if box is not None else 0),
        predictions_faded=int(out.faded.sum()) + (box.predictions_faded if box is not None else 0),
        object_frames=R if on is None else int(ran.sum()),
        update_form="information, iterated and reweighted (compiled, per joint)",
        update_passes_mean=float(passes.mean()) if passes.size else 0.0)


def _leading(P0: F64 | InitialCov, E: int) -> F64 | InitialCov:
    """The leading ``E x E`` entries of initial covariances ``P0 (R, n, n)`` (lazy where ``P0`` is)."""
    R = P0.shape[0]
    e = np.arange(E)
    if isinstance(P0, np.ndarray):
        return P0[:, :E, :E]
    return P0.entries(np.arange(R), np.broadcast_to(e, (R, E)))
