"""Review on the pictures (issue 67's targets, the part built so far): the overlay videos and the
3D page in a real browser.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/review_targets.py [--data ../shared/data]

On the shared mouse (``sleap_minimal_session``, its PROVENANCE.md: 4 cameras, 120 frames, the
proofread SLEAP labels and the mouse videos; anipose's calibration in mm with its copied
``side`` camera, so ``--refine-calib``): ``gt3d reconstruct``, then the overlays of
``gt3d report --frames`` (:mod:`gt3dkit.viz.overlays`), timed on their own, and per camera

* the overlay has the source video's frame count;
* at frames 10, 60 and 110, the pixel at each projected joint whose disc no label cross reaches
  is the track's colour (magenta), and the pixel at each label is the label's (green), H.264's
  loss allowed for;
* the whole ``gt3d report --frames`` as a user runs it (a process), timed;
* its ``scene.html`` in headless Chromium through selenium (:mod:`gt3dkit.viz.browser`): no console
  error, no request leaving the machine, the slider changes the 3D view and the camera images,
  hovering an object shows its id; the same for CMC3's boxes (``cmc3_detector_boxes``, 15 people,
  no frames of its own) where present;
* a simulated 4 000-frame box scene (6 cameras, 5 people): ``gt3d report``'s peak memory (the
  child's maximum resident set) and time.

Prints each target with PASS or FAIL; exit status 1 when one fails.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gt3dkit.api import load_run  # noqa: E402
from gt3dkit.geom.camera import project_points  # noqa: E402
from gt3dkit.viz.browser import browser_available, check_scene_page  # noqa: E402
from gt3dkit.viz.overlays import OverlayOptions, prepared_sources, write_overlays  # noqa: E402

GT3D = str(Path(sys.executable).with_name("gt3d"))
RESULTS: list[tuple[str, bool]] = []


def check(what: str, ok: bool, detail: str) -> None:
    RESULTS.append((what, ok))
    print(f"  target {what}: {detail} {'PASS' if ok else 'FAIL'}")


def colours_at(video: Path, frames: tuple[int, ...], out: Path, cam: int) -> tuple[int, int, int, int]:
    """At ``frames`` of ``video``: (joints checked, of them the track's colour, labels checked, of
    them the label's colour)."""
    run = load_run(out, "the overlays are checked against the run")
    sc, tr = run.scene, run.tracks
    c = sc.rig.cameras[cam]
    cap = cv2.VideoCapture(str(video))
    got = {}
    k = 0
    while True:
        ok, img = cap.read()
        if not ok:
            break
        if k in frames:
            got[k] = img.astype(int)
        k += 1
    cap.release()
    nj = okj = nl = okl = 0
    for f, img in got.items():
        labels = sc.obs.kpt_uv_px[(sc.obs.frame == f) & (sc.obs.cam == cam)].reshape(-1, 2)
        labels = labels[np.isfinite(labels).all(axis=1)]
        for r in np.flatnonzero(tr.frame == f):
            uv, _ = project_points(tr.kpt_world[r], sc.rig.K[cam:cam + 1], sc.rig.dist[cam:cam + 1],
                                   sc.rig.R[cam:cam + 1], sc.rig.t[cam:cam + 1])
            for p in uv[:, 0]:
                inside = np.isfinite(p).all() and 5 <= p[0] < c.width - 5 and 5 <= p[1] < c.height - 5
                if not inside or (labels.size and np.min(np.abs(labels - p).max(axis=1)) < 6):
                    continue
                b, g, r_ = img[int(round(p[1])), int(round(p[0]))]
                nj += 1
                okj += bool(b > 150 and r_ > 150 and g < 110)
        for p in labels:
            b, g, r_ = img[int(round(p[1])), int(round(p[0]))]
            nl += 1
            okl += bool(g > 140 and b < 110 and r_ < 110)
    return nj, okj, nl, okl


def browse(name: str, page: Path, cameras: int) -> None:
    """The page in headless Chromium, as a reviewer would try it."""
    if not browser_available():
        check(f"{name} in headless Chromium", False, "chromium or chromium-driver missing (make setup)")
        return
    seen = check_scene_page(page)
    mb = page.stat().st_size / 1e6
    print(f"  {name}: {mb:.1f} MB, loaded in {seen.load_s:.1f} s")
    check(f"{name}: no console error, no request leaving the machine",
          not seen.console_errors and not seen.requests_away, f"{seen.console_errors} {seen.requests_away}")
    moved = seen.canvas_changed and seen.frames[0] != seen.frames[1]
    check(f"{name}: the slider changes the 3D view", moved,
          f"frame {seen.frames[0]} -> {seen.frames[1]}, canvas "
          + ("changed" if seen.canvas_changed else "same"))
    if cameras:
        check(f"{name}: ... and the camera images", seen.video_times[0] != seen.video_times[1]
              and len(seen.video_times[1]) == cameras,
              f"overlay times {seen.video_times[0][:1]} -> {seen.video_times[1][:1]} ({cameras} cameras)")
    check(f"{name}: hovering an object shows its id", seen.hover.startswith("id "), repr(seen.hover))


def long_report() -> None:
    """The report of a simulated 4 000-frame box scene: its peak memory and time."""
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        subprocess.run([GT3D, "simulate", "--kind", "boxes", "--frames", "4000", "--people", "5", "--seed",
                        "1", "--out", str(tmp / "in")], capture_output=True, check=True)
        subprocess.run([GT3D, "reconstruct", str(tmp / "in"), "--out", str(tmp / "out"), "--quiet"],
                       capture_output=True, check=True)
        # the report alone in a process of its own, whose children's peak is the report's
        probe = ("import resource, subprocess, sys; r = subprocess.run(sys.argv[1:], capture_output=True); "
                 "print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)")
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", probe, GT3D, "report", str(tmp / "out"), "--quiet"],
                           capture_output=True, text=True)
        sec = time.perf_counter() - t0
        code, peak_kb = (int(x) for x in p.stdout.split())
        mb = (tmp / "out" / "report" / "scene.html").stat().st_size / 1e6 if code == 0 else 0.0
        print(f"a simulated 4 000-frame box scene: gt3d report {sec:.1f} s, scene.html {mb:.1f} MB")
        check("its report in at most 1 GB", code == 0 and peak_kb <= 1024 * 1024,
              f"peak resident {peak_kb / 1024:.0f} MB")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = ap.parse_args()
    data = args.data / "sleap_minimal_session"
    if not data.is_dir():
        print(f"skipped: {data} absent")
        return 0
    with tempfile.TemporaryDirectory() as tmp_s:
        out = Path(tmp_s) / "mouse"
        p = subprocess.run([GT3D, "reconstruct", str(data), "--out", str(out), "--calib-units", "mm",
                            "--refine-calib", "--quiet"], capture_output=True, text=True)
        if p.returncode != 0:
            print(f"reconstruct failed: {p.stderr.strip()}")
            return 1
        run = load_run(out, "the overlays")
        opts = OverlayOptions(data)
        t0 = time.perf_counter()
        sources, _ = prepared_sources(run.scene, opts)
        videos, _ = write_overlays(run.scene, run.tracks, run.anomalies, sources, opts,
                                   Path(tmp_s) / "overlays", progress=False)
        sec = time.perf_counter() - t0
        print(f"the shared mouse: {len(videos)} cameras, {sum(v.frames for v in videos)} frames drawn")
        check("overlays of 4 x 120 frames in <= 20 s", sec <= 20.0, f"{sec:.1f} s")
        for v in videos:
            cam = run.scene.rig.index(v.camera)
            src = next(s for s in sources if s.camera == v.camera)
            check(f"{v.camera}: the source's frame count", v.frames == src.n_frames,
                  f"{v.frames} of {src.n_frames}, {v.width} x {v.height} px")
            nj, okj, nl, okl = colours_at(Path(tmp_s) / v.file, (10, 60, 110), out, cam)
            check(f"{v.camera}: joints in the track's colour, labels in the label's",
                  okj == nj > 0 and okl == nl > 0,
                  f"{okj} of {nj} joints, {okl} of {nl} labels at frames 10, 60, 110")
        t0 = time.perf_counter()
        p = subprocess.run([GT3D, "report", str(out), "--frames", str(data), "--quiet"], capture_output=True,
                           text=True)
        print(f"  gt3d report --frames (the whole report, a process): {time.perf_counter() - t0:.1f} s, "
              f"exit {p.returncode}{': ' + p.stderr.strip() if p.returncode else ''}")
        browse("the mouse's scene.html", out / "report" / "scene.html", cameras=4)
        cmc3 = args.data / "cmc3_detector_boxes"
        if cmc3.is_dir():
            boxes = Path(tmp_s) / "cmc3"
            subprocess.run([GT3D, "reconstruct", str(cmc3), "--out", str(boxes), "--quiet"],
                           capture_output=True)
            subprocess.run([GT3D, "report", str(boxes), "--quiet"], capture_output=True)
            browse("CMC3's scene.html", boxes / "report" / "scene.html", cameras=0)
    long_report()
    failed = [w for w, ok in RESULTS if not ok]
    print(f"\n{len(RESULTS) - len(failed)} of {len(RESULTS)} targets met")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
