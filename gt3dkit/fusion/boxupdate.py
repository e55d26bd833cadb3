r"""The iterated, robust information-form update of :func:`gt3dkit.fusion.ukf.ukf_update_information`
for the box measurement alone, compiled (numba).

With boxes only, every frame's update is one :class:`gt3dkit.fusion.ukf.Block` (the tangent
boxes of all cameras, a function of the centre and the log semi-axes): a 9-entry state, a
6-dimensional marginal, 12 sigma points, at most ``4 C`` edges. The numpy formulation spends
~2 ms per frame in ~500 array calls on batches of ~30 objects; here each object is a few
thousand flops in one loop (the tangent box of :mod:`gt3dkit.geom.boxkernel` inlined), and the
objects of a frame run in parallel on :func:`gt3dkit.threads.compiled_threads` threads.

The mathematics is that of the numpy path, which stays the reference (the tests hold this one
to it, row by row): the same statistical linear regression, the same information update,
leave-one-out robust weights (:mod:`gt3dkit.fusion.robust`) and statistics. One difference:
the numpy path stops iterating when *every* row of the batch has converged, this one per row
(a converged row's further passes change it by less than the convergence tolerance).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from gt3dkit.geom.boxkernel import _named, camera_setup, pair_box
from gt3dkit.types import F64

_LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class BoxCameras:
    """The camera arrays the compiled tangent box needs (contiguous float64)."""

    world_from_body: F64
    K: F64
    dist: F64
    R: F64
    t: F64
    depth_sign: F64

    @classmethod
    def of(cls, cams: Any) -> BoxCameras:
        C = len(cams.K)
        f = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        return cls(f(cams.world_from_body), f(cams.K), f(cams.dist), f(cams.R), f(cams.t),
                   f(np.broadcast_to(np.asarray(cams.depth_sign, dtype=np.float64), (C,))))


@numba.njit(cache=True, nogil=True)
def _chol(A: F64, L: F64) -> bool:
    """Lower Cholesky factor of the symmetric ``A (n, n)`` into ``L``; False if not PD."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@numba.njit(cache=True, nogil=True)
def _safe_chol(A: F64, L: F64) -> int:
    """:func:`gt3dkit.fusion.ukf.safe_cholesky` of one matrix: ``L`` of ``(A + A^T) / 2``,
    eigenvalue-clipped if that is not PD. Returns 1 if a repair was needed, else 0."""
    n = A.shape[0]
    S = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            S[i, j] = 0.5 * (A[i, j] + A[j, i])
    if _chol(S, L):
        return 0
    if not np.all(np.isfinite(S)):
        L[:, :] = np.nan
        return 1
    w, V = np.linalg.eigh(S)
    wmax = max(w.max(), 1e-300)
    bad = 1 if w.min() <= 1e-15 * wmax else 0
    w = np.maximum(w, 1e-12 * wmax)
    P2 = (V * w) @ V.T
    for i in range(n):
        for j in range(n):
            S[i, j] = 0.5 * (P2[i, j] + P2[j, i])
    if not _chol(S, L):
        for i in range(n):
            for j in range(n):
                L[i, j] = np.nan
    return bad


@numba.njit(cache=True, nogil=True)
def _lower_inverse(L: F64, Li: F64) -> None:
    """``Li = L^-1`` of a lower triangular ``L`` (forward substitution)."""
    n = L.shape[0]
    for j in range(n):
        for i in range(n):
            if i < j:
                Li[i, j] = 0.0
                continue
            s = 1.0 if i == j else 0.0
            for k in range(j, i):
                s -= L[i, k] * Li[k, j]
            Li[i, j] = s / L[i, i]


