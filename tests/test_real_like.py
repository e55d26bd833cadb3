"""The simulator's real-label conditions (WILDTRACK's): boxes an annotation tool drew from a solid
placed on a 2.5 cm ground grid (the occupancy-map rectangle, or a cylinder's box), partly outside
the image; walkers who stop and turn between two annotations at 2 fps; and the estimators on them:
the smoothers as good as the per-frame fit, no row far off, sds that cover."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from gt3dkit.api import reconstruct
from gt3dkit.eval.metrics import match_rows
from gt3dkit.sim import POSITION_GRID_M, Errors, simulate
from tests.scenes import written_scene


@pytest.mark.parametrize("labels", ["cylinder", "pom"])
def test_an_annotation_tools_solid_is_round_and_on_its_grid(labels: str) -> None:
    """(The boxes themselves: tests/geom/test_box_models.py, against OpenCV.)"""
    sim = simulate("wildtrack", seed=3, frames=6, people=8, labels=labels, errors=Errors(dropped=0.0))
    np.testing.assert_allclose(sim.center_world[:, :2] / POSITION_GRID_M,
                               np.round(sim.center_world[:, :2] / POSITION_GRID_M), atol=1e-9)
    np.testing.assert_array_equal(sim.semi_axes[:, 0], sim.semi_axes[:, 1])  # round


def test_stop_and_turn_walkers_stop_and_turn() -> None:
    sim = simulate("wildtrack", seed=4, frames=60, people=10, motion="stop-and-turn", labels="cylinder")
    dt = 5 / 10.0  # WILDTRACK: every 5th frame at 10 fps
    stops = turns = 0
    for i in np.unique(sim.truth_id):
        p = sim.center_world[sim.truth_id == i, :2]
        v = np.linalg.norm(np.diff(p, axis=0), axis=1) / dt
        a = np.linalg.norm(np.diff(p, 2, axis=0), axis=1) / dt**2
        stops += int(np.any((v[:-1] < 0.1) & (v[1:] < 0.1)))  # standing for a second
        turns += int(np.any(a > 2.5))  # the labels' own accelerations
    assert stops >= 5 and turns >= 5, (stops, turns)


@pytest.mark.parametrize(("seed", "labels"), [(1, "pom"), (3, "cylinder")])
def test_smoothers_on_real_like_labels(tmp_path: Path, seed: int, labels: str) -> None:
    """An annotation tool's labels, partly outside the image, stop-and-turn walkers at 2 fps: UKF
    and GTSAM at most 1.1x the per-frame fit's mean ground error, no row 0.1 m off, 98 % within the
    sd."""
    sc, sim = written_scene(tmp_path, "wildtrack", seed=seed, frames=60, people=16, motion="stop-and-turn",
                            labels=labels, errors=Errors(dropped=0.0))
    assert sc.box_model == labels
    W, H = sc.rig.wh[:, 0], sc.rig.wh[:, 1]
    b = sc.obs.box_xyxy_px
    outside = (b[:, 0] < 0) | (b[:, 1] < 0) | (b[:, 2] > W[sc.obs.cam] - 1) | (b[:, 3] > H[sc.obs.cam] - 1)
    assert outside.sum() >= 20  # read as they are: no clipping
    mean = {}
    for est in ("ukf", "gtsam", "triangulation"):
        t = reconstruct(sc, est)
        it, ig = match_rows(t, sc.truth)
        e2 = t.center_world[it, :2] - sc.truth.center_world[ig, :2]
        err = np.linalg.norm(e2, axis=1)
        mean[est] = err.mean()
        if est != "triangulation":
            assert len(np.unique(ig)) == len(sc.truth.frame)
            assert err.max() < 0.1, (est, err.max())
            z2 = np.sum(e2**2 / (t.center_sd[it, :2] ** 2 + (POSITION_GRID_M / np.sqrt(12)) ** 2), axis=1)
            assert np.mean(z2 <= chi2.ppf(0.99, 2)) >= 0.98, est
    assert mean["ukf"] <= 1.1 * mean["triangulation"], mean
    assert mean["gtsam"] <= 1.1 * mean["triangulation"], mean


def test_a_detector_in_a_crowd() -> None:
    """Detections as a detector in a crowd makes them (:class:`Errors`): joints hidden behind a
    nearer person guessed at low confidence, joints taken from another person, left/right swaps,
    confidences above 1, and pixel noise that grows as the confidence falls. The run reads the
    confidences above 1 with one warning, learns that the least confident points are the
    noisiest (the factor of the lowest confidence bin well above ``1/conf``'s), keeps every joint
    within centimetres, and flags the joints taken from another person and the swaps."""
    from gt3dkit.api import estimate_checked, load_scene
    from gt3dkit.fusion.base import make_estimator
    from gt3dkit.sim import simulate_skeletons, write_skeleton_scene

    errors = Errors(occluded=0.5, wrong_person=0.02, over_one=0.05, noise_by_confidence=True, swaps=0.02)
    sk = simulate_skeletons("native", seed=5, frames=30, people=4, cameras=6, noise_px=1.5, errors=errors,
                            confidences=True)
    kinds = [k for *_, k, _ in sk.injected]
    for kind in ("occluded_joint", "wrong_person_joint", "swapped_joints", "confidence_above_1"):
        assert kinds.count(kind) >= 2, kind
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        write_skeleton_scene(sk, Path(tmp) / "in", "native")
        scene = load_scene(Path(tmp) / "in")
    assert sum("confidence above 1" in w for w in scene.all_warnings) == 1
    tracks, qa = estimate_checked(scene, make_estimator("ukf"))
    curve = tracks.info.details["preparation"]["keypoints"]["confidence"]
    assert curve["factor"][0] > 2.0 * curve["confidence"][-1] / curve["confidence"][0]
    it, ig = match_rows(tracks, scene.truth)
    e = np.linalg.norm(tracks.kpt_world[it] - scene.truth.kpt_world[ig], axis=-1)
    assert np.nanmedian(e) < 0.003 and np.nanmax(e) < 0.05
    flagged = {(int(f), c, int(i), str(j)) for f, c, i, j, *_ in qa.rows}
    for kind in ("wrong_person_joint", "swapped_joints"):
        hits = [(f, c, i, str(j).split("+")[0]) for f, c, i, j, k, _ in sk.injected if k == kind]
        found = [h for h in hits if h in flagged]
        assert len(found) >= 0.8 * len(hits), (kind, hits, sorted(flagged))
