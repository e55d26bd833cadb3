"""Boxes as detectors draw them (the box-misfit issue's targets), on real CMC1 detector boxes:

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/drawn_targets.py [--data ../shared/data]

``../shared/data/cmc1_detector_boxes`` (research use, not bundled; its PROVENANCE.md): real
Faster R-CNN boxes around 3 people in 4 cameras at 4 fps, the dataset's 3D truth and the dataset
authors' own tracker output. Per estimator (``gt3d reconstruct``'s pipeline) and for the authors'
tracker, per frame each truth person is matched to the nearest estimate on the floor (Hungarian,
1 m gate; the same rule for every row of the table), and

* the ground distance to the truth centre: mean, median, p95, worst;
* the ratio to the per-frame fit (``triangulation``);
* MOTA (CLEAR-MOT, 1 m) and the truth person-frames with a row;
* the annotation QA of the UKF run: the share of boxes flagged, and the first flags;
* the truth's own jitter: how far the truth lies from a smooth path through itself
  (Savitzky-Golay, 2nd order, 9 frames = 2.25 s), the floor below which no smooth estimate
  of a walker's path can be scored, whatever its boxes;
* the CMC1 truth paths drawn as exact ellipsoid boxes with 3 px noise into the same four
  cameras (3 seeds): the smoother against the per-frame fit where the truth walks;
* a simulated crowd (WILDTRACK rig, 30 walkers, 2 px) with its boxes drawn around the visible
  body (``Errors(cut_by_nearer=True)``, 3 seeds): the UKF with the cut edges handled
  (:mod:`gt3dkit.fusion.preparation.occlusion`), reading them as the person's edges, and on whole boxes.

Prints each target with PASS or FAIL; exit status 1 when one fails.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.signal import savgol_filter

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gt3dkit.api import annotation_qa, load_scene, reconstruct, with_box_model  # noqa: E402
from gt3dkit.eval.metrics import box_errors  # noqa: E402
from gt3dkit.eval.tracking import tracking_scores  # noqa: E402
from gt3dkit.fusion.preparation.boxfit import state_boxes  # noqa: E402
from gt3dkit.geom.camera import Cams  # noqa: E402
from gt3dkit.sim import Errors, simulate, write_scene  # noqa: E402
from gt3dkit.types import GroundTruth, Observations, Scene, TrackSet  # noqa: E402

ESTIMATORS = ("ukf", "gtsam", "triangulation")
GATE_M = 1.0
RESULTS: list[tuple[str, bool]] = []


def check(what: str, ok: bool, detail: str) -> None:
    RESULTS.append((what, ok))
    print(f"  target {what}: {detail} {'PASS' if ok else 'FAIL'}")


def ground_errors(frame_e: np.ndarray, xy_e: np.ndarray, frame_t: np.ndarray, xy_t: np.ndarray
                  ) -> np.ndarray:
    """Per truth row the floor distance (m) to the estimate a per-frame Hungarian assignment
    (``GATE_M`` gate) gives it; inf where none. ``xy_* (N, 2)`` floor coordinates."""
    out = np.full(len(frame_t), np.inf)
    for f in np.unique(frame_t):
        ti, ei = np.flatnonzero(frame_t == f), np.flatnonzero(frame_e == f)
        if not ei.size:
            continue
        D = np.linalg.norm(xy_t[ti, None] - xy_e[None, ei], axis=-1)
        r, c = linear_sum_assignment(np.where(D <= GATE_M, D, 1e6))
        ok = D[r, c] <= GATE_M
        out[ti[r[ok]]] = D[r[ok], c[ok]]
    return out


def peer_tracks(path: Path, like: TrackSet) -> TrackSet:
    """The authors' tracker output (``frame id -1 x5 x y z x_half y_half z_half``) as a TrackSet."""
    a = np.loadtxt(path, ndmin=2)
    n = len(a)
    return dataclasses.replace(like, frame=a[:, 0].astype(np.int64), track_id=a[:, 1].astype(np.int64),
                               center_world=a[:, 7:10], semi_axes=a[:, 10:13],
                               center_sd=np.full((n, 3), np.nan),
                               n_views=np.zeros(n, np.int64), kpt_world=np.zeros((n, 0, 3)),
                               kpt_sd=np.zeros((n, 0)))


