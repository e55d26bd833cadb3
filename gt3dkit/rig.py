"""The camera model and the rig: one calibrated camera with one of OpenCV's lens models (pinhole
with radial-tangential distortion, or fisheye), and the cameras of a recording with their world
frame.

Conventions: ``cam_from_world`` (``X_cam = R @ X_world + t``, OpenCV), metres, pixels of the
distorted image with pixel centres at integers. Every calibration format
(:mod:`gt3dkit.calib.formats`) converts to this at its edge. Validated once, at
construction: rotations (storage precision re-orthonormalised), intrinsics, a distortion
that does not fold the image, magnitudes.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]


def as_array(x: npt.ArrayLike, shape: tuple[int | None, ...], name: str, *, finite: bool = True) -> F64:
    """``x`` as float64 of ``shape`` (None = any length), or ValueError naming ``name``."""
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"expected {name} of shape {want}, got {a.shape}")
    if finite and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite values")
    return a


#: Largest ``max |R R^T - I|`` accepted (and re-orthonormalised) as storage precision of a
#: rotation matrix: 7 stored digits give ~1e-6, a real error (a wrong sign, a typo) ~1e-1.
R_STORAGE_TOL = 1e-4


#: Largest world coordinate (m) and intrinsic value (px) taken as a number, not a typo.
MAX_WORLD_M = 1e6
MAX_PIXELS = 1e7
MAX_DIST_COEF = 1e4

#: The lens models a camera may have (OpenCV's), and their codes in a stacked lens array
#: (:func:`gt3dkit.geom.camera.distort`: column 5).
LENSES = ("pinhole", "fisheye")
LENS_CODES = {"pinhole": 0.0, "fisheye": 1.0}


def _along_rays(K: F64, dist: F64, r: F64, th: F64) -> tuple[F64, F64, F64]:
    """OpenCV's distortion (k1 k2 p1 p2 k3) along rays of the undistorted (normalised) plane.

    Parameters
    ----------
    r : (1, N) radii, normalised; th : (T, 1) ray angles, rad.

    Returns
    -------
    u, v : (T, N) distorted pixels relative to the principal point
    det : (T, N) the map's Jacobian determinant (> 0 where it preserves orientation)
    """
    k1, k2, p1, p2, k3 = (float(v) for v in dist)
    x, y = r * np.cos(th), r * np.sin(th)
    with np.errstate(over="ignore", invalid="ignore"):
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        dr = k1 + 2 * k2 * r2 + 3 * k3 * r2**2  # d rad / d r2
        xd = x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        a = rad + 2 * x * x * dr + 2 * p1 * y + 6 * p2 * x
        b = 2 * x * y * dr + 2 * p1 * x + 2 * p2 * y  # both off-diagonal entries
        d = rad + 2 * y * y * dr + 6 * p1 * y + 2 * p2 * x
        return K[0, 0] * xd + K[0, 1] * yd, K[1, 1] * yd, a * d - b * b


def _corner_px(K: F64, width: int, height: int) -> F64:
    """(4, 2) the image's corners relative to the principal point, px."""
    c = np.array([[0, 0], [width - 1, 0], [0, height - 1], [width - 1, height - 1]], dtype=np.float64)
    return c - K[:2, 2]


def distortion_fold(K: F64, dist: F64, width: int, height: int) -> float | None:
    """Where OpenCV's distortion (k1 k2 p1 p2 k3) folds over before it covers the image.

    Walks rays from the principal point outwards in the undistorted (normalised) plane until
    their distorted image leaves the image; the map must stay orientation-preserving
    (Jacobian determinant > 0) all the way, else some pixels have two undistorted points.
    Returns None if it does, else the fraction of the way to the image border at the first
    fold (0 also when a ray never reaches the border: the lens squeezes the image).
    """
    if not np.any(dist):
        return None
    c = _corner_px(K, width, height)
    corner = float(np.max(np.hypot(c[:, 0] / K[0, 0], c[:, 1] / K[1, 1])))
    th = np.linspace(0, 2 * np.pi, 96, endpoint=False)[:, None]
    r = np.concatenate([np.linspace(0, 2 * corner, 301)[1:], np.linspace(2 * corner, 10 * corner, 101)[1:]])
    r = r[None, :]
    u, v, det = _along_rays(K, dist, r, th)
    with np.errstate(invalid="ignore"):
        u, v = u + K[0, 2], v + K[1, 2]
        out = ~((u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1))
    if not out.any(axis=1).all():
        return 0.0  # some ray stays inside: the distortion squeezes the image
    first_out = np.argmax(out, axis=1)  # (rays,)
    before = np.arange(r.shape[1])[None, :] < first_out[:, None]
    bad = before & ~(det > 0)
    if not bad.any():
        return None
    ray, k = np.argwhere(bad)[0]
    return float(r[0, k] / r[0, first_out[ray]])


