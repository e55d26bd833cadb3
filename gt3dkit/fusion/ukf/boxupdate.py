r"""The box measurement's statistical linear regression, and the whole filter of a boxes-only
model as one compiled loop (numba).

With boxes only, a row's measurement is the tangent boxes of all cameras, a function of the
centre and the log semi-axes (a 6-dimensional marginal of the state, 12 sigma points, at most
``4 C`` edges). :func:`box_regression` regresses them on that marginal (the tangent box of
:mod:`gt3dkit.geom.boxkernel` inlined); it is the box block's regression for every filter
(:meth:`gt3dkit.fusion.ukf.measurement.Model.blocks`).

:func:`forward` and :func:`backward` run the filter of a boxes-only model as chains of rows per
object: each object's filter is independent of the others', so objects run in parallel on
:func:`gt3dkit.threads.compiled_threads` threads and the frames of one object in order. Every
step is the one implementation of the package: the prediction and RTS step of
:mod:`gt3dkit.fusion.ukf.kalman`, ``F, Q`` of :mod:`gt3dkit.fusion.motion`, the update of
:mod:`gt3dkit.fusion.ukf.update`; only the order of the loops differs from the filter over frames
(:class:`gt3dkit.fusion.ukf.smoother.FrameLoop`), and the tests hold the two to each other.

:class:`LinearisedSearch` prices a process-noise value as a linear Kalman filter, the boxes'
regression fixed per row.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.motion import SPACE, Noise, StateIndex, accel_shape, transition
from gt3dkit.fusion.preparation.robust import chi2_isf
from gt3dkit.fusion.ukf.config import NoiseRows, UKFConfig
from gt3dkit.fusion.ukf.filterloop import Chains, backward_chain, forward_chain, register
from gt3dkit.fusion.ukf.filterrun import FilterRun
from gt3dkit.fusion.ukf.initial import Init
from gt3dkit.fusion.ukf.kalman import ellipsoid_linearisation, fade_centre, fade_factor, predict_row, rts_row
from gt3dkit.fusion.ukf.rowsmodel import BoxModel, BoxSigma, RowsModel
from gt3dkit.fusion.ukf.sigma import SigmaWeights
from gt3dkit.fusion.ukf.update import (
    Columns,
    Current,
    Measured,
    Posterior,
    Prior,
    Regression,
    Scores,
    information_pass,
    pass_row,
    prior_factor,
    statistics,
)
from gt3dkit.geom.boxkernel import EDGES, pair_box
from gt3dkit.geom.boxrig import BoxRig
from gt3dkit.geom.smallmat import safe_chol, solve_sym
from gt3dkit.threads import run_split
from gt3dkit.types import F64, I64


class RowsOut(NamedTuple):
    """The updated rows ``x (R, n)``, ``P (R, n, n)``, their statistics ``stats (R, 5)`` (NIS,
    dof, log-likelihood, passes, repairs) and per measurement entry the final ``weights``, the
    point's squared leave-one-out ``score2`` and the residual ``resid`` ``(R, m)``."""

    x: F64
    P: F64
    stats: F64
    weights: F64
    score2: F64
    resid: F64


