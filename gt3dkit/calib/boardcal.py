r"""A rig from board views: intrinsics per camera, extrinsics, one bundle adjustment.

Steps (:func:`calibrate_board`):

1. **Intrinsics** per camera, from all its views (``cv2.calibrateCameraExtended``: Zhang's
   planar method, then Levenberg-Marquardt on OpenCV's ``k1 k2 p1 p2 k3`` pinhole model).
   A view that reprojects far worse than the camera's others (OpenCV's per-view errors: board
   found wrongly, a marker misread, motion blur) is left out and the fit repeated.
2. **Board poses** per view (``cv2.solvePnP``, IPPE for a plane, then LM refinement).
3. **Extrinsics**: for every pair of cameras, the relative pose each frame both saw implies;
   the medoid of those (the candidate nearest the others) is the pair's pose. A maximum
   spanning tree over the pairs (weighted by shared frames) chains every camera to the first.
   A camera no chain reaches is named: its extrinsics cannot be found. A checkerboard, which
   looks the same turned by 180 degrees, is read the way that agrees with the other cameras.
4. **Bundle adjustment** over every camera's intrinsics and pose and every board pose
   (:class:`BoardProblem`, :func:`robust_lm`: soft-L1 loss of scale 1 px), the board's corners
   held at their printed positions, which fixes the metric scale. Then views that reproject far
   worse than their camera's others are dropped and it runs again.

The same problem with the cameras held poses the board in frames left out of the fit
(:func:`pose_boards`: the held-out check, and any rig's reprojection on given corners).

Why not pycolmap's or GTSAM's bundle adjuster: COLMAP's OPENCV model has no ``k3`` (the shared
mouse rig's lenses need it) and its FULL_OPENCV model refines ``k3`` only with the rational
``k4 k5 k6``, which our camera model does not hold; its adjuster takes a moving board only as
COLMAP rig frames with constant 3D points; GTSAM has no factor for a point on a moving board seen through a
camera with Brown-Conrady distortion and unknown intrinsics except as a Python
``CustomFactor``, called once per corner per iteration. Why not scipy's ``least_squares``
for small problems: its exact trust region takes an SVD of the whole (residuals x parameters)
Jacobian at every step (2.9 s against 1.1 s for the shared rig, the same minimum to 1e-7 px),
and its iterative one needs 170 steps. Beyond :data:`DENSE_MAX_PARAMS` parameters scipy's
sparse trust region is used.

Uncertainty: the parameters' covariance is ``s^2 (J^T J)^{-1}`` at the solution (``s^2`` the
residuals' variance), from which each camera's focal, centre and rotation sd follow.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from scipy.sparse import csc_matrix

from gt3dkit.calib.board import Board
from gt3dkit.calib.boardinput import View
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import distort
from gt3dkit.geom.triangulate import normalized_points
from gt3dkit.rig import LENS_CODES, LENSES, Camera, Rig
from gt3dkit.types import F64, JsonDict

#: A camera's intrinsics in the solver: ``fx fy cx cy`` and its lens's five coefficients (``k1 k2 p1
#: p2 k3``, or a fisheye's ``k1 k2 k3 k4 0``, whose fifth is never moved); an intrinsics row
#: (``INTR_WIDTH``) adds the lens model's code (:func:`gt3dkit.geom.camera.distort`).
N_INTR = 9
INTR_WIDTH = 10
#: A camera's lens is chosen by the data (``lens="auto"``) as OpenCV's fisheye model when that
#: model's corner RMS is below this fraction of the pinhole model's on the views both kept.
FISHEYE_GAIN = 0.8
#: Up to this many parameters (about 300 board frames) the solver takes Levenberg-Marquardt steps
#: on a dense Jacobian; beyond, scipy's iterative trust-region steps on a sparse one.
DENSE_MAX_PARAMS = 2000
#: Rounds of the joint fit (each after the first without the views the last showed wrong).
ROUNDS = 3


@dataclass(frozen=True)
class BoardConfig:
    """Settings of :func:`calibrate_board`.

    ``origin``: ``"camera"`` (the first camera's frame; up = its image's up) or ``"floor"`` (the
    board of ``floor_frame``, or of the frame the most cameras saw, as the floor: x, y on the
    board, z up towards the cameras, origin at its first inner corner).
    ``holdout_every``: every k-th synchronised frame (k-1, 2k-1, ...) is left out of the fits and
    reported on its own; 0 keeps every frame.
    ``fixed``: cameras whose intrinsics are given (matched by name): only their poses are found.
    """

    origin: str = "camera"
    floor_frame: int | None = None
    holdout_every: int = 0
    outlier_px: float = 1.5  # a view is wrong when its RMS exceeds this and 4x the camera's median
    fixed: tuple[Camera, ...] = ()
    min_views: int = 6  # fewer views than this: a warning, and the focal's sd says how uncertain
    lens: str = "auto"  # "pinhole", "fisheye" or "auto" (each camera's by the data: FISHEYE_GAIN)
    lens_of: tuple[tuple[str, str], ...] = ()  # (camera, lens) pairs that override ``lens``

    def __post_init__(self) -> None:
        for who, lens in (("", self.lens), *self.lens_of):
            if lens not in (*LENSES, "auto"):
                raise ValueError(f"{who + ': ' if who else ''}lens {lens!r} is not one of "
                                 f"{', '.join((*LENSES, 'auto'))}")

    def lens_for(self, name: str) -> str:
        """The lens asked of camera ``name``: its own, else the rig's."""
        return dict(self.lens_of).get(name, self.lens)


@dataclass(frozen=True)
class CameraReport:
    """What the calibration says of one camera."""

    name: str
    views_used: int
    rms_px: float
    p95_px: float
    holdout_rms_px: float | None
    worst: tuple[tuple[str, float], ...]  # (view label, RMS px), worst first
    dropped: tuple[tuple[str, str], ...]  # (view label, why)
    focal_sd_px: float
    centre_sd_mm: float
    rotation_sd_deg: float
    uv_used_px: F64  # (N, 2) every corner the fit used: where the image is covered


