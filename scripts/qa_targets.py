"""Issue 11 targets: annotation QA and the report.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/qa_targets.py [--seeds 2] [--only ...]

* boxes: a seeded WILDTRACK-layout scene, 30 frames x 8 people, 1 px noise, with one box shifted
  120 px in one view and one person's boxes in every view at one frame replaced by those of a
  spot 4 m away: both found, at most 2 false alarms, the other rows' centre error at the
  clean-scene level (within 10 % or 0.5 mm). People more than half hidden behind nearer people
  are not annotated in that view (as annotators do).
* views: the same kind of scene with 2 % of the boxes in plain sight left out and one camera
  1-2 frames out of sync: every left-out box found (missing_view), the camera found with its
  offset (time_offset), at most 2 false alarms.
* keypoints: the real CMU Panoptic sequence (projected joints, 2 px noise) with detector glitches
  and a run of wrong detections in one view: every one flagged, fewer than 3 % of all points
  flagged.
* report: `gt3d reconstruct` + `gt3d report` (real subprocesses) on the bundled MultiviewX data
  and on the Panoptic keypoint scene: each report has at least 4 pictures, the open3d renders
  among them, and no warning.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from pathlib import Path

import numpy as np

from gt3dkit.api import annotation_qa, load_scene, reconstruct
from gt3dkit.commands.common import bundled
from gt3dkit.eval.metrics import box_errors
from gt3dkit.sim import Errors, simulate, write_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from tests.inject import corrupt_keypoints, move_person, shift_box  # noqa: E402


def check(label: str, ok: bool, value: str) -> bool:
    print(f"  target {label}: {value} {'PASS' if ok else 'FAIL'}")
    return ok


def boxes(seed: int) -> bool:
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "w"
        sim = simulate("wildtrack", seed=seed, frames=30, people=8, noise_px=1.0,
                       errors=Errors(dropped=0.0, hide_covered=0.5))
        write_scene(sim, root, "wildtrack")
        clean = load_scene(root)
        e0 = box_errors(reconstruct(clean, "ukf"), clean.truth, clean.rig.up).centre_mean_m
        rng = np.random.default_rng(seed)
        f1, f2 = int(rng.integers(3, 13)), int(rng.integers(16, 27))
        s_frame, s_view, s_id = shift_box(root, f1, 0, 120.0)
        frame2 = int(sorted(p.stem for p in (root / "annotations_positions").glob("*.json"))[f2])
        ids = sorted({int(i) for i in sim.truth_id[sim.truth_frame == frame2]})
        j_id = ids[1]
        i = int(np.flatnonzero((sim.truth_frame == frame2) & (sim.truth_id == j_id))[0])
        import json

        people = json.loads(sorted((root / "annotations_positions").glob("*.json"))[f2].read_text())
        person = next(k for k, p in enumerate(people) if p["personID"] == j_id)
        move_person(root, clean.rig, f2, person, sim.center_world[i] + np.array([4.0, 0, 0]),
                    sim.semi_axes[i])
        bad = load_scene(root)
        tr = reconstruct(bad, "ukf")
        qa = annotation_qa(bad, tr)
    name = bad.rig.names[s_view]
    is_shift = [r for r in qa.rows if (r[0], r[1], r[2]) == (s_frame, name, s_id)]
    # the moved frame splits the id twice: into it, and back out of it to the person's own track
    is_jump = [r for r in qa.rows if (r[0], r[2]) == (frame2, j_id) or (
        r[2] == j_id and r[4] == "identity_split" and f"in frame {frame2} " in r[6])]
    false = [r for r in qa.rows if r not in is_shift and r not in is_jump]
    keep = ~(((tr.frame == s_frame) & (tr.track_id == s_id)) | ((tr.frame == frame2) & (tr.track_id == j_id)))
    sub = dataclasses.replace(tr, **{k: getattr(tr, k)[keep] for k in (
        "frame", "track_id", "center_world", "semi_axes", "center_sd", "n_views", "kpt_world", "kpt_sd")})
    e1 = box_errors(sub, bad.truth, bad.rig.up).centre_mean_m
    print(f"boxes seed {seed}: flags {qa.counts()}; shifted box {s_frame}/{name}/id {s_id}: "
          f"{[r[4] for r in is_shift]}; moved person {frame2}/id {j_id}: {[r[4] for r in is_jump]}; "
          f"centre error clean {1000 * e0:.2f} mm, other rows {1000 * e1:.2f} mm")
    for r in false:
        print(f"    false alarm: {r}")
    ok = check("shifted box found", bool(is_shift), str(bool(is_shift)))
    ok &= check("moved person found", bool(is_jump), str(bool(is_jump)))
    ok &= check("false alarms <= 2", len(false) <= 2, str(len(false)))
    ok &= check("other rows' centre error at the clean level", e1 <= max(1.1 * e0, e0 + 5e-4),
                f"{1000 * e1:.2f} mm vs {1000 * e0:.2f} mm")
    return ok


def views(seed: int) -> bool:
    """Boxes left out in plain sight (2 %) and one camera a few frames out of sync: every
    missing box found (outside the unsynchronised camera, whose per-view flags are folded into
    its one row), the camera found with its offset, at most 2 false alarms."""
    rng = np.random.default_rng(1000 + seed)
    cam, shift = int(rng.integers(7)), int(rng.choice([-2, -1, 1, 2]))
    with tempfile.TemporaryDirectory() as tmp:
        sim = simulate("wildtrack", seed=seed, frames=30, people=8, noise_px=1.0,
                       errors=Errors(dropped=0.0, hide_covered=0.5, missing=0.02, time_offset=(cam, shift)))
        write_scene(sim, Path(tmp) / "w", "wildtrack")
        sc = load_scene(Path(tmp) / "w")
        qa = annotation_qa(sc, reconstruct(sc, "ukf"))
    name = sc.rig.names[cam]
    missing = {(i[0], i[1], i[2]) for i in sim.injected if i[4] == "missing_view" and i[1] != name}
    found = {(r[0], r[1], r[2]) for r in qa.rows if r[4] == "missing_view"}
    offs = [r for r in qa.rows if r[4] == "time_offset"]
    right = [r for r in offs if r[1] == name and f"best {shift:+d} frame" in r[6]]
    false = [r for r in qa.rows if not ((r[0], r[1], r[2]) in missing or r in right)]
    print(f"views seed {seed}: {len(missing)} boxes left out in plain sight, camera {name} {shift:+d} "
          f"frames out of sync; flags {qa.counts()}")
    for r in false:
        print(f"    false alarm: {r}")
    for x in sorted(missing - found):
        print(f"    missed: {x}")
    ok = check("every box left out in plain sight found", missing <= found,
               f"{len(missing & found)}/{len(missing)}")
    ok &= check("the unsynchronised camera found with its offset", bool(right),
                "; ".join(r[1] + ": " + r[6][:60] for r in offs) or "none")
    ok &= check("false alarms <= 2", len(false) <= 2, str(len(false)))
    return ok


def keypoints(seed: int) -> bool:
    scene = load_scene(bundled("panoptic_160906_band1"), noise_px=2.0, seed=seed)
    bad, injected = corrupt_keypoints(scene, Errors(glitch=0.002, outliers=0.001), seed=seed)
    # a run of wrong detections in one view: 10 consecutive frames of one person in one camera
    obs = bad.obs
    rng = np.random.default_rng(seed)
    cam = int(rng.integers(len(bad.rig.cameras)))
    pid = int(rng.choice(np.unique(obs.track_id)))
    frames = np.unique(obs.frame[(obs.track_id == pid) & (obs.cam == cam)])[:10]
    m = (obs.track_id == pid) & (obs.cam == cam) & np.isin(obs.frame, frames)
    kpt = obs.kpt_uv_px.copy()
    kpt[m] += np.array([150.0, -90.0])  # another person's detections: offset, consistent
    bad = dataclasses.replace(bad, obs=dataclasses.replace(obs, kpt_uv_px=kpt))
    tr = reconstruct(bad, "ukf")
    qa = annotation_qa(bad, tr)
    names = bad.rig.names
    flagged_views = {(r[0], r[1], r[2]) for r in qa.rows}
    missed = [x for x in injected if (int(x[0]), x[1], int(x[2])) not in flagged_views]
    run_missed = [int(f) for f in frames if (int(f), names[cam], pid) not in flagged_views]
    n_points = int(np.isfinite(bad.obs.kpt_uv_px[..., 0]).sum())
    n_flag_points = sum(2 if r[4] == "swapped_joints" else 1 for r in qa.rows if r[3] != "")
    share = n_flag_points / n_points
    print(f"keypoints seed {seed}: {len(injected)} injected detector errors + a 10-frame run in camera "
          f"{names[cam]} (person {pid}); flags {qa.counts()} = {100 * share:.2f} % of {n_points} points;"
          f" missed {len(missed)} injected, {len(run_missed)} run frames")
    for x in missed[:5]:
        print(f"    missed: {x}")
    ok = check("every injected error flagged", not missed, f"{len(injected) - len(missed)}/{len(injected)}")
    ok &= check("every frame of the run flagged", not run_missed,
                f"{len(frames) - len(run_missed)}/{len(frames)}")
    ok &= check("< 3 % of points flagged", share < 0.03, f"{100 * share:.2f} %")
    return ok


def report() -> bool:
    import subprocess

    ok = True
    with tempfile.TemporaryDirectory() as tmp:
        for label, args in (
            ("MultiviewX boxes", [str(bundled("multiviewx"))]),
            ("Panoptic keypoints", [str(bundled("panoptic_160906_band1")), "--noise-px", "2"]),
        ):
            out = Path(tmp) / label.split()[0]
            gt3d = [sys.executable, "-m", "gt3dkit.cli"]
            r1 = subprocess.run([*gt3d, "reconstruct", *args, "--out", str(out)], capture_output=True,
                                text=True)
            r2 = subprocess.run([*gt3d, "report", str(out)], capture_output=True, text=True)
            pngs = sorted(p.relative_to(out / "report").as_posix() for p in (out / "report").rglob("*.png"))
            renders = [p for p in pngs if p in ("overview.png", "closeup.png")]
            print(f"report {label}: exit {r1.returncode}/{r2.returncode}; {r2.stdout.strip()} "
                  f"{r2.stderr.strip()[:300]}")
            ok &= check(f"{label}: report with >= 4 pictures incl. both open3d renders, no warning",
                        r1.returncode == r2.returncode == 0 and len(pngs) >= 4 and len(renders) == 2
                        and "warning" not in r2.stderr, f"{len(pngs)} pictures, renders {renders}")
    return ok


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--only", default="boxes,views,keypoints,report")
    args = ap.parse_args()
    ok = True
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        if "boxes" in args.only:
            ok &= boxes(seed)
        if "views" in args.only:
            ok &= views(seed)
        if "keypoints" in args.only:
            ok &= keypoints(seed)
    if "report" in args.only:
        ok &= report()
    print(f"\n{'ALL TARGETS PASS' if ok else 'SOME TARGETS FAIL'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
