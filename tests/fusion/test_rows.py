"""fusion.preparation.rows: the object-frame table every estimator works on, against a brute-force build of
the same table from the observations, one Python dict entry at a time."""

from __future__ import annotations

import dataclasses

import numpy as np

from gt3dkit.fusion.preparation.rows import build_rows, usable_edges
from gt3dkit.sim import Errors
from tests.scenes import written_scene


def test_rows_are_the_observations_laid_out(tmp_path) -> None:
    """Every object has a row for every frame of the scene from its first to its last
    annotation (gaps included), rows sorted by frame then object; each (row, camera) holds that
    camera's box (or NaN), its usable edges (not within 1 px of the border), the observation's
    row, and the chains ``prev_row``/``next_row`` link an object's rows in frame order."""
    scene, _ = written_scene(tmp_path, "native", seed=7, frames=12, people=6, noise_px=1.0,
                             errors=Errors(dropped=0.3))
    # one object with a frame missing in the middle of its annotations (a gap row)
    obs = scene.obs
    pid = int(obs.track_id[0])
    fr = np.unique(obs.frame[obs.track_id == pid])
    drop = (obs.track_id == pid) & (obs.frame == fr[len(fr) // 2])
    scene = dataclasses.replace(scene, obs=obs.select(~drop))
    obs = scene.obs
    rows = build_rows(scene)
    frames = list(np.asarray(scene.frames))
    # brute force: the expected rows in order, and each (frame, id, camera) -> observation row
    expect = []
    for t, f in enumerate(frames):
        for o, i in enumerate(np.unique(obs.track_id)):
            seen = obs.frame[obs.track_id == i]
            if seen.min() <= f <= seen.max():
                expect.append((t, o))
    assert list(zip(rows.row_t.tolist(), rows.row_o.tolist(), strict=True)) == expect
    keys = zip(obs.frame, obs.track_id, obs.cam, strict=True)
    at = {(int(f), int(i), int(c)): k for k, (f, i, c) in enumerate(keys)}
    wh = scene.rig.wh
    for r, (t, o) in enumerate(expect):
        f, i = frames[t], int(rows.obj_ids[o])
        for c in range(len(scene.rig.cameras)):
            k = at.get((f, i, c), -1)
            assert rows.obs_row[r, c] == k
            if k < 0:
                assert np.isnan(rows.box_z[r, c]).all() and not rows.box_mask[r, c].any()
            else:
                np.testing.assert_array_equal(rows.box_z[r, c], obs.box_xyxy_px[k])
                np.testing.assert_array_equal(rows.box_mask[r, c],
                                              usable_edges(obs.box_xyxy_px[k][None], wh[c:c + 1], 1.0)[0])
        mine = [q for q, (tq, oq) in enumerate(expect) if oq == o]
        pos = mine.index(r)
        assert rows.prev_row[r] == (mine[pos - 1] if pos else -1)
        assert rows.next_row[r] == (mine[pos + 1] if pos + 1 < len(mine) else -1)
    assert np.array_equal(rows.n_views, (rows.obs_row >= 0).sum(axis=1))
    assert any(rows.n_views == 0)  # the gap row is there, seen by no camera
    for t in range(len(frames)):
        want = {r for r, (tr, _) in enumerate(expect) if tr == t}
        assert set(range(rows.t_start[t], rows.t_start[t + 1])) == want