@numba.njit(cache=True, nogil=True)
def _row(b: int, x: F64, P: F64, z: F64, mask: np.ndarray, Rd: F64, w0: F64, xl: F64, Pl: F64,
         iterations: int, dims: np.ndarray, Wm: F64, Wc: F64, scale: float, robust: bool,
         c_thr: float, g_thr: float, Rc: F64, gx: F64, gy: F64, K: F64, dist: F64, R: F64,
         t: F64, ds: F64, steps: int, x_out: F64, P_out: F64, stats: F64, wt_out: F64,
         score_out: F64, resid_out: F64) -> None:
    n = x.shape[1]
    m = z.shape[1]
    C = K.shape[0]
    d = dims.shape[0]
    S = Wm.shape[0]
    first = S - 2 * d  # 1 with the centre point, 0 without (the cubature rule)
    repaired = 0
    xb0 = x[b]
    Psym = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            Psym[i, j] = 0.5 * (P[b, i, j] + P[b, j, i])
    if np.all(np.isfinite(Psym)):
        Pinv = np.linalg.inv(Psym)
    else:
        Pinv = np.full((n, n), np.nan)
    xj = xl[b].copy()
    Pj = Pl[b].copy()
    wt = w0[b].copy()
    Pb = np.empty((d, d))
    Lb = np.empty((d, d))
    X = np.empty((S, d))
    Z = np.empty((S, C, 4))
    want = np.empty(C, dtype=np.bool_)
    mk = np.empty(m, dtype=np.bool_)
    zhat = np.empty(m)
    Pxz = np.empty((d, m))
    At = np.empty((d, m))
    omega = np.empty(m)
    cvec = np.empty(m)
    D = np.empty(m)
    Dinv = np.empty(m)
    nu = np.empty(m)
    Jinf = np.empty((n, n))
    g = np.empty(n)
    Lj = np.empty((n, n))
    Li = np.empty((n, n))
    P_post = np.empty((n, n))
    x_post = np.empty(n)
    resid = np.zeros(m)
    score2 = np.zeros(m)
    it = 0
    for it in range(iterations):
        last = it == iterations - 1
        # --- statistical linear regression on the (centre, log axes) marginal's sigma points
        for i in range(d):
            for k in range(d):
                Pb[i, k] = Pj[dims[i], dims[k]]
        repaired += _safe_chol(Pb, Lb)
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
        elif np.all(np.isfinite(Pb)) and np.all(np.isfinite(Pxz)):
            At[:, :] = np.linalg.solve(Pb, Pxz)
        else:
            At[:, :] = np.nan
        for k in range(m):
            om = var_z[k]
            cc = z[b, k] - zhat[k]
            for i in range(d):
                om -= Pxz[i, k] * At[i, k]
                cc += At[i, k] * xj[dims[i]]
            omega[k] = max(om, 0.0) if mk[k] else 0.0
            cvec[k] = cc
            D[k] = Rd[b, k] + omega[k]
            if mk[k]:
                Dinv[k] = wt[k] / D[k]
                v = cc
                for i in range(d):
                    v -= At[i, k] * xb0[dims[i]]
                nu[k] = v
            else:
                Dinv[k] = 0.0
                nu[k] = 0.0
        # --- information update
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
        repaired += _safe_chol(Jinf, Lj)
        _lower_inverse(Lj, Li)
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
    LP = np.empty((n, n))
    _safe_chol(P[b], LP)  # (repairs of the prior are not counted, as in the numpy path)
    logdet = 0.0
    dof = 0
    quad = 0.0
    for k in range(m):
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
    x_out[b] = x_post
    P_out[b] = P_post
    stats[b, 0] = quad
    stats[b, 1] = dof
    stats[b, 2] = -0.5 * (quad + logdet + dof * _LOG_2PI)
    stats[b, 3] = it + 1
    stats[b, 4] = repaired
    for k in range(m):
        wt_out[b, k] = wt[k] if mask[b, k] else 1.0
        score_out[b, k] = score2[k]
        resid_out[b, k] = resid[k]


def _rows(x: F64, P: F64, z: F64, mask: np.ndarray, Rd: F64, w0: F64, xl: F64, Pl: F64,
          iterations: int, dims: np.ndarray, Wm: F64, Wc: F64, scale: float, robust: bool,
          c_thr: float, g_thr: float, Rb: F64, K: F64, dist: F64, R: F64, t: F64, ds: F64,
          steps: int, x_out: F64, P_out: F64, stats: F64, wt_out: F64, score_out: F64,
          resid_out: F64) -> None:
    Rc, gx, gy = camera_setup(Rb, K, R)
    for b in numba.prange(x.shape[0]):
        _row(b, x, P, z, mask, Rd, w0, xl, Pl, iterations, dims, Wm, Wc, scale, robust, c_thr, g_thr,
             Rc, gx, gy, K, dist, R, t, ds, steps, x_out, P_out, stats, wt_out, score_out, resid_out)


