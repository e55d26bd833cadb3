"""Write DeepLabCut files with ``movement`` (an independent writer of DeepLabCut's and SLEAP's
formats), run from its own environment (``make movement-env``)::

    .venv-movement/bin/python scripts/peer_movement.py IN.npz OUT_DIR

``IN.npz`` holds, per camera ``name`` (listed in ``cameras``): ``<name>_position``
``(frames, 2, keypoints, individuals)`` in pixels (NaN: not seen) and ``<name>_confidence``
``(frames, keypoints, individuals)``; and ``keypoints``, ``individuals``. Each camera's poses go
to ``OUT_DIR/video_<name>DLC_movement.h5`` through ``movement.io.load_poses.from_numpy`` and
``movement.io.save_poses.to_dlc_file`` (one multi-animal file per camera).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from movement.io import load_poses, save_poses


def main() -> int:
    src, out = Path(sys.argv[1]), Path(sys.argv[2])
    data = np.load(src)
    keypoints = [str(x) for x in data["keypoints"]]
    individuals = [str(x) for x in data["individuals"]]
    out.mkdir(parents=True, exist_ok=True)
    for name in (str(x) for x in data["cameras"]):
        ds = load_poses.from_numpy(data[f"{name}_position"], data[f"{name}_confidence"],
                                   individual_names=individuals, keypoint_names=keypoints,
                                   source_software="DeepLabCut")
        save_poses.to_dlc_file(ds, out / f"video_{name}DLC_movement.h5", split_individuals=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
