"""Annotation QA: injected annotator and detector errors are found, and little else."""

from __future__ import annotations

import csv
import json

import numpy as np

from gt3dkit.api import load_scene, reconstruct
from gt3dkit.sim import Errors, simulate, simulate_skeletons, write_scene, write_skeleton_scene
from tests.inject import move_person, shift_box


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


def test_shifted_box_and_a_mis_keyed_frame(tmp_path) -> None:
    """A shifted box is flagged; one frame whose views all describe someone 4 m away (a mis-keyed
    id) splits the id: that frame is reconstructed where its views agree, the frames around it
    are not bent towards it, and anomalies.csv says where and why."""
    sim = simulate("wildtrack", seed=2, frames=16, people=5, noise_px=1.0,
                   errors=Errors(dropped=0.0, hide_covered=0.5))
    root = tmp_path / "w"
    write_scene(sim, root, "wildtrack")
    clean = load_scene(root)
    frame, view, pid = shift_box(root, 4, 0, 120.0)
    files = sorted((root / "annotations_positions").glob("*.json"))
    people = json.loads(files[10].read_text())
    jf, jid = int(files[10].stem), people[1]["personID"]
    i = int(np.flatnonzero((sim.truth_frame == jf) & (sim.truth_id == jid))[0])
    elsewhere = sim.center_world[i] + np.array([4.0, 0, 0])
    move_person(root, clean.rig, 10, 1, elsewhere, sim.semi_axes[i])
    tracks = reconstruct(load_scene(root), "ukf", out=tmp_path / "out")
    flags = _rows(tmp_path / "out" / "anomalies.csv")
    kinds = {(int(r["frame"]), r["camera"], int(r["id"]), r["kind"]) for r in flags}
    assert (frame, clean.rig.names[view], pid, "shifted_box") in kinds
    assert (jf, "", jid, "identity_split") in kinds  # into the moved frame ...
    after = [int(r["frame"]) for r in flags if r["kind"] == "identity_split" and int(r["id"]) == jid]
    assert len(after) == 2 and min(after) == jf  # ... and out of it
    assert len(flags) <= 5
    assert tracks.info.identity.splits == 2
    mine = tracks.track_id == jid
    r = np.flatnonzero(mine & (tracks.frame == jf))[0]
    assert np.linalg.norm(tracks.center_world[r, :2] - elsewhere[:2]) < 0.1  # where its views are
    for k in np.flatnonzero(mine & (tracks.frame != jf)):  # the rest where the person really was
        t = np.flatnonzero((sim.truth_frame == tracks.frame[k]) & (sim.truth_id == jid))[0]
        assert np.linalg.norm(tracks.center_world[k, :2] - sim.center_world[t, :2]) < 0.1
    assert len(tracks) == len(np.unique(np.c_[tracks.frame, tracks.track_id], axis=0))  # one row each


def test_missing_views_and_an_unsynchronised_camera(tmp_path) -> None:
    sim = simulate("wildtrack", seed=3, frames=16, people=6, noise_px=1.0,
                   errors=Errors(dropped=0.0, missing=0.03, time_offset=(5, 2), hide_covered=0.5))
    write_scene(sim, tmp_path / "w", "wildtrack")
    sc = load_scene(tmp_path / "w")
    reconstruct(sc, "ukf", out=tmp_path / "out")
    flags = _rows(tmp_path / "out" / "anomalies.csv")
    cam = sc.rig.names[5]
    offs = [r for r in flags if r["kind"] == "time_offset"]
    assert [r["camera"] for r in offs] == [cam] and "best +2 frame" in offs[0]["detail"]
    assert offs[0]["id"] == "" and offs[0]["joint"] == ""
    missing = {(r[0], r[1], r[2]) for r in sim.injected if r[4] == "missing_view" and r[1] != cam}
    assert missing
    found = {(int(r["frame"]), r["camera"], int(r["id"])) for r in flags if r["kind"] == "missing_view"}
    assert missing <= found
    assert len(found - missing) <= 2
    # the unsynchronised camera's own per-view flags are folded into its one row
    assert not [r for r in flags if r["camera"] == cam and r["kind"] != "time_offset"]


