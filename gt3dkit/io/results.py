"""Reading a ``gt3d reconstruct`` output back: its tracks and meta.json (with the scene it was
made from: :func:`gt3dkit.api.load_run`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from gt3dkit.errors import InputError
from gt3dkit.io.writers import read_keypoints_csv, read_tracks_csv
from gt3dkit.jsondoc import json_list, json_num, json_str
from gt3dkit.parse import load_json
from gt3dkit.skeletons import SKELETONS
from gt3dkit.types import JsonDict, TrackSet


@dataclass
class Result:
    """A reconstruct output without its input: tracks (with keypoints when written), meta.json."""

    out: Path
    meta: JsonDict
    tracks: TrackSet

    @property
    def joints(self) -> tuple[str, ...]:
        return tuple(str(x) for x in json_list(self.meta, "frame", "joints"))

    @property
    def marker_names(self) -> tuple[str, ...]:
        """Joint names as the detector names them (OpenPose's ``RBigToe``...), for exports."""
        sk = json_str(self.meta, "frame", "skeleton")
        if isinstance(sk, str) and sk in SKELETONS and SKELETONS[sk].n_joints == len(self.joints):
            return SKELETONS[sk].marker_names
        return self.joints

    @property
    def fps(self) -> float:
        return json_num(self.meta, "input", "fps") or 0.0


def read_result(out: Path) -> Result:
    out = Path(out)
    if not out.is_dir():
        raise InputError(str(out), "not a folder")
    for f in ("tracks.csv", "meta.json"):
        if not (out / f).is_file():
            runs = sorted(d.name for d in out.iterdir() if (d / "tracks.csv").is_file()
                          and (d / "meta.json").is_file())
            if runs:  # a gt3d compare output: one run per estimator
                raise InputError(str(out), f"no {f}: a gt3d compare output holds one run per estimator: "
                                           f"pass one of them ({', '.join(str(out / r) for r in runs)})")
            raise InputError(str(out), f"no {f}: not a gt3d reconstruct output (nor an estimator's "
                                       "folder of a gt3d compare output)")
    meta = load_json(out / "meta.json")
    if not isinstance(meta, dict) or not isinstance(meta.get("input"), dict) \
            or not isinstance(meta.get("frame"), dict):
        raise InputError(str(out / "meta.json"), "expected an object with input and frame (a gt3d output)")
    tracks = read_tracks_csv(out / "tracks.csv")
    res = Result(out, meta, tracks)
    if (out / "keypoints.csv").is_file() and res.joints:
        res.tracks = read_keypoints_csv(out / "keypoints.csv", tracks, len(res.joints))
    return res
