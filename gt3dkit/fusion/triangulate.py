"""The no-temporal-model baseline, per object-frame.

* Boxes: one least-squares ellipsoid per object-frame (:func:`fit_boxes`).
* Keypoints: linear (DLT) triangulation of the undistorted points of each joint.

Object-frames seen by fewer than two cameras get no row; their number is in
``info["skipped_lt2_views"]``. Keypoint-only objects get the ellipsoid around their
joints, as the UKF does.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.ukf_smoother import ellipsoid_around, prepare
from gt3dkit.types import Scene, TrackSet


@dataclass(frozen=True)
class TriangulationConfig:
    clip_tol_px: float = 1.0
    min_views: int = 2


class Triangulation:
    """Per-frame least-squares fit (boxes) and DLT (keypoints); no temporal model."""

    name = "triangulation"

    def __init__(self, config: TriangulationConfig | None = None) -> None:
        self.config = config or TriangulationConfig()

    def estimate(self, scene: Scene) -> TrackSet:
        t0 = time.perf_counter()
        pre = prepare(scene, self.config.clip_tol_px)
        rows, cams, fit = pre.rows, pre.cams, pre.fit
        R = len(rows)
        info: dict[str, object] = {"estimator": self.name, "params": dict(self.config.__dict__)}
        keep = np.zeros(R, bool)
        centre = np.full((R, 3), np.nan)
        semi = np.full((R, 3), np.nan)
        sd = np.full((R, 3), np.nan)
        kpt = np.zeros((R, 0, 3))
        kpt_sd = np.zeros((R, 0))
        if fit is not None:
            n_box_views = np.all(np.isfinite(rows.box_z), axis=-1).sum(axis=1)
            sigma = pre.sigma_box
            ok = fit.ok & (n_box_views >= self.config.min_views)
            keep |= ok
            centre[ok], semi[ok] = fit.center_world[ok], np.exp(fit.log_axes[ok])
            sd[ok] = np.sqrt(np.einsum("rii->ri", fit.cov[ok][:, :3, :3])) * sigma
            info["sigma_px"] = sigma
        if pre.kpt0 is not None:
            kpt, rms = pre.kpt0, pre.sigma_kpt
            nv = np.isfinite(rows.kpt_z[..., 0]).sum(axis=1)  # (R, J)
            # first-order sd: pixel noise at the joint's depth, averaged over its views
            depth = np.einsum("cj,rkj->rkc", cams.R[:, 2, :], kpt) + cams.t[:, 2]
            f = cams.K[:, [0, 1], [0, 1]].mean(axis=1)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # joints no camera saw
                m_per_px = np.nanmedian(np.where(np.isfinite(np.swapaxes(rows.kpt_z[..., 0], 1, 2)),
                                                 np.abs(depth) / f, np.nan), axis=2)
            kpt_sd = rms * m_per_px / np.sqrt(np.maximum(nv, 1))
            kpt_sd[~np.isfinite(kpt[..., 0])] = np.nan
            has = np.isfinite(kpt[..., 0]).any(axis=1)
            nobox = ~keep & has
            c2, s2, d2 = ellipsoid_around(kpt, kpt_sd, cams.world_from_body)
            centre[nobox], semi[nobox], sd[nobox] = c2[nobox], s2[nobox], d2[nobox]
            keep |= has
            info["kpt_sigma_px"] = rms
        k = np.flatnonzero(keep)
        info.update({"skipped_lt2_views": int(R - k.size), "object_frames": int(k.size),
                     "seconds": time.perf_counter() - t0})
        return TrackSet(frame=rows.frames[rows.row_t[k]], track_id=rows.obj_ids[rows.row_o[k]],
                        center_world=centre[k], semi_axes=semi[k], center_sd=sd[k],
                        n_views=rows.n_views[k], kpt_world=kpt[k], kpt_sd=kpt_sd[k], info=info)
