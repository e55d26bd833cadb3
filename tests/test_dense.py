"""Rows of the output: by default one per annotated object-frame (one camera or more);
``--every-frame [STEP]`` a row for every frame of the grid from each object's first to its last
annotation, interpolated through gaps (``n_views`` 0) with an sd that covers."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from gt3dkit.api import reconstruct
from gt3dkit.cli import main
from gt3dkit.eval.metrics import match_rows
from gt3dkit.io.writers import read_tracks_csv
from gt3dkit.sim import Errors
from gt3dkit.types import Scene
from tests.scenes import written_scene


@pytest.fixture(scope="module")
def gap(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Scene]:
    """Six walkers, six cameras, 10 fps; frames 8-13 (0.6 s) carry no annotation at all."""
    root = tmp_path_factory.mktemp("dense") / "in"
    sc, _ = written_scene(root, "native", seed=7, frames=30, people=6, noise_px=1.0, motion="walk",
                          errors=Errors(gap=(8, 14), dropped=0.0))
    return root, sc


def test_default_rows_are_the_annotated_object_frames(gap: tuple[Path, Scene]) -> None:
    _, sc = gap
    tracks = reconstruct(sc, "ukf")
    annotated = {(int(f), int(i)) for f, i in zip(sc.obs.frame, sc.obs.track_id, strict=True)}
    assert {(int(f), int(i)) for f, i in zip(tracks.frame, tracks.track_id, strict=True)} == annotated
    assert (tracks.n_views > 0).all()


def test_every_frame_interpolates_through_the_gap_with_an_sd_that_covers(gap: tuple[Path, Scene]) -> None:
    _, sc = gap
    plain = reconstruct(sc, "ukf")
    dense = reconstruct(sc, "ukf", every_frame=0)
    # every frame of the grid (step 1 here) from each object's first to its last annotation
    for i in np.unique(sc.obs.track_id):
        f = sc.obs.frame[sc.obs.track_id == i]
        np.testing.assert_array_equal(np.sort(dense.frame[dense.track_id == i]),
                                      np.arange(f.min(), f.max() + 1))
    inter = dense.n_views == 0
    spans = [(sc.obs.frame[sc.obs.track_id == i].min(), sc.obs.frame[sc.obs.track_id == i].max())
             for i in np.unique(sc.obs.track_id)]
    gap_frames = np.setdiff1d(np.arange(sc.obs.frame.min(), sc.obs.frame.max() + 1), sc.obs.frame)
    expected = sum(int(np.sum((gap_frames > a) & (gap_frames < b))) for a, b in spans)
    assert len(gap_frames) == 6 and inter.sum() == expected >= 12
    it, ig = match_rows(dense, sc.truth)
    e2 = dense.center_world[it, :2] - sc.truth.center_world[ig, :2]
    z2 = np.sum(e2**2 / dense.center_sd[it, :2] ** 2, axis=1)
    gone = inter[it]
    err = np.linalg.norm(e2, axis=1)
    assert np.mean(z2[gone] <= chi2.ppf(0.99, 2)) >= 0.9, np.mean(z2[gone] <= chi2.ppf(0.99, 2))
    assert err[gone].max() < 0.5, err[gone].max()  # 0.6 s of walking at most
    # the sd grows into the gap: larger on interpolated rows than on annotated ones
    assert np.median(dense.center_sd[inter, :2]) > 2 * np.median(dense.center_sd[~inter, :2])
    # on the annotated rows, the dense run agrees with the plain one
    a, b = match_rows(dense, plain)
    d = np.linalg.norm(dense.center_world[a] - plain.center_world[b], axis=1)
    assert len(b) == len(plain) and d.max() < 0.005, d.max()


def test_every_frame_step_and_the_csv_column(gap: tuple[Path, Scene], tmp_path: Path) -> None:
    root, sc = gap
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "d"), "--every-frame", "2",
                 "--quiet"]) == 0
    back = read_tracks_csv(tmp_path / "d" / "tracks.csv")
    assert (tmp_path / "d" / "tracks.csv").read_text().splitlines()[0].endswith(",n_views")
    annotated = np.unique(sc.obs.frame)
    grid = np.arange(annotated.min(), annotated.max() + 1, 2)
    assert set(np.unique(back.frame).tolist()) == set(grid.tolist()) | set(annotated.tolist())
    assert (back.n_views == 0).any() and (back.n_views >= 0).all()
    assert main(["reconstruct", str(root), "--out", str(tmp_path / "p"), "--quiet"]) == 0
    assert not (tmp_path / "p" / "tracks.csv").read_text().splitlines()[0].endswith(",n_views")
    assert (read_tracks_csv(tmp_path / "p" / "tracks.csv").n_views == -1).all()  # not recorded


def test_every_frame_needs_a_motion_model(gap: tuple[Path, Scene], tmp_path: Path,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    root, _ = gap
    out = tmp_path / "t"
    assert main(["reconstruct", str(root), "--out", str(out), "--every-frame", "--estimator",
                 "triangulation"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --every-frame: the triangulation estimator")
    assert not out.exists()


def test_a_turn_between_keyframes_is_spread_over_the_frames_between(tmp_path: Path) -> None:
    """Walkers who stop and turn, labelled at every third frame of 2 fps (keyframes 1.5 s apart):
    where a keyframe contradicts the prediction (a turn inside the gap), the frames between take
    the turn a little at a time. Before, the prediction was faded at the keyframe only and the
    frames between kept the old heading (a metre off at the frame before the keyframe)."""
    sc, sim = written_scene(tmp_path / "in", "native", seed=4, frames=40, people=8, noise_px=1.0,
                            motion="stop-and-turn", fps=2.0, errors=Errors(dropped=0.0))
    keys = np.unique(sc.obs.frame)[::3]
    sparse = dataclasses.replace(sc, obs=sc.obs.select(np.flatnonzero(np.isin(sc.obs.frame, keys))))
    dense = reconstruct(sparse, "ukf", every_frame=0)
    it, ig = match_rows(dense, sc.truth)
    inter = dense.n_views[it] == 0
    err = np.linalg.norm(dense.center_world[it, :2] - sc.truth.center_world[ig, :2], axis=1)
    # the truth's own path between the keyframes, straight: what any interpolation of them can do
    straight = np.zeros(len(it))
    for i in np.unique(dense.track_id[it]):
        m = sc.truth.track_id == i
        f, c = sc.truth.frame[m], sc.truth.center_world[m, :2]
        k = np.isin(f, keys)
        on = np.flatnonzero(dense.track_id[it] == i)
        q = dense.frame[it][on]
        lin = np.stack([np.interp(q, f[k], c[k, j]) for j in range(2)], 1)
        straight[on] = np.linalg.norm(lin - sc.truth.center_world[ig[on], :2], axis=1)
    assert inter.sum() > 100
    assert err[inter].max() < 1.5 * straight[inter].max(), (err[inter].max(), straight[inter].max())
    assert np.mean(err[inter]) < 1.5 * np.mean(straight[inter]), (err[inter].mean(), straight[inter].mean())
    z2 = np.sum((dense.center_world[it, :2] - sc.truth.center_world[ig, :2]) ** 2
                / dense.center_sd[it, :2] ** 2, axis=1)
    assert np.mean(z2[inter] <= chi2.ppf(0.99, 2)) >= 0.9


def test_bridged_rows_are_the_unseen_ones_of_short_gaps_between_views() -> None:
    from gt3dkit.api import bridged

    frame = np.array([0, 1, 2, 3, 4, 5, 6, 7, 8, 0, 1, 2])
    obj = np.array([1, 1, 1, 1, 1, 1, 1, 1, 1, 2, 2, 2])
    seen = np.array([1, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0], bool)
    # object 1: frame 1 (views 2 frames apart) bridged, 3-5 (views 4 apart) only at 4 frames, after
    # its last view never; object 2: before its first view and after its last, never
    assert bridged(frame, obj, seen, 3.0).tolist() == [0, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]
    assert bridged(frame, obj, seen, 4.0).tolist() == [0, 1, 0, 1, 1, 1, 0, 0, 0, 0, 0, 0]
    shuffled = np.random.default_rng(0).permutation(len(frame))
    assert np.array_equal(bridged(frame[shuffled], obj[shuffled], seen[shuffled], 4.0),
                          bridged(frame, obj, seen, 4.0)[shuffled])


@pytest.mark.parametrize("cut", [True, False])
def test_a_person_no_camera_labels_for_a_frame_keeps_a_row_where_labels_follow_visibility(
        tmp_path: Path, cut: bool) -> None:
    """Boxes drawn around what each camera sees (cut by nearer people, as a detector draws them):
    a person left out of every camera in one frame is hidden or missed, not gone: the default
    run bridges that frame (a row of n_views 0). Boxes of a shape placed in the world: the
    labeller says the person is not there: no row."""
    sc, _ = written_scene(tmp_path / "in", "native", seed=3, frames=12, people=30, noise_px=2.0,
                          motion="walk", errors=Errors(cut_by_nearer=cut, dropped=0.0))
    obs = sc.obs
    who = int(np.bincount(obs.track_id).argmax())
    frames = np.unique(obs.frame[obs.track_id == who])
    hole = int(frames[len(frames) // 2])
    keep = ~((obs.track_id == who) & (obs.frame == hole))
    sc = dataclasses.replace(sc, obs=obs.select(keep))
    tracks = reconstruct(sc, "ukf", out=tmp_path / "out")
    row = (tracks.frame == hole) & (tracks.track_id == who)
    assert row.sum() == (1 if cut else 0)
    if cut:
        assert tracks.n_views[row][0] == 0
        back = read_tracks_csv(tmp_path / "out" / "tracks.csv")
        assert int((back.n_views == 0).sum()) == int((tracks.n_views == 0).sum()) > 0