@numba.njit(cache=True, nogil=True)
def box_regression(xj: F64, Pj: F64, meas: Measured, sig: BoxSigma, rig: BoxRig, seen_s: F64, at: int,
                   lin: Regression) -> int:
    """Statistical linear regression of a row's boxes (``meas``: that row's ``(m,)``) on the
    ellipsoid marginal of ``N(xj, Pj)`` (sigma rule ``sig``) into the box columns ``at + k`` of
    ``lin``: ``z ~ A x + b + e``, ``e ~ N(0, D)`` (``D`` = the noise + the linearisation error).
    An edge is used where annotated and every sigma point's box is finite. With the velocity among
    ``sig.dims`` (nine entries), camera ``c``'s box was taken ``seen_s[c]`` seconds after the row's
    time and outlines the ellipsoid whose centre the motion model moves by then (``c + δ v``;
    :func:`gt3dkit.fusion.ukf.jointupdate.point_regression` for joints). Returns 1 if the marginal's
    factor needed a repair."""
    dims = sig.dims
    C = rig.cam.shape[0]
    m = EDGES * C
    d = dims.shape[0]
    S = sig.Wm.shape[0]
    Pb = np.empty((d, d))
    X = np.empty((S, d))
    Z = np.empty((S, C, EDGES))
    want = np.empty(C, dtype=np.bool_)
    repaired = sigma_points(xj, Pj, dims, sig.scale, Pb, X)
    la = d - SPACE  # the log semi-axes: the last three of the marginal
    timed = d > 2 * SPACE
    for c in range(C):
        want[c] = False
        for e in range(EDGES):
            want[c] = want[c] or meas.mask[at + EDGES * c + e]
    for s in range(S):
        sq = (math.exp(2.0 * X[s, la]), math.exp(2.0 * X[s, la + 1]), math.exp(2.0 * X[s, la + 2]))
        for c in range(C):
            dt = seen_s[c] if timed else 0.0
            at_view = (X[s, 0] + dt * X[s, SPACE], X[s, 1] + dt * X[s, SPACE + 1],
                       X[s, 2] + dt * X[s, SPACE + 2])
            pair_box(at_view, sq, c, rig, want[c], Z, s)
    regress(X, Z.reshape(S, m), xj, dims, sig.Wm, sig.Wc, Pb, meas, at, lin)
    return repaired


@numba.njit(cache=True, nogil=True)
def sigma_points(xj: F64, Pj: F64, dims: I64, scale: float, Pb: F64, X: F64) -> int:
    """The sigma points ``X (S, d)`` of the marginal on ``dims (d,)`` of ``N(xj, Pj)``: with the
    centre point first when ``S = 2 d + 1``, then ``+-scale`` times the columns of the marginal's
    Cholesky factor; ``Pb (d, d)`` receives the marginal. Returns 1 if the factor needed a repair."""
    d = dims.shape[0]
    first = X.shape[0] - 2 * d  # 1 with the centre point, 0 without (the cubature rule)
    Lb = np.empty((d, d))
    for i in range(d):
        for k in range(d):
            Pb[i, k] = Pj[dims[i], dims[k]]
    repaired = safe_chol(Pb, Lb)
    if first == 1:
        for i in range(d):
            X[0, i] = xj[dims[i]]
    for s in range(d):
        for i in range(d):
            X[first + s, i] = xj[dims[i]] + scale * Lb[i, s]
            X[first + d + s, i] = xj[dims[i]] - scale * Lb[i, s]
    return repaired


@numba.njit(cache=True, nogil=True)
def regress(X: F64, Z: F64, xj: F64, dims: I64, Wm: F64, Wc: F64, Pb: F64, meas: Measured, at: int,
            lin: Regression) -> None:
    """Statistical linear regression of the measurements ``Z (S, m)`` of the sigma points ``X (S,
    d)`` (of the marginal ``Pb`` on ``dims`` of ``N(xj, .)``, weights ``Wm, Wc``) into the
    columns ``at + k`` of ``lin``: ``z ~ A x + b + e``, ``e ~ N(0, D)`` (``D`` = the noise of
    ``meas`` + the linearisation error); an entry is used where ``meas`` has it and every sigma
    point's is finite."""
    S, m = Z.shape
    d = dims.shape[0]
    mk = lin.used[at:at + m]
    zhat = np.empty(m)
    for k in range(m):
        ok = meas.mask[at + k]
        if ok:
            for s in range(S):
                if not np.isfinite(Z[s, k]):
                    ok = False
                    break
        mk[k] = ok
        zh = 0.0
        if ok:
            for s in range(S):
                zh += Wm[s] * Z[s, k]
        zhat[k] = zh
    var_z = np.zeros(m)
    Pxz = np.zeros((d, m))
    At = np.empty((d, m))
    for s in range(S):
        for k in range(m):
            if not mk[k]:
                continue
            dz = Z[s, k] - zhat[k]
            var_z[k] += Wc[s] * dz * dz
            for i in range(d):
                Pxz[i, k] += Wc[s] * (X[s, i] - xj[dims[i]]) * dz
    if not mk.any():
        At[:, :] = 0.0
    elif np.all(np.isfinite(Pxz)):
        solve_sym(Pb, Pxz, At)
    else:
        At[:, :] = np.nan
    for k in range(m):
        om = var_z[k]
        cc = meas.z[at + k] - zhat[k]
        for i in range(d):
            om -= Pxz[i, k] * At[i, k]
            cc += At[i, k] * xj[dims[i]]
            lin.At[at + k, i] = At[i, k]
        lin.c[at + k] = cc
        lin.D[at + k] = meas.var[at + k] + (max(om, 0.0) if mk[k] else 0.0)


