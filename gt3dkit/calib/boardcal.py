r"""A rig from board views: intrinsics per camera, extrinsics, one bundle adjustment.

Steps (:func:`calibrate_board`):

1. **Intrinsics** per camera, from all its views (``cv2.calibrateCameraExtended``: Zhang's
   planar method, then Levenberg-Marquardt on OpenCV's ``k1 k2 p1 p2 k3`` pinhole model).
   A view that reprojects far worse than the camera's others (board found wrongly: a marker
   misread, motion blur, a flipped checkerboard) is left out and the fit repeated.
2. **Board poses** per view (``cv2.solvePnP``, IPPE for a plane, then LM refinement).
3. **Extrinsics**: for every pair of cameras, the relative pose each frame both saw implies;
   the medoid of those (the candidate nearest the others) is the pair's pose. A maximum
   spanning tree over the pairs (weighted by shared frames) chains every camera to the first.
   A camera no chain reaches is named: its extrinsics cannot be found.
4. **Bundle adjustment** over every camera's intrinsics and pose and every board pose:
   ``scipy.optimize.least_squares`` (trust region, sparse finite-difference Jacobian,
   soft-L1 loss of scale 1 px), the board's corners held at their printed positions, which
   fixes the metric scale. Then views that reproject far worse than the rest are dropped
   and it runs again.

Why scipy's solver and not pycolmap's or GTSAM's bundle adjuster: COLMAP's OPENCV model has
no ``k3`` (strong lenses such as the shared mouse rig need it: its fit with ``k3 = 0`` rises
above 0.6 px) and its adjuster takes a moving board only as COLMAP rig frames with constant
3D points; GTSAM has no factor for a point on a moving board seen through a camera with
Brown-Conrady distortion and unknown intrinsics except as a Python ``CustomFactor``, called once
per corner per iteration. A sparse trust-region solve of a few hundred parameters takes
well under a second here.

Uncertainty: the parameters' covariance is ``s^2 (J^T J)^{-1}`` at the solution (``s^2`` the
residuals' variance), from which each camera's focal, centre and rotation sd follow.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from gt3dkit.calib.board import Board
from gt3dkit.calib.boardinput import View
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import apply_K, distort
from gt3dkit.rig import Camera, Rig
from gt3dkit.types import F64, JsonDict

#: 180 degrees about the board's z through its centre: the other reading of a checkerboard.
N_INTR = 9  # fx fy cx cy k1 k2 p1 p2 k3
#: Up to this many parameters (about 300 board frames) the solver takes exact steps on a dense
#: Jacobian; beyond, iterative ones on a sparse Jacobian.
DENSE_MAX_PARAMS = 2000


@dataclass(frozen=True)
class BoardConfig:
    """Settings of :func:`calibrate_board`.

    ``origin``: ``"camera"`` (the first camera's frame; up = its image's up) or ``"floor"`` (the
    board of ``floor_frame``, or of the frame the most cameras saw, as the floor: x, y on the
    board, z up towards the cameras, origin at its first inner corner).
    ``holdout_every``: every k-th synchronised frame (k-1, 2k-1, ...) is left out of the fits and
    reported on its own; 0 keeps every frame.
    """

    origin: str = "camera"
    floor_frame: int | None = None
    holdout_every: int = 0
    outlier_px: float = 1.5  # a view is wrong when its RMS exceeds this and 4x the camera's median
    fixed: dict[str, Camera] = field(default_factory=dict)  # given intrinsics, by camera name
    min_views: int = 6  # fewer views than this: a warning, and the focal's sd says how uncertain


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
    T = np.zeros(np.shape(rvec)[:-1] + (4, 4))
    T[..., :3, :3] = (
        Rotation.from_rotvec(np.reshape(rvec, (-1, 3))).as_matrix().reshape(T.shape[:-2] + (3, 3))
    )
    T[..., :3, 3] = t
    T[..., 3, 3] = 1.0
    return T


def _inv(T: F64) -> F64:
    out = np.zeros_like(T)
    R = np.swapaxes(T[..., :3, :3], -1, -2)
    out[..., :3, :3] = R
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", R, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _pose_distance(a: F64, b: F64, scale_m: float) -> F64:
    """Rotation angle (rad) plus translation distance in ``scale_m`` units, (N,) of (N, 4, 4) pairs."""
    dR = np.einsum("...ji,...jk->...ik", a[..., :3, :3], b[..., :3, :3])
    ang = np.arccos(np.clip((np.trace(dR, axis1=-2, axis2=-1) - 1) / 2, -1, 1))
    return ang + np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1) / scale_m


def project(X_cam: F64, intr: F64) -> F64:
    """(M, 2) distorted pixels of (M, 3) camera-frame points with per-point intrinsics (M, 9)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        xy = X_cam[:, :2] / X_cam[:, 2:3]
    K = np.zeros((len(intr), 3, 3))
    K[:, 0, 0], K[:, 1, 1], K[:, 0, 2], K[:, 1, 2], K[:, 2, 2] = (
        intr[:, 0],
        intr[:, 1],
        intr[:, 2],
        intr[:, 3],
        1,
    )
    return apply_K(distort(xy, intr[:, 4:9]), K)


