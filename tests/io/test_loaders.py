"""Loaders: the real MultiviewX subset, and round trips of simulated scenes in every layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gt3dkit.api import load_scene
from gt3dkit.calib.formats.grid import MULTIVIEWX, WILDTRACK
from gt3dkit.errors import InputError
from gt3dkit.geom.camera import Cams
from gt3dkit.geom.conics import ellipsoid_boxes
from gt3dkit.io.datasets import detect_layout, native
from gt3dkit.sim import Errors, simulate_skeletons, write_skeleton_scene
from tests.scenes import written_scene


def test_multiviewx_subset(multiviewx) -> None:
    s = multiviewx
    assert s.layout == "multiviewx" and s.rig.names == [f"Camera{i}" for i in range(1, 7)]
    assert len(s.frames) == 10 and len(s.truth.frame) == 434
    assert s.obs.has_box.all() and len(s.obs) == 2126
    # Unity's left-handed world: every calibration sees the scene at negative Z_cam
    assert np.all(s.rig.depth_sign == -1)
    centres = np.stack([c.center_world for c in s.rig.cameras])
    np.testing.assert_allclose(centres[:, 2], 2.5, atol=0.01)
    # positionID 243441 -> (441/40, 243/40) m
    xy = MULTIVIEWX.position_to_xy(np.array([243441]))
    np.testing.assert_allclose(xy, [[11.025, 6.075]])
    assert s.truth.source.startswith("multiviewx")


def test_grid_positions_round_trip() -> None:
    for g in (WILDTRACK, MULTIVIEWX):
        pos = np.array([0, 1, 12345, 200_000])
        np.testing.assert_array_equal(g.xy_to_position(g.position_to_xy(pos)), pos)
    np.testing.assert_allclose(WILDTRACK.position_to_xy(np.array([481])), [[-2.975, -8.975]])


@pytest.mark.parametrize("layout", ["native", "wildtrack", "multiviewx"])
def test_simulated_layout_round_trip(tmp_path: Path, layout: str) -> None:
    scene, sim = written_scene(tmp_path, layout, seed=1, frames=5, people=3, errors=Errors(dropped=0.2))
    assert detect_layout(tmp_path) == layout
    assert scene.rig.names == [c.name for c in sim.rig.cameras]
    for a, b in zip(scene.rig.cameras, sim.rig.cameras, strict=True):
        np.testing.assert_allclose(a.K, b.K)
        np.testing.assert_allclose(a.R, b.R, atol=1e-9)
        np.testing.assert_allclose(a.t, b.t, atol=1e-9)
        assert a.depth_sign == 1.0
    # every simulated box comes back in the same (frame, camera, id) slot
    seen = np.isfinite(sim.boxes[..., 0])
    assert len(scene.obs) == seen.sum()
    expect = sim.boxes[seen]
    if layout == "multiviewx":  # loader adds back the generator's truncation bias
        expect = expect + 0.5
    i, c = np.nonzero(seen)
    order = np.lexsort((sim.truth_id[i], c, sim.truth_frame[i]))
    np.testing.assert_allclose(scene.obs.box_xyxy_px, expect[order])
    np.testing.assert_array_equal(scene.obs.frame, sim.truth_frame[i][order])
    np.testing.assert_allclose(scene.truth.center_world, sim.center_world, atol=1e-6)


def test_simulated_boxes_are_projections_of_the_truth(tmp_path: Path) -> None:
    scene, sim = written_scene(tmp_path, "native", seed=2, frames=3, people=2, errors=Errors(dropped=0.0))
    cams = Cams.of(scene.rig)
    box, _ = ellipsoid_boxes(sim.center_world, sim.semi_axes, cams.world_from_body, cams.K,
                             cams.dist, cams.R, cams.t)
    seen = np.isfinite(sim.boxes)
    inside = seen & (sim.boxes > 0.5) & (sim.boxes < 1918)
    assert np.abs(sim.boxes[inside] - box[inside]).max() <= 0.5 + 1e-9


def test_detect_layout_rejects_unknown(tmp_path: Path) -> None:
    from gt3dkit.errors import InputError

    with pytest.raises(InputError, match="unknown input layout"):
        load_scene(tmp_path)


def test_wildtrack_plain_text_extrinsics(tmp_path: Path) -> None:
    """WILDTRACK's own extr_*.xml hold rvec/tvec as plain number lists, in centimetres."""
    import cv2

    scene, sim = written_scene(tmp_path, "wildtrack", seed=1, frames=3, people=2)
    cam = sim.rig.cameras[2]
    rvec, _ = cv2.Rodrigues(cam.R)
    p = tmp_path / "calibrations" / "extrinsic" / f"extr_{cam.name}.xml"
    p.write_text('<?xml version="1.0" encoding="UTF-8"?>\n<opencv_storage>\n'
                 f"<rvec>{' '.join(f'{v:.12g}' for v in rvec.ravel())}</rvec>\n"
                 f"<tvec>{' '.join(f'{v:.12g}' for v in cam.t * 100)}</tvec>\n"
                 "</opencv_storage>\n")
    again = load_scene(tmp_path)
    np.testing.assert_allclose(again.rig.cameras[2].R, cam.R, atol=1e-9)
    np.testing.assert_allclose(again.rig.cameras[2].t, cam.t, atol=1e-9)


