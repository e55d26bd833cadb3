"""MOTChallenge files per camera in, cross-view association of per-camera ids."""

from __future__ import annotations

import csv
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_scene
from gt3dkit.errors import InputError
from gt3dkit.sim import Errors, simulate, write_scene

GT3D = [sys.executable, "-m", "gt3dkit.cli"]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory: pytest.TempPathFactory):
    root = Path(tmp_path_factory.mktemp("mot"))
    sim = simulate("wildtrack", seed=5, frames=20, people=10, noise_px=1.0, motion="walk",
                   errors=Errors(dropped=0.05, hide_covered=0.5, single_view=0.2))
    write_scene(sim, root / "mot", "mot", id_seed=7)
    write_scene(sim, root / "global", "wildtrack")
    return sim, root


def _clusters_are_people(sim, scene) -> None:
    """Every global id holds the boxes of exactly one true person (boxes matched to truth by
    frame and box equality) and every person is one global id."""
    obs = scene.obs
    truth_of = {}
    for m in range(len(sim.truth_frame)):
        for c in range(len(scene.rig.cameras)):
            b = sim.boxes[m, c]
            if np.isfinite(b).all():
                truth_of[(int(sim.truth_frame[m]), c, *np.round(b, 3))] = int(sim.truth_id[m])
    pairs = {(int(g), truth_of[(int(f), int(c), *np.round(b, 3))])
             for f, c, g, b in zip(obs.frame, obs.cam, obs.track_id, obs.box_xyxy_px, strict=True)}
    gids = [g for g, _ in pairs]
    tids = [t for _, t in pairs]
    assert len(set(gids)) == len(gids), "a global id holds two people"
    assert len(set(tids)) == len(tids), "a person is split over two global ids"


def test_per_camera_ids_are_associated(scenes) -> None:
    sim, root = scenes
    sc = load_scene(root / "mot")
    assert sc.layout == "mot" and sc.association is not None
    _clusters_are_people(sim, sc)
    lone = [r for r in sc.association.rows if "single view" in r[7]]
    assert lone  # the bystanders (one camera each) stay their own people
    assert all(np.isfinite(r[4]) and 0 <= r[4] <= 1 for r in sc.association.rows if not r[7])


def test_reconstruction_equals_global_ids(scenes, tmp_path: Path) -> None:
    from gt3dkit.api import reconstruct
    from gt3dkit.eval.metrics import box_errors, relabel_to_truth

    sim, root = scenes
    g, m = load_scene(root / "global"), load_scene(root / "mot")
    tg = reconstruct(g, "triangulation")
    tm = relabel_to_truth(reconstruct(m, "triangulation", out=tmp_path / "o"), m.truth, m.rig.up)
    eg, em = box_errors(tg, g.truth, g.rig.up), box_errors(tm, m.truth, m.rig.up)
    assert em.rows_matched == eg.rows_matched
    assert em.centre_mean_m == pytest.approx(eg.centre_mean_m, rel=1e-6)
    assert (tmp_path / "o" / "association.csv").is_file()


def test_overrides_and_their_errors(scenes, tmp_path: Path) -> None:
    sim, root = scenes
    sc = load_scene(root / "mot")
    rows = sc.association.rows
    # split one camera's track off into a person of its own
    cam, local, gid = next((r[0], r[1], r[3]) for r in rows if not r[7])
    over = tmp_path / "assoc.csv"
    with open(over, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["camera", "local_id", "frame", "global_id"])
        w.writerow([cam, local, "", 999])
    sc2 = load_scene(root / "mot", association=over)
    mine = sc2.association.mapping()
    assert mine[(cam, local, None)] == 999
    assert sum(1 for k, v in mine.items() if v == gid) == sum(1 for r in rows if r[3] == gid) - 1
    # two tracks of one camera made one person while both are in view: named
    frames: dict[int, set[int]] = {}
    for line in (root / "mot" / "mot" / f"{cam}.txt").read_text().splitlines():
        f_, i_ = line.split(",")[:2]
        frames.setdefault(int(i_), set()).add(int(f_))
    other = next(i for i, fs in frames.items() if i != local and fs & frames[local])
    with open(over, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["camera", "local_id", "frame", "global_id"])
        w.writerow([cam, local, "", 500])
        w.writerow([cam, other, "", 500])
    with pytest.raises(InputError, match="are both global id 500"):
        load_scene(root / "mot", association=over)
    with open(over, "w", newline="") as f:
        f.write("camera,local_id,frame,global_id\nnocam,1,,2\n")
    with pytest.raises(InputError, match="unknown camera"):
        load_scene(root / "mot", association=over)