def test_people_hidden_behind_others_are_not_missing(tmp_path) -> None:
    """Annotators leave out people hidden behind nearer ones: never a missing_view."""
    sim = simulate("wildtrack", seed=6, frames=12, people=12, noise_px=1.0, errors=Errors(dropped=0.0,
                                                                                          hide_covered=0.5))
    write_scene(sim, tmp_path / "w", "wildtrack")
    assert np.isnan(sim.boxes).all(axis=-1).sum() > 0
    reconstruct(load_scene(tmp_path / "w"), "ukf", out=tmp_path / "out")
    flags = _rows(tmp_path / "out" / "anomalies.csv")
    assert len([r for r in flags if r["kind"] == "missing_view"]) <= 2


def test_covered_fraction_against_a_pixel_count() -> None:
    from gt3dkit.geom.conics import covered_fraction

    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 60, size=(5, 1, 2))
    wh = rng.uniform(10, 40, size=(5, 1, 2))
    box = np.concatenate([xy, xy + wh], axis=-1)
    depth = rng.uniform(1, 10, size=(5, 1))
    cov = covered_fraction(box, depth)
    g = np.mgrid[0:120:0.25, 0:120:0.25].reshape(2, -1).T + 0.125  # pixel grid, 1/16 px^2 cells
    inside = [(g[:, 0] >= b[0]) & (g[:, 0] < b[2]) & (g[:, 1] >= b[1]) & (g[:, 1] < b[3]) for b in box[:, 0]]
    for i in range(5):
        nearer = [k for k in range(5) if depth[k, 0] < depth[i, 0]]
        per = sum((inside[i] & inside[k]).sum() for k in nearer) / inside[i].sum()  # sum of overlaps
        assert abs(cov[i, 0] - min(per, 1.0)) < 0.02


def test_real_multiviewx_has_no_missing_views(multiviewx, tmp_path) -> None:
    """The real MultiviewX labels annotate every visible person; a tangent box that the lens
    model folds (xmin > xmax near the image edge) is no view an annotator missed."""
    reconstruct(multiviewx, "triangulation", out=tmp_path / "o")
    rows = _rows(tmp_path / "o" / "anomalies.csv")
    assert not [r for r in rows if r["kind"] == "missing_view"], rows[:3]


def test_cut_edges_by_hand() -> None:
    """An edge inside a nearer object's box (by more than the margin, the boxes sharing half the
    label's extent across it) is cut; a farther object, or the label's own box, cuts nothing."""
    from gt3dkit.geom.conics import cut_edges

    label = np.array([[[100.0, 100, 140, 300]], [[80, 220, 160, 400]]])  # (2 objects, 1 camera, 4)
    box = label.copy()
    cut, who = cut_edges(label, box, np.array([[10.0], [5.0]]))
    assert cut[0, 0].tolist() == [False, False, False, True] and who[0, 0] == 1  # feet behind object 1
    assert not cut[1].any() and who[1, 0] == -1  # the nearer one is cut by nobody
    cut, who = cut_edges(label, box, np.array([[5.0], [10.0]]))  # the other way round
    assert cut[1, 0].tolist() == [False, True, False, False] and not cut[0].any()
    cut, _ = cut_edges(label, box, np.array([[10.0], [9.8]]))  # within the depth tolerance
    assert not cut.any()


