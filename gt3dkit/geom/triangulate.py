"""Batched linear (DLT) triangulation of undistorted points."""

from __future__ import annotations

import numpy as np

from gt3dkit.geom.camera import unapply_K, undistort
from gt3dkit.geom.trikernel import robust_triangulate_compiled
from gt3dkit.types import F64


def normalized_points(uv_px: F64, K: F64, dist: F64) -> F64:
    """(..., C, 2) distorted pixels -> undistorted normalised coordinates."""
    return undistort(unapply_K(uv_px, K), dist)


def triangulate_dlt(xy_n: F64, R: F64, t: F64) -> tuple[F64, np.ndarray]:
    r"""Linear multi-view triangulation (Hartley & Zisserman, 2nd ed., 12.2).

    For each camera ``c`` seeing the point at normalised ``(x, y)``, the rows
    ``x P_3 - P_1`` and ``y P_3 - P_2`` of ``P = [R | t]`` go into ``A``; the point is
    the right singular vector of ``A`` with the smallest singular value.

    Parameters
    ----------
    xy_n : (N, C, 2) float64
        Undistorted normalised coordinates; NaN = not seen.
    R, t : (C, 3, 3), (C, 3) ``cam_from_world``

    Returns
    -------
    X_world : (N, 3) float64
        NaN where fewer than 2 cameras saw the point.
    n_views : (N,) int
    """
    seen = np.all(np.isfinite(xy_n), axis=-1)  # (N, C)
    xy = np.where(seen[..., None], xy_n, 0.0)
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (C, 3, 4)
    rows_x = xy[..., 0, None] * P[:, 2] - P[:, 0]  # (N, C, 4)
    rows_y = xy[..., 1, None] * P[:, 2] - P[:, 1]
    A = np.concatenate([rows_x, rows_y], axis=1) * np.concatenate([seen, seen], axis=1)[..., None]
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1, :]
    n_views = seen.sum(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:]
    X[n_views < 2] = np.nan
    return X, n_views


def _dlt_rows(xy_n: F64, R: F64, t: F64) -> F64:
    """Per view the 4x4 normal matrix ``r_x r_x^T + r_y r_y^T`` of its two DLT rows
    ``x P_3 - P_1`` and ``y P_3 - P_2``: ``(N, C, 4, 4)`` (zero where not seen)."""
    xy = np.nan_to_num(xy_n)
    P = np.concatenate([R, t[:, :, None]], axis=2)  # (C, 3, 4)
    rx = xy[..., 0, None] * P[:, 2] - P[:, 0]  # (N, C, 4)
    ry = xy[..., 1, None] * P[:, 2] - P[:, 1]
    O = rx[..., :, None] * rx[..., None, :] + ry[..., :, None] * ry[..., None, :]
    seen = np.all(np.isfinite(xy_n), axis=-1)
    return np.where(seen[..., None, None], O, 0.0)


