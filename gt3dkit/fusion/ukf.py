r"""Batched unscented Kalman filter and Rauch-Tung-Striebel smoother steps.

Pure functions on arrays with a leading batch axis ``B`` (one row per object):
means ``(B, n)``, covariances ``(B, n, n)``. The measurement function receives all
sigma points of all objects at once, ``(B, S, n) -> (B, S, m)``.

Missing measurement entries are handled by a boolean mask ``(B, m)``: a masked
entry gets zero innovation, zero cross-covariance and a unit diagonal in the
innovation covariance, which makes its Kalman gain exactly zero, i.e. the same
result as leaving the entry out (objects with different numbers of visible box
edges or joints share one batched update).

References
----------
* Wan & van der Merwe, "The unscented Kalman filter for nonlinear estimation", 2000
  (scaled sigma points, weights).
* Särkkä, "Unscented Rauch-Tung-Striebel smoother", IEEE TAC 2008. With a linear
  motion model (ours) the unscented RTS gain ``C_{k+1} (P^-_{k+1})^{-1}`` equals the
  linear one ``P_k F^T (P^-_{k+1})^{-1}`` exactly, so :func:`rts_step` uses ``F``.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from gt3dkit.fusion.robust import RobustConfig, deleted_score2, point_weights
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


def _wcov(Wc: F64, dA: F64, dB: F64) -> F64:
    """Weighted cross-covariance ``sum_s Wc[s] dA[:, s, :, None] dB[:, s, None, :]`` (B, i, j)."""
    return np.swapaxes(dA * Wc[None, :, None], -1, -2) @ dB


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


def sigma_points(x: F64, P: F64, w: SigmaWeights) -> tuple[F64, int]:
    """Sigma points ``(B, 2n+1, n)`` of means ``(B, n)`` and covariances ``(B, n, n)``."""
    L, repaired = safe_cholesky(P)
    scale = np.sqrt(w.n + w.lam)
    offs = scale * np.swapaxes(L, -1, -2)  # rows are scaled columns of L
    X = np.concatenate([x[:, None, :], x[:, None, :] + offs, x[:, None, :] - offs], axis=1)
    return X, repaired


def unscented_transform(Y: F64, w: SigmaWeights) -> tuple[F64, F64]:
    """Mean ``(B, m)`` and covariance ``(B, m, m)`` of transformed sigma points ``(B, S, m)``."""
    mean = np.einsum("s,bsm->bm", w.Wm, Y)
    d = Y - mean[:, None, :]
    cov = _wcov(w.Wc, d, d)
    return mean, cov


def _regression_points(xj: F64, Pj: F64, mask: F64, h: MeasureFn, w: SigmaWeights
                       ) -> tuple[np.ndarray, F64, F64, F64, int]:
    """Sigma points of ``(xj, Pj)`` through ``h``: usable mask ``(B, m)`` (measured and finite
    at every sigma point), ``zhat (B, m)``, deviations ``dX (B, S, n)``, ``dZ (B, S, m)``."""
    X, rep = sigma_points(xj, Pj, w)
    Z = h(X)
    mk = mask & np.all(np.isfinite(Z), axis=1)
    Zm = np.where(mk[:, None, :], Z, 0.0)
    zhat = np.einsum("s,bsm->bm", w.Wm, Zm)
    return mk, zhat, X - xj[:, None, :], Zm - zhat[:, None, :], rep


def ukf_update(
    x: F64, P: F64, z: F64, mask: F64, R_diag: F64, h: MeasureFn, w: SigmaWeights,
    iterations: int = 1, x_lin: F64 | None = None, P_lin: F64 | None = None,
) -> tuple[F64, F64, dict[str, float | int]]:
    r"""One stacked, masked UKF update; iterated by posterior linearisation.

    With ``iterations = 1`` this is the standard UKF update. With more, each pass
    re-linearises ``h`` by statistical linear regression at the current posterior
    (the iterated posterior linearisation filter, García-Fernández et al., IEEE TSP
    2015): sigma points of ``(x_j, P_j)`` give

    .. math::
        A = P_{xz}^\top P_j^{-1},\quad b = \hat z - A x_j,\quad
        \Omega = P_{zz} - A P_j A^\top,

    then a Kalman update of the *prior* with ``z = A x + b + e``,
    ``e ~ N(0, \Omega + R)``. This removes the error of linearising far from the
    posterior when the prediction is poor (large process noise, first frame).

    Parameters
    ----------
    x : (B, n), P : (B, n, n)
        Prior means and covariances.
    z : (B, m)
        Measurements; any value where ``mask`` is False.
    mask : (B, m) bool
        Which entries are measured.
    R_diag : (B, m) or (m,) or scalar
        Measurement noise variances.
    h : callable ``(B, S, n) -> (B, S, m)``
    x_lin, P_lin : (B, n), (B, n, n), optional
        Where the first pass linearises (default: the prior). A better guess than a
        vague prior (e.g. a triangulated point for a joint the filter has lost) keeps
        the sigma points where ``h`` is defined.

    Returns
    -------
    x_post : (B, n), P_post : (B, n, n), info : dict
        ``repaired`` (covariances that needed an eigenvalue repair), ``nis`` (sum of
        normalised innovation squared of the first pass), ``loglik`` (Gaussian
        log-likelihood of the measured entries, first pass) and ``dof`` (measured
        entries).
    """
    B, m = z.shape
    R_b = np.broadcast_to(np.asarray(R_diag, dtype=np.float64), (B, m))
    idx = np.arange(m)
    xj, Pj = (x, P) if x_lin is None or P_lin is None else (x_lin, P_lin)
    repaired = 0
    info: dict[str, float | int] = {}
    for it in range(iterations):
        mk, zhat, dX, dZ, rep = _regression_points(xj, Pj, mask, h, w)
        repaired += rep
        Pzz = _wcov(w.Wc, dZ, dZ)
        Pxz = _wcov(w.Wc, dX, dZ)
        if xj is x:
            S, C, nu = Pzz, Pxz, z - zhat
        else:
            # A^T = Pj^-1 Pxz ; Omega = Pzz - A Pj A^T
            At = np.linalg.solve(Pj, Pxz)  # (B, n, m)
            Om = Pzz - np.swapaxes(Pxz, -1, -2) @ At
            C = P @ At  # P_prior A^T
            S = np.swapaxes(At, -1, -2) @ C + Om
            nu = z - zhat - (np.swapaxes(At, -1, -2) @ (x - xj)[..., None])[..., 0]
        S = S.copy()
        S[:, idx, idx] += np.where(mk, R_b, 1.0)
        nu = np.where(mk, nu, 0.0)
        Ls, rep2 = safe_cholesky(S)
        repaired += rep2
        Kt = np.linalg.solve(np.swapaxes(Ls, -1, -2),
                             np.linalg.solve(Ls, np.swapaxes(C, -1, -2)))  # (B, m, n) = K^T
        x_post = x + (np.swapaxes(Kt, -1, -2) @ nu[..., None])[..., 0]
        P_post = P - np.swapaxes(Kt, -1, -2) @ np.swapaxes(C, -1, -2)
        P_post = 0.5 * (P_post + np.swapaxes(P_post, -1, -2))
        if it == 0:
            white = np.linalg.solve(Ls, nu[..., None])[..., 0]
            logdet = 2 * np.sum(np.log(np.einsum("bii->bi", Ls)), axis=1)
            dof = int(mk.sum())
            info = {"nis": float(np.sum(white**2)), "dof": dof,
                    "loglik": float(-0.5 * (np.sum(white**2) + logdet.sum()
                                            + dof * np.log(2 * np.pi)))}
        xj, Pj = x_post, P_post
    info["repaired"] = repaired
    return x_post, P_post, info


@dataclass(frozen=True)
class Block:
    """Measurements that each depend on a few state entries only.

    ``G`` groups of ``k`` measurement columns ``cols (G, k)``; group ``g`` is a function of the
    ``d`` state entries ``dims[g]`` (``dims (G, d)``) through ``h: (B, G, S, d) -> (B, G, S, k)``.
    A joint's projections into every camera depend on that joint's three coordinates only, a
    box on the centre and the semi-axes, a bone on its two joints: the statistical linear
    regression of such a group needs the sigma points of its ``d``-dimensional marginal only
    (``2d`` points, not ``2n``), and its information is a ``d x d`` block. ``disjoint``: no two
    groups share a state entry (their blocks can be added by assignment). ``masked``: ``h``
    also takes the usable columns ``(B, G, k)`` and may leave the others out (NaN).
    ``compiled``: the data of a compiled form of the whole update for this block alone (the box
    block: :mod:`gt3dkit.fusion.boxupdate`), or None.
    """

    dims: np.ndarray
    cols: np.ndarray
    h: MeasureFn
    disjoint: bool = True
    masked: bool = False
    compiled: Any = None


def whole_state_block(n: int, m: int, h: MeasureFn) -> Block:
    """A measurement function ``(B, S, n) -> (B, S, m)`` of the whole state as one block."""
    return Block(np.arange(n)[None], np.arange(m)[None], lambda X: h(X[:, 0])[:, None])


@dataclass
class _Lin:
    """One block's regression at ``(x_j, P_j)``: usable ``mk (B, G, k)``, ``At (B, G, d, k)``
    (``A^T``), ``c (B, G, k)`` (``z - b``: the linearised model is ``A x + b``) and the
    linearisation error's diagonal ``omega (B, G, k)``."""

    mk: np.ndarray
    At: F64
    c: F64
    omega: F64