@numba.njit(cache=True, nogil=True)
def box_regressions(rows: I64, x: F64, P: F64, meas: Measured, sig: BoxSigma, rig: BoxRig, at: int,
                    lin: Regression, repaired: I64) -> None:
    """:func:`box_regression` of each row ``r`` in ``rows`` about ``N(x[r], P[r])`` into ``lin``
    (``(R, ...)`` arrays), its repairs added to ``repaired[r]``."""
    for r in rows:
        repaired[r] += box_regression(x[r], P[r], Measured(meas.z[r], meas.mask[r], meas.var[r]), sig, rig,
                                      np.zeros(rig.cam.shape[0]), at,
                                      Regression(lin.used[r], lin.At[r], lin.c[r], lin.D[r]))


@numba.njit(cache=True, nogil=True)
def update_row(b: int, x: F64, P: F64, xl: F64, Pl: F64, data: Measured, w0: F64, box: BoxModel,
               out: RowsOut) -> None:
    """The iterated, robust update (:func:`gt3dkit.fusion.ukf.update.pass_row`) of row ``b`` with
    prior ``x (n,), P (n, n)`` by its boxes (``data``, start weights ``w0``: ``(R, m)``), the
    first pass linearised at ``xl, Pl``; into ``out``'s row ``b``."""
    n = x.shape[0]
    m = data.z.shape[1]
    d = box.cols.dims.shape[1]
    LP, Pinv = np.empty((n, n)), np.empty((n, n))
    prior_factor(P, LP, Pinv)
    prior = Prior(x, Pinv, LP)
    cur = Current(xl.copy(), Pl.copy(), w0[b].copy(), np.empty(m))
    lin = Regression(np.zeros(m, np.bool_), np.zeros((m, d)), np.zeros(m), np.ones(m))
    post = Posterior(np.empty(n), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty(n),
                     np.zeros(m), np.zeros(m))
    scores = Scores(np.zeros(m), np.zeros(m))
    meas = Measured(data.z[b], data.mask[b], data.var[b])
    seen = box.seen_s[b] if box.seen_s.shape[0] else np.zeros(box.rig.cam.shape[0])
    repaired = 0
    it = 0
    for it in range(box.iterations):
        repaired += box_regression(cur.xj, cur.Pj, meas, box.sigma, box.rig, seen, box.at, lin)
        done, rep = pass_row(it, it == box.iterations - 1, box.robust, prior, lin, box.cols, cur, post,
                             scores)
        repaired += rep
        if done:
            break
    quad, dof, ll = statistics(prior, lin, cur.wt, post)
    out.x[b] = post.x
    out.P[b] = post.P
    out.stats[b, 0] = quad
    out.stats[b, 1] = dof
    out.stats[b, 2] = ll
    out.stats[b, 3] = it + 1
    out.stats[b, 4] = repaired
    for k in range(m):
        out.weights[b, k] = cur.wt[k] if meas.mask[k] else 1.0
        out.score2[b, k] = scores.score2[k]
        out.resid[b, k] = scores.resid[k]


class Start(NamedTuple):
    """Initial state ``x0 (R, n)`` and covariance ``P0 (R, n, n)`` of every row (read where an
    object starts)."""

    x0: F64
    P0: F64


