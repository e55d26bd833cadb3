"""Boxes drawn around the visible part of a person (gt3dkit.fusion.preparation.occlusion and the simulator's
``Errors.cut_by_nearer``): the cut edges are found, left out where the data say they mislead,
reported, and kept where a label set draws people whole."""

from __future__ import annotations

import csv
import json
import re

import numpy as np
import pytest

from gt3dkit.api import load_scene, reconstruct
from gt3dkit.eval.metrics import box_errors
from gt3dkit.fusion.preparation import occlusion
from gt3dkit.fusion.preparation.prepare import prepare
from gt3dkit.fusion.ukf.config import UKFConfig
from gt3dkit.qa.anomalies import which_cut
from gt3dkit.sim import Errors, simulate, write_scene


def _crowd(seed: int, cut: bool, frames: int = 12, people: int = 30):
    return simulate("wildtrack", seed=seed, frames=frames, people=people, noise_px=2.0, motion="walk",
                    errors=Errors(cut_by_nearer=cut))


def test_the_simulator_cuts_a_box_where_a_nearer_box_begins() -> None:
    """Every cut box is smaller than the whole one on the cut sides only, and its cut sides lie on
    the opposite edge of another person's box in that view (the same boxes, uncut, as the plain
    scene: the cut draws no random numbers; an unannotated person cuts too, so most, not all,
    cut sides find the box that cut them among the annotated ones)."""
    whole, cut = _crowd(0, False), _crowd(0, True)
    rows = [r for r in cut.injected if r[4] == "cut_box"]
    assert len(rows) > 100
    names = [c.name for c in cut.rig.cameras]
    found = []
    for frame, cam, pid, _, _, detail in rows:
        i = int(np.flatnonzero((cut.truth_frame == frame) & (cut.truth_id == pid))[0])
        c = names.index(cam)
        a, b = whole.boxes[i, c], cut.boxes[i, c]
        moved = np.flatnonzero(a != b)
        assert len(moved) and all(n in detail for n in np.array(["xmin", "ymin", "xmax", "ymax"])[moved])
        assert np.all((b[:2] >= a[:2]) & (b[2:] <= a[2:]))  # only ever smaller
        others = whole.boxes[(whole.truth_frame == frame) & (np.arange(len(whole.truth_id)) != i), c]
        found += [bool(np.any(np.isclose(others[:, 2 - e if e in (0, 2) else 4 - e], b[e]))) for e in moved]
    assert np.mean(found) > 0.8


@pytest.fixture(scope="module")
def crowd_runs(tmp_path_factory):
    """A crowd's boxes as drawn and whole, each reconstructed with the cut edges handled, and the
    drawn ones again with nothing left out (the variance ratio needed set out of reach)."""
    out = {}
    for name, cut in (("whole", False), ("drawn", True)):
        root = tmp_path_factory.mktemp(name)
        write_scene(_crowd(0, cut), root / "in", "native")
        scene = load_scene(root / "in")
        tracks = reconstruct(scene, "ukf", out=root / "out")
        out[name] = (scene, tracks, root / "out")
    scene = out["drawn"][0]
    out["drawn, read as whole"] = (scene, reconstruct(scene, "ukf", cut_variance_ratio=1e12), None)
    return out


def test_cut_edges_are_left_out_and_the_estimate_holds(crowd_runs) -> None:
    err = {k: box_errors(t, s.truth, s.rig.up).ground_mean_m for k, (s, t, _) in crowd_runs.items()}
    assert err["drawn"] < 0.9 * err["drawn, read as whole"], err  # 12.4 against 15.0 mm
    assert err["drawn"] < 1.4 * err["whole"], err  # 12.4 against 10.0 mm
    meta = json.loads((crowd_runs["drawn"][2] / "meta.json").read_text())
    cut = meta["estimator"]["preparation"]["boxes"]["cut_edges"]
    assert sum(cut["left_out"].values()) > 100
    ratio = cut["variance_ratio"]
    assert all(ratio[k] >= UKFConfig().cut_variance_ratio for k, n in cut["left_out"].items() if n)
    flags = (crowd_runs["drawn"][2] / "anomalies.csv").read_text()
    assert flags.count(",cut_edges,") == len(crowd_runs["drawn"][0].rig.cameras)  # a row per camera