def test_a_box_cut_by_a_nearer_person_is_not_a_shifted_box(tmp_path) -> None:
    """A box drawn around the visible part of a person whose legs a nearer person hides (its
    bottom moved up into the nearer one's box) is listed as cut_box, not shifted_box; the same cut
    where nobody stands in front is a shifted_box."""
    import dataclasses

    from gt3dkit.api import annotation_qa
    from gt3dkit.geom.camera import Cams
    from gt3dkit.geom.conics import model_boxes

    sim = simulate("wildtrack", seed=2, frames=8, people=14, noise_px=1.0, errors=Errors(dropped=0.0))
    write_scene(sim, tmp_path / "w", "wildtrack")
    scene = load_scene(tmp_path / "w")
    tracks = reconstruct(scene, "ukf")
    box, depth = model_boxes(tracks.center_world, tracks.semi_axes, Cams.of(scene.rig, scene.box_model))
    obs = scene.obs
    key = {(int(f), int(i)): k for k, (f, i) in enumerate(zip(tracks.frame, tracks.track_id, strict=True))}
    behind = alone = None
    for r in range(len(obs)):
        f, c, a = int(obs.frame[r]), int(obs.cam[r]), key[(int(obs.frame[r]), int(obs.track_id[r]))]
        lab = obs.box_xyxy_px[r]
        h, w = lab[3] - lab[1], lab[2] - lab[0]
        if h < 80:
            continue
        ids = np.unique(obs.track_id[obs.frame == f])
        others = [key[(f, int(i))] for i in ids if int(i) != obs.track_id[r]]
        over = [k for k in others if min(lab[2], box[k, c, 2]) - max(lab[0], box[k, c, 0]) > 0
                and min(lab[3], box[k, c, 3]) - max(lab[1], box[k, c, 1]) > 0]
        if not over and alone is None:
            alone = (r, lab[1] + 0.5 * h)
        for k in over:
            y = max(box[k, c, 1] + 10, lab[1] + 0.5 * h)
            wide = min(lab[2], box[k, c, 2]) - max(lab[0], box[k, c, 0]) >= 0.6 * w
            if behind is None and wide and depth[k, c] < depth[a, c] - 1.0 and y < min(lab[3] - 0.3 * h,
                                                                                      box[k, c, 3] - 10):
                behind = (r, y)
    assert behind is not None and alone is not None
    xyxy = obs.box_xyxy_px.copy()
    for r, y in (behind, alone):
        xyxy[r, 3] = y
    cut = dataclasses.replace(scene, obs=dataclasses.replace(obs, box_xyxy_px=xyxy))
    flags = {(int(f), cam, int(i)): kind for f, cam, i, _, kind, _, _ in
             annotation_qa(cut, reconstruct(cut, "ukf")).rows if kind in ("cut_box", "shifted_box",
                                                                             "size_outlier")}
    names = scene.rig.names
    where = {r: (int(obs.frame[r]), names[int(obs.cam[r])], int(obs.track_id[r])) for r, _ in (behind, alone)}
    assert flags.get(where[behind[0]]) == "cut_box", flags
    assert flags.get(where[alone[0]]) in ("shifted_box", "size_outlier"), flags


def test_another_persons_box_under_an_id_is_named(tmp_path) -> None:
    """A view's label replaced by the box of another person in that view (a detector's box of the
    nearer of two people given the farther one's id, as CMC1's ids were given by overlap) is a
    shifted_box that names the person whose box it is."""
    import dataclasses

    from gt3dkit.api import annotation_qa
    from gt3dkit.qa.anomalies import _iou

    sim = simulate("wildtrack", seed=2, frames=8, people=14, noise_px=1.0, errors=Errors(dropped=0.0))
    write_scene(sim, tmp_path / "w", "wildtrack")
    scene = load_scene(tmp_path / "w")
    obs = scene.obs
    pick = None
    for r in range(len(obs)):
        view = (obs.frame == obs.frame[r]) & (obs.cam == obs.cam[r])
        same = np.flatnonzero(view & (obs.track_id != obs.track_id[r]))
        far = [q for q in same if _iou(obs.box_xyxy_px[q], obs.box_xyxy_px[r]) < 0.05
               and (obs.box_xyxy_px[q, 3] - obs.box_xyxy_px[q, 1]) > 60]
        if far and (obs.box_xyxy_px[r, 3] - obs.box_xyxy_px[r, 1]) > 60:
            pick = (r, far[0])
            break
    assert pick is not None
    r, q = pick
    xyxy = obs.box_xyxy_px.copy()
    xyxy[r] = obs.box_xyxy_px[q]
    swapped = dataclasses.replace(scene, obs=dataclasses.replace(obs, box_xyxy_px=xyxy))
    rows = annotation_qa(swapped, reconstruct(swapped, "ukf")).rows
    mine = [a for a in rows if (a[0], a[1], a[2]) == (int(obs.frame[r]), scene.rig.names[int(obs.cam[r])],
                                                       int(obs.track_id[r]))]
    assert mine and mine[0][4] == "shifted_box", mine
    assert f"fits object {int(obs.track_id[q])}'s box" in mine[0][6], mine
