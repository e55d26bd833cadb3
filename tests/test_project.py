"""gt3d project: the estimate drawn back into the cameras as CVAT, MOTChallenge and COCO labels."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.cli import main
from gt3dkit.io.results import read_result
from gt3dkit.sim import Errors, simulate, write_scene


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A reconstructed box scene with views left out (proposals) and a gap (interpolations)."""
    root = Path(tmp_path_factory.mktemp("project"))
    sim = simulate("native", seed=5, frames=16, people=4, noise_px=0.5,
                   errors=Errors(missing=0.1, gap=(6, 8), dropped=0.1))
    write_scene(sim, root / "in", "native")
    assert main(["reconstruct", str(root / "in"), "--out", str(root / "out"), "--every-frame"]) == 0
    return root, root / "out"


def _same_rows(a, b) -> tuple[np.ndarray, np.ndarray]:
    """The row indices of the tracks ``a`` and ``b`` for the same (frame, id), asserting they
    have the same rows."""
    ka = {(int(f), int(i)): k for k, (f, i) in enumerate(zip(a.frame, a.track_id, strict=True))}
    kb = {(int(f), int(i)): k for k, (f, i) in enumerate(zip(b.frame, b.track_id, strict=True))}
    assert set(ka) == set(kb)
    return (np.array([k[key] for key in sorted(ka)]) for k in (ka, kb))


@pytest.mark.parametrize("fmt", ["cvat", "mot", "coco"])
def test_project_round_trip(run, fmt: str, capsys) -> None:
    """Every label comes back as it was; the drawn shapes nobody changed are left out (they are
    the estimate's own projection): reading the files back gives the same estimate."""
    root, out = run
    dest = root / f"proj_{fmt}"
    assert main(["project", str(out), "--format", fmt, "--to", str(dest)]) == 0
    summary = json.loads((dest / "projection.json").read_text())
    assert summary["annotated"] > 0 and summary["proposed"] > 0 and summary["interpolated"] > 0
    assert summary["shapes"] == summary["annotated"] + summary["proposed"] + summary["interpolated"]
    back = root / f"back_{fmt}"
    capsys.readouterr()
    assert main(["reconstruct", str(dest), "--out", str(back), "--every-frame",
                 "--association", str(dest / "association.csv")]) == 0
    drawn = summary["proposed"] + summary["interpolated"]
    assert f"{drawn} " in capsys.readouterr().err  # the warning counts what it left out
    a, b = read_result(out).tracks, read_result(back).tracks
    ia, ib = _same_rows(a, b)
    np.testing.assert_allclose(b.center_world[ib], a.center_world[ia], atol=1e-4)  # 0.1 mm
    np.testing.assert_allclose(b.center_sd[ib], a.center_sd[ia], rtol=1e-3)


def test_a_moved_proposal_is_a_label_and_cvat_renumbering_keeps_ids(run, capsys) -> None:
    """CVAT numbers tracks 0, 1, ... on export: the track_id attribute keeps the run's ids. A
    proposal an annotator moved comes back as a label (and moves the estimate)."""
    root, out = run
    dest = root / "moved"
    assert main(["project", str(out), "--format", "cvat", "--to", str(dest)]) == 0
    moved = None
    for path in sorted((dest / "cvat").glob("*.xml")):
        doc = ET.parse(path)
        for k, track in enumerate(doc.getroot().iter("track")):
            track.set("id", str(k))  # as CVAT's export numbers them
            for box in track.findall("box"):
                src = {a.get("name"): a.text for a in box.findall("attribute")}["source"]
                if moved is None and src == "proposed" and box.get("outside") == "0":
                    moved = (int(box.get("frame")), int(track.findall("box")[0].find(
                        "attribute[@name='gt3d_id']").text))
                    box.set("xtl", str(float(box.get("xtl")) + 1.0))
                    box.set("xbr", str(float(box.get("xbr")) + 1.0))
        doc.write(path)
    assert moved is not None
    back = root / "moved_back"
    capsys.readouterr()
    assert main(["reconstruct", str(dest), "--out", str(back), "--every-frame", "--association",
                 str(dest / "association.csv")]) == 0
    a, b = read_result(out).tracks, read_result(back).tracks
    ia, ib = _same_rows(a, b)
    d = np.linalg.norm(a.center_world[ia] - b.center_world[ib], axis=1)
    key = np.c_[a.frame[ia], a.track_id[ia]]
    at = np.flatnonzero((key == moved).all(axis=1))
    # the moved box is a label: the estimate follows it there most; elsewhere it barely moves
    # (the labels' noise level changes a little), and the ids are the run's
    assert len(at) == 1 and d[at[0]] > 1e-4 and d[at[0]] > 2 * np.median(d)
    assert np.median(d) < 1e-3


