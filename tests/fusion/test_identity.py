"""Identity integrity (gt3dkit.fusion.preparation.identity): an id reused for another person is split into
pieces, each estimated on its own; no object-frame is left out; every command runs the same
pieces."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import estimate_scene, reconstruct, split_ids
from gt3dkit.arrays import lookup_rows
from gt3dkit.compare import compare
from gt3dkit.eval.metrics import match_rows
from gt3dkit.fusion.base import make_estimator
from gt3dkit.fusion.preparation.identity import identity_segments
from gt3dkit.fusion.preparation.pieces import input_ids, pieces_prepared
from gt3dkit.fusion.preparation.prepare import prepare
from gt3dkit.fusion.preparation.rows import build_rows
from gt3dkit.sim import Errors
from gt3dkit.types import GroundTruth, Scene
from tests.scenes import written_scene


def reused(scene: Scene, a: int, b: int, frame: int) -> Scene:
    """``scene`` where person ``a`` is annotated until ``frame`` and person ``b`` from ``frame`` on,
    both under id ``a`` (an id handed to the next person), the truth carrying the same ids."""
    o, t = scene.obs, scene.truth
    keep = ((o.track_id == a) & (o.frame < frame)) | ((o.track_id == b) & (o.frame >= frame)) | \
        ((o.track_id != a) & (o.track_id != b))
    obs = o.select(keep)
    obs = dataclasses.replace(obs, track_id=np.where(obs.track_id == b, a, obs.track_id))
    tk = ((t.track_id == a) & (t.frame < frame)) | ((t.track_id == b) & (t.frame >= frame)) | \
        ((t.track_id != a) & (t.track_id != b))
    truth = GroundTruth(t.frame[tk], np.where(t.track_id[tk] == b, a, t.track_id[tk]), t.center_world[tk],
                        t.semi_axes[tk], t.kpt_world[tk], t.source)
    return dataclasses.replace(scene, obs=obs, truth=truth)


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Scene:
    sc, _ = written_scene(tmp_path_factory.mktemp("ident"), "native", seed=4, frames=24, people=4,
                          noise_px=1.0,
                          motion="walk", errors=Errors(dropped=0.0))
    ids = np.unique(sc.obs.track_id)
    return reused(sc, int(ids[0]), int(ids[1]), int(np.unique(sc.obs.frame)[12]))


@pytest.mark.parametrize("estimator", ["ukf", "gtsam"])
def test_a_reused_id_is_split_and_every_row_follows_its_views(scene: Scene, estimator: str) -> None:
    a = int(np.unique(scene.obs.track_id)[0])
    at = int(np.unique(scene.obs.frame)[12])
    segs = identity_segments(prepare(scene), scene.fps)
    assert [(s.track_id, s.frame_after) for s in segs.splits] == [(a, at)]
    tracks = reconstruct(scene, estimator)
    it, ig = match_rows(tracks, scene.truth)
    assert len(ig) == len(scene.truth.frame)  # no object-frame left out
    err = np.linalg.norm(tracks.center_world[it, :2] - scene.truth.center_world[ig, :2], axis=1)
    assert err.max() < 0.1, err.max()
    assert tracks.info.identity.splits == 1
    assert [(s["id"], s["segment"],
             s["first_frame"]) for s in tracks.info.segments if s["id"] == a][1] == \
        (a, 1, at)


def test_an_unsplit_scene_is_estimated_as_it_was(tmp_path: Path) -> None:
    """No split: the tracks are the estimator's own, with the same rows."""
    sc, _ = written_scene(tmp_path, "native", seed=5, frames=12, people=3, noise_px=1.0, motion="walk")
    pre = prepare(sc)
    segs = identity_segments(pre, sc.fps)
    assert segs.splits == () and not segs.segment.any()
    est = make_estimator("ukf")
    a = estimate_scene(sc, est, None, segs)
    b = make_estimator("ukf").estimate(sc)
    np.testing.assert_array_equal(a.center_world, b.center_world)


def test_compare_runs_the_pieces_reconstruct_runs(scene: Scene, tmp_path: Path) -> None:
    """One estimation path: compare's UKF and GTSAM tracks are reconstruct's (compare prepares
    the pieces once, and GTSAM reuses the UKF's noise search on them)."""
    compare(scene, tmp_path / "cmp", ("ukf", "gtsam", "triangulation"), progress=False)
    for name in ("ukf", "gtsam"):
        alone = reconstruct(scene, name, out=tmp_path / name)
        mine = (tmp_path / name / "tracks.csv").read_text()
        assert (tmp_path / "cmp" / name / "tracks.csv").read_text() == mine, name
        assert alone.info.identity.splits == 1