@dataclass(frozen=True)
class BoardCalibration:
    rig: Rig
    cameras: tuple[CameraReport, ...]
    board: Board
    frame_poses: dict[int, F64]  # synchronised frame -> (4, 4) world_from_board
    warnings: tuple[str, ...]
    holdout_frames: tuple[int, ...]

    def report(self) -> JsonDict:
        return {
            "board": self.board.describe(),
            "world_frame": self.rig.frame_name,
            "up": self.rig.up.tolist(),
            "holdout_frames": list(self.holdout_frames),
            "warnings": list(self.warnings),
            "cameras": {
                c.name: {
                    "lens": self.rig.cameras[self.rig.index(c.name)].lens,
                    "views_used": c.views_used,
                    "rms_px": c.rms_px,
                    "p95_px": c.p95_px,
                    "holdout_rms_px": c.holdout_rms_px,
                    "worst_views": [{"view": v, "rms_px": e} for v, e in c.worst],
                    "dropped_views": [{"view": v, "why": w} for v, w in c.dropped],
                    "focal_sd_px": c.focal_sd_px,
                    "centre_sd_mm": c.centre_sd_mm,
                    "rotation_sd_deg": c.rotation_sd_deg,
                }
                for c in self.cameras
            },
        }


# ----------------------------------------------------------------------------- geometry


def rt_matrix(rvec: F64, t: F64) -> F64:
    """(..., 4, 4) rigid transforms from (..., 3) rotation vectors and translations."""
    from scipy.spatial.transform import Rotation  # heavy to import (scipy): only where it runs

    T = np.zeros(np.shape(rvec)[:-1] + (4, 4))
    R = Rotation.from_rotvec(np.reshape(rvec, (-1, 3))).as_matrix()
    T[..., :3, :3] = R.reshape(T.shape[:-2] + (3, 3))
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def rt_vector(T: F64) -> F64:
    """(..., 6) rotation vector and translation of (..., 4, 4) rigid transforms."""
    from scipy.spatial.transform import Rotation  # heavy to import (scipy): only where it runs

    rv = Rotation.from_matrix(np.reshape(T[..., :3, :3], (-1, 3, 3))).as_rotvec()
    return np.concatenate([rv.reshape(T.shape[:-2] + (3,)), T[..., :3, 3]], axis=-1)


def rigid_inverse(T: F64) -> F64:
    """(..., 4, 4) inverses of rigid transforms."""
    out = np.zeros_like(T)
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _pose_distance(a: F64, b: F64, scale_m: float) -> F64:
    """Rotation angle (rad) plus translation distance in ``scale_m`` units of broadcast (..., 4, 4) pairs."""
    dR = np.einsum("...ji,...jk->...ik", a[..., :3, :3], b[..., :3, :3])
    ang = np.arccos(np.clip((np.trace(dR, axis1=-2, axis2=-1) - 1) / 2, -1, 1))
    return ang + np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1) / scale_m


def project(X_cam: F64, intr: F64) -> F64:
    """(M, 2) distorted pixels of (M, 3) camera-frame points with per-point intrinsics rows
    (M, ``INTR_WIDTH``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = distort(X_cam[:, :2] / X_cam[:, 2:3], intr[:, 4:INTR_WIDTH])
    return xy * intr[:, 0:2] + intr[:, 2:4]


def intr_row(K: F64, lens_row: F64) -> F64:
    """(``INTR_WIDTH``,) a camera's intrinsics row of its K (3, 3) and lens (6,)."""
    return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *lens_row])


def intr_lens(intr: F64) -> str:
    """The lens model's name of an intrinsics row."""
    return next(n for n, code in LENS_CODES.items() if code == intr[N_INTR])


def rig_arrays(rig: Rig, names: Sequence[str]) -> tuple[F64, F64]:
    """``names``' intrinsics rows (C, ``INTR_WIDTH``) and cam_from_world poses (C, 4, 4) in ``rig``."""
    cams = [rig.cameras[rig.index(n)] for n in names]
    intr = np.array([intr_row(c.K, c.lens_row) for c in cams])
    T = np.tile(np.eye(4), (len(cams), 1, 1))
    T[:, :3, :3] = [c.R for c in cams]
    T[:, :3, 3] = [c.t for c in cams]
    return intr, T


def intr_K(intr: F64) -> F64:
    """(3, 3) K of one camera's intrinsics row."""
    return np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1]])


# ----------------------------------------------------------------------------- intrinsics


@dataclass(frozen=True)
class IntrinsicsFit:
    """One camera's intrinsics from its own board views: its intrinsics row (``INTR_WIDTH``,), the
    focal's sd (px; NaN where the model's fit gives none), the views kept (indices) with their RMS
    (px), and those dropped (index, why)."""

    intr: F64
    focal_sd_px: float
    keep: list[int]
    keep_rms_px: F64
    dropped: list[tuple[int, str]]

    @property
    def lens(self) -> str:
        return intr_lens(self.intr)


def _wrong_view(rms: float, median: float, model: str) -> str:
    return (f"reprojects {rms:.1f} px with this camera's {model} intrinsics (its views' median "
            f"{median:.2f} px): the board was found wrongly")


def fit_intrinsics(
    views: Sequence[View], board: Board, size: tuple[int, int], outlier_px: float, lens: str = "pinhole"
) -> IntrinsicsFit:
    """One camera's intrinsics from its views with OpenCV's ``lens`` model; ``"auto"``: both
    models, and the fisheye where its corner RMS on the views both kept is below
    :data:`FISHEYE_GAIN` times the pinhole's."""
    pin = _fit_pinhole(views, board, size, outlier_px)
    if lens == "pinhole":
        return pin
    fish = _fit_fisheye(views, board, pin, outlier_px)
    if lens == "fisheye":
        return fish
    both = sorted(set(pin.keep) & set(fish.keep))
    rms_p = np.sqrt(np.mean(pin.keep_rms_px[[pin.keep.index(k) for k in both]] ** 2))
    rms_f = np.sqrt(np.mean(fish.keep_rms_px[[fish.keep.index(k) for k in both]] ** 2))
    return fish if rms_f < FISHEYE_GAIN * rms_p else pin


