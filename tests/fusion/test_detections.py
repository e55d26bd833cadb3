"""fusion/preparation/detections.py: people from detections without identities. A person OpenPose finds as two
skeletons in one view (the upper body and the legs, as it does on real Shelf) is one person, not
two; two whole people are never merged."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.cli import main

#: BODY_25's legs (hips to toes): the part OpenPose finds apart from the upper body
LEGS = (9, 10, 11, 12, 13, 14, 19, 20, 21, 22, 23, 24)


def _ids(out: Path) -> tuple[set[int], list[dict[str, str]]]:
    with (out / "association.csv").open() as f:
        rows = list(csv.DictReader(f))
    return {int(r["global_id"]) for r in rows if int(r["global_id"]) >= 0}, rows


def test_a_person_split_in_one_view_stays_one_person(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    trial = tmp_path / "t"
    assert main(["simulate", "--kind", "skeleton", "--format", "openpose", "--seed", "5", "--frames", "8",
                 "--people", "2", "--cameras", "4", "--out", str(trial)]) == 0
    assert main(["reconstruct", str(trial), "--out", str(tmp_path / "whole"), "--quiet"]) == 0
    people, rows = _ids(tmp_path / "whole")
    assert not any("second detection" in r["note"] for r in rows)
    # split every person of one camera's frame into its upper body and its legs
    cam = sorted(p for p in (trial / "pose").iterdir() if p.is_dir())[0]
    page = sorted(cam.glob("*.json"))[4]
    doc = json.loads(page.read_text())
    split = []
    for person in doc["people"]:
        k = np.asarray(person["pose_keypoints_2d"], dtype=float).reshape(25, 3)
        legs, upper = k.copy(), k.copy()
        upper[list(LEGS)] = 0.0
        legs[[j for j in range(25) if j not in LEGS]] = 0.0
        split += [{**person, "pose_keypoints_2d": upper.ravel().tolist()},
                  {**person, "pose_keypoints_2d": legs.ravel().tolist()}]
    assert len(split) >= 2
    doc["people"] = split
    page.write_text(json.dumps(doc))
    capsys.readouterr()
    assert main(["reconstruct", str(trial), "--out", str(tmp_path / "split"), "--quiet"]) == 0
    err = capsys.readouterr().err
    people_split, rows = _ids(tmp_path / "split")
    assert len(people_split) == len(people), err
    # each split person is one: its second part merged (and its camera's duplicate left out), or,
    # where that part has too few joints in common with the other views, left out unconfirmed
    seconds = [r for r in rows if "second detection" in r["note"]]
    assert 1 <= len(seconds) <= len(split) // 2, err
    assert all(r["global_id"] == "-1" for r in seconds)
    assert f"{len(seconds)} detections of a person a camera had already detected" in err


#: BODY_25's right leg below the hip: knee, ankle, big toe, small toe, heel
RIGHT_LEG = (10, 11, 22, 23, 24)


def test_a_leg_found_twice_does_not_take_the_persons_other_views(tmp_path: Path) -> None:
    """A view where the detector put a person's right leg on something else and found the leg
    again as a skeleton of its own (real Shelf, frame 6): the few joints of that leg agree with
    the person's other views as well as the whole skeleton does, and grouped first they took one
    of those views into a second person. The well-supported pairs go first, and two views with
    too few joints in common to compare (a person half out of one view) neither join nor part
    a group: every frame has as many people as the trial has, and the legs are left out."""
    trial = tmp_path / "t"
    assert main(["simulate", "--kind", "skeleton", "--format", "openpose", "--seed", "5", "--frames", "8",
                 "--people", "2", "--cameras", "4", "--noise-px", "2", "--out", str(trial)]) == 0
    assert main(["reconstruct", str(trial), "--out", str(tmp_path / "whole"), "--quiet"]) == 0
    people, _ = _ids(tmp_path / "whole")
    cams = sorted(p for p in (trial / "pose").iterdir() if p.is_dir())
    for page in sorted(cams[0].glob("*.json")):
        doc = json.loads(page.read_text())
        extra = []
        for person in doc["people"]:
            k = np.asarray(person["pose_keypoints_2d"], dtype=float).reshape(25, 3)
            leg = np.zeros_like(k)
            leg[list(RIGHT_LEG)] = k[list(RIGHT_LEG)]
            k[list(RIGHT_LEG), :2] += [90.0, -60.0]  # the whole skeleton's leg, misplaced
            person["pose_keypoints_2d"] = k.ravel().tolist()
            extra.append({**person, "pose_keypoints_2d": leg.ravel().tolist()})
        doc["people"] += extra
        page.write_text(json.dumps(doc))
    assert main(["reconstruct", str(trial), "--out", str(tmp_path / "legs"), "--quiet"]) == 0
    got, rows = _ids(tmp_path / "legs")
    assert len(got) == len(people)
    per_frame: dict[int, set[int]] = {}
    for r in rows:
        if int(r["global_id"]) >= 0:
            per_frame.setdefault(int(r["frame"]), set()).add(int(r["global_id"]))
    assert all(len(v) == len(people) for v in per_frame.values()), per_frame
    # every camera's whole skeletons are the people's, in every frame (4 cameras x 2 people)
    assert sum(int(r["global_id"]) >= 0 for r in rows) == 8 * 4 * len(people)