def distortion_valid_radius(K: F64, dist: F64, width: int, height: int) -> float | None:
    """The distance (px) from the principal point, in the image, within which OpenCV's distortion
    (k1 k2 p1 p2 k3) is one-to-one; None where it is so over the whole image.

    Along 360 rays from the principal point in the undistorted plane, the image radius each ray
    reaches before the map stops being orientation-preserving (Jacobian determinant <= 0); the
    nearest such point bounds the valid disc. Beyond it a pixel has two undistorted points,
    so observations there cannot be used.
    """
    if not np.any(dist):
        return None
    corner_px = float(np.max(np.hypot(*_corner_px(K, width, height).T)))
    th = np.linspace(0, 2 * np.pi, 360, endpoint=False)[:, None]
    r = np.linspace(0, 10 * corner_px / min(K[0, 0], K[1, 1]), 4001)[1:][None, :]
    u, v, det = _along_rays(K, dist, r, th)
    bad = ~(det > 0)
    folds = bad.any(axis=1)
    if not folds.any():
        return None
    before = np.arange(r.shape[1])[None, :] < np.argmax(bad, axis=1)[:, None]
    with np.errstate(invalid="ignore"):
        reach = np.where(before, np.hypot(u, v), 0.0).max(axis=1)  # (rays,) px reached before each fold
    radius = float(reach[folds].min())
    return None if radius >= corner_px else radius


def fisheye_valid_radius(K: F64, dist: F64, width: int, height: int) -> float | None:
    """The distance (px) from the principal point within which OpenCV's fisheye model (``k1 k2 k3
    k4``) is one-to-one; None where it is so over the whole image (or up to 90 degrees off the
    axis, beyond which no ray of ``X/Z`` reaches).

    ``θ_d(θ)`` must increase over the rays the image holds; where it turns back first, the radius
    it reached there bounds the valid disc.
    """
    k1, k2, k3, k4 = (float(v) for v in dist[:4])
    f = min(K[0, 0], K[1, 1])
    corner = float(np.max(np.hypot(*_corner_px(K, width, height).T))) / f  # θ_d the image reaches
    th = np.linspace(0, np.pi / 2, 4001)[1:]
    t2 = th * th
    theta_d = th * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    slope = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
    inside = np.concatenate([[True], theta_d[:-1] < corner])  # rays up to the first beyond the corner
    bad = (slope <= 0) & inside
    if not bad.any():
        return None
    reach = float(np.max(theta_d[: int(np.argmax(bad))], initial=0.0))
    return reach * f


#: A lens model that turns back (folds) within the image is read, with its observations beyond
#: the fold left out, when it is one-to-one over at least this fraction of the half of the
#: image's shorter side around the principal point (anipose's k1-only fits of strong lenses turn
#: back near the image's corners, 1.08 x the half height on the shared mouse rig); nearer the
#: centre it is a typo or a calibration of another image size, and refused.
MIN_VALID_RADIUS = 0.9


