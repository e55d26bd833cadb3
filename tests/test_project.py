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


@pytest.mark.parametrize("fmt", ["cvat", "mot", "coco"])
def test_project_round_trip(run, fmt: str, capsys) -> None:
    """Every label comes back as it was, proposals and interpolations come from the estimate,
    and reading the files back (the proposals accepted) gives the same estimate."""
    root, out = run
    dest = root / f"proj_{fmt}"
    assert main(["project", str(out), "--format", fmt, "--to", str(dest)]) == 0
    summary = json.loads((dest / "projection.json").read_text())
    assert summary["annotated"] > 0 and summary["proposed"] > 0 and summary["interpolated"] > 0
    assert summary["shapes"] == summary["annotated"] + summary["proposed"] + summary["interpolated"]
    back = root / f"back_{fmt}"
    assert main(["reconstruct", str(dest), "--out", str(back), "--every-frame",
                 "--association", str(dest / "association.csv")]) == 0
    a, b = read_result(out).tracks, read_result(back).tracks
    ka = {(int(f), int(i)): k for k, (f, i) in enumerate(zip(a.frame, a.track_id, strict=True))}
    kb = {(int(f), int(i)): k for k, (f, i) in enumerate(zip(b.frame, b.track_id, strict=True))}
    assert set(ka) == set(kb)
    ia, ib = (np.array([k[key] for key in sorted(ka)]) for k in (ka, kb))
    d = np.linalg.norm(a.center_world[ia] - b.center_world[ib], axis=1)
    sd = np.linalg.norm(a.center_sd[ia], axis=1)
    # the estimate comes back to under 1 mm in the median, at most about one sd (the accepted proposals
    # change the labels' fitted noise level and the process noise found): issue 24's 1 mm
    # everywhere is not reached yet
    assert np.median(d) < 0.001 and (d / sd).max() < 1.5, (np.median(d), (d / sd).max())


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