def _intr_of(cam: Camera) -> F64:
    return np.array([cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], *cam.dist])


# ----------------------------------------------------------------------------- intrinsics


def _views_rms(obj: list[F64], img: list[F64], rv: Sequence[F64], tv: Sequence[F64], K: F64, d: F64) -> F64:
    import cv2

    out = []
    for o, i, r, t in zip(obj, img, rv, tv, strict=True):
        p, _ = cv2.projectPoints(o, r, t, K, d)
        out.append(float(np.sqrt(np.mean(np.sum((p.reshape(-1, 2) - i) ** 2, axis=1)))))
    return np.array(out)


def fit_intrinsics(
    views: list[View], board: Board, size: tuple[int, int], outlier_px: float
) -> tuple[F64, F64, float, list[int], list[tuple[int, str]]]:
    """One camera's K (3, 3), dist (5,), focal sd (px), the views kept and those dropped (why)."""
    import cv2

    corners = board.corners_board().astype(np.float32)
    obj = [corners[v.det.ids] for v in views]
    img = [v.det.uv_px.astype(np.float32) for v in views]
    keep = list(range(len(views)))
    dropped: list[tuple[int, str]] = []
    flags = 0
    if len(views) < 4:  # too few views for the full model: principal point at the centre, no k3
        flags = cv2.CALIB_FIX_PRINCIPAL_POINT | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST
    K0 = np.array([[max(size), 0, (size[0] - 1) / 2], [0, max(size), (size[1] - 1) / 2], [0, 0, 1]])
    for _ in range(4):
        o = [obj[k] for k in keep]
        i = [img[k] for k in keep]
        _, K, d, rv, tv, sd, _, _ = cv2.calibrateCameraExtended(
            o, i, size, K0.copy(), np.zeros(5), flags=flags | cv2.CALIB_USE_INTRINSIC_GUESS
        )
        rms = _views_rms([x.astype(np.float64) for x in o], [x.astype(np.float64) for x in i], rv, tv, K, d)
        lim = max(outlier_px, 4 * float(np.median(rms)))
        bad = [keep[j] for j in np.flatnonzero(rms > lim)]
        if not bad or len(keep) - len(bad) < 3:
            break
        dropped += [
            (
                k,
                f"reprojects {rms[keep.index(k)]:.1f} px with this camera's intrinsics (its views' "
                f"median {np.median(rms):.2f} px): the board was found wrongly",
            )
            for k in bad
        ]
        keep = [k for k in keep if k not in bad]
    sd_f = float(np.hypot(sd[0, 0], sd[1, 0]) / np.sqrt(2)) if np.all(np.isfinite(sd[:2])) else float("nan")
    return K, np.asarray(d, dtype=np.float64).reshape(-1)[:5], sd_f, keep, dropped


def board_pose(view: View, board: Board, K: F64, d: F64) -> F64:
    """(4, 4) cam_from_board of one view (IPPE, then LM)."""
    import cv2

    X = board.corners_board()[view.det.ids]
    ok, rv, tv = cv2.solvePnP(X, view.det.uv_px, K, d, flags=cv2.SOLVEPNP_IPPE)
    if not ok:
        ok, rv, tv = cv2.solvePnP(X, view.det.uv_px, K, d, flags=cv2.SOLVEPNP_ITERATIVE)
    rv, tv = cv2.solvePnPRefineLM(X, view.det.uv_px, K, d, rv, tv)
    return rt_matrix(rv.reshape(3), tv.reshape(3))


# ----------------------------------------------------------------------------- extrinsics