@dataclass(frozen=True)
class Camera:
    """One calibrated camera: OpenCV's pinhole model with its lens distortion, or its fisheye model.

    Attributes
    ----------
    name : str
        The camera's name in the input (``"Camera1"``, ``"00_03"``, ...).
    width, height : int
        Image size in pixels.
    K : (3, 3) float64
        Intrinsic matrix (pixels).
    dist : (5,) float64
        OpenCV ``k1 k2 p1 p2 k3`` for the pinhole model; ``k1 k2 k3 k4 0`` for the fisheye model
        (``cv::fisheye``: ``θ_d = θ (1 + k1 θ² + k2 θ⁴ + k3 θ⁶ + k4 θ⁸)``, ``θ`` the ray's angle off
        the axis).
    R : (3, 3) float64
        Rotation ``cam_from_world``.
    t : (3,) float64
        Translation ``cam_from_world``, metres.
    r_deviation : float
        ``max |R R^T - I|`` of the rotation as stored, before it was re-orthonormalised
        (calibrations stored to 6-7 digits are off by ~1e-6; up to
        :data:`R_STORAGE_TOL` is accepted as storage precision, more is an error).
    depth_sign : float
        +1 for a normal calibration, whose visible points have ``Z_cam > 0``. -1 for a
        calibration solved in a left-handed world (MultiviewX's Unity export): OpenCV's
        projection ``K (R X + t) / Z`` still holds, but seen points have ``Z_cam < 0``.
        Only "in front of the camera" tests and ray directions use it.
    valid_radius_px : float or None
        Where the lens model turns back before the image's corners: the distance (px) from the
        principal point within which it is one-to-one (computed; observations beyond it are
        left out). None: one-to-one over the whole image.
    lens : str
        ``"pinhole"`` or ``"fisheye"`` (:data:`LENSES`).
    """

    name: str
    width: int
    height: int
    K: F64
    dist: F64
    R: F64
    t: F64
    depth_sign: float = 1.0
    r_deviation: float = 0.0
    valid_radius_px: float | None = None
    lens: str = "pinhole"

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", as_array(self.K, (3, 3), f"camera {self.name}: K"))
        if self.lens not in LENSES:
            raise ValueError(f"camera {self.name}: lens {self.lens!r} is not one of {', '.join(LENSES)}")
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if self.lens == "fisheye":
            if d.size not in (4, 5) or (d.size == 5 and d[4] != 0):
                raise ValueError(f"camera {self.name}: a fisheye lens has OpenCV's 4 coefficients "
                                 f"k1 k2 k3 k4, got {d.size}")
            d = np.concatenate([d[:4], [0.0]])
        elif d.size not in (0, 4, 5, 8, 12, 14):  # OpenCV's distortion vector lengths
            raise ValueError(f"camera {self.name}: dist has {d.size} coefficients; OpenCV's "
                             "k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]] has 4, 5, 8, 12 or 14")
        if d.size > 5 and np.any(d[5:] != 0):
            raise ValueError(
                f"camera {self.name}: only OpenCV k1 k2 p1 p2 k3 distortion is supported, "
                f"got {d.size} non-zero coefficients"
            )
        d = np.concatenate([d[:5], np.zeros(max(0, 5 - d.size))])
        object.__setattr__(self, "dist", as_array(d, (5,), f"camera {self.name}: dist"))
        R = as_array(self.R, (3, 3), f"camera {self.name}: R")
        if np.abs(R).max() > 1 + R_STORAGE_TOL:  # (and R R^T would overflow)
            raise ValueError(f"camera {self.name}: R is not a rotation matrix (an entry of "
                             f"magnitude {np.abs(R).max():.3g})")
        dev = float(np.abs(R @ R.T - np.eye(3)).max())
        if dev > R_STORAGE_TOL or np.linalg.det(R) < 0:
            raise ValueError(f"camera {self.name}: R is not a rotation matrix "
                             f"(max |R R^T - I| = {dev:.2g}, det = {np.linalg.det(R):.4g}; "
                             f"up to {R_STORAGE_TOL:g} is accepted as storage precision)")
        if dev > 1e-9:  # beyond float round-off
            U, _, Vt = np.linalg.svd(R)  # nearest rotation (Frobenius norm)
            R = U @ Vt
            object.__setattr__(self, "r_deviation", max(float(self.r_deviation), dev))
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", as_array(np.reshape(self.t, -1), (3,), f"camera {self.name}: t"))
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera {self.name}: image size must be positive")
        if self.depth_sign not in (1.0, -1.0):
            raise ValueError(f"camera {self.name}: depth_sign must be +1 or -1")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0 or self.K[2, 2] != 1.0:
            raise ValueError(f"camera {self.name}: K must have positive focal lengths and K[2,2]=1")
        if self.K[1, 0] != 0 or self.K[2, 0] != 0 or self.K[2, 1] != 0:
            raise ValueError(f"camera {self.name}: K must be upper triangular "
                             "[[fx, s, cx], [0, fy, cy], [0, 0, 1]]")
        if np.abs(self.K).max() > MAX_PIXELS or np.abs(self.t).max() > MAX_WORLD_M:
            raise ValueError(f"camera {self.name}: K beyond {MAX_PIXELS:g} px or t beyond "
                             f"{MAX_WORLD_M:g} m")
        if np.abs(self.dist).max() > MAX_DIST_COEF:
            raise ValueError(f"camera {self.name}: a dist coefficient beyond {MAX_DIST_COEF:g}")
        if self.lens == "fisheye":
            self._check_fisheye()
            return
        fold = distortion_fold(self.K, self.dist, int(self.width), int(self.height))
        if fold is not None:
            radius = distortion_valid_radius(self.K, self.dist, int(self.width), int(self.height))
            half = 0.5 * min(self.width, self.height)
            if fold == 0.0 or radius is None or radius < MIN_VALID_RADIUS * half:
                raise ValueError(f"camera {self.name}: dist {np.round(self.dist, 6).tolist()} folds the "
                                 f"image (the radial distortion turns back at {fold:.0%} of the way to the "
                                 "farthest corner"
                                 + (f", {radius:.0f} px from the principal point" if radius else "")
                                 + "): not a calibration of this image size")
            object.__setattr__(self, "valid_radius_px", radius)

    def _check_fisheye(self) -> None:
        radius = fisheye_valid_radius(self.K, self.dist, int(self.width), int(self.height))
        if radius is None:
            return
        if radius < MIN_VALID_RADIUS * 0.5 * min(self.width, self.height):
            k = np.round(self.dist[:4], 6).tolist()
            raise ValueError(f"camera {self.name}: fisheye coefficients {k} "
                             f"turn back {radius:.0f} px from the principal point: not a calibration of "
                             "this image size")
        object.__setattr__(self, "valid_radius_px", radius)

    @property
    def center_world(self) -> F64:
        """(3,) camera centre in the world frame, metres."""
        return -self.R.T @ self.t

    @property
    def coefficients(self) -> F64:
        """The lens model's own coefficients: ``k1 k2 p1 p2 k3`` (5,), or a fisheye's ``k1 k2 k3 k4`` (4,)."""
        return self.dist[:4] if self.lens == "fisheye" else self.dist

    @property
    def lens_row(self) -> F64:
        """(6,) the lens as the batched geometry takes it: ``dist`` and the model's code
        (:func:`gt3dkit.geom.camera.distort`)."""
        return np.append(self.dist, LENS_CODES[self.lens])