def _fit_fisheye(views: Sequence[View], board: Board, pin: IntrinsicsFit, outlier_px: float) -> IntrinsicsFit:
    """OpenCV's fisheye model fitted to one camera's views by the joint fit's own solver
    (:class:`BoardProblem`: its intrinsics and each view's board pose), from the pinhole fit's K and
    an equidistant lens, dropping views that reproject badly as :func:`_fit_pinhole` does.

    Not ``cv2.fisheye.calibrate``: its start (``InitExtrinsics``) fails its own assertion on views
    whose corners reach far off the axis, the views a wide lens needs (16 of 38 single views of the
    simulator's 1280 x 1024 fisheye cameras)."""
    intr = pin.intr.copy()
    intr[4:N_INTR] = 0.0
    intr[N_INTR] = LENS_CODES["fisheye"]
    one = [replace(v, cam=0, synced=False) for v in views]
    corners = board.corners_board()
    keep = list(range(len(one)))
    dropped: list[tuple[int, str]] = []
    sd = float("nan")
    for round_ in range(ROUNDS + 1):
        use = [one[k] for k in keep]
        poses = np.array([rt_vector(board_pose(v, board, intr)) for v in use])
        prob, _ = board_problem(use, [corners[v.det.ids] for v in use], intr[None], np.zeros((1, 6)),
                                np.ones(1, bool), np.zeros(1, bool))
        res = solve(prob, prob.pack(intr[None], np.zeros((1, 6)), poses))
        intr = prob.split(res.x)[0][0]
        rms = prob.view_rms(res.fun, len(use))
        sd = float(_covariance_sd(res, prob)[0][0])
        median = float(np.median(rms))
        bad = np.flatnonzero(rms > max(outlier_px, 4 * median))
        if not bad.size or len(keep) - bad.size < 3 or round_ == ROUNDS:
            break
        dropped += [(keep[j], _wrong_view(rms[j], median, "fisheye")) for j in bad]
        keep = [k for j, k in enumerate(keep) if j not in set(bad.tolist())]
    return IntrinsicsFit(intr, sd, keep, rms, dropped)


def _fit_pinhole(
    views: Sequence[View], board: Board, size: tuple[int, int], outlier_px: float
) -> IntrinsicsFit:
    """``cv2.calibrateCameraExtended`` (pinhole, ``k1 k2 p1 p2 k3``), dropping views that OpenCV's
    own per-view errors mark as wrong."""
    import cv2

    corners = board.corners_board().astype(np.float32)
    obj = [corners[v.det.ids] for v in views]
    img = [v.det.uv_px.astype(np.float32) for v in views]
    keep = list(range(len(views)))
    dropped: list[tuple[int, str]] = []
    flags = cv2.CALIB_USE_INTRINSIC_GUESS
    if len(views) < 4:  # too few views for the full model: principal point at the centre, no k3
        flags |= cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    K0 = np.array([[max(size), 0, (size[0] - 1) / 2], [0, max(size), (size[1] - 1) / 2], [0, 0, 1]])
    for _ in range(4):
        _, K, d, _, _, sd, _, per_view = cv2.calibrateCameraExtended(
            [obj[k] for k in keep], [img[k] for k in keep], size, K0.copy(), np.zeros(5), flags=flags
        )
        rms = per_view.reshape(-1)
        median = float(np.median(rms))
        bad = np.flatnonzero(rms > max(outlier_px, 4 * median))
        if not bad.size or len(keep) - bad.size < 3:
            break
        dropped += [(keep[j], _wrong_view(rms[j], median, "pinhole")) for j in bad]
        keep = [k for j, k in enumerate(keep) if j not in set(bad.tolist())]
        kept_rms = np.delete(rms, bad)  # (the last round's drops are not refitted)
    else:
        rms = kept_rms
    sd_f = float(np.hypot(sd[0, 0], sd[1, 0]) / np.sqrt(2)) if np.all(np.isfinite(sd[:2])) else float("nan")
    lens_row = np.r_[np.asarray(d, dtype=np.float64).reshape(-1)[:5], LENS_CODES["pinhole"]]
    return IntrinsicsFit(intr_row(np.asarray(K, dtype=np.float64), lens_row), sd_f, keep,
                         np.asarray(rms, dtype=np.float64), dropped)