@pytest.mark.parametrize("seed", [11, 12])
def test_simulated_reused_and_exchanged_ids_are_all_split(tmp_path: Path, seed: int) -> None:
    """The simulator's id errors (an id handed to another person, two ids exchanged for 1-4
    frames; the truth carries the labels' ids, as WILDTRACK's does): every one that places an id
    where it cannot have got to is split there, no object-frame is left out and every row is
    within 0.1 m of its truth."""
    sc, sim = written_scene(tmp_path, "native", seed=seed, frames=30, people=10, noise_px=1.0, motion="walk",
                            errors=Errors(dropped=0.0, reused_ids=2, exchanged_ids=2))
    errs = [r for r in sim.injected if r[4] in ("reused_id", "exchanged_ids")]
    assert len(errs) == 4
    segs = identity_segments(prepare(sc), sc.fps)
    split_at = {(s.track_id, s.frame_after) for s in segs.splits}
    frames = np.unique(sc.obs.frame)
    checked = 0
    for frame, _, a, _, kind, detail in errs:
        # where the id's views were the frame before and are now (the truth carries the labels' ids)
        before = frames[np.searchsorted(frames, frame) - 1]

        def where(f: int, i: int) -> np.ndarray:
            return sc.truth.center_world[(sc.truth.frame == f) & (sc.truth.track_id == i)][0, :2]

        jump = np.linalg.norm(where(frame, a) - where(before, a))
        if jump > 1.0:  # 10 m/s at 10 fps: no walker gets there
            assert (a, frame) in split_at, (kind, detail, frame, a, jump, sorted(split_at))
            checked += 1
            if kind == "exchanged_ids":  # recognised as one exchange of the two ids
                b = int(detail.split()[1])
                assert any(e.frame == frame and {e.track_id, e.other_id} == {a, b} for e in segs.exchanges)
    assert checked >= 3
    # an id reused by another person is no exchange
    reuses = {(f, a) for f, _, a, _, kind, _ in errs if kind == "reused_id"}
    assert not any((e.frame, e.track_id) in reuses or (e.frame, e.other_id) in reuses for e in segs.exchanges)
    tracks = reconstruct(sc, "ukf")
    it, ig = match_rows(tracks, sc.truth)
    assert len(ig) == len(sc.truth.frame)
    err = np.linalg.norm(tracks.center_world[it, :2] - sc.truth.center_world[ig, :2], axis=1)
    assert err.max() < 0.1, err.max()


def test_an_identity_split_picture_shows_both_places(scene: Scene, tmp_path: Path) -> None:
    """The report's picture of an identity split: the id's views where it was (the previous
    piece's last frame, from segments.csv) above its views at the split, each cropped there."""
    import matplotlib.image as mpimg

    from gt3dkit.viz.panels import anomaly_thumbnail, view_residuals
    from gt3dkit.viz.report import _split_frames

    a = int(np.unique(scene.obs.track_id)[0])
    at = int(np.unique(scene.obs.frame)[12])
    tracks = reconstruct(scene, "ukf", out=tmp_path / "run")
    before = _split_frames(tmp_path / "run")
    assert before == {(a, at): int(np.unique(scene.obs.frame)[11])}
    res = view_residuals(tracks, prepare(scene))
    one, two = tmp_path / "one.png", tmp_path / "two.png"
    assert anomaly_thumbnail(scene, res, at, a, "", None, one)
    assert anomaly_thumbnail(scene, res, at, a, "", None, two, before=before[(a, at)])
    h1, h2 = mpimg.imread(one).shape[0], mpimg.imread(two).shape[0]
    assert h2 == 2 * h1  # two rows of views: before, and at the split