def test_camera_names_paired_by_order_and_bad_rows(scenes, tmp_path: Path) -> None:
    import shutil

    sim, root = scenes
    d = tmp_path / "renamed"
    shutil.copytree(root / "mot", d)
    for k, p in enumerate(sorted((d / "mot").glob("*.txt"))):
        p.rename(d / "mot" / f"cam_{k + 1}.txt")
    sc = load_scene(d)
    assert any("paired by sorted order" in w and "cam_1 -> CVLab1" in w for w in sc.warnings)
    p = d / "mot" / "cam_2.txt"
    lines = p.read_text().splitlines()
    for bad, needle in ((lines[0].split(",")[0] + ",3,1,2", "fields"),
                        ("5,-1,10,10,20,40,1,-1,-1,-1", "without a track id"),
                        ("5,3,10,10,0,40,1,-1,-1,-1", "degenerate")):
        p.write_text("\n".join([*lines, bad]) + "\n")
        with pytest.raises(InputError, match=needle) as e:
            load_scene(d)
        assert "cam_2.txt: line" in str(e.value)
    p.write_text("\n".join([*lines, "5,3,10,10,20,40,0,-1,-1,-1"]) + "\n")
    assert any("conf 0" in w for w in load_scene(d).warnings)


def test_associate_command(scenes, tmp_path: Path) -> None:
    _, root = scenes
    r = subprocess.run([*GT3D, "associate", str(root / "mot"), "--out", str(tmp_path / "a")],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "per-camera tracks ->" in r.stdout
    head = (tmp_path / "a" / "association.csv").read_text().splitlines()[0]
    assert head == "camera,local_id,frame,global_id,confidence,frames,median_m,note"
    r = subprocess.run([*GT3D, "associate", str(root / "global"), "--out", str(tmp_path / "b")],
                       capture_output=True, text=True)
    assert r.returncode == 2 and "already global" in r.stderr


def _trial(tmp_path: Path, skeleton: str = "body25", seed: int = 1) -> Path:
    import dataclasses

    from gt3dkit.sim import simulate_skeletons, to_z_up, write_openpose

    sk = to_z_up(simulate_skeletons("native", seed=seed, frames=12, people=2, cameras=4, noise_px=1.0,
                                    skeleton=skeleton, confidences=True))
    uv = sk.uv.copy()
    uv[np.ix_(sk.truth_id == 1, [2, 3])] = np.nan  # a bystander in two views
    write_openpose(dataclasses.replace(sk, uv=uv), tmp_path / "trial", seed=seed)
    return tmp_path / "trial"


def test_openpose_trial(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from gt3dkit.io.datasets import openpose
    from gt3dkit.skeletons import SKELETONS

    root = _trial(tmp_path)
    sc = load_scene(root)
    monkeypatch.setattr(openpose, "CHUNK_FILES", 2)  # each camera's files gathered in many blocks
    small = load_scene(root)
    for k in ("frame", "cam", "track_id", "kpt_uv_px", "kpt_conf"):
        np.testing.assert_array_equal(getattr(small.obs, k), getattr(sc.obs, k))
    assert small.obs.origin == sc.obs.origin and sc.obs.origin[0].endswith("keypoints.json: people[0]")
    assert sc.layout == "openpose" and sc.skeleton == "body25" and sc.fps == 30.0 and not sc.fps_assumed
    assert sc.obs.n_joints == 25 and sc.obs.kpt_conf is not None  # every joint, confidences kept
    assert any("paired by sorted order" in w for w in sc.warnings)
    assert len(np.unique(sc.obs.track_id)) == 2
    # each person's detections, in every frame and view, come from one true person: the
    # person seen in all four views is the participant
    per = {int(i): len(np.unique(sc.obs.cam[sc.obs.track_id == i])) for i in np.unique(sc.obs.track_id)}
    assert sorted(per.values()) == [2, 4]
    # body25b is told from body25 by where joint 1 lies
    assert load_scene(_trial(tmp_path / "b", "body25b")).skeleton == "body25b"
    # exports use the detector's names
    r = subprocess.run([*GT3D, "reconstruct", str(root), "--out", str(tmp_path / "o")], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([*GT3D, "export", str(tmp_path / "o"), "--format", "trc"], capture_output=True,
                       text=True)
    assert r.returncode == 0, r.stderr
    head = (tmp_path / "o" / "export_trc" / "id0.trc").read_text().splitlines()[3].split("\t")
    assert [x for x in head[2:] if x] == list(SKELETONS["body25"].marker_names)
    assert "RBigToe" in head and "LHeel" in head


def test_openpose_bad_files(tmp_path: Path) -> None:
    import json

    root = _trial(tmp_path)
    f = sorted((root / "pose" / "cam2_json").glob("*.json"))[3]
    good = f.read_text()
    doc = json.loads(good)
    for bad, needle in (({"people": 3}, "people"),
                        ({"people": [{"pose_keypoints_2d": [1, 2, 0.5] * 24}]}, "24 joints"),
                        ({"people": [{"pose_keypoints_2d": [1, 2, -0.5] * 25}]}, "negative confidence"),
                        ({"people": [{"pose_keypoints_2d": [1, 2, True] * 25}]}, "numbers"),
                        ({"people": [{"pose_keypoints_2d": ["a"] * 75}]}, "numbers")):
        f.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=needle) as e:
            load_scene(root)
        assert f.name in str(e.value)
    f.write_text(good[: len(good) // 2])
    with pytest.raises(InputError) as e:
        load_scene(root)
    assert f.name in str(e.value)
    far = json.loads(good)
    far["people"][-1]["pose_keypoints_2d"][3 * 4 + 1] = -1e9  # joint 4's y, detected
    far["people"][-1]["pose_keypoints_2d"][3 * 4 + 2] = 0.5
    f.write_text(json.dumps(far))
    with pytest.raises(InputError, match="far outside") as e:
        load_scene(root)
    assert e.value.where.endswith(f"{f.name}: people[{len(far['people']) - 1}]"), str(e.value)
    assert doc["people"]


def test_cvat_and_coco_tasks(tmp_path: Path) -> None:
    """CVAT for video XML (boxes, ids per task) and COCO keypoints (with and without track ids)
    read, associated and reconstructed like the same scene with global ids."""
    from gt3dkit.api import reconstruct
    from gt3dkit.eval.metrics import relabel_to_truth
    from gt3dkit.sim import simulate_skeletons, write_coco, write_skeleton_scene

    sim = simulate("wildtrack", seed=3, frames=10, people=6, noise_px=1.0, errors=Errors(dropped=0.0,
                                                                                         hide_covered=0.5))
    write_scene(sim, tmp_path / "cvat", "cvat", id_seed=2)
    sc = load_scene(tmp_path / "cvat")
    assert sc.layout == "cvat" and len({r[3] for r in sc.association.rows}) == 6
    _clusters_are_people(sim, sc)
    sk = simulate_skeletons("native", seed=4, frames=8, people=2, cameras=5, noise_px=1.0)
    write_skeleton_scene(sk, tmp_path / "native", "native")
    def err(tr, truth) -> float:
        from gt3dkit.eval.metrics import match_rows

        it, ig = match_rows(tr, truth)
        return float(np.nanmedian(np.linalg.norm(tr.kpt_world[it] - truth.kpt_world[ig], axis=-1)))

    nat = load_scene(tmp_path / "native")
    e_ref = err(reconstruct(nat, "triangulation"), nat.truth)
    assert np.isfinite(e_ref)
    for ids in (True, False):
        write_coco(sk, tmp_path / f"coco{ids}", track_ids=ids, seed=1)
        c = load_scene(tmp_path / f"coco{ids}")
        assert c.layout == "coco" and c.skeleton == "coco19"
        assert len(np.unique(c.obs.track_id)) == 2
        tr = relabel_to_truth(reconstruct(c, "triangulation"), c.truth, c.rig.up)
        assert err(tr, c.truth) == pytest.approx(e_ref, rel=0.05, abs=1e-4)
    # a broken CVAT file: one line naming the file and the line
    p = next((tmp_path / "cvat" / "cvat").glob("*.xml"))
    p.write_text(p.read_text()[:300])
    with pytest.raises(InputError, match=r"line \d+.*malformed XML"):
        load_scene(tmp_path / "cvat")


def test_cvat_skeleton_tracks_parse(tmp_path: Path) -> None:
    """CVAT for video 1.1 skeleton tracks: joints by label, outside shapes and points skipped."""
    from gt3dkit.io.datasets.tasks import _read_cvat

    p = tmp_path / "cam.xml"
    p.write_text("""<?xml version="1.0" encoding="utf-8"?>
<annotations><version>1.1</version>
  <track id="4" label="person" source="manual">
    <skeleton frame="7" keyframe="1" outside="0" occluded="0">
      <points label="left_ankle" outside="0" occluded="0" points="100.5,200.25"/>
      <points label="nose" outside="1" occluded="0" points="1,2"/>
    </skeleton>
    <skeleton frame="8" keyframe="0" outside="1"><points label="left_ankle" points="1,1"/></skeleton>
    <box frame="9" outside="0" occluded="0" xtl="1" ytl="2" xbr="30" ybr="80" z_order="0"/>
  </track>
</annotations>""")
    items = _read_cvat(p, p.read_bytes(), [])
    assert [(f, t, box, pts, drawn) for f, t, _, box, pts, _, drawn in items] == [
        (7, 4, None, {"left_ankle": (100.5, 200.25, 1.0)}, False), (9, 4, [1.0, 2.0, 30.0, 80.0], {}, False)]
    p.write_text(p.read_text().replace('points="100.5,200.25"', 'points="100.5"'))
    with pytest.raises(InputError, match="track '4' frame '7' joint 'left_ankle'"):
        _read_cvat(p, p.read_bytes(), [])


def test_pair_costs_are_opencvs_two_view_triangulation() -> None:
    """The association's batched pair cost is, per pair of detections, the median over the joints
    both saw of the RMS reprojection error (px) of OpenCV's two-view DLT (``cv2.triangulatePoints``;
    inf behind a camera); inf with too few common joints; pairs of one frame and different cameras,
    in row order. The detections are of different people: many pairs cannot be one."""
    import cv2

    from gt3dkit.fusion.preparation.detections import frame_pairs, pair_costs

    rng = np.random.default_rng(4)
    C, J, N = 3, 9, 12
    R = np.stack([cv2.Rodrigues(rng.normal(scale=0.3, size=3))[0] for _ in range(C)])
    t = np.c_[rng.normal(scale=0.5, size=(C, 2)), rng.uniform(4, 6, C)]
    f = np.array([900.0, 1100.0, 1000.0])
    X = rng.normal(scale=0.6, size=(N, J, 3))
    cam = np.arange(N) % C
    Xc = np.einsum("nij,nkj->nki", R[cam], X) + t[cam][:, None]
    xy = Xc[..., :2] / Xc[..., 2:] + rng.normal(scale=3e-3, size=(N, J, 2))
    xy[rng.random((N, J)) < 0.2] = np.nan
    xy[5, :6] = np.nan  # too few joints for any pair
    frame = np.repeat(np.arange(N // 4), 4)
    a, b = frame_pairs(frame, cam)
    want = [(i, k) for i in range(N) for k in range(i + 1, N) if frame[i] == frame[k] and cam[i] != cam[k]]
    assert list(zip(a.tolist(), b.tolist(), strict=True)) == want
    Pw = np.concatenate([R, t[:, :, None]], axis=2)
    got = pair_costs(xy, a, b, cam, Pw, f, 4)
    for k, (i, j) in enumerate(want):
        ok = np.isfinite(xy[i]).all(1) & np.isfinite(xy[j]).all(1)
        if ok.sum() < 4:
            assert got[k] == np.inf
            continue
        Xh = cv2.triangulatePoints(Pw[cam[i]], Pw[cam[j]], xy[i, ok].T, xy[j, ok].T)
        P3 = (Xh[:3] / Xh[3]).T
        e2 = []
        for v, fv in ((cam[i], f[cam[i]]), (cam[j], f[cam[j]])):
            q = P3 @ R[v].T + t[v]
            d2 = np.sum((q[:, :2] / q[:, 2:] - xy[i if v == cam[i] else j, ok]) ** 2, axis=1) * fv**2
            e2.append(np.where(q[:, 2] > 0, d2, np.inf))  # behind a camera: no reprojection
        np.testing.assert_allclose(got[k], np.median(np.sqrt(np.mean(e2, axis=0))), rtol=1e-6)
    assert np.isinf(got).any() and np.isfinite(got).sum() > 5


def test_openpose_confidences_above_one_are_read_as_one_with_a_warning(tmp_path: Path) -> None:
    """OpenPose's confidences are heatmap peaks (real files hold up to ~1.04): a folder with some
    runs, each such value read as 1, and one warning line says how many and the largest."""
    import json

    root = _trial(tmp_path)
    files = sorted((root / "pose" / "cam2_json").glob("*.json"))
    doc = json.loads(files[1].read_text())
    doc["people"][0]["pose_keypoints_2d"][2] = 1.037
    files[1].write_text(json.dumps(doc))
    scene = load_scene(root)
    said = [w for w in scene.warnings if "confidence above 1" in w]
    assert len(said) == 1 and "1.037" in said[0] and said[0].startswith("1 detection")
    assert np.nanmax(scene.obs.kpt_conf) == 1.0


def test_openpose_files_without_people_are_said(tmp_path: Path) -> None:
    """A frame where the detector found no one in a camera (``"people": []``, as OpenPose writes
    it) is valid: read, and counted in one warning line."""
    import json

    root = _trial(tmp_path)
    assert not any("list no person" in w for w in load_scene(root).warnings)
    pages = sorted((root / "pose" / "cam2_json").glob("*.json"))[2:4]
    for page in pages:
        doc = json.loads(page.read_text())
        doc["people"] = []
        page.write_text(json.dumps(doc))
    n = sum(1 for _ in (root / "pose").glob("*/*.json"))
    said = [w for w in load_scene(root).warnings if "list no person" in w]
    assert said == [f"2 of {n} files list no person (frames where the detector found no one in that camera)"]


def test_an_openpose_trial_read_with_a_skeleton_file(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """``--skeleton FILE`` on OpenPose JSON: a copy of BODY_25 under another name gives the built-in's
    estimate and is carried in meta.json; a skeleton of another joint count is one line, exit 2,
    nothing written (it was a KeyError)."""
    from gt3dkit.api import reconstruct
    from gt3dkit.cli import main
    from gt3dkit.io.skeletonfile import write_skeleton
    from gt3dkit.skeletons import SKELETONS

    root = _trial(tmp_path)
    mine = dataclasses.replace(SKELETONS["body25"], name="my_body")
    write_skeleton(mine, tmp_path / "my_body.toml")
    built_in = reconstruct(load_scene(root), "ukf")
    sc = load_scene(root, skeleton=str(tmp_path / "my_body.toml"))
    assert sc.skeleton == "my_body" and sc.skeleton_doc is not None
    from_file = reconstruct(sc, "ukf", out=tmp_path / "out")
    np.testing.assert_array_equal(from_file.kpt_world, built_in.kpt_world)
    assert '"skeleton_doc"' in (tmp_path / "out" / "meta.json").read_text()
    code = main(["reconstruct", str(root), "--skeleton", "mouse", "--out", str(tmp_path / "bad")])
    err = capsys.readouterr().err
    assert code == 2 and err == "error: --skeleton: mouse has 11 joints, the files 25\n", err
    assert not (tmp_path / "bad").exists()
