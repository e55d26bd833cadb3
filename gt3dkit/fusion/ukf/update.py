r"""The iterated, robust information-form update of one row, written once and compiled.

A pass takes a row's measurements linearised about ``(x_j, P_j)`` (a :class:`Regression`:
``z ~ A x + b + e``, ``e ~ N(0, D)``, ``D`` = noise + the linearisation error's diagonal) and
updates the prior ``N(x, P)`` in state space:

.. math::
    P^+ = (P^{-1} + A^\top W D^{-1} A)^{-1},\quad
    x^+ = x + P^+ A^\top W D^{-1} (z - A x - b),

``W`` a weight per entry. Robust (iteratively reweighted): after every pass but the last, each
measurement point's leave-one-out score against the new posterior gives its weight
(:func:`gt3dkit.fusion.preparation.robust.point_weight`, the one rule every estimator's weights follow).
A row stops iterating once a pass's posterior is where it linearised and no weight changes.
The statistics (normalised innovation square, its degrees of freedom, log-likelihood) are of the
last pass with its weights, by the matrix determinant lemma (no ``m x m`` matrix).

Which state entries each group of measurement columns depends on is a :class:`Columns` (a box:
the centre and log semi-axes; a joint's projections: the joint; a bone: its two joints), so one
implementation serves every measurement model; the regression itself is the measurement model's
(:mod:`gt3dkit.fusion.ukf.boxupdate` for boxes, the reference ``block_regression``
(``tests/oracles_frames.py``) for the
others). The compiled filter calls :func:`pass_row` per row, the filter over frames
:func:`pass_rows` per batch.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

from gt3dkit.arrays import contiguous
from gt3dkit.fusion.preparation.robust import point_weight
from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.geom.smallmat import chol, chol_solve, lower_inverse, safe_chol, solve_sym, symmetrised
from gt3dkit.types import F64, I64

drop_stale()  # before any compiled function below is called (and its cache read)

_LOG_2PI = math.log(2.0 * math.pi)
#: A pass whose posterior moved less than this (squared, in posterior sds) from where it
#: linearised, and whose spread changed by less than ``SPREAD_TOL``, has converged.
STEP_TOL2 = 1e-4
SPREAD_TOL = 1e-3


class Columns(NamedTuple):
    """The structure of the measurement vector (``m`` columns), the same for every row.

    dims : (G, d) the state entries of each group of columns (-1: padding)
    first : (m,) the first column of the column's point (robust reweighting)
    size : (m,) the entries of the column's point; 0: never reweighted
    c_thr, g_thr : (m,) the point's down-weighting and rejection thresholds on its score
    order, start, width : the columns by group: group ``g`` is the columns
        ``order[start[g]:start[g + 1]]``, which all depend on the ``width[g]`` entries
        ``dims[g]`` (a box on the ellipsoid, a joint's projections on the joint, a bone on its
        two joints)
    """

    dims: I64
    first: I64
    size: I64
    c_thr: F64
    g_thr: F64
    order: I64
    start: I64
    width: I64


class Measured(NamedTuple):
    """Rows' measurements ``z``, which are present ``mask`` and their variances ``var``: ``(R,
    m)`` each, or ``(m,)`` for one row."""

    z: F64
    mask: np.ndarray
    var: F64


class Regression(NamedTuple):
    """One row's measurements linearised: ``used (m,)`` (measured, and finite at every sigma
    point), ``At (m, d)`` each column's row of ``A`` over its ``dims``, ``c (m,)`` = ``z - b``,
    ``D (m,)`` the noise plus linearisation error."""

    used: np.ndarray
    At: F64
    c: F64
    D: F64


class Prior(NamedTuple):
    """The prior mean ``x (n,)``, its covariance's inverse ``Pinv`` and Cholesky factor ``LP``."""

    x: F64
    Pinv: F64
    LP: F64


class Current(NamedTuple):
    """Where a pass linearises, ``xj (n,)``, ``Pj (n, n)``, the weights it uses ``wt (m,)`` and the
    next pass's ``new_w (m,)``."""

    xj: F64
    Pj: F64
    wt: F64
    new_w: F64


class Posterior(NamedTuple):
    """A pass's result ``x (n,)``, ``P (n, n)``, its information ``J`` with factor ``L`` and
    information vector ``g``; each column's weighted information ``Dinv (m,)`` and innovation
    against the prior ``nu (m,)``."""

    x: F64
    P: F64
    J: F64
    L: F64
    g: F64
    Dinv: F64
    nu: F64


class Scores(NamedTuple):
    """Each column's residual at the posterior ``resid (m,)`` and its point's squared
    leave-one-out score ``score2 (m,)``."""

    resid: F64
    score2: F64


@numba.njit(cache=True, nogil=True)
def prior_factor(P: F64, LP: F64, Pinv: F64) -> None:
    """The prior covariance ``P (n, n)``'s Cholesky factor ``LP`` (for its log-determinant) and
    inverse ``Pinv``, from one factorisation (where not positive definite: the inverse of the
    matrix itself, and the factor repaired; repairs of the prior are not counted)."""
    n = P.shape[0]
    Psym = symmetrised(P)
    if chol(Psym, LP):
        chol_solve(LP, np.eye(n), Pinv)
    else:
        solve_sym(Psym, np.eye(n), Pinv)
        safe_chol(Psym, LP)


