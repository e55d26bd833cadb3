"""Each kind of bad input: one clear line naming file and entry, exit 2, nothing written."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.cli import main
from gt3dkit.sim import Errors

from .scenes import written_scene


def _run(tmp_path: Path, src: Path, capsys) -> tuple[int, str, Path]:
    out = tmp_path / "out"
    code = main(["reconstruct", str(src), "--out", str(out)])
    err = capsys.readouterr().err
    return code, err, out


def _check(code: int, err: str, out: Path, *needles: str) -> None:
    assert code == 2
    assert err.startswith("error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    for n in needles:
        assert n in err, (n, err)
    assert not out.exists()


@pytest.fixture
def native(tmp_path: Path) -> Path:
    root = tmp_path / "in"
    written_scene(root, "native", seed=0, frames=4, people=2, errors=Errors(dropped=0.0))
    return root


@pytest.fixture
def wild(tmp_path: Path) -> Path:
    root = tmp_path / "in"
    written_scene(root, "wildtrack", seed=0, frames=3, people=2, errors=Errors(dropped=0.0))
    return root


def _append_box_row(root: Path, row: str) -> int:
    p = root / "boxes.csv"
    lines = p.read_text().splitlines()
    lines.append(row)
    p.write_text("\n".join(lines) + "\n")
    return len(lines)


def test_malformed_cameras_json(tmp_path, native, capsys) -> None:
    (native / "cameras.json").write_text('{"cameras": [')
    _check(*_run(tmp_path, native, capsys), "cameras.json", "malformed JSON")


def test_camera_without_rotation_matrix(tmp_path, native, capsys) -> None:
    doc = json.loads((native / "cameras.json").read_text())
    doc["cameras"][1]["R"] = [[1, 0, 0], [0, 1, 0], [0, 0, 2]]
    (native / "cameras.json").write_text(json.dumps(doc))
    _check(*_run(tmp_path, native, capsys), "cameras.json", "cam1", "rotation")


def test_malformed_csv_value(tmp_path, native, capsys) -> None:
    line = _append_box_row(native, "0,cam0,0,10,20,abc,40")
    _check(*_run(tmp_path, native, capsys), "boxes.csv", f"line {line}", "malformed")


def test_field_longer_than_csv_reads(tmp_path, native, capsys) -> None:
    """A number of 200 000 digits: numpy reads it, Python's csv reader (row by row, for the
    checks) refuses it; one line naming the file and line (a regression: it was an internal error)."""
    line = _append_box_row(native, "0,cam0,9,10,20,30," + "4" * 200_000)
    _check(*_run(tmp_path, native, capsys), "boxes.csv", f"line {line}", "field larger than field limit")


def test_wrong_csv_header(tmp_path, native, capsys) -> None:
    p = native / "boxes.csv"
    p.write_text("frame,cam,id\n" + "\n".join(p.read_text().splitlines()[1:]))
    _check(*_run(tmp_path, native, capsys), "boxes.csv", "expected header")


def test_unknown_camera(tmp_path, native, capsys) -> None:
    line = _append_box_row(native, "0,cam99,0,10,20,30,40")
    _check(*_run(tmp_path, native, capsys), "boxes.csv", f"line {line}", "unknown camera 'cam99'")


@pytest.mark.parametrize("box", ["30,20,30,40", "30,20,10,40", "10,50,30,40"])
def test_degenerate_box(tmp_path, native, capsys, box) -> None:
    line = _append_box_row(native, f"0,cam0,7,{box}")
    _check(*_run(tmp_path, native, capsys), "boxes.csv", f"line {line}", "degenerate box")


@pytest.mark.parametrize("value", ["nan", "inf"])
def test_non_finite_box(tmp_path, native, capsys, value) -> None:
    line = _append_box_row(native, f"0,cam0,7,10,20,{value},40")
    _check(*_run(tmp_path, native, capsys), "boxes.csv", f"line {line}", "non-finite")


def test_duplicate_box(tmp_path, native, capsys) -> None:
    first = (native / "boxes.csv").read_text().splitlines()[1]
    line = _append_box_row(native, first)
    _check(*_run(tmp_path, native, capsys), "boxes.csv", f"line {line}", "second box")


def test_box_of_an_object_behind_the_camera(tmp_path, native, capsys) -> None:
    """A camera facing away from the scene claims to see object 0."""
    doc = json.loads((native / "cameras.json").read_text())
    cam = dict(doc["cameras"][0])
    R = np.array(cam["R"])
    C = -R.T @ np.array(cam["t"])
    flip = np.diag([-1.0, 1.0, -1.0])  # turn around the camera's own y axis
    R2 = flip @ R
    cam.update(name="backwards", R=R2.tolist(), t=(-R2 @ C).tolist())
    doc["cameras"].append(cam)
    (native / "cameras.json").write_text(json.dumps(doc))
    line = _append_box_row(native, "0,backwards,0,900,400,1000,700")
    _check(*_run(tmp_path, native, capsys), "boxes.csv", f"line {line}", "behind camera backwards")


def test_missing_calibration_file(tmp_path, wild, capsys) -> None:
    (wild / "calibrations" / "extrinsic" / "extr_CVLab3.xml").unlink()
    _check(*_run(tmp_path, wild, capsys), "extr_CVLab3.xml", "missing calibration file")


def test_view_without_calibration(tmp_path, wild, capsys) -> None:
    (wild / "calibrations" / "extrinsic" / "extr_CVLab3.xml").unlink()
    (wild / "calibrations" / "intrinsic_zero" / "intr_CVLab3.xml").unlink()
    _check(*_run(tmp_path, wild, capsys), "annotations_positions", "viewNum 2",
           "no calibration for camera CVLab3")


def test_malformed_xml(tmp_path, wild, capsys) -> None:
    (wild / "calibrations" / "intrinsic_zero" / "intr_CVLab1.xml").write_text("<opencv_storage><ca")
    _check(*_run(tmp_path, wild, capsys), "intr_CVLab1.xml")


def test_unknown_view_number(tmp_path, wild, capsys) -> None:
    p = sorted((wild / "annotations_positions").glob("*.json"))[0]
    people = json.loads(p.read_text())
    people[0]["views"].append({"viewNum": 9, "xmin": 1, "ymin": 2, "xmax": 30, "ymax": 40})
    p.write_text(json.dumps(people))
    _check(*_run(tmp_path, wild, capsys), p.name, "viewNum 9", "unknown camera")


def test_nan_in_annotation_json(tmp_path, wild, capsys) -> None:
    p = sorted((wild / "annotations_positions").glob("*.json"))[1]
    people = json.loads(p.read_text())
    people[1]["views"][0].update(xmin=float("nan"), ymin=3)
    p.write_text(json.dumps(people))  # json writes NaN, which Python's json reads back
    _check(*_run(tmp_path, wild, capsys), p.name, f"personID {people[1]['personID']}",
           "non-finite")


def test_truncated_annotation_json(tmp_path, wild, capsys) -> None:
    p = sorted((wild / "annotations_positions").glob("*.json"))[0]
    p.write_text(p.read_text()[:100])
    _check(*_run(tmp_path, wild, capsys), p.name, "malformed JSON")


def test_failed_run_leaves_existing_output_untouched(tmp_path, native, capsys) -> None:
    out = tmp_path / "out"
    assert main(["reconstruct", str(native), "--out", str(out), "--estimator",
                 "triangulation"]) == 0
    before = (out / "tracks.csv").read_text()
    _append_box_row(native, "0,cam0,7,30,20,30,40")
    assert main(["reconstruct", str(native), "--out", str(out)]) == 2
    assert (out / "tracks.csv").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "out"]  # no temp dirs left
