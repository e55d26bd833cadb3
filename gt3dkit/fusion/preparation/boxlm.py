r"""The per-frame Levenberg-Marquardt box fit of :func:`gt3dkit.fusion.preparation.boxfit.fit_boxes`,
compiled (numba): one object-frame at a time, start to convergence, in one loop.

Each object-frame's residuals are a few hundred flops per camera
(:func:`gt3dkit.geom.boxkernel.pair_box` inlined) and the 6 x 6 normal equations are solved in
place; object-frames are split over :func:`gt3dkit.threads.compiled_threads` threads. The
problem: whitened edge residuals plus the log-axes prior; the damping rule (``/5`` on a better
step, ``x10`` on a worse one); converged when a step moves no parameter by 1e-7. The Jacobian
is the tangent box's analytic one (:func:`gt3dkit.geom.boxkernel.pair_box_grad`). The tests hold
the minima to scipy's ``least_squares`` on the same residuals.

numba's cache is keyed by each file alone; :mod:`gt3dkit.geom.kernel_cache` drops every kernel
cache of the package when any kernel file changed (the tangent box and the small matrices are
compiled into these functions).
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.motion import SPACE
from gt3dkit.geom.boxkernel import EDGES, pair_box, pair_box_grad
from gt3dkit.geom.boxrig import BoxCameras, BoxRig, box_rig
from gt3dkit.geom.smallmat import solve_sym
from gt3dkit.threads import run_split
from gt3dkit.types import F64

_BIG = float(np.finfo(np.float64).max)
#: The fit's parameters: the centre (3), then the log semi-axes (3).
N_PARAMS = 2 * SPACE


class FitNoise(NamedTuple):
    """What whitens the residuals: each edge kind's sd ``sig (4,)`` (px), the log semi-axes'
    prior mean ``prior (3,)`` and sd ``prior_sd (3,)``."""

    sig: F64
    prior: F64
    prior_sd: F64


class FrameBoxes(NamedTuple):
    """One object-frame's boxes ``z (C, 4)``, its measured edges ``mask (C, 4)`` and the cameras
    with any edge ``use (C,)``."""

    z: F64
    mask: np.ndarray
    use: np.ndarray


class Scratch(NamedTuple):
    """Work arrays: one camera's boxes ``box (1, C, 4)`` and derivatives ``grad (4, 6)``."""

    box: F64
    grad: F64


@numba.njit(cache=True, nogil=True, inline="always")
def _finite(v: float) -> float:
    """``np.nan_to_num`` of one value: NaN -> 0, +-inf -> the largest float."""
    if np.isfinite(v):
        return v
    if np.isnan(v):
        return 0.0
    return _BIG if v > 0 else -_BIG


@numba.njit(cache=True, nogil=True)
def _residuals(q: F64, frame: FrameBoxes, noise: FitNoise, rig: BoxRig, scratch: Scratch, r: F64, J: F64,
               with_jac: bool) -> float:
    """Whitened residuals ``r (4 C + 3,)`` of the parameters ``q (6,)`` (centre, log axes) against
    one object-frame's boxes; returns the cost ``sum r^2`` (inf when a used edge has no box:
    behind the camera). ``with_jac``: also their Jacobian ``J (4 C + 3, 6)`` (the tangent box's
    analytic derivatives, :func:`gt3dkit.geom.boxkernel.pair_box_grad`, ~3x the cost; NaN -> 0
    as the numpy path); without, the values alone (a trial step)."""
    C = rig.cam.shape[0]
    zn, mn, use = frame
    sig, prior, prior_sd = noise
    box, grad = scratch
    centre = (q[0], q[1], q[2])
    la = (q[SPACE], q[SPACE + 1], q[SPACE + 2])
    s = (np.exp(2.0 * la[0]), np.exp(2.0 * la[1]), np.exp(2.0 * la[2]))
    cost = 0.0
    bad = False
    if with_jac:
        J[:, :] = 0.0
    for c in range(C):
        if not use[c]:
            for e in range(EDGES):
                r[EDGES * c + e] = 0.0
            continue
        if with_jac:
            pair_box_grad(centre, la, c, rig, box[0, c], grad)
        else:
            pair_box(centre, s, c, rig, True, box, 0)
        for e in range(EDGES):
            if mn[c, e]:
                v = (box[0, c, e] - zn[c, e]) / sig[e]
                if not np.isfinite(v):
                    v = np.nan
                    bad = True
                r[EDGES * c + e] = v
                cost += v * v
                if with_jac:
                    for j in range(N_PARAMS):
                        J[EDGES * c + e, j] = _finite(grad[e, j] / sig[e])
            else:
                r[EDGES * c + e] = 0.0
    for i in range(SPACE):
        v = (la[i] - prior[i]) / prior_sd[i]
        r[EDGES * C + i] = v
        cost += v * v
        if with_jac:
            J[EDGES * C + i, SPACE + i] = 1.0 / prior_sd[i]
    if bad or not np.isfinite(cost):
        return np.inf
    return cost


