"""Refine camera poses from boxes: cameras jointly with every object-frame's ellipsoid, through
the exact tangent box of the projected ellipsoid (our measurement model; pycolmap has no such
residual), as a sparse robust least squares (``scipy.optimize.least_squares``, soft-L1 loss).

Parameters: per refined camera a rotation vector and a centre shift (with weak priors, 2
degrees and 20 cm, that make the free similarity of the problem well-posed; the result is
aligned back to the input's camera centres), per object-frame a centre, per object its log
semi-axes (a person keeps their size; started at the robust per-frame fits). Residuals: the
kept box edges over their noise level.
Validated like the keypoint refinement (held-out time blocks, :mod:`gt3dkit.refine.keypoints`).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np
from scipy.sparse import coo_matrix

from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.conics import model_boxes
from gt3dkit.refine.common import (
    RefineConfig,
    RefineResult,
    align_to,
    check_enough,
    large_moves,
    pose_change,
    time_blocks,
    transform_rig,
    umeyama,
)
from gt3dkit.rig import Rig
from gt3dkit.types import F64, JsonDict, Scene

PRIOR_ROT_RAD = np.radians(2.0)
PRIOR_SHIFT_M = 0.2
#: People stand on the floor (height 0 along up) when the per-frame ellipsoids' bottoms sit
#: within this of it (median): then the floor anchors the rig's height and tilt.
FLOOR_TOL_M = 0.2


def _cams(rig: Rig, variable: np.ndarray, p: F64) -> tuple[F64, F64]:
    """(R (C,3,3), t (C,3)) of the rig with the variable cameras moved by ``p`` (6 per camera)."""
    from scipy.spatial.transform import Rotation  # heavy to import (scipy): only where it runs

    R, t = rig.R.copy(), rig.t.copy()
    for k, c in enumerate(np.flatnonzero(variable)):
        w, d = p[6 * k: 6 * k + 3], p[6 * k + 3: 6 * k + 6]
        Rc = Rotation.from_rotvec(w).as_matrix() @ rig.cameras[c].R
        R[c], t[c] = Rc, -Rc @ (rig.cameras[c].center_world + d)
    return R, t


def fit_boxes(rig: Rig, cams: Cams, z: F64, keep: np.ndarray, sigma: F64, start: tuple[F64, F64],
              variable: np.ndarray, obj: np.ndarray, max_nfev: int = 100,
              floor_sd: float | None = None) -> tuple[Rig, F64, F64]:
    """Least squares over the variable cameras, every row's centre and every object's log
    semi-axes (people keep their size: this is what makes boxes constrain the cameras).

    z : (N, C, 4) boxes; keep : (N, C, 4) edges to use; sigma : (4,) px; start : ``(X0, L0)``,
    (N, 3) start centres and log semi-axes; obj : (N,) object index 0..O-1 of each row.
    cams: the input's cameras, for the body frame and the box model (the pose is ``rig``'s).
    Returns (rig, centres (N, 3), log axes (N, 3)).
    """
    from scipy.optimize import least_squares  # heavy to import (scipy): only where it runs

    X0, L0 = start
    N, C = len(X0), len(rig.cameras)
    O = int(obj.max()) + 1 if N else 0
    nv = int(variable.sum())
    ii, cc, ee = np.nonzero(keep)
    s = sigma[cc, ee] if sigma.ndim == 2 else sigma[ee]
    L_obj = np.array([np.median(L0[obj == o], axis=0) for o in range(O)]).reshape(O, 3)
    a0, a1 = 6 * nv, 6 * nv + 3 * N  # camera | centres | object log axes

    def unpack(q: F64) -> tuple[F64, F64]:
        return q[a0:a1].reshape(N, 3), q[a1:].reshape(O, 3)[obj]

    def resid(q: F64) -> F64:
        R, t = _cams(rig, variable, q[:a0])
        X, L = unpack(q)
        box, _ = model_boxes(X, np.exp(L), cams._replace(R=R, t=t))
        r = (box[ii, cc, ee] - z[ii, cc, ee]) / s
        prior = q[:a0].reshape(nv, 2, 3) / np.array([PRIOR_ROT_RAD, PRIOR_SHIFT_M])[None, :, None]
        out = [np.nan_to_num(r, nan=1e3, posinf=1e3, neginf=-1e3), prior.ravel()]
        if floor_sd is not None:  # people stand on the floor: ellipsoid bottom at height 0
            out.append((X @ rig.up - np.exp(L[:, 2])) / floor_sd)
        return np.concatenate(out)

    m = len(ii)
    vidx = np.full(C, -1)
    vidx[variable] = np.arange(nv)
    k3, k6 = np.arange(3), np.arange(6)
    on_cam = np.flatnonzero(vidx[cc] >= 0)
    r_idx = [np.repeat(np.arange(m), 3), np.repeat(np.arange(m), 3), np.repeat(on_cam, 6),
             m + np.arange(a0)]
    c_idx = [(a0 + 3 * ii[:, None] + k3).ravel(), (a1 + 3 * obj[ii][:, None] + k3).ravel(),
             (6 * vidx[cc[on_cam]][:, None] + k6).ravel(), np.arange(a0)]
    n_res = m + a0
    if floor_sd is not None:  # each floor residual: its row's centre and its object's height
        rows_f = m + a0 + np.arange(N)
        r_idx += [np.repeat(rows_f, 3), rows_f]
        c_idx += [(a0 + 3 * np.arange(N)[:, None] + k3).ravel(), a1 + 3 * obj + 2]
        n_res += N
    r_all, c_all = np.concatenate(r_idx), np.concatenate(c_idx)
    J = coo_matrix((np.ones(r_all.size, np.int8), (r_all, c_all)), shape=(n_res, a1 + 3 * O))
    q0 = np.concatenate([np.zeros(a0), X0.ravel(), L_obj.ravel()])
    sol = least_squares(resid, q0, jac_sparsity=J.tocsr(), loss="soft_l1", f_scale=2.0,
                        x_scale="jac", max_nfev=max_nfev, method="trf")
    R, t = _cams(rig, variable, sol.x[:a0])
    moved = tuple(replace(c, R=R[i], t=t[i]) for i, c in enumerate(rig.cameras))
    X, L = unpack(sol.x)
    return Rig(moved, up=rig.up, frame_name=rig.frame_name), X, L


def edge_sigmas(rig: Rig, cams: Cams, z: F64, keep: np.ndarray, X: F64, L: F64, floor: float = 0.3) -> F64:
    """(C, 4) robust noise level of each camera's edge kinds (1.4826 MAD of the signed residuals
    of a fit, at least ``floor`` px): vertical edges are often several times more precise than
    horizontal ones (a person's width changes as they turn, their height does not)."""
    box, _ = model_boxes(X, np.exp(L), cams._replace(R=rig.R, t=rig.t))
    r = box - z
    C = keep.shape[1]
    mad = np.full((C, 4), np.nan)
    for c in range(C):
        for e in range(4):
            v = r[keep[:, c, e] & np.isfinite(r[:, c, e]), c, e]
            if v.size >= 3:
                mad[c, e] = 1.4826 * np.median(np.abs(v - np.median(v)))
    fallback = float(np.median(mad[np.isfinite(mad)])) if np.isfinite(mad).any() else 1.0
    return np.maximum(np.where(np.isfinite(mad), mad, fallback), floor)


def fit_reweighted(rig: Rig, cams: Cams, z: F64, keep: np.ndarray, sigma: F64, X0: F64, L0: F64,
                   variable: np.ndarray, obj: np.ndarray, floor_sd: float | None
                   ) -> tuple[Rig, F64, F64, F64]:
    """:func:`fit_boxes`, then again with each camera's edge kinds weighted by their own noise
    level measured on the first fit; the result in the input's frame (:func:`back_to`).
    Returns (rig, centres, log axes, sigmas (C, 4))."""
    new, X, L = fit_boxes(rig, cams, z, keep, sigma, (X0, L0), variable, obj, floor_sd=floor_sd)
    sig = edge_sigmas(new, cams, z, keep, X, L)
    new, X, L = fit_boxes(rig, cams, z, keep, sig, (X, L), variable, obj, floor_sd=floor_sd)
    return back_to(new, rig, variable, floor_sd is not None), X, L, sig


def back_to(new: Rig, ref: Rig, variable: np.ndarray, on_floor: bool) -> Rig:
    """The refined rig in the input's frame: unchanged where two or more cameras were held;
    else the similarity that best maps the camera centres onto the input's, restricted to the
    floor's plane (a turn about up, a horizontal shift, a scale about the floor's origin)
    where the floor anchored the height and tilt."""
    from scipy.spatial.transform import Rotation  # heavy to import (scipy): only where it runs

    if (~variable).sum() >= 2:
        return new
    if not on_floor:
        return align_to(new, ref)[0]
    B = ref.world_from_body()[:, :2]  # floor axes
    a = np.array([c.center_world for c in new.cameras]) @ B
    b = np.array([c.center_world for c in ref.cameras]) @ B
    s, R2, t2 = umeyama(np.c_[a, np.zeros(len(a))], np.c_[b, np.zeros(len(b))])
    th = np.arctan2(R2[1, 0], R2[0, 0])
    Rw = Rotation.from_rotvec(th * ref.up).as_matrix()
    return transform_rig(new, s, Rw, B @ t2[:2])


def box_residuals(rig: Rig, cams: Cams, z: F64, keep: np.ndarray, sigma: F64, X0: F64, L0: F64,
                  obj: np.ndarray) -> F64:
    """(N, C, 4) |edge residual| (px, NaN where unused) after re-fitting every row's ellipsoid
    with the cameras of ``rig`` held fixed."""
    _, X, L = fit_boxes(rig, cams, z, keep, sigma, (X0, L0), np.zeros(len(rig.cameras), bool), obj, 40)
    box, _ = model_boxes(X, np.exp(L), cams._replace(R=rig.R, t=rig.t))
    return np.where(keep, np.abs(box - z), np.nan)


def refine_boxes(scene: Scene, pre: Prepared, cfg: RefineConfig) -> RefineResult:
    t0 = time.perf_counter()
    rig, rows, fit = scene.rig, pre.rows, pre.fit
    if fit is None:
        raise ValueError("refine_boxes needs a preparation of boxes (its per-frame fits)")
    C = len(rig.cameras)
    cams = pre.cams
    keep = pre.box_keep & np.isfinite(rows.box_z)
    use = fit.ok & (keep.any(axis=2).sum(axis=1) >= 2)  # rows seen by two or more cameras
    z, keep = rows.box_z[use], keep[use]
    X0, L0 = fit.center_world[use], fit.log_axes[use]
    obj = rows.row_o[use]
    obj = np.unique(obj, return_inverse=True)[1]
    sigma = np.asarray(pre.sigma_box, dtype=np.float64) * np.sqrt(pre.box_tail)  # the fits' level
    bottom = X0 @ rig.up - np.exp(L0[:, 2])  # ellipsoid bottoms' heights (input rig)
    floor_med = float(np.median(bottom)) if bottom.size else np.inf
    floor_sd = (max(1.4826 * float(np.median(np.abs(bottom - floor_med))), 0.01)
                if abs(floor_med) < FLOOR_TOL_M else None)
    n_obs = keep.any(axis=2).sum(axis=0)
    check_enough(rig, n_obs, cfg, "boxes of objects seen by two or more cameras")
    fold = time_blocks(rows.frames[rows.row_t[use]], cfg.folds)
    gains = np.full((cfg.folds, C), -np.inf)
    held = np.zeros((2, cfg.folds, C))
    for f in range(cfg.folds):
        a, b = fold != f, fold == f
        variable = keep[a].any(axis=2).sum(axis=0) >= cfg.min_points
        if not variable.any():
            continue
        cand, _, _, _ = fit_reweighted(rig, cams, z[a], keep[a], sigma, X0[a], L0[a], variable,
                                       np.unique(obj[a], return_inverse=True)[1], floor_sd)
        ob = np.unique(obj[b], return_inverse=True)[1]
        e_in = box_residuals(rig, cams, z[b], keep[b], sigma, X0[b], L0[b], ob)
        e_ref = box_residuals(cand, cams, z[b], keep[b], sigma, X0[b], L0[b], ob)
        for c in range(C):
            ei, er = e_in[:, c][np.isfinite(e_in[:, c])], e_ref[:, c][np.isfinite(e_ref[:, c])]
            if ei.size < cfg.min_points:
                continue
            held[0, f, c], held[1, f, c] = np.median(ei), np.median(er)
            gains[f, c] = (held[0, f, c] - held[1, f, c]) / max(held[0, f, c], 1e-12)
    accept = np.all(gains > cfg.min_gain, axis=0)
    new = rig
    if accept.any():
        new, _, _, sig = fit_reweighted(rig, cams, z, keep, sigma, X0, L0, accept, obj, floor_sd)
    e_before = box_residuals(rig, cams, z, keep, sigma, X0, L0, obj)
    e_after = box_residuals(new, cams, z, keep, sigma, X0, L0, obj) if accept.any() else e_before
    per_camera: dict[str, JsonDict] = {}
    report: JsonDict = {"method": "cameras + ellipsoids, tangent-box residual (scipy soft-L1)",
                              "floor": ({"used": True, "sd_m": floor_sd, "median_bottom_m": floor_med}
                                        if floor_sd is not None else
                                        {"used": False, "median_bottom_m": floor_med}),
                              "box_sigma_px": sigma.tolist(), "folds": cfg.folds,
                              "refine_intrinsics": False, "cameras": per_camera}
    for c, cam in enumerate(rig.cameras):
        dc, da = pose_change(cam, new.cameras[c])
        eb, ea = e_before[:, c], e_after[:, c]
        why = ("refined: held-out box residual lower in every fold" if accept[c] else
               f"kept: too few boxes ({int(n_obs[c])})" if n_obs[c] < 2 * cfg.min_points else
               f"kept: refining did not lower its held-out box residual by {cfg.min_gain:.0%} in every fold")
        per_camera[cam.name] = {
            "refined": bool(accept[c]), "why": why, "observations": int(n_obs[c]),
            "heldout_median_px_input": held[0, :, c].round(4).tolist(),
            "heldout_median_px_refined": held[1, :, c].round(4).tolist(),
            "median_px_before": float(np.nanmedian(eb)) if np.isfinite(eb).any() else None,
            "median_px_after": float(np.nanmedian(ea)) if np.isfinite(ea).any() else None,
            "centre_moved_m": dc, "rotation_moved_deg": da}
    report["refined_cameras"] = [c.name for c, a in zip(rig.cameras, accept, strict=True) if a]
    report["large_moves"] = list(large_moves(rig, new, accept, X0))
    report["seconds"] = time.perf_counter() - t0
    return RefineResult(new, report)
