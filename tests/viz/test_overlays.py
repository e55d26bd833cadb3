"""`gt3d report OUT --frames SOURCE`: the estimate drawn over the cameras' own frames, an H.264
video per camera (:mod:`gt3dkit.viz.overlays`)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from gt3dkit.api import load_run
from gt3dkit.geom.camera import project_points
from gt3dkit.sim import Errors, simulate_skeletons, write_skeleton_scene

GT3D = [sys.executable, "-m", "gt3dkit.cli"]
GREY = 90


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*GT3D, *args], capture_output=True, text=True)


def _video(path: Path, n: int, wh: tuple[int, int]) -> None:
    import imageio_ffmpeg

    w = imageio_ffmpeg.write_frames(str(path), wh, fps=10.0, codec="libx264", pix_fmt_in="bgr24",
                                    macro_block_size=2, ffmpeg_log_level="error")
    w.send(None)
    for _ in range(n):
        w.send(np.full((wh[1], wh[0], 3), GREY, np.uint8))
    w.close()


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """A 3-camera skeleton scene (frames 0-9), its run, and its frames: camera 0 a video, camera
    1 an image folder, camera 2 a video in its own folder."""
    root = Path(tmp_path_factory.mktemp("overlays"))
    sk = simulate_skeletons("native", seed=5, frames=10, people=1, cameras=3, noise_px=3.0, fps=10.0,
                            errors=Errors(outliers=0.03))
    assert sk.frames.min() >= 0
    write_skeleton_scene(sk, root / "in", "native")
    r = _run("reconstruct", str(root / "in"), "--out", str(root / "out"), "--quiet")
    assert r.returncode == 0, r.stderr
    frames = root / "frames"
    (frames / sk.rig.names[1]).mkdir(parents=True)
    (frames / sk.rig.names[2]).mkdir()
    n = int(sk.frames.max()) + 1
    wh = (sk.rig.cameras[0].width, sk.rig.cameras[0].height)
    _video(frames / f"{sk.rig.names[0]}.mp4", n, wh)
    for f in range(n):
        cv2.imwrite(str(frames / sk.rig.names[1] / f"img{f}.png"), np.full((wh[1], wh[0], 3), GREY, np.uint8))
    _video(frames / sk.rig.names[2] / "any_name.mp4", n, wh)
    return root, frames


def _frame(path: Path, k: int) -> np.ndarray:
    cap = cv2.VideoCapture(str(path))
    img = None
    for _ in range(k + 1):
        ok, img = cap.read()
        assert ok
    cap.release()
    assert img is not None
    return img


def test_the_overlay_draws_the_estimate_and_the_labels_where_they_are(run: tuple[Path, Path]) -> None:
    root, frames = run
    out = root / "out"
    r = _run("report", str(out), "--frames", str(frames), "--overlay-width", "4000", "--quiet")
    assert r.returncode == 0 and "warning" not in r.stderr, r.stderr
    page = (out / "report" / "index.html").read_text()
    assert "Overlays on your frames" in page and 'src="overlays/' in page
    # each flagged frame's still, linked from the anomaly table
    links = re.findall(r'<a href="(overlays/stills/[^"]+)">on your frame</a>', page)
    rows = (out / "anomalies.csv").read_text().splitlines()[1:]
    flagged = {(r.split(",")[0], r.split(",")[1]) for r in rows if r.split(",")[1]}
    assert links and len(set(links)) == len(flagged), (len(links), flagged)
    assert all((out / "report" / s).is_file() for s in links)
    res = load_run(out, "test")
    sc, tr = res.scene, res.tracks
    checked = 0
    for c, cam in enumerate(sc.rig.cameras):
        video = out / "report" / "overlays" / f"{cam.name}.mp4"
        cap = cv2.VideoCapture(str(video))
        assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == int(sc.frames.max()) + 1  # the source's
        cap.release()
        f = int(sc.frames[len(sc.frames) // 2])
        img = _frame(video, f).astype(int)
        row = np.flatnonzero(tr.frame == f)[0]
        uv, depth = project_points(tr.kpt_world[row], sc.rig.K[c:c + 1], sc.rig.dist[c:c + 1],
                                   sc.rig.R[c:c + 1], sc.rig.t[c:c + 1])
        labels = sc.obs.kpt_uv_px[(sc.obs.frame == f) & (sc.obs.cam == c)].reshape(-1, 2)
        labels = labels[np.isfinite(labels).all(axis=1)]
        for j, p in enumerate(uv[:, 0]):
            # a joint's disc where no label cross reaches: the track's colour (magenta)
            inside = np.isfinite(p).all() and 5 <= p[0] < cam.width - 5 and 5 <= p[1] < cam.height - 5
            if not inside or (labels.size and np.min(np.abs(labels - p).max(axis=1)) < 6):
                continue
            b, g, rr = img[int(round(p[1])), int(round(p[0]))]
            assert b > 150 and rr > 150 and g < 110, (cam.name, j, (b, g, rr))
            checked += 1
        for p in labels:  # a label's cross: green
            b, g, rr = img[int(round(p[1])), int(round(p[0]))]
            assert g > 140 and b < 110 and rr < 110, (cam.name, (b, g, rr))
    assert checked >= 3


def test_frames_that_do_not_fit_are_one_line_and_nothing_is_written(run: tuple[Path, Path],
                                                                     tmp_path: Path) -> None:
    root, frames = run
    out = root / "out"
    res = load_run(out, "test")
    names = res.scene.rig.names
    n = int(res.scene.frames.max()) + 1
    wh = (res.scene.rig.cameras[0].width, res.scene.rig.cameras[0].height)
    report_before = sorted(p.name for p in (out / "report").rglob("*")) if (out / "report").exists() else []

    def refused(src: Path, *extra: str) -> str:
        r = _run("report", str(out), "--frames", str(src), "--quiet", *extra)
        one_line = r.stderr.startswith("error: ") and len(r.stderr.splitlines()) == 1
        assert r.returncode == 2 and one_line, r.stderr
        after = sorted(p.name for p in (out / "report").rglob("*")) if (out / "report").exists() else []
        assert after == report_before
        return r.stderr

    short = tmp_path / "short"
    short.mkdir()
    _video(short / f"{names[0]}.mp4", n - 3, wh)
    err = refused(short)
    assert f"{names[0]}.mp4" in err and "3 more" in err and "--frame-offset" in err
    err = refused(frames, "--frame-offset", "5")
    assert "5 more" in err
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / f"{names[0]}.mp4").write_text("not a video")
    assert "cannot be decoded" in refused(broken)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "no camera's frames" in refused(empty)
    small = tmp_path / "small"
    small.mkdir()
    _video(small / f"{names[0]}.mp4", n, (320, 240))
    assert "320 x 240" in refused(small)


def test_a_camera_without_frames_among_others_is_a_warning(run: tuple[Path, Path], tmp_path: Path) -> None:
    root, frames = run
    out = root / "out"
    res = load_run(out, "test")
    names = res.scene.rig.names
    one = tmp_path / "one"
    one.mkdir()
    (one / f"{names[0]}.mp4").symlink_to(frames / f"{names[0]}.mp4")
    r = _run("report", str(out), "--frames", str(one), "--overlay-step", "2", "--overlay-width", "640",
             "--quiet")
    assert r.returncode == 0, r.stderr
    said = [w for w in r.stderr.splitlines() if w.startswith("warning: ")]
    assert len(said) == 2 and all("its overlay is left out" in w for w in said)
    videos = sorted(p.name for p in (out / "report" / "overlays").glob("*.mp4"))
    assert videos == [f"{names[0]}.mp4"]
    stills = {p.name.split("_")[0] for p in (out / "report" / "overlays").glob("stills/*.jpg")}
    assert stills <= {names[0].split("_")[0]}  # only the camera with frames has stills
    cap = cv2.VideoCapture(str(out / "report" / "overlays" / videos[0]))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == -(-(int(res.scene.frames.max()) + 1) // 2)
    assert int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == 640
    cap.release()


def test_the_scene_page_in_a_real_browser(run: tuple[Path, Path]) -> None:
    """``report/scene.html`` in headless Chromium (``make setup`` installs it): it loads from
    ``file://`` with no console error and no request leaving the machine; moving the slider
    changes the 3D view and the camera images; hovering an object shows its id."""
    from gt3dkit.viz.browser import browser_available, check_scene_page

    root, frames = run
    out = root / "out"
    r = _run("report", str(out), "--frames", str(frames), "--overlay-width", "640", "--quiet")
    assert r.returncode == 0, r.stderr
    page = out / "report" / "scene.html"
    assert 'href="scene.html"' in (out / "report" / "index.html").read_text()
    text = page.read_text()
    assert "https://" not in text.split("<script type='text/javascript'>", 2)[-1]  # our part: no URL
    if not browser_available():
        pytest.fail("headless Chromium is not installed: make setup installs chromium and chromium-driver")
    seen = check_scene_page(page)
    assert seen.console_errors == [] and seen.requests_away == [], (seen.console_errors, seen.requests_away)
    assert seen.frames[0] != seen.frames[1] and seen.canvas_changed
    assert seen.video_times[0] != seen.video_times[1] and len(seen.video_times[1]) == 3
    assert seen.hover.startswith("id "), seen.hover


def test_the_overlays_drawn_by_a_dask_cluster_are_the_local_ones(run: tuple[Path, Path]) -> None:
    """``--scheduler``: each camera's overlay drawn by a worker of a local Dask cluster on loopback:
    the same videos' frames and stills as drawn here."""
    distributed = pytest.importorskip("distributed")
    root, frames = run
    out = root / "out"
    r = _run("report", str(out), "--frames", str(frames), "--overlay-width", "640", "--quiet")
    assert r.returncode == 0, r.stderr
    local = {p.name: p.read_bytes() for p in (out / "report" / "overlays").rglob("*.jpg")}
    counts = {p.name: int(cv2.VideoCapture(str(p)).get(cv2.CAP_PROP_FRAME_COUNT))
              for p in (out / "report" / "overlays").glob("*.mp4")}
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        r = _run("report", str(out), "--frames", str(frames), "--overlay-width", "640", "--quiet",
                 "--scheduler", cluster.scheduler_address)
    assert r.returncode == 0, r.stderr
    assert {p.name: p.read_bytes() for p in (out / "report" / "overlays").rglob("*.jpg")} == local
    assert {p.name: int(cv2.VideoCapture(str(p)).get(cv2.CAP_PROP_FRAME_COUNT))
            for p in (out / "report" / "overlays").glob("*.mp4")} == counts
    r = _run("report", str(out), "--scheduler", "127.0.0.1:1", "--quiet")
    assert r.returncode == 2 and "give --frames" in r.stderr