def _flips(board: Board) -> list[F64]:
    """Board-frame transforms between the readings a detection may have: the identity, and for a
    checkerboard its 180 degree turn about the board's centre (its corners read backwards)."""
    if board.kind == "charuco":
        return [np.eye(4)]
    nx, ny = board.inner
    c = np.array([(nx + 1) / 2, (ny + 1) / 2, 0]) * board.square_m
    F = np.diag([-1.0, -1.0, 1.0, 1.0])
    F[:3, 3] = 2 * c
    return [np.eye(4), F]


def _medoid(cands: F64, scale_m: float) -> F64:
    n = len(cands)
    D = _pose_distance(cands[:, None], cands[None, :], scale_m)
    return cands[int(np.argmin(np.median(D, axis=1) if n > 2 else D.sum(1)))]


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
            for b in cs[i + 1 :]:
                for F in flips:  # b_from_a, each reading of b's board
                    pair[(a, b)].append(seen[b] @ F @ _inv(seen[a]))
    scale = board.square_m * max(board.inner)
    weight = {k: len(v) // len(flips) for k, v in pair.items()}
    rel = {k: _medoid(np.array(v), scale) for k, v in pair.items()}
    out = np.full((n_cams, 4, 4), np.nan)
    out[0] = np.eye(4)
    done = {0}
    while True:  # Prim's maximum spanning tree from camera 0
        best = None
        for (a, b), w in weight.items():
            if (a in done) != (b in done) and (best is None or w > best[2]):
                best = (a, b, w)
        if best is None:
            break
        a, b, _ = best
        if a in done:
            out[b] = rel[(a, b)] @ out[a]
            done.add(b)
        else:
            out[a] = _inv(rel[(a, b)]) @ out[b]
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


# ----------------------------------------------------------------------------- bundle adjustment


@dataclass
class _Problem:
    """Observations flattened for the solver: ``cam``, ``pose`` (board pose index), ``local``
    (the pose is in the camera's own frame: a view of no synchronised frame), ``X`` (M, 3)
    board-frame corners, ``uv`` (M, 2)."""

    cam: np.ndarray
    pose: np.ndarray
    local: np.ndarray
    X: F64
    uv: F64
    view: np.ndarray  # (M,) index into the view list
    n_cams: int
    n_poses: int
    free_intr: np.ndarray  # (C,) bool
    ref: int = 0

    def split(self, x: F64, intr0: F64) -> tuple[F64, F64, F64]:
        C, P = self.n_cams, self.n_poses
        nfi = int(self.free_intr.sum())
        intr = intr0.copy()
        intr[self.free_intr] = x[: nfi * N_INTR].reshape(nfi, N_INTR)
        o = nfi * N_INTR
        ext = np.zeros((C, 6))
        others = [c for c in range(C) if c != self.ref]
        ext[others] = x[o : o + 6 * (C - 1)].reshape(C - 1, 6)
        o += 6 * (C - 1)
        poses = x[o : o + 6 * P].reshape(P, 6)
        return intr, ext, poses

    def residuals(self, x: F64, intr0: F64) -> F64:
        intr, ext, poses = self.split(x, intr0)
        Tp = rt_matrix(poses[:, :3], poses[:, 3:])
        Tc = rt_matrix(ext[:, :3], ext[:, 3:])
        Xw = np.einsum("mij,mj->mi", Tp[self.pose, :3, :3], self.X) + Tp[self.pose, :3, 3]
        Xc = np.einsum("mij,mj->mi", Tc[self.cam, :3, :3], Xw) + Tc[self.cam, :3, 3]
        Xc = np.where(self.local[:, None], Xw, Xc)
        r = project(Xc, intr[self.cam]) - self.uv
        return np.nan_to_num(r, nan=1e4).reshape(-1)

    def column_groups(self) -> np.ndarray:
        """(n_params,) group of each parameter: parameters of one group touch disjoint residuals
        (the same entry of every camera's intrinsics, of every camera's pose, of every board
        pose), so one perturbed evaluation gives the Jacobian's columns of a whole group."""
        C = self.n_cams
        nfi = int(self.free_intr.sum())
        g = [
            np.tile(np.arange(N_INTR), nfi),
            N_INTR + np.tile(np.arange(6), C - 1),
            N_INTR + 6 + np.tile(np.arange(6), self.n_poses),
        ]
        return np.concatenate(g)

    def jacobian(self, x: F64, intr0: F64) -> F64:
        """Dense forward-difference Jacobian, a residual evaluation per column group."""
        f0 = self.residuals(x, intr0)
        groups = self.column_groups()
        A = self.sparsity().tocsc()
        J = np.zeros((len(f0), len(x)))
        h = 1e-7 * np.maximum(1.0, np.abs(x))
        for g in np.unique(groups):
            cols = np.flatnonzero(groups == g)
            dx = np.zeros_like(x)
            dx[cols] = h[cols]
            df = self.residuals(x + dx, intr0) - f0
            for j in cols:
                rows = A.indices[A.indptr[j] : A.indptr[j + 1]]
                J[rows, j] = df[rows] / h[j]
        return J

    def sparsity(self) -> lil_matrix:
        C = self.n_cams
        nfi = int(self.free_intr.sum())
        col_intr = np.full(C, -1)
        col_intr[self.free_intr] = np.arange(nfi) * N_INTR
        col_ext = np.full(C, -1)
        others = [c for c in range(C) if c != self.ref]
        col_ext[others] = nfi * N_INTR + 6 * np.arange(C - 1)
        o = nfi * N_INTR + 6 * (C - 1)
        M = len(self.cam)
        A = lil_matrix((2 * M, o + 6 * self.n_poses), dtype=np.int8)
        rows = np.arange(M)
        for k in range(2):
            rr = 2 * rows + k
            for j in range(6):
                A[rr, o + 6 * self.pose + j] = 1
            m = col_intr[self.cam] >= 0
            for j in range(N_INTR):
                A[rr[m], col_intr[self.cam[m]] + j] = 1
            m = (col_ext[self.cam] >= 0) & ~self.local
            for j in range(6):
                A[rr[m], col_ext[self.cam[m]] + j] = 1
        return A


@dataclass(frozen=True)
class LMResult:
    """What :func:`robust_lm` returns (the fields of scipy's ``OptimizeResult`` that are used)."""

    x: F64
    fun: F64
    jac: F64
    nfev: int


def robust_lm(
    fun: object, jac: object, x0: F64, f_scale: float = 1.0, max_iter: int = 50, tol: float = 1e-10
) -> LMResult:
    r"""Levenberg-Marquardt with soft-L1 weights (iteratively reweighted least squares).

    Minimises :math:`\sum_i \rho(r_i^2)` with :math:`\rho(z) = 2 s^2 (\sqrt{1 + z/s^2} - 1)`
    (scipy's ``soft_l1``) by Gauss-Newton steps on :math:`w_i r_i` with :math:`w_i =
    \rho'(r_i^2)^{1/2}` (Triggs et al., "Bundle adjustment: a modern synthesis", 2000, sec. 3.3),
    damped by Marquardt's diagonal scaling. Written here, not scipy's exact trust region, because
    that takes an SVD of the whole (residuals x parameters) Jacobian at every step, 60 % of the
    shared rig's calibration time; here each step solves the (parameters x parameters) normal
    equations. ``fun(x) -> (M,)``, ``jac(x) -> (M, n)``.
    """
    x = np.asarray(x0, dtype=np.float64).copy()
    f, nfev = fun(x), 1  # type: ignore[operator]

    def cost(r: F64) -> float:
        return float(np.sum(2 * f_scale**2 * (np.sqrt(1 + (r / f_scale) ** 2) - 1)))

    c = cost(f)
    lam = 1e-3
    J = jac(x)  # type: ignore[operator]
    for _ in range(max_iter):
        w = (1 + (f / f_scale) ** 2) ** -0.25  # sqrt of rho'
        Jw = J * w[:, None]
        A = Jw.T @ Jw
        g = Jw.T @ (w * f)
        d = np.diag(A).copy()
        d[d == 0] = 1.0
        improved = False
        for _try in range(10):
            try:
                step = -np.linalg.solve(A + lam * np.diag(d), g)
            except np.linalg.LinAlgError:
                lam *= 10
                continue
            fn = fun(x + step)  # type: ignore[operator]
            nfev += 1
            cn = cost(fn)
            if cn < c:
                improved = True
                x, f, lam = x + step, fn, max(lam / 10, 1e-9)
                done = c - cn < tol * max(c, 1e-12) or np.linalg.norm(step) < tol * (1 + np.linalg.norm(x))
                c = cn
                break
            lam *= 10
        if not improved or done:
            break
        J = jac(x)  # type: ignore[operator]
    return LMResult(x, f, jac(x), nfev)  # type: ignore[operator]


def _covariance_sd(res: object, prob: _Problem, x: F64, intr0: F64) -> tuple[F64, F64, F64]:
    """Per camera: focal sd (px), centre sd (m), rotation sd (rad), from ``s^2 (J^T J)^{-1}``."""
    J = res.jac  # type: ignore[attr-defined]
    J = J.toarray() if hasattr(J, "toarray") else np.asarray(J)
    r = res.fun  # type: ignore[attr-defined]
    dof = max(1, len(r) - len(x))
    s2 = float(np.sum(r * r) / dof)
    C = prob.n_cams
    nan = np.full(C, np.nan)
    if J.shape[1] > 4000:
        return nan, nan, nan
    cov = np.linalg.pinv(J.T @ J) * s2
    nfi = int(prob.free_intr.sum())
    f_sd, c_sd, r_sd = nan.copy(), np.zeros(C), np.zeros(C)
    fi = np.flatnonzero(prob.free_intr)
    for k, c in enumerate(fi):
        f_sd[c] = np.sqrt(0.5 * (cov[k * N_INTR, k * N_INTR] + cov[k * N_INTR + 1, k * N_INTR + 1]))
    _, ext, _ = prob.split(x, intr0)
    others = [c for c in range(C) if c != prob.ref]
    for k, c in enumerate(others):
        o = nfi * N_INTR + 6 * k
        S = cov[o : o + 6, o : o + 6]
        r_sd[c] = np.sqrt(np.trace(S[:3, :3]) / 3)
        # centre = -R^T t: its covariance by finite differences of the map
        p0 = ext[c].copy()

        def centre(p: F64) -> F64:
            R = Rotation.from_rotvec(p[:3]).as_matrix()
            return -R.T @ p[3:]

        Jc = np.zeros((3, 6))
        for j in range(6):
            dp = np.zeros(6)
            dp[j] = 1e-6
            Jc[:, j] = (centre(p0 + dp) - centre(p0 - dp)) / 2e-6
        c_sd[c] = np.sqrt(np.trace(Jc @ S @ Jc.T) / 3)
    return f_sd, c_sd, r_sd


def _view_rms(r: F64, view: np.ndarray, n_views: int) -> F64:
    e2 = (r.reshape(-1, 2) ** 2).sum(1)
    s = np.bincount(view, e2, minlength=n_views)
    n = np.bincount(view, minlength=n_views)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(s / n)


def _fit_frame_poses(
    rig_T: F64, intr: F64, views: list[View], board: Board, start: dict[int, F64]
) -> tuple[dict[int, F64], dict[int, F64]]:
    """Board poses of frames with the cameras held (the held-out check); per view residuals."""
    frames = sorted({v.frame for v in views})
    poses: dict[int, F64] = {}
    resid: dict[int, F64] = {}
    corners = board.corners_board()
    for f in frames:
        vs = [(k, v) for k, v in enumerate(views) if v.frame == f]
        if f not in start:
            continue
        X = np.concatenate([corners[v.det.ids] for _, v in vs])
        cam = np.concatenate([np.full(len(v.det.ids), v.cam) for _, v in vs])
        uv = np.concatenate([v.det.uv_px for _, v in vs])

        def fun(p: F64, X: F64 = X, cam: np.ndarray = cam, uv: F64 = uv) -> F64:
            T = rt_matrix(p[:3], p[3:])
            Xw = X @ T[:3, :3].T + T[:3, 3]
            Xc = np.einsum("mij,mj->mi", rig_T[cam, :3, :3], Xw) + rig_T[cam, :3, 3]
            return np.nan_to_num(project(Xc, intr[cam]) - uv, nan=1e4).reshape(-1)

        T0 = start[f]
        p0 = np.concatenate([Rotation.from_matrix(T0[:3, :3]).as_rotvec(), T0[:3, 3]])
        sol = least_squares(fun, p0, loss="soft_l1", f_scale=1.0)
        poses[f] = rt_matrix(sol.x[:3], sol.x[3:])
        r = fun(sol.x).reshape(-1, 2)
        o = 0
        for k, v in vs:
            n = len(v.det.ids)
            resid[k] = r[o : o + n]
            o += n
    return poses, resid


def calibrate_board(
    views: list[View], board: Board, names: Sequence[str], sizes: Sequence[tuple[int, int]], cfg: BoardConfig
) -> BoardCalibration:
    """The rig of ``names`` from their board ``views`` (see the module docstring)."""
    C = len(names)
    warnings: list[str] = []
    synced_frames = sorted({v.frame for v in views if v.synced})
    hold = set()
    if cfg.holdout_every > 0:
        hold = {f for f in synced_frames if f % cfg.holdout_every == cfg.holdout_every - 1}
    fit_views = [v for v in views if not (v.synced and v.frame in hold)]
    held_views = [v for v in views if v.synced and v.frame in hold]
    dropped: dict[int, list[tuple[str, str]]] = defaultdict(list)
    # 1. intrinsics
    K = np.zeros((C, 3, 3))
    D = np.zeros((C, 5))
    f_sd_intr = np.full(C, np.nan)
    keep_views: list[View] = []
    for c, name in enumerate(names):
        vs = [v for v in fit_views if v.cam == c]
        if name in cfg.fixed:
            K[c], D[c] = cfg.fixed[name].K, cfg.fixed[name].dist
            if (cfg.fixed[name].width, cfg.fixed[name].height) != tuple(sizes[c]):
                raise InputError(
                    name,
                    f"the given intrinsics are for {cfg.fixed[name].width}x"
                    f"{cfg.fixed[name].height} images, its board views are "
                    f"{sizes[c][0]}x{sizes[c][1]}",
                )
            keep_views += vs
            continue
        if not vs:
            raise InputError(
                name,
                "the board was found in none of its frames: check the board's "
                "description (dictionary, square count, marker size; for anipose's "
                "board.toml marker_bits and dict_size) and that the frames show it",
            )
        if len(vs) < cfg.min_views:
            warnings.append(
                f"camera {name}: {len(vs)} board views (fewer than {cfg.min_views}): its "
                "intrinsics are uncertain (see its focal sd)"
            )
        K[c], D[c], f_sd_intr[c], keep, drop = fit_intrinsics(vs, board, sizes[c], cfg.outlier_px)
        keep_views += [vs[k] for k in keep]
        dropped[c] += [(vs[k].label, why) for k, why in drop]
    # 2. poses of the synchronised views
    vpose = {(v.cam, v.frame): board_pose(v, board, K[v.cam], D[v.cam]) for v in keep_views if v.synced}
    synced_cams = sorted({v.cam for v in keep_views if v.synced})
    if synced_cams and len(synced_cams) < C:
        missing = [names[c] for c in range(C) if c not in synced_cams]
        raise InputError(
            ", ".join(missing),
            "has no board view taken together with the other cameras: its extrinsics cannot be found",
        )
    single = len(synced_cams) == 0
    rig_T = np.tile(np.eye(4), (C, 1, 1)) if single else chain_cameras(vpose, C, names, board)
    # 3. starting board poses (world = camera 0's frame), each view's reading of a checkerboard
    flips = _flips(board)
    frame_pose: dict[int, F64] = {}
    for f in sorted({v.frame for v in keep_views if v.synced}):
        seen = {v.cam: vpose[(v.cam, v.frame)] for v in keep_views if v.synced and v.frame == f}
        best = max(
            seen,
            key=lambda c: len(
                next(v for v in keep_views if v.synced and v.cam == c and v.frame == f).det.ids
            ),
        )
        frame_pose[f] = _inv(rig_T[best]) @ seen[best]
    corners = board.corners_board()
    obs_views: list[View] = []
    obs_X: list[F64] = []
    for v in keep_views:
        X = corners[v.det.ids]
        if v.synced and len(flips) > 1:  # the reading that agrees with the frame's pose
            T = vpose[(v.cam, v.frame)]
            want = rig_T[v.cam] @ frame_pose[v.frame]
            d = [float(_pose_distance(T @ F, want, board.square_m * max(board.inner))) for F in flips]
            if int(np.argmin(d)) == 1:
                X = (flips[1][:3, :3] @ X.T).T + flips[1][:3, 3]
        obs_views.append(v)
        obs_X.append(X)
    # 4. bundle adjustment, then without the views it shows to be wrong
    intr0 = np.concatenate([K[:, 0, 0:1], K[:, 1, 1:2], K[:, 0, 2:3], K[:, 1, 2:3], D], axis=1)
    free = np.array([n not in cfg.fixed for n in names])
    for _round in range(3):
        pose_keys: list[tuple[str, int]] = []
        pidx = {}
        for k, v in enumerate(obs_views):
            key = ("f", v.frame) if v.synced else ("v", k)
            if key not in pidx:
                pidx[key] = len(pose_keys)
                pose_keys.append(key)
        p0 = np.zeros((len(pose_keys), 6))
        for (kind, i), j in pidx.items():
            T = (
                frame_pose[i]
                if kind == "f"
                else board_pose(obs_views[i], board, K[obs_views[i].cam], D[obs_views[i].cam])
            )
            p0[j] = np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])
        n_obs = [len(v.det.ids) for v in obs_views]
        prob = _Problem(
            cam=np.repeat([v.cam for v in obs_views], n_obs),
            pose=np.repeat(
                [pidx[("f", v.frame) if v.synced else ("v", k)] for k, v in enumerate(obs_views)], n_obs
            ),
            local=np.repeat([not v.synced for v in obs_views], n_obs).astype(bool),
            X=np.concatenate(obs_X),
            uv=np.concatenate([v.det.uv_px for v in obs_views]),
            view=np.repeat(np.arange(len(obs_views)), n_obs),
            n_cams=C,
            n_poses=len(pose_keys),
            free_intr=free,
        )
        ext0 = np.array(
            [np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]]) for T in rig_T]
        )
        x0 = np.concatenate(
            [intr0[free].reshape(-1), ext0[[c for c in range(C) if c != 0]].reshape(-1), p0.reshape(-1)]
        )
        if len(x0) <= DENSE_MAX_PARAMS:  # few parameters: Levenberg-Marquardt on the normal equations
            res = robust_lm(partial(prob.residuals, intr0=intr0), partial(prob.jacobian, intr0=intr0), x0)
        else:
            res = least_squares(
                prob.residuals,
                x0,
                jac_sparsity=prob.sparsity(),
                method="trf",
                x_scale="jac",
                loss="soft_l1",
                f_scale=1.0,
                args=(intr0,),
                max_nfev=300,
            )
        vr = _view_rms(res.fun, prob.view, len(obs_views))
        bad = []
        for c in range(C):
            ks = [k for k, v in enumerate(obs_views) if v.cam == c]
            if not ks:
                continue
            lim = max(cfg.outlier_px, 4 * float(np.median(vr[ks])))
            bad += [k for k in ks if vr[k] > lim]
        intr_fit, ext, poses = prob.split(res.x, intr0)
        if not bad or _round == 2:
            break
        for k in bad:
            v = obs_views[k]
            dropped[v.cam].append(
                (
                    v.label,
                    f"reprojects {vr[k]:.1f} px in the joint fit: the board was found "
                    "wrongly, or the frame is not simultaneous with the others",
                )
            )
        keep = [k for k in range(len(obs_views)) if k not in set(bad)]
        obs_views = [obs_views[k] for k in keep]
        obs_X = [obs_X[k] for k in keep]
        intr0 = intr_fit
        rig_T = rt_matrix(ext[:, :3], ext[:, 3:])
        for (kind, i), j in pidx.items():
            if kind == "f":
                frame_pose[i] = rt_matrix(poses[j, :3], poses[j, 3:])
    f_sd, c_sd, r_sd = _covariance_sd(res, prob, res.x, intr0)
    rig_T = rt_matrix(ext[:, :3], ext[:, 3:])
    fposes = {i: rt_matrix(poses[j, :3], poses[j, 3:]) for (kind, i), j in pidx.items() if kind == "f"}
    # 5. the world frame
    world_from_ref, up, frame_name = _world(cfg, names, rig_T, fposes, keep_views)
    ref_from_world = _inv(world_from_ref)
    cams = []
    for c, name in enumerate(names):
        T = rig_T[c] @ ref_from_world
        Kc = np.array([[intr_fit[c, 0], 0, intr_fit[c, 2]], [0, intr_fit[c, 1], intr_fit[c, 3]], [0, 0, 1]])
        try:
            cams.append(
                Camera(name, int(sizes[c][0]), int(sizes[c][1]), Kc, intr_fit[c, 4:9], T[:3, :3], T[:3, 3])
            )
        except ValueError as e:
            raise InputError(
                name, f"the calibration failed ({e}): too few or too similar board views"
            ) from None
    rig = Rig(tuple(cams), up=up, frame_name=frame_name)
    fposes_w = {f: world_from_ref @ T for f, T in fposes.items()}
    # 6. per camera figures; the held-out frames posed with the rig held
    r = res.fun.reshape(-1, 2)
    e = np.sqrt((r**2).sum(1))
    vr = _view_rms(res.fun, prob.view, len(obs_views))
    hold_r: dict[int, F64] = {}
    if held_views:
        start = {}
        for f in sorted({v.frame for v in held_views}):
            vs = [v for v in held_views if v.frame == f]
            v = max(vs, key=lambda v: len(v.det.ids))
            start[f] = _inv(rig_T[v.cam]) @ board_pose(
                v, board, intr_K(intr_fit[v.cam]), intr_fit[v.cam, 4:9]
            )
        _, hold_r = _fit_frame_poses(rig_T, intr_fit, held_views, board, start)
    reports = []
    for c, name in enumerate(names):
        m = prob.cam == c
        ks = [k for k, v in enumerate(obs_views) if v.cam == c]
        worst = sorted(((obs_views[k].label, float(vr[k])) for k in ks), key=lambda t: -t[1])[:3]
        hr = [hold_r[k] for k, v in enumerate(held_views) if v.cam == c and k in hold_r]
        hold_rms = float(np.sqrt(np.mean(np.sum(np.concatenate(hr) ** 2, axis=1)))) if hr else None
        fs = float(f_sd[c]) if np.isfinite(f_sd[c]) else float(f_sd_intr[c])
        reports.append(
            CameraReport(
                name,
                len(ks),
                float(np.sqrt(np.mean(e[m] ** 2))) if m.any() else float("nan"),
                float(np.percentile(e[m], 95)) if m.any() else float("nan"),
                hold_rms,
                tuple(worst),
                tuple(dropped[c]),
                fs,
                float(c_sd[c]) * 1e3,
                float(np.degrees(r_sd[c])),
                prob.uv[m],
            )
        )
        if np.isfinite(fs) and fs > 0.01 * Kc[0, 0]:
            warnings.append(
                f"camera {name}: focal length uncertain by {fs:.1f} px (more than 1 %): "
                "film the board closer, tilted, and over the whole image"
            )
    return BoardCalibration(rig, tuple(reports), board, fposes_w, tuple(warnings), tuple(sorted(hold)))


