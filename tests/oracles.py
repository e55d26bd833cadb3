"""Slow, independent formulations the tests hold the package's compiled code to (oracles), and
the baselines of ``scripts/bench_throughput.py``."""

from __future__ import annotations

import numpy as np

from gt3dkit.fusion.ukf.sigma import MeasureFn, SigmaWeights, safe_cholesky
from gt3dkit.geom.camera import apply_K, distort
from gt3dkit.geom.conics import outline_ellipse
from gt3dkit.geom.triangulate import _dlt_rows, _pairs, reprojection_sq_px, triangulate_weighted
from gt3dkit.types import F64

# Directions of the four edges: xmin, ymin, xmax, ymax (we maximise dir . uv).
_EDGE_DIRS = np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]])


def ellipsoid_boxes_numpy(
    center_world: F64,
    semi_axes: F64,
    world_from_body: F64,
    K: F64,
    dist: F64,
    R: F64,
    t: F64,
    depth_sign: F64 | float = 1.0,
    newton_steps: int = 2,
) -> tuple[F64, F64]:
    """Tight boxes of ellipsoids in every camera's distorted image: the numpy reference of
    :func:`gt3dkit.geom.conics.ellipsoid_boxes` (whole-array operations, central differences).

    Parameters
    ----------
    center_world : (..., 3) float64, metres
    semi_axes : (..., 3) float64, metres
    world_from_body : (3, 3) float64
    K, dist, R, t : stacked arrays of ``C`` cameras
    depth_sign : (C,) see :class:`gt3dkit.types.Camera`
    newton_steps : int
        Refinement steps for distortion (ignored when all ``dist`` are zero).

    Returns
    -------
    box_xyxy_px : (..., C, 4) float64
        ``xmin, ymin, xmax, ymax``; NaN where the ellipsoid is not wholly in front.
    margin : (..., C) float64
        See :func:`outline_ellipse`.
    """
    m, E, margin = outline_ellipse(center_world, semi_axes, world_from_body, R, t, depth_sign)
    if not np.any(dist):
        half = np.sqrt(np.maximum(np.stack([E[..., 0, 0], E[..., 1, 1]], -1), 0.0))
        lo = apply_K(m - half, K)
        hi = apply_K(m + half, K)
        # K with zero skew keeps the axis order; with skew fall through to general path
        if not np.any(K[:, 0, 1]):
            return np.concatenate([lo, hi], axis=-1), margin
    # Cholesky-like factor L with L L^T = E (2x2, closed form), NaN-safe
    e00 = np.maximum(E[..., 0, 0], 1e-300)
    l00 = np.sqrt(e00)
    l10 = E[..., 1, 0] / l00
    l11 = np.sqrt(np.maximum(E[..., 1, 1] - l10 * l10, 0.0))
    # edge-direction in pixels -> direction in normalised coords: dir . (A xy) = (A^T dir) . xy
    A = K[:, :2, :2]  # (C,2,2)
    g = np.einsum("cji,ej->cei", A, _EDGE_DIRS)  # (C,4,2)
    # L^T g  -> seed angle per edge
    gx, gy = g[..., 0], g[..., 1]  # (C,4)
    ltg0 = l00[..., None] * gx + l10[..., None] * gy  # (...,C,4)
    ltg1 = l11[..., None] * gy
    theta = np.arctan2(ltg1, ltg0)

    def value(th: F64) -> F64:
        u = np.stack([np.cos(th), np.sin(th)], -1)  # (...,C,4,2)
        p0 = m[..., None, 0] + l00[..., None] * u[..., 0]
        p1 = m[..., None, 1] + l10[..., None] * u[..., 0] + l11[..., None] * u[..., 1]
        xy = np.stack([p0, p1], -1)  # (...,C,4,2)
        uv = apply_K(distort(xy, dist[:, None, :]), K[:, None])  # per camera, over edges
        return uv[..., 0] * _EDGE_DIRS[:, 0] + uv[..., 1] * _EDGE_DIRS[:, 1]

    if np.any(dist):
        h = 1e-3
        for _ in range(newton_steps):
            f0, fp, fm = value(theta), value(theta + h), value(theta - h)
            d1 = (fp - fm) / (2 * h)
            d2 = (fp - 2 * f0 + fm) / (h * h)
            step = np.where(d2 < 0, -d1 / np.where(d2 < 0, d2, -1.0), 0.0)
            theta = theta + np.clip(step, -0.5, 0.5)
    v = value(theta)
    box = v * np.array([-1.0, -1.0, 1.0, 1.0])
    return box, margin


# --- the unscented Kalman filter's covariance-form update (held to filterpy; the package's
# information-form update is held to it) -------------------------------------------------


