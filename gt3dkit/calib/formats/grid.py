"""WILDTRACK / MultiviewX calibrations: ``calibrations/<intrinsic dir>/intr_<CAM>.xml`` (K,
distortion) and ``calibrations/extrinsic/extr_<CAM>.xml`` (rvec, tvec in the layout's units),
read and written."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gt3dkit.calib.formats.opencv import read_storage
from gt3dkit.errors import InputError
from gt3dkit.parse import read_hashed
from gt3dkit.rig import Camera, Rig

# cv2 is imported in the functions that use it: 26 MB and 30 ms that a run whose calibration is
# not WILDTRACK's or MultiviewX's never needs


@dataclass(frozen=True)
class GridLayout:
    name: str
    cameras: tuple[str, ...]
    intrinsic_dir: str
    tvec_to_m: float
    grid_width: int  # cells along x
    grid_height: int  # cells along y
    cell_m: float
    origin_xy_m: tuple[float, float]
    fps: float
    truncated_px: bool = False
    width: int = 1920
    height: int = 1080

    @property
    def n_positions(self) -> int:
        """Cells of the positionID grid (1440 x 480 WILDTRACK, 1000 x 640 MultiviewX)."""
        return self.grid_width * self.grid_height

    def position_to_xy(self, pos: np.ndarray) -> np.ndarray:
        """(N,) positionID -> (N, 2) ground x, y in metres."""
        pos = np.asarray(pos, dtype=np.int64)
        x = self.origin_xy_m[0] + self.cell_m * (pos % self.grid_width)
        y = self.origin_xy_m[1] + self.cell_m * (pos // self.grid_width)
        return np.stack([x, y], axis=-1).astype(np.float64)

    def xy_to_position(self, xy: np.ndarray) -> np.ndarray:
        ix = np.rint((xy[..., 0] - self.origin_xy_m[0]) / self.cell_m).astype(np.int64)
        iy = np.rint((xy[..., 1] - self.origin_xy_m[1]) / self.cell_m).astype(np.int64)
        return iy * self.grid_width + ix


WILDTRACK = GridLayout(
    name="wildtrack",
    cameras=("CVLab1", "CVLab2", "CVLab3", "CVLab4", "IDIAP1", "IDIAP2", "IDIAP3"),
    intrinsic_dir="intrinsic_zero", tvec_to_m=0.01, grid_width=480, grid_height=1440, cell_m=0.025,
    origin_xy_m=(-3.0, -9.0), fps=10.0,
)
MULTIVIEWX = GridLayout(
    name="multiviewx",
    cameras=("Camera1", "Camera2", "Camera3", "Camera4", "Camera5", "Camera6"),
    intrinsic_dir="intrinsic", tvec_to_m=1.0, grid_width=1000, grid_height=640, cell_m=0.025,
    origin_xy_m=(0.0, 0.0), fps=2.0,
    # MultiviewX's generatePOM.py stores projected box edges with ``astype(int)``, which
    # truncates towards zero: the edge lies in [v, v+1) (v >= 0), so v + 0.5 is unbiased.
    truncated_px=True,
)
LAYOUTS = {g.name: g for g in (WILDTRACK, MULTIVIEWX)}


def load_camera(root: Path, g: GridLayout, name: str, files: dict[str, str]) -> Camera | None:
    import cv2
    intr = root / "calibrations" / g.intrinsic_dir / f"intr_{name}.xml"
    extr = root / "calibrations" / "extrinsic" / f"extr_{name}.xml"
    if not intr.exists() and not extr.exists():
        return None
    for p in (intr, extr):
        if not p.exists():
            raise InputError(str(p), f"missing calibration file for camera {name}")
    (intr_raw, intr_sha), (extr_raw, extr_sha) = read_hashed(intr), read_hashed(extr)  # each read once
    K, dist = read_storage(intr, ("camera_matrix", "distortion_coefficients"), intr_raw)
    rvec, tvec = read_storage(extr, ("rvec", "tvec"), extr_raw)
    if K.shape != (3, 3) or rvec.size != 3 or tvec.size != 3:
        raise InputError(str(extr), f"camera {name}: expected 3x3 camera_matrix, 3-vector rvec/tvec")
    R, _ = cv2.Rodrigues(rvec.reshape(3))
    for p, digest in ((intr, intr_sha), (extr, extr_sha)):
        files[str(p.relative_to(root))] = digest
    t = tvec.reshape(3) * g.tvec_to_m
    # Chirality: a camera of these ground-plane datasets looks down at the ground, so the
    # ray through the middle of its bottom image row meets z = 0 in front of it. Where it
    # only does so for negative depth, the calibration was solved in a left-handed world
    # (MultiviewX: Unity), and seen points have Z_cam < 0.
    bottom = np.linalg.solve(K, np.array([K[0, 2], g.height - 1.0, 1.0]))
    sign = 1.0 if (R.T @ bottom)[2] < 0 else -1.0
    try:
        return Camera(name=name, width=g.width, height=g.height, K=K, dist=dist.reshape(-1),
                      R=np.asarray(R, dtype=np.float64), t=t, depth_sign=sign)
    except ValueError as e:
        raise InputError(str(intr), str(e)) from None


def layout_of(root: Path) -> GridLayout | None:
    for g in LAYOUTS.values():
        if (Path(root) / "calibrations" / g.intrinsic_dir).is_dir():
            return g
    return None


def read(root: Path, g: GridLayout | None = None) -> Rig:
    root = Path(root)
    g = g or layout_of(root)
    if g is None:
        raise InputError(str(root), "no calibrations/intrinsic_zero or calibrations/intrinsic")
    files: dict[str, str] = {}
    cams = [c for c in (load_camera(root, g, n, files) for n in g.cameras) if c is not None]
    if not cams:
        raise InputError(str(root / "calibrations"), "no camera calibrations found")
    return Rig(tuple(cams), frame_name=f"{g.name} world (x, y on the ground, z up)")


def write(rig: Rig, root: Path, g: GridLayout) -> None:
    """The calibration files of ``rig`` in ``g``'s layout under ``root``."""
    import cv2
    intr = Path(root) / "calibrations" / g.intrinsic_dir
    extr = Path(root) / "calibrations" / "extrinsic"
    intr.mkdir(parents=True, exist_ok=True)
    extr.mkdir(parents=True, exist_ok=True)
    for c in rig.cameras:
        fs = cv2.FileStorage(str(intr / f"intr_{c.name}.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", c.K)
        fs.write("distortion_coefficients", c.dist.reshape(1, 5))
        fs.release()
        rvec, _ = cv2.Rodrigues(c.R)
        fs = cv2.FileStorage(str(extr / f"extr_{c.name}.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("rvec", rvec.reshape(3, 1))
        fs.write("tvec", (c.t / g.tvec_to_m).reshape(3, 1))
        fs.release()