rows_serial = numba.njit(cache=True, nogil=True)(_named(_rows, "rows_serial"))
rows_parallel = numba.njit(cache=True, nogil=True, parallel=True)(_named(_rows, "rows_parallel"))


def applies(blocks: list[Any], m: int, robust_blocks: tuple[tuple[slice, int], ...]) -> bool:
    """Whether the compiled update can run these blocks: the box block alone, covering the whole
    measurement vector, robust (if at all) edge by edge."""
    if len(blocks) != 1 or blocks[0].compiled is None:
        return False
    blk = blocks[0]
    return (blk.dims.shape[0] == 1 and blk.cols.shape == (1, m) and np.array_equal(blk.cols[0], np.arange(m))
            and all(sl.indices(m) == (0, m, 1) and d == 1 for sl, d in robust_blocks))


def box_update(x: F64, P: F64, z: F64, mask: np.ndarray, R_diag: F64, blk: Any, w: Any, iterations: int,
               x_lin: F64 | None, P_lin: F64 | None, weight0: F64 | None, robust: Any,
               robust_blocks: tuple[tuple[slice, int], ...]) -> tuple[F64, F64, dict[str, Any]]:
    """:func:`gt3dkit.fusion.ukf.ukf_update_information` for the box block alone (see
    :func:`applies`), compiled; same arguments (``w`` the state's sigma weights: their
    ``alpha, beta, kappa`` are used for the block's marginal) and the same outputs."""
    from gt3dkit.fusion.ukf import SigmaWeights
    from gt3dkit.threads import compiled_threads

    B, m = z.shape
    n = x.shape[1]
    cams: BoxCameras = blk.compiled
    dims = np.ascontiguousarray(blk.dims[0], dtype=np.int64)
    sw = SigmaWeights(len(dims), w.alpha, w.beta, w.kappa)
    Wm, Wc = sw.Wm, sw.Wc
    if Wm[0] == 0.0 and Wc[0] == 0.0:  # the cubature rule gives the centre no weight
        Wm, Wc = Wm[1:], Wc[1:]
    c = lambda a, dt=np.float64: np.ascontiguousarray(a, dtype=dt)  # noqa: E731
    x, P = c(x), c(P)
    xl = x if x_lin is None or P_lin is None else c(x_lin)
    Pl = P if x_lin is None or P_lin is None else c(P_lin)
    Rd = c(np.broadcast_to(np.asarray(R_diag, dtype=np.float64), (B, m)))
    w0 = np.ones((B, m)) if weight0 is None else c(weight0)
    on = robust is not None and bool(robust_blocks)
    c_thr, g_thr = robust.thresholds(1) if on else (0.0, 0.0)
    if on and not robust.enabled:  # point_weights gives 1 everywhere
        c_thr, g_thr = np.inf, np.inf
    x_out, P_out = np.empty((B, n)), np.empty((B, n, n))
    stats = np.empty((B, 5))
    wt, score2, resid = np.empty((B, m)), np.empty((B, m)), np.empty((B, m))
    par = compiled_threads() > 1 and B > 1
    run = rows_parallel if par else rows_serial
    run(x, P, c(z), c(mask, np.bool_), Rd, w0, xl, Pl, int(iterations), dims, c(Wm), c(Wc),
        float(np.sqrt(sw.n + sw.lam)), on, float(c_thr), float(g_thr), cams.world_from_body, cams.K,
        cams.dist, cams.R, cams.t, cams.depth_sign, 2, x_out, P_out, stats, wt, score2, resid)
    quad, dof, ll = stats[:, 0], stats[:, 1].astype(np.int64), stats[:, 2]
    info = {"nis": float(quad.sum()), "dof": int(dof.sum()), "loglik": float(ll.sum()),
            "nis_rows": quad, "dof_rows": dof, "loglik_rows": ll,
            "passes": int(stats[:, 3].max()) if B else 0, "repaired": int(stats[:, 4].sum()),
            "weights": wt, "score2": score2, "residual": resid}
    return x_out, P_out, info
