r"""Batched projection with OpenCV's lens models: pinhole with its 5-parameter distortion, and fisheye.

Shapes: batch dimensions lead, then the camera axis ``C`` where there is one,
then the coordinate. Cameras are given as stacked arrays (see ``Rig``):
``K (C,3,3)``, ``dist (C,6)`` (the lens: coefficients and model, :func:`distort`),
``R (C,3,3)``, ``t (C,3)`` with ``X_cam = R X_world + t``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from gt3dkit.types import BOX_MODEL_REGISTRY, F64, LENS_CODES, Rig


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


#: Column of a stacked lens array (``dist (C, 6)``) that names the lens model; its codes.
LENS_COL = 5
PINHOLE, FISHEYE = LENS_CODES["pinhole"], LENS_CODES["fisheye"]


def lens_code(dist: F64) -> F64:
    """The lens model code of stacked lens arrays ``dist (..., 5|6)``: :data:`PINHOLE` where there
    is no model column (five OpenCV coefficients), else column :data:`LENS_COL`."""
    if dist.shape[-1] <= LENS_COL:
        return np.zeros(dist.shape[:-1])
    return dist[..., LENS_COL]


def distort(xy_n: F64, dist: F64) -> F64:
    r"""Apply a camera's lens model to normalised coordinates.

    OpenCV's pinhole model (radial-tangential, ``k1 k2 p1 p2 k3``):

    .. math::
        x' = x (1 + k_1 r^2 + k_2 r^4 + k_3 r^6) + 2 p_1 x y + p_2 (r^2 + 2 x^2)

    OpenCV's fisheye model (``cv::fisheye``, equidistant with ``k1 k2 k3 k4``), with
    :math:`\theta = \arctan r`:

    .. math::
        x' = \frac{\theta (1 + k_1 \theta^2 + k_2 \theta^4 + k_3 \theta^6 + k_4 \theta^8)}{r} x

    Parameters
    ----------
    xy_n : (..., C, 2) float64
        Undistorted normalised coordinates ``(X/Z, Y/Z)``.
    dist : (C, 5) or (C, 6) float64
        Per camera the model's coefficients (``k1 k2 p1 p2 k3``, or ``k1 k2 k3 k4 0`` for a
        fisheye), and in column :data:`LENS_COL` the model (:data:`PINHOLE` / :data:`FISHEYE`;
        absent: pinhole). Broadcast against ``xy_n[..., 0]``.

    Returns
    -------
    (..., C, 2) float64
    """
    code = lens_code(dist)
    fish = code == FISHEYE
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        if not np.any(fish):
            return _distort(xy_n, dist)
        out_f = _distort_fisheye(xy_n, dist)
        if np.all(fish):
            return out_f
        return np.where(np.broadcast_to(fish, xy_n.shape[:-1])[..., None], out_f, _distort(xy_n, dist))


def _distort(xy_n: F64, dist: F64) -> F64:
    x, y = xy_n[..., 0], xy_n[..., 1]
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=-1)


def fisheye_theta_d(theta: F64, dist: F64) -> F64:
    """OpenCV's fisheye ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)`` (``dist[..., :4]``)."""
    t2 = theta * theta
    k1, k2, k3, k4 = (dist[..., i] for i in range(4))
    return theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))


def _distort_fisheye(xy_n: F64, dist: F64) -> F64:
    r = np.hypot(xy_n[..., 0], xy_n[..., 1])
    theta_d = fisheye_theta_d(np.arctan(r), dist)
    scale = np.where(r > 1e-8, theta_d / np.where(r > 1e-8, r, 1.0), 1.0)  # as cv::fisheye
    return xy_n * scale[..., None]


def undistort(xy_d: F64, dist: F64, iters: int = 20) -> F64:
    """Invert :func:`distort`: fixed-point iteration for the pinhole model (as
    ``cv2.undistortPoints``), Newton on ``θ`` for the fisheye model (as
    ``cv2.fisheye.undistortPoints``).

    Parameters
    ----------
    xy_d : (..., C, 2) float64
        Distorted normalised coordinates ``K^-1 uv``.
    dist : (C, 5) or (C, 6) float64, as :func:`distort`

    Returns
    -------
    (..., C, 2) float64
        NaN for a fisheye point whose ray would be 90 degrees or more off the axis, or where
        its lens model turns back before reaching it.
    """
    fish = lens_code(dist) == FISHEYE
    xy = xy_d.copy()
    if not np.all(fish):
        for _ in range(iters):
            err = distort(xy, dist) - xy_d
            xy = xy - err
    if not np.any(fish):
        return xy
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out_f = _undistort_fisheye(xy_d, dist, iters)
    return np.where(np.broadcast_to(fish, xy_d.shape[:-1])[..., None], out_f, xy)


def _undistort_fisheye(xy_d: F64, dist: F64, iters: int) -> F64:
    theta_d = np.hypot(xy_d[..., 0], xy_d[..., 1])
    k1, k2, k3, k4 = (dist[..., i] for i in range(4))
    theta = np.minimum(theta_d, np.pi / 2)
    for _ in range(iters):
        t2 = theta * theta
        f = fisheye_theta_d(theta, dist) - theta_d
        df = 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))
        theta = theta - np.where(df > 0, f / np.where(df > 0, df, 1.0), 0.0)
    t2 = theta * theta
    ok = ((np.abs(fisheye_theta_d(theta, dist) - theta_d) < 1e-9 * np.maximum(1.0, theta_d))
          & (theta >= 0) & (theta < np.pi / 2)
          & (1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4))) > 0))
    scale = np.where(theta_d > 1e-8, np.tan(theta) / np.where(theta_d > 1e-8, theta_d, 1.0), 1.0)
    return np.where(ok[..., None], xy_d * scale[..., None], np.nan)


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
    dist: F64  # (C, 6) lens coefficients and model (distort)
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
