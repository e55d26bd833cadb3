"""Seeded synthetic scenes for the tests: every estimator runs on these.

Thin wrappers over :mod:`gt3dkit.sim` that write a scene in a layout and load it
back through the loader, so each test exercises the same path as a user.
"""

from __future__ import annotations

from pathlib import Path

from gt3dkit.api import load_scene
from gt3dkit.sim import Errors, simulate, write_scene
from gt3dkit.types import Scene, SimScene


def written_scene(root: Path, layout: str = "native", **kw: object) -> tuple[Scene, SimScene]:
    """Simulate (seeded by ``kw['seed']``), write to ``root`` in ``layout``, load back."""
    sim = simulate(layout, **kw)  # type: ignore[arg-type]
    write_scene(sim, root, layout)
    return load_scene(root), sim


SMALL = dict(seed=3, frames=12, people=4, noise_px=0.0, errors=Errors(dropped=0.15))