def test_the_cut_edges_rows_say_which_boxes(crowd_runs) -> None:
    """Each camera's ``cut_edges`` row names the boxes whose edges it left out (ids, runs of
    frames): as many as it counts, the very boxes the preparation left edges of out, and most of
    those the simulator cut (where a kind's cut edges mislead, all of that kind inside a nearer
    box are left out, of boxes drawn whole too)."""
    scene, _, out = crowd_runs["drawn"]
    cut = {(c, i, f) for f, c, i, _, kind, _ in _crowd(0, True).injected if kind == "cut_box"}
    pre = prepare(scene)
    rows = pre.rows
    left_out = {(scene.rig.names[c], int(rows.obj_ids[rows.row_o[r]]), int(rows.frames[rows.row_t[r]]))
                for r, c in zip(*np.nonzero(pre.box_cut.any(axis=2)), strict=True)}
    frames = np.unique(scene.obs.frame)
    said: set[tuple[str, int, int]] = set()
    counted = 0
    with open(out / "anomalies.csv", newline="") as fh:
        for row in csv.DictReader(fh):
            if row["kind"] != "cut_edges":
                continue
            counted += int(re.search(r"edges of (\d+) of its", row["detail"]).group(1))
            for pid, runs in re.findall(r"id (\d+) frames ([\d, -]+) \(", row["detail"].split("Which: ")[1]):
                for run in runs.split(", "):
                    a, _, b = run.partition("-")
                    said |= {(row["camera"], int(pid), int(f)) for f in frames[(frames >= int(a))
                                                                              & (frames <= int(b or a))]}
    assert counted > 50 and len(said) == counted
    assert said == left_out
    by = pre.box_cut_by  # each left-out edge lies in a nearer object's box of its frame
    r, c, e = np.nonzero(pre.box_cut)
    assert (by[r, c, e] >= 0).all() and (rows.row_t[by[r, c, e]] == rows.row_t[r]).all()
    assert (by[r, c, e] != r).all()
    # nearer that camera (by the final fits: those the cut was judged by moved since, a little)
    depth = np.linalg.norm(pre.fit.center_world[:, None, :] - pre.cams.centres[None], axis=-1)  # (R, C) m
    assert (depth[by[r, c, e], c] < depth[r, c]).all()
    assert len(said & cut) > 0.5 * len(said), (len(said & cut), len(said))


def test_which_cut_by_hand() -> None:
    """Runs of consecutive frames (the frames' own step) per object, with the kinds of its cut
    edges; rows without a cut edge are not named."""
    ids = np.array([2, 2, 2, 2, 3, 3, 5])
    frames = np.array([10, 15, 20, 30, 15, 20, 25])
    cut = np.zeros((7, 4), bool)
    cut[[0, 1, 2, 3], 3] = True
    cut[3, 0] = True
    cut[5, 0] = True
    assert which_cut(ids, frames, cut) == "id 2 frames 10-20, 30 (xmin, ymax); id 3 frames 20 (xmin)"
    by = np.where(cut, 7, -1)
    by[0, 3] = 5
    assert which_cut(ids, frames, cut, by) == ("id 2 frames 10-20, 30 (xmin, ymax; inside ids 5, 7); "
                                               "id 3 frames 20 (xmin; inside id 7)")


def test_whole_boxes_keep_every_edge(crowd_runs) -> None:
    """Boxes drawn whole (an ellipsoid's tangent box behind a nearer person too): the edges inside
    a nearer box vary as the others, and none is left out."""
    meta = json.loads((crowd_runs["whole"][2] / "meta.json").read_text())
    cut = meta["estimator"]["preparation"]["boxes"]["cut_edges"]
    assert sum(cut["found"].values()) > 100
    assert sum(cut["left_out"].values()) == 0
    assert ",cut_edges," not in (crowd_runs["whole"][2] / "anomalies.csv").read_text()


def test_a_sliver_and_a_clipped_box_are_no_calibration_error(tmp_path) -> None:
    """Two views of a person, one a sliver left by a nearer person and the other cut by the image
    border, place the person behind one of the two cameras; neither view can be left out to
    place it, so that is no proof of a wrong calibration: the run goes on (it stopped with "the
    object of this box is behind camera IDIAP1")."""
    write_scene(simulate("wildtrack", seed=1, frames=30, people=40, noise_px=2.0, motion="walk",
                         errors=Errors(cut_by_nearer=True)), tmp_path, "native")
    pre = prepare(load_scene(tmp_path))
    assert pre.fit is not None and pre.fit.ok.mean() > 0.95


@pytest.mark.parametrize("cut", [True, False])
def test_a_long_recording_is_judged_on_a_sample_first(tmp_path, cut: bool, monkeypatch) -> None:
    """Over :data:`CUT_SAMPLE_FRAMES` frames the cut edges are judged on every k-th frame first:
    boxes drawn whole then search no further (the sample's cut edges only) and keep every edge;
    boxes drawn as seen are searched whole and lose exactly the edges a search without the sample
    does."""
    write_scene(_crowd(0, cut, frames=560, people=14), tmp_path, "native")
    scene = load_scene(tmp_path)
    assert len(scene.frames) > occlusion.CUT_SAMPLE_FRAMES
    sampled = prepare(scene)
    monkeypatch.setattr(occlusion, "CUT_SAMPLE_FRAMES", 10**9)
    whole = prepare(scene)
    found = [sum(p.info.boxes.cut_edges["found"].values()) for p in (sampled, whole)]  # type: ignore[union-attr,index]
    if cut:
        assert sampled.box_cut is not None and np.array_equal(sampled.box_cut, whole.box_cut)
        assert found[0] == found[1]
    else:
        assert sampled.box_cut is None and whole.box_cut is None
        assert 0 < found[0] < 0.5 * found[1]
