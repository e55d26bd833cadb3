"""The robust triangulation of :func:`gt3dkit.geom.triangulate.robust_triangulate` compiled (numba),
one point at a time (points split over :func:`gt3dkit.threads.compiled_threads` threads): the
all-view DLT and the two-view points of the given view pairs as hypotheses, the truncated cost,
two refits on the inliers; the 4x4 null vector by Jacobi rotations
(:func:`gt3dkit.geom.smallmat.eigh_jacobi`). The tests hold it to the batched numpy formulation it
replaced (``tests/oracles.py``, 5x slower) and to OpenCV's two-view triangulation."""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.geom.smallmat import eigh_jacobi
from gt3dkit.threads import run_split
from gt3dkit.types import F64, I64

drop_stale()  # before any compiled function below is called (and its cache read)


@numba.njit(cache=True, nogil=True)
def _normal(xy: F64, Pc: F64, O: F64) -> None:
    """``O (4, 4)`` = ``r_x r_x^T + r_y r_y^T`` of a view at normalised ``xy (2,)`` with ``Pc = [R |
    t] (3, 4)`` (``r_x = x P_3 - P_1``, ``r_y = y P_3 - P_2``)."""
    rx = np.empty(4)
    ry = np.empty(4)
    for k in range(4):
        rx[k] = xy[0] * Pc[2, k] - Pc[0, k]
        ry[k] = xy[1] * Pc[2, k] - Pc[1, k]
    for i in range(4):
        for j in range(4):
            O[i, j] = rx[i] * rx[j] + ry[i] * ry[j]


@numba.njit(cache=True, nogil=True)
def _null(M: F64, X: F64) -> None:
    """The eigenvector of ``M (4, 4)``'s smallest eigenvalue, dehomogenised, into ``X (3,)``."""
    w, V = eigh_jacobi(M)
    k = 0
    for i in range(1, 4):
        if w[i] < w[k]:
            k = i
    for i in range(3):
        X[i] = V[i, k] / V[3, k]


@numba.njit(cache=True, nogil=True)
def _inhomogeneous(M: F64, X: F64) -> None:
    """:func:`gt3dkit.geom.triangulate._inhomogeneous_point` of one ``M (4, 4)`` into ``X (3,)``."""
    a = M
    c0 = (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1], a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2],
          a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    c1 = (a[2, 1] * a[0, 2] - a[2, 2] * a[0, 1], a[2, 2] * a[0, 0] - a[2, 0] * a[0, 2],
          a[2, 0] * a[0, 1] - a[2, 1] * a[0, 0])
    c2 = (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1], a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2],
          a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0])
    det = a[0, 0] * c0[0] + a[0, 1] * c0[1] + a[0, 2] * c0[2]
    b0, b1, b2 = -a[0, 3], -a[1, 3], -a[2, 3]
    tr = a[0, 0] + a[1, 1] + a[2, 2]
    singular = det <= 1e-10 * tr**3
    for i in range(3):
        v = (c0[i] * b0 + c1[i] * b1 + c2[i] * b2) / det if det != 0.0 else np.nan
        X[i] = v if (np.isfinite(v) and not singular) else np.nan


@numba.njit(cache=True, nogil=True)
def _reproj(X: F64, xy: F64, Pc: F64, f: float, ds: float) -> float:
    """:func:`gt3dkit.geom.triangulate.reprojection_sq_px` of one point in one view (NaN where
    ``X`` or ``xy`` is, inf behind the camera)."""
    c0 = Pc[0, 0] * X[0] + Pc[0, 1] * X[1] + Pc[0, 2] * X[2] + Pc[0, 3]
    c1 = Pc[1, 0] * X[0] + Pc[1, 1] * X[1] + Pc[1, 2] * X[2] + Pc[1, 3]
    z = Pc[2, 0] * X[0] + Pc[2, 1] * X[1] + Pc[2, 2] * X[2] + Pc[2, 3]
    if not z * ds > 0:  # behind (or NaN)
        return np.inf
    d0 = c0 / z - xy[0]
    d1 = c1 / z - xy[1]
    return (d0 * d0 + d1 * d1) * f * f


@numba.njit(cache=True, nogil=True)
def _weighted(O: F64, w2: F64, X: F64) -> None:
    """The null point of ``sum_c w2[c] O[c]`` into ``X``; NaN where fewer than two ``w2 > 0``."""
    M = np.zeros((4, 4))
    n = 0
    for c in range(O.shape[0]):
        if w2[c] > 0:
            n += 1
            for i in range(4):
                for j in range(4):
                    M[i, j] += w2[c] * O[c, i, j]
    if n < 2:
        X[:] = np.nan
        return
    _null(M, X)


class Views(NamedTuple):
    """The points' views ``xy (N, C, 2)`` (normalised; NaN: not seen), their relative variances
    ``s (N, C)``, and the cameras: ``Pc (C, 3, 4)`` = ``[R | t]``, focal lengths ``f (C,)`` px and
    depth signs ``ds (C,)``."""

    xy: F64
    s: F64
    Pc: F64
    f: F64
    ds: F64