def _wcov(Wc: F64, dA: F64, dB: F64) -> F64:
    """Weighted cross-covariance ``sum_s Wc[s] dA[:, s, :, None] dB[:, s, None, :]`` (B, i, j)."""
    return np.swapaxes(dA * Wc[None, :, None], -1, -2) @ dB


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


def inhomogeneous_point(M: F64) -> F64:
    """``(..., 4, 4)`` normal matrices -> ``(..., 3)`` the least-squares point with the
    homogeneous coordinate fixed to 1 (``X = -M[:3, :3]^-1 M[:3, 3]``, the 3x3 inverse by
    cofactors; NaN where singular: ``det < 1e-10 trace^3``, e.g. one view's ray). The same
    point as :func:`_null_point` without noise and within the noise with it, at a tenth of
    the time of a batched ``eigh``: the two-view hypotheses of :func:`robust_triangulate`,
    which are only scored."""
    A, b = M[..., :3, :3], -M[..., :3, 3]
    c0 = np.cross(A[..., 1, :], A[..., 2, :])
    c1 = np.cross(A[..., 2, :], A[..., 0, :])
    c2 = np.cross(A[..., 0, :], A[..., 1, :])
    det = np.einsum("...i,...i->...", A[..., 0, :], c0)
    with np.errstate(divide="ignore", invalid="ignore"):  # A symmetric: A^-1 = [c0 c1 c2] / det
        X = np.einsum("...ij,...j->...i", np.stack([c0, c1, c2], -1), b) / det[..., None]
    singular = det <= 1e-10 * np.einsum("...ii->...", A) ** 3
    return np.where(np.isfinite(X) & ~singular[..., None], X, np.nan)


def robust_triangulate_numpy(xy_n: F64, R: F64, t: F64, f_px: F64, thr_px: float,
                             var_scale: F64 | None = None, depth_sign: F64 | float = 1.0, max_pairs: int = 64,
                             chunk: int = 4096) -> tuple[F64, np.ndarray, F64]:
    """The batched numpy formulation of :func:`gt3dkit.geom.triangulate.robust_triangulate` (finite
    threshold) that the compiled one (:mod:`gt3dkit.geom.trikernel`) replaced: the same arguments
    and results, in chunks of ``chunk`` points."""
    N, C = xy_n.shape[:2]
    seen = np.all(np.isfinite(xy_n), axis=-1)
    s = np.ones((N, C)) if var_scale is None else var_scale
    X = np.full((N, 3), np.nan)
    inl = np.zeros((N, C), bool)
    e2 = np.full((N, C), np.inf)
    pairs = _pairs(C, max_pairs)
    for a in range(0, N, chunk):
        sl = slice(a, min(a + chunk, N))
        xy, sn, sc = xy_n[sl], seen[sl], s[sl]
        n = len(xy)
        O = _dlt_rows(xy, R, t)
        cands = [triangulate_weighted(xy, R, t, sn.astype(np.float64), O)[:, None]]
        if len(pairs):
            Xp = inhomogeneous_point(O[:, pairs[:, 0]] + O[:, pairs[:, 1]])  # (n, P, 3)
            both = sn[:, pairs[:, 0]] & sn[:, pairs[:, 1]]
            cands.append(np.where(both[..., None], Xp, np.nan))
        Xc = np.concatenate(cands, axis=1)  # (n, P+1, 3)
        ec = reprojection_sq_px(Xc, xy[:, None], R, t, f_px, depth_sign) / sc[:, None]
        cost = np.sum(np.where(sn[:, None], np.minimum(np.nan_to_num(ec, nan=np.inf), thr_px**2),
                               0.0), axis=2)
        cost = np.where(np.all(np.isfinite(Xc), axis=2), cost, np.inf)
        best = Xc[np.arange(n), np.argmin(cost, axis=1)]
        for _ in range(2):
            eb = reprojection_sq_px(best, xy, R, t, f_px, depth_sign) / sc
            w = (sn & (np.nan_to_num(eb, nan=np.inf) < thr_px**2)).astype(np.float64)
            refit = triangulate_weighted(xy, R, t, w / np.sqrt(sc), O)
            best = np.where(np.isfinite(refit), refit, best)
        eb = reprojection_sq_px(best, xy, R, t, f_px, depth_sign)
        good = sn & (np.nan_to_num(eb / sc, nan=np.inf) < thr_px**2)
        ok = good.sum(axis=1) >= 2
        X[sl] = np.where(ok[:, None], best, np.nan)
        inl[sl] = good & ok[:, None]
        e2[sl] = np.where(sn, eb, np.inf)
    return X, inl, e2
