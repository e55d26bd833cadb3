r"""The iterated, robust information-form update of :func:`gt3dkit.fusion.ukf.ukf_update_information`
for the box measurement alone, compiled (numba).

With boxes only, every frame's update is one :class:`gt3dkit.fusion.ukf.Block` (the tangent
boxes of all cameras, a function of the centre and the log semi-axes): a 9-entry state, a
6-dimensional marginal, 12 sigma points, at most ``4 C`` edges. The numpy formulation spends
~2 ms per frame in ~500 array calls on batches of ~30 objects; here each object is a few
thousand flops in one loop (the tangent box of :mod:`gt3dkit.geom.boxkernel` inlined), and the
objects run on :func:`gt3dkit.threads.compiled_threads` threads (:func:`gt3dkit.threads.run_split`).

The mathematics is that of the numpy path, which stays the reference (the tests hold this one
to it, row by row): the same statistical linear regression, the same information update,
leave-one-out robust weights (:mod:`gt3dkit.fusion.robust`) and statistics. One difference:
the numpy path stops iterating when *every* row of the batch has converged, this one per row
(a converged row's further passes change it by less than the convergence tolerance).

numba caches each compiled function next to its module, keyed by that module's file only: after
editing :mod:`gt3dkit.geom.boxkernel` (whose tangent box is compiled into these functions),
remove ``gt3dkit/fusion/__pycache__/boxupdate*.nb*`` too, or this module keeps the old box. (A
fresh install or clone has no cache; ``make setup`` compiles everything once.)
"""

from __future__ import annotations

import math
from typing import Any

import numba
import numpy as np

from gt3dkit.fusion.robust import chi2_isf
from gt3dkit.fusion.ukf import SigmaWeights
from gt3dkit.geom.boxkernel import BoxCameras, camera_setup, contiguous, pair_box
from gt3dkit.geom.smallmat import chol, chol_solve, lower_inverse, matmul, safe_chol, solve_sym, symmetrised
from gt3dkit.threads import run_split
from gt3dkit.types import F64

_LOG_2PI = math.log(2.0 * math.pi)


@numba.njit(cache=True, nogil=True)
def _prior_factor(Pb: F64, LP: F64, Pinv: F64) -> None:
    """The prior covariance ``Pb (n, n)``'s Cholesky factor ``LP`` (for its log-determinant) and
    inverse ``Pinv``, from one factorisation."""
    n = Pb.shape[0]
    Psym = symmetrised(Pb)
    if chol(Psym, LP):
        chol_solve(LP, np.eye(n), Pinv)
    else:  # not positive definite: the inverse of the matrix itself (as np.linalg.inv), and the
        solve_sym(Psym, np.eye(n), Pinv)  # factor repaired (repairs of the prior are not
        safe_chol(Psym, LP)               # counted, as in the numpy path)


