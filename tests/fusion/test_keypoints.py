"""Keypoints: Panoptic loader, DLT against GTSAM, the keypoint UKF, outputs, bad input."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import gtsam
import numpy as np
import pytest

from gt3dkit import load_scene, reconstruct
from gt3dkit.cli import main
from gt3dkit.commands.common import bundled
from gt3dkit.eval.pose import mpjpe_by_id, pose_scores, score_tracks
from gt3dkit.geom.camera import project_points
from gt3dkit.geom.triangulate import normalized_points, triangulate_dlt
from gt3dkit.sim import Errors, simulate_skeletons, write_skeleton_scene
from gt3dkit.skeletons import SKELETONS, skeleton_for


@pytest.fixture(scope="module")
def skel_native(tmp_path_factory):
    root = Path(tmp_path_factory.mktemp("skel")) / "in"
    sim = simulate_skeletons("native", seed=2, frames=8, people=2, cameras=6, errors=Errors(dropped=0.05))
    write_skeleton_scene(sim, root, "native")
    return root, sim


def test_panoptic_real_subset_loads() -> None:
    s = load_scene(bundled("panoptic_160906_band1"))
    assert s.layout == "panoptic" and s.skeleton == "coco19"
    assert len(s.rig.cameras) == 31 and all(c.name.startswith("00_") for c in s.rig.cameras)
    np.testing.assert_allclose(s.rig.up, [0, -1, 0])
    assert len(s.frames) == 20 and sorted(set(s.truth.track_id.tolist())) == [0, 1, 2]
    # centimetres -> metres: people stand at y <= 0 with heads about 1.6 m up (y ~ -1.6)
    assert np.nanmin(s.truth.kpt_world[..., 1]) > -2.2 and np.nanmin(s.truth.kpt_world[..., 1]) < -1.2
    # camera centres on the dome: |x|,|z| up to ~2.5 m, not 250
    c = np.stack([cam.center_world for cam in s.rig.cameras])
    assert 1.5 < np.abs(c[:, [0, 2]]).max() < 4.0
    # joints with confidence -1 have no truth and are never observed
    raw = json.loads((bundled("panoptic_160906_band1") / "hdPose3d_stage1_coco19" /
                      "body3DScene_00000168.json").read_text())
    conf = np.array(raw["bodies"][0]["joints19"]).reshape(19, 4)[:, 3]
    row = np.flatnonzero((s.truth.frame == 168) & (s.truth.track_id == raw["bodies"][0]["id"]))[0]
    np.testing.assert_array_equal(np.isnan(s.truth.kpt_world[row, :, 0]), conf < 0.1)


def test_panoptic_loader_on_written_sequence(tmp_path: Path) -> None:
    sim = simulate_skeletons("panoptic", seed=4, frames=3, people=2, cameras=4)
    write_skeleton_scene(sim, tmp_path, "panoptic")
    doc = json.loads((tmp_path / "calibration_sim.json").read_text())
    assert any(c["type"] == "vga" for c in doc["cameras"])
    s = load_scene(tmp_path)
    assert [c.name for c in s.rig.cameras] == [c.name for c in sim.rig.cameras]  # VGA dropped
    for a, b in zip(s.rig.cameras, sim.rig.cameras, strict=True):
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)  # written in cm, read in m
    order = np.lexsort((s.truth.track_id, s.truth.frame))
    order_sim = np.lexsort((sim.truth_id, sim.truth_frame))
    np.testing.assert_allclose(s.truth.kpt_world[order], sim.kpt_world[order_sim], atol=1e-6)
    # the 2D points are the distorted projections of the joints
    r = 0
    f, i, c = s.obs.frame[r], s.obs.track_id[r], s.obs.cam[r]
    X = s.truth.kpt_world[(s.truth.frame == f) & (s.truth.track_id == i)][0]
    uv, _ = project_points(X, s.rig.K[c:c + 1], s.rig.dist[c:c + 1], s.rig.R[c:c + 1],
                           s.rig.t[c:c + 1])
    seen = np.isfinite(s.obs.kpt_uv_px[r, :, 0])
    np.testing.assert_allclose(s.obs.kpt_uv_px[r][seen], uv[seen, 0], atol=1e-9)
    # a camera subset
    sub = load_scene(tmp_path, cameras=["00_00", "00_02"])
    assert sub.rig.names == ["00_00", "00_02"]


@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_dlt_matches_gtsam_triangulation(noise: float) -> None:
    sim = simulate_skeletons("native", seed=5, frames=2, people=1, cameras=6, errors=Errors(dropped=0.0),
                             noise_px=noise)
    rig = sim.rig
    uv = sim.uv[0]  # (C, J, 2)
    xy = normalized_points(np.swapaxes(uv, 0, 1), rig.K, rig.dist)  # (J, C, 2)
    X, nv = triangulate_dlt(xy, rig.R, rig.t)
    poses = [gtsam.Pose3(gtsam.Rot3(c.R.T), c.center_world) for c in rig.cameras]
    cal = gtsam.Cal3_S2(1.0, 1.0, 0.0, 0.0, 0.0)
    for j in range(xy.shape[0]):
        ok = np.isfinite(xy[j, :, 0])
        ref = gtsam.triangulatePoint3([p for p, o in zip(poses, ok, strict=True) if o], cal,
                                      [m for m in xy[j][ok]], 1e-9, False)
        np.testing.assert_allclose(X[j], np.asarray(ref).reshape(3), atol=1e-9 if noise == 0 else 1e-4)
        if noise == 0:
            np.testing.assert_allclose(X[j], sim.kpt_world[0, j], atol=1e-9)


def test_ukf_skeleton_scene(skel_native, tmp_path: Path) -> None:
    root, sim = skel_native
    scene = load_scene(root)
    assert scene.skeleton == "coco19" and scene.rig.up[1] == -1
    out = tmp_path / "out"
    tracks = reconstruct(scene, "ukf", out=out)
    mm, matched, total = mpjpe_by_id(tracks, scene.truth)
    assert matched == total == 16 and mm < 0.01
    p = score_tracks(tracks, scene.truth)
    assert p.ap[25] > 0.9999 and p.recall_500 == 1.0
    # the person's bone lengths come out in meta.json, equal to the simulated skeleton's
    meta = json.loads((out / "meta.json").read_text())
    assert meta["frame"]["skeleton"] == "coco19" and meta["frame"]["up"] == [0.0, -1.0, 0.0]
    bones = SKELETONS["coco19"].bones
    true_len = np.linalg.norm(sim.kpt_world[0, bones[:, 0]] - sim.kpt_world[0, bones[:, 1]], axis=1)
    got = meta["estimator"]["bones"]["per_person"]["0"]
    lengths = np.array([v["length"] for v in got.values()])
    np.testing.assert_allclose(lengths, true_len, atol=1e-3)
    with open(out / "keypoints.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["frame", "id", "joint", "x", "y", "z", "sd"] and len(rows) == 1 + 16 * 19
    assert main(["evaluate", str(out), "--truth", str(root)]) == 0


def test_ukf_beats_dlt_with_noise(tmp_path: Path) -> None:
    sim = simulate_skeletons("native", seed=3, frames=12, people=1, cameras=8, noise_px=2.0)
    write_skeleton_scene(sim, tmp_path, "native")
    scene = load_scene(tmp_path)
    u = mpjpe_by_id(reconstruct(scene, "ukf"), scene.truth)[0]
    t = mpjpe_by_id(reconstruct(scene, "triangulation"), scene.truth)[0]
    # seeds 3-5 measured 1.3-1.6 mm (DLT 2.9-3.0 mm): 2 px noise, 8 cameras
    assert u < 2.0
    assert u < 0.6 * t


def test_pose_metrics_hand_worked() -> None:
    """Two frames, two people. Frame 1: pred A 10 mm off person 0, pred B 60 mm off person 1.
    Frame 2: one pred 30 mm off person 0, person 1 missed. 4 truth poses."""
    T = np.zeros((4, 2, 3))
    T[1] += 1000.0
    T[3] += 1000.0
    tf = np.array([1, 1, 2, 2])
    P = np.stack([T[0] + [10, 0, 0], T[1] + [0, 60, 0], T[2] + [0, 0, 30]])
    s = pose_scores(np.array([1, 1, 2]), P, np.array([0.9, 0.8, 0.7]), tf, T)
    # AP@25: only the first prediction is a TP: precision 1 at recall 1/4 -> 0.25
    assert s.ap[25] == pytest.approx(0.25, abs=1e-4)
    # AP@50: TP, FP, TP -> precision envelope 1 at recall .25, 2/3 at recall .5
    assert s.ap[50] == pytest.approx(0.25 * 1 + 0.25 * 2 / 3, abs=1e-4)
    assert s.ap[100] == pytest.approx(0.75, abs=1e-4)
    assert s.mpjpe_mm == pytest.approx((10 + 60 + 30) / 3)
    assert s.recall_500 == pytest.approx(0.75)


def test_skeleton_choice() -> None:
    assert skeleton_for(15).name == "panoptic15"
    assert skeleton_for(17).name == "coco17"
    assert skeleton_for(19).name == "coco19"
    assert len(SKELETONS["panoptic15"].bones) == 14
    with pytest.raises(ValueError, match="no skeleton has 25 joints"):
        skeleton_for(25)


# ----------------------------------------------------------------------------- bad input


def _run(tmp_path, src, capsys, *extra):
    out = tmp_path / "out"
    code = main(["reconstruct", str(src), "--out", str(out), *extra])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1, err
    assert not out.exists()
    return err


def _copy(src: Path, dst: Path) -> Path:
    import shutil

    shutil.copytree(src, dst)
    return dst


def _append(p: Path, row: str) -> int:
    lines = p.read_text().splitlines() + [row]
    p.write_text("\n".join(lines) + "\n")
    return len(lines)


def test_joint_outside_skeleton(tmp_path, skel_native, capsys) -> None:
    root = _copy(skel_native[0], tmp_path / "in")
    line = _append(root / "keypoints.csv", "100,00_00,0,19,10,20")
    err = _run(tmp_path, root, capsys)
    assert "keypoints.csv: line" in err and f"line {line}" in err and "joint index 19" in err


def test_unknown_camera_in_keypoints(tmp_path, skel_native, capsys) -> None:
    root = _copy(skel_native[0], tmp_path / "in")
    line = _append(root / "keypoints.csv", "100,nocam,0,3,10,20")
    err = _run(tmp_path, root, capsys)
    assert f"line {line}" in err and "unknown camera 'nocam'" in err


def test_nan_keypoint(tmp_path, skel_native, capsys) -> None:
    root = _copy(skel_native[0], tmp_path / "in")
    line = _append(root / "keypoints.csv", "100,00_01,0,3,nan,20")
    err = _run(tmp_path, root, capsys)
    assert f"line {line}" in err and "non-finite" in err


def test_calibration_without_hd_cameras(tmp_path, capsys) -> None:
    sim = simulate_skeletons("panoptic", seed=1, frames=2, people=1, cameras=3)
    root = tmp_path / "in"
    write_skeleton_scene(sim, root, "panoptic")
    p = root / "calibration_sim.json"
    doc = json.loads(p.read_text())
    doc["cameras"] = [c for c in doc["cameras"] if c["type"] != "hd"]
    p.write_text(json.dumps(doc))
    err = _run(tmp_path, root, capsys)
    assert "calibration_sim.json" in err and "no HD cameras" in err


def test_truncated_body_file(tmp_path, capsys) -> None:
    sim = simulate_skeletons("panoptic", seed=1, frames=2, people=1, cameras=3)
    root = tmp_path / "in"
    write_skeleton_scene(sim, root, "panoptic")
    p = sorted((root / "hdPose3d_stage1_coco19").glob("*.json"))[1]
    p.write_text(p.read_text()[:-40])
    err = _run(tmp_path, root, capsys)
    assert p.name in err and "truncated" in err


def test_unknown_panoptic_camera(tmp_path, capsys) -> None:
    sim = simulate_skeletons("panoptic", seed=1, frames=2, people=1, cameras=3)
    root = tmp_path / "in"
    write_skeleton_scene(sim, root, "panoptic")
    err = _run(tmp_path, root, capsys, "--cameras", "00_00,00_77")
    assert "00_77" in err


def test_object_seen_by_one_camera_only(tmp_path, skel_native, capsys) -> None:
    """Keypoints of one view give no 3D position: the object is left out, with a warning."""
    root = _copy(skel_native[0], tmp_path / "in")
    _append(root / "keypoints.csv", "100,00_01,42,3,900,500")
    out = tmp_path / "out"
    assert main(["reconstruct", str(root), "--out", str(out), "--estimator", "triangulation"]) == 0
    err = capsys.readouterr().err
    assert err.count("warning: ") == 1 and "1 objects with keypoints only" in err and "42" in err
    assert "42" not in {r.split(",")[1] for r in (out / "tracks.csv").read_text().splitlines()}


def test_objects_that_two_views_never_see_together(tmp_path, skel_native, capsys) -> None:
    """Two cameras, but never in the same frame: no 3D position, an error naming the object."""
    root = _copy(skel_native[0], tmp_path / "in")
    line = _append(root / "keypoints.csv", "100,00_01,42,3,900,500")
    _append(root / "keypoints.csv", "101,00_02,42,3,900,500")
    err = _run(tmp_path, root, capsys)
    assert f"line {line}" in err and "id 42 is never seen by two cameras" in err


def test_ellipsoid_around_ignores_joints_known_to_a_metre_only() -> None:
    from gt3dkit.fusion.preparation.prepare import ellipsoid_around

    kpt = np.zeros((2, 4, 3))
    kpt[:, :, 2] = [0.0, 0.5, 1.0, 1.7]  # a standing person, z up
    kpt[:, 3] = [0.0, 0.0, -3.0]  # one joint extrapolated under the floor
    sd = np.array([[0.002, 0.002, 0.002, 1.1], [1.0, 1.2, 0.9, 1.1]])
    centre, semi, csd = ellipsoid_around(kpt, sd, np.eye(3))
    np.testing.assert_allclose(centre[0], [0, 0, 0.5])  # the three known joints only
    np.testing.assert_allclose(semi[0, 2], 0.5 + 0.1)
    assert csd[0, 0] == pytest.approx(0.002)
    np.testing.assert_allclose(centre[1], [0, 0, -1.0])  # none known: every joint
