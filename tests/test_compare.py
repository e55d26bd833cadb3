"""GTSAM smoother and gt3d compare."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from gt3dkit import load_scene, reconstruct
from gt3dkit.cli import main
from gt3dkit.eval.metrics import box_errors
from gt3dkit.eval.pose import mpjpe_by_id
from gt3dkit.sim import Errors, simulate_skeletons, write_skeleton_scene


def test_gtsam_on_exact_box_scene(small_native) -> None:
    scene, _ = small_native
    tr = reconstruct(scene, "gtsam")
    e = box_errors(tr, scene.truth, scene.rig.up)
    assert e.coverage == 1.0 and e.centre_mean_m < 0.004 and e.height_mean_m < 0.004
    assert np.all(np.isfinite(tr.center_sd)) and np.all(tr.center_sd > 0)
    assert tr.info.details["iterations"] > 0


@pytest.mark.parametrize("fixed_noise", [False, True])
def test_gtsam_box_chain_is_gtsams_own_graph(tmp_path: Path, monkeypatch, fixed_noise: bool) -> None:
    """The box objects' graph linearised in batches (gtsam_chain.solve_boxes) is GTSAM's
    own nonlinear graph of CustomFactors and robust noise models (GTSAMSmoother._solve_object):
    the same solution, iterations and marginal sds on a scene whose shifted boxes, gaps and
    one-camera objects make the Huber losses and the rows without views matter; with the
    process noise fixed, through the discrepancy principle's restarts as well."""
    from gt3dkit.fusion.graph import smoother as sg
    from gt3dkit.fusion.preparation.prepare import prepare
    from gt3dkit.sim import Errors, simulate, write_scene

    sim = simulate("native", seed=4, frames=30, people=4, noise_px=1.0,
                   errors=Errors(shifted=0.05, gap=(10, 13), single_view=1, dropped=0.2),
                   motion="stop-and-turn")
    write_scene(sim, tmp_path, "native")
    scene = load_scene(tmp_path)
    pre = prepare(scene)
    cfg = sg.GTSAMConfig(accel_sd=0.05, shape_sd=0.01, discrepancy_step=30.0) if fixed_noise \
        else sg.GTSAMConfig()
    est = sg.GTSAMSmoother(cfg)
    batched = est.estimate(scene, pre)

    def own_graph(gtsam, cfg, pre, mine, start_values, tuned, fps, start=None):
        return est._solve_object(gtsam, pre, mine, start_values, None, [], tuned, fps, start)

    monkeypatch.setattr(sg, "solve_boxes", own_graph)
    ref = est.estimate(scene, pre)
    assert batched.info.details["iterations"] == ref.info.details["iterations"]
    checks, ref_checks = (t.info.details["process_noise_discrepancy"] for t in (batched, ref))
    assert [c["rescaled"] for c in checks] == [c["rescaled"] for c in ref_checks]
    assert [c["measurement_chi2_per_entry"] for c in checks] == pytest.approx(
        [c["measurement_chi2_per_entry"] for c in ref_checks], rel=1e-9)
    assert checks[0]["rescaled"] if fixed_noise else not checks
    np.testing.assert_allclose(batched.center_world, ref.center_world, atol=1e-7)
    np.testing.assert_allclose(batched.semi_axes, ref.semi_axes, rtol=1e-7)
    np.testing.assert_allclose(batched.center_sd, ref.center_sd, rtol=1e-6)


def test_gtsam_on_skeleton_scene(tmp_path: Path) -> None:
    sim = simulate_skeletons("native", seed=6, frames=6, people=1, cameras=5, errors=Errors(dropped=0.05))
    write_skeleton_scene(sim, tmp_path, "native")
    scene = load_scene(tmp_path)
    tr = reconstruct(scene, "gtsam")
    mm, matched, total = mpjpe_by_id(tr, scene.truth)
    assert matched == total and mm < 0.05
    assert np.all(np.isfinite(tr.kpt_sd)) and np.all(tr.kpt_sd > 0)


def test_cli_compare(tmp_path: Path, capsys) -> None:
    src = tmp_path / "in"
    assert main(["simulate", "--out", str(src), "--seed", "2", "--frames", "6",
                 "--people", "2"]) == 0
    out = tmp_path / "cmp"
    assert main(["compare", str(src), "--out", str(out), "--no-progress"]) == 0
    for name in ("ukf", "gtsam", "triangulation"):
        assert (out / name / "tracks.csv").exists() and (out / name / "meta.json").exists()
    with open(out / "comparison.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["estimator"] for r in rows] == ["ukf", "gtsam", "triangulation"]
    for r in rows:
        assert float(r["reproj_mean_px"]) < 1.0  # whole-pixel boxes
        assert float(r["truth_centre_mean_m"]) < 0.01
    # the distance between two estimators' centres, recomputed from their tracks.csv
    def centres(name: str) -> dict[tuple[str, str], np.ndarray]:
        with open(out / name / "tracks.csv") as f:
            return {(r["frame"], r["id"]): np.array([float(r[k]) for k in "xyz"]) for r in csv.DictReader(f)}

    ukf, gts = centres("ukf"), centres("gtsam")
    d = np.array([np.linalg.norm(ukf[k] - gts[k]) for k in ukf.keys() & gts.keys()])
    assert len(d) > 0
    assert float(rows[0]["dist_to_gtsam_mean_m"]) == pytest.approx(d.mean(), abs=2e-6)  # 6-decimal files
    assert float(rows[0]["dist_to_gtsam_mean_m"]) < 0.01
    assert "comparison.csv" in capsys.readouterr().out