class Motion(NamedTuple):
    """The process noise of each row's step ``accel, shape, joint_accel, position (R,)``
    (:class:`gt3dkit.fusion.motion.Noise`), the shape of the centre's acceleration noise ``A (3,
    3)`` (:func:`gt3dkit.fusion.motion.accel_shape`) and the state's layout."""

    accel: F64
    shape: F64
    joint_accel: F64
    position: F64
    A: F64
    ix: StateIndex


@numba.njit(cache=True, nogil=True)
def motion_noise(motion: Motion, row: int) -> Noise:
    """The noise of the step into row ``row``."""
    return Noise(motion.accel[row], motion.shape[row], motion.joint_accel[row], motion.position[row])


class Fading(NamedTuple):
    """Fading and the linearisation point: ``on``, the chi-square ``limit``, per row whether the
    frame's own fit ``determined (R,)`` the centre, that fit ``x_frame (R, n)`` with its
    ellipsoid covariance ``cov6 (R, 6, 6)`` and centre trace ``frame_trace (R,)``."""

    on: bool
    limit: float
    determined: np.ndarray
    x_frame: F64
    cov6: F64
    frame_trace: F64


class Track(NamedTuple):
    """The forward pass's predictions ``x_p (R, n)``, ``P_p (R, n, n)`` and which were faded
    ``faded (R,)``."""

    x_p: F64
    P_p: F64
    faded: np.ndarray


class BoxChain(NamedTuple):
    """The box kind's bundle for :mod:`gt3dkit.fusion.ukf.filterloop`: the chains, the initial
    states, the motion, fading, the measurements and first weights, the box model, the rows'
    outputs and predictions, and work arrays ``F, Q (n, n)``, the linearisation point ``x_l (n,),
    P_l (n, n)`` and the fading test's ``e (3,), S (3, 3)``."""

    chains: Chains
    start: Start
    motion: Motion
    fading: Fading
    data: Measured
    w0: F64
    box: BoxModel
    out: RowsOut
    track: Track
    F: F64
    Q: F64
    x_l: F64
    P_l: F64
    e: F64
    S: F64


@numba.njit(cache=True, nogil=True)
def _start(ctx: BoxChain, e: int, row: int) -> None:
    ctx.track.x_p[row] = ctx.start.x0[row]
    ctx.track.P_p[row] = ctx.start.P0[row]


@numba.njit(cache=True, nogil=True)
def _predict(ctx: BoxChain, e: int, row: int, prev: int, f: float) -> None:
    """Row ``row``'s prediction from its filtered predecessor ``prev``, the centre's noise scaled
    by ``f``."""
    motion, track = ctx.motion, ctx.track
    noise = motion_noise(motion, row)
    transition(ctx.chains.t_s[row] - ctx.chains.t_s[prev],
               Noise(noise.accel_sd * f, noise.shape_sd, noise.joint_accel_sd, noise.position_sd * f),
               motion.A, motion.ix, ctx.F, ctx.Q)
    predict_row(ctx.out.x[prev], ctx.out.P[prev], ctx.F, ctx.Q, track.x_p[row], track.P_p[row])


@numba.njit(cache=True, nogil=True)
def _fades(ctx: BoxChain, e: int, row: int) -> bool:
    return ctx.fading.on and ctx.fading.determined[row]


@numba.njit(cache=True, nogil=True)
def _centre_fade(ctx: BoxChain, e: int, row: int) -> float:
    """:func:`gt3dkit.fusion.ukf.kalman.fade_factor` of row ``row``'s prediction against the frame's
    own fit."""
    fading, track, c0 = ctx.fading, ctx.track, ctx.motion.ix.centre
    for i in range(SPACE):
        ctx.e[i] = fading.x_frame[row, c0 + i] - track.x_p[row, c0 + i]
        for j in range(SPACE):
            ctx.S[i, j] = track.P_p[row, c0 + i, c0 + j] + fading.cov6[row, i, j]
    return fade_factor(ctx.e, ctx.S, fading.limit)