@numba.njit(cache=True, nogil=True)
def _slr(b: int, xj: F64, Pj: F64, z: F64, mask: np.ndarray, Rd: F64, dims: np.ndarray, Wm: F64, Wc: F64,
         scale: float, Rc: F64, gx: F64, gy: F64, K: F64, dist: F64, R: F64, t: F64, ds: F64, steps: int,
         mk: np.ndarray, At: F64, cvec: F64, D: F64) -> int:
    """Statistical linear regression of row ``b``'s boxes on the (centre, log axes) marginal of
    ``N(xj, Pj)``: ``z ~ At^T x[dims] + (cvec - z) + e``, ``e ~ N(0, D)`` (``D`` = measurement
    noise ``Rd`` + linearisation error); ``mk``: the edges used (annotated, and every sigma
    point's box finite). Returns 1 if the marginal's factor needed a repair."""
    m = z.shape[1]
    C = K.shape[0]
    d = dims.shape[0]
    S = Wm.shape[0]
    first = S - 2 * d  # 1 with the centre point, 0 without (the cubature rule)
    Pb = np.empty((d, d))
    Lb = np.empty((d, d))
    X = np.empty((S, d))
    Z = np.empty((S, C, 4))
    want = np.empty(C, dtype=np.bool_)
    zhat = np.empty(m)
    Pxz = np.empty((d, m))
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
    for c in range(C):
        want[c] = mask[b, 4 * c] or mask[b, 4 * c + 1] or mask[b, 4 * c + 2] or mask[b, 4 * c + 3]
    for s in range(S):
        e0, e1, e2 = math.exp(X[s, 3]), math.exp(X[s, 4]), math.exp(X[s, 5])
        for c in range(C):
            pair_box(X[s, 0], X[s, 1], X[s, 2], e0 * e0, e1 * e1, e2 * e2, c, Rc, gx, gy, K, dist,
                     R, t, ds, steps, want[c], Z, s)
    for k in range(m):
        ok = mask[b, k]
        if ok:
            for s in range(S):
                if not np.isfinite(Z[s, k // 4, k % 4]):
                    ok = False
                    break
        mk[k] = ok
        zh = 0.0
        if ok:
            for s in range(S):
                zh += Wm[s] * Z[s, k // 4, k % 4]
        zhat[k] = zh
    var_z = np.zeros(m)
    for i in range(d):
        for k in range(m):
            Pxz[i, k] = 0.0
    for s in range(S):
        for k in range(m):
            if not mk[k]:
                continue
            dz = Z[s, k // 4, k % 4] - zhat[k]
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
        cc = z[b, k] - zhat[k]
        for i in range(d):
            om -= Pxz[i, k] * At[i, k]
            cc += At[i, k] * xj[dims[i]]
        cvec[k] = cc
        D[k] = Rd[b, k] + (max(om, 0.0) if mk[k] else 0.0)
    return repaired


@numba.njit(cache=True, nogil=True)
def _innovation(xb0: F64, dims: np.ndarray, mk: np.ndarray, wt: F64, At: F64, cvec: F64, D: F64, Dinv: F64,
                nu: F64) -> None:
    """Each edge's weighted information ``Dinv = wt / D`` and innovation ``nu = cvec - At^T xb0``
    against the prior mean ``xb0`` (0 for an edge not used)."""
    for k in range(cvec.shape[0]):
        if mk[k]:
            Dinv[k] = wt[k] / D[k]
            v = cvec[k]
            for i in range(dims.shape[0]):
                v -= At[i, k] * xb0[dims[i]]
            nu[k] = v
        else:
            Dinv[k] = 0.0
            nu[k] = 0.0


@numba.njit(cache=True, nogil=True)
def _information(xb0: F64, Pinv: F64, At: F64, Dinv: F64, nu: F64, dims: np.ndarray, Jinf: F64, g: F64,
                 Lj: F64, P_post: F64, x_post: F64) -> int:
    """The information update of the prior ``(xb0, Pinv)`` by the linear(ised) edges: posterior
    ``x_post, P_post``, its information ``Jinf`` with factor ``Lj`` and the information vector
    ``g``. Returns 1 if ``Jinf``'s factor needed a repair."""
    n = xb0.shape[0]
    m = nu.shape[0]
    d = dims.shape[0]
    Li = np.empty((n, n))
    for i in range(n):
        g[i] = 0.0
        for j in range(n):
            Jinf[i, j] = Pinv[i, j]
    for i in range(d):
        gi = 0.0
        for k in range(m):
            gi += At[i, k] * Dinv[k] * nu[k]
        g[dims[i]] += gi
        for j in range(d):
            h = 0.0
            for k in range(m):
                h += At[i, k] * Dinv[k] * At[j, k]
            Jinf[dims[i], dims[j]] += h
    repaired = safe_chol(Jinf, Lj)
    lower_inverse(Lj, Li)
    for i in range(n):
        for j in range(n):
            s_ = 0.0
            for k in range(max(i, j), n):
                s_ += Li[k, i] * Li[k, j]
            P_post[i, j] = s_
    for i in range(n):
        s_ = 0.0
        for j in range(n):
            s_ += P_post[i, j] * g[j]
        x_post[i] = xb0[i] + s_
    return repaired


@numba.njit(cache=True, nogil=True)
def _loglik(mk: np.ndarray, wt: F64, D: F64, Dinv: F64, nu: F64, Lj: F64, LP: F64, P_post: F64,
            g: F64) -> tuple[float, int, float]:
    """The normalised innovation square, its degrees of freedom and the log-likelihood of an
    information update (by the matrix determinant lemma: no ``m x m`` matrix is formed)."""
    n = Lj.shape[0]
    logdet = 0.0
    dof = 0
    quad = 0.0
    for k in range(nu.shape[0]):
        if mk[k] and wt[k] > 0:
            logdet += math.log(D[k] / wt[k])
            dof += 1
        quad += nu[k] * nu[k] * Dinv[k]
    for i in range(n):
        logdet += 2.0 * math.log(Lj[i, i]) + 2.0 * math.log(LP[i, i])
        s_ = 0.0
        for j in range(n):
            s_ += P_post[i, j] * g[j]
        quad -= g[i] * s_
    return quad, dof, -0.5 * (quad + logdet + dof * _LOG_2PI)


@numba.njit(cache=True, nogil=True)
def _row(b: int, x: F64, P: F64, z: F64, mask: np.ndarray, Rd: F64, w0: F64, xl: F64, Pl: F64,
         iterations: int, dims: np.ndarray, Wm: F64, Wc: F64, scale: float, robust: bool,
         c_thr: float, g_thr: float, Rc: F64, gx: F64, gy: F64, K: F64, dist: F64, R: F64,
         t: F64, ds: F64, steps: int, x_out: F64, P_out: F64, stats: F64, wt_out: F64,
         score_out: F64, resid_out: F64) -> None:
    n = x.shape[1]
    m = z.shape[1]
    d = dims.shape[0]
    repaired = 0
    xb0 = x[b]
    LP = np.empty((n, n))
    Pinv = np.empty((n, n))
    _prior_factor(P[b], LP, Pinv)
    xj = xl[b].copy()
    Pj = Pl[b].copy()
    wt = w0[b].copy()
    mk = np.empty(m, dtype=np.bool_)
    At = np.empty((d, m))
    cvec = np.empty(m)
    D = np.empty(m)
    Dinv = np.empty(m)
    nu = np.empty(m)
    Jinf = np.empty((n, n))
    g = np.empty(n)
    Lj = np.empty((n, n))
    P_post = np.empty((n, n))
    x_post = np.empty(n)
    resid = np.zeros(m)
    score2 = np.zeros(m)
    it = 0
    for it in range(iterations):
        last = it == iterations - 1
        repaired += _slr(b, xj, Pj, z, mask, Rd, dims, Wm, Wc, scale, Rc, gx, gy, K, dist, R, t, ds, steps,
                         mk, At, cvec, D)
        _innovation(xb0, dims, mk, wt, At, cvec, D, Dinv, nu)
        repaired += _information(xb0, Pinv, At, Dinv, nu, dims, Jinf, g, Lj, P_post, x_post)
        converged = False
        if it > 0:
            q = 0.0
            for i in range(n):
                st = 0.0
                for j in range(n):
                    st += Lj[j, i] * (x_post[j] - xj[j])
                q += st * st
            tp, tj = 0.0, 0.0
            for i in range(n):
                tp += P_post[i, i]
                tj += Pj[i, i]
            converged = q < 1e-4 and abs(tp / tj - 1.0) < 1e-3
        if robust:
            changed = False
            new_w = wt.copy()
            for k in range(m):
                if not mk[k]:
                    resid[k] = 0.0
                    score2[k] = 0.0
                    continue
                r = cvec[k]
                pk = 0.0
                for i in range(d):
                    r -= At[i, k] * x_post[dims[i]]
                    a = 0.0
                    for j in range(d):
                        a += P_post[dims[i], dims[j]] * At[j, k]
                    pk += At[i, k] * a
                resid[k] = r
                hh = min(max(wt[k] * pk / max(D[k], 1e-300), 0.0), 1.0 - 1e-9)
                rl = r / (1.0 - hh)
                e2 = rl * rl / (D[k] + pk / (1.0 - hh))
                score2[k] = e2
                if not last:  # robust.point_weights of a one-entry point
                    e = math.sqrt(max(0.0 if np.isnan(e2) else e2, 0.0))
                    if e >= g_thr:
                        nw = 0.0
                    elif e <= c_thr:
                        nw = 1.0
                    else:
                        tp_ = min(max(1.0 - ((e - c_thr) / (g_thr - c_thr)) ** 2, 0.0), 1.0)
                        nw = (c_thr / max(e, 1e-300)) * tp_ * tp_
                    if nw != wt[k]:
                        changed = True
                        new_w[k] = nw
            if not last:
                converged = converged and not changed
                if not converged:
                    wt[:] = new_w
        if last or converged:
            break
        xj[:] = x_post
        Pj[:, :] = P_post
    # --- statistics of the last pass, with the weights it used
    quad, dof, ll = _loglik(mk, wt, D, Dinv, nu, Lj, LP, P_post, g)
    x_out[b] = x_post
    P_out[b] = P_post
    stats[b, 0] = quad
    stats[b, 1] = dof
    stats[b, 2] = ll
    stats[b, 3] = it + 1
    stats[b, 4] = repaired
    for k in range(m):
        wt_out[b, k] = wt[k] if mask[b, k] else 1.0
        score_out[b, k] = score2[k]
        resid_out[b, k] = resid[k]


@numba.njit(cache=True, nogil=True)
def rows_update(x: F64, P: F64, z: F64, mask: np.ndarray, Rd: F64, w0: F64, xl: F64, Pl: F64,
                iterations: int, dims: np.ndarray, Wm: F64, Wc: F64, scale: float, robust: bool,
                c_thr: float, g_thr: float, Rb: F64, K: F64, dist: F64, R: F64, t: F64, ds: F64,
                steps: int, x_out: F64, P_out: F64, stats: F64, wt_out: F64, score_out: F64,
                resid_out: F64, a: int, b: int) -> None:
    """:func:`_row` for the batch rows ``a..b-1``."""
    Rc, gx, gy = camera_setup(Rb, K, R)
    for r in range(a, b):
        _row(r, x, P, z, mask, Rd, w0, xl, Pl, iterations, dims, Wm, Wc, scale, robust, c_thr, g_thr,
             Rc, gx, gy, K, dist, R, t, ds, steps, x_out, P_out, stats, wt_out, score_out, resid_out)


def _block_rule(blk: Any, alpha: float, beta: float, kappa: float, robust: Any,
                robust_blocks: tuple[tuple[slice, int], ...]) -> tuple[np.ndarray, F64, F64, float, bool,
                                                                       float, float]:
    """The box block's state entries ``dims``, its marginal's sigma weights ``Wm, Wc`` (without
    the centre point where the rule gives it no weight) and ``scale``, and the robust rule:
    ``(dims, Wm, Wc, scale, robust_on, c, g)`` (thresholds of a one-entry point)."""
    dims = contiguous(blk.dims[0], np.int64)
    sw = SigmaWeights(len(dims), alpha, beta, kappa)
    Wm, Wc = sw.Wm, sw.Wc
    if Wm[0] == 0.0 and Wc[0] == 0.0:  # the cubature rule gives the centre no weight
        Wm, Wc = Wm[1:], Wc[1:]
    on = robust is not None and bool(robust_blocks)
    c_thr, g_thr = robust.thresholds(1) if on else (0.0, 0.0)
    if on and not robust.enabled:  # point_weights gives 1 everywhere
        c_thr, g_thr = np.inf, np.inf
    return dims, contiguous(Wm), contiguous(Wc), float(np.sqrt(sw.n + sw.lam)), on, float(c_thr), float(g_thr)


def applies(blocks: list[Any], m: int, robust_blocks: tuple[tuple[slice, int], ...]) -> bool:
    """Whether the compiled update can run these blocks: the box block alone, covering the whole
    measurement vector, robust (if at all) edge by edge."""
    if len(blocks) != 1 or blocks[0].compiled is None:
        return False
    blk = blocks[0]
    return (blk.dims.shape[0] == 1 and blk.cols.shape == (1, m) and np.array_equal(blk.cols[0], np.arange(m))
            and all(sl.indices(m) == (0, m, 1) and d == 1 for sl, d in robust_blocks))


def box_update(x: F64, P: F64, z: F64, mask: np.ndarray, R_diag: F64, blocks: list[Any], w: Any,
               iterations: int, x_lin: F64 | None, P_lin: F64 | None, weight0: F64 | None, robust: Any,
               robust_blocks: tuple[tuple[slice, int], ...]) -> tuple[F64, F64, dict[str, Any]]:
    """:func:`gt3dkit.fusion.ukf.ukf_update_information` for the box block alone (``blocks``: that
    one block, see :func:`applies`), compiled; same arguments (``w`` the state's sigma weights:
    their ``alpha, beta, kappa`` are used for the block's marginal) and the same outputs."""
    blk = blocks[0]
    B, m = z.shape
    n = x.shape[1]
    cams: BoxCameras = blk.compiled
    dims, Wm, Wc, scale, on, c_thr, g_thr = _block_rule(blk, w.alpha, w.beta, w.kappa, robust, robust_blocks)
    c = contiguous
    x, P = c(x), c(P)
    xl = x if x_lin is None or P_lin is None else c(x_lin)
    Pl = P if x_lin is None or P_lin is None else c(P_lin)
    Rd = c(np.broadcast_to(np.asarray(R_diag, dtype=np.float64), (B, m)))
    w0 = np.ones((B, m)) if weight0 is None else c(weight0)
    x_out, P_out = np.empty((B, n)), np.empty((B, n, n))
    stats = np.empty((B, 5))
    wt, score2, resid = np.empty((B, m)), np.empty((B, m)), np.empty((B, m))
    args = (x, P, c(z), c(mask, np.bool_), Rd, w0, xl, Pl, int(iterations), dims, Wm, Wc,
            scale, on, c_thr, g_thr, cams.world_from_body, cams.K,
            cams.dist, cams.R, cams.t, cams.depth_sign, 2, x_out, P_out, stats, wt, score2, resid)
    run_split(lambda a, b: rows_update(*args, a, b), B, 4)
    quad, dof, ll = stats[:, 0], stats[:, 1].astype(np.int64), stats[:, 2]
    info = {"nis": float(quad.sum()), "dof": int(dof.sum()), "loglik": float(ll.sum()),
            "nis_rows": quad, "dof_rows": dof, "loglik_rows": ll,
            "passes": int(stats[:, 3].max()) if B else 0, "repaired": int(stats[:, 4].sum()),
            "weights": wt, "score2": score2, "residual": resid}
    return x_out, P_out, info


# --- the whole forward pass and the RTS smoother of a boxes-only model, compiled ---------------
# (gt3dkit.fusion.ukf_smoother.run_filter's loop over frames, as chains of rows per object: each
# object's filter is independent of the others', so the objects run in parallel and the frames
# of one object in order; the numpy loop over frames stays the reference the tests hold it to)


@numba.njit(cache=True, nogil=True)
def _transition(dt: float, accel_sd: float, shape_sd: float, A: F64, F: F64, Q: F64) -> None:
    """:meth:`gt3dkit.fusion.motion.StateLayout.transition` of the 9-entry box state for one
    step ``dt`` (s): ``A (3, 3)`` shapes the centre's acceleration noise (``I + (r^2 - 1) u u^T``)."""
    F[:, :] = 0.0
    Q[:, :] = 0.0
    for i in range(9):
        F[i, i] = 1.0
    qa2 = accel_sd * accel_sd
    b00, b01, b11 = qa2 * dt**3 / 3.0, qa2 * dt**2 / 2.0, qa2 * dt
    for i in range(3):
        F[i, 3 + i] = dt
        for j in range(3):
            Q[i, j] = b00 * A[i, j]
            Q[i, 3 + j] = b01 * A[i, j]
            Q[3 + i, j] = b01 * A[i, j]
            Q[3 + i, 3 + j] = b11 * A[i, j]
        Q[6 + i, 6 + i] = shape_sd * shape_sd * dt


@numba.njit(cache=True, nogil=True)
def _predict(x: F64, P: F64, F: F64, Q: F64, x_out: F64, P_out: F64) -> None:
    """``x_out = F x``, ``P_out = (F P F^T + Q)`` symmetrised (:func:`gt3dkit.fusion.ukf.predict_linear`)."""
    n = x.shape[0]
    FP = np.empty((n, n))
    Pp = np.empty((n, n))
    matmul(F, P, FP)
    matmul(FP, F.T, Pp)
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += F[i, j] * x[j]
        x_out[i] = s
    for i in range(n):
        for j in range(n):
            P_out[i, j] = 0.5 * ((Pp[i, j] + Q[i, j]) + (Pp[j, i] + Q[j, i]))


@numba.njit(cache=True, nogil=True)
def forward(first: np.ndarray, next_row: np.ndarray, run: np.ndarray, t_s: F64, x0: F64, P0: F64,
             accel: F64, shape: F64, A: F64, fade: bool, fade_lim: float, determined: np.ndarray,
             x_frame: F64, cov6: F64, frame_trace: F64, z: F64, mask: np.ndarray, Rd: F64, w0: F64,
             iterations: int, dims: np.ndarray, Wm: F64, Wc: F64, scale: float, robust: bool,
             c_thr: float, g_thr: float, Rb: F64, K: F64, dist: F64, R: F64, t: F64, ds: F64,
             steps: int, x_p: F64, P_p: F64, x_l: F64, P_l: F64, x_f: F64, P_f: F64, stats: F64,
             wt: F64, score2: F64, resid: F64, faded: np.ndarray) -> None:
    """Forward filter of every object ``o`` with ``first[o] >= 0``: its rows from ``first[o]``
    along ``next_row`` while ``run``; writes the predictions ``x_p, P_p``, the filtered
    ``x_f, P_f`` and each row's statistics (see :func:`_row`). ``faded[row]``: the prediction
    was faded (:meth:`gt3dkit.fusion.measurement.Model.prior_conflict`)."""
    Rc, gx, gy = camera_setup(Rb, K, R)
    n = x0.shape[1]
    for o in range(first.shape[0]):
        row = first[o]
        prev = -1
        F = np.empty((n, n))
        Q = np.empty((n, n))
        while row >= 0 and run[row]:
            if prev < 0:
                x_p[row] = x0[row]
                P_p[row] = P0[row]
            else:
                _transition(t_s[row] - t_s[prev], accel[row], shape[row], A, F, Q)
                _predict(x_f[prev], P_f[prev], F, Q, x_p[row], P_p[row])
                if fade and determined[row]:
                    e = np.empty(3)
                    S = np.empty((3, 3))
                    for i in range(3):
                        e[i] = x_frame[row, i] - x_p[row, i]
                        for j in range(3):
                            S[i, j] = P_p[row, i, j] + cov6[row, i, j]
                    if np.all(np.isfinite(S)) and np.all(np.isfinite(e)):
                        Se = np.empty((3, 1))
                        solve_sym(S, e.reshape(3, 1), Se)
                        d2 = e[0] * Se[0, 0] + e[1] * Se[1, 0] + e[2] * Se[2, 0]
                        if d2 > fade_lim:
                            f = math.sqrt(d2 / 3.0)
                            for i in range(n):
                                si = f if i < 6 else 1.0
                                for j in range(n):
                                    P_p[row, i, j] *= si * (f if j < 6 else 1.0)
                            faded[row] = True
            # the linearisation point (Model.linearisation_point, boxes)
            x_l[row] = x_p[row]
            P_l[row] = P_p[row]
            tr = P_p[row, 0, 0] + P_p[row, 1, 1] + P_p[row, 2, 2]
            if tr > frame_trace[row]:
                for a in range(dims.shape[0]):
                    x_l[row, dims[a]] = x_frame[row, dims[a]]
                    for j in range(n):
                        P_l[row, dims[a], j] = 0.0
                        P_l[row, j, dims[a]] = 0.0
                for a in range(dims.shape[0]):
                    for b in range(dims.shape[0]):
                        P_l[row, dims[a], dims[b]] = cov6[row, a, b]
            _row(row, x_p, P_p, z, mask, Rd, w0, x_l, P_l, iterations, dims, Wm, Wc, scale, robust, c_thr,
                 g_thr, Rc, gx, gy, K, dist, R, t, ds, steps, x_f, P_f, stats, wt, score2, resid)
            prev = row
            row = next_row[row]


@numba.njit(cache=True, nogil=True)
def backward(last: np.ndarray, prev_row: np.ndarray, run: np.ndarray, t_s: F64, A: F64, accel: F64,
              shape: F64, x_p: F64, P_p: F64, x_s: F64, P_s: F64) -> None:
    """RTS smoother along each object's rows, from ``last[o]`` back along ``prev_row`` while
    ``run``: ``x_s, P_s`` hold the filtered values on entry and the smoothed ones on exit
    (:func:`gt3dkit.fusion.ukf.rts_step`)."""
    n = x_s.shape[1]
    for o in range(last.shape[0]):
        nxt = last[o]
        if nxt < 0:
            continue
        row = prev_row[nxt]
        F = np.empty((n, n))
        Q = np.empty((n, n))
        FPt = np.empty((n, n))
        Gt = np.empty((n, n))
        D = np.empty((n, n))
        GD = np.empty((n, n))
        GDG = np.empty((n, n))
        while row >= 0 and run[row] and run[nxt]:
            _transition(t_s[nxt] - t_s[row], accel[row], shape[row], A, F, Q)
            matmul(F, P_s[row], FPt)  # (P F^T)^T = F P (P_s[row] still holds the filtered covariance)
            solve_sym(P_p[nxt], FPt, Gt)  # G^T = P_p^-1 (P F^T)^T
            for i in range(n):
                s = 0.0
                for j in range(n):
                    s += Gt[j, i] * (x_s[nxt, j] - x_p[nxt, j])
                x_s[row, i] += s
                for j in range(n):
                    D[i, j] = P_s[nxt, i, j] - P_p[nxt, i, j]
            matmul(Gt.T, D, GD)
            matmul(GD, Gt, GDG)
            for i in range(n):
                for j in range(n):
                    P_s[row, i, j] += 0.5 * (GDG[i, j] + GDG[j, i])
            nxt = row
            row = prev_row[row]




@numba.njit(cache=True, nogil=True)
def slr_rows(rows: np.ndarray, x: F64, P: F64, z: F64, mask: np.ndarray, Rd: F64, dims: np.ndarray, Wm: F64,
             Wc: F64, scale: float, Rb: F64, K: F64, dist: F64, R: F64, t: F64, ds: F64, steps: int,
             mk: np.ndarray, At: F64, cvec: F64, D: F64) -> None:
    """:func:`_slr` of each row in ``rows`` about ``N(x[row], P[row])``, into ``mk, At, cvec, D``
    (indexed by row)."""
    Rc, gx, gy = camera_setup(Rb, K, R)
    for r in rows:
        _slr(r, x[r], P[r], z, mask, Rd, dims, Wm, Wc, scale, Rc, gx, gy, K, dist, R, t, ds, steps, mk[r],
             At[r], cvec[r], D[r])


@numba.njit(cache=True, nogil=True)
def linear_forward(first: np.ndarray, next_row: np.ndarray, run: np.ndarray, t_s: F64, x0: F64, P0: F64,
                   accel_sd: float, shape_sd: float, A: F64, mk: np.ndarray, At: F64, cvec: F64, D: F64,
                   w0: F64, dims: np.ndarray) -> float:
    """The log-likelihood of a forward pass with the boxes' regression fixed per row (``mk, At,
    cvec, D`` of :func:`slr_rows`): a linear Kalman filter of every object ``o`` with ``first[o]
    >= 0`` along ``next_row`` while ``run``, at one process noise; weights ``w0``. The same
    prediction, information update and likelihood as :func:`forward` (no fading)."""
    n = x0.shape[1]
    m = cvec.shape[1]
    F = np.empty((n, n))
    Q = np.empty((n, n))
    x_p = np.empty(n)
    P_p = np.empty((n, n))
    LP = np.empty((n, n))
    Pinv = np.empty((n, n))
    Dinv = np.empty(m)
    nu = np.empty(m)
    Jinf = np.empty((n, n))
    g = np.empty(n)
    Lj = np.empty((n, n))
    x_f = np.empty(n)
    P_f = np.empty((n, n))
    total = 0.0
    for o in range(first.shape[0]):
        row = first[o]
        prev = -1
        while row >= 0 and run[row]:
            if prev < 0:
                x_p[:] = x0[row]
                P_p[:, :] = P0[row]
            else:
                _transition(t_s[row] - t_s[prev], accel_sd, shape_sd, A, F, Q)
                _predict(x_f, P_f, F, Q, x_p, P_p)
            _prior_factor(P_p, LP, Pinv)
            _innovation(x_p, dims, mk[row], w0[row], At[row], cvec[row], D[row], Dinv, nu)
            _information(x_p, Pinv, At[row], Dinv, nu, dims, Jinf, g, Lj, P_f, x_f)
            total += _loglik(mk[row], w0[row], D[row], Dinv, nu, Lj, LP, P_f, g)[2]
            prev = row
            row = next_row[row]
    return total


def _chains(model: Any, cfg: Any, fps: float, on: np.ndarray | None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, F64, F64]:
    """Each object's rows as a chain: ``run (R,)`` the rows taken (``on``, default all), ``first,
    last (O,)`` each object's first and last row (-1: not run), ``t_s (R,)`` the rows' times (s)
    and ``A (3, 3)`` the centre's acceleration-noise shape (``I + (r^2 - 1) u u^T``)."""
    rows = model.rows
    R, O = len(rows), len(rows.obj_ids)
    run = np.ones(R, bool) if on is None else np.asarray(on, bool)
    first = np.full(O, -1, np.int64)
    last = np.full(O, -1, np.int64)
    starts = np.flatnonzero(rows.prev_row < 0)
    ends = np.flatnonzero(rows.next_row < 0)
    first[rows.row_o[starts]] = np.where(run[starts], starts, -1)
    last[rows.row_o[ends]] = np.where(run[ends], ends, -1)
    t_s = np.ascontiguousarray(rows.frames[rows.row_t] / fps, dtype=np.float64)
    u = np.asarray(model.cams.up, dtype=np.float64)
    A = np.eye(3) + ((cfg.vertical_ratio**2 - 1.0) * np.outer(u, u) if cfg.vertical_ratio != 1.0 else 0.0)
    return run, first, last, t_s, A


class LinearisedSearch:
    """The likelihood of the box forward pass at many process-noise values, each the price of a
    linear Kalman filter: the boxes are regressed (:func:`_slr`) once per row, about a smoothed
    estimate ``N(x_lin, P_lin)`` of the rows ``on`` (posterior linearisation: García-Fernández,
    Svensson & Särkkä, "Iterated posterior linearization smoother", IEEE TAC 62, 2017), and
    every noise value reuses that regression. The full pass re-linearises at each prediction
    (:func:`forward`); for boxes, whose tangent box bends little over a prediction's spread,
    the two likelihoods' maxima are close (``tests/test_speed_structure.py`` compares the
    noise values found)."""

    def __init__(self, model: Any, init: Any, cfg: Any, fps: float, x_lin: F64, P_lin: F64, weights: F64,
                 on: np.ndarray | None) -> None:
        rows = model.rows
        R = len(rows)
        m = model.z.shape[1]
        blk = model.blocks()[0]
        bc: BoxCameras = blk.compiled
        dims, Wm, Wc, scale, _, _, _ = _block_rule(blk, cfg.alpha, cfg.beta, cfg.kappa, None, ())
        self.run, first, _, t_s, self.A = _chains(model, cfg, fps, on)
        sel = np.flatnonzero(self.run)
        self.mk = np.zeros((R, m), np.bool_)
        self.At = np.zeros((R, len(dims), m))
        self.cvec = np.zeros((R, m))
        self.D = np.ones((R, m))
        c = contiguous
        slr_rows(c(sel, np.int64), c(x_lin), c(P_lin), c(model.z), c(model.mask, np.bool_),
                 c(np.broadcast_to(model.var, (R, m))), dims, Wm, Wc, scale, bc.world_from_body, bc.K,
                 bc.dist, bc.R, bc.t, bc.depth_sign, 2, self.mk, self.At, self.cvec, self.D)
        self.first = first[first >= 0]
        self.args = (c(rows.next_row, np.int64), self.run, t_s, c(init.x0), c(init.P0))
        self.w0 = c(np.broadcast_to(weights, (R, m)))
        self.dims = dims

    def logliks(self, accel_sd: list[float], shape_sd: list[float]) -> list[float]:
        """The forward pass's log-likelihood at each ``(accel_sd, shape_sd)`` pair (the pairs
        split over threads)."""
        out = [0.0] * len(accel_sd)
        nr, run, t_s, x0, P0 = self.args

        def part(a: int, b: int) -> None:
            for i in range(a, b):
                out[i] = linear_forward(self.first, nr, run, t_s, x0, P0, float(accel_sd[i]),
                                        float(shape_sd[i]), self.A, self.mk, self.At, self.cvec, self.D,
                                        self.w0, self.dims)

        run_split(part, len(out))
        return out


def run_boxes(model: Any, init: Any, cfg: Any, fps: float, collect: bool, fade: bool,
              on: np.ndarray | None, noise_rows: dict[str, F64] | None) -> tuple[F64, F64, dict[str, Any]]:
    """:func:`gt3dkit.fusion.ukf_smoother.run_filter` of a boxes-only model (see
    :func:`applies_to_model`), compiled: same arguments, same outputs."""
    rows, layout = model.rows, model.layout
    if cfg.accel_sd is None or cfg.shape_sd is None:
        raise ValueError("run_filter needs numeric accel_sd and shape_sd")
    R, n = len(rows), layout.n
    m = model.z.shape[1]
    blk = model.blocks()[0]
    bc: BoxCameras = blk.compiled
    dims, Wm, Wc, scale, on_r, c_thr, g_thr = _block_rule(
        blk, cfg.alpha, cfg.beta, cfg.kappa, cfg.robust_config if cfg.robust else None, model.robust_blocks)
    per = noise_rows or {}
    accel = contiguous(np.broadcast_to(per.get("accel_sd", cfg.accel_sd), (R,)))
    shape = contiguous(np.broadcast_to(per.get("shape_sd", cfg.shape_sd), (R,)))
    run, first, last, t_s, A = _chains(model, cfg, fps, on)
    O = len(rows.obj_ids)
    c = contiguous
    x_p, P_p = np.zeros((R, n)), np.zeros((R, n, n))
    x_l, P_l = np.zeros((R, n)), np.zeros((R, n, n))
    x_f, P_f = np.zeros((R, n)), np.zeros((R, n, n))
    stats = np.zeros((R, 5))
    wt, score2, resid = np.ones((R, m)), np.zeros((R, m)), np.zeros((R, m))
    faded = np.zeros(R, bool)
    # objects in two halves of about equal rows (each thread runs whole objects)
    objs = np.flatnonzero(first >= 0)
    size = np.bincount(rows.row_o, minlength=O)[objs]
    objs = objs[np.argsort(-size, kind="stable")]  # longest first, dealt alternately
    groups = [np.sort(objs[k::2]) for k in range(2)]
    args = (c(rows.next_row, np.int64), run, t_s, c(init.x0), c(init.P0), accel, shape, A, bool(fade),
            float(chi2_isf(1e-3, 3)), c(model.centre_determined, np.bool_), c(model.x_frame),
            c(model.cov6_frame), c(model.frame_centre_trace), c(model.z), c(model.mask, np.bool_),
            c(np.broadcast_to(model.var, (R, m))), c(model.weight0), int(cfg.iterations), dims, Wm, Wc,
            scale, on_r, c_thr, g_thr, bc.world_from_body, bc.K,
            bc.dist, bc.R, bc.t, bc.depth_sign, 2, x_p, P_p, x_l, P_l, x_f, P_f, stats, wt, score2, resid,
            faded)

    def fwd(a: int, b: int) -> None:
        for g in groups[a:b]:
            forward(c(first[g], np.int64), *args)

    run_split(fwd, len(groups) if len(objs) > 1 else 1)
    del x_l, P_l
    if cfg.smooth:
        prev = c(rows.prev_row, np.int64)

        def bwd(a: int, b: int) -> None:
            for g in groups[a:b]:
                backward(c(last[g], np.int64), prev, run, t_s, A, accel, shape, x_p, P_p, x_f, P_f)

        run_split(bwd, len(groups) if len(objs) > 1 else 1)
    done = run & (stats[:, 3] > 0)
    per_row = {"nis_rows": np.where(done, stats[:, 0], 0.0), "dof_rows": np.where(done, stats[:, 1], 0.0),
               "loglik_rows": np.where(done, stats[:, 2], 0.0)}
    out = {"weights": np.where(done[:, None], wt, 0.0), "score2": np.where(done[:, None], score2, 0.0),
           "residual": np.where(done[:, None], resid, 0.0)} if collect else {}
    info: dict[str, Any] = {
        "pd_repairs": int(stats[done, 4].sum()),
        "predictions_faded": int(faded.sum()),
        "object_frames": R if on is None else int(run.sum()),
        "update_form": "information, iterated and reweighted (compiled, per object)",
        "update_passes_mean": float(stats[done, 3].mean()) if done.any() else 0.0,
        **out, **per_row,
    }
    return x_f, P_f, info


def applies_to_model(model: Any) -> bool:
    """Whether :func:`run_boxes` can run this model: boxes only (no joints), its one block
    compiled (:func:`applies`)."""
    lay = model.layout
    if lay.n_joints or not model.use_box or model.bones is not None:
        return False
    if (lay.n, lay.center, lay.velocity, lay.log_axes) != (9, slice(0, 3), slice(3, 6), slice(6, 9)):
        return False  # the compiled motion model and fading are written for this layout
    return applies(model.blocks(), model.z.shape[1], model.robust_blocks)
