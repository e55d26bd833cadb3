"""The library entry points the CLI is a thin layer over: loading an input (reading it, the
cross-camera association where its ids are per camera, the checks), reconstructing, reading a
run back with its scene."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gt3dkit.calib.formats.native import rig_of_doc
from gt3dkit.errors import InputError
from gt3dkit.fusion.associate import apply_association, associate, associate_detections, read_overrides
from gt3dkit.fusion.base import ESTIMATORS, Estimator, make_estimator
from gt3dkit.fusion.prepare import prepare
from gt3dkit.io.datasets import ASSOCIATED, checks, read_scene
from gt3dkit.io.results import read_result
from gt3dkit.io.writers import ANOMALY_COLUMNS, read_keypoints_csv, write_outputs
from gt3dkit.parse import read_csv_rows
from gt3dkit.qa.anomalies import find_anomalies, identity_jumps
from gt3dkit.threads import small_matrix_blas
from gt3dkit.types import Scene, TrackSet

__all__ = ["ESTIMATORS", "annotation_qa", "load_run", "load_scene", "make_estimator", "reconstruct"]


def load_scene(root: Path | str, layout: str | None = None, skeleton: str | None = None,
               fps: float | None = None, calib: Path | str | None = None,
               association: Path | str | None = None, **panoptic_options: Any) -> Scene:
    """Load any supported input folder (layout detected when not given): read it
    (:func:`gt3dkit.io.datasets.read_scene`, whose arguments these are), give ids per camera or
    none global identities (:mod:`gt3dkit.fusion.associate`, with the overrides of the file
    ``association``), then check it (:func:`gt3dkit.io.datasets.checks.check_scene`)."""
    scene = read_scene(root, layout, skeleton, fps, calib, association, **panoptic_options)
    if scene.layout in ASSOCIATED:  # ids per camera or none -> global identities, before the checks
        over = read_overrides(Path(association), scene.rig.names) if association is not None else None
        per_frame = scene.layout == "openpose" or scene.association == "detections"
        assoc = (associate_detections if per_frame else associate)(scene, overrides=over)
        scene = dataclasses.replace(apply_association(scene, assoc), association=assoc)
        out = sum(1 for r in assoc.rows if r[3] < 0)
        if out:
            scene = dataclasses.replace(scene, warnings=(*scene.warnings, f"{out} detections no second view "
                                                         "confirms left out (association.csv, global id -1)"))
        if not len(scene.obs):
            raise InputError(str(root), "no person is seen by two cameras at once (nothing to reconstruct)")
    return checks.check_scene(scene)


def reconstruct(scene: Scene | str | Path, estimator: str | Estimator = "ukf",
                out: str | Path | None = None, extra_meta: dict[str, Any] | None = None,
                on_stage: Callable[[str], None] | None = None, **config: Any) -> TrackSet:
    """Estimate tracks for a scene (or an input folder); write ``out`` if given (with
    ``extra_meta`` added to its meta.json). ``on_stage(name)`` is called as each stage starts
    (a progress display)."""
    stage = on_stage or (lambda name: None)

    with small_matrix_blas():  # one BLAS thread for our small matrices (gt3dkit.threads)
        sc = scene if isinstance(scene, Scene) else load_scene(Path(scene))
        est = make_estimator(estimator, **config) if isinstance(estimator, str) else estimator
        stage("per-frame fits")
        own = getattr(est, "prepare", None)
        pre = own(sc) if callable(own) else prepare(sc)
        jumps = identity_jumps(pre, sc.fps)
        clean = without_identity_jumps(sc, pre, jumps)
        stage(f"{getattr(est, 'name', 'estimator')}")
        # the preparation is the estimator's own when no annotation was left out
        tracks = est.estimate(clean, pre) if clean is sc and callable(own) else est.estimate(clean)
        if out is not None:
            stage("annotation QA, writing")
            qa = find_anomalies(sc, tracks, pre, jumps=jumps)
            tracks.info["qa"] = {"anomalies": qa.counts(), "file": "anomalies.csv",
                                 "left_out_object_frames": len(sc.obs) - len(clean.obs)}
            write_outputs(Path(out), sc, tracks, extra_meta, anomalies=qa)
    return tracks


def without_identity_jumps(scene: Scene, pre: Any, jumps: list[Any] | None = None) -> Scene:
    """``scene`` without the annotations of object-frames whose views agree on a place the
    object cannot have reached (:func:`gt3dkit.qa.anomalies.identity_jumps`: a swapped or
    mis-keyed id): they belong to someone else, and would bend the track."""
    jumps = identity_jumps(pre, scene.fps) if jumps is None else jumps
    if not jumps:
        return scene
    rows = pre.rows
    bad = {(int(rows.frames[rows.row_t[r]]), int(rows.obj_ids[rows.row_o[r]])) for r, *_ in jumps}
    keep = np.array([(int(f), int(i)) not in bad for f, i in
                     zip(scene.obs.frame, scene.obs.track_id, strict=True)])
    return dataclasses.replace(scene, obs=scene.obs.select(keep))


def annotation_qa(scene: Scene, tracks: TrackSet) -> Any:
    """Every input annotation scored against ``tracks``: :class:`gt3dkit.qa.anomalies.Anomalies`."""
    return find_anomalies(scene, tracks, prepare(scene))


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
        scene = dataclasses.replace(scene, rig=rig_of_doc(refined, f"{where}: calibration_refinement"))
        notes.append("cameras: the refined calibration the run used (meta.json calibration_refinement)")
    return scene, notes


def load_run(out: Path) -> Run:
    """:func:`read_result` plus the scene it was made from and its anomalies."""
    res = read_result(out)
    out = res.out
    scene, notes = _load_scene(out, res.meta)
    tracks = res.tracks
    if (out / "keypoints.csv").is_file() and scene.obs.n_joints \
            and tracks.kpt_world.shape[1] != scene.obs.n_joints:
        tracks = read_keypoints_csv(out / "keypoints.csv", tracks, scene.obs.n_joints)
    anomalies = []
    if (out / "anomalies.csv").is_file():
        anomalies = [dict(r) for _, r in read_csv_rows(out / "anomalies.csv", ANOMALY_COLUMNS)]
    return Run(out, res.meta, scene, tracks, anomalies, notes)
