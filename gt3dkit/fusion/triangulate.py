"""The no-temporal-model baseline: one least-squares ellipsoid per object-frame.

Object-frames seen by fewer than two cameras get no row; their number is in
``info["skipped_lt2_views"]``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from gt3dkit.fusion.boxfit import auto_sigma_px, fit_boxes
from gt3dkit.fusion.rows import build_rows
from gt3dkit.fusion.ukf_smoother import check_in_front
from gt3dkit.geom.camera import Cams
from gt3dkit.types import Scene, TrackSet


@dataclass(frozen=True)
class TriangulationConfig:
    clip_tol_px: float = 1.0
    min_views: int = 2


class Triangulation:
    """Per-frame least-squares fit (boxes); no temporal model."""

    name = "triangulation"

    def __init__(self, config: TriangulationConfig | None = None) -> None:
        self.config = config or TriangulationConfig()

    def estimate(self, scene: Scene) -> TrackSet:
        t0 = time.perf_counter()
        rows = build_rows(scene, self.config.clip_tol_px)
        cams = Cams.of(scene.rig)
        n_box_views = np.all(np.isfinite(rows.box_z), axis=-1).sum(axis=1)
        fit = fit_boxes(rows.box_z, rows.box_mask, cams)
        check_in_front(scene, rows, fit)
        sigma = auto_sigma_px(fit)
        keep = fit.ok & (n_box_views >= self.config.min_views)
        sd = np.sqrt(np.einsum("rii->ri", fit.cov[:, :3, :3])) * sigma
        info = {"estimator": self.name, "params": dict(self.config.__dict__),
                "sigma_px": sigma, "skipped_lt2_views": int((~keep).sum()),
                "object_frames": int(keep.sum()), "seconds": time.perf_counter() - t0}
        k = np.flatnonzero(keep)
        return TrackSet(frame=rows.frames[rows.row_t[k]], track_id=rows.obj_ids[rows.row_o[k]],
                        center_world=fit.center_world[k], semi_axes=np.exp(fit.log_axes[k]),
                        center_sd=sd[k], n_views=rows.n_views[k],
                        kpt_world=np.zeros((len(k), 0, 3)), kpt_sd=np.zeros((len(k), 0)),
                        info=info)
