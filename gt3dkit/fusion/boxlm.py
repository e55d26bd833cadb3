r"""The per-frame Levenberg-Marquardt box fit of :func:`gt3dkit.fusion.boxfit.fit_boxes`,
compiled (numba): one object-frame at a time, start to convergence, in one loop.

The numpy formulation in :func:`gt3dkit.fusion.boxfit.fit_boxes` (``compiled=False``) is the
reference, and the tests hold this one to it. Batched over all object-frames in numpy, each LM
iteration is ~15 whole-array calls around 7 tangent-box calls (the residuals and a
forward-difference Jacobian) on the still active rows; on the 400-frame x 40-person benchmark
scene those calls cost twice the tangent boxes themselves. Here each object-frame's residuals
are a few hundred flops per camera (:func:`gt3dkit.geom.boxkernel.pair_box` inlined) and the
6 x 6 normal equations are solved in place; object-frames are split over
:func:`gt3dkit.threads.compiled_threads` threads.

The same least-squares problem as the reference: whitened edge residuals plus the log-axes
prior, the damping rule (``/5`` on a better step, ``x10`` on a worse one), the same convergence
test. Two differences: the Jacobian is the tangent box's analytic one
(:func:`gt3dkit.geom.boxkernel.pair_box_grad`; the reference differentiates numerically: six
extra tangent boxes per step and twelve for the final covariance), and the 6 x 6 damped system
is solved by Cholesky (numpy: LU). The paths differ by rounding; the minima agree to the
convergence tolerance where the problem is well posed (two views or more).

numba's cache is keyed by each file alone; :mod:`gt3dkit.geom.kernel_cache` drops every kernel
cache of the package when any kernel file changed (the tangent box and the small matrices are
compiled into these functions).
"""

from __future__ import annotations

import numba
import numpy as np

from gt3dkit.geom.boxkernel import BoxCameras, camera_setup, contiguous, pair_box, pair_box_grad
from gt3dkit.geom.smallmat import solve_sym
from gt3dkit.threads import run_split
from gt3dkit.types import F64

_BIG = float(np.finfo(np.float64).max)


@numba.njit(cache=True, nogil=True, inline="always")
def _finite(v: float) -> float:
    """``np.nan_to_num`` of one value: NaN -> 0, +-inf -> the largest float."""
    if np.isfinite(v):
        return v
    if np.isnan(v):
        return 0.0
    return _BIG if v > 0 else -_BIG


@numba.njit(cache=True, nogil=True)
def _residuals(q: F64, zn: F64, mn: np.ndarray, use: np.ndarray, sig: F64, prior: F64, prior_sd: F64,
               Rc: F64, gx: F64, gy: F64, K: F64, dist: F64, R: F64, t: F64, ds: F64, steps: int,
               box: F64, grad: F64, r: F64, J: F64, with_jac: bool) -> float:
    """Whitened residuals ``r (4 C + 3,)`` of the parameters ``q (6,)`` (centre, log axes) against
    one object-frame's boxes ``zn (C, 4)`` (edges ``mn``; cameras ``use`` with any edge); returns
    the cost ``sum r^2`` (inf when a used edge has no box: behind the camera). ``with_jac``: also
    their Jacobian ``J (4 C + 3, 6)`` (the tangent box's analytic derivatives,
    :func:`gt3dkit.geom.boxkernel.pair_box_grad`, ~3x the cost; NaN -> 0 as the numpy path);
    without, the values alone (a trial step). ``box (1, C, 4)``, ``grad (4, 6)``: scratch."""
    C = K.shape[0]
    s0, s1, s2 = np.exp(2.0 * q[3]), np.exp(2.0 * q[4]), np.exp(2.0 * q[5])
    cost = 0.0
    bad = False
    if with_jac:
        J[:, :] = 0.0
    for c in range(C):
        if not use[c]:
            for e in range(4):
                r[4 * c + e] = 0.0
            continue
        if with_jac:
            pair_box_grad(q[0], q[1], q[2], q[3], q[4], q[5], c, Rc, gx, gy, K, dist, R, t, ds, steps,
                          box[0, c], grad)
        else:
            pair_box(q[0], q[1], q[2], s0, s1, s2, c, Rc, gx, gy, K, dist, R, t, ds, steps, True, box, 0)
        for e in range(4):
            if mn[c, e]:
                v = (box[0, c, e] - zn[c, e]) / sig[e]
                if not np.isfinite(v):
                    v = np.nan
                    bad = True
                r[4 * c + e] = v
                cost += v * v
                if with_jac:
                    for j in range(6):
                        J[4 * c + e, j] = _finite(grad[e, j] / sig[e])
            else:
                r[4 * c + e] = 0.0
    for i in range(3):
        v = (q[3 + i] - prior[i]) / prior_sd[i]
        r[4 * C + i] = v
        cost += v * v
        if with_jac:
            J[4 * C + i, 3 + i] = 1.0 / prior_sd[i]
    if bad or not np.isfinite(cost):
        return np.inf
    return cost


