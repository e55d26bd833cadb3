"""Synthetic board views: a ChArUco board or a checkerboard drawn by OpenCV, seen through known
cameras with lens distortion (OpenCV's pinhole or fisheye model), blurred and with pixel noise.

Each output pixel is traced back: undistorted (the inverse of the camera's distortion, as
``cv2.undistortPoints``), cast as a ray, cut with the board's plane, and the board's printed image
is sampled there (``cv2.remap``, bilinear); outside the board a mid-grey wall. So a test checks
the calibration against cameras it did not make.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gt3dkit.calib.board import Board
from gt3dkit.geom.camera import unapply_K, undistort
from gt3dkit.rig import Camera, Rig
from gt3dkit.types import F64

PX_PER_SQUARE = 60  # the printed board's resolution
SUBPIXELS = 2  # points a pixel's side averaged (its area integrated)


@dataclass(frozen=True)
class BoardScene:
    rig: Rig
    world_from_board: F64  # (F, 4, 4)
    images: list[list[np.ndarray]]  # [camera][frame] (H, W) uint8


def board_image(board: Board) -> np.ndarray:
    """(H, W) uint8 print of the board, ``PX_PER_SQUARE`` pixels a square, no margin."""
    w, h = board.squares_x * PX_PER_SQUARE, board.squares_y * PX_PER_SQUARE
    if board.kind == "charuco":
        return board.opencv_board().generateImage((w, h), marginSize=0, borderBits=1)
    i, j = np.meshgrid(np.arange(w) // PX_PER_SQUARE, np.arange(h) // PX_PER_SQUARE)
    return np.where((i + j) % 2 == 0, 0, 255).astype(np.uint8)


def pixel_directions(cam: Camera, sub: int = SUBPIXELS) -> F64:
    """(H sub, W sub, 3) the rays of ``sub`` x ``sub`` points spread over each pixel, in the
    camera frame (``z = 1``): undistorted (the inverse of the camera's distortion, by fixed-point
    iteration as ``cv2.undistortPoints``). A pixel integrates the light over its area, so a
    rendered pixel is the mean of its points (:func:`render_view`)."""
    off = (np.arange(sub) + 0.5) / sub - 0.5
    u = (np.arange(cam.width)[:, None] + off).reshape(-1).astype(np.float64)
    v = (np.arange(cam.height)[:, None] + off).reshape(-1).astype(np.float64)
    uu, vv = np.meshgrid(u, v)
    uv = np.stack([uu, vv], -1)[:, :, None, :]  # (H, W, 1, 2)
    xy = undistort(unapply_K(uv, cam.K[None]), cam.lens_row[None], iters=30)[:, :, 0]  # (H, W, 2)
    return np.concatenate([xy, np.ones(xy.shape[:2] + (1,))], -1)


def render_view(
    d_cam: F64,
    cam_from_board: F64,
    board: Board,
    printed: np.ndarray,
    rng: np.random.Generator,
    noise: float = 2.0,
    blur: float = 0.6,
    sub: int = SUBPIXELS,
) -> np.ndarray:
    """(H, W) uint8 image of the board through a camera whose pixels' rays are ``d_cam``
    (:func:`pixel_directions` with the same ``sub``)."""
    import cv2

    R, t = cam_from_board[:3, :3], cam_from_board[:3, 3]
    # board point X (z = 0): R X + t = s d  ->  in the board frame, o + s e with o = -R^T t, e = R^T d
    o = -R.T @ t
    e = d_cam @ R  # (H, W, 3) = R^T d
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -o[2] / e[..., 2]
        X = o + s[..., None] * e
    ok = s > 0
    scale = PX_PER_SQUARE / board.square_m
    mx = np.where(ok, X[..., 0] * scale - 0.5, -10).astype(np.float32)
    my = np.where(ok, X[..., 1] * scale - 0.5, -10).astype(np.float32)
    img = cv2.remap(printed, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=128)
    h, w = img.shape[0] // sub, img.shape[1] // sub
    img = img.reshape(h, sub, w, sub).mean(axis=(1, 3), dtype=np.float32)  # each pixel's area
    img = cv2.GaussianBlur(img, (0, 0), blur) if blur > 0 else img
    img = img + rng.normal(0, noise, img.shape)
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def board_scene(
    board: Board,
    n_frames: int = 14,
    seed: int = 0,
    width: int = 640,
    height: int = 480,
    n_cams: int = 3,
    strong_lens: bool = False,
    lens: str = "pinhole",
) -> BoardScene:
    """``n_cams`` cameras on an arc 0.8 m from a board moved and tilted in front of them.

    ``lens="fisheye"``: wide lenses (OpenCV's fisheye model, focal about 0.35 x the width: some 80
    degrees either side of the axis across the image) on an arc 0.45 m from the board, which moves
    0.2-0.5 m from them and further across their views, so its corners reach the lenses' edges."""
    from scipy.spatial.transform import Rotation  # heavy to import (scipy): only where it runs

    rng = np.random.default_rng(seed)
    printed = board_image(board)
    cams = []
    centre = np.array([board.squares_x, board.squares_y, 0]) * board.square_m / 2
    wide = lens == "fisheye"
    arc_m = 0.45 if wide else 0.8
    for c in range(n_cams):
        ang = np.radians(-25 + 50 * c / max(1, n_cams - 1))
        pos = centre + np.array([arc_m * np.sin(ang), 0.05 * c, -arc_m * np.cos(ang)])
        z = centre - pos
        z /= np.linalg.norm(z)
        x = np.cross([0, 1.0, 0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        R = np.stack([x, y, z])  # cam_from_world rows
        f = rng.uniform(0.9, 1.1) * width * (0.35 if wide else 1.0)
        K = np.array(
            [
                [f, 0, width / 2 + rng.uniform(-10, 10)],
                [0, f * rng.uniform(0.995, 1.005), height / 2 + rng.uniform(-10, 10)],
                [0, 0, 1],
            ]
        )
        k1 = -0.25 if strong_lens else rng.uniform(-0.15, 0.05)
        dist = np.array([k1, 0.05 if strong_lens else 0.02, 0.0005, -0.0005, 0.0])
        if wide:
            dist = np.array([rng.uniform(0.0, 0.06), rng.uniform(-0.03, 0.0), 0.005, -0.001])
        cams.append(Camera(f"cam{c}", width, height, K, dist, R, -R @ pos, lens=lens))
    rig = Rig(tuple(cams), up=np.array([0.0, -1.0, 0.0]), frame_name="board scene")
    poses = []
    for _ in range(n_frames):
        rv = rng.normal(0, 0.35, 3)
        Rb = Rotation.from_rotvec(rv).as_matrix()
        # across the view, 0.45-0.85 m from the cameras (wide lenses: 0.2-0.5 m, further across)
        lo, hi = (-0.3, -0.25, -0.25), (0.3, 0.25, 0.05)
        if not wide:
            lo, hi = (-0.2, -0.15, -0.35), (0.2, 0.15, 0.05)
        tb = centre + rng.uniform(lo, hi) - Rb @ centre
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = Rb, tb
        poses.append(T)
    images = []
    for cam in cams:
        Tc = np.eye(4)
        Tc[:3, :3], Tc[:3, 3] = cam.R, cam.t
        d_cam = pixel_directions(cam, SUBPIXELS)
        images.append([render_view(d_cam, Tc @ T, board, printed, rng) for T in poses])
    return BoardScene(rig, np.array(poses), images)