class Found(NamedTuple):
    """What :func:`robust_points` writes: the points ``X (N, 3)`` (NaN: under two inliers), the
    inliers ``inl (N, C)`` and the squared reprojection errors ``e2 (N, C)`` px^2 (inf: not seen)."""

    X: F64
    inl: np.ndarray
    e2: F64


@numba.njit(cache=True, nogil=True)
def robust_points(a: int, b: int, views: Views, thr2: float, pairs: I64, out: Found) -> None:
    """Points ``a..b-1`` of ``views`` (see :func:`gt3dkit.geom.triangulate.robust_triangulate`;
    ``thr2`` the squared threshold, ``pairs (P, 2)`` the two-view hypotheses' views) into ``out``."""
    xy, s, Pc, f, ds = views
    X, inl, e2 = out
    C = xy.shape[1]
    P = pairs.shape[0]
    O = np.zeros((C, 4, 4))
    sn = np.zeros(C, np.bool_)
    w2 = np.empty(C)
    cand = np.empty((P + 1, 3))
    M = np.empty((4, 4))
    best = np.empty(3)
    refit = np.empty(3)
    for n in range(a, b):
        for c in range(C):
            sn[c] = np.isfinite(xy[n, c, 0]) and np.isfinite(xy[n, c, 1])
            if sn[c]:
                _normal(xy[n, c], Pc[c], O[c])
            else:
                O[c, :, :] = 0.0
            w2[c] = 1.0 if sn[c] else 0.0
        _weighted(O, w2, cand[0])
        for p in range(P):
            i, j = pairs[p, 0], pairs[p, 1]
            if sn[i] and sn[j]:
                for u in range(4):
                    for v in range(4):
                        M[u, v] = O[i, u, v] + O[j, u, v]
                _inhomogeneous(M, cand[p + 1])
            else:
                cand[p + 1, :] = np.nan
        kbest = 0
        cbest = np.inf
        for k in range(P + 1):
            if not (np.isfinite(cand[k, 0]) and np.isfinite(cand[k, 1]) and np.isfinite(cand[k, 2])):
                continue
            cost = 0.0
            for c in range(C):
                if sn[c]:
                    e = _reproj(cand[k], xy[n, c], Pc[c], f[c], ds[c]) / s[n, c]
                    cost += min(e if not np.isnan(e) else np.inf, thr2)
            if cost < cbest:
                cbest = cost
                kbest = k
        best[:] = cand[kbest]
        for _ in range(2):
            for c in range(C):
                w2[c] = 0.0
                if sn[c]:
                    e = _reproj(best, xy[n, c], Pc[c], f[c], ds[c]) / s[n, c]
                    if (e if not np.isnan(e) else np.inf) < thr2:
                        w2[c] = 1.0 / s[n, c]
            _weighted(O, w2, refit)
            for i in range(3):
                if np.isfinite(refit[i]):
                    best[i] = refit[i]
        good = 0
        for c in range(C):
            inl[n, c] = False
            e2[n, c] = np.inf
            if sn[c]:
                e = _reproj(best, xy[n, c], Pc[c], f[c], ds[c])
                e2[n, c] = e
                q = e / s[n, c]
                if (q if not np.isnan(q) else np.inf) < thr2:
                    inl[n, c] = True
                    good += 1
        ok = good >= 2
        for i in range(3):
            X[n, i] = best[i] if ok else np.nan
        if not ok:
            for c in range(C):
                inl[n, c] = False


def robust_triangulate_compiled(xy_n: F64, R: F64, t: F64, f_px: F64, thr_px: float, s: F64,
                                depth_sign: F64, pairs: I64) -> tuple[F64, np.ndarray, F64]:
    """:func:`gt3dkit.geom.triangulate.robust_triangulate` with a finite threshold, compiled
    (arguments and results as there; ``s (N, C)`` the relative variances, ``pairs (P, 2)`` the
    two-view hypotheses' views)."""
    N, C = xy_n.shape[:2]
    c = np.ascontiguousarray
    Pc = c(np.concatenate([R, t[:, :, None]], axis=2), dtype=np.float64)
    out = Found(np.empty((N, 3)), np.zeros((N, C), np.bool_), np.empty((N, C)))
    views = Views(c(xy_n, dtype=np.float64), c(np.broadcast_to(s, (N, C)), dtype=np.float64), Pc,
                  c(f_px, dtype=np.float64), c(np.broadcast_to(depth_sign, (C,)), dtype=np.float64))
    pairs = c(pairs, dtype=np.int64).reshape(-1, 2)

    def part(a: int, b: int) -> None:
        robust_points(a, b, views, float(thr_px) ** 2, pairs, out)

    run_split(part, N, min_per_thread=2048)
    return out
