"""The estimator interface shared by the UKF smoother, the GTSAM smoother and triangulation,
and the one registry of estimators (the CLI, ``gt3d compare`` and the API read it)."""

from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module
from typing import Protocol

from gt3dkit.fusion.preparation.prepare import Prepared
from gt3dkit.fusion.ukf.bones import BoneSamples, PersonBones
from gt3dkit.types import OptionValue, Scene, TrackSet


@dataclass(frozen=True)
class Capabilities:
    """What an estimator can do besides :meth:`Estimator.estimate`, declared (never probed):
    ``process_noise`` -- it tunes its process noise and says the values it would choose
    (:meth:`Estimator.process_noise`: a long sequence's windows fix them once); ``bone_samples``
    -- it ties each person's joints by their bones and can give the first pass's bones
    (:meth:`Estimator.bone_samples`: the windows pool them)."""

    process_noise: bool = False
    bone_samples: bool = False


class Estimator(Protocol):
    """Anything that turns a loaded scene into tracks.

    ``name`` goes into ``meta.json``; the settings used (after any automatic tuning) go
    into ``TrackSet.info``. ``pre`` lets several estimators share one preparation.
    ``capabilities`` declares which of the optional steps do anything; an estimator without one
    still has the method, returning None.
    """

    name: str
    capabilities: Capabilities
    #: each person's bone lengths found outside the run (a long sequence's first round,
    #: :mod:`gt3dkit.windows`), used in place of its own; ignored without ``bone_samples``
    bones: PersonBones | None

    def prepare(self, scene: Scene) -> Prepared:
        """The preparation :meth:`estimate` would make itself (with this estimator's settings)."""
        ...

    def estimate(self, scene: Scene, pre: Prepared | None = None) -> TrackSet: ...

    def process_noise(self, scene: Scene, pre: Prepared | None = None) -> dict[str, float] | None:
        """The process noise :meth:`estimate` would choose, without the estimate (None: it
        tunes none)."""
        ...

    def bone_samples(self, scene: Scene, pre: Prepared | None = None) -> BoneSamples | None:
        """The first pass's bones of every row that :meth:`estimate` would tie the joints with,
        without the rest of the estimate (None: it ties none)."""
        ...


@dataclass(frozen=True)
class Entry:
    """Where an estimator lives (imported lazily: GTSAM is heavy), what it is, and what it can
    do: ``over_time`` -- it estimates each object over its frames together (a motion model), so
    it has estimates between annotations (``--every-frame``) and gains from time windows
    (``--window``, ``--jobs``, ``--scheduler``); False: each frame on its own."""

    module: str
    cls: str
    config: str
    summary: str
    over_time: bool = True


REGISTRY: dict[str, Entry] = {
    "ukf": Entry("gt3dkit.fusion.ukf.smoother", "UKFSmoother", "UKFConfig",
                 "robust UKF + RTS smoother (the primary estimator)"),
    "gtsam": Entry("gt3dkit.fusion.graph.smoother", "GTSAMSmoother", "GTSAMConfig",
                   "GTSAM factor-graph smoother (independent cross-check)"),
    "triangulation": Entry("gt3dkit.fusion.triangulate", "Triangulation", "TriangulationConfig",
                           "robust per-frame fits, no temporal model (baseline)", over_time=False),
}
ESTIMATORS = tuple(REGISTRY)


def over_time(name: str) -> bool:
    """Whether the estimator ``name`` estimates over time (:attr:`Entry.over_time`)."""
    return REGISTRY[name].over_time if name in REGISTRY else True


def make_estimator(name: str = "ukf", **config: OptionValue) -> Estimator:
    """An estimator by name with its config fields as keyword arguments."""
    if name not in REGISTRY:
        raise ValueError(f"unknown estimator {name!r} (known: {', '.join(ESTIMATORS)})")
    e = REGISTRY[name]
    mod = import_module(e.module)
    est: Estimator = getattr(mod, e.cls)(getattr(mod, e.config)(**config))
    return est