def _block_regression(xj: F64, Pj: F64, z: F64, mask: np.ndarray, blk: Block, alpha: float,
                      beta: float, kappa: float) -> tuple[_Lin, int]:
    """Statistical linear regression of one block on its marginal's sigma points."""
    dims, cols = blk.dims, blk.cols
    d = dims.shape[1]
    w = SigmaWeights(d, alpha, beta, kappa)
    xb = xj[:, dims]  # (B, G, d)
    Pb = Pj[:, dims[:, :, None], dims[:, None, :]]  # (B, G, d, d)
    B, G = xb.shape[:2]
    L, rep = safe_cholesky(Pb.reshape(B * G, d, d))
    offs = (np.sqrt(w.n + w.lam) * np.swapaxes(L, -1, -2)).reshape(B, G, d, d)
    Wm, Wc = w.Wm, w.Wc
    centre = bool(Wm[0] != 0.0 or Wc[0] != 0.0)  # the cubature rule gives it no weight
    pts = [xb[:, :, None, :]] if centre else []
    X = np.concatenate(pts + [xb[:, :, None, :] + offs, xb[:, :, None, :] - offs], axis=2)
    if not centre:
        Wm, Wc = Wm[1:], Wc[1:]
    Z = blk.h(X, mask[:, cols]) if blk.masked else blk.h(X)  # (B, G, S, k)
    mk = mask[:, cols] & np.all(np.isfinite(Z), axis=2)
    Zm = np.where(mk[:, :, None, :], Z, 0.0)
    zhat = np.einsum("s,bgsk->bgk", Wm, Zm)
    dX = X - xb[:, :, None, :]
    dZ = Zm - zhat[:, :, None, :]
    Pxz = np.swapaxes(dX * Wc[:, None], -1, -2) @ dZ  # (B, G, d, k)
    At = np.linalg.solve(Pb, Pxz)
    var_z = np.einsum("s,bgsk->bgk", Wc, dZ * dZ)
    omega = np.maximum(var_z - np.sum(Pxz * At, axis=2), 0.0)
    c = z[:, cols] - zhat + np.einsum("bgdk,bgd->bgk", At, xb)
    return _Lin(mk, At, c, omega), rep


