"""Real OpenPose detections on Shelf, scored as the Shelf papers score them:

    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/shelf_targets.py [--data ../shared/data] [--out DIR]

``gt3d reconstruct`` runs on ``../shared/data/shelf_first_half`` (real BODY_25 JSON, no
identities; its PROVENANCE.md says how Shelf is scored), then per frame each truth actor gets the
nearest estimated person (mean error over Shelf's 14 joints), and

* **PCP**: a limb is correct when the mean of its two ends' errors is at most half its true
  length; nine limbs between Shelf's joints and the torso (mid-hip to the bottom of the head);
  averaged per actor, the score the mean over actors 1-3 (VoxelPose, MvP, 4D Association);
* **MPJPE** over the 12 limb joints of those matches, and the count of joints more than 300 mm off;
* per limb group (head, torso, upper/lower arms, upper/lower legs) and per actor, so that the worst
  rows show;
* the person ids the run made (the truth has 4 actors).

BODY_25 names are mapped to COCO-17's, then to Shelf's as VoxelPose's ``coco2shelf3D`` does
(the head from the nose, ears and shoulders). A joint the run left out (NaN) counts as wrong.
Prints; nothing is asserted (the targets belong to the keypoint issue).
"""

from __future__ import annotations

import argparse
import csv
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gt3dkit.api import load_scene, reconstruct  # noqa: E402
from gt3dkit.skeletons import SKELETONS  # noqa: E402

#: COCO-17 joint -> its name in gt3dkit's detector skeletons (BODY_25, HALPE_26, COCO-18)
COCO_NAMES = ("Nose", "LEye", "REye", "LEar", "REar", "LShoulder", "RShoulder", "LElbow", "RElbow",
              "LWrist", "RWrist", "LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle")
#: Shelf's first 12 joints from COCO-17 (VoxelPose's coco2shelf)
COCO2SHELF = np.array([16, 14, 12, 11, 13, 15, 10, 8, 6, 5, 7, 9])
#: the nine limbs between Shelf joints; the torso (mid-hip to bottom of the head) is the tenth
LIMBS = ((0, 1), (1, 2), (3, 4), (4, 5), (6, 7), (7, 8), (9, 10), (10, 11), (12, 13))
GROUPS = {"head": (8,), "torso": (9,), "upper arms": (5, 6), "lower arms": (4, 7),
          "upper legs": (1, 2), "lower legs": (0, 3)}
LIMB_JOINTS = np.arange(12)
SHELF_JOINTS = ("r_ankle", "r_knee", "r_hip", "l_hip", "l_knee", "l_ankle", "r_wrist", "r_elbow",
                "r_shoulder", "l_shoulder", "l_elbow", "l_wrist", "head_bottom", "head_top", "pelvis")


def to_shelf(coco: np.ndarray) -> np.ndarray:
    """``(..., 17, 3)`` COCO-17 joints (z up, metres) -> ``(..., 14, 3)`` Shelf joints."""
    shelf = np.zeros(coco.shape[:-2] + (14, 3))
    shelf[..., :12, :] = coco[..., COCO2SHELF, :]
    mid_sho = (coco[..., 5, :] + coco[..., 6, :]) / 2
    head_center = (coco[..., 3, :] + coco[..., 4, :]) / 2
    head_bottom = (mid_sho + head_center) / 2
    head_top = head_bottom + (head_center - head_bottom) * 2
    bottom = (shelf[..., 8, :] + shelf[..., 9, :]) / 2
    top = bottom + (coco[..., 0, :] - bottom) * np.array([0.75, 0.75, 1.5])
    bottom = bottom + (coco[..., 0, :] - bottom) * 0.5
    shelf[..., 13, :] = top * 0.75 + head_top * 0.25
    shelf[..., 12, :] = bottom * 0.75 + head_bottom * 0.25
    return shelf


def read_truth(path: Path) -> dict[int, dict[int, np.ndarray]]:
    """frame -> actor -> (15, 3) joints (Shelf order, pelvis last)."""
    out: dict[int, dict[int, np.ndarray]] = {}
    with path.open() as f:
        for r in csv.DictReader(f):
            fr, a = int(r["frame"]), int(r["actor"])
            j = int(r["joint"]) if r["joint"].isdigit() else SHELF_JOINTS.index(r["joint"])
            out.setdefault(fr, {}).setdefault(a, np.full((15, 3), np.nan))[j] = [float(r["x"]), float(r["y"]),
                                                                               float(r["z"])]
    return out


