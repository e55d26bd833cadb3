"""`gt3d report`: the HTML report and its pictures (open3d renders run in a child process)."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gt3dkit.sim import Errors, simulate, simulate_skeletons, write_scene, write_skeleton_scene
from gt3dkit.viz.render3d import Drawing, RenderError, View, render, unit_sphere

GT3D = [sys.executable, "-m", "gt3dkit.cli"]


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*GT3D, *args], capture_output=True, text=True)


def _read_png(path: Path) -> np.ndarray:
    import matplotlib.image as mpimg

    return mpimg.imread(path)


def _check_page(report: Path) -> list[str]:
    """Every picture the page references exists beside it (relative paths); returns them."""
    page = (report / "index.html").read_text()
    srcs = re.findall(r'src="([^"]+)"', page)
    assert srcs
    for s in srcs:
        assert not s.startswith(("/", "http")), s
        assert (report / s).is_file(), s
    return srcs


def test_render_matches_the_pinhole() -> None:
    """A ball rendered by open3d lands where View.project puts its centre (labels drawn by
    matplotlib on top depend on it), from an oblique view."""
    d = Drawing()
    V, F = unit_sphere()
    X = np.array([1.5, -0.7, 0.4])
    d.add_mesh(V * 0.08 + X, F, (1.0, 0.0, 0.0))
    d.add_lines(np.array([[0, 0, 0], [1, 0, 0.0]]), [(0, 1)], (0.0, 0.0, 1.0))
    view = View(eye=np.array([-3.0, -4.0, 3.0]), centre=np.array([0.5, 0.0, 0.0]), up=np.array([0, 0, 1.0]),
                width=640, height=480)
    img = render(d, view).astype(float)
    red = (img[..., 0] > 150) & (img[..., 1] < 90) & (img[..., 2] < 90)
    assert red.sum() > 20
    v, u = np.nonzero(red)
    (pu, pv), = view.project(X[None])
    assert abs(u.mean() - pu) < 2.0 and abs(v.mean() - pv) < 2.0, (u.mean(), v.mean(), pu, pv)
    blue = (img[..., 2] > 150) & (img[..., 0] < 90)
    assert blue.any()  # the line set is drawn too


@pytest.fixture(scope="module")
def box_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = Path(tmp_path_factory.mktemp("report_boxes"))
    sim = simulate("wildtrack", seed=4, frames=12, people=4, noise_px=1.0,
                   errors=Errors(dropped=0.0, hide_covered=0.5, shifted=0.01))
    write_scene(sim, root / "in", "wildtrack")
    r = _run("reconstruct", str(root / "in"), "--out", str(root / "out"))
    assert r.returncode == 0, r.stderr
    return root


def test_report_of_a_box_run(box_run: Path) -> None:
    out = box_run / "out"
    r = _run("report", str(out))
    assert r.returncode == 0, r.stderr
    assert "warning" not in r.stderr and "Traceback" not in r.stderr
    report = out / "report"
    assert str(report / "index.html") in r.stdout
    srcs = _check_page(report)
    for name in ("overview.png", "closeup.png", "residuals.png", "tracks.png", "camera_00.png"):
        assert name in srcs
    # the overview shows the objects in their colours (tab10), not an empty canvas
    img = _read_png(report / "overview.png")[..., :3]
    assert img.shape[0] > 200 and img.shape[1] > 400
    assert (np.abs(img - img[0, 0]).sum(axis=-1) > 0.3).mean() > 0.01
    # one picture per anomaly row (up to the cap), each of the views involved
    flagged = (out / "anomalies.csv").read_text().strip().splitlines()[1:]
    assert flagged
    assert len(list((report / "anomalies").glob("*.png"))) == min(len(flagged), 60)
    # a second report replaces the first whole; the input folder is untouched
    before = sorted(p.name for p in (box_run / "in").rglob("*"))
    assert _run("report", str(out)).returncode == 0
    assert sorted(p.name for p in (box_run / "in").rglob("*")) == before
    assert not [p for p in out.iterdir() if p.name.startswith(".report")]


def test_report_of_a_keypoint_run_and_a_comparison(tmp_path: Path, box_run: Path) -> None:
    sk = simulate_skeletons("native", seed=2, frames=8, people=2, cameras=5, noise_px=1.0,
                            errors=Errors(outliers=0.01))
    write_skeleton_scene(sk, tmp_path / "in", "native")
    assert _run("reconstruct", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--estimator",
                "triangulation").returncode == 0
    r = _run("report", str(tmp_path / "out"))
    assert r.returncode == 0, r.stderr
    srcs = _check_page(tmp_path / "out" / "report")
    assert len(srcs) >= 4 and "closeup.png" in srcs
    page = (tmp_path / "out" / "report" / "index.html").read_text()
    assert "Keypoint noise learnt from the data" in page and "<td>nose</td>" in page.lower()
    r = _run("compare", str(box_run / "in"), "--out", str(tmp_path / "cmp"), "--no-progress")
    assert r.returncode == 0, r.stderr
    r = _run("report", str(tmp_path / "cmp"))
    assert r.returncode == 0, r.stderr
    srcs = _check_page(tmp_path / "cmp" / "report")
    assert "side_by_side.png" in srcs and "disagreement.png" in srcs
    assert any(s.endswith("/overview.png") for s in srcs)


def test_report_errors(tmp_path: Path, box_run: Path) -> None:
    r = _run("report", str(tmp_path))
    assert r.returncode == 2 and r.stderr.startswith("error: ") and len(r.stderr.splitlines()) == 1
    assert "no tracks.csv" in r.stderr
    # the input moved away since the run: named, no half-written report
    moved = tmp_path / "copy"
    shutil.copytree(box_run / "out", moved / "out")
    shutil.copytree(box_run / "in", moved / "in")
    meta = (moved / "out" / "meta.json").read_text().replace(str((box_run / "in").resolve()),
                                                             str((moved / "in2").resolve()))
    (moved / "out" / "meta.json").write_text(meta)
    shutil.rmtree(moved / "out" / "report", ignore_errors=True)
    r = _run("report", str(moved / "out"))
    assert r.returncode == 2 and "is not there any more" in r.stderr, r.stderr
    assert not (moved / "out" / "report").exists()


def test_a_failed_render_is_a_warning_not_a_lost_report(box_run: Path, tmp_path: Path, monkeypatch) -> None:
    from gt3dkit.viz import overview, report

    def broken(*a, **k):
        raise RenderError("open3d failed (no EGL display)")

    monkeypatch.setattr(overview, "Rendering", broken)
    out = tmp_path / "out"
    shutil.copytree(box_run / "out", out)
    index, warnings = report.write_report(out)
    assert len(warnings) == 1 and "overview.png, closeup.png not made" in warnings[0]
    assert "no EGL display" in warnings[0]
    page = index.read_text()
    assert "no EGL display" in page and "camera_00.png" in page


def test_a_huge_sd_reads_back(tmp_path: Path) -> None:
    """A one-view row's sd can exceed any world coordinate (depth left open): what the writer
    writes, the readers (report, evaluate) read."""
    from gt3dkit.io.writers import read_tracks_csv, write_tracks_csv
    from gt3dkit.types import TrackSet

    n = 2
    tr = TrackSet(frame=np.array([0, 1]), track_id=np.array([3, 3]), center_world=np.ones((n, 3)),
                  semi_axes=np.full((n, 3), 0.3), center_sd=np.array([[0.01] * 3, [2e6, 3e7, 0.5]]),
                  n_views=np.array([2, 1]), kpt_world=np.zeros((n, 0, 3)), kpt_sd=np.zeros((n, 0)))
    write_tracks_csv(tmp_path / "tracks.csv", tr)
    back = read_tracks_csv(tmp_path / "tracks.csv")
    assert np.allclose(back.center_sd, tr.center_sd, rtol=1e-6)