def _scatter(J: F64, g: F64, blk: Block, H: F64, v: F64) -> None:
    """``J[:, dims, dims] += H (B, G, d, d)`` and ``g[:, dims] += v (B, G, d)`` in place."""
    dims = blk.dims
    if blk.disjoint:
        J[:, dims[:, :, None], dims[:, None, :]] += H
        g[:, dims] += v
    else:
        bi = np.arange(J.shape[0])[:, None, None, None]
        np.add.at(J, (bi, dims[None, :, :, None], dims[None, :, None, :]), H)
        np.add.at(g, (np.arange(J.shape[0])[:, None, None], dims[None]), v)


def ukf_update_information(
    x: F64, P: F64, z: F64, mask: F64, R_diag: F64, h: MeasureFn | Sequence[Block], w: SigmaWeights,
    iterations: int = 1, x_lin: F64 | None = None, P_lin: F64 | None = None,
    weight0: F64 | None = None, robust: RobustConfig | None = None,
    robust_blocks: tuple[tuple[slice, int], ...] = (),
) -> tuple[F64, F64, dict[str, Any]]:
    r"""The iterated update of :func:`ukf_update` in information form, optionally robust.

    Each pass linearises ``h`` by statistical linear regression at ``(x_j, P_j)``
    (``A, b`` and the diagonal of the linearisation error ``Omega``) and updates the prior
    in state space,

    .. math::
        P^+ = (P^{-1} + A^\top W D^{-1} A)^{-1},\quad
        x^+ = x + P^+ A^\top W D^{-1} (z - A x - b),\quad D = R + \mathrm{diag}(\Omega),

    which costs ``O(n^3 + m n^2)`` instead of ``O(m^3)``. Keeping only the diagonal of
    ``Omega`` is the one approximation; ``Omega`` vanishes as the posterior tightens.

    Robust (iteratively reweighted) update: ``W = diag(w)`` holds a weight per entry,
    ``weight0`` to start with (e.g. the per-frame fits' verdicts), then after every pass
    the weights of the points in ``robust_blocks`` (``(slice of z, entries per point)``)
    are recomputed from their leave-one-out scores against the new posterior
    (:mod:`gt3dkit.fusion.robust`). A weight of 0 removes the entry exactly.

    ``h`` is a function of the whole state or a list of :class:`Block` (each regressed on its
    own marginal's sigma points). The passes stop early once a pass's posterior is where it
    linearised and no weight changes (``info["passes"]``): a further pass would repeat it.

    Returns ``x_post, P_post, info`` as :func:`ukf_update`; ``loglik`` and ``nis`` are of
    the last pass with its weights (noise ``D / w`` for the kept entries: what the estimate
    rests on), and ``info``
    also holds ``nis_rows``, ``dof_rows``, ``loglik_rows`` (the same per batch row, ``(B,)``),
    ``weights (B, m)`` (those the last pass used), ``score2 (B, m)`` (each
    entry's point's squared leave-one-out score at the final posterior) and
    ``residual (B, m)`` (``z - h(x_post)``, linearised).
    """
    B, m = z.shape
    n = x.shape[1]
    blocks = [whole_state_block(n, m, h)] if callable(h) else list(h)
    R_b = np.broadcast_to(np.asarray(R_diag, dtype=np.float64), (B, m))
    Pinv = np.linalg.inv(0.5 * (P + np.swapaxes(P, -1, -2)))
    xj, Pj = (x, P) if x_lin is None or P_lin is None else (x_lin, P_lin)
    wt = np.ones((B, m)) if weight0 is None else np.asarray(weight0, dtype=np.float64).copy()
    repaired = 0
    eye = np.eye(n)
    score2 = np.zeros((B, m))
    resid = np.zeros((B, m))
    mk = np.zeros((B, m), bool)
    D = np.ones((B, m))
    lin = np.zeros((B, m))
    for it in range(iterations):
        Jinf = Pinv.copy()
        g = np.zeros((B, n))
        lins = []
        for blk in blocks:
            L, rep = _block_regression(xj, Pj, z, mask, blk, w.alpha, w.beta, w.kappa)
            repaired += rep
            cols = blk.cols
            mk[:, cols] = L.mk
            Db = R_b[:, cols] + L.omega
            D[:, cols] = Db
            Dinv = np.where(L.mk, wt[:, cols] / Db, 0.0)  # (B, G, k)
            lin[:, cols] = L.c
            nu = np.where(L.mk, L.c - np.einsum("bgdk,bgd->bgk", L.At, x[:, blk.dims]), 0.0)
            AtD = L.At * Dinv[:, :, None, :]
            _scatter(Jinf, g, blk, AtD @ np.swapaxes(L.At, -1, -2), np.einsum("bgdk,bgk->bgd", AtD, nu))
            lins.append((blk, L, nu, Dinv))
        Lj, rep2 = safe_cholesky(Jinf)
        repaired += rep2
        Li = np.linalg.solve(Lj, np.broadcast_to(eye, Lj.shape))
        P_post = np.swapaxes(Li, -1, -2) @ Li
        x_post = x + (P_post @ g[..., None])[..., 0]
        last = it == iterations - 1
        # converged: the posterior is where this pass linearised (to 0.01 sd and 1e-3 of the
        # spread), so a further pass would linearise at the same place and change nothing
        converged = False
        if it > 0:
            step = np.einsum("bji,bj->bi", Lj, x_post - xj)  # L^T dx: |.|^2 = dx^T P+^-1 dx
            spread = np.einsum("bii->b", P_post) / np.einsum("bii->b", Pj)
            converged = bool(np.max(np.sum(step * step, axis=1)) < 1e-4
                             and np.max(np.abs(spread - 1.0)) < 1e-3)
        if robust is not None and robust_blocks:
            p = np.zeros((B, m))
            for blk, L, _, _ in lins:
                dims = blk.dims
                xb = x_post[:, dims]
                Pb = P_post[:, dims[:, :, None], dims[:, None, :]]
                resid[:, blk.cols] = np.where(L.mk, L.c - np.einsum("bgdk,bgd->bgk", L.At, xb), 0.0)
                p[:, blk.cols] = np.sum(L.At * (Pb @ L.At), axis=2)  # diag(A P+ A^T)
            e2 = np.where(mk, deleted_score2(resid, D, p, wt), 0.0)
            new_wt = wt.copy()
            for sl, d in robust_blocks:
                e2b = e2[:, sl].reshape(B, -1, d).sum(axis=2)
                score2[:, sl] = np.repeat(e2b, d, axis=1)
                if not last:
                    new_wt[:, sl] = np.repeat(point_weights(e2b, d, robust), d, axis=1)
            if not last:
                new_wt = np.where(mk, new_wt, wt)
                converged = converged and bool(np.array_equal(new_wt, wt))
                if not converged:
                    wt = new_wt
        if last or converged:
            break
        xj, Pj = x_post, P_post
    # statistics of the last pass, with the weights it used (what the estimate rests on)
    LP, _ = safe_cholesky(P)
    used = mk & (wt > 0)
    logdet = (np.sum(np.log(np.where(used, D / np.where(used, wt, 1.0), 1.0)), axis=1)
              + 2 * np.sum(np.log(np.einsum("bii->bi", Lj)), axis=1)
              + 2 * np.sum(np.log(np.einsum("bii->bi", LP)), axis=1))
    quad = (sum(np.sum(nu * nu * Dinv, axis=(1, 2)) for _, _, nu, Dinv in lins)
            - np.einsum("bi,bi->b", g, (P_post @ g[..., None])[..., 0]))
    dof_b = used.sum(axis=1)
    ll_b = -0.5 * (quad + logdet + dof_b * np.log(2 * np.pi))
    info = {"nis": float(quad.sum()), "dof": int(dof_b.sum()), "loglik": float(ll_b.sum()),
            "nis_rows": quad, "dof_rows": dof_b, "loglik_rows": ll_b, "passes": it + 1}
    info.update(repaired=repaired, weights=np.where(mask, wt, 1.0), score2=score2,
                residual=resid)
    return x_post, P_post, info


