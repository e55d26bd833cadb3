"""The peer in ``scripts/bench_long.py``: aniposelib 0.8.0's ``triangulate`` + ``optim_points`` on a
gt3dkit native skeleton scene, configured as ../shared/notes/peer-aniposelib.md says is fair
(anipose's own config defaults: ``scale_smooth`` 2, ``scale_length`` 2, ``scale_length_weak`` 1,
``reproj_error_threshold`` 5, ``soft_l1``, ``n_deriv_smooth`` 3, the skeleton's bones as
constraints; ``optim_points`` skipped below 20 finite points, as anipose does).

Runs in the benchmark's own environment, not gt3dkit's (aniposelib needs opencv-contrib-python,
which clashes with gt3dkit's opencv-python-headless, and jax)::

    make bench-env        # .venv-bench: pip install ".[bench]"'s requirement, aniposelib 0.8.0
    .venv-bench/bin/python scripts/peer_aniposelib.py SCENE --bones 0-1,0-2,... --out points.csv

It reads only ``SCENE/cameras.json`` and ``SCENE/keypoints.csv`` (gt3dkit's native layout: world
to camera ``x = R X + t`` in metres, OpenCV distortion) and writes ``frame,id,joint,x,y,z``.
aniposelib knows no people: each id is its own array over its first to last frame.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
from aniposelib.cameras import Camera, CameraGroup

CONFIG = {"scale_smooth": 2, "scale_length": 2, "scale_length_weak": 1, "reproj_error_threshold": 5,
          "reproj_loss": "soft_l1", "n_deriv_smooth": 3}


def camera_group(path: Path) -> tuple[CameraGroup, list[str]]:
    cams = json.loads(path.read_text())["cameras"]
    group = [Camera(matrix=np.asarray(c["K"], float), dist=np.asarray(c["dist"], float),
                    size=(c["width"], c["height"]), rvec=cv2.Rodrigues(np.asarray(c["R"], float))[0].ravel(),
                    tvec=np.asarray(c["t"], float), name=c["name"]) for c in cams]
    return CameraGroup(group), [c["name"] for c in cams]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--bones", required=True, help="the skeleton's bones as joint index pairs: 0-1,0-2,...")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    group, names = camera_group(args.scene / "cameras.json")
    bones = [[int(a) for a in b.split("-")] for b in args.bones.split(",")]
    kp = pd.read_csv(args.scene / "keypoints.csv")
    cam_of = {n: k for k, n in enumerate(names)}
    n_joints = int(kp.joint.max()) + 1
    out = []
    for pid, rows in kp.groupby("id"):
        f0, f1 = int(rows.frame.min()), int(rows.frame.max())
        pts = np.full((len(names), f1 - f0 + 1, n_joints, 2), np.nan)
        c = rows.camera.astype(str).map(cam_of).to_numpy()
        pts[c, rows.frame.to_numpy() - f0, rows.joint.to_numpy()] = rows[["u", "v"]].to_numpy()
        C, N, J, _ = pts.shape
        p3 = group.triangulate(pts.reshape(C, N * J, 2), progress=False).reshape(N, J, 3)
        if np.sum(np.isfinite(p3[..., 0])) >= 20:
            p3 = group.optim_points(pts, p3, constraints=bones, constraints_weak=[], **CONFIG)
        frames = np.unique(rows.frame.to_numpy())
        for f in frames:
            for j in range(J):
                out.append((int(f), int(pid), j, *p3[f - f0, j]))
    pd.DataFrame(out, columns=["frame", "id", "joint", "x", "y", "z"]).dropna().to_csv(args.out, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
