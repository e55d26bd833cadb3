"""The no-temporal-model baseline, per object-frame: the robust per-frame fits of
:func:`gt3dkit.fusion.preparation.prepare.prepare`, reported as they are.

* Boxes: one least-squares ellipsoid per object-frame (Levenberg-Marquardt on the tangent-box
  edges, edges the other views disagree with left out).
* Keypoints: robust (MSAC) DLT triangulation of the undistorted points of each joint, with
  its first-order covariance.

Object-frames seen by fewer than two cameras get no row; their number is in
``info.skipped_lt2_views``. Keypoint-only objects get the ellipsoid around their
joints, as the UKF does.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.base import Capabilities
from gt3dkit.fusion.preparation.prepare import Prepared, axis_sd, ellipsoid_around, largest_sd, prepare
from gt3dkit.fusion.ukf.bones import PersonBones
from gt3dkit.types import JsonDict, RunInfo, Scene, TrackSet


@dataclass(frozen=True)
class TriangulationConfig:
    clip_tol_px: float = 1.0
    min_views: int = 2
    sigma_px: float | None = None  # box-edge noise (px); None = from the data


class Triangulation:
    """Per-frame least-squares fit (boxes) and DLT (keypoints); no temporal model."""

    name = "triangulation"
    bones: PersonBones | None = None  # (no bones: Estimator.bones)

    capabilities = Capabilities()

    def __init__(self, config: TriangulationConfig | None = None) -> None:
        self.config = config or TriangulationConfig()

    def process_noise(self, scene: Scene, pre: Prepared | None = None) -> None:
        """None: each frame on its own, no process noise."""
        return None

    def bone_samples(self, scene: Scene, pre: Prepared | None = None) -> None:
        """None: it ties no bones."""
        return None

    def prepare(self, scene: Scene) -> Prepared:
        return prepare(scene, self.config.clip_tol_px, self.config.sigma_px)

    def estimate(self, scene: Scene, pre: Prepared | None = None) -> TrackSet:
        t0 = time.perf_counter()
        pre = pre or self.prepare(scene)
        rows, cams, fit = pre.rows, pre.cams, pre.fit
        R = len(rows)
        details: JsonDict = {}
        keep = np.zeros(R, bool)
        centre = np.full((R, 3), np.nan)
        semi = np.full((R, 3), np.nan)
        sd = np.full((R, 3), np.nan)
        kpt = np.zeros((R, 0, 3))
        kpt_sd = np.zeros((R, 0))
        if fit is not None:
            n_box_views = np.all(np.isfinite(rows.box_z), axis=-1).sum(axis=1)
            ok = fit.ok & (n_box_views >= self.config.min_views)
            keep |= ok
            centre[ok], semi[ok] = fit.center_world[ok], np.exp(fit.log_axes[ok])
            sd[ok] = axis_sd(fit.cov[ok][:, :3, :3])
            details["sigma_px"] = pre.info.boxes.sigma_px if pre.info.boxes is not None else None
        if pre.kpt0 is not None and pre.kpt0_cov is not None:
            kpt = pre.kpt0
            kpt_sd = largest_sd(pre.kpt0_cov)
            kpt_sd[~np.isfinite(kpt[..., 0])] = np.nan
            has = np.isfinite(kpt[..., 0]).any(axis=1)
            nobox = ~keep & has
            c2, s2, d2 = ellipsoid_around(kpt, kpt_sd, cams.world_from_body)
            centre[nobox], semi[nobox], sd[nobox] = c2[nobox], s2[nobox], d2[nobox]
            keep |= has
            details["kpt_sigma_px"] = pre.info.keypoints.sigma_px if pre.info.keypoints is not None else None
        details["preparation"] = pre.info.as_json()
        k = np.flatnonzero(keep)
        info = RunInfo(self.name, dict(self.config.__dict__), time.perf_counter() - t0,
                       object_frames=int(k.size), skipped_lt2_views=int(R - k.size), details=details)
        return TrackSet(frame=rows.frames[rows.row_t[k]], track_id=rows.obj_ids[rows.row_o[k]],
                        center_world=centre[k], semi_axes=semi[k], center_sd=sd[k],
                        n_views=rows.n_views[k], kpt_world=kpt[k], kpt_sd=kpt_sd[k], info=info)
