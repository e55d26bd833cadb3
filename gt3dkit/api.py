"""The library entry points the CLI is a thin layer over."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from gt3dkit.fusion.base import ESTIMATORS, Estimator, make_estimator
from gt3dkit.types import Scene, TrackSet

__all__ = ["ESTIMATORS", "annotation_qa", "make_estimator", "reconstruct"]


def reconstruct(scene: Scene | str | Path, estimator: str | Estimator = "ukf",
                out: str | Path | None = None, extra_meta: dict[str, Any] | None = None,
                on_stage: Callable[[str], None] | None = None, **config: Any) -> TrackSet:
    """Estimate tracks for a scene (or an input folder); write ``out`` if given (with
    ``extra_meta`` added to its meta.json). ``on_stage(name)`` is called as each stage starts
    (a progress display)."""
    stage = on_stage or (lambda name: None)
    from gt3dkit.fusion.prepare import prepare
    from gt3dkit.io.datasets import load_scene
    from gt3dkit.io.writers import write_outputs
    from gt3dkit.qa.anomalies import find_anomalies, identity_jumps
    from gt3dkit.threads import small_matrix_blas

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
    import dataclasses

    import numpy as np

    from gt3dkit.qa.anomalies import identity_jumps

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
    from gt3dkit.fusion.prepare import prepare
    from gt3dkit.qa.anomalies import find_anomalies

    return find_anomalies(scene, tracks, prepare(scene))
