"""fusion.triangulate, the per-frame baseline: two views' joints against OpenCV's own
triangulation, and the rows it cannot place counted, not invented."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import cv2
import numpy as np

from gt3dkit.api import load_scene, reconstruct
from gt3dkit.sim import simulate_skeletons, write_skeleton_scene


def _opencv_joints(scene, frame: int, track: int) -> np.ndarray:
    """(J, 3) ``cv2.triangulatePoints`` of the two views of (frame, track): the pixels undistorted
    by ``cv2.undistortPoints`` (iterated to 1e-12), the projection matrices ``[R | t]``."""
    obs = scene.obs
    m = np.flatnonzero((obs.frame == frame) & (obs.track_id == track))
    assert len(m) == 2
    P, pts = [], []
    stop = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    for k in m:
        cam = scene.rig.cameras[int(obs.cam[k])]
        P.append(np.c_[cam.R, cam.t])
        uv = obs.kpt_uv_px[k].reshape(-1, 1, 2)
        pts.append(cv2.undistortPoints(uv, cam.K, cam.dist, None, None, None, stop).reshape(-1, 2).T)
    Xh = cv2.triangulatePoints(P[0], P[1], pts[0], pts[1])
    return (Xh[:3] / Xh[3]).T


def test_two_views_are_opencvs_triangulation(tmp_path: Path) -> None:
    """With two cameras (1 px noise) every joint is where OpenCV's linear triangulation puts it;
    a row one camera alone sees is left out and counted in ``info.skipped_lt2_views``."""
    sk = simulate_skeletons("native", seed=3, frames=4, people=2, cameras=2, noise_px=1.0)
    write_skeleton_scene(sk, tmp_path / "in", "native")
    scene = load_scene(tmp_path / "in")
    tracks = reconstruct(scene, "triangulation")
    assert len(tracks) == 8 and tracks.info.skipped_lt2_views == 0
    checked = 0
    for r in range(len(tracks)):
        ref = _opencv_joints(scene, int(tracks.frame[r]), int(tracks.track_id[r]))
        seen = np.isfinite(tracks.kpt_world[r]).all(axis=1)
        np.testing.assert_allclose(tracks.kpt_world[r][seen], ref[seen], rtol=0, atol=1e-6)
        checked += int(seen.sum())
    assert checked > 100
    # one camera's view of (first frame, first id) removed: that row has one view left
    obs = scene.obs
    f0, t0 = int(tracks.frame[0]), int(tracks.track_id[0])
    drop = np.flatnonzero((obs.frame == f0) & (obs.track_id == t0))[:1]
    keep = np.ones(len(obs), bool)
    keep[drop] = False
    lone = reconstruct(dataclasses.replace(scene, obs=obs.select(keep)), "triangulation")
    assert len(lone) == 7 and lone.info.skipped_lt2_views == 1
    assert not np.any((lone.frame == f0) & (lone.track_id == t0))
