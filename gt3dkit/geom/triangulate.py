"""Batched linear (DLT) triangulation of undistorted points."""

from __future__ import annotations

import numpy as np

from gt3dkit.geom.camera import unapply_K, undistort
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