def _csv(path: Path) -> list[dict[str, str]]:
    import csv

    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_an_edited_segments_file_overrides_the_splits(tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    """``--segments FILE``: the pieces of an edited segments.csv replace the automatic splits of the
    ids it lists (merged back into one, or cut where the automatic test saw nothing); compare runs
    the same pieces; a file whose pieces overlap is one error line, exit 2, nothing written."""
    from gt3dkit.cli import main
    from gt3dkit.io.writers import read_tracks_csv

    root = tmp_path / "in"
    sc, sim = written_scene(root, "native", seed=21, frames=24, people=5, noise_px=1.0, motion="walk",
                            errors=Errors(dropped=0.0, reused_ids=1))
    (frame, _, a, _, _, _), = [r for r in sim.injected if r[4] == "reused_id"]
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "auto"), "--quiet"]) == 0
    auto = _csv(tmp_path / "auto" / "segments.csv")
    assert [(int(r["id"]), int(r["first_frame"])) for r in auto if r["segment"] == "1"] == [(a, frame)]
    other = int(next(i for i in np.unique(sc.obs.track_id) if i != a))
    f_other = np.unique(sc.obs.frame[sc.obs.track_id == other])
    cut = int(f_other[len(f_other) // 2])
    edited = tmp_path / "segments.csv"
    edited.write_text("id,segment,first_frame,last_frame,rows\n"
                      f"{a},0,{sc.obs.frame.min()},{sc.obs.frame.max()},\n"  # merged: one person after all
                      f"{other},0,{f_other[0]},{cut - 1},\n{other},1,{cut},{f_other[-1]},\n")
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "given"), "--segments", str(edited),
                 "--quiet"]) == 0
    rows = _csv(tmp_path / "given" / "segments.csv")
    assert {(int(r["id"]), int(r["first_frame"])) for r in rows if r["segment"] != "0"} == {(other, cut)}
    flags = [r for r in _csv(tmp_path / "given" / "anomalies.csv") if r["kind"] == "identity_split"]
    assert [(int(r["id"]), int(r["frame"])) for r in flags] == [(other, cut)]
    assert "corrections file" in flags[0]["detail"]
    # the merged id is one track again, over the same rows
    n = len(read_tracks_csv(tmp_path / "auto" / "tracks.csv"))
    assert len(read_tracks_csv(tmp_path / "given" / "tracks.csv")) == n
    assert main(["compare", str(root), "--out", str(tmp_path / "cmp"), "--segments", str(edited),
                 "--quiet"]) == 0
    key = [(r["id"], r["segment"], r["first_frame"]) for r in rows]
    ukf = _csv(tmp_path / "cmp" / "ukf" / "segments.csv")
    assert [(r["id"], r["segment"], r["first_frame"]) for r in ukf] == key
    capsys.readouterr()
    edited.write_text(f"id,segment,first_frame,last_frame,rows\n{a},0,0,10,\n{a},1,10,30,\n")
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "bad"), "--segments", str(edited)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {edited}: line 3: id {a}: frames 10-30 overlap"), err
    assert not (tmp_path / "bad").exists()


def test_the_pieces_preparation_is_the_whole_ones_at_their_rows(scene: Scene) -> None:
    """The pieces' preparation taken from the whole scene's (one preparation a run) agrees with the
    pieces prepared anew (brute force): the same object-frames, fits, kept edges, noise levels and
    per-frame states, to the fits' convergence."""
    whole = prepare(scene)
    segs = identity_segments(whole, scene.fps)
    pieces, back = split_ids(scene, whole.rows, segs)
    taken, anew = pieces_prepared(whole, pieces, back), prepare(pieces)
    assert len(taken.rows) == len(anew.rows) <= len(whole.rows)  # a gap between the pieces has no row
    built = build_rows(pieces)  # the rows regrouped from the whole's are those built anew, exactly
    for name in ("frames", "obj_ids", "row_t", "row_o", "prev_row", "next_row", "t_start", "obs_row"):
        np.testing.assert_array_equal(getattr(taken.rows, name), getattr(built, name), err_msg=name)
    np.testing.assert_array_equal(taken.rows.box_z, built.box_z)
    np.testing.assert_array_equal(taken.rows.obs_row, anew.rows.obs_row)
    np.testing.assert_array_equal(taken.rows.box_mask, anew.rows.box_mask)
    np.testing.assert_array_equal(taken.box_keep, anew.box_keep)
    np.testing.assert_allclose(taken.sigma_box, anew.sigma_box, rtol=1e-12)
    assert taken.fit is not None and anew.fit is not None
    np.testing.assert_allclose(taken.fit.center_world, anew.fit.center_world, atol=1e-6)
    for a, b in zip(taken.frame_state(), anew.frame_state(), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-6, rtol=1e-6)
    src = lookup_rows(np.c_[whole.rows.row_t, whole.rows.obj_ids[whole.rows.row_o]],  # the same object-frame
                      np.c_[taken.rows.row_t, input_ids(taken.rows.obj_ids, back)[taken.rows.row_o]])
    assert (src >= 0).all()
    np.testing.assert_array_equal(whole.rows.frames[whole.rows.row_t[src]],
                                  taken.rows.frames[taken.rows.row_t])