@dataclass(frozen=True)
class Rig:
    """Cameras keyed by index ``cam`` (0..C-1) in a fixed order, and the world frame.

    The stacked arrays (``K (C,3,3)``, ``dist (C,5)``, ``R (C,3,3)``, ``t (C,3)``,
    ``wh (C,2)``) are what the batched geometry functions take.
    """

    cameras: tuple[Camera, ...]
    up: F64 = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    frame_name: str = "input world frame"

    def __post_init__(self) -> None:
        if len(self.cameras) == 0:
            raise ValueError("a rig needs at least one camera")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate camera names in rig: {names}")
        up = as_array(np.reshape(self.up, -1), (3,), "up")
        n = np.linalg.norm(up)
        if n == 0:
            raise ValueError("up vector must be non-zero")
        object.__setattr__(self, "up", up / n)

    @property
    def names(self) -> list[str]:
        return [c.name for c in self.cameras]

    def index(self, name: str) -> int:
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(name) from None

    def in_metres(self, metres_per_unit: float) -> Rig:
        """This rig with its lengths given in a unit of ``metres_per_unit`` metres (an anipose
        calibration's board units: millimetres) in metres: every camera's translation scaled
        (its rotation and intrinsics are without length)."""
        return replace(self, cameras=tuple(replace(c, t=c.t * metres_per_unit) for c in self.cameras))

    @property
    def K(self) -> F64:
        return np.stack([c.K for c in self.cameras])

    @property
    def dist(self) -> F64:
        """(C, 6) each camera's lens: its coefficients and its model's code (:attr:`Camera.lens_row`)."""
        return np.stack([c.lens_row for c in self.cameras])

    @property
    def R(self) -> F64:
        return np.stack([c.R for c in self.cameras])

    @property
    def t(self) -> F64:
        return np.stack([c.t for c in self.cameras])

    @property
    def depth_sign(self) -> F64:
        return np.array([c.depth_sign for c in self.cameras], dtype=np.float64)

    @property
    def wh(self) -> F64:
        return np.array([[c.width, c.height] for c in self.cameras], dtype=np.float64)

    def world_from_body(self) -> F64:
        """(3, 3) rotation whose third column is ``up``; the body x axis is the world
        axis most orthogonal to ``up`` (world x for z-up and y-down worlds)."""
        up = self.up
        ax = np.eye(3)[int(np.argmin(np.abs(up)))]
        x = ax - up * (ax @ up)
        x /= np.linalg.norm(x)
        y = np.cross(up, x)
        return np.stack([x, y, up], axis=1)


