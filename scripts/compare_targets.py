# %% [markdown]
# # Estimators side by side: the targets of issue 5
#
# The three estimators behind one interface (UKF + RTS, GTSAM smoother, per-frame
# triangulation) on seeded synthetic scenes with 2 px noise:
# * skeletons: 10 HD cameras (Panoptic-like dome, distortion), 3 people x 30 frames, coco19;
# * boxes: WILDTRACK layout, 7 cameras, 10 people x 40 frames, 15 % of views dropped.
# Also the paper's tracking metrics (MOTA, IDF1, HOTA, OSPA(2) at 1 m) on the box scenes.
#
# Run: `.venv/bin/python scripts/compare_targets.py [--seeds 3]`

# %%
from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

from gt3dkit import load_scene, reconstruct
from gt3dkit.eval.metrics import box_errors
from gt3dkit.eval.pose import mpjpe_by_id
from gt3dkit.eval.tracking import tracking_scores
from gt3dkit.sim import simulate, simulate_skeletons, write_scene, write_skeleton_scene

ESTS = ("ukf", "gtsam", "triangulation")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    args = ap.parse_args(argv)
    sk: dict[str, list[list[float]]] = {e: [] for e in ESTS}
    bx: dict[str, list[list[float]]] = {e: [] for e in ESTS}
    for seed in range(args.seeds):
        with tempfile.TemporaryDirectory() as d:
            sim = simulate_skeletons("native", seed=seed, frames=30, people=3, noise_px=2.0,
                                     cameras=10)
            write_skeleton_scene(sim, Path(d), "native")
            scene = load_scene(Path(d))
            for e in ESTS:
                tr = reconstruct(scene, e)
                mm, matched, total = mpjpe_by_id(tr, scene.truth)
                sk[e].append([mm, matched / total, tr.info.seconds])
        with tempfile.TemporaryDirectory() as d:
            sim2 = simulate("wildtrack", seed=seed, frames=40, people=10, noise_px=2.0)
            write_scene(sim2, Path(d), "wildtrack")
            scene = load_scene(Path(d))
            for e in ESTS:
                tr = reconstruct(scene, e)
                er = box_errors(tr, scene.truth, scene.rig.up)
                t = tracking_scores(tr, scene.truth, scene.rig.up)
                bx[e].append([1e3 * er.centre_mean_m, 1e3 * er.height_mean_m, er.coverage,
                              100 * t["mota"], 100 * t["idf1"], 100 * t["hota"], t["ospa2_m"],
                              tr.info.seconds])
    S = {e: np.mean(v, axis=0) for e, v in sk.items()}
    B = {e: np.mean(v, axis=0) for e, v in bx.items()}
    print(f"skeletons, 10 cameras, 2 px noise ({args.seeds} seeds)")
    print(f"{'estimator':<15}{'MPJPE mm':>10}{'covered%':>10}{'sec':>7}")
    for e in ESTS:
        print(f"{e:<15}{S[e][0]:>10.3f}{100 * S[e][1]:>10.1f}{S[e][2]:>7.1f}")
    print(f"\nboxes, WILDTRACK layout, 2 px noise ({args.seeds} seeds)")
    print(f"{'estimator':<15}{'centre mm':>10}{'height mm':>10}{'cover%':>8}{'MOTA':>7}{'IDF1':>7}"
          f"{'HOTA':>7}{'OSPA2 m':>9}{'sec':>7}")
    for e in ESTS:
        b = B[e]
        print(f"{e:<15}{b[0]:>10.2f}{b[1]:>10.2f}{100 * b[2]:>8.1f}{b[3]:>7.1f}{b[4]:>7.1f}"
              f"{b[5]:>7.1f}{b[6]:>9.4f}{b[7]:>7.1f}")
    checks = [
        ("skeleton UKF MPJPE <= 2.0 mm", S["ukf"][0] <= 2.0, S["ukf"][0]),
        ("skeleton GTSAM MPJPE <= 2.0 mm", S["gtsam"][0] <= 2.0, S["gtsam"][0]),
        ("skeleton UKF and GTSAM cover every pose",
         min(min(r[1] for r in sk["ukf"]), min(r[1] for r in sk["gtsam"])) == 1.0, 1.0),
        ("skeleton triangulation MPJPE <= 3.5 mm", S["triangulation"][0] <= 3.5,
         S["triangulation"][0]),
        ("skeleton GTSAM / triangulation <= 0.7", S["gtsam"][0] / S["triangulation"][0] <= 0.7,
         S["gtsam"][0] / S["triangulation"][0]),
        ("boxes UKF centre <= 12 mm, height <= 6 mm", B["ukf"][0] <= 12 and B["ukf"][1] <= 6,
         B["ukf"][0]),
        ("boxes GTSAM centre <= 12 mm, height <= 6 mm", B["gtsam"][0] <= 12 and B["gtsam"][1] <= 6,
         B["gtsam"][0]),
        ("boxes triangulation centre <= 30 mm", B["triangulation"][0] <= 30, B["triangulation"][0]),
        ("boxes GTSAM / triangulation <= 0.9", B["gtsam"][0] / B["triangulation"][0] <= 0.9,
         B["gtsam"][0] / B["triangulation"][0]),
    ]
    ok = True
    print()
    for what, good, v in checks:
        ok &= bool(good)
        print(f"  target {what}: {v:.3f} {'PASS' if good else 'FAIL'}")
    print("\nALL TARGETS PASS" if ok else "\nSOME TARGETS FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