def _null_point(M: F64) -> F64:
    """``(..., 4, 4)`` normal matrices -> ``(..., 3)`` the eigenvector of the smallest
    eigenvalue, dehomogenised (NaN at infinity)."""
    _, V = np.linalg.eigh(M)
    Xh = V[..., :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return Xh[..., :3] / Xh[..., 3:]


def triangulate_weighted(xy_n: F64, R: F64, t: F64, weight: F64, rows: F64 | None = None) -> F64:
    """DLT with a weight per view (rows scaled by it; 0 = view unused), solved as the smallest
    eigenvector of the 4x4 normal matrix ``sum_c w_c^2 (r_x r_x^T + r_y r_y^T)``.

    xy_n : (N, C, 2) normalised coordinates (any value where ``weight`` is 0);
    weight : (N, C) >= 0; rows : the ``(N, C, 4, 4)`` of :func:`_dlt_rows` if already made.
    Returns ``X_world (N, 3)``, NaN where fewer than 2 views have a positive weight.
    """
    use = weight > 0
    O = _dlt_rows(xy_n, R, t) if rows is None else rows
    w2 = np.where(use, weight, 0.0) ** 2
    X = _null_point(np.einsum("nc,ncij->nij", w2, O))
    X[use.sum(axis=1) < 2] = np.nan
    return X


def reprojection_sq_px(X_world: F64, xy_n: F64, R: F64, t: F64, f_px: F64,
                       depth_sign: F64 | float = 1.0) -> F64:
    """Squared reprojection distances (approximate pixels: normalised distance x focal).

    X_world : (..., 3); xy_n : (..., C, 2) undistorted normalised observations;
    f_px : (C,) focal length. Returns ``(..., C)``; ``inf`` where the point is behind.
    """
    Xc = np.einsum("cij,...j->...ci", R, X_world) + t
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        d = Xc[..., :2] / z[..., None] - xy_n
        e2 = np.sum(d * d, axis=-1) * f_px**2
    return np.where(z * depth_sign > 0, e2, np.inf)


def _pairs(C: int, max_pairs: int) -> np.ndarray:
    """View pairs to draw 2-view hypotheses from: all, or a spread of strides ``(P, 2)``."""
    allp = np.array([(a, b) for a in range(C) for b in range(a + 1, C)], dtype=np.int64)
    if len(allp) <= max_pairs:
        return allp.reshape(-1, 2)
    strides = np.unique(np.geomspace(1, C // 2, num=max(1, max_pairs // C)).astype(int))
    return np.array([(a, (a + s) % C) for s in strides for a in range(C)], dtype=np.int64)


def robust_triangulate(xy_n: F64, R: F64, t: F64, f_px: F64, thr_px: float,
                       var_scale: F64 | None = None, depth_sign: F64 | float = 1.0,
                       max_pairs: int = 64) -> tuple[F64, np.ndarray, F64]:
    r"""Triangulation that survives gross errors in a minority of views (MSAC + refit).

    Two-view DLT hypotheses from pairs of seen views (and the all-view DLT) are scored by
    the truncated reprojection cost ``sum_c min(e_c^2 / s_c, thr^2)`` (Torr & Zisserman,
    "MLESAC", CVIU 2000); the best one's inliers (``e^2 / s < thr^2``) are triangulated
    again, twice (compiled, one point at a time: :mod:`gt3dkit.geom.trikernel`).

    Parameters
    ----------
    xy_n : (N, C, 2) undistorted normalised coordinates, NaN = not seen
    R, t : (C, 3, 3), (C, 3) ``cam_from_world``
    f_px : (C,) focal lengths (pixels per normalised unit)
    thr_px : inlier threshold (pixels); ``inf`` = no robustness (every view an inlier)
    var_scale : (N, C) relative variance of each observation (e.g. 1 / confidence)

    Returns
    -------
    X_world : (N, 3), NaN with fewer than 2 inliers
    inlier : (N, C) bool
    e2_px : (N, C) squared reprojection error at ``X_world`` (inf where not seen)
    """
    N, C = xy_n.shape[:2]
    seen = np.all(np.isfinite(xy_n), axis=-1)
    s = np.ones((N, C)) if var_scale is None else var_scale
    if not np.isfinite(thr_px):  # no threshold: the plain (weighted) DLT of every view
        X = triangulate_weighted(xy_n, R, t, seen / np.sqrt(s))
        e2 = np.where(seen, reprojection_sq_px(X, xy_n, R, t, f_px, depth_sign), np.inf)
        return X, seen & np.all(np.isfinite(X), axis=1)[:, None], e2
    return robust_triangulate_compiled(xy_n, R, t, f_px, thr_px, s, np.broadcast_to(depth_sign, (C,)),
                                       _pairs(C, max_pairs))


def triangulation_cov(X_world: F64, R: F64, t: F64, f_px: F64, info_weight: F64) -> F64:
    r"""First-order covariance ``(N, 3, 3)`` of triangulated points, in units of the pixel
    variance: ``(sum_c w_c J_c^T J_c)^{-1}`` with ``J_c`` the 2x3 Jacobian of camera ``c``'s
    projection (pixels per metre) and ``w_c = info_weight (N, C)`` (0 = view unused).
    Infinite variance (``inf`` on the diagonal) where the point is not determined.
    """
    Xc = np.einsum("cij,...j->...ci", R, X_world) + t  # (N, C, 3)
    z = Xc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x, y = Xc[..., 0] / z, Xc[..., 1] / z
        inv = f_px / z
    Jn = np.zeros(Xc.shape[:-1] + (2, 3))
    Jn[..., 0, 0] = inv
    Jn[..., 0, 2] = -inv * x
    Jn[..., 1, 1] = inv
    Jn[..., 1, 2] = -inv * y
    used = np.asarray(np.isfinite(Jn).all(axis=(-2, -1)))  # a point at depth 0 or unknown: no information
    Jw = np.where(used[..., None, None], Jn, 0.0) @ R  # (N, C, 2, 3)
    w = np.where(used, info_weight, 0.0)
    Info = np.einsum("nc,ncki,nckj->nij", w, Jw, Jw)
    out = np.full(Info.shape, np.inf)
    det_ok = np.linalg.cond(Info) < 1e12
    if det_ok.any():
        out[det_ok] = np.linalg.inv(Info[det_ok])
    return out