def _native_keypoints(root: Path, rows: list[str], conf: bool = False) -> Path:
    """A native skeleton scene's folder with ``rows`` of ``keypoints.csv`` (cameras of a simulated one)."""
    sim = simulate_skeletons("native", seed=2, frames=2, people=1, cameras=4)
    write_skeleton_scene(sim, root, "native")
    (root / "keypoints.csv").write_text("frame,camera,id,joint,u,v" + (",conf" if conf else "") + "\n"
                                        + "".join(r + "\n" for r in rows))
    return root


@pytest.mark.parametrize("block", [3, 65536])
def test_keypoints_read_in_blocks_as_row_by_row(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 block: int) -> None:
    """keypoints.csv read in checked blocks gives the scene the row-by-row reader gives (rows, origins,
    confidences, undetected points skipped), and a bad row or a point given twice, in one block or
    across two, is reported at its own line."""
    monkeypatch.setattr(native, "KEYPOINT_BLOCK_ROWS", block)
    sim = simulate_skeletons("native", seed=2, frames=6, people=2, noise_px=1.0, cameras=4)
    write_skeleton_scene(sim, tmp_path / "a", "native")
    head, *body = (tmp_path / "a" / "keypoints.csv").read_text().splitlines()
    rng = np.random.default_rng(0)
    for order, lines in (("as written", body), ("shuffled", [body[k] for k in rng.permutation(len(body))]),
                         ("joint-major", sorted(body, key=lambda r: int(r.split(",")[3])))):
        # a block's points are gathered into rows, whatever order the file holds them in
        (tmp_path / "a" / "keypoints.csv").write_text("\n".join([head, *lines]) + "\n")
        fast = load_scene(tmp_path / "a")
        with monkeypatch.context() as m:
            m.setattr(native, "_checked_keypoints", lambda *a: None)  # every block row by row
            slow = load_scene(tmp_path / "a")
        for k in ("frame", "cam", "track_id"):
            np.testing.assert_array_equal(getattr(fast.obs, k), getattr(slow.obs, k))
        np.testing.assert_array_equal(fast.obs.kpt_uv_px, slow.obs.kpt_uv_px)
        assert fast.obs.origin == slow.obs.origin, order
    monkeypatch.undo()
    monkeypatch.setattr(native, "KEYPOINT_BLOCK_ROWS", block)
    cam = sim.rig.names[0]
    ok = [f"{f},{c},1,{j},100.5,200.25,{p}" for f, j, p in ((0, 0, 0.9), (0, 1, 0.0), (0, 2, 1), (1, 0, 0.5))
          for c in sim.rig.names[:2]]  # lines 2-9
    s = load_scene(_native_keypoints(tmp_path / "c", ok, conf=True))
    assert len(s.obs) == 4 and s.obs.kpt_conf is not None
    np.testing.assert_allclose(s.obs.kpt_conf[0, :3], [0.9, np.nan, 1.0])
    assert any("2 keypoints with confidence 0" in w for w in s.warnings)
    assert s.obs.origin[0].endswith("keypoints.csv: line 2")
    # a detector's heatmap peak above 1 (OpenPose writes up to ~1.04): read as 1, one warning
    s = load_scene(_native_keypoints(tmp_path / "peak", ok[:1] + [f"1,{cam},1,3,10,20,1.03"] + ok[1:],
                                     conf=True))
    assert s.obs.kpt_conf is not None and np.nanmax(s.obs.kpt_conf) == 1.0
    said = [w for w in s.warnings if "confidence above 1" in w]
    assert len(said) == 1 and "1 keypoint(s)" in said[0] and "up to 1.03" in said[0], s.warnings
    for rows, line, what in (
            (ok + [f"0,{cam},1,2,1,1,0.5"], 10, "second keypoint 2 for object 1 in frame 0"),
            (ok[:1] + [f"0,{cam},1,0,1,1,0.5"] + ok[1:], 3, "second keypoint 0 for object 1 in frame 0"),
            (ok + [f"1,{cam},1,0,1e9,20,0.5"], 10, "far outside"),
            (ok + [f"1,{cam},1,0,10,20,2.5"], 10, "confidence must be in [0, 1]"),
            (ok + ["1,nosuch,1,0,10,20,1"], 10, "unknown camera 'nosuch'"),
            (ok + [f"1,{cam},1.5,0,10,20,1"], 10, "id must be an integer")):
        with pytest.raises(InputError) as e:
            load_scene(_native_keypoints(tmp_path / f"e{line}{what[:4]}", rows, conf=True))
        assert e.value.where.endswith(f"keypoints.csv: line {line}") and what in e.value.problem, str(e.value)


