"""The library entry points the CLI is a thin layer over."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gt3dkit.fusion.base import ESTIMATORS, Estimator, make_estimator
from gt3dkit.types import Scene, TrackSet

__all__ = ["ESTIMATORS", "make_estimator", "reconstruct"]


def reconstruct(scene: Scene | str | Path, estimator: str | Estimator = "ukf",
                out: str | Path | None = None, extra_meta: dict[str, Any] | None = None,
                **config: Any) -> TrackSet:
    """Estimate tracks for a scene (or an input folder); write ``out`` if given (with
    ``extra_meta`` added to its meta.json)."""
    from gt3dkit.io.datasets import load_scene
    from gt3dkit.io.writers import write_outputs

    sc = scene if isinstance(scene, Scene) else load_scene(Path(scene))
    est = make_estimator(estimator, **config) if isinstance(estimator, str) else estimator
    tracks = est.estimate(sc)
    if out is not None:
        write_outputs(Path(out), sc, tracks, extra_meta)
    return tracks
