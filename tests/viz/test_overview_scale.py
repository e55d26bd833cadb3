"""The 3D overview drawn to the objects' scale: a mouse's skeleton on a grid of 10 cm cells with
joints a tenth the size of a person's, people (and larger) on 1 m cells as before."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from gt3dkit.api import load_scene
from gt3dkit.sim import simulate_skeletons, write_skeleton_scene
from gt3dkit.types import SkeletonScene, TrackSet
from gt3dkit.viz.overview import grid_cell_m, object_size_m, overview_drawing


def _truth_tracks(skeleton: str) -> tuple[SkeletonScene, TrackSet]:
    sk = simulate_skeletons("native", seed=1, frames=3, people=2, cameras=4, skeleton=skeleton)
    R = len(sk.truth_id)
    tracks = TrackSet(frame=sk.truth_frame, track_id=sk.truth_id, center_world=sk.kpt_world.mean(axis=1),
                      semi_axes=np.full((R, 3), 0.1), center_sd=np.full((R, 3), 0.01),
                      n_views=np.full(R, 4), kpt_world=sk.kpt_world,
                      kpt_sd=np.full(sk.kpt_world.shape[:2], 0.01))
    return sk, tracks


def test_the_grid_and_the_joints_follow_the_objects_size() -> None:
    assert grid_cell_m(1.7) == 1.0 and grid_cell_m(4.5) == 1.0  # people, cars: metres as before
    assert grid_cell_m(0.12) == 0.1 and grid_cell_m(0.03) == 0.01
    _, person = _truth_tracks("coco17")
    _, mouse = _truth_tracks("mouse")
    assert 1.0 < object_size_m(person) < 2.5 and 0.05 < object_size_m(mouse) < 0.3
    boxes = TrackSet(frame=np.zeros(2, np.int64), track_id=np.arange(2), center_world=np.zeros((2, 3)),
                     semi_axes=np.array([[0.3, 0.3, 0.9], [0.25, 0.3, 0.85]]), center_sd=np.zeros((2, 3)),
                     n_views=np.full(2, 3), kpt_world=np.zeros((2, 0, 3)), kpt_sd=np.zeros((2, 0)))
    assert abs(object_size_m(boxes) - 1.75) < 1e-9


def test_a_mouse_is_drawn_at_its_own_scale(tmp_path: Path) -> None:
    for skeleton, cell in (("coco17", 1.0), ("mouse", 0.1)):
        sk, tracks = _truth_tracks(skeleton)
        write_skeleton_scene(sk, tmp_path / skeleton, "native")
        scene = load_scene(tmp_path / skeleton)
        drawing, _, _ = overview_drawing(scene, tracks, int(tracks.frame[0]), close_up=True)
        balls = [m for m in drawing.meshes if len(m[0]) > 20]  # the joints' spheres
        radius = max(float(np.ptp(v[:, 0])) / 2 for v, *_ in balls)
        assert abs(radius - 0.025 * cell) < 1e-3 * cell, (skeleton, radius)