@numba.njit(cache=True, nogil=True)
def information_pass(prior: Prior, lin: Regression, cols: Columns, wt: F64, post: Posterior) -> int:
    """The information update of ``prior`` by the linearised columns with weights ``wt`` into
    ``post``. Returns 1 if the information's factor needed a repair."""
    n = prior.x.shape[0]
    d = cols.dims.shape[1]
    J, g = post.J, post.g
    for i in range(n):
        g[i] = 0.0
        for j in range(n):
            J[i, j] = prior.Pinv[i, j]
    H = np.empty((d, d))
    gv = np.empty(d)
    for q in range(cols.start.shape[0] - 1):  # a group's columns share their state entries
        w = cols.width[q]
        dq = cols.dims[q]
        H[:w, :w] = 0.0
        gv[:w] = 0.0
        for k in cols.order[cols.start[q]:cols.start[q + 1]]:
            if not lin.used[k]:
                post.Dinv[k] = 0.0
                post.nu[k] = 0.0
                continue
            dk = wt[k] / lin.D[k]
            v = lin.c[k]
            for a in range(w):
                v -= lin.At[k, a] * prior.x[dq[a]]
            post.Dinv[k] = dk
            post.nu[k] = v
            for a in range(w):
                h = lin.At[k, a] * dk
                gv[a] += h * v
                for b in range(w):
                    H[a, b] += h * lin.At[k, b]
        for a in range(w):
            g[dq[a]] += gv[a]
            for b in range(w):
                J[dq[a], dq[b]] += H[a, b]
    repaired = safe_chol(J, post.L)
    Li = np.empty((n, n))
    lower_inverse(post.L, Li)
    P = post.P  # P = Li^T Li, rows of Li at a time (each entry's sum over k in order)
    P[:, :] = 0.0
    for k in range(n):
        for i in range(k + 1):
            lki = Li[k, i]
            for j in range(k + 1):
                P[i, j] += lki * Li[k, j]
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += post.P[i, j] * g[j]
        post.x[i] = prior.x[i] + s
    return repaired


@numba.njit(cache=True, nogil=True)
def converged(post: Posterior, xj: F64, Pj: F64) -> bool:
    """The posterior is where the pass linearised (``|L^T (x^+ - x_j)|^2 < STEP_TOL2``) with the
    same spread (trace ratio within ``SPREAD_TOL`` of 1): a further pass would repeat it."""
    n = xj.shape[0]
    q = 0.0
    for i in range(n):
        s = 0.0
        for j in range(n):
            s += post.L[j, i] * (post.x[j] - xj[j])
        q += s * s
    tp, tj = 0.0, 0.0
    for i in range(n):
        tp += post.P[i, i]
        tj += Pj[i, i]
    return q < STEP_TOL2 and abs(tp / tj - 1.0) < SPREAD_TOL


@numba.njit(cache=True, nogil=True)
def rescore(post: Posterior, lin: Regression, cols: Columns, cur: Current, scores: Scores) -> bool:
    """Each used column's residual at the posterior and leave-one-out score (summed over its
    point), and in ``cur.new_w`` the weight its point's score gives (a column not reweighted, or
    not used, keeps its weight). Returns whether a weight changed."""
    m = lin.c.shape[0]
    d = cols.dims.shape[1]
    e2 = np.zeros(m)
    Pq = np.empty((d, d))
    for q in range(cols.start.shape[0] - 1):
        w = cols.width[q]
        dq = cols.dims[q]
        for a in range(w):
            for b in range(w):
                Pq[a, b] = post.P[dq[a], dq[b]]
        for k in cols.order[cols.start[q]:cols.start[q + 1]]:
            scores.resid[k] = 0.0
            scores.score2[k] = 0.0
            if not lin.used[k]:
                continue
            r = lin.c[k]
            pk = 0.0
            for a in range(w):
                r -= lin.At[k, a] * post.x[dq[a]]
                s = 0.0
                for b in range(w):
                    s += Pq[a, b] * lin.At[k, b]
                pk += lin.At[k, a] * s
            scores.resid[k] = r
            h = min(max(cur.wt[k] * pk / max(lin.D[k], 1e-300), 0.0), 1.0 - 1e-9)
            rl = r / (1.0 - h)
            e2[k] = rl * rl / (lin.D[k] + pk / (1.0 - h))
    changed = False
    for k in range(m):
        cur.new_w[k] = cur.wt[k]
        if cols.size[k] == 0:
            continue
        s = 0.0
        for q in range(cols.first[k], cols.first[k] + cols.size[k]):
            s += e2[q]
        scores.score2[k] = s
        if lin.used[k]:
            w = point_weight(s, cols.c_thr[k], cols.g_thr[k])
            if w != cur.wt[k]:
                cur.new_w[k] = w
                changed = True
    return changed


