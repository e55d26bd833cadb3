"""Seeded synthetic scenes with known truth, written in any input layout.

People are vertical ellipsoids standing on the ground (centre height = vertical
semi-axis) walking smooth paths (a straight line plus a slow sinusoid) over a
rectangle seen by a ring of cameras with mild lens distortion. Each person is
annotated from a random first to a random last frame. Boxes are the exact
tangent boxes of the ellipsoids (:func:`gt3dkit.geom.conics.ellipsoid_boxes`),
plus Gaussian noise on every edge, clipped to the image and rounded to whole
pixels (truncated towards zero for the MultiviewX layout, as its generator does);
a view is dropped at random with probability ``dropout``.
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gt3dkit.geom.camera import Cams
from gt3dkit.geom.conics import ellipsoid_boxes
from gt3dkit.io.atomic import write_dir_atomically
from gt3dkit.io.datasets.wildtrack import LAYOUTS as GRID_LAYOUTS
from gt3dkit.io.datasets.wildtrack import GridLayout
from gt3dkit.types import F64, I64, Camera, Rig

SIM_LAYOUTS = ("wildtrack", "multiviewx", "native")


@dataclass(frozen=True)
class SimScene:
    """A synthetic scene.

    frames : (T,) frame numbers; fps : frame-number rate
    truth_frame, truth_id : (M,); center_world (M, 3), semi_axes (M, 3), metres
    boxes : (M, C, 4) annotated boxes in pixels (NaN = not seen)
    """

    rig: Rig
    frames: I64
    fps: float
    truth_frame: I64
    truth_id: I64
    center_world: F64
    semi_axes: F64
    boxes: F64


def _look_at(center: F64, target: F64) -> tuple[F64, F64]:
    """cam_from_world ``R, t`` of a camera at ``center`` looking at ``target`` (z up)."""
    z = target - center
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ center


def make_rig(n_cams: int, area_lo: F64, area_hi: F64, names: list[str],
             rng: np.random.Generator) -> Rig:
    """A ring of ``n_cams`` 1920x1080 cameras around the area, 2.5-6 m high, mild distortion."""
    mid = (area_lo + area_hi) / 2
    half = (area_hi - area_lo) / 2
    cams = []
    for i in range(n_cams):
        ang = 2 * np.pi * (i + rng.uniform(-0.15, 0.15)) / n_cams
        pos = np.r_[mid + (half + 5.0) * np.array([np.cos(ang), np.sin(ang)]), rng.uniform(2.5, 6)]
        target = np.r_[mid + rng.uniform(-0.2, 0.2, 2) * half, 0.8]
        R, t = _look_at(pos, target)
        f = rng.uniform(900, 1200)
        K = np.array([[f, 0, 960 + rng.uniform(-20, 20)], [0, f, 540 + rng.uniform(-20, 20)],
                      [0, 0, 1]])
        dist = np.array([rng.uniform(-0.08, -0.02), rng.uniform(0.0, 0.03),
                         rng.uniform(-1e-3, 1e-3), rng.uniform(-1e-3, 1e-3), 0.0])
        cams.append(Camera(names[i], 1920, 1080, K, dist, R, t))
    return Rig(tuple(cams), up=np.array([0.0, 0.0, 1.0]), frame_name="synthetic world (z up)")


def simulate(layout: str = "native", seed: int = 0, frames: int = 40, people: int = 10,
             noise_px: float = 0.0, dropout: float = 0.15) -> SimScene:
    """Generate a seeded scene. See the module docstring."""
    if layout not in SIM_LAYOUTS:
        raise ValueError(f"unknown layout {layout!r} (known: {', '.join(SIM_LAYOUTS)})")
    if frames < 2 or people < 1 or noise_px < 0 or not 0 <= dropout < 1:
        raise ValueError("need frames >= 2, people >= 1, noise_px >= 0, 0 <= dropout < 1")
    rng = np.random.default_rng(seed)
    if layout == "wildtrack":
        g = GRID_LAYOUTS["wildtrack"]
        lo, hi = np.array([-1.0, -6.0]), np.array([7.0, 14.0])
        names, step, fps = list(g.cameras), 5, g.fps
    elif layout == "multiviewx":
        g = GRID_LAYOUTS["multiviewx"]
        lo, hi = np.array([3.0, 2.0]), np.array([22.0, 14.0])
        names, step, fps = list(g.cameras), 1, g.fps
    else:
        lo, hi = np.array([-6.0, -4.0]), np.array([6.0, 4.0])
        names, step, fps = [f"cam{i}" for i in range(6)], 1, 10.0
    rig = make_rig(len(names), lo, hi, names, rng)
    frame_numbers = np.arange(frames, dtype=np.int64) * step + (1 if layout == "multiviewx" else 0)
    t_s = frame_numbers / fps
    T = t_s[-1] - t_s[0]
    rows_f, rows_id, centers, axes = [], [], [], []
    for pid in range(people):
        ab = rng.uniform(0.2, 0.3, 2)
        c = rng.uniform(0.8, 0.95)
        p0 = rng.uniform(lo + 1, hi - 1)
        p1 = rng.uniform(lo + 1, hi - 1)
        amp = rng.uniform(0.2, 0.6) * rng.normal(size=2) / np.sqrt(2)
        period = rng.uniform(8, 16)
        phase = rng.uniform(0, 2 * np.pi)
        first = int(rng.integers(0, frames // 3))
        last = int(rng.integers(2 * frames // 3, frames))
        for k in range(first, last + 1):
            s = (t_s[k] - t_s[0]) / max(T, 1e-9)
            xy = p0 + (p1 - p0) * s + amp * np.sin(2 * np.pi * (t_s[k] - t_s[0]) / period + phase)
            rows_f.append(frame_numbers[k])
            rows_id.append(pid)
            centers.append([xy[0], xy[1], c])
            axes.append([ab[0], ab[1], c])
    center = np.array(centers)
    semi = np.array(axes)
    cams = Cams.of(rig)
    box, margin = ellipsoid_boxes(center, semi, cams.world_from_body, cams.K, cams.dist, cams.R,
                                  cams.t, cams.depth_sign)
    box = box + rng.normal(scale=noise_px, size=box.shape) if noise_px > 0 else box
    W, H = cams.wh[:, 0], cams.wh[:, 1]
    inside = (margin > 0) & (box[..., 2] > 0) & (box[..., 0] < W - 1) & (box[..., 3] > 0) \
        & (box[..., 1] < H - 1)
    box = np.stack([np.clip(box[..., 0], 0, W - 1), np.clip(box[..., 1], 0, H - 1),
                    np.clip(box[..., 2], 0, W - 1), np.clip(box[..., 3], 0, H - 1)], -1)
    box = np.trunc(box) if layout == "multiviewx" else np.rint(box)
    seen = inside & (rng.uniform(size=inside.shape) >= dropout)
    seen &= (box[..., 2] > box[..., 0]) & (box[..., 3] > box[..., 1])
    box = np.where(seen[..., None], box, np.nan)
    return SimScene(rig=rig, frames=frame_numbers, fps=fps, truth_frame=np.array(rows_f),
                    truth_id=np.array(rows_id), center_world=center, semi_axes=semi, boxes=box)


def write_scene(sim: SimScene, out: Path, layout: str) -> None:
    """Write ``sim`` as an input folder of ``layout`` (atomically), with ``truth.csv``."""
    if layout not in SIM_LAYOUTS:
        raise ValueError(f"unknown layout {layout!r}")

    def write(tmp: Path) -> None:
        _write_truth(sim, tmp / "truth.csv")
        if layout == "native":
            _write_native(sim, tmp)
        else:
            _write_grid(sim, tmp, GRID_LAYOUTS[layout])

    write_dir_atomically(Path(out), write)


def _write_truth(sim: SimScene, path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "id", "x", "y", "z", "a", "b", "c"])
        for i in range(len(sim.truth_frame)):
            w.writerow([int(sim.truth_frame[i]), int(sim.truth_id[i]),
                        *(f"{v:.6f}" for v in sim.center_world[i]),
                        *(f"{v:.6f}" for v in sim.semi_axes[i])])


def _write_native(sim: SimScene, tmp: Path) -> None:
    doc = {"up": sim.rig.up.tolist(), "fps": sim.fps, "frame": sim.rig.frame_name, "units": "m",
           "cameras": [{"name": c.name, "width": c.width, "height": c.height,
                        "K": c.K.tolist(), "dist": c.dist.tolist(), "R": c.R.tolist(),
                        "t": c.t.tolist()} for c in sim.rig.cameras]}
    (tmp / "cameras.json").write_text(json.dumps(doc, indent=1))
    with open(tmp / "boxes.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["frame", "camera", "id", "xmin", "ymin", "xmax", "ymax"])
        for i in range(len(sim.truth_frame)):
            for c, cam in enumerate(sim.rig.cameras):
                b = sim.boxes[i, c]
                if np.all(np.isfinite(b)):
                    w.writerow([int(sim.truth_frame[i]), cam.name, int(sim.truth_id[i]),
                                *(f"{v:g}" for v in b)])


def _write_grid(sim: SimScene, tmp: Path, g: GridLayout) -> None:
    intr = tmp / "calibrations" / g.intrinsic_dir
    extr = tmp / "calibrations" / "extrinsic"
    intr.mkdir(parents=True)
    extr.mkdir(parents=True)
    for c in sim.rig.cameras:
        fs = cv2.FileStorage(str(intr / f"intr_{c.name}.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", c.K)
        fs.write("distortion_coefficients", c.dist.reshape(1, 5))
        fs.release()
        rvec, _ = cv2.Rodrigues(c.R)
        fs = cv2.FileStorage(str(extr / f"extr_{c.name}.xml"), cv2.FILE_STORAGE_WRITE)
        fs.write("rvec", rvec.reshape(3, 1))
        fs.write("tvec", (c.t / g.tvec_to_m).reshape(3, 1))
        fs.release()
    ann = tmp / "annotations_positions"
    ann.mkdir()
    width = 8 if g.name == "wildtrack" else 5
    pos = g.xy_to_position(sim.center_world[:, :2])
    for f in sim.frames:
        people = []
        for i in np.flatnonzero(sim.truth_frame == f):
            views = []
            for c in range(len(sim.rig.cameras)):
                b = sim.boxes[i, c]
                vals = [-1, -1, -1, -1] if not np.all(np.isfinite(b)) else [int(v) for v in b]
                views.append(dict(zip(("viewNum", "xmin", "ymin", "xmax", "ymax"), [c, *vals], strict=True)))
            people.append({"personID": int(sim.truth_id[i]), "positionID": int(pos[i]),
                           "views": views})
        (ann / f"{int(f):0{width}d}.json").write_text(json.dumps(people, indent=1))
