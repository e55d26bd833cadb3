"""Typed containers at the edges of the package.

Everything inside ``geom/`` and ``fusion/`` works on plain batched numpy arrays;
these frozen dataclasses carry those arrays between the loaders, the estimators
and the writers, and validate them once, at construction.

Conventions
-----------
* Cameras are ``cam_from_world``: ``X_cam = R @ X_world + t`` (OpenCV), metres.
* Pixels are OpenCV pixels of the *distorted* image (pixel centres at integers).
* Missing data is NaN (a box of four NaNs, a keypoint of two NaNs).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import numpy.typing as npt

F64 = npt.NDArray[np.float64]
I64 = npt.NDArray[np.int64]
B8 = npt.NDArray[np.bool_]


def _arr(x: Any, shape: tuple[int | None, ...], name: str, *, finite: bool = True) -> F64:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape, strict=True)):
        want = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"expected {name} of shape {want}, got {a.shape}")
    if finite and not np.all(np.isfinite(a)):
        raise ValueError(f"{name} has non-finite values")
    return a


@dataclass(frozen=True)
class Camera:
    """One calibrated pinhole camera with OpenCV lens distortion.

    Attributes
    ----------
    name : str
        The camera's name in the input (``"Camera1"``, ``"00_03"``, ...).
    width, height : int
        Image size in pixels.
    K : (3, 3) float64
        Intrinsic matrix (pixels).
    dist : (5,) float64
        OpenCV ``k1 k2 p1 p2 k3``.
    R : (3, 3) float64
        Rotation ``cam_from_world``.
    t : (3,) float64
        Translation ``cam_from_world``, metres.
    depth_sign : float
        +1 for a normal calibration, whose visible points have ``Z_cam > 0``. -1 for a
        calibration solved in a left-handed world (MultiviewX's Unity export): OpenCV's
        projection ``K (R X + t) / Z`` still holds, but seen points have ``Z_cam < 0``.
        Only "in front of the camera" tests and ray directions use it.
    """

    name: str
    width: int
    height: int
    K: F64
    dist: F64
    R: F64
    t: F64
    depth_sign: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", _arr(self.K, (3, 3), f"camera {self.name}: K"))
        d = np.asarray(self.dist, dtype=np.float64).reshape(-1)
        if d.size > 5 and np.any(d[5:] != 0):
            raise ValueError(
                f"camera {self.name}: only OpenCV k1 k2 p1 p2 k3 distortion is supported, "
                f"got {d.size} non-zero coefficients"
            )
        d = np.concatenate([d[:5], np.zeros(max(0, 5 - d.size))])
        object.__setattr__(self, "dist", _arr(d, (5,), f"camera {self.name}: dist"))
        R = _arr(self.R, (3, 3), f"camera {self.name}: R")
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
            raise ValueError(f"camera {self.name}: R is not a rotation matrix")
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", _arr(np.reshape(self.t, -1), (3,), f"camera {self.name}: t"))
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"camera {self.name}: image size must be positive")
        if self.depth_sign not in (1.0, -1.0):
            raise ValueError(f"camera {self.name}: depth_sign must be +1 or -1")
        if self.K[0, 0] <= 0 or self.K[1, 1] <= 0 or self.K[2, 2] != 1.0:
            raise ValueError(f"camera {self.name}: K must have positive focal lengths and K[2,2]=1")

    @property
    def center_world(self) -> F64:
        """(3,) camera centre in the world frame, metres."""
        return -self.R.T @ self.t


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
        up = _arr(np.reshape(self.up, -1), (3,), "up")
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

    @property
    def K(self) -> F64:
        return np.stack([c.K for c in self.cameras])

    @property
    def dist(self) -> F64:
        return np.stack([c.dist for c in self.cameras])

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


@dataclass(frozen=True)
class Observations:
    """2D annotations, one row per (frame, camera, object).

    Attributes
    ----------
    frame : (N,) int64
    cam : (N,) int64
        Index into ``Rig.cameras``.
    track_id : (N,) int64
    box_xyxy_px : (N, 4) float64
        ``xmin, ymin, xmax, ymax`` in distorted pixels; NaN = no box in this row.
    kpt_uv_px : (N, J, 2) float64
        Keypoints in distorted pixels; NaN = not seen. ``J`` may be 0.
    origin : tuple[str, ...]
        For each row, where it came from (``"file: entry"``), for error messages.
    """

    frame: I64
    cam: I64
    track_id: I64
    box_xyxy_px: F64
    kpt_uv_px: F64
    origin: tuple[str, ...]

    def __post_init__(self) -> None:
        n = len(self.frame)
        for name in ("frame", "cam", "track_id"):
            a = np.asarray(getattr(self, name), dtype=np.int64).reshape(-1)
            if a.shape != (n,):
                raise ValueError(f"expected {name} of shape ({n},), got {a.shape}")
            object.__setattr__(self, name, a)
        object.__setattr__(self, "box_xyxy_px", _arr(self.box_xyxy_px, (n, 4), "box_xyxy_px",
                                                     finite=False))
        k = np.asarray(self.kpt_uv_px, dtype=np.float64)
        if k.ndim != 3 or k.shape[0] != n or k.shape[2] != 2:
            raise ValueError(f"expected kpt_uv_px of shape ({n}, J, 2), got {k.shape}")
        object.__setattr__(self, "kpt_uv_px", k)
        if len(self.origin) != n:
            raise ValueError(f"expected {n} origins, got {len(self.origin)}")

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def n_joints(self) -> int:
        return int(self.kpt_uv_px.shape[1])

    @property
    def has_box(self) -> B8:
        """(N,) rows that carry a box."""
        return np.all(np.isfinite(self.box_xyxy_px), axis=1)

    def select(self, rows: npt.NDArray[Any]) -> Observations:
        rows = np.asarray(rows)
        idx = np.flatnonzero(rows) if rows.dtype == bool else rows
        return Observations(self.frame[idx], self.cam[idx], self.track_id[idx],
                            self.box_xyxy_px[idx], self.kpt_uv_px[idx],
                            tuple(self.origin[i] for i in idx))


@dataclass(frozen=True)
class GroundTruth:
    """What an input says the 3D truth is. NaN = not given.

    Attributes
    ----------
    frame, track_id : (M,) int64
    center_world : (M, 3) float64
        Ellipsoid centre (metres). For WILDTRACK/MultiviewX only the ground position
        is known: its two horizontal coordinates are set and the vertical one is NaN.
    semi_axes : (M, 3) float64
        Along body x, y, up (metres).
    kpt_world : (M, J, 3) float64
        3D joints (metres).
    """

    frame: I64
    track_id: I64
    center_world: F64
    semi_axes: F64
    kpt_world: F64
    source: str = ""


@dataclass(frozen=True)
class Scene:
    """A loaded input: rig, annotations, optional truth, and where they came from."""

    rig: Rig
    obs: Observations
    layout: str
    fps: float
    frames: I64
    truth: GroundTruth | None = None
    skeleton: str | None = None
    files: dict[str, str] = field(default_factory=dict)  # relative path -> sha256
    root: str = ""


@dataclass(frozen=True)
class TrackSet:
    """Estimator output: one row per (frame, object).

    Attributes
    ----------
    frame, track_id : (M,) int64
    center_world : (M, 3) float64, metres
    semi_axes : (M, 3) float64, metres, along body x, y, up
    center_sd : (M, 3) float64, metres, marginal standard deviation of the centre
    n_views : (M,) int64, cameras with an annotation of this object in this frame
    kpt_world : (M, J, 3) float64, metres (J may be 0)
    kpt_sd : (M, J) float64, metres (RMS over the three axes)
    info : dict
        Estimator name, parameters and diagnostics for ``meta.json``.
    """

    frame: I64
    track_id: I64
    center_world: F64
    semi_axes: F64
    center_sd: F64
    n_views: I64
    kpt_world: F64
    kpt_sd: F64
    info: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frame)
