r"""Batched pinhole projection with OpenCV's 5-parameter lens distortion.

Shapes: batch dimensions lead, then the camera axis ``C`` where there is one,
then the coordinate. Cameras are given as stacked arrays (see ``Rig``):
``K (C,3,3)``, ``dist (C,5)``, ``R (C,3,3)``, ``t (C,3)`` with
``X_cam = R X_world + t``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gt3dkit.types import BOX_MODEL_REGISTRY, F64, Rig


def cam_from_world_points(X_world: F64, R: F64, t: F64) -> F64:
    """Points in every camera's frame.

    Parameters
    ----------
    X_world : (..., 3) float64
    R : (C, 3, 3) float64
    t : (C, 3) float64

    Returns
    -------
    X_cam : (..., C, 3) float64
    """
    return np.einsum("cij,...j->...ci", R, X_world) + t


def distort(xy_n: F64, dist: F64) -> F64:
    r"""Apply OpenCV's radial-tangential distortion to normalised coordinates.

    .. math::
        x' = x (1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2 x^2)

    Parameters
    ----------
    xy_n : (..., C, 2) float64
        Undistorted normalised coordinates ``(X/Z, Y/Z)``.
    dist : (C, 5) float64
        ``k1 k2 p1 p2 k3`` per camera (broadcast against ``xy_n[..., 0]``).

    Returns
    -------
    (..., C, 2) float64
    """
    with np.errstate(over="ignore", invalid="ignore"):
        return _distort(xy_n, dist)


def _distort(xy_n: F64, dist: F64) -> F64:
    x, y = xy_n[..., 0], xy_n[..., 1]
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def undistort(xy_d: F64, dist: F64, iters: int = 20) -> F64:
    """Invert :func:`distort` by fixed-point iteration (as ``cv2.undistortPoints``).

    Parameters
    ----------
    xy_d : (..., C, 2) float64
        Distorted normalised coordinates ``K^-1 uv``.
    dist : (C, 5) float64

    Returns
    -------
    (..., C, 2) float64
    """
    xy = xy_d.copy()
    for _ in range(iters):
        err = distort(xy, dist) - xy_d
        xy = xy - err
    return xy


def apply_K(xy: F64, K: F64) -> F64:
    """(..., C, 2) normalised -> pixels with ``K (C,3,3)`` (or any shape ``(..., 3, 3)``
    that broadcasts against ``xy[..., 0]``)."""
    x, y = xy[..., 0], xy[..., 1]
    u = K[..., 0, 0] * x + K[..., 0, 1] * y + K[..., 0, 2]
    v = K[..., 1, 1] * y + K[..., 1, 2]
    return np.stack([u, v], axis=-1)


def unapply_K(uv_px: F64, K: F64) -> F64:
    """(..., C, 2) pixels -> normalised coordinates (inverse of :func:`apply_K`; ``K`` as there)."""
    y = (uv_px[..., 1] - K[..., 1, 2]) / K[..., 1, 1]
    x = (uv_px[..., 0] - K[..., 0, 2] - K[..., 0, 1] * y) / K[..., 0, 0]
    return np.stack([x, y], axis=-1)


def project_points(X_world: F64, K: F64, dist: F64, R: F64, t: F64,
                   depth_sign: F64 | float = 1.0) -> tuple[F64, F64]:
    """Project world points into every camera, with distortion.

    Parameters
    ----------
    X_world : (..., 3) float64, metres
    K, dist, R, t : stacked camera arrays for ``C`` cameras

    Returns
    -------
    uv_px : (..., C, 2) float64
        Distorted pixels; NaN where the point is not in front of the camera.
    depth : (..., C) float64
        ``depth_sign * Z`` in the camera frame (metres), > 0 in front.
    """
    X_cam = cam_from_world_points(X_world, R, t)
    z = X_cam[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = X_cam[..., :2] / z[..., None]
    uv = apply_K(distort(xy, dist), K)
    depth = z * depth_sign
    uv = np.where((depth > 1e-9)[..., None], uv, np.nan)
    return uv, depth


def pixel_rays(uv_px: F64, K: F64, dist: F64, R: F64, t: F64,
               depth_sign: F64 | float = 1.0) -> tuple[F64, F64]:
    """Back-project distorted pixels to world rays.

    Parameters
    ----------
    uv_px : (..., C, 2) float64

    Returns
    -------
    origin_world : (C, 3) float64
        Camera centres.
    dir_world : (..., C, 3) float64
        Ray directions (unit), pointing out of the camera.
    """
    xy = undistort(unapply_K(uv_px, K), dist)
    d_cam = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
    d_cam = d_cam * np.asarray(depth_sign)[..., None]
    d_world = np.einsum("cji,...cj->...ci", R, d_cam)  # R^T d
    d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
    origin = -np.einsum("cji,cj->ci", R, t)
    return origin, d_world


class Cams(NamedTuple):
    """Stacked arrays of a rig's ``C`` cameras, as the batched functions take them."""

    K: F64  # (C, 3, 3)
    dist: F64  # (C, 5)
    R: F64  # (C, 3, 3) cam_from_world
    t: F64  # (C, 3) metres
    wh: F64  # (C, 2) pixels
    world_from_body: F64  # (3, 3), body z = up
    up: F64  # (3,)
    depth_sign: F64  # (C,) +1, or -1 for left-handed calibrations (see Camera)
    box_model: int = 0  # how a state draws its box: BoxModelEntry.index (types.BOX_MODEL_REGISTRY)

    @classmethod
    def of(cls, rig: Rig, box_model: str = "ellipsoid") -> Cams:
        return cls(rig.K, rig.dist, rig.R, rig.t, rig.wh, rig.world_from_body(), rig.up,
                   rig.depth_sign, BOX_MODEL_REGISTRY[box_model].index)

    @property
    def centres(self) -> F64:
        """(C, 3) each camera's centre in the world (``-R^T t``), metres."""
        return -np.einsum("cji,cj->ci", self.R, self.t)

    def take(self, idx: np.ndarray) -> Cams:
        """The cameras ``idx`` only (same body frame and box model)."""
        return Cams(self.K[idx], self.dist[idx], self.R[idx], self.t[idx], self.wh[idx],
                    self.world_from_body, self.up, self.depth_sign[idx], self.box_model)
