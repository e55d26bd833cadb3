"""The estimator interface shared by the UKF smoother, the GTSAM smoother and triangulation."""

from __future__ import annotations

from typing import Protocol

from gt3dkit.types import Scene, TrackSet


class Estimator(Protocol):
    """Anything that turns a loaded scene into tracks.

    ``name`` goes into ``meta.json``; ``params()`` returns the settings used (after
    any automatic tuning, filled in ``TrackSet.info``).
    """

    name: str

    def estimate(self, scene: Scene) -> TrackSet: ...