def row(name: str, tracks: TrackSet, truth: GroundTruth) -> dict[str, float]:
    e = ground_errors(tracks.frame, tracks.center_world[:, :2], truth.frame, truth.center_world[:, :2])
    ok = np.isfinite(e)
    mota = 100 * float(tracking_scores(tracks, truth, np.array([0.0, 0.0, 1.0]))["mota"])
    out = {"mean": 1000 * e[ok].mean(), "median": 1000 * np.median(e[ok]),
           "p95": 1000 * np.percentile(e[ok], 95),
           "worst": 1000 * e[ok].max(), "cover": 100 * ok.mean(), "mota": mota}
    print(f"  {name:<22}{out['mean']:8.1f}{out['median']:8.1f}{out['p95']:8.1f}{out['worst']:8.0f}"
          f"{out['cover']:8.1f}{out['mota']:8.2f}")
    return out


def truth_jitter(truth: GroundTruth, window: int = 9) -> float:
    """Mean floor distance (m) of the truth from a Savitzky-Golay path through itself."""
    d = []
    for i in np.unique(truth.track_id):
        m = np.flatnonzero(truth.track_id == i)
        m = m[np.argsort(truth.frame[m])]
        if len(m) > window:
            xy = truth.center_world[m, :2]
            d.append(np.linalg.norm(savgol_filter(xy, window, 2, axis=0) - xy, axis=1))
    return float(np.mean(np.concatenate(d)))


