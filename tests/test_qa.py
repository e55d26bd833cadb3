"""Annotation QA: injected annotator and detector errors are found, and little else."""

from __future__ import annotations

import csv
import json

import numpy as np

from gt3dkit.api import reconstruct
from gt3dkit.io.datasets import load_scene
from gt3dkit.qa.inject import move_person, shift_box
from gt3dkit.sim import Errors, simulate, simulate_skeletons, write_scene, write_skeleton_scene


def _rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_detector_errors_are_flagged(tmp_path) -> None:
    sk = simulate_skeletons("native", seed=5, frames=12, people=2, cameras=6, noise_px=1.0, confidences=True,
                            errors=Errors(outliers=0.01, swaps=0.08, glitch=0.005))
    write_skeleton_scene(sk, tmp_path / "in", "native")
    reconstruct(load_scene(tmp_path / "in"), "ukf", out=tmp_path / "out")
    flags = _rows(tmp_path / "out" / "anomalies.csv")
    injected = _rows(tmp_path / "in" / "injected.csv")
    assert injected
    seen = {(r["frame"], r["camera"], r["id"]) for r in flags}
    assert all((r["frame"], r["camera"], r["id"]) in seen for r in injected)
    wrong = [r for r in flags if (r["frame"], r["camera"], r["id"]) not in
             {(x["frame"], x["camera"], x["id"]) for x in injected}]
    assert len(wrong) <= 2, wrong
    swaps = [r for r in injected if r["kind"] == "swapped_joints"]
    assert swaps and all(any(f["kind"] == "swapped_joints" and (f["frame"], f["camera"], f["id"]) ==
                             (r["frame"], r["camera"], r["id"]) for f in flags) for r in swaps)
    meta = json.loads((tmp_path / "out" / "meta.json").read_text())
    assert sum(meta["estimator"]["qa"]["anomalies"].values()) == len(flags)


def test_shifted_box_and_identity_jump(tmp_path) -> None:
    sim = simulate("wildtrack", seed=2, frames=16, people=5, noise_px=1.0, dropout=0.1)
    root = tmp_path / "w"
    write_scene(sim, root, "wildtrack")
    clean = load_scene(root)
    frame, view, pid = shift_box(root, 4, 0, 120.0)
    files = sorted((root / "annotations_positions").glob("*.json"))
    people = json.loads(files[10].read_text())
    jf, jid = int(files[10].stem), people[1]["personID"]
    i = int(np.flatnonzero((sim.truth_frame == jf) & (sim.truth_id == jid))[0])
    move_person(root, clean.rig, 10, 1, sim.center_world[i] + np.array([4.0, 0, 0]), sim.semi_axes[i])
    tracks = reconstruct(load_scene(root), "ukf", out=tmp_path / "out")
    flags = _rows(tmp_path / "out" / "anomalies.csv")
    kinds = {(int(r["frame"]), r["camera"], int(r["id"])): r["kind"] for r in flags}
    assert kinds.get((frame, clean.rig.names[view], pid)) == "shifted_box"
    assert kinds.get((jf, "", jid)) == "identity_jump"
    assert len(flags) <= 4
    # the moved frame was left out: the track passes where the person really was
    r = np.flatnonzero((tracks.frame == jf) & (tracks.track_id == jid))[0]
    assert np.linalg.norm(tracks.center_world[r, :2] - sim.center_world[i, :2]) < 0.1