@pytest.mark.parametrize("block", [5, 65536])
def test_boxes_read_in_blocks_as_row_by_row(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                            block: int) -> None:
    """boxes.csv read in checked blocks gives the scene the row-by-row reader gives (rows, boxes,
    origins, boxes of -1s skipped with their warning), and a bad row or a box given twice, in one
    block or across two, is reported at its own line as the row-by-row reader reports it."""
    monkeypatch.setattr(native, "KEYPOINT_BLOCK_ROWS", block)
    fast, _ = written_scene(tmp_path / "a", "native", seed=3, frames=6, people=4, noise_px=1.0)
    monkeypatch.setattr(native, "_checked_boxes", lambda *a: None)  # every block row by row
    slow = load_scene(tmp_path / "a")
    for k in ("frame", "cam", "track_id", "box_xyxy_px"):
        np.testing.assert_array_equal(getattr(fast.obs, k), getattr(slow.obs, k))
    assert fast.obs.origin == slow.obs.origin and len(fast.obs) > 20
    assert fast.obs.origin[3] == slow.obs.origin[3] and ": line " in fast.obs.origin[3]
    monkeypatch.undo()
    monkeypatch.setattr(native, "KEYPOINT_BLOCK_ROWS", block)
    text = (tmp_path / "a" / "boxes.csv").read_text().splitlines()
    head, body = text[0], text[1:12]
    cam = body[0].split(",")[1]
    for extra, what in ((body[2], "second box for object"), (f"0,{cam},7,10,10,5,20", "degenerate box"),
                        (f"0,{cam},7,10,10,1e9,20", "far outside"),
                        ("0,nosuch,7,10,10,50,60", "unknown camera"),
                        (f"0,{cam},7.5,10,10,50,60", "id must be an integer")):
        root = tmp_path / f"e{what[:6]}"
        root.mkdir()
        (root / "cameras.json").write_text((tmp_path / "a" / "cameras.json").read_text())
        (root / "boxes.csv").write_text("\n".join([head, *body, f"0,{cam},9,-1,-1,-1,-1", extra]) + "\n")
        with pytest.raises(InputError) as e:
            load_scene(root)
        assert e.value.where.endswith(f"boxes.csv: line {len(body) + 3}"), str(e.value)
        assert what in e.value.problem, str(e.value)
    (root / "boxes.csv").write_text("\n".join([head, *body, f"0,{cam},9,-1,-1,-1,-1"]) + "\n")
    s = load_scene(root)
    assert len(s.obs) == len(body) and any("1 boxes of -1s read as not seen" in w for w in s.warnings)


def test_wildtrack_rows_keep_their_entry(tmp_path: Path) -> None:
    """A WILDTRACK-layout frame file's boxes (added as one checked block) name their file, person
    and view; a second file of the same frame number giving a person again is reported."""
    scene, _ = written_scene(tmp_path / "w", "wildtrack", seed=3, frames=4, people=3, noise_px=1.0)
    o = scene.obs
    k = len(o) - 1
    assert o.origin[k].endswith(f": personID {o.track_id[k]}, viewNum {o.cam[k]}"), o.origin[k]
    ann = sorted((tmp_path / "w" / "annotations_positions").glob("*.json"))
    (ann[0].with_name("0" + ann[0].name)).write_text(ann[0].read_text())  # frame 0 again
    with pytest.raises(InputError) as e:
        load_scene(tmp_path / "w")
    assert "second" in e.value.problem, str(e.value)