def intr_K(intr: F64) -> F64:
    return np.array([[intr[0], 0, intr[2]], [0, intr[1], intr[3]], [0, 0, 1]])


def _world(
    cfg: BoardConfig, names: Sequence[str], rig_T: F64, fposes: dict[int, F64], views: list[View]
) -> tuple[F64, F64, str]:
    """world_from_ref (4, 4), up (3,), the frame's name."""
    if cfg.origin == "camera" or not fposes:
        # up: minus the reference camera's image y
        return (
            np.eye(4),
            np.array([0.0, -1.0, 0.0]),
            f"camera {names[0]}'s frame (metres; up = its image's up)",
        )
    if cfg.origin != "floor":
        raise InputError("--origin", f"must be camera or floor, got {cfg.origin!r}")
    if cfg.floor_frame is not None:
        if cfg.floor_frame not in fposes:
            raise InputError(
                "--floor-frame",
                f"frame {cfg.floor_frame} has no board pose (posed frames: "
                f"{', '.join(map(str, sorted(fposes)[:10]))}...)",
            )
        f = cfg.floor_frame
    else:
        count: dict[int, int] = defaultdict(int)
        for v in views:
            if v.synced and v.frame in fposes:
                count[v.frame] += 1
        f = max(sorted(count), key=lambda k: count[k])
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # board z points away from the cameras: turn it up
    world_from_ref = flip @ _inv(fposes[f])
    centres = np.array([(_inv(T) @ np.array([0, 0, 0, 1.0]))[:3] for T in rig_T])
    z = (world_from_ref[:3, :3] @ centres.T).T[:, 2] + world_from_ref[2, 3]
    if np.median(z) < 0:  # cameras below: they saw the board from its back
        world_from_ref = np.diag([1.0, -1.0, -1.0, 1.0]) @ world_from_ref
    return world_from_ref, np.array([0.0, 0.0, 1.0]), f"the board of frame {f} as the floor (metres, z up)"


def identity_poses(rig: Rig) -> Rig:
    """``rig``'s cameras with no pose (intrinsics only): each at the origin, looking along +z."""
    cams = tuple(Camera(c.name, c.width, c.height, c.K, c.dist, np.eye(3), np.zeros(3)) for c in rig.cameras)
    return Rig(
        cams,
        up=np.array([0.0, -1.0, 0.0]),
        frame_name="intrinsics only: every camera at the origin (poses not calibrated)",
    )