def predict_linear(x: F64, P: F64, F: F64, Q: F64) -> tuple[F64, F64]:
    """Linear prediction for ``(B, n)``, ``(B, n, n)`` with ``F, Q (B, n, n)`` or ``(n, n)``."""
    F = np.broadcast_to(F, P.shape)
    xp = (F @ x[..., None])[..., 0]
    Pp = F @ P @ np.swapaxes(F, -1, -2) + Q
    return xp, 0.5 * (Pp + np.swapaxes(Pp, -1, -2))


def rts_step(
    x_f: F64, P_f: F64, x_p_next: F64, P_p_next: F64, x_s_next: F64, P_s_next: F64, F: F64
) -> tuple[F64, F64]:
    r"""One backward RTS step for a batch.

    .. math::
        G_k = P_k F^\top (P^-_{k+1})^{-1},\quad
        m^s_k = m_k + G_k (m^s_{k+1} - m^-_{k+1}),\quad
        P^s_k = P_k + G_k (P^s_{k+1} - P^-_{k+1}) G_k^\top

    Shapes: means ``(B, n)``, covariances ``(B, n, n)``, ``F`` ``(B, n, n)`` or ``(n, n)``.
    """
    F = np.broadcast_to(F, P_f.shape)
    C = P_f @ np.swapaxes(F, -1, -2)  # P F^T
    G = np.swapaxes(np.linalg.solve(P_p_next, np.swapaxes(C, -1, -2)), -1, -2)
    x_s = x_f + (G @ (x_s_next - x_p_next)[..., None])[..., 0]
    P_s = P_f + G @ (P_s_next - P_p_next) @ np.swapaxes(G, -1, -2)
    return x_s, 0.5 * (P_s + np.swapaxes(P_s, -1, -2))
