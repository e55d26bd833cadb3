r"""The unscented measurement update of a batch of rows: sigma-point weights, the statistical
linear regression of each measurement block, and the driver of the iterated, robust,
information-form update (:mod:`gt3dkit.fusion.update` holds the update itself, one row at a
time, compiled).

Arrays carry a leading batch axis ``B`` (one row per object): means ``(B, n)``, covariances
``(B, n, n)``, measurements ``(B, m)`` with a mask of the present entries (a missing entry has
no weight: the same as leaving it out, so objects with different visible box edges or joints
share one batch).

References
----------
* Wan & van der Merwe, "The unscented Kalman filter for nonlinear estimation", 2000
  (scaled sigma points, weights).
* García-Fernández, Svensson, Morelande & Särkkä, "Posterior linearization filter: principles
  and implementation using sigma points", IEEE TSP 63, 2015 (the iterated regression).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gt3dkit.fusion.robust import RobustConfig
from gt3dkit.fusion.update import Columns, Measured, Regression, pass_rows, row_state, statistics_rows
from gt3dkit.geom.boxkernel import contiguous
from gt3dkit.types import F64

MeasureFn = Callable[[F64], F64]


@dataclass(frozen=True)
class SigmaWeights:
    """Scaled unscented weights for an ``n``-dimensional state (2n+1 points).

    Defaults ``alpha=1, beta=0, kappa=0`` give the cubature rule: ``W_0 = 0`` and
    all other weights ``1/(2n)`` (all non-negative, so predicted covariances are
    positive semi-definite by construction).
    """

    n: int
    alpha: float = 1.0
    beta: float = 0.0
    kappa: float = 0.0

    @property
    def lam(self) -> float:
        return self.alpha**2 * (self.n + self.kappa) - self.n

    @property
    def Wm(self) -> F64:
        w = np.full(2 * self.n + 1, 1.0 / (2 * (self.n + self.lam)))
        w[0] = self.lam / (self.n + self.lam)
        return w

    @property
    def Wc(self) -> F64:
        w = self.Wm.copy()
        w[0] += 1.0 - self.alpha**2 + self.beta
        return w


def safe_cholesky(P: F64) -> tuple[F64, int]:
    """Lower Cholesky factors of ``(B, n, n)``; eigenvalue-clipped where not PD.

    Returns the factors and how many matrices needed repair.
    """
    P = 0.5 * (P + np.swapaxes(P, -1, -2))
    try:
        return np.linalg.cholesky(P), 0
    except np.linalg.LinAlgError:
        pass
    w, V = np.linalg.eigh(P)
    bad = w.min(axis=-1) <= 1e-15 * np.maximum(w.max(axis=-1), 1e-300)
    floor = 1e-12 * np.maximum(w.max(axis=-1, keepdims=True), 1e-300)
    w = np.maximum(w, floor)
    P2 = (V * w[:, None, :]) @ np.swapaxes(V, -1, -2)
    return np.linalg.cholesky(0.5 * (P2 + np.swapaxes(P2, -1, -2))), int(bad.sum())


@dataclass(frozen=True)
class Block:
    """Measurements that each depend on a few state entries only.

    ``G`` groups of ``k`` measurement columns ``cols (G, k)``; group ``g`` is a function of the
    ``d`` state entries ``dims[g]`` (``dims (G, d)``) through ``h: (B, G, S, d) -> (B, G, S, k)``.
    A joint's projections into every camera depend on that joint's three coordinates only, a
    box on the centre and the semi-axes, a bone on its two joints: the statistical linear
    regression of such a group needs the sigma points of its ``d``-dimensional marginal only
    (``2d`` points, not ``2n``), and its information is a ``d x d`` block.
    ``masked``: ``h`` also takes the usable columns ``(B, G, k)``
    and may leave the others out (NaN). ``regress``: the block's own regression (the box block's
    is compiled, :func:`gt3dkit.fusion.boxupdate.box_regressions`), called as
    ``regress(rows, xj, Pj, meas, w, lin, repaired)`` (see :func:`block_regression`); None: the
    sigma points of ``h`` (:func:`block_regression`).
    """

    dims: np.ndarray
    cols: np.ndarray
    h: MeasureFn | None
    masked: bool = False
    regress: Callable[..., None] | None = None


def whole_state_block(n: int, m: int, h: MeasureFn) -> Block:
    """A measurement function ``(B, S, n) -> (B, S, m)`` of the whole state as one block."""
    return Block(np.arange(n)[None], np.arange(m)[None], lambda X: h(X[:, 0])[:, None])


def block_regression(blk: Block, rows: np.ndarray, xj: F64, Pj: F64, meas: Measured, w: SigmaWeights,
                     lin: Regression, repaired: np.ndarray) -> None:
    """Statistical linear regression of one block's columns for the batch rows ``rows`` about
    ``N(xj[rows], Pj[rows])`` (``(B, n)``, ``(B, n, n)``; ``meas``: the batch's ``z, mask, var
    (B, m)``) on each group's marginal's sigma points, into ``lin``'s rows (``(B, ...)``
    arrays, :class:`gt3dkit.fusion.update.Regression`); each row's factor repairs added to
    ``repaired (B,)``."""
    if blk.regress is not None:
        blk.regress(rows, xj, Pj, meas, w, lin, repaired)
        return
    dims, cols = blk.dims, blk.cols
    G, d = dims.shape
    k = cols.shape[1]
    ws = SigmaWeights(d, w.alpha, w.beta, w.kappa)
    xb = xj[rows][:, dims]  # (B, G, d)
    Pb = Pj[rows][:, dims[:, :, None], dims[:, None, :]]  # (B, G, d, d)
    B = len(rows)
    L, rep = _safe_cholesky_rows(Pb.reshape(B * G, d, d))
    repaired[rows] += rep.reshape(B, G).sum(axis=1)
    offs = (np.sqrt(ws.n + ws.lam) * np.swapaxes(L, -1, -2)).reshape(B, G, d, d)
    Wm, Wc = ws.Wm, ws.Wc
    centre = bool(Wm[0] != 0.0 or Wc[0] != 0.0)  # the cubature rule gives it no weight
    pts = [xb[:, :, None, :]] if centre else []
    X = np.concatenate(pts + [xb[:, :, None, :] + offs, xb[:, :, None, :] - offs], axis=2)
    if not centre:
        Wm, Wc = Wm[1:], Wc[1:]
    mask = meas.mask[rows][:, cols]
    assert blk.h is not None
    Z = blk.h(X, mask) if blk.masked else blk.h(X)  # (B, G, S, k)
    mk = mask & np.all(np.isfinite(Z), axis=2)
    Zm = np.where(mk[:, :, None, :], Z, 0.0)
    zhat = np.einsum("s,bgsk->bgk", Wm, Zm)
    dX = X - xb[:, :, None, :]
    dZ = Zm - zhat[:, :, None, :]
    Pxz = np.swapaxes(dX * Wc[:, None], -1, -2) @ dZ  # (B, G, d, k)
    At = np.linalg.solve(Pb, Pxz)
    var_z = np.einsum("s,bgsk->bgk", Wc, dZ * dZ)
    omega = np.maximum(var_z - np.sum(Pxz * At, axis=2), 0.0)
    c = meas.z[rows][:, cols] - zhat + np.einsum("bgdk,bgd->bgk", At, xb)
    flat = cols.reshape(-1)
    r2 = rows[:, None]
    lin.used[r2, flat] = mk.reshape(B, G * k)
    lin.At[r2, flat, :d] = np.swapaxes(At, 2, 3).reshape(B, G * k, d)
    lin.c[r2, flat] = c.reshape(B, G * k)
    lin.D[r2, flat] = meas.var[rows][:, flat] + omega.reshape(B, G * k)


def _safe_cholesky_rows(P: F64) -> tuple[F64, np.ndarray]:
    """:func:`safe_cholesky` with the repairs per matrix ``(N,)``."""
    L, rep = safe_cholesky(P)
    if not rep:
        return L, np.zeros(len(P), np.int64)
    w = np.linalg.eigvalsh(0.5 * (P + np.swapaxes(P, -1, -2)))
    return L, (w.min(axis=-1) <= 1e-15 * np.maximum(w.max(axis=-1), 1e-300)).astype(np.int64)


@dataclass(frozen=True)
class Robust:
    """Which measurement points an update may down-weight: ``blocks`` of ``(slice of the
    measurement vector, entries per point)``, judged by ``config``."""

    config: RobustConfig
    blocks: tuple[tuple[slice, int], ...]


def ukf_update_information(
    x: F64, P: F64, meas: Measured, h: MeasureFn | Sequence[Block], w: SigmaWeights, iterations: int = 1,
    lin_point: tuple[F64, F64] | None = None, weight0: F64 | None = None, robust: Robust | None = None,
    columns: Columns | None = None,
) -> tuple[F64, F64, dict[str, Any]]:
    r"""The iterated, optionally robust unscented update of a batch of rows in information form:
    the regression of every block (:func:`block_regression`), then the update of
    :mod:`gt3dkit.fusion.update` per row (:func:`gt3dkit.fusion.update.pass_rows`), until every
    row is done.

    Each pass linearises ``h`` by statistical linear regression at ``(x_j, P_j)`` (``A, b`` and
    the diagonal of the linearisation error ``Omega``) and updates the prior in state space,

    .. math::
        P^+ = (P^{-1} + A^\top W D^{-1} A)^{-1},\quad
        x^+ = x + P^+ A^\top W D^{-1} (z - A x - b),\quad D = R + \mathrm{diag}(\Omega),

    which costs ``O(n^3 + m n^2)`` instead of ``O(m^3)``. Keeping only the diagonal of
    ``Omega`` is the one approximation; ``Omega`` vanishes as the posterior tightens. With one
    pass and the prior as linearisation point this is the standard UKF update (the tests hold
    it to filterpy's through a covariance-form oracle).

    Parameters
    ----------
    x, P : (B, n), (B, n, n) the priors
    meas : the batch's measurements ``z``, present entries ``mask`` and noise variances ``var``,
        ``(B, m)`` each
    h : a function ``(B, S, n) -> (B, S, m)`` of the whole state, or a list of :class:`Block`
        (each regressed on its own marginal's sigma points)
    lin_point : ``(x_lin, P_lin)`` where the first pass linearises (default: the prior)
    weight0 : (B, m) the weights the first pass uses (default 1; 0 removes an entry exactly)
    robust : after every pass but the last, the points of ``robust.blocks`` are reweighted by
        their leave-one-out scores against the new posterior (:mod:`gt3dkit.fusion.robust`)
    columns : the blocks' :class:`gt3dkit.fusion.update.Columns` (default: made here from
        ``h`` and ``robust``)

    A row stops once a pass's posterior is where it linearised and no weight changes
    (``info["passes_rows"]``): a further pass would repeat it.

    Returns ``x_post, P_post, info``: ``nis``, ``dof``, ``loglik`` (of the last pass with its
    weights: noise ``D / w`` for the kept entries, what the estimate rests on), the same per
    row (``nis_rows``, ``dof_rows``, ``loglik_rows``, ``(B,)``), ``passes``, ``repaired``
    (factors that needed an eigenvalue repair), ``weights (B, m)`` (those the last pass used),
    ``score2 (B, m)`` (each entry's point's squared leave-one-out score at the final posterior)
    and ``residual (B, m)`` (``z - h(x_post)``, linearised).
    """
    z = contiguous(meas.z)
    B, m = z.shape
    n = x.shape[1]
    blocks = [whole_state_block(n, m, h)] if callable(h) else list(h)
    cols = columns if columns is not None else block_columns(blocks, m, robust)
    mask = contiguous(meas.mask, np.bool_)
    meas = Measured(z, mask, contiguous(np.broadcast_to(np.asarray(meas.var, dtype=np.float64),
                                                                  (B, m))))
    xj, Pj = (x, P) if lin_point is None else lin_point
    wt = np.ones((B, m)) if weight0 is None else weight0
    st = row_state(x, P, xj, Pj, wt)
    lin = Regression(np.zeros((B, m), np.bool_), np.zeros((B, m, cols.dims.shape[1])), np.zeros((B, m)),
                     np.ones((B, m)))
    done = np.zeros(B, np.bool_)
    repaired = np.zeros(B, np.int64)
    passes = np.zeros(B, np.int64)
    active = np.arange(B, dtype=np.int64)
    on = bool(np.any(cols.size > 0))
    for it in range(iterations):
        for blk in blocks:
            block_regression(blk, active, st.xj, st.Pj, meas, w, lin, repaired)
        pass_rows(active, it, it == iterations - 1, on, lin, cols, st, done, repaired)
        passes[active] = it + 1
        active = active[~done[active]]
        if not len(active):
            break
    stats = np.empty((B, 3))
    statistics_rows(lin, st, stats)
    quad, dof_b, ll_b = stats[:, 0], stats[:, 1].astype(np.int64), stats[:, 2]
    info: dict[str, Any] = {
        "nis": float(quad.sum()), "dof": int(dof_b.sum()), "loglik": float(ll_b.sum()),
        "nis_rows": quad, "dof_rows": dof_b, "loglik_rows": ll_b, "passes_rows": passes,
        "passes": int(passes.max()) if B else 0, "repaired": int(repaired.sum()),
        "weights": np.where(mask, st.wt, 1.0), "score2": st.scores.score2, "residual": st.scores.resid}
    return st.post.x, st.post.P, info


def block_columns(blocks: Sequence[Block], m: int, robust: Robust | None) -> Columns:
    """The :class:`gt3dkit.fusion.update.Columns` of ``m`` measurement columns made of ``blocks``:
    the state entries of each column's group and, with ``robust``, the points of its blocks with
    their thresholds (infinite when its config is disabled)."""
    d = max(b.dims.shape[1] for b in blocks)
    dims = np.concatenate([np.pad(b.dims, ((0, 0), (0, d - b.dims.shape[1])), constant_values=-1)
                           for b in blocks]).astype(np.int64)  # (G, d): each group's entries
    order = np.concatenate([b.cols.reshape(-1) for b in blocks]).astype(np.int64)
    sizes = np.concatenate([np.full(b.cols.shape[0], b.cols.shape[1]) for b in blocks])
    start = np.r_[0, np.cumsum(sizes)].astype(np.int64)
    width = np.concatenate([np.full(b.cols.shape[0], b.dims.shape[1]) for b in blocks]).astype(np.int64)
    first = np.arange(m, dtype=np.int64)
    size = np.zeros(m, np.int64)
    c_thr, g_thr = np.full(m, np.inf), np.full(m, np.inf)
    for sl, e in robust.blocks if robust is not None else ():
        k = np.arange(*sl.indices(m))
        first[k] = k[0] + (k - k[0]) // e * e
        size[k] = e
        if robust.config.enabled:
            c_thr[k], g_thr[k] = robust.config.thresholds(e)
    return Columns(dims, first, size, c_thr, g_thr, order, start, width)