def exact_boxes(scene: Scene, seed: int, noise_px: float = 3.0, dropped: float = 0.1) -> Scene:
    """``scene``'s truth ellipsoids drawn as exact tangent boxes into its cameras, each edge with
    ``noise_px`` Gaussian noise, clipped at the border, a ``dropped`` share of views left out."""
    rng = np.random.default_rng(seed)
    cams = Cams.of(scene.rig)
    t = scene.truth
    box = state_boxes(t.center_world, np.log(t.semi_axes), cams)  # (M, C, 4)
    M, C = box.shape[:2]
    cam = np.tile(np.arange(C), M)
    b = box.reshape(-1, 4) + rng.normal(0.0, noise_px, (M * C, 4))
    W, H = cams.wh[cam, 0] - 1.0, cams.wh[cam, 1] - 1.0
    seen = np.isfinite(b).all(axis=1) & (b[:, 2] > 0) & (b[:, 0] < W) & (b[:, 3] > 0) & (b[:, 1] < H)
    b = np.c_[np.maximum(b[:, 0], 0), np.maximum(b[:, 1], 0), np.minimum(b[:, 2], W), np.minimum(b[:, 3], H)]
    keep = seen & (rng.uniform(size=M * C) >= dropped)
    obs = Observations(np.repeat(t.frame, C)[keep], cam[keep], np.repeat(t.track_id, C)[keep], b[keep],
                       np.zeros((int(keep.sum()), 0, 2)), ["exact boxes"] * int(keep.sum()))
    return with_box_model(dataclasses.replace(scene, obs=obs), "ellipsoid")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    args = ap.parse_args()
    root = args.data / "cmc1_detector_boxes"
    if not root.is_dir():
        print(f"skipped: {root} absent")
        return 0
    scene = load_scene(root)
    truth = scene.truth
    print(f"CMC1 real detector boxes: {len(scene.obs)} boxes, {len(truth.frame)} truth person-frames; "
          "ground distance to the truth centre (mm)")
    print(f"  {'estimator':<22}{'mean':>8}{'median':>8}{'p95':>8}{'worst':>8}{'rows%':>8}{'MOTA':>8}")
    res, runs = {}, {}
    for name in ESTIMATORS:
        runs[name] = reconstruct(scene, name)
        res[name] = row(name, runs[name], truth)
    peer = sorted((root / "reference_estimates").glob("*.txt"))
    if peer:
        row("authors' tracker", peer_tracks(peer[0], runs["ukf"]), truth)
    jit = truth_jitter(truth)
    print(f"  the truth's own jitter: {1000 * jit:.1f} mm mean from a smooth path through itself "
          "(Savitzky-Golay, 9 frames): the floor a smooth estimate is scored against")
    u, tri = res["ukf"], res["triangulation"]
    check("CMC1 UKF mean <= 55 mm", u["mean"] <= 55, f"{u['mean']:.1f} mm")
    check("CMC1 UKF p95 <= 100 mm", u["p95"] <= 100, f"{u['p95']:.1f} mm")
    check("CMC1 UKF mean <= 0.75 x the per-frame fit", u["mean"] <= 0.75 * tri["mean"],
          f"{u['mean'] / tri['mean']:.3f}")
    check("CMC1 UKF MOTA 100", u["mota"] >= 100 - 1e-9, f"{u['mota']:.2f}")
    check("CMC1 UKF every truth person-frame has a row", u["cover"] >= 100 - 1e-9, f"{u['cover']:.1f} %")
    qa = annotation_qa(scene, runs["ukf"])
    counts = qa.counts()
    per_box = sum(v for k, v in counts.items() if k in ("shifted_box", "size_outlier"))
    check("CMC1 QA flags <= 2 % of boxes", per_box <= 0.02 * len(scene.obs),
          f"{per_box} of {len(scene.obs)} ({100 * per_box / len(scene.obs):.2f} %; {counts})")
    shown = [a for a in qa.rows if a[4] in ("shifted_box", "size_outlier", "cut_box")]
    for frame, cam, oid, _, kind, _, detail in shown[:8]:
        print(f"    {kind} frame {frame} id {oid} camera {cam}: {detail}")
    print("\nCMC1 truth paths as exact ellipsoid boxes, 3 px noise, 10 % of views left out "
          "(ground distance, mm):")
    m = {"ukf": [], "triangulation": []}
    for seed in range(3):
        sc = exact_boxes(scene, seed)
        for name in m:
            tr = reconstruct(sc, name)
            e = ground_errors(tr.frame, tr.center_world[:, :2], truth.frame, truth.center_world[:, :2])
            m[name].append(1000 * e[np.isfinite(e)].mean())
        print(f"  seed {seed}: UKF {m['ukf'][-1]:.2f}, per-frame fit {m['triangulation'][-1]:.2f}")
    check("exact CMC1 paths: the smoother below the per-frame fit",
          float(np.mean(m["ukf"])) < float(np.mean(m["triangulation"])),
          f"{np.mean(m['ukf']):.2f} vs {np.mean(m['triangulation']):.2f} mm")
    print("\nSimulated crowd, boxes drawn around the visible body (WILDTRACK rig, 30 walkers, 12 frames, "
          "2 px; UKF ground error, mm):")
    handled, as_whole, whole = "cut edges handled", "cut edges read as the person's", "whole boxes"
    crowd: dict[str, list[float]] = {handled: [], as_whole: [], whole: []}
    for seed in range(3):
        with tempfile.TemporaryDirectory() as d:
            for cut, names in ((True, (handled, as_whole)), (False, (whole,))):
                sim = simulate("wildtrack", seed=seed, frames=12, people=30, noise_px=2.0, motion="walk",
                               errors=Errors(cut_by_nearer=cut))
                write_scene(sim, Path(d) / str(cut), "native")
                sc = load_scene(Path(d) / str(cut))
                for name in names:
                    # read as the person's edges: no kind of cut edge is ever left out
                    whole_edges = {"cut_variance_ratio": 1e12} if name == as_whole else {}
                    tr = reconstruct(sc, "ukf", **whole_edges)
                    crowd[name].append(1000 * box_errors(tr, sc.truth, sc.rig.up).ground_mean_m)
    for name, v in crowd.items():
        print(f"  {name:<34}" + "  ".join(f"{x:6.2f}" for x in v) + f"   mean {np.mean(v):.2f}")
    m = {k: float(np.mean(v)) for k, v in crowd.items()}
    check("drawn crowd: the cut edges handled beat reading them as the person's", m[handled] < m[as_whole],
          f"{m[handled]:.2f} vs {m[as_whole]:.2f} mm")
    bad = [w for w, ok in RESULTS if not ok]
    print("\nALL TARGETS PASS" if not bad else f"\n{len(bad)} TARGETS FAIL")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
