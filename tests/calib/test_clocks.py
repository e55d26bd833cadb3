"""gt3dkit.refine.clocks: each camera's clock from the people, held to the simulator's people with
cameras late by whole and fractional frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_detections
from gt3dkit.io.clocks import read_time_offsets
from gt3dkit.refine.clocks import estimate_clocks, follow, synchronised, tracks_of
from gt3dkit.refine.people import PeopleConfig, calibrate_people, person_views
from gt3dkit.sim import simulate_skeletons, write_skeleton_scene
from gt3dkit.types import Scene

LATE = np.array([0.0, 2.0, -1.5, 0.3, 0.0, 0.7])  # frames, per camera


@pytest.fixture(scope="module")
def people(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    root = tmp_path_factory.mktemp("clocks")
    write_skeleton_scene(simulate_skeletons("native", seed=2, frames=40, people=3, noise_px=1.5, cameras=6),
                         root, "native")
    return load_detections(root)


@pytest.fixture(scope="module")
def late_people(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    """The same people seen by cameras late by :data:`LATE` (the simulator's exact motion at each
    camera's own time)."""
    root = tmp_path_factory.mktemp("late")
    write_skeleton_scene(simulate_skeletons("native", seed=2, frames=40, people=3, noise_px=1.5, cameras=6,
                                            late_frames=LATE), root, "native")
    return load_detections(root)


def test_tracks_follow_each_person(people: Scene) -> None:
    pv = person_views(people, PeopleConfig())
    succ, pred = follow(pv)
    assert (succ >= 0).mean() > 0.9
    np.testing.assert_array_equal(pred[succ[succ >= 0]], np.flatnonzero(succ >= 0))
    track = tracks_of(succ, pred)
    # a track stays with one simulated person (the native layout's ids are the truth's)
    same = [len(set(people.obs.track_id[track == t].tolist())) == 1 for t in np.unique(track)]
    assert np.mean(same) > 0.95


def test_clocks_through_the_true_rig(people: Scene, late_people: Scene) -> None:
    pv = person_views(people, PeopleConfig())
    sync = estimate_clocks(pv, people.rig)
    assert np.abs(sync.late_frames).max() < 0.1  # measured 0.045
    late = estimate_clocks(person_views(late_people, PeopleConfig()), people.rig)
    err = np.abs(late.late_frames - LATE)
    assert err.max() < 0.1, late.late_frames  # measured 0.037
    assert np.all(err[1:] < 3 * late.sd_frames[1:] + 0.02)  # the sd covers the error
    moved = synchronised(pv, follow(pv)[0], np.array([0.0, 1.0, 0, 0, 0, 0]))
    assert np.array_equal(moved.frame[pv.cam == 1], pv.frame[pv.cam == 1] - 1)


def test_rig_and_clocks_from_late_cameras(people: Scene, late_people: Scene) -> None:
    res = calibrate_people(late_people, PeopleConfig(clocks=True))
    assert res.clocks is not None
    assert np.abs(res.clocks.late_frames - LATE).max() < 0.15  # measured 0.04-0.07
    assert res.report["clocks"]["late_frames"][people.rig.names[1]] == pytest.approx(LATE[1], abs=0.15)


def test_cli_writes_the_clocks(late_people: Scene, tmp_path: Path) -> None:
    import subprocess
    import sys

    out = tmp_path / "cal"
    p = subprocess.run([sys.executable, "-m", "gt3dkit.cli", "calib", "people", str(late_people.root),
                        "--clocks",
                        "--out", str(out)], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    rows = (out / "time_offsets.csv").read_text().splitlines()
    assert rows[0] == "camera,late_frames,sd_frames,fps" and len(rows) == 7
    clocks = read_time_offsets(out / "time_offsets.csv")
    assert np.abs(clocks.late_frames - LATE).max() < 0.1, clocks.late_frames  # measured 0.03
    said = json.loads((out / "calib_report.json").read_text())["clocks"]
    assert said["rounds"]
    assert said["cameras"]["00_01"]["late_frames"] == pytest.approx(clocks.late_frames[1], abs=1e-3)
    assert "clocks from the people (frames late" in p.stdout
