"""Shared fixtures of the filter tests."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest

from gt3dkit.api import load_scene
from gt3dkit.fusion.ukf import smoother as us
from gt3dkit.fusion.ukf.measurement import Model
from gt3dkit.sim import simulate_skeletons, write_skeleton_scene


@pytest.fixture(scope="session")
def skeleton_prepared(tmp_path_factory: pytest.TempPathFactory):
    """A small skeleton scene (10 frames, 2 people, 5 cameras, 1 px) prepared for the UKF: the
    scene, its preparation, the model and a config with the process noise fixed."""
    root = Path(tmp_path_factory.mktemp("skeleton")) / "in"
    sim = simulate_skeletons("native", seed=6, frames=10, people=2, cameras=5, noise_px=1.0)
    write_skeleton_scene(sim, root, "native")
    scene = load_scene(root)
    est = us.UKFSmoother()
    pre = est.prepare(scene)
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01, joint_accel_sd=0.5)
    return scene, pre, Model.of(pre), cfg