@numba.njit(cache=True, nogil=True)
def _faded(ctx: BoxChain, e: int, row: int, f: float) -> None:
    if f != 1.0:
        fade_centre(ctx.track.P_p[row], f, ctx.motion.ix)
    ctx.track.faded[row] = True


@numba.njit(cache=True, nogil=True)
def _measured(ctx: BoxChain, e: int, row: int) -> bool:
    data = ctx.data
    for k in range(data.mask.shape[1]):
        if data.mask[row, k]:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _keep(ctx: BoxChain, e: int, row: int) -> None:
    ctx.out.x[row] = ctx.track.x_p[row]
    ctx.out.P[row] = ctx.track.P_p[row]


@numba.njit(cache=True, nogil=True)
def _update(ctx: BoxChain, e: int, row: int) -> None:
    track, fading = ctx.track, ctx.fading
    ellipsoid_linearisation(track.x_p[row], track.P_p[row], fading.x_frame[row], fading.cov6[row],
                            fading.frame_trace[row], ctx.box.sigma.dims, ctx.motion.ix, ctx.x_l, ctx.P_l)
    update_row(row, track.x_p[row], track.P_p[row], ctx.x_l, ctx.P_l, ctx.data, ctx.w0, ctx.box, ctx.out)


@numba.njit(cache=True, nogil=True)
def _smooth(ctx: BoxChain, e: int, row: int, nxt: int) -> None:
    motion, out, track = ctx.motion, ctx.out, ctx.track
    transition(ctx.chains.t_s[nxt] - ctx.chains.t_s[row], motion_noise(motion, row), motion.A,
               motion.ix, ctx.F, ctx.Q)
    rts_row(out.x[row], out.P[row], track.x_p[nxt], track.P_p[nxt], out.x[nxt], out.P[nxt], ctx.F,
            out.x[row], out.P[row])


register(BoxChain, start=_start, predict=_predict, fades=_fades, fade=_centre_fade, faded=_faded,
         measured=_measured, keep=_keep, update=_update, smooth=_smooth)


def box_chain(chains: Chains, start: Start, motion: Motion, fading: Fading, data: Measured, w0: F64,
              box: BoxModel, out: RowsOut, track: Track) -> BoxChain:
    """The bundle of a run, with its own work arrays (one per thread)."""
    n = motion.ix.n
    return BoxChain(chains, start, motion, fading, data, w0, box, out, track, np.empty((n, n)),
                    np.empty((n, n)), np.empty(n), np.empty((n, n)), np.empty(SPACE),
                    np.empty((SPACE, SPACE)))


@numba.njit(cache=True, nogil=True)
def forward(first: I64, ctx: BoxChain) -> None:
    """Forward filter (:func:`gt3dkit.fusion.ukf.filterloop.forward_chain`) of every object whose
    first row is in ``first``: the filtered rows into ``ctx.out``, the predictions into
    ``ctx.track``."""
    for row0 in first:
        forward_chain(ctx, 0, row0)


@numba.njit(cache=True, nogil=True)
def backward(last: I64, ctx: BoxChain) -> None:
    """RTS smoother (:func:`gt3dkit.fusion.ukf.filterloop.backward_chain`) of every object from its
    last row in ``last``: ``ctx.out`` holds the filtered values on entry and the smoothed ones on
    exit."""
    for nxt0 in last:
        backward_chain(ctx, 0, nxt0)