@numba.njit(cache=True, nogil=True)
def fit_rows(p: F64, z: F64, mask: np.ndarray, active: np.ndarray, noise: FitNoise, iters: int,
             cams: BoxCameras,
             r_out: F64, J_out: F64) -> None:
    """LM fits of the object-frames ``p (N, 6)`` (start in, result out) to ``z (N, C, 4)`` (edges
    ``mask``), those with ``active`` only; ``r_out (N, 4 C + 3)`` the residuals at the result
    (all rows) and ``J_out (N, 4 C + 3, 6)`` their Jacobian (analytic, NaN -> 0)."""
    N, C = z.shape[0], cams.K.shape[0]
    M = EDGES * C + SPACE
    rig = box_rig(cams, 2)
    scratch = Scratch(np.empty((1, C, EDGES)), np.empty((EDGES, N_PARAMS)))
    r = np.empty(M)
    r3 = np.empty(M)
    J = np.empty((M, N_PARAMS))
    A = np.empty((N_PARAMS, N_PARAMS))
    g = np.empty((N_PARAMS, 1))
    dl = np.empty((N_PARAMS, 1))
    q = np.empty(N_PARAMS)
    use = np.empty(C, np.bool_)
    for n in range(N):
        mn = mask[n]
        for c in range(C):
            use[c] = mn[c, 0] or mn[c, 1] or mn[c, 2] or mn[c, 3]
        frame = FrameBoxes(z[n], mn, use)
        cost = _residuals(p[n], frame, noise, rig, scratch, r, J, True)
        lam = 1e-3
        if active[n]:
            stale = False  # r and J are of an older point than p[n]
            for _ in range(iters):
                for i in range(N_PARAMS):
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
                for i in range(N_PARAMS):
                    A[i, i] += lam * A[i, i] + 1e-12
                solve_sym(A, g, dl)
                big = 0.0
                for j in range(N_PARAMS):
                    q[j] = p[n, j] - dl[j, 0]
                    big = max(big, abs(dl[j, 0]))
                c_new = _residuals(q, frame, noise, rig, scratch, r3, J, False)
                better = c_new < cost
                if better:
                    for j in range(N_PARAMS):
                        p[n, j] = q[j]
                    cost = c_new
                    lam = max(lam / 5.0, 1e-9)
                    stale = True
                else:
                    lam *= 10.0
                if (better and big < 1e-7) or lam > 1e8 or not np.isfinite(big):
                    break
                if better:  # the residuals and Jacobian at the new point
                    _residuals(p[n], frame, noise, rig, scratch, r, J, True)
                    stale = False
            if stale:  # the loop ended on an accepted step
                _residuals(p[n], frame, noise, rig, scratch, r, J, True)
        for m in range(M):
            r_out[n, m] = r[m]
            for i in range(N_PARAMS):
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
    r = np.empty((N, EDGES * C + SPACE))
    J = np.empty((N, EDGES * C + SPACE, N_PARAMS))
    noise = FitNoise(*(contiguous(np.broadcast_to(np.asarray(a, dtype=np.float64), (k,)))
                       for a, k in ((sig, EDGES), (prior, SPACE), (prior_sd, SPACE))))

    def part(a: int, b: int) -> None:
        fit_rows(p[a:b], zc[a:b], mc[a:b], ac[a:b], noise, int(iters), cams, r[a:b], J[a:b])

    run_split(part, N, MIN_ROWS_PER_THREAD)
    return p, r, J