@numba.njit(cache=True, nogil=True)
def fit_rows(p: F64, z: F64, mask: np.ndarray, active: np.ndarray, sig: F64, prior: F64, prior_sd: F64,
             iters: int, Rb: F64, K: F64, dist: F64, R: F64, t: F64, ds: F64, steps: int,
             r_out: F64, J_out: F64) -> None:
    """LM fits of the object-frames ``p (N, 6)`` (start in, result out) to ``z (N, C, 4)`` (edges
    ``mask``), those with ``active`` only; ``r_out (N, 4 C + 3)`` the residuals at the result
    (all rows) and ``J_out (N, 4 C + 3, 6)`` their Jacobian (analytic, NaN -> 0)."""
    N, C = z.shape[0], K.shape[0]
    M = 4 * C + 3
    Rc, gx, gy = camera_setup(Rb, K, R)
    box = np.empty((1, C, 4))
    grad = np.empty((4, 6))
    r = np.empty(M)
    r3 = np.empty(M)
    J = np.empty((M, 6))
    A = np.empty((6, 6))
    g = np.empty((6, 1))
    dl = np.empty((6, 1))
    q = np.empty(6)
    use = np.empty(C, np.bool_)
    for n in range(N):
        zn, mn = z[n], mask[n]
        for c in range(C):
            use[c] = mn[c, 0] or mn[c, 1] or mn[c, 2] or mn[c, 3]
        cost = _residuals(p[n], zn, mn, use, sig, prior, prior_sd, Rc, gx, gy, K, dist, R, t, ds, steps, box,
                          grad, r, J, True)
        lam = 1e-3
        if active[n]:
            stale = False  # r and J are of an older point than p[n]
            for _ in range(iters):
                for i in range(6):
                    s = 0.0
                    for m in range(M):
                        rm = r[m] if np.isfinite(r[m]) else 0.0
                        s += J[m, i] * rm
                    g[i, 0] = s
                    for j in range(i + 1):
                        s = 0.0
                        for m in range(M):
                            s += J[m, i] * J[m, j]
                        A[i, j] = s
                        A[j, i] = s
                for i in range(6):
                    A[i, i] += lam * A[i, i] + 1e-12
                solve_sym(A, g, dl)
                big = 0.0
                for j in range(6):
                    q[j] = p[n, j] - dl[j, 0]
                    big = max(big, abs(dl[j, 0]))
                c_new = _residuals(q, zn, mn, use, sig, prior, prior_sd, Rc, gx, gy, K, dist, R, t, ds,
                                   steps, box, grad, r3, J, False)
                better = c_new < cost
                if better:
                    for j in range(6):
                        p[n, j] = q[j]
                    cost = c_new
                    lam = max(lam / 5.0, 1e-9)
                    stale = True
                else:
                    lam *= 10.0
                if (better and big < 1e-7) or lam > 1e8 or not np.isfinite(big):
                    break
                if better:  # the residuals and Jacobian at the new point
                    _residuals(p[n], zn, mn, use, sig, prior, prior_sd, Rc, gx, gy, K, dist, R, t, ds,
                               steps, box, grad, r, J, True)
                    stale = False
            if stale:  # the loop ended on an accepted step
                _residuals(p[n], zn, mn, use, sig, prior, prior_sd, Rc, gx, gy, K, dist, R, t, ds, steps,
                           box, grad, r, J, True)
        for m in range(M):
            r_out[n, m] = r[m]
            for i in range(6):
                J_out[n, m, i] = J[m, i]


#: object-frames per thread below which a fit is not split (one is ~50-200 us)
MIN_ROWS_PER_THREAD = 16


def fit_compiled(p0: F64, z: F64, mask: np.ndarray, active: np.ndarray, sig: F64, prior: F64,
                 prior_sd: F64, iters: int, cams: BoxCameras) -> tuple[F64, F64, F64]:
    """Run :func:`fit_rows` on ``N`` object-frames split over threads: the fitted parameters
    ``(N, 6)``, residuals ``(N, 4 C + 3)`` and Jacobian ``(N, 4 C + 3, 6)``."""
    N, C = z.shape[:2]
    p = contiguous(p0.copy())
    zc, mc, ac = contiguous(z), contiguous(mask, np.bool_), contiguous(active, np.bool_)
    r = np.empty((N, 4 * C + 3))
    J = np.empty((N, 4 * C + 3, 6))
    sg, pr, ps = (contiguous(np.broadcast_to(np.asarray(a, dtype=np.float64), (k,)))
                  for a, k in ((sig, 4), (prior, 3), (prior_sd, 3)))

    def part(a: int, b: int) -> None:
        fit_rows(p[a:b], zc[a:b], mc[a:b], ac[a:b], sg, pr, ps, int(iters), cams.world_from_body,
                 cams.K, cams.dist, cams.R, cams.t, cams.depth_sign, 2, r[a:b], J[a:b])

    run_split(part, N, MIN_ROWS_PER_THREAD)
    return p, r, J