@numba.njit(cache=True, nogil=True)
def linear_forward(first: I64, chains: Chains, start: Start, motion: Motion, lins: Regression, w0: F64,
                   cols: Columns) -> float:
    """The log-likelihood of a forward pass with each row's regression fixed (``lins``: ``(R,
    ...)``, :func:`box_regressions`): a linear Kalman filter of every object whose first row is in
    ``first``, weights ``w0 (R, m)``; the prediction, update and likelihood of :func:`forward`
    (no fading, one pass)."""
    n = motion.ix.n
    m = w0.shape[1]
    F, Q = np.empty((n, n)), np.empty((n, n))
    x_p, P_p = np.empty(n), np.empty((n, n))
    LP, Pinv = np.empty((n, n)), np.empty((n, n))
    post = Posterior(np.empty(n), np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty(n),
                     np.zeros(m), np.zeros(m))
    total = 0.0
    for row0 in first:
        row = row0
        prev = -1
        while row >= 0 and chains.run[row]:
            if prev < 0:
                x_p[:] = start.x0[row]
                P_p[:, :] = start.P0[row]
            else:
                transition(chains.t_s[row] - chains.t_s[prev],
                           motion_noise(motion, row), motion.A,
                           motion.ix, F, Q)
                predict_row(post.x, post.P, F, Q, x_p, P_p)
            prior_factor(P_p, LP, Pinv)
            prior = Prior(x_p, Pinv, LP)
            lin = Regression(lins.used[row], lins.At[row], lins.c[row], lins.D[row])
            information_pass(prior, lin, cols, w0[row], post)
            total += statistics(prior, lin, w0[row], post)[2]
            prev = row
            row = chains.next_row[row]
    return total


def box_sigma(dims: I64, alpha: float, beta: float, kappa: float) -> BoxSigma:
    """The :class:`BoxSigma` of the ellipsoid entries ``dims (6,)`` under the scaled unscented
    rule ``alpha, beta, kappa`` (:class:`gt3dkit.fusion.ukf.sigma.SigmaWeights`)."""
    sw = SigmaWeights(len(dims), alpha, beta, kappa)
    Wm, Wc = sw.Wm, sw.Wc
    if Wm[0] == 0.0 and Wc[0] == 0.0:  # the cubature rule gives the centre no weight
        Wm, Wc = Wm[1:], Wc[1:]
    return BoxSigma(contiguous(dims, np.int64), contiguous(Wm), contiguous(Wc), float(np.sqrt(sw.n + sw.lam)))


def measured(z: F64, mask: np.ndarray, var: F64) -> Measured:
    """Rows' measurements as :class:`Measured` (contiguous; ``var`` broadcast to ``z``)."""
    return Measured(contiguous(z), contiguous(mask, np.bool_), contiguous(np.broadcast_to(var, z.shape)))


def regression_rows(B: int, m: int, d: int) -> Regression:
    """Empty ``(B, ...)`` regressions of ``m`` columns over at most ``d`` state entries."""
    return Regression(np.zeros((B, m), np.bool_), np.zeros((B, m, d)), np.zeros((B, m)), np.ones((B, m)))


def object_chains(model: RowsModel, fps: float, on: np.ndarray | None) -> tuple[Chains, I64, I64]:
    """The rows as :class:`Chains` and each object's first and last row ``(O,)`` (-1: not run)."""
    rows = model.rows
    R, O = len(rows), len(rows.obj_ids)
    run = np.ones(R, bool) if on is None else contiguous(on, np.bool_)
    first = np.full(O, -1, np.int64)
    last = np.full(O, -1, np.int64)
    starts = np.flatnonzero(rows.prev_row < 0)
    ends = np.flatnonzero(rows.next_row < 0)
    first[rows.row_o[starts]] = np.where(run[starts], starts, -1)
    last[rows.row_o[ends]] = np.where(run[ends], ends, -1)
    t_s = contiguous(rows.frames[rows.row_t] / fps)
    return Chains(contiguous(rows.next_row, np.int64), contiguous(rows.prev_row, np.int64), run,
                  t_s), first, last


def motion_of(model: RowsModel, cfg: UKFConfig, noise_rows: NoiseRows | None = None) -> Motion:
    """The rows' process noise (``cfg``'s, or ``noise_rows``' per row) as :class:`Motion`."""
    R = len(model.rows)
    per = noise_rows or {}

    def col(name: str, default: F64 | float | None = None) -> F64:
        v = per.get(name, getattr(cfg, name))
        return contiguous(np.broadcast_to(np.asarray(default if v is None else v, dtype=np.float64), (R,)))

    accel = col("accel_sd")  # the joints move with the centre's noise unless given their own
    return Motion(accel, col("shape_sd"), col("joint_accel_sd", accel), col("position_sd", 0.0),
                  accel_shape(model.cams.up, cfg.vertical_ratio), model.layout.index)


