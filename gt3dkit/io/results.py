"""Reading a ``gt3d reconstruct`` output back: its tracks, meta.json and anomalies, and (for
pictures and 2D overlays) the scene it was made from, loaded again with the options recorded
in meta.json and the refined cameras after ``--refine-calib``."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from gt3dkit.errors import InputError
from gt3dkit.types import Scene, TrackSet


@dataclass
class Result:
    """A reconstruct output without its input: tracks (with keypoints when written), meta.json."""

    out: Path
    meta: dict[str, Any]
    tracks: TrackSet

    @property
    def joints(self) -> tuple[str, ...]:
        j = (self.meta.get("frame") or {}).get("joints") or ()
        return tuple(str(x) for x in j)

    @property
    def marker_names(self) -> tuple[str, ...]:
        """Joint names as the detector names them (OpenPose's ``RBigToe``...), for exports."""
        from gt3dkit.skeletons import SKELETONS

        sk = (self.meta.get("frame") or {}).get("skeleton")
        if isinstance(sk, str) and sk in SKELETONS and SKELETONS[sk].n_joints == len(self.joints):
            return SKELETONS[sk].marker_names
        return self.joints

    @property
    def fps(self) -> float:
        return float((self.meta.get("input") or {}).get("fps") or 0.0)


def read_result(out: Path) -> Result:
    from gt3dkit.io.datasets.common import load_json
    from gt3dkit.io.writers import read_keypoints_csv, read_tracks_csv

    out = Path(out)
    if not out.is_dir():
        raise InputError(str(out), "not a folder")
    for f in ("tracks.csv", "meta.json"):
        if not (out / f).is_file():
            raise InputError(str(out), f"no {f}: not a gt3d reconstruct or compare output")
    meta = load_json(out / "meta.json")
    if not isinstance(meta, dict) or not isinstance(meta.get("input"), dict) \
            or not isinstance(meta.get("frame"), dict):
        raise InputError(str(out / "meta.json"), "expected an object with input and frame (a gt3d output)")
    tracks = read_tracks_csv(out / "tracks.csv")
    res = Result(out, meta, tracks)
    if (out / "keypoints.csv").is_file() and res.joints:
        res.tracks = read_keypoints_csv(out / "keypoints.csv", tracks, len(res.joints))
    return res


@dataclass
class Run:
    """A reconstruct output read back, with the scene it was made from."""

    out: Path
    meta: dict[str, Any]
    scene: Scene
    tracks: TrackSet
    anomalies: list[dict[str, str]]
    notes: list[str]


def _load_scene(out: Path, meta: dict[str, Any]) -> tuple[Scene, list[str]]:
    from gt3dkit.calib.formats.native import rig_of_doc
    from gt3dkit.io.datasets import load_scene

    where = str(out / "meta.json")
    inp = meta.get("input")
    if not isinstance(inp, dict) or not isinstance(inp.get("load", inp), dict):
        raise InputError(where, "input: missing (not a gt3d reconstruct output?)")
    load = dict(inp.get("load") or {"root": inp.get("root"), "layout": inp.get("layout")})
    root = load.pop("root", None)
    if not isinstance(root, str) or not root:
        raise InputError(where, "input: no input folder recorded")
    if not Path(root).is_dir():
        raise InputError(where, f"input: the input folder {root} is not there any more (the report "
                                "draws the annotations)")
    if load.get("calib") and not Path(load["calib"]).exists():
        raise InputError(where, f"input: the calibration {load['calib']} is not there any more")
    known = {"layout", "skeleton", "fps", "calib", "cameras", "noise_px", "seed", "min_conf", "association"}
    scene = load_scene(Path(root), **{k: v for k, v in load.items() if k in known})
    notes = []
    old = inp.get("files_sha256") or {}
    changed = sorted(k for k, v in scene.files.items() if old.get(k) not in (None, v))
    if changed:
        notes.append(f"input files changed since the run: {', '.join(changed[:5])}"
                     + (" ..." if len(changed) > 5 else "") + " (the pictures show today's files)")
    refined = (meta.get("calibration_refinement") or {}).get("refined_rig")
    if refined:
        scene = replace(scene, rig=rig_of_doc(refined, f"{where}: calibration_refinement"))
        notes.append("cameras: the refined calibration the run used (meta.json calibration_refinement)")
    return scene, notes


def load_run(out: Path) -> Run:
    """:func:`read_result` plus the scene it was made from and its anomalies."""
    from gt3dkit.io.datasets.common import read_csv_rows
    from gt3dkit.io.writers import read_keypoints_csv
    from gt3dkit.qa.anomalies import COLUMNS

    res = read_result(out)
    out = res.out
    scene, notes = _load_scene(out, res.meta)
    tracks = res.tracks
    if (out / "keypoints.csv").is_file() and scene.obs.n_joints \
            and tracks.kpt_world.shape[1] != scene.obs.n_joints:
        tracks = read_keypoints_csv(out / "keypoints.csv", tracks, scene.obs.n_joints)
    anomalies = []
    if (out / "anomalies.csv").is_file():
        anomalies = [dict(r) for _, r in read_csv_rows(out / "anomalies.csv", COLUMNS)]
    return Run(out, res.meta, scene, tracks, anomalies, notes)
