"""Shelf with identities given: gt3dkit beside aniposelib on the same real OpenPose detections.

    make bench-env        # .venv-bench: aniposelib 0.8.0 (../shared/notes/peer-aniposelib.md)
    OPENBLAS_NUM_THREADS=1 .venv/bin/python scripts/shelf_peer.py [--data DIR] [--peer PYTHON]

The detections of ``../shared/data/shelf_first_half`` are given the actors' identities the way a
user who has them would: in each (frame, camera) every detection is matched to the actor whose
truth joints, projected into that camera, lie nearest its own (Hungarian on the mean pixel
distance over Shelf's 12 limb joints, accepted under :data:`MATCH_PX`); the others (bystanders,
partial skeletons) are left out. The identities are all the truth lends: the pixels and
confidences are OpenPose's. Both methods read the same native folder (``cameras.json`` +
``keypoints.csv`` with BODY_25's 25 joints):

* ``gt3d reconstruct`` (UKF, its defaults);
* aniposelib ``triangulate`` + ``optim_points`` (``scripts/peer_aniposelib.py``: anipose's config,
  BODY_25's bones as constraints).

Each is scored as ``scripts/shelf_targets.py`` scores (PCP, MPJPE over the 12 limb joints,
joints beyond 300 mm) and timed as a whole process (``/usr/bin/time``: wall seconds, peak
memory). Prints; nothing is asserted.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "scripts"))

from bench_long import timed  # noqa: E402
from shelf_targets import COCO2SHELF, COCO_NAMES, read_truth, score, to_shelf  # noqa: E402

from gt3dkit.geom.camera import project_points  # noqa: E402
from gt3dkit.io.datasets import read_scene  # noqa: E402
from gt3dkit.skeletons import SKELETONS  # noqa: E402

#: A detection is an actor's when its limb joints lie this close (mean, px) to the actor's
#: projected truth joints (Shelf's hips and head are not OpenPose's: tens of pixels apart).
MATCH_PX = 60.0
GT3D = str(Path(sys.executable).with_name("gt3d"))


def given_ids(root: Path, truth: dict) -> tuple[list[list[str]], int, int]:
    """The rows of ``keypoints.csv`` (frame, camera, id, joint, u, v, conf) of the detections
    matched to an actor, with the actor as the id; and the detections matched and read."""
    scene = read_scene(root)
    obs, rig = scene.obs, scene.rig
    names = SKELETONS[scene.skeleton].marker_names
    body = np.array([names.index(COCO_NAMES[c]) for c in COCO2SHELF])  # Shelf limb joint -> BODY_25
    out, matched = [], 0
    for f in np.unique(obs.frame):
        actors = sorted(a for a, g in truth.get(int(f), {}).items() if np.isfinite(g[:12]).all())
        if not actors:
            continue
        X = np.stack([truth[int(f)][a][:12] for a in actors])  # (A, 12, 3)
        uv, _ = project_points(X, rig.K, rig.dist, rig.R, rig.t)  # (A, 12, C, 2)
        for c in np.unique(obs.cam[obs.frame == f]):
            rows = np.flatnonzero((obs.frame == f) & (obs.cam == c))
            det = obs.kpt_uv_px[rows][:, body]  # (D, 12, 2)
            conf = obs.kpt_conf[rows][:, body] if obs.kpt_conf is not None else np.ones(det.shape[:2])
            d = np.linalg.norm(det[:, None] - uv[None, :, :, c], axis=-1)  # (D, A, 12)
            ok = (conf > 0.1)[:, None, :] & np.isfinite(d)
            n = ok.sum(axis=2)
            cost = np.where(n >= 4, np.where(ok, d, 0).sum(axis=2) / np.maximum(n, 1), 1e6)
            for i, a in zip(*linear_sum_assignment(cost), strict=True):
                if cost[i, a] > MATCH_PX:
                    continue
                matched += 1
                r = rows[i]
                for j in range(len(names)):
                    u, v = obs.kpt_uv_px[r, j]
                    cf = obs.kpt_conf[r, j] if obs.kpt_conf is not None else 1.0
                    if np.isfinite(u) and np.isfinite(v) and cf > 0:
                        out.append([str(int(f)), rig.names[int(c)], str(actors[a]), str(j), f"{u:.3f}",
                                    f"{v:.3f}", f"{min(float(cf), 1.0):.4f}"])
    return out, matched, len(obs)


def shelf_joints(points: Path, skeleton: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``frame,id,joint,x,y,z`` -> per (frame, id): frames, ids and Shelf's 14 joints."""
    names = SKELETONS[skeleton].marker_names
    rows: dict[tuple[int, int], np.ndarray] = {}
    with points.open() as fh:
        for r in csv.DictReader(fh):
            k = (int(r["frame"]), int(r["id"]))
            rows.setdefault(k, np.full((len(names), 3), np.nan))[int(r["joint"])] = [
                float(r["x"]), float(r["y"]), float(r["z"])]
    keys = sorted(rows)
    kw = np.stack([rows[k] for k in keys])
    coco = kw[:, [names.index(n) for n in COCO_NAMES]]
    return np.array([k[0] for k in keys]), np.array([k[1] for k in keys]), to_shelf(coco)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--peer", default=str(REPO / ".venv-bench" / "bin" / "python"))
    args = ap.parse_args()
    root = args.data / "shelf_first_half"
    if not root.exists():
        print(f"skipped: {root} absent")
        return 0
    truth = read_truth(root / "truth_shelf15.csv")
    rows, matched, total = given_ids(root, truth)
    tmp = Path(tempfile.mkdtemp(prefix="shelf_peer_"))
    scene_dir = tmp / "scene"
    scene_dir.mkdir()
    cams = json.loads((root / "cameras.json").read_text())
    cams["skeleton"] = "body25"
    (scene_dir / "cameras.json").write_text(json.dumps(cams))
    with (scene_dir / "keypoints.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["frame", "camera", "id", "joint", "u", "v", "conf"])
        w.writerows(rows)
    print(f"Shelf frames 0-149 with identities given: {matched} of {total} detections matched to an actor "
          f"(within {MATCH_PX:g} px), {len(rows)} keypoints ({scene_dir})")
    results = {}
    sec, gb, _ = timed([GT3D, "reconstruct", str(scene_dir), "--out", str(tmp / "gt3d"), "--quiet"])
    results["gt3dkit UKF"] = (tmp / "gt3d" / "keypoints.csv", sec, gb)
    if Path(args.peer).exists():
        bones = ",".join(f"{a}-{b}" for a, b in SKELETONS["body25"].bones)
        sec, gb, _ = timed([args.peer, str(REPO / "scripts" / "peer_aniposelib.py"), str(scene_dir),
                            "--bones", bones, "--out", str(tmp / "peer.csv")])
        results["aniposelib optim_points"] = (tmp / "peer.csv", sec, gb)
    else:
        print(f"  aniposelib skipped: {args.peer} absent (make bench-env)")
    print(f"  {'method':26s} {'PCP':>6s} {'MPJPE mm':>9s} {'>300 mm':>8s} {'s':>6s} {'GB':>6s}")
    for name, (points, sec, gb) in results.items():
        frames, ids, shelf = shelf_joints(points, "body25")
        res = score(frames, shelf, truth, ids)
        limbs = ", ".join(f"{g} {100 * v:.1f}" for g, v in res["groups"].items())
        actors = ", ".join(f"{a}: {100 * v:.1f}" for a, v in res["per_actor"].items())
        print(f"  {name:26s} {100 * res['pcp']:6.1f} {res['mpjpe_mm']:9.1f} {res['over_300mm']:8d} "
              f"{sec:6.1f} {gb:6.2f}   by limb: {limbs}; by actor: {actors}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
