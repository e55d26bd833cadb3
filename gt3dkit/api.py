"""The library entry points the CLI is a thin layer over."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gt3dkit.fusion.base import Estimator
from gt3dkit.types import Scene, TrackSet

ESTIMATORS = ("ukf", "gtsam", "triangulation")


def make_estimator(name: str = "ukf", **config: Any) -> Estimator:
    """An estimator by name with its config fields as keyword arguments."""
    if name == "ukf":
        from gt3dkit.fusion.ukf_smoother import UKFConfig, UKFSmoother

        return UKFSmoother(UKFConfig(**config))
    if name == "gtsam":
        from gt3dkit.fusion.smoother_gtsam import GTSAMConfig, GTSAMSmoother

        return GTSAMSmoother(GTSAMConfig(**config))
    if name == "triangulation":
        from gt3dkit.fusion.triangulate import Triangulation, TriangulationConfig

        return Triangulation(TriangulationConfig(**config))
    raise ValueError(f"unknown estimator {name!r} (known: {', '.join(ESTIMATORS)})")


def reconstruct(scene: Scene | str | Path, estimator: str | Estimator = "ukf",
                out: str | Path | None = None, **config: Any) -> TrackSet:
    """Estimate tracks for a scene (or an input folder); write ``out`` if given."""
    from gt3dkit.io.datasets import load_scene
    from gt3dkit.io.writers import write_outputs

    sc = scene if isinstance(scene, Scene) else load_scene(Path(scene))
    est = make_estimator(estimator, **config) if isinstance(estimator, str) else estimator
    tracks = est.estimate(sc)
    if out is not None:
        write_outputs(Path(out), sc, tracks)
    return tracks