def board_pose(view: View, board: Board, intr: F64) -> F64:
    """(4, 4) cam_from_board of one view (IPPE, then LM) with a camera's intrinsics row; through a
    fisheye lens, on the corners' undistorted normalised coordinates (OpenCV's PnP knows only the
    pinhole model)."""
    import cv2

    X = board.corners_board()[view.det.ids]
    K, d, uv = intr_K(intr), intr[4 : 4 + 5], view.det.uv_px
    if intr_lens(intr) == "fisheye":
        uv = normalized_points(uv[:, None], K[None], intr[None, 4:INTR_WIDTH])[:, 0]
        # (a corner beyond 90 degrees off the axis has no such point)
        seen = np.asarray(np.isfinite(uv).all(1))
        X, uv, K, d = X[seen], uv[seen], np.eye(3), np.zeros(5)
    ok, rv, tv = cv2.solvePnP(X, uv, K, d, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rv, tv = cv2.solvePnP(X, uv, K, d, flags=cv2.SOLVEPNP_ITERATIVE)
    rv, tv = cv2.solvePnPRefineLM(X, uv, K, d, rv, tv)
    return rt_matrix(np.asarray(rv, dtype=np.float64).reshape(3), np.asarray(tv, dtype=np.float64).reshape(3))


# ----------------------------------------------------------------------------- extrinsics


def _flips(board: Board) -> F64:
    """(R, 4, 4) board-frame transforms between the readings a detection may have: the identity,
    and for a checkerboard its 180 degree turn about the board's centre (corners read backwards)."""
    if board.kind == "charuco":
        return np.eye(4)[None]
    nx, ny = board.inner
    F = np.diag([-1.0, -1.0, 1.0, 1.0])
    F[:2, 3] = np.array([nx + 1, ny + 1]) * board.square_m
    return np.stack([np.eye(4), F])


def _scale_m(board: Board) -> float:
    """The length a pose distance counts a radian as: the board's longer inner side."""
    return board.square_m * max(board.inner)


def _medoid(cands: F64, scale_m: float) -> F64:
    D = _pose_distance(cands[:, None], cands[None, :], scale_m)
    return cands[int(np.argmin(np.median(D, axis=1) if len(cands) > 2 else D.sum(1)))]


def chain_cameras(poses: dict[tuple[int, int], F64], n_cams: int, names: Sequence[str], board: Board) -> F64:
    """(C, 4, 4) cam_from_ref of every camera from per-view cam_from_board poses keyed (cam, frame)."""
    by_frame: dict[int, dict[int, F64]] = defaultdict(dict)
    for (c, f), T in poses.items():
        by_frame[f][c] = T
    flips = _flips(board)
    pair: dict[tuple[int, int], list[F64]] = defaultdict(list)
    for seen in by_frame.values():
        cs = sorted(seen)
        for i, a in enumerate(cs):
            for b in cs[i + 1 :]:  # b_from_a, each reading of b's board
                pair[(a, b)] += list(seen[b] @ flips @ rigid_inverse(seen[a]))
    weight = {k: len(v) // len(flips) for k, v in pair.items()}
    rel = {k: _medoid(np.array(v), _scale_m(board)) for k, v in pair.items()}
    out = np.full((n_cams, 4, 4), np.nan)
    out[0] = np.eye(4)
    done = {0}
    while True:  # Prim's maximum spanning tree from camera 0
        edges = [(w, a, b) for (a, b), w in weight.items() if (a in done) != (b in done)]
        if not edges:
            break
        _, a, b = max(edges)
        if a in done:
            out[b] = rel[(a, b)] @ out[a]
            done.add(b)
        else:
            out[a] = rigid_inverse(rel[(a, b)]) @ out[b]
            done.add(a)
    missing = [names[c] for c in range(n_cams) if c not in done]
    if missing:
        raise InputError(
            ", ".join(missing),
            f"never sees the board in the same frame as {names[0]} or a camera "
            "linked to it: its extrinsics cannot be found (film the board "
            "where it and another camera both see it)",
        )
    return out


def _frame_starts(views: Sequence[View], cam_from_board: Sequence[F64], cam_from_ref: F64) -> dict[int, F64]:
    """Each synchronised frame's ref_from_board, from the view of it that saw the most corners."""
    best: dict[int, int] = {}
    for k, v in enumerate(views):
        if v.synced and (v.frame not in best or len(v.det.ids) > len(views[best[v.frame]].det.ids)):
            best[v.frame] = k
    return {f: rigid_inverse(cam_from_ref[views[k].cam]) @ cam_from_board[k] for f, k in best.items()}


def _read_corners(
    views: Sequence[View],
    cam_from_board: Sequence[F64],
    cam_from_ref: F64,
    frame_pose: dict[int, F64],
    board: Board,
) -> list[F64]:
    """Each view's corners in the board frame (N, 3), in the reading (of a checkerboard's two) that
    agrees with its frame's pose."""
    flips = _flips(board)
    corners = board.corners_board()
    out = []
    for v, T in zip(views, cam_from_board, strict=True):
        X = corners[v.det.ids]
        if v.synced and len(flips) > 1:
            want = cam_from_ref[v.cam] @ frame_pose[v.frame]
            F = flips[int(np.argmin(_pose_distance(T @ flips, want, _scale_m(board))))]
            X = X @ F[:3, :3].T + F[:3, 3]
        out.append(X)
    return out


# ----------------------------------------------------------------------------- the problem


@dataclass(frozen=True)
class BoardProblem:
    """Every corner observation of a board calibration, flattened for the solver.

    The parameters ``x`` are, in order, the free cameras' intrinsics (``N_INTR`` each), the free
    cameras' cam_from_ref poses (6 each: rotation vector, translation) and every board pose (6
    each). A board pose is ref_from_board for a synchronised frame, or cam_from_board for a view of
    no synchronised frame (``local``). What is not free is taken from ``intr0`` and ``ext0``.

    Arrays, one entry per corner observation ``M``: ``cam``, ``pose`` (board pose index),
    ``local`` (bool), ``view`` (index into the views), ``X`` (M, 3) board-frame corner, metres,
    ``uv`` (M, 2) its detected pixel.
    """

    cam: np.ndarray
    pose: np.ndarray
    local: np.ndarray
    view: np.ndarray
    X: F64
    uv: F64
    intr0: F64  # (C, INTR_WIDTH) intrinsics rows
    ext0: F64  # (C, 6)
    n_poses: int
    free_intr: np.ndarray  # (C,) bool
    free_ext: np.ndarray  # (C,) bool
    sparsity: csc_matrix = field(init=False, repr=False)
    groups: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        C = len(self.intr0)
        col_intr = np.where(self.free_intr, N_INTR * (np.cumsum(self.free_intr) - 1), -1)
        n_intr = N_INTR * int(self.free_intr.sum())
        col_ext = np.where(self.free_ext, n_intr + 6 * (np.cumsum(self.free_ext) - 1), -1)
        col_pose = n_intr + 6 * int(self.free_ext.sum())
        M = len(self.cam)
        rows, cols = [], []
        blocks = (
            (col_pose + 6 * self.pose, 6, np.ones(M, bool)),
            (col_intr[self.cam], N_INTR, col_intr[self.cam] >= 0),
            (col_ext[self.cam], 6, (col_ext[self.cam] >= 0) & ~self.local),
        )
        for start, n, on in blocks:
            m = np.flatnonzero(on)
            for k in range(2):  # a corner's x and y residuals
                rows.append(np.repeat(2 * m + k, n))
                cols.append((start[m, None] + np.arange(n)).reshape(-1))
        r, c = np.concatenate(rows), np.concatenate(cols)
        n_params = col_pose + 6 * self.n_poses
        object.__setattr__(
            self, "sparsity", csc_matrix((np.ones(len(r), np.int8), (r, c)), shape=(2 * M, n_params))
        )
        # columns that touch disjoint residuals share a group: the same entry of every free camera's
        # intrinsics, of every free camera's pose, of every board pose
        groups = np.concatenate(
            [
                np.tile(np.arange(N_INTR), int(self.free_intr.sum())),
                N_INTR + np.tile(np.arange(6), int(self.free_ext.sum())),
                N_INTR + 6 + np.tile(np.arange(6), self.n_poses),
            ]
        )
        object.__setattr__(self, "groups", groups)
        if C != len(self.ext0):
            raise ValueError(f"intr0 has {C} cameras, ext0 {len(self.ext0)}")

    @property
    def n_params(self) -> int:
        return int(self.sparsity.shape[1])

    def split(self, x: F64) -> tuple[F64, F64, F64]:
        """Intrinsics rows (C, INTR_WIDTH), cam_from_ref poses (C, 6) and board poses (P, 6) of ``x``."""
        n_i, n_e = N_INTR * int(self.free_intr.sum()), 6 * int(self.free_ext.sum())
        intr, ext = self.intr0.copy(), self.ext0.copy()
        intr[self.free_intr, :N_INTR] = x[:n_i].reshape(-1, N_INTR)
        ext[self.free_ext] = x[n_i : n_i + n_e].reshape(-1, 6)
        return intr, ext, x[n_i + n_e :].reshape(-1, 6)

    def pack(self, intr: F64, ext: F64, poses: F64) -> F64:
        return np.concatenate(
            [intr[self.free_intr, :N_INTR].reshape(-1), ext[self.free_ext].reshape(-1), poses.reshape(-1)]
        )

    def residuals(self, x: F64) -> F64:
        """(2 M,) reprojection residuals, px (a corner behind its camera: 1e4)."""
        intr, ext, poses = self.split(x)
        Tp = rt_matrix(poses[:, :3], poses[:, 3:])[self.pose]
        Tc = rt_matrix(ext[:, :3], ext[:, 3:])[self.cam]
        Xb = np.einsum("mij,mj->mi", Tp[:, :3, :3], self.X) + Tp[:, :3, 3]
        Xc = np.einsum("mij,mj->mi", Tc[:, :3, :3], Xb) + Tc[:, :3, 3]
        Xc = np.where(self.local[:, None], Xb, Xc)
        return np.nan_to_num(project(Xc, intr[self.cam]) - self.uv, nan=1e4).reshape(-1)

    def jacobian(self, x: F64) -> F64:
        """Dense forward-difference Jacobian (2 M, n), one residual evaluation per column group."""
        f0 = self.residuals(x)
        J = np.zeros((len(f0), len(x)))
        h = 1e-7 * np.maximum(1.0, np.abs(x))
        for g in np.unique(self.groups):
            cols = np.flatnonzero(self.groups == g)
            dx = np.zeros_like(x)
            dx[cols] = h[cols]
            df = self.residuals(x + dx) - f0
            rows, which = self.sparsity[:, cols].nonzero()
            J[rows, cols[which]] = df[rows] / h[cols[which]]
        return J

    def view_rms(self, r: F64, n_views: int) -> F64:
        """(V,) RMS reprojection (px) of each view, of residuals ``r`` (2 M,)."""
        e2 = (r.reshape(-1, 2) ** 2).sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.sqrt(np.bincount(self.view, e2, n_views) / np.bincount(self.view, minlength=n_views))


PoseKey = tuple[int, int]  # (-1, frame) for a synchronised frame; (camera, frame) for a view alone


def _pose_key(v: View) -> PoseKey:
    return (-1, v.frame) if v.synced else (v.cam, v.frame)


def board_problem(
    views: Sequence[View],
    X: Sequence[F64],
    intr0: F64,
    ext0: F64,
    free_intr: np.ndarray,
    free_ext: np.ndarray,
) -> tuple[BoardProblem, list[PoseKey]]:
    """The problem of ``views`` (their corners ``X`` in the board frame) and its board poses' keys
    (:data:`PoseKey`)."""
    keys: list[PoseKey] = []
    index: dict[PoseKey, int] = {}
    pose = []
    for v in views:
        key = _pose_key(v)
        if key not in index:
            index[key] = len(keys)
            keys.append(key)
        pose.append(index[key])
    n = [len(x) for x in X]
    prob = BoardProblem(
        cam=np.repeat([v.cam for v in views], n),
        pose=np.repeat(pose, n),
        local=np.repeat([not v.synced for v in views], n).astype(bool),
        view=np.repeat(np.arange(len(views)), n),
        X=np.concatenate(X),
        uv=np.concatenate([v.det.uv_px for v in views]),
        intr0=intr0,
        ext0=ext0,
        n_poses=len(keys),
        free_intr=free_intr,
        free_ext=free_ext,
    )
    return prob, keys


@dataclass(frozen=True)
class LMResult:
    """A solve's parameters ``x``, residuals ``fun`` and Jacobian ``jac`` there (dense, or sparse
    from scipy's solver), and how many residual evaluations it took."""

    x: F64
    fun: F64
    jac: Any
    nfev: int


def robust_lm(
    fun: Callable[[F64], F64],
    jac: Callable[[F64], F64],
    x0: F64,
    f_scale: float = 1.0,
    max_iter: int = 50,
    tol: float = 1e-10,
) -> LMResult:
    r"""Levenberg-Marquardt with soft-L1 weights (iteratively reweighted least squares).

    Minimises :math:`\sum_i \rho(r_i^2)` with :math:`\rho(z) = 2 s^2 (\sqrt{1 + z/s^2} - 1)`
    (scipy's ``soft_l1``) by Gauss-Newton steps on :math:`w_i r_i` with :math:`w_i =
    \rho'(r_i^2)^{1/2}` (Triggs et al., "Bundle adjustment: a modern synthesis", 2000, sec. 3.3),
    damped by Marquardt's diagonal scaling; each step solves the (parameters x parameters) normal
    equations. ``fun(x) -> (M,)``, ``jac(x) -> (M, n)``.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    f, nfev = fun(x), 1

    def cost(r: F64) -> float:
        return float(np.sum(2 * f_scale**2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))

    c, lam, J = cost(f), 1e-3, jac(x)
    for _ in range(max_iter):
        w = (1 + (f / f_scale) ** 2) ** -0.25  # sqrt of rho'
        Jw = J * w[:, None]
        A, g = Jw.T @ Jw, Jw.T @ (w * f)
        d = np.diag(A).copy()
        d[d == 0] = 1.0
        step = None
        for _try in range(10):
            try:
                trial = -np.linalg.solve(A + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            fn = fun(x + trial)
            nfev += 1
            if cost(fn) < c:
                step = trial
                break
            lam *= 10
        if step is None:
            break
        cn = cost(fn)
        x, f, lam = x + step, fn, max(lam / 10, 1e-9)
        converged = c - cn < tol * max(c, 1e-12) or np.linalg.norm(step) < tol * (1 + np.linalg.norm(x))
        c = cn
        if converged:
            break
        J = jac(x)
    return LMResult(x, f, jac(x), nfev)


def solve(prob: BoardProblem, x0: F64) -> LMResult:
    """:func:`robust_lm` on a dense Jacobian up to :data:`DENSE_MAX_PARAMS` parameters, else scipy's
    sparse trust region (the same soft-L1 loss)."""
    from scipy.optimize import least_squares  # heavy to import (scipy): only where it runs

    if prob.n_params <= DENSE_MAX_PARAMS:
        return robust_lm(prob.residuals, prob.jacobian, x0)
    res = least_squares(
        prob.residuals,
        x0,
        jac_sparsity=prob.sparsity,
        method="trf",
        x_scale="jac",
        loss="soft_l1",
        f_scale=1.0,
        max_nfev=300,
    )
    return LMResult(res.x, res.fun, res.jac, int(res.nfev))


def _covariance_sd(res: LMResult, prob: BoardProblem) -> tuple[F64, F64, F64]:
    """Per camera: focal sd (px), centre sd (m), rotation sd (rad), from ``s^2 (J^T J)^{-1}``
    (NaN for what is held, and for problems beyond :data:`DENSE_MAX_PARAMS` parameters)."""
    C = len(prob.intr0)
    f_sd, c_sd, r_sd = np.full(C, np.nan), np.zeros(C), np.zeros(C)
    if prob.n_params > DENSE_MAX_PARAMS:
        return f_sd, c_sd * np.nan, r_sd * np.nan
    J = res.jac.toarray() if hasattr(res.jac, "toarray") else np.asarray(res.jac)
    s2 = float(np.sum(res.fun**2) / max(1, len(res.fun) - len(res.x)))
    cov = np.linalg.pinv(J.T @ J) * s2
    free = np.flatnonzero(prob.free_intr)
    fx = N_INTR * np.arange(len(free))  # each free camera's fx column; fy follows
    f_sd[free] = np.sqrt(0.5 * (cov[fx, fx] + cov[fx + 1, fx + 1]))
    _, ext, _ = prob.split(res.x)
    start = N_INTR * len(free)
    for k, c in enumerate(np.flatnonzero(prob.free_ext)):
        S = cov[start + 6 * k : start + 6 * k + 6, start + 6 * k : start + 6 * k + 6]
        r_sd[c] = np.sqrt(np.trace(S[:3, :3]) / 3)
        # the centre -R^T t: its covariance through the map's Jacobian (central differences)
        Jc = np.zeros((3, 6))
        for j in range(6):
            dp = np.zeros(6)
            dp[j] = 1e-6
            hi, lo = (
                rt_matrix((ext[c] + dp)[:3], (ext[c] + dp)[3:]),
                rt_matrix((ext[c] - dp)[:3], (ext[c] - dp)[3:]),
            )
            Jc[:, j] = (rigid_inverse(hi)[:3, 3] - rigid_inverse(lo)[:3, 3]) / 2e-6
        c_sd[c] = np.sqrt(np.trace(Jc @ S @ Jc.T) / 3)
    return f_sd, c_sd, r_sd


# ----------------------------------------------------------------------------- poses with the rig held


def pose_boards(
    rig: Rig, names: Sequence[str], views: Sequence[View], board: Board
) -> tuple[dict[int, F64], list[F64]]:
    """The board's pose in each synchronised frame of ``views`` with ``rig``'s cameras held (a
    checkerboard read the way that agrees with the frame), and each view's residuals (N, 2) px.

    ``views[k].cam`` indexes ``names``. Returns world_from_board (4, 4) per frame.
    """
    intr, T = rig_arrays(rig, names)
    vpose = [board_pose(v, board, intr[v.cam]) for v in views]
    starts = _frame_starts(views, vpose, T)
    X = _read_corners(views, vpose, T, starts, board)
    held = np.zeros(len(names), bool)
    prob, keys = board_problem(views, X, intr, rt_vector(T), held, held)
    res = solve(prob, prob.pack(intr, rt_vector(T), rt_vector(np.array([starts[f] for _, f in keys]))))
    _, _, poses = prob.split(res.x)
    r = res.fun.reshape(-1, 2)
    return (
        {f: rt_matrix(p[:3], p[3:]) for (_, f), p in zip(keys, poses, strict=True)},
        [r[prob.view == k] for k in range(len(views))],
    )


# ----------------------------------------------------------------------------- the calibration


def _wrong_views(vr: F64, cams: np.ndarray, outlier_px: float) -> np.ndarray:
    """Views whose RMS exceeds ``outlier_px`` and 4x their camera's median."""
    med = np.array([np.median(vr[cams == c]) if (cams == c).any() else 0.0 for c in range(cams.max() + 1)])
    return np.flatnonzero(vr > np.maximum(outlier_px, 4 * med[cams]))


def _intrinsics(views: list[View], board: Board, names: Sequence[str], sizes: Sequence[tuple[int, int]],
                cfg: BoardConfig, hold: set[int], dropped: dict[int, list[tuple[str, str]]],
                warnings: list[str]) -> tuple[F64, F64, list[View]]:
    """Step 1 of the module docstring: each camera's intrinsics rows ``(C, INTR_WIDTH)`` (given, or
    fitted on its own views but the held-out frames'), their focal sds ``(C,)`` (NaN: given) and
    the views the joint fit starts from; the views left out added to ``dropped``, warnings to
    ``warnings``."""
    C = len(names)
    fixed = {c.name: c for c in cfg.fixed}
    intr, f_sd0 = np.zeros((C, INTR_WIDTH)), np.full(C, np.nan)
    fit: list[View] = []
    for c, name in enumerate(names):
        vs = [v for v in views if v.cam == c and not (v.synced and v.frame in hold)]
        if name in fixed:
            given = fixed[name]
            if (given.width, given.height) != tuple(sizes[c]):
                raise InputError(
                    name,
                    f"the given intrinsics are for {given.width}x{given.height} images, its "
                    f"board views are {sizes[c][0]}x{sizes[c][1]}",
                )
            intr[c] = intr_row(given.K, given.lens_row)
            fit += vs
            continue
        if not vs:
            raise InputError(
                name,
                "the board was found in none of its frames: check the board's description "
                "(dictionary, square count, marker size; for anipose's board.toml marker_bits "
                "and dict_size) and that the frames show it",
            )
        if len(vs) < cfg.min_views:
            warnings.append(
                f"camera {name}: {len(vs)} board views (fewer than {cfg.min_views}): its intrinsics "
                "are uncertain (see its focal sd)"
            )
        got = fit_intrinsics(vs, board, sizes[c], cfg.outlier_px, cfg.lens_for(name))
        intr[c], f_sd0[c] = got.intr, got.focal_sd_px
        fit += [vs[k] for k in got.keep]
        dropped[c] += [(vs[k].label, why) for k, why in got.dropped]
    return intr, f_sd0, fit


class JointFit(NamedTuple):
    """The joint fit's end (module docstring, step 4): its views ``fit``, problem, residuals
    ``fun``, each view's rms ``vr``, the sds of each camera's focal (px), centre (m) and rotation
    (rad), and the intrinsics rows."""

    fit: list[View]
    prob: BoardProblem
    fun: F64
    vr: F64
    f_sd: F64
    c_sd: F64
    r_sd: F64
    intr: F64


def _lens_warnings(rig: Rig, prob: BoardProblem) -> list[str]:
    """A warning per camera whose fitted lens model turns back within the image (how far the
    board's corners reached)."""
    out = []
    for cam in rig.cameras:
        if cam.valid_radius_px is not None:
            reach = float(np.max(np.hypot(*(prob.uv[prob.cam == rig.index(cam.name)] - cam.K[:2, 2]).T)))
            out.append(
                f"camera {cam.name}: the fitted lens model turns back {cam.valid_radius_px:.0f} px "
                f"from the principal point (the board's corners reached {reach:.0f} px): film the "
                "board nearer the image's corners to calibrate the lens there"
            )
    return out


def _reports(rig: Rig, names: Sequence[str], board: Board, held_views: list[View], joint: JointFit,
             dropped: dict[int, list[tuple[str, str]]], warnings: list[str]) -> list[CameraReport]:
    """Step 6 of the module docstring: each camera's figures from the ``joint`` fit, the held-out
    frames posed with the rig held; a warning where a focal length is uncertain by more than 1 %."""
    fit, prob, fun, vr, f_sd, c_sd, r_sd, intr = joint
    held_r = pose_boards(rig, names, held_views, board)[1] if held_views else []
    e = np.sqrt((fun.reshape(-1, 2) ** 2).sum(1))
    reports = []
    for c, name in enumerate(names):
        m = prob.cam == c
        ks = [k for k, v in enumerate(fit) if v.cam == c]
        worst = sorted(((fit[k].label, float(vr[k])) for k in ks), key=lambda t: -t[1])[:3]
        hr = [r for v, r in zip(held_views, held_r, strict=True) if v.cam == c]
        hold_rms = float(np.sqrt(np.mean(np.sum(np.concatenate(hr) ** 2, axis=1)))) if hr else None
        reports.append(
            CameraReport(
                name,
                len(ks),
                float(np.sqrt(np.mean(e[m] ** 2))),
                float(np.percentile(e[m], 95)),
                hold_rms,
                tuple(worst),
                tuple(dropped[c]),
                float(f_sd[c]),
                float(c_sd[c]) * 1e3,
                float(np.degrees(r_sd[c])),
                prob.uv[m],
            )
        )
        if np.isfinite(f_sd[c]) and f_sd[c] > 0.01 * intr[c, 0]:
            warnings.append(
                f"camera {name}: focal length uncertain by {f_sd[c]:.1f} px (more than 1 %): film the "
                "board closer, tilted, and over the whole image"
            )
    return reports


def calibrate_board(
    views: list[View], board: Board, names: Sequence[str], sizes: Sequence[tuple[int, int]], cfg: BoardConfig
) -> BoardCalibration:
    """The rig of ``names`` from their board ``views`` (see the module docstring)."""
    C = len(names)
    warnings: list[str] = []
    synced = sorted({v.frame for v in views if v.synced})
    k_out = cfg.holdout_every
    hold = {f for f in synced if k_out > 0 and f % k_out == k_out - 1}
    held_views = [v for v in views if v.synced and v.frame in hold]
    dropped: dict[int, list[tuple[str, str]]] = defaultdict(list)
    # 1. intrinsics
    fixed = {c.name: c for c in cfg.fixed}
    intr, f_sd0, fit = _intrinsics(views, board, names, sizes, cfg, hold, dropped, warnings)
    # 2. poses of every view, 3. extrinsics
    vpose = [board_pose(v, board, intr[v.cam]) for v in fit]
    seen = {v.cam for v in fit if v.synced}
    if seen and len(seen) < C:
        raise InputError(
            ", ".join(n for c, n in enumerate(names) if c not in seen),
            "has no board view taken together with the other cameras: its extrinsics cannot be found",
        )
    if seen:
        rig_T = chain_cameras(
            {(v.cam, v.frame): T for v, T in zip(fit, vpose, strict=True) if v.synced}, C, names, board
        )
    else:
        rig_T = np.tile(np.eye(4), (C, 1, 1))
    starts = _frame_starts(fit, vpose, rig_T)
    X = _read_corners(fit, vpose, rig_T, starts, board)
    # 4. the joint fit, then again without the views it shows to be wrong
    ext = rt_vector(rig_T)
    pose6 = {(-1, f): rt_vector(T) for f, T in starts.items()}
    pose6 |= {_pose_key(v): rt_vector(T) for v, T in zip(fit, vpose, strict=True) if not v.synced}
    free_intr = np.array([n not in fixed for n in names])
    free_ext = np.arange(C) != 0
    for round_ in range(ROUNDS):
        prob, keys = board_problem(fit, X, intr, ext, free_intr, free_ext)
        res = solve(prob, prob.pack(intr, ext, np.array([pose6[k] for k in keys])))
        intr, ext, poses = prob.split(res.x)
        pose6 = dict(zip(keys, poses, strict=True))
        vr = prob.view_rms(res.fun, len(fit))
        bad = _wrong_views(vr, np.array([v.cam for v in fit]), cfg.outlier_px)
        if not bad.size or round_ == ROUNDS - 1:
            break
        for k in bad:
            dropped[fit[k].cam].append(
                (
                    fit[k].label,
                    f"reprojects {vr[k]:.1f} px in the joint fit: the board was "
                    "found wrongly, or the frame is not simultaneous with the others",
                )
            )
        keep = np.setdiff1d(np.arange(len(fit)), bad)
        fit, X = [fit[k] for k in keep], [X[k] for k in keep]
    f_sd, c_sd, r_sd = _covariance_sd(res, prob)
    f_sd = np.where(np.isfinite(f_sd), f_sd, f_sd0)
    # 5. the world frame and the rig
    rig_T = rt_matrix(ext[:, :3], ext[:, 3:])
    fposes = {f: rt_matrix(p[:3], p[3:]) for (cam, f), p in pose6.items() if cam < 0}
    world_from_ref, up, frame_name = _world(cfg, rig_T, fposes, fit, names)
    rig = _rig(names, sizes, intr, rig_T @ rigid_inverse(world_from_ref), up, frame_name)
    warnings += _lens_warnings(rig, prob)
    # 6. per camera figures; the held-out frames posed with the rig held
    joint = JointFit(fit, prob, res.fun, vr, f_sd, c_sd, r_sd, intr)
    reports = _reports(rig, names, board, held_views, joint, dropped, warnings)
    return BoardCalibration(
        rig,
        tuple(reports),
        board,
        {f: world_from_ref @ T for f, T in fposes.items()},
        tuple(warnings),
        tuple(sorted(hold)),
    )


def _rig(
    names: Sequence[str],
    sizes: Sequence[tuple[int, int]],
    intr: F64,
    cam_from_world: F64,
    up: F64,
    frame_name: str,
) -> Rig:
    cams = []
    for c, name in enumerate(names):
        try:
            cams.append(
                Camera(
                    name,
                    int(sizes[c][0]),
                    int(sizes[c][1]),
                    intr_K(intr[c]),
                    intr[c, 4:N_INTR] if intr_lens(intr[c]) == "pinhole" else intr[c, 4:8],
                    cam_from_world[c, :3, :3],
                    cam_from_world[c, :3, 3],
                    lens=intr_lens(intr[c]),
                )
            )
        except ValueError as e:
            raise InputError(
                name, f"the calibration failed ({e}): too few or too similar board views"
            ) from None
    return Rig(tuple(cams), up=up, frame_name=frame_name)


def identity_poses(rig: Rig) -> Rig:
    """``rig``'s cameras with no pose (intrinsics only): each at the origin, looking along +z."""
    cams = tuple(replace(c, R=np.eye(3), t=np.zeros(3)) for c in rig.cameras)
    return Rig(
        cams,
        up=np.array([0.0, -1.0, 0.0]),
        frame_name="intrinsics only: every camera at the origin (poses not calibrated)",
    )


def _world(
    cfg: BoardConfig, rig_T: F64, fposes: dict[int, F64], views: Sequence[View], names: Sequence[str]
) -> tuple[F64, F64, str]:
    """world_from_ref (4, 4), up (3,), the frame's name."""
    if cfg.origin not in ("camera", "floor"):
        raise InputError("--origin", f"must be camera or floor, got {cfg.origin!r}")
    if cfg.origin == "camera" or not fposes:  # up: the reference camera's image's up (its -y)
        return (
            np.eye(4),
            np.array([0.0, -1.0, 0.0]),
            f"camera {names[0]}'s frame (metres; up = its image's up)",
        )
    if cfg.floor_frame is not None:
        if cfg.floor_frame not in fposes:
            raise InputError(
                "--floor-frame",
                f"frame {cfg.floor_frame} has no board pose (posed frames: "
                f"{', '.join(map(str, sorted(fposes)[:10]))}...)",
            )
        f = cfg.floor_frame
    else:  # the frame the most cameras saw (the earliest of those)
        count = np.bincount([v.frame for v in views if v.synced and v.frame in fposes])
        f = int(np.argmax(count))
    # the board's z points away from the cameras that saw it: turn it up
    world_from_ref = np.diag([1.0, -1.0, -1.0, 1.0]) @ rigid_inverse(fposes[f])
    centres = (world_from_ref @ rigid_inverse(rig_T))[:, :3, 3]
    if np.median(centres[:, 2]) < 0:  # cameras below: they saw the board from its back
        world_from_ref = np.diag([1.0, -1.0, -1.0, 1.0]) @ world_from_ref
    return world_from_ref, np.array([0.0, 0.0, 1.0]), f"the board of frame {f} as the floor (metres, z up)"