@numba.njit(cache=True, nogil=True)
def pass_row(it: int, last: bool, robust: bool, prior: Prior, lin: Regression, cols: Columns, cur: Current,
             post: Posterior, scores: Scores) -> tuple[bool, int]:
    """Pass ``it`` of a row's iterated update: the information update, then (``robust``) the
    scores and the next weights. Returns whether the row is done (``last``, or converged with
    no weight changed) and the factor repairs; when not done, ``cur`` holds the next pass's
    linearisation point and weights."""
    repaired = information_pass(prior, lin, cols, cur.wt, post)
    done = it > 0 and converged(post, cur.xj, cur.Pj)
    if robust:
        changed = rescore(post, lin, cols, cur, scores)
        if not last:
            done = done and not changed
            if not done:
                cur.wt[:] = cur.new_w
    done = done or last
    if not done:
        cur.xj[:] = post.x
        cur.Pj[:, :] = post.P
    return done, repaired


@numba.njit(cache=True, nogil=True)
def statistics(prior: Prior, lin: Regression, wt: F64, post: Posterior) -> tuple[float, int, float]:
    """The normalised innovation square, its degrees of freedom and the log-likelihood of the
    last pass with its weights (noise ``D / w`` for the kept entries: what the estimate rests
    on)."""
    n = post.L.shape[0]
    logdet = 0.0
    dof = 0
    quad = 0.0
    for k in range(lin.c.shape[0]):
        if lin.used[k] and wt[k] > 0:
            logdet += math.log(lin.D[k] / wt[k])
            dof += 1
        quad += post.nu[k] * post.nu[k] * post.Dinv[k]
    for i in range(n):
        logdet += 2.0 * math.log(post.L[i, i]) + 2.0 * math.log(prior.LP[i, i])
        s = 0.0
        for j in range(n):
            s += post.P[i, j] * post.g[j]
        quad -= post.g[i] * s
    return quad, dof, -0.5 * (quad + logdet + dof * _LOG_2PI)


class RowState(NamedTuple):
    """A batch's priors, linearisation points, weights and posteriors (``B`` rows; the
    per-row forms of :class:`Prior`, :class:`Current`, :class:`Posterior`, :class:`Scores`)."""

    x: F64
    Pinv: F64
    LP: F64
    xj: F64
    Pj: F64
    wt: F64
    new_w: F64
    post: Posterior
    scores: Scores


def row_state(x: F64, P: F64, xj: F64, Pj: F64, wt: F64) -> RowState:
    """The work arrays of a batch's update, its priors factored (:func:`prior_factor`)."""
    B, n = x.shape
    m = wt.shape[1]
    Pinv, LP = np.empty((B, n, n)), np.empty((B, n, n))
    prior_factors(contiguous(P), LP, Pinv)
    post = Posterior(np.empty((B, n)), np.empty((B, n, n)), np.empty((B, n, n)), np.empty((B, n, n)),
                     np.empty((B, n)), np.zeros((B, m)), np.zeros((B, m)))
    return RowState(contiguous(x), Pinv, LP, np.array(xj, dtype=np.float64),
                    np.array(Pj, dtype=np.float64), np.array(wt, dtype=np.float64), np.empty((B, m)), post,
                    Scores(np.zeros((B, m)), np.zeros((B, m))))


@numba.njit(cache=True, nogil=True)
def prior_factors(P: F64, LP: F64, Pinv: F64) -> None:
    """:func:`prior_factor` of every row of ``P (B, n, n)``."""
    for b in range(P.shape[0]):
        prior_factor(P[b], LP[b], Pinv[b])


@numba.njit(cache=True, nogil=True)
def pass_rows(rows: I64, it: int, last: bool, robust: bool, lin: Regression, cols: Columns, st: RowState,
              done: np.ndarray, repaired: I64) -> None:
    """:func:`pass_row` of the batch rows ``rows`` (``lin``: ``(B, ...)`` arrays): ``done``,
    ``repaired (B,)`` updated."""
    p = st.post
    for b in rows:
        d, r = pass_row(it, last, robust, Prior(st.x[b], st.Pinv[b], st.LP[b]),
                        Regression(lin.used[b], lin.At[b], lin.c[b], lin.D[b]), cols,
                        Current(st.xj[b], st.Pj[b], st.wt[b], st.new_w[b]),
                        Posterior(p.x[b], p.P[b], p.J[b], p.L[b], p.g[b], p.Dinv[b], p.nu[b]),
                        Scores(st.scores.resid[b], st.scores.score2[b]))
        done[b] = d
        repaired[b] += r


@numba.njit(cache=True, nogil=True)
def statistics_rows(lin: Regression, st: RowState, out: F64) -> None:
    """:func:`statistics` of every batch row into ``out (B, 3)``: NIS, dof, log-likelihood."""
    p = st.post
    for b in range(st.x.shape[0]):
        q, d, ll = statistics(Prior(st.x[b], st.Pinv[b], st.LP[b]),
                              Regression(lin.used[b], lin.At[b], lin.c[b], lin.D[b]), st.wt[b],
                              Posterior(p.x[b], p.P[b], p.J[b], p.L[b], p.g[b], p.Dinv[b], p.nu[b]))
        out[b, 0] = q
        out[b, 1] = d
        out[b, 2] = ll
