"""gt3dkit.refine.people (``gt3d calib people``): the cameras' poses from the people in a scene with
no calibration of its poses and no identities, held to the simulator's cameras; its bad input."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_detections, load_run
from gt3dkit.calib.formats import read_calibration
from gt3dkit.errors import InputError
from gt3dkit.refine.common import transform_rig, umeyama
from gt3dkit.refine.people import PeopleConfig, against_given, calibrate_people
from gt3dkit.rig import Rig
from gt3dkit.sim import simulate, simulate_skeletons, write_scene, write_skeleton_scene
from gt3dkit.skeletons import Skeleton
from gt3dkit.viz.report import _people_rig


def _gt3d(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "gt3dkit.cli", *args], capture_output=True, text=True)


@pytest.fixture(scope="module")
def people_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Three people walking before six cameras, 40 frames, 1.5 px noise, written with ids that the
    calibration does not use."""
    root = tmp_path_factory.mktemp("people")
    write_skeleton_scene(simulate_skeletons("native", seed=2, frames=40, people=3, noise_px=1.5, cameras=6),
                         root, "native")
    return root


def _errors(ours: Rig, truth: Rig) -> tuple[np.ndarray, np.ndarray, float]:
    """Centre (m) and rotation (deg) errors after the similarity that maps the centres, and its scale."""
    E = np.array([c.center_world for c in ours.cameras])
    T = np.array([truth.cameras[truth.index(n)].center_world for n in ours.names])
    s, R, t = umeyama(E, T)
    centre = np.linalg.norm((s * (R @ E.T)).T + t - T, axis=1)
    ref = [truth.cameras[truth.index(c.name)].R for c in ours.cameras]
    rot = [np.degrees(np.arccos(np.clip((np.trace((c.R @ R.T).T @ Rt) - 1) / 2, -1, 1)))
           for c, Rt in zip(ours.cameras, ref, strict=True)]
    return centre, np.array(rot), s


def test_mirror_index() -> None:
    sk = Skeleton("five", ("nose", "l_eye", "r_eye", "l_hip", "r_hip"), ())
    np.testing.assert_array_equal(sk.mirror(), [0, 2, 1, 4, 3])


def test_rig_from_people_recovers_the_cameras(people_dir: Path) -> None:
    scene = load_detections(people_dir)
    res = calibrate_people(scene)
    assert res.rig.names == scene.rig.names
    centre, rot, s = _errors(res.rig, scene.rig)
    assert centre.max() < 0.01, centre  # measured 0.6-1.5 mm over a 5 m rig
    assert rot.max() < 0.1, rot  # measured 0.015-0.044 degrees
    assert abs(s - 1) < 0.08  # typical bone lengths: measured 4.9 % (the simulator's people are small)
    np.testing.assert_allclose(res.rig.up, [0, 0, 1])
    rep = res.report
    assert rep["reprojection_median_px"] < 2.5 and rep["people"] >= 100


def test_height_sets_the_scale(people_dir: Path) -> None:
    scene = load_detections(people_dir)
    a = calibrate_people(scene, PeopleConfig(height_m=1.60))
    b = calibrate_people(scene, PeopleConfig(height_m=1.80))
    span = [np.ptp([c.center_world for c in r.rig.cameras], axis=0).max() for r in (a, b)]
    assert span[1] / span[0] == pytest.approx(1.80 / 1.60, rel=1e-3)
    assert "--height" in a.report["world"]["scale_from"]


