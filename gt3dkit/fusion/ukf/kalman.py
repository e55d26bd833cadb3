r"""The linear steps of the filter, each written once and compiled: prediction, the RTS step,
fading a prediction the frame's own views contradict, and moving the linearisation point of
the ellipsoid to the frame's own fit. The compiled filter (:mod:`gt3dkit.fusion.ukf.boxupdate`)
calls the row functions; the filter over frames (:mod:`gt3dkit.fusion.ukf.smoother`) and
:class:`gt3dkit.fusion.ukf.measurement.Model` call their batched forms.

References: Rauch, Tung & Striebel, AIAA J. 3 (1965) (the smoother); Särkkä, "Unscented
Rauch-Tung-Striebel smoother", IEEE TAC 2008 (with a linear motion model the unscented RTS gain
is the linear one, ``P_k F^T (P^-_{k+1})^{-1}``); Fagin, "Recursive linear regression theory,
optimal filter theory, and error analyses of optimal systems", IEEE Int. Conv. Rec. 1964
(fading memory).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.motion import SPACE, StateIndex
from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.geom.smallmat import matmul, matmul_sparse_left, solve_sym
from gt3dkit.types import F64, I64

drop_stale()  # before any compiled function below is called (and its cache read)


@numba.njit(cache=True, nogil=True)
def predict_row(x: F64, P: F64, F: F64, Q: F64, x_out: F64, P_out: F64) -> None:
    """``x_out = F x (n,)``, ``P_out = F P F^T + Q (n, n)``, symmetrised. ``F`` is sparse (constant
    velocity: two entries per row at most): both products skip its zeros, ``O(n^2)`` instead of
    ``O(n^3)``; the second as ``Pt = F (F P)^T = (F P F^T)^T``, whose transposed entries the
    symmetrisation adds in the other order (the same bits as the dense ``F P F^T``)."""
    n = x.shape[0]
    FP = np.empty((n, n))
    Pt = np.empty((n, n))
    matmul_sparse_left(F, P, FP)
    matmul_sparse_left(F, FP.T, Pt)
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += F[i, j] * x[j]
        x_out[i] = s
    for i in range(n):
        for j in range(n):
            P_out[i, j] = 0.5 * ((Pt[j, i] + Q[i, j]) + (Pt[i, j] + Q[j, i]))


@numba.njit(cache=True, nogil=True)
def predict_rows(x: F64, P: F64, F: F64, Q: F64, x_out: F64, P_out: F64) -> None:
    """:func:`predict_row` of every row ``b`` of ``x (B, n)``, ``P, F, Q (B, n, n)``."""
    for b in range(x.shape[0]):
        predict_row(x[b], P[b], F[b], Q[b], x_out[b], P_out[b])


@numba.njit(cache=True, nogil=True)
def rts_row(x_f: F64, P_f: F64, x_p: F64, P_p: F64, x_s: F64, P_s: F64, F: F64, x_out: F64,
            P_out: F64) -> None:
    r"""One backward RTS step: from the filtered ``x_f, P_f`` of a row, the next row's prediction
    ``x_p, P_p`` and smoothed ``x_s, P_s``, with ``F`` between them:

    .. math::
        G = P_f F^\top (P^-)^{-1},\quad x_{out} = x_f + G (x_s - x^-),\quad
        P_{out} = P_f + G (P_s - P^-) G^\top \text{ (symmetrised)}.

    ``x_out, P_out`` may be ``x_f, P_f`` themselves."""
    n = x_f.shape[0]
    FPt = np.empty((n, n))
    Gt = np.empty((n, n))
    D = np.empty((n, n))
    GD = np.empty((n, n))
    GDG = np.empty((n, n))
    matmul_sparse_left(F, P_f, FPt)  # (P F^T)^T = F P
    solve_sym(P_p, FPt, Gt)  # G^T = P_p^-1 (P F^T)^T
    for i in range(n):
        for j in range(n):
            D[i, j] = P_s[i, j] - P_p[i, j]
    matmul(Gt.T, D, GD)
    matmul(GD, Gt, GDG)
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += Gt[j, i] * (x_s[j] - x_p[j])
        x_out[i] = x_f[i] + s
    for i in range(n):
        for j in range(n):
            P_out[i, j] = P_f[i, j] + 0.5 * (GDG[i, j] + GDG[j, i])


@numba.njit(cache=True, nogil=True)
def rts_rows(x_f: F64, P_f: F64, x_p: F64, P_p: F64, x_s: F64, P_s: F64, F: F64, x_out: F64,
             P_out: F64) -> None:
    """:func:`rts_row` of every row of a batch (means ``(B, n)``, matrices ``(B, n, n)``)."""
    for b in range(x_f.shape[0]):
        rts_row(x_f[b], P_f[b], x_p[b], P_p[b], x_s[b], P_s[b], F[b], x_out[b], P_out[b])


@numba.njit(cache=True, nogil=True)
def fade_factor(e: F64, S: F64, limit: float) -> float:
    r"""The fading factor of a point predicted ``e (3,)`` away from where the frame's own views
    put it, with ``S (3, 3)`` the sum of both covariances: ``sqrt(1 + (d^2 - limit) / 3)`` where
    ``d^2 = e^T S^{-1} e`` exceeds ``limit`` (a chi-square(3) quantile), else 1 (also where
    ``e`` or ``S`` is not finite). Continuous in ``d^2``: the covariance grows by the excess over
    the limit per degree of freedom (as ``d^2 / 3`` far beyond it), so two nearly equal
    predictions fade nearly alike (a factor jumping from 1 to ``sqrt(limit / 3)`` = 2.3 at the
    limit made the estimate jump with it: the windows of a long sequence and its whole run,
    whose predictions differ by a hair, then differed by up to 3.9 of their sd)."""
    if not (np.all(np.isfinite(S)) and np.all(np.isfinite(e))):
        return 1.0
    Se = np.empty((SPACE, 1))
    solve_sym(S, e.reshape(SPACE, 1), Se)
    d2 = 0.0
    for i in range(SPACE):
        d2 += e[i] * Se[i, 0]
    return math.sqrt(1.0 + (d2 - limit) / SPACE) if d2 > limit else 1.0


@numba.njit(cache=True, nogil=True)
def fade_factors(e: F64, S: F64, limit: float, out: F64) -> None:
    """:func:`fade_factor` of each point of ``e (K, 3)``, ``S (K, 3, 3)`` into ``out (K,)``."""
    for k in range(e.shape[0]):
        out[k] = fade_factor(e[k], S[k], limit)


def fade_factors_of(e: F64, S: F64, limit: float) -> F64:
    """:func:`fade_factor` of points ``e (..., 3)`` with ``S (..., 3, 3)``: ``(...)``."""
    shape = e.shape[:-1]
    out = np.empty(int(np.prod(shape)))
    fade_factors(contiguous(e.reshape(-1, SPACE)), contiguous(S.reshape(-1, SPACE, SPACE)), float(limit), out)
    return out.reshape(shape)


@numba.njit(cache=True, nogil=True)
def fade_centre(P: F64, f: float, ix: StateIndex) -> None:
    """``P <- S P S`` in place with ``S`` = ``f`` on the centre and its velocity, 1 elsewhere."""
    n = ix.n
    for i in range(n):
        si = f if (ix.centre <= i < ix.centre + SPACE or ix.velocity <= i < ix.velocity + SPACE) else 1.0
        for j in range(n):
            sj = f if (ix.centre <= j < ix.centre + SPACE or ix.velocity <= j < ix.velocity + SPACE) else 1.0
            P[i, j] *= si * sj


@numba.njit(cache=True, nogil=True)
def ellipsoid_linearisation(x: F64, P: F64, x_frame: F64, cov_frame: F64, frame_trace: float,
                            dims: I64, ix: StateIndex, x_l: F64, P_l: F64) -> bool:
    """Where a row's update linearises the ellipsoid: ``x_l, P_l`` = the prior ``x, P``, except
    where the prior's centre
    trace exceeds the frame's own fit's ``frame_trace``: then the ellipsoid entries ``dims (6,)``
    are the fit's ``x_frame (n,)`` with its covariance ``cov_frame (6, 6)``, decorrelated from
    the rest. Returns whether it moved."""
    x_l[:] = x
    P_l[:, :] = P
    tr = 0.0
    for i in range(SPACE):
        tr += P[ix.centre + i, ix.centre + i]
    if not tr > frame_trace:
        return False
    n = ix.n
    for a in range(dims.shape[0]):
        x_l[dims[a]] = x_frame[dims[a]]
        for j in range(n):
            P_l[dims[a], j] = 0.0
            P_l[j, dims[a]] = 0.0
    for a in range(dims.shape[0]):
        for b in range(dims.shape[0]):
            P_l[dims[a], dims[b]] = cov_frame[a, b]
    return True


@numba.njit(cache=True, nogil=True)
def ellipsoid_linearisations(x: F64, P: F64, x_frame: F64, cov_frame: F64, frame_trace: F64, dims: I64,
                             ix: StateIndex, x_l: F64, P_l: F64, moved: np.ndarray) -> None:
    """:func:`ellipsoid_linearisation` of every row of a batch."""
    for b in range(x.shape[0]):
        moved[b] = ellipsoid_linearisation(x[b], P[b], x_frame[b], cov_frame[b], frame_trace[b], dims, ix,
                                           x_l[b], P_l[b])
