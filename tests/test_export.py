"""`gt3d export`: C3D, TRC, JSON and Rerun files read back with readers gt3dkit did not write
(the `c3d` package, pandas, the `rerun` CLI)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.io.writers import read_keypoints_csv, read_tracks_csv
from gt3dkit.sim import Errors, simulate, simulate_skeletons, write_scene, write_skeleton_scene
from gt3dkit.skeletons import SKELETONS

GT3D = [sys.executable, "-m", "gt3dkit.cli"]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*GT3D, *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def skel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = Path(tmp_path_factory.mktemp("export"))
    sk = simulate_skeletons("native", seed=3, frames=10, people=2, cameras=5, noise_px=1.0)
    write_skeleton_scene(sk, root / "in", "native")
    r = _run("reconstruct", str(root / "in"), "--out", str(root / "out"))
    assert r.returncode == 0, r.stderr
    return root / "out"


def _truth_markers(out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(frames, ids, (M, J, 3) keypoints) from keypoints.csv."""
    tr = read_tracks_csv(out / "tracks.csv")
    tr = read_keypoints_csv(out / "keypoints.csv", tr, len(SKELETONS["coco19"].joints))
    return tr.frame, tr.track_id, tr.kpt_world


def test_c3d_reads_back_with_the_c3d_package(skel: Path) -> None:
    import c3d

    r = _run("export", str(skel), "--format", "c3d")
    assert r.returncode == 0, r.stderr
    path = skel / "export_c3d" / "tracks.c3d"
    frames, ids, X = _truth_markers(skel)
    meta = json.loads((skel / "meta.json").read_text())
    with open(path, "rb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no analog data"
        rd = c3d.Reader(f)
        labels = [s.strip() for s in rd.point_labels]
        assert rd.header.frame_rate == pytest.approx(meta["input"]["fps"])
        assert rd.get("POINT:UNITS").string_value.strip() == "mm"
        data = [p.copy() for _, p, _ in rd.read_frames()]
    joints = SKELETONS["coco19"].joints
    assert labels == [f"id{i}_{j}" for i in np.unique(ids) for j in joints]
    first = int(np.unique(frames)[0])
    checked = 0
    for k in range(len(frames)):
        n = int(frames[k]) - first
        for j, name in enumerate(joints):
            m = labels.index(f"id{ids[k]}_{name}")
            if np.isfinite(X[k, j]).all():
                assert data[n][m, 3] >= 0  # valid
                assert np.abs(data[n][m, :3] - 1000 * X[k, j]).max() < 0.1  # mm
                checked += 1
    assert checked > 100


def test_trc_reads_back_with_pandas(skel: Path) -> None:
    import pandas as pd

    r = _run("export", str(skel), "--format", "trc", "--to", str(skel.parent / "trc"))
    assert r.returncode == 0, r.stderr
    frames, ids, X = _truth_markers(skel)
    up = np.array(json.loads((skel / "meta.json").read_text())["frame"]["up"])
    joints = SKELETONS["coco19"].joints
    for i in np.unique(ids):
        path = skel.parent / "trc" / f"id{i}.trc"
        head = path.read_text().splitlines()
        assert head[2].split("\t")[4] == "m"
        names = [x for x in head[3].split("\t")[2:] if x]
        assert names == list(joints)
        df = pd.read_csv(path, sep="\t", skiprows=5, header=None)
        Y = df.iloc[:, 2:2 + 3 * len(joints)].to_numpy(float).reshape(len(df), len(joints), 3)
        m = np.flatnonzero(ids == i)
        n = np.searchsorted(np.unique(frames), frames[m])
        Xi = X[m]
        both = np.isfinite(Xi).all(-1) & np.isfinite(Y[n]).all(-1)
        assert both.sum() > 50
        # distances between markers are kept (whatever the axis convention) ...
        a, b = np.nonzero(both)
        for r_ in np.unique(a)[:5]:
            js = b[a == r_]
            d_in = np.linalg.norm(Xi[r_, js][:, None] - Xi[r_, js][None], axis=-1)
            d_out = np.linalg.norm(Y[n[r_], js][:, None] - Y[n[r_], js][None], axis=-1)
            assert np.abs(d_in - d_out).max() < 1e-4
        # ... and OpenSim's y is the world's up
        assert np.abs(Y[n][both][:, 1] - Xi[both] @ up).max() < 1e-4


def test_json_and_rerun(skel: Path) -> None:
    assert _run("export", str(skel), "--format", "json").returncode == 0
    doc = json.loads((skel / "export_json" / "tracks.json").read_text())
    frames, ids, X = _truth_markers(skel)
    assert doc["header"]["units"] == "m" and doc["header"]["joints"] == list(SKELETONS["coco19"].joints)
    recs = {(f["frame"], o["id"]): o for f in doc["frames"] for o in f["objects"]}
    assert len(recs) == len(frames)
    k = len(frames) // 2
    kp = recs[(int(frames[k]), int(ids[k]))]["keypoints"]
    for j in range(X.shape[1]):
        if np.isfinite(X[k, j]).all():
            assert np.allclose(kp[j], X[k, j], atol=1e-6)
    r = _run("export", str(skel), "--format", "rerun")
    assert r.returncode == 0, r.stderr
    rrd = skel / "export_rerun" / "tracks.rrd"
    rerun = Path(sys.executable).parent / "rerun"
    v = subprocess.run([str(rerun), "rrd", "verify", str(rrd)], capture_output=True, text=True, timeout=120)
    assert v.returncode == 0, v.stderr
    p = subprocess.run([str(rerun), "rrd", "print", str(rrd)], capture_output=True, text=True, timeout=120)
    for entity in ("/world/ellipsoids", "/world/cameras/00_00/image/keypoints", "/world/skeletons/id0"):
        assert entity in p.stdout


def test_box_output_as_c3d_markers_and_errors(tmp_path: Path) -> None:
    import c3d

    write_scene(simulate("native", seed=2, frames=6, people=3, errors=Errors(dropped=0.0)), tmp_path / "in",
                "native")
    assert _run("reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out")).returncode == 0
    assert _run("export", str(tmp_path / "out"), "--format", "c3d").returncode == 0
    with open(tmp_path / "out" / "export_c3d" / "tracks.c3d", "rb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        labels = [s.strip() for s in c3d.Reader(f).point_labels]
    tr = read_tracks_csv(tmp_path / "out" / "tracks.csv")
    assert labels == [f"id{i}" for i in np.unique(tr.track_id)]
    r = _run("export", str(tmp_path / "in"), "--format", "c3d")
    assert r.returncode == 2 and r.stderr.startswith("error: ") and "tracks.csv" in r.stderr
    before = sorted(p.name for p in (tmp_path / "in").iterdir())
    r = _run("export", str(tmp_path / "out"), "--format", "c3d", "--to", str(tmp_path / "in"))
    assert r.returncode == 2 and r.stderr.startswith("error: --to:") and "input folder" in r.stderr, r.stderr
    assert sorted(p.name for p in (tmp_path / "in").iterdir()) == before
    r = _run("export", str(tmp_path / "out"), "--format", "c3d", "--to", str(tmp_path / "out"))
    assert r.returncode == 2, r.stderr
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("x")
    r = _run("export", str(tmp_path / "out"), "--format", "c3d", "--to", str(tmp_path / "mine"))
    assert r.returncode == 2 and "gt3dkit did not write" in r.stderr
    r = _run("export", str(tmp_path / "out"), "--format", "fbx")
    assert r.returncode == 2 and "--format" in r.stderr


def test_a_users_joint_map(skel: Path, tmp_path: Path) -> None:
    """``--joint-map``: the export's joints are the user's affine combinations of the run's
    (weights summing to 1), their sds ``sqrt(sum w^2 sd^2)``; the run's keypoints.csv keeps the
    detector's joints; export.json names the map and its sha256. Every mistake in the map is one
    error line naming its entry, nothing written."""
    from gt3dkit.io.results import read_result

    res = read_result(skel)
    joints = res.joints
    table = {"hip_centre": {"l_hip": 0.5, "r_hip": 0.5}, "head_top": {"nose": 1.5, "neck": -0.5},
             "l_ankle": {"l_ankle": 1}}
    good = tmp_path / "map.json"
    good.write_text(json.dumps({"name": "mine", "from": res.meta["frame"]["skeleton"], "joints": table}))
    before = (skel / "keypoints.csv").read_bytes()
    r = _run("export", str(skel), "--format", "json", "--to", str(tmp_path / "m"), "--joint-map",
             str(good))
    assert r.returncode == 0, r.stderr
    assert (skel / "keypoints.csv").read_bytes() == before
    doc = json.loads((tmp_path / "m" / "tracks.json").read_text())
    assert doc["header"]["joints"] == list(table) and doc["header"]["skeleton"] == "mine"
    info = json.loads((tmp_path / "m" / "export.json").read_text())
    assert info["joint_map"]["sha256"] == hashlib.sha256(good.read_bytes()).hexdigest()
    tr = res.tracks
    W = np.zeros((len(table), len(joints)))
    for k, combo in enumerate(table.values()):
        for j, w in combo.items():
            W[k, joints.index(j)] = w
    checked = 0
    for fr in doc["frames"]:
        for o in fr["objects"]:
            k = int(np.flatnonzero((tr.frame == fr["frame"]) & (tr.track_id == o["id"]))[0])
            for q, (x, sd) in enumerate(zip(o["keypoints"], o["keypoint_sd"], strict=True)):
                if x is None:
                    continue
                np.testing.assert_allclose(x, W[q] @ tr.kpt_world[k], atol=2e-6)
                np.testing.assert_allclose(sd, np.sqrt(W[q] ** 2 @ tr.kpt_sd[k] ** 2), atol=2e-6)
                checked += 1
    assert checked > 50
    for bad, needle in (({"hip_centre": {"l_hip": 0.5, "r_hip": 0.4}},
                         "joints.hip_centre: the weights sum to 0.9"),
                        ({"x": {"tail": 1}}, "joints.x.tail: the run has no joint 'tail'"),
                        ({"x": {"nose": "1"}}, "joints.x.nose: the weight must be a finite number")):
        p = tmp_path / "bad.json"
        p.write_text(json.dumps({"name": "mine", "from": res.meta["frame"]["skeleton"], "joints": bad}))
        r = _run("export", str(skel), "--format", "json", "--to", str(tmp_path / "b"), "--joint-map",
                 str(p))
        assert r.returncode == 2 and needle in r.stderr and r.stderr.count("\n") == 1, r.stderr
        assert not (tmp_path / "b").exists()
    r = _run("export", str(skel), "--format", "rerun", "--to", str(tmp_path / "b"), "--joint-map",
             str(good))
    assert r.returncode == 2 and "--joint-map: rerun draws the run" in r.stderr
    assert not (tmp_path / "b").exists()
    p.write_text(json.dumps({"name": "mine", "from": "body25", "joints": table}))
    r = _run("export", str(skel), "--format", "json", "--to", str(tmp_path / "b"), "--joint-map",
             str(p))
    assert r.returncode == 2 and "from: the map is from 'body25'" in r.stderr