def test_cvat_tracks_end_and_carry_attributes(run) -> None:
    root, out = run
    dest = root / "cvat_attr"
    assert main(["project", str(out), "--format", "cvat", "--to", str(dest), "--every-frame"]) == 0
    for path in (dest / "cvat").glob("*.xml"):
        doc = ET.parse(path).getroot()
        assert doc.findtext("version") == "1.1" and doc.find("meta/task/mode").text == "interpolation"
        for track in doc.iter("track"):
            boxes = track.findall("box")
            assert boxes[-1].get("outside") == "1"  # a track ends, CVAT does not carry it on
            frames = [int(b.get("frame")) for b in boxes]
            assert frames == sorted(frames) and len(set(frames)) == len(frames)
            for b in boxes:
                attrs = {a.get("name"): a.text or "" for a in b.findall("attribute")}
                assert attrs["source"] in ("annotated", "proposed", "interpolated")
                assert attrs["gt3d_id"] == track.get("id")
                assert float(attrs["sd_px"]) >= 0 and 0 < float(attrs["confidence"]) <= 1


def test_only_flagged_keeps_what_needs_a_person(run) -> None:
    root, out = run
    dest = root / "flagged"
    assert main(["project", str(out), "--format", "mot", "--to", str(dest), "--only-flagged"]) == 0
    s = json.loads((dest / "projection.json").read_text())
    assert s["annotated"] <= s["flagged"]
    assert s["proposed"] > 0


@pytest.mark.parametrize("args,problem", [
    (["--format", "cvat", "--cameras", "nope"], "no camera 'nope'"),
    (["--format", "tiff"], "invalid choice"),
])
def test_project_bad_options(run, args: list[str], problem: str, capsys) -> None:
    root, out = run
    dest = root / "bad"
    assert main(["project", str(out), "--to", str(dest), *args]) == 2
    assert problem in capsys.readouterr().err
    assert not dest.exists()


def test_project_refuses_a_folder_that_is_not_a_run_and_the_input(run, capsys) -> None:
    root, out = run
    assert main(["project", str(root / "in"), "--format", "mot", "--to", str(root / "x")]) == 2
    assert "not a gt3d" in capsys.readouterr().err
    assert main(["project", str(out), "--format", "mot", "--to", str(root / "in" / "x")]) == 2
    assert "input folder" in capsys.readouterr().err
    assert not (root / "x").exists() and not (root / "in" / "x").exists()


LABELS_PY = Path(__file__).resolve().parents[1] / ".venv-labels" / "bin" / "python"


@pytest.mark.skipif(not LABELS_PY.exists(), reason="datumaro's own environment: make labels-env "
                                                    "(make test builds it)")
def test_datumaro_reads_every_cvat_shape_and_attribute(run) -> None:
    """datumaro (CVAT's own import and export) finds every shape gt3d project wrote, at its
    frame, with its box and every attribute."""
    import subprocess

    root, out = run
    dest = root / "dm"
    assert main(["project", str(out), "--format", "cvat", "--to", str(dest), "--every-frame"]) == 0
    res = subprocess.run([str(LABELS_PY), str(Path(__file__).with_name("peer_datumaro.py")),
                          str(dest / "cvat")], capture_output=True, text=True, check=False)
    assert res.returncode == 0, res.stderr[-2000:]
    seen = json.loads(res.stdout)
    names = {"source", "anomalies", "sd_px", "confidence", "gt3d_id", "segment", "drawn_digest",
             "track_id", "occluded"}
    ours: dict[str, list[tuple]] = {}
    for path in (dest / "cvat").glob("*.xml"):
        for track in ET.parse(path).getroot().iter("track"):
            for b in track.findall("box"):
                if b.get("outside") == "0":
                    ours.setdefault(path.stem, []).append(
                        (int(b.get("frame")), int(track.get("id")),
                         tuple(round(float(b.get(k)), 2) for k in ("xtl", "ytl", "xbr", "ybr")),
                         b.find("attribute[@name='source']").text))
    assert sum(len(v) for v in ours.values()) == json.loads((dest / "projection.json").read_text())["shapes"]
    assert set(seen) == set(ours)
    for cam, shapes in seen.items():
        assert all(s["type"] == "bbox" and names <= set(s["attributes"]) for s in shapes)
        theirs = sorted((s["frame"], int(s["attributes"]["track_id"]), tuple(round(v, 2) for v in s["box"]),
                         s["attributes"]["source"]) for s in shapes)
        assert theirs == sorted(ours[cam]), cam


