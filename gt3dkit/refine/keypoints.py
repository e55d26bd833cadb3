"""Refine a rig from the annotations, and only where the data supports it.

Keypoints: every joint that two or more views saw in a frame (and that the robust per-frame
triangulation kept) is a track; pycolmap bundle adjustment refines the camera poses
(optionally focal length and distortion) and the points, with a Cauchy loss at the data's
keypoint noise.

Boxes: the cameras are refined jointly with every object-frame's ellipsoid through our own
measurement model, the exact tangent box of the projected ellipsoid (which pycolmap cannot
express): a sparse robust least squares (scipy) over camera poses and ellipsoids.

Validation: the frames are split into time blocks; each block's fit is scored on the other
block's observations (re-triangulated / re-fitted with the candidate cameras). A camera keeps
its input pose unless refining it lowers its held-out reprojection error in every fold by
more than ``min_gain`` (half: see :class:`RefineConfig`); the final fit (all frames) moves
only the accepted cameras. The refined rig is brought back to the input's world frame and
metric scale by a similarity alignment of the camera centres (only needed when fewer than
two cameras stay fixed).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from gt3dkit.calib.formats.colmap import intrinsics_of, to_reconstruction
from gt3dkit.errors import InputError
from gt3dkit.fusion.preparation.prepare import Prepared, prepare
from gt3dkit.geom.camera import project_points
from gt3dkit.geom.triangulate import normalized_points, triangulate_weighted
from gt3dkit.refine.boxes import refine_boxes
from gt3dkit.refine.common import (
    RefineConfig,
    RefineResult,
    align_to,
    check_enough,
    large_moves,
    pose_change,
    time_blocks,
)
from gt3dkit.rig import Rig
from gt3dkit.types import F64, JsonDict, Scene


@dataclass(frozen=True)
class Tracks:
    """Keypoint tracks: point p seen by camera cam[k] at uv[k] (OpenCV px) for k in obs of p."""

    X0: F64  # (P, 3) initial points
    time: np.ndarray  # (P,) frame number of each point
    point: np.ndarray  # (M,) point index of each observation
    cam: np.ndarray  # (M,) camera index
    uv: F64  # (M, 2)

    def subset(self, keep_points: np.ndarray) -> Tracks:
        idx = np.flatnonzero(keep_points)
        new = np.full(len(self.X0), -1)
        new[idx] = np.arange(idx.size)
        m = keep_points[self.point]
        return Tracks(self.X0[idx], self.time[idx], new[self.point[m]], self.cam[m], self.uv[m])


def keypoint_tracks(pre: Prepared) -> Tracks | None:
    """The tracks of a prepared scene: kept keypoints of joints triangulated in their frame."""
    if pre.kpt0 is None:
        return None
    rows = pre.rows
    z = np.swapaxes(rows.kpt_z, 1, 2)  # (R, J, C, 2)
    keep = np.swapaxes(pre.kpt_keep, 1, 2) & np.isfinite(z[..., 0])  # (R, J, C)
    ok = np.isfinite(pre.kpt0[..., 0]) & (keep.sum(axis=-1) >= 2)  # (R, J)
    r, j = np.nonzero(ok)
    X0 = pre.kpt0[r, j]
    k = keep[r, j]  # (P, C)
    p, c = np.nonzero(k)
    return Tracks(X0, rows.frames[rows.row_t[r]], p, c, z[r[p], j[p], c])


def ba_keypoints(rig: Rig, tr: Tracks, variable: np.ndarray, cfg: RefineConfig, sigma_px: float
                 ) -> Rig:
    """pycolmap bundle adjustment of the cameras ``variable`` (bool per camera) and the points."""
    import pycolmap


    C = len(rig.cameras)
    kp, idx = [], np.zeros(len(tr.cam), np.int64)
    for c in range(C):
        m = tr.cam == c
        idx[m] = np.arange(m.sum())
        kp.append(tr.uv[m])
    rec = to_reconstruction(rig, keypoints=kp)
    for p in range(len(tr.X0)):
        m = np.flatnonzero(tr.point == p)
        track = pycolmap.Track([pycolmap.TrackElement(int(tr.cam[k]) + 1, int(idx[k])) for k in m])
        rec.add_point3D(tr.X0[p].astype(np.float64), track)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = cfg.refine_intrinsics
    opts.refine_extra_params = cfg.refine_intrinsics and cfg.refine_distortion
    opts.refine_principal_point = False
    opts.print_summary = False
    opts.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    opts.ceres.loss_function_scale = cfg.loss_scale * sigma_px
    opts.ceres.solver_options.max_num_iterations = cfg.max_iterations
    opts.ceres.solver_options.num_threads = 1
    config = pycolmap.BundleAdjustmentConfig()
    for c in range(C):
        config.add_image(c + 1)
        if not variable[c]:
            config.set_constant_rig_from_world_pose(c + 1)
            config.set_constant_cam_intrinsics(c + 1)
    if (~variable).sum() < 2:
        config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(opts, config, rec).solve()
    cams = []
    for c, cam in enumerate(rig.cameras):
        m = rec.image(c + 1).cam_from_world().matrix()
        K, d, _ = intrinsics_of(rec.camera(c + 1).model_name, np.asarray(rec.camera(c + 1).params))
        if not cfg.refine_intrinsics:
            K, d = cam.K, cam.dist
        cams.append(replace(cam, K=K, dist=d, R=m[:, :3], t=m[:, 3]))
    out = Rig(tuple(cams), up=rig.up, frame_name=rig.frame_name)
    return out if (~variable).sum() >= 2 else align_to(out, rig)[0]


def retriangulated(rig: Rig, tr: Tracks) -> tuple[F64, F64]:
    """``(P, 3)`` every track's point triangulated again with ``rig`` (DLT over all its views), and
    ``(P, C, 2)`` its observations (px, NaN where a camera has none)."""
    P, C = len(tr.X0), len(rig.cameras)
    uv = np.full((P, C, 2), np.nan)
    uv[tr.point, tr.cam] = tr.uv
    xy = normalized_points(uv, rig.K, rig.dist)
    w = np.isfinite(xy[..., 0]).astype(np.float64)
    return triangulate_weighted(np.nan_to_num(xy), rig.R, rig.t, w), uv


def keypoint_residuals(rig: Rig, tr: Tracks) -> F64:
    """(M,) reprojection distance (px) of every observation, its point re-triangulated (robust
    DLT over all its views) with ``rig``."""
    X, uv = retriangulated(rig, tr)
    proj, _ = project_points(X[:, None], rig.K, rig.dist, rig.R, rig.t, rig.depth_sign)
    d = np.linalg.norm(proj[:, 0] - uv, axis=-1)  # (P, C)
    return d[tr.point, tr.cam]


# ----------------------------------------------------------------------------- the procedure


def refine(scene: Scene, cfg: RefineConfig | None = None) -> RefineResult:
    """Refine ``scene``'s rig (see the module docstring); the report says, per camera, the
    held-out reprojection error before/after, the pose change, and why it was (not) refined."""
    cfg = cfg or RefineConfig()
    t0 = time.perf_counter()
    pre = prepare(scene)
    rig = scene.rig
    C = len(rig.cameras)
    tr = keypoint_tracks(pre)
    if tr is None or len(tr.X0) == 0:
        if pre.use_box:
            return refine_boxes(scene, pre, cfg)
        raise InputError(scene.root or "input", "no keypoints seen by two views: nothing to refine")
    sigma = float(np.median(pre.sigma_kpt))
    n_obs = np.bincount(tr.cam, minlength=C)
    check_enough(rig, n_obs, cfg, "keypoints seen with another view")
    fold = time_blocks(tr.time, cfg.folds)
    gains = np.full((cfg.folds, C), -np.inf)
    held = {"input_px": np.zeros((cfg.folds, C)), "refined_px": np.zeros((cfg.folds, C))}
    for f in range(cfg.folds):
        fit, test = tr.subset(fold != f), tr.subset(fold == f)
        n_fit = np.bincount(fit.cam, minlength=C)
        variable = n_fit >= cfg.min_points
        if variable.sum() == 0:
            continue
        cand = ba_keypoints(rig, fit, variable, cfg, sigma)
        e_in, e_ref = keypoint_residuals(rig, test), keypoint_residuals(cand, test)
        for c in range(C):
            m = (test.cam == c) & np.isfinite(e_in) & np.isfinite(e_ref)
            if m.sum() < cfg.min_points:
                continue
            a, b = float(np.median(e_in[m])), float(np.median(e_ref[m]))
            held["input_px"][f, c], held["refined_px"][f, c] = a, b
            gains[f, c] = (a - b) / max(a, 1e-12)
    accept = np.all(gains > cfg.min_gain, axis=0)
    per_camera: dict[str, JsonDict] = {}
    report: JsonDict = {"method": "pycolmap bundle adjustment of keypoint tracks (Cauchy loss)",
                              "keypoint_sigma_px": sigma, "folds": cfg.folds,
                              "refine_intrinsics": cfg.refine_intrinsics, "cameras": per_camera}
    new = rig
    if accept.any():
        new = ba_keypoints(rig, tr, accept, cfg, sigma)
    e_before, e_after = keypoint_residuals(rig, tr), keypoint_residuals(new, tr)
    for c, cam in enumerate(rig.cameras):
        m = tr.cam == c
        dc, da = pose_change(cam, new.cameras[c])
        why = ("refined: held-out reprojection lower in every fold" if accept[c] else
               f"kept: too few observations ({int(n_obs[c])} < {cfg.min_points} per fit)"
               if n_obs[c] < 2 * cfg.min_points else
               "kept: refining did not lower its held-out reprojection by "
               f"{cfg.min_gain:.0%} in every fold")
        per_camera[cam.name] = {
            "refined": bool(accept[c]), "why": why, "observations": int(n_obs[c]),
            "heldout_median_px_input": held["input_px"][:, c].round(4).tolist(),
            "heldout_median_px_refined": held["refined_px"][:, c].round(4).tolist(),
            "median_px_before": float(np.nanmedian(e_before[m])) if m.any() else None,
            "median_px_after": float(np.nanmedian(e_after[m])) if m.any() else None,
            "centre_moved_m": dc, "rotation_moved_deg": da}
    report["refined_cameras"] = [c.name for c, a in zip(rig.cameras, accept, strict=True) if a]
    report["large_moves"] = list(large_moves(rig, new, accept, tr.X0))
    report["seconds"] = time.perf_counter() - t0
    return RefineResult(new, report)