def run_boxes(model: RowsModel, init: Init, cfg: UKFConfig, fps: float, collect: bool, fade: bool,
              on: np.ndarray | None, noise_rows: NoiseRows | None) -> FilterRun:
    """The filter (and RTS) of a boxes-only model (:func:`applies_to_model`) as chains of rows,
    objects in parallel: the arguments and outputs of
    :func:`gt3dkit.fusion.ukf.filtering.run_filter`."""
    rows, layout = model.rows, model.layout
    R, n = len(rows), layout.n
    m = model.z.shape[1]
    robust = cfg.robust_config if cfg.robust else None
    timed = bool(np.any(rows.seen_at != 0.0))  # views off their rows' times: the boxes on the velocity too
    seen = rows.seen_at / fps if timed else None
    box = model.box_measurement(cfg.alpha, cfg.beta, cfg.kappa, robust, seen)._replace(
        iterations=int(cfg.iterations), robust=robust is not None and bool(model.robust_blocks))
    chains, first, last = object_chains(model, fps, on)
    motion = motion_of(model, cfg, noise_rows)
    fading = Fading(bool(fade), float(chi2_isf(1e-3, SPACE)), contiguous(model.centre_determined, np.bool_),
                    contiguous(model.x_frame), contiguous(model.cov6_frame),
                    contiguous(model.frame_centre_trace))
    out = RowsOut(np.zeros((R, n)), np.zeros((R, n, n)), np.zeros((R, 5)), np.ones((R, m)), np.zeros((R, m)),
                  np.zeros((R, m)))
    track = Track(np.zeros((R, n)), np.zeros((R, n, n)), np.zeros(R, bool))
    start = Start(contiguous(init.x0), contiguous(init.P0))
    data = measured(model.z, model.mask, model.var)
    w0 = contiguous(model.weight0)
    # objects in two halves of about equal rows (each thread runs whole objects)
    objs = np.flatnonzero(first >= 0)
    size = np.bincount(rows.row_o, minlength=len(rows.obj_ids))[objs]
    objs = objs[np.argsort(-size, kind="stable")]  # longest first, dealt alternately
    groups = [np.sort(objs[k::2]) for k in range(2)]
    parts = len(groups) if len(objs) > 1 else 1

    def fwd(a: int, b: int) -> None:
        for g in groups[a:b]:
            forward(contiguous(first[g], np.int64),
                    box_chain(chains, start, motion, fading, data, w0, box, out, track))

    run_split(fwd, parts)
    if cfg.smooth:
        def bwd(a: int, b: int) -> None:
            for g in groups[a:b]:
                backward(contiguous(last[g], np.int64),
                         box_chain(chains, start, motion, fading, data, w0, box, out, track))

        run_split(bwd, parts)
    stats = out.stats
    done = chains.run & (stats[:, 3] > 0)

    def entries(a: F64) -> F64 | None:
        return np.where(done[:, None], a, 0.0) if collect else None

    return FilterRun(
        out.x, out.P, np.where(done, stats[:, 0], 0.0), np.where(done, stats[:, 1], 0.0),
        np.where(done, stats[:, 2], 0.0), entries(out.weights), entries(out.score2), entries(out.resid),
        pd_repairs=int(stats[done, 4].sum()), predictions_faded=int(track.faded.sum()),
        object_frames=R if on is None else int(chains.run.sum()),
        update_form="information, iterated and reweighted (compiled, per object)",
        update_passes_mean=float(stats[done, 3].mean()) if done.any() else 0.0)


def applies_to_model(model: RowsModel) -> bool:
    """Whether :func:`run_boxes` runs this model: the boxes alone measure it (no joints, no
    information added to them)."""
    return bool(model.use_box and not model.layout.n_joints and model.joint_info is None)