def test_pycocotools_reads_every_coco_shape(tmp_path) -> None:
    """pycocotools (the COCO API) reads the files of a keypoint run: every shape per camera,
    its keypoints (x, y, v per joint), bbox, track id, score and attributes."""
    from pycocotools.coco import COCO

    from gt3dkit.sim import simulate_skeletons, write_skeleton_scene

    sim = simulate_skeletons("native", seed=3, frames=6, people=2, cameras=4, noise_px=0.5)
    write_skeleton_scene(sim, tmp_path / "in", "native")
    assert main(["reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert main(["project", str(tmp_path / "out"), "--format", "coco", "--to", str(tmp_path / "p")]) == 0
    summary = json.loads((tmp_path / "p" / "projection.json").read_text())
    total = 0
    for path in sorted((tmp_path / "p" / "coco").glob("*.json")):
        coco = COCO(str(path))
        cat = coco.loadCats(coco.getCatIds())[0]
        J = len(cat["keypoints"])
        assert J == 19 and len(cat["skeleton"]) > 0
        anns = coco.loadAnns(coco.getAnnIds())
        total += len(anns)
        for a in anns:
            assert len(a["keypoints"]) == 3 * J
            assert a["num_keypoints"] == sum(v > 0 for v in a["keypoints"][2::3])
            assert a["image_id"] in coco.imgs and len(a["bbox"]) == 4 and 0 < a["score"] <= 1
            assert {"source", "sd_px", "gt3d_id", "drawn_digest"} <= set(a["attributes"])
            assert isinstance(a["track_id"], int)
    assert total == summary["shapes"] > 0


def test_keypoint_round_trip_through_coco(tmp_path, capsys) -> None:
    """A keypoint run's COCO files read back give the same joints: the bbox COCO needs, drawn by
    gt3d around a keypoint label that had none, is not read back as a box label (bbox_digest),
    and a bbox an annotator moved is."""
    from gt3dkit.sim import simulate_skeletons, write_skeleton_scene

    sim = simulate_skeletons("native", seed=3, frames=8, people=2, cameras=4, noise_px=0.5)
    write_skeleton_scene(sim, tmp_path / "in", "native")
    assert main(["reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--quiet"]) == 0
    assert main(["project", str(tmp_path / "out"), "--format", "coco", "--to", str(tmp_path / "p")]) == 0
    assert main(["reconstruct", str(tmp_path / "p"), "--out", str(tmp_path / "back"), "--quiet",
                 "--association", str(tmp_path / "p" / "association.csv")]) == 0
    a, b = read_result(tmp_path / "out").tracks, read_result(tmp_path / "back").tracks
    ia, ib = _same_rows(a, b)
    np.testing.assert_allclose(b.kpt_world[ib], a.kpt_world[ia], atol=1e-4)  # 0.1 mm
    # an annotator draws a box of their own on one annotation: it is a box label again
    path = sorted((tmp_path / "p" / "coco").glob("*.json"))[0]
    doc = json.loads(path.read_text())
    ann = next(x for x in doc["annotations"] if x["attributes"]["source"] == "annotated")
    ann["bbox"] = [v + 3.0 for v in ann["bbox"]]
    path.write_text(json.dumps(doc))
    from gt3dkit.api import load_scene

    obs = load_scene(tmp_path / "p", association=tmp_path / "p" / "association.csv").obs
    assert np.isfinite(obs.box_xyxy_px).all(axis=1).sum() == 1