def score(frames: np.ndarray, shelf: np.ndarray, truth: dict, ids: np.ndarray | None = None) -> dict:
    """PCP per actor and limb, MPJPE over limb joints and the number beyond 300 mm; per actor the
    person-frames with an estimate within 0.5 m (mean over the 14 joints) and the share of its
    frames its most frequent id covers (``ids``: each estimate row's person id)."""
    correct: dict[int, np.ndarray] = {}
    total: dict[int, int] = {}
    errs: list[np.ndarray] = []
    near: dict[int, list[int]] = {}  # actor -> the id of the estimate within 0.5 m per frame (-1: none)
    for fr, actors in truth.items():
        mine = np.flatnonzero(frames == fr)
        for a, gt in actors.items():
            if not np.isfinite(gt[:14]).all():
                continue
            correct.setdefault(a, np.zeros(10))
            total[a] = total.get(a, 0) + 1
            if not mine.size:
                errs.append(np.full(12, np.inf))
                near.setdefault(a, []).append(-1)
                continue
            d = np.linalg.norm(shelf[mine] - gt[None, :14], axis=-1)  # (P, 14)
            d = np.where(np.isfinite(d), d, 10.0)
            best = int(np.argmin(d.mean(axis=1)))
            p = d[best]
            within = d[best].mean() <= 0.5
            near.setdefault(a, []).append(int(ids[mine[best]]) if ids is not None and within else
                                          (0 if within else -1))
            pred = shelf[mine][int(np.argmin(d.mean(axis=1)))]
            for k, (s, e) in enumerate(LIMBS):
                correct[a][k] += (p[s] + p[e]) / 2 <= 0.5 * np.linalg.norm(gt[s] - gt[e])
            gh, ph = (gt[2] + gt[3]) / 2, (pred[2] + pred[3]) / 2
            eh = np.linalg.norm(ph - gh) if np.isfinite(ph).all() else 10.0
            correct[a][9] += (eh + p[12]) / 2 <= 0.5 * np.linalg.norm(gh - gt[12])
            errs.append(p[LIMB_JOINTS])
    per_joint = np.mean(np.minimum(np.array(errs), 10.0), axis=0) if errs else np.zeros(12)
    e = np.concatenate(errs) if errs else np.zeros(0)
    per_actor = {a: float(correct[a].sum() / (10 * total[a])) for a in sorted(correct)}
    groups = {g: float(np.mean([correct[a][list(ks)].sum() / (len(ks) * total[a])
                                for a in sorted(correct) if a <= 3])) for g, ks in GROUPS.items()}
    within = {a: float(np.mean(np.asarray(v) >= 0)) for a, v in sorted(near.items())}
    cover = {}
    for a, v in sorted(near.items()):
        v = np.asarray(v)
        top = np.bincount(v[v >= 0]).max() if (v >= 0).any() else 0
        cover[a] = float(top / len(v))
    return {"pcp": float(np.mean([v for a, v in per_actor.items() if a <= 3])), "per_actor": per_actor,
            "within_0_5m": within, "one_id": cover,
            "groups": groups, "mpjpe_mm": 1000 * float(np.mean(np.minimum(e, 10.0))),
            "over_300mm": int(np.sum(e > 0.3)), "joints": int(e.size),
            "per_joint_mm": dict(zip(SHELF_JOINTS[:12], (1000 * per_joint).round(1).tolist(), strict=True))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--out", type=Path, help="keep the reconstruct output here")
    args = ap.parse_args()
    root = args.data / "shelf_first_half"
    if not root.exists():
        print(f"skipped: {root} absent")
        return 0
    out = args.out or Path(tempfile.mkdtemp(prefix="shelf_")) / "out"
    t0 = time.perf_counter()
    scene = load_scene(root)
    for w in scene.all_warnings:
        print(f"warning: {w}")
    tracks = reconstruct(scene, "ukf", out=out)
    took = time.perf_counter() - t0
    names = SKELETONS[scene.skeleton].marker_names
    coco = tracks.kpt_world[:, [names.index(n) for n in COCO_NAMES]]
    res = score(tracks.frame, to_shelf(coco), read_truth(root / "truth_shelf15.csv"), tracks.track_id)
    print(f"Shelf frames 0-149, real OpenPose {scene.skeleton}, no identities ({took:.1f} s, {out}):")
    print(f"  PCP {100 * res['pcp']:.1f} (actors 1-3: "
          + ", ".join(f"{a}: {100 * v:.1f}" for a, v in res["per_actor"].items()) + ")")
    print("  by limb: " + ", ".join(f"{g} {100 * v:.1f}" for g, v in res["groups"].items()))
    print(f"  MPJPE {res['mpjpe_mm']:.1f} mm over the 12 limb joints; {res['over_300mm']} of {res['joints']} "
          "joints more than 300 mm off")
    print("  MPJPE by joint (mm): " + ", ".join(f"{j} {v:.0f}" for j, v in sorted(
        res["per_joint_mm"].items(), key=lambda kv: -kv[1])))
    print(f"  person ids: {len(np.unique(tracks.track_id))} (the truth has 4 actors)")
    print("  truth person-frames with an estimate within 0.5 m: "
          + ", ".join(f"actor {a} {100 * v:.1f} %" for a, v in res["within_0_5m"].items()))
    print("  frames covered by each actor's most frequent id: "
          + ", ".join(f"actor {a} {100 * v:.1f} %" for a, v in res["one_id"].items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
