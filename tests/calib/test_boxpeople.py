"""gt3dkit.refine.boxpeople: a rig from people's boxes, held to the simulator's rig (ellipsoid
people, ids across cameras) after the similarity that best maps the camera centres."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_detections
from gt3dkit.cli import main
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.conics import model_boxes
from gt3dkit.refine.boxpeople import calibrate_boxes
from gt3dkit.refine.common import umeyama
from gt3dkit.sim import simulate, write_scene
from gt3dkit.types import Observations, Scene


@pytest.fixture(scope="module")
def boxes(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    root = tmp_path_factory.mktemp("boxes") / "sim"
    write_scene(simulate("native", seed=0, frames=40, people=10, noise_px=1.0), root, "native")
    return load_detections(root)


def test_rig_from_boxes(boxes: Scene) -> None:
    res = calibrate_boxes(boxes)
    ours = np.array([c.center_world for c in res.rig.cameras])
    truth = np.array([c.center_world for c in boxes.rig.cameras])
    s, R, t = umeyama(ours, truth)
    centre = np.linalg.norm((s * (R @ ours.T)).T + t - truth, axis=1)
    rot = np.array([np.degrees(np.arccos(np.clip((np.trace((a.R @ R.T).T @ b.R) - 1) / 2, -1, 1)))
                    for a, b in zip(res.rig.cameras, boxes.rig.cameras, strict=True)])
    # measured: centres 3.3-8.6 cm, rotations 0.31-1.1 deg, up 0.21 deg, scale 1.07 (the simulated
    # people are not 1.7 m tall on average)
    assert centre.max() < 0.15 and rot.max() < 1.5, (centre, rot)
    assert np.degrees(np.arccos(np.clip((R @ res.rig.up) @ boxes.rig.up, -1, 1))) < 1.0
    sd = np.array([[v["centre_sd_m"], v["rotation_sd_deg"]] for v in res.report["cameras"].values()])
    assert np.all(centre < 3 * np.sqrt(3) * sd[:, 0]) and np.all(rot < 3 * np.sqrt(3) * sd[:, 1])
    assert res.report["from"] == "boxes" and "plane through their feet" in res.report["world"]["frame"]


def test_a_camera_with_too_few_people(boxes: Scene) -> None:
    o = boxes.obs
    last = o.cam == len(boxes.rig.cameras) - 1
    keep = ~last | (np.cumsum(last) <= 8)  # the last camera keeps eight boxes
    with pytest.raises(InputError, match=rf"^{boxes.rig.names[-1]}: shares at most \d+ whole boxes"):
        calibrate_boxes(dataclasses.replace(boxes, obs=o.select(keep)))


def test_cli_boxes(boxes: Scene, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cal"
    assert main(["calib", "people", boxes.root, "--out", str(out), "--height", "1.75"]) == 0
    said = capsys.readouterr().out
    assert "box points (feet, heads)" in said and "vs input cm" in said
    rep = json.loads((out / "calib_report.json").read_text())
    assert "1.75 m" in rep["world"]["frame"]
    assert main(["calib", "people", boxes.root, "--out", str(tmp_path / "c2"), "--clocks"]) == 2
    assert capsys.readouterr().err.strip() == ("error: --clocks / --time-offsets auto: applies to keypoints "
                                              "(a rig from boxes takes the intrinsics given and one clock)")
    assert not (tmp_path / "c2").exists()


def test_ids_of_each_camera_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root = tmp_path / "mot"
    write_scene(simulate("native", seed=0, frames=10, people=4), root, "mot")
    assert main(["calib", "people", str(root), "--out", str(tmp_path / "cal")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "needs each person's id the same in every camera" in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "cal").exists()


def test_everyone_on_one_line_is_refused(boxes: Scene) -> None:
    """People walking along one line across the floor: their feet and heads lie in one plane, which
    leaves the essential matrix ambiguous."""
    rig = boxes.rig
    n = 60
    s = np.linspace(-4, 4, n)
    X = np.stack([s, 0.3 * s, np.full(n, 0.85)], 1)  # along the line y = 0.3 x, the body's centre
    axes = np.tile([0.25, 0.25, 0.85], (n, 1))
    box, _ = model_boxes(X, axes, Cams.of(rig))  # (n, C, 4)
    C = len(rig.cameras)
    ok = np.isfinite(box).all(-1)
    f, c = np.nonzero(ok)
    obs = Observations(f, c, np.zeros(len(f), np.int64), box[f, c], np.zeros((len(f), 0, 2)),
                       [f"line: {k}" for k in range(len(f))])
    assert len(np.unique(c)) == C
    with pytest.raises(InputError, match="one plane .* not determined"):
        calibrate_boxes(dataclasses.replace(boxes, obs=obs, frames=np.arange(n)))