def test_cli_writes_the_rig_and_refuses_a_camera_with_no_people(people_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "cal"
    p = _gt3d("calib", "people", str(people_dir), "--out", str(out), "--format", "toml")
    assert p.returncode == 0, p.stderr
    assert len(read_calibration(out / "calibration" / "calibration.toml").cameras) == 6
    assert json.loads((out / "calib_report.json").read_text())["world"]["scale_from"].startswith("typical")
    assert "median" in p.stdout and "ctr sd cm" in p.stdout
    # one camera's detections moved to frames no other camera has: it shares no one
    bad = tmp_path / "bad"
    bad.mkdir()
    for f in people_dir.iterdir():
        (bad / f.name).write_bytes(f.read_bytes())
    with (bad / "keypoints.csv").open(newline="") as fh:
        rows = list(csv.reader(fh))
    head, body = rows[0], rows[1:]
    ci, fi = head.index("camera"), head.index("frame")
    for r in body:
        if r[ci] == "00_03":
            r[fi] = str(int(r[fi]) + 100000)
    with (bad / "keypoints.csv").open("w", newline="") as fh:
        csv.writer(fh).writerows([head, *body])
    out2 = tmp_path / "cal2"
    p = _gt3d("calib", "people", str(bad), "--out", str(out2))
    assert p.returncode == 2, p.stderr
    assert p.stderr.startswith("error: ") and p.stderr.count("\n") == 1
    assert "camera 00_03" in p.stderr and "cannot be placed" in p.stderr
    assert not out2.exists()


def test_boxes_only_input_is_refused(tmp_path: Path) -> None:
    write_scene(simulate("native", seed=1, frames=4, people=2), tmp_path, "native")
    with pytest.raises(InputError, match="no keypoints"):
        calibrate_people(load_detections(tmp_path))


def test_reconstruct_with_the_rig_from_the_people(people_dir: Path, tmp_path: Path) -> None:
    """``gt3d reconstruct --calib people``: the poses found first, the run in the people's world, the
    rig in meta.json (where the report's re-reading takes it from); other commands refuse it."""
    out = tmp_path / "run"
    p = _gt3d("reconstruct", str(people_dir), "--calib", "people", "--out", str(out))
    assert p.returncode == 0, p.stderr
    assert "cameras placed from the people: 6" in p.stdout
    # the truth (in the input's calibration's frame) is scored with the tracks moved into it
    assert "(scored in the input calibration's frame" in p.stdout
    row = next(ln for ln in p.stdout.splitlines() if ln.startswith("ukf, all joints"))
    assert float(row.split()[-1]) < 2.0, row  # MPJPE by id: measured 1.25 mm (1.11 with the true rig)
    meta = json.loads((out / "meta.json").read_text())
    people = meta["calibration_from_people"]
    assert len(people["rig"]["cameras"]) == 6 and people["reprojection_median_px"] < 2.5
    assert meta["input"]["load"]["calib"] is None
    run = load_run(out, "the test reads it back")
    assert any("from the people" in n for n in run.notes)
    np.testing.assert_allclose(run.scene.rig.t, [c["t"] for c in people["rig"]["cameras"]])
    p = _gt3d("compare", str(people_dir), "--calib", "people", "--out", str(tmp_path / "cmp"))
    assert p.returncode == 2 and "people applies to gt3d reconstruct" in p.stderr


def test_rig_beside_the_given_one(people_dir: Path) -> None:
    """The found rig beside the input's: a copy of the input moved by a similarity is 0 cm and 0
    degrees from it; the report's section lists the cameras; intrinsics-only rigs are not compared."""
    given = load_detections(people_dir).rig
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    moved = transform_rig(given, 0.5, R, np.array([1.0, 2, 3]))
    got = against_given(moved, given)
    assert got is not None and got["scale_given_over_found"] == pytest.approx(2.0)
    assert max(c["centre_m"] for c in got["cameras"].values()) < 1e-9
    assert max(c["rotation_deg"] for c in got["cameras"].values()) < 1e-5
    flat = transform_rig(given, 1e-6, np.eye(3), np.zeros(3))
    assert against_given(moved, flat) is None
    html = _people_rig({"cameras": {n: {"centre_sd_m": 0.01, "rotation_sd_deg": 0.1, "median_px": 2.0}
                                    for n in given.names}, "against_input_calibration": got})
    assert html.count("<tr>") == 1 + len(given.names) and "input&#x27;s calibration" in html


def test_up_and_the_floor_are_the_skeleton_files(people_dir: Path, tmp_path: Path) -> None:
    """A skeleton file's ``up`` and ``floor`` joints set the people's world: the built-in's copy
    gives the built-in's rig; without them the rig from people is one line naming the keys."""
    from gt3dkit.io.skeletonfile import write_skeleton
    from gt3dkit.skeletons import SKELETONS

    scene = load_detections(people_dir)
    assert scene.skeleton is not None
    built_in = SKELETONS[scene.skeleton]
    assert built_in.floor == ("l_ankle", "r_ankle") and built_in.up
    write_skeleton(built_in, tmp_path / "mine.toml")
    mine = calibrate_people(load_detections(people_dir, skeleton=str(tmp_path / "mine.toml")))
    ref = calibrate_people(scene)
    for a, b in zip(mine.rig.cameras, ref.rig.cameras, strict=True):
        np.testing.assert_allclose(a.center_world, b.center_world, atol=1e-9)
    text = (tmp_path / "mine.toml").read_text()
    (tmp_path / "no_floor.toml").write_text("\n".join(ln for ln in text.splitlines()
                                                     if not ln.startswith(("up =", "floor ="))) + "\n")
    with pytest.raises(InputError, match="up and floor"):
        calibrate_people(load_detections(people_dir, skeleton=str(tmp_path / "no_floor.toml")))
