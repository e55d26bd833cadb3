"""Box-edge noise by crowding (:mod:`gt3dkit.fusion.preparation.crowd`): each label's covered
share, and the bands' levels used only where the data show crowded edges varying more."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from gt3dkit.fusion.preparation.crowd import CROWD_RATIO_NEEDED, band_of, covered_share, crowd_levels


def _rows(box_z: np.ndarray, row_t: np.ndarray) -> SimpleNamespace:
    return SimpleNamespace(box_z=box_z, row_t=row_t)


def test_covered_share_is_the_area_other_labels_of_the_view_cover() -> None:
    nan = [np.nan] * 4
    box = np.array([
        [[0, 0, 10, 10], nan],     # frame 0: half of it under the next one in camera 0
        [[5, 0, 15, 10], [0, 0, 4, 4]],
        [[100, 100, 110, 120], [0, 0, 4, 4]],  # frame 1: alone in camera 0, on top of the next in 1
        [[0, 0, 1, 1], [0, 0, 2, 4]],
    ], dtype=float)
    share = covered_share(_rows(box, np.array([0, 0, 1, 1])))
    np.testing.assert_allclose(share[:2, 0], [0.5, 0.5])
    assert np.isnan(share[0, 1]) and share[1, 1] == 0.0  # frame 0's camera 1: one label only
    assert share[2, 0] == 0.0 and share[2, 1] == 0.5 and share[3, 1] == 1.0  # 8 of 8 px covered
    assert band_of(np.array([0.0, 0.3, 0.5, 0.99, np.nan])).tolist() == [0, 1, 2, 3, 0]


def _crowd(seed: int, crowded_sd: float) -> tuple[object, np.ndarray]:
    """400 frames of 4 people in 2 cameras: two stand apart, two overlap by 60 %; the overlapping
    ones' edge residuals have ``crowded_sd`` times the others' spread."""
    rng = np.random.default_rng(seed)
    F, C = 400, 2
    x = np.array([0.0, 300.0, 600.0, 660.0])
    box = np.zeros((F * 4, C, 4))
    box[..., 0] = np.repeat(np.tile(x, F)[:, None], C, 1)
    box[..., 2] = box[..., 0] + 100
    box[..., 3] = 200
    rows = _rows(box, np.repeat(np.arange(F), 4))
    crowded = np.tile([False, False, True, True], F)
    sd = np.where(crowded, crowded_sd, 1.0)[:, None, None]
    r2 = (rng.normal(size=box.shape) * sd) ** 2
    return crowd_levels(rows, r2, np.ones_like(r2), np.ones(box.shape, bool), 0.001), crowded


def test_crowded_edges_that_vary_more_are_weighted_by_their_band() -> None:
    levels, crowded = _crowd(0, 2.0)
    assert levels.used
    scale = levels.scale()
    assert scale is not None
    np.testing.assert_allclose(scale[~crowded], 1.0)
    assert np.all(np.abs(scale[crowded] - 4.0) < 0.8)  # the variance: (2 sd)^2 over 1


def test_bands_that_vary_alike_keep_the_one_level() -> None:
    levels, _ = _crowd(1, 1.0)
    assert not levels.used and levels.scale() is None
    assert levels.ratio.max() < CROWD_RATIO_NEEDED


def test_a_crowd_in_a_room_seen_from_its_corners() -> None:
    """The simulator's crowded room (4 cameras in its top corners looking down, 4 fps, 12 walkers,
    boxes cut by nearer people as a detector draws them): the scene loads (no box is said to be
    behind its camera because other views, cut, place its person metres off), the UKF beats the
    per-frame fit on the floor, and every truth person-frame has a row."""
    import tempfile
    from pathlib import Path

    from gt3dkit.api import load_scene, reconstruct
    from gt3dkit.eval.metrics import box_errors
    from gt3dkit.sim import Errors, simulate, write_scene

    sim = simulate("native", seed=1, frames=40, people=12, noise_px=3.0, motion="walk", rig="room",
                   errors=Errors(cut_by_nearer=True))
    assert sim.fps == 4.0 and len(sim.rig.cameras) == 4
    assert sum(1 for row in sim.injected if row[4] == "cut_box") > 100
    with tempfile.TemporaryDirectory() as d:
        write_scene(sim, Path(d) / "in", "native")
        scene = load_scene(Path(d) / "in")
    ukf, per_frame = reconstruct(scene, "ukf"), reconstruct(scene, "triangulation")
    assert scene.truth is not None
    e_ukf = box_errors(ukf, scene.truth, scene.rig.up)
    e_tri = box_errors(per_frame, scene.truth, scene.rig.up)
    assert e_ukf.ground_mean_m < 0.85 * e_tri.ground_mean_m, (e_ukf.ground_mean_m, e_tri.ground_mean_m)
    assert e_ukf.coverage == 1.0
