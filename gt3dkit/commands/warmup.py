"""Compile every kernel once (``make setup``; the test session's first fixture): ``python -m
gt3dkit.commands.warmup``. A first real run then loads machine code from numba's cache instead of
spending about a minute compiling (:mod:`gt3dkit.geom.kernel_cache` drops stale caches)."""

from __future__ import annotations

import subprocess
import sys
import time
from dataclasses import replace

from gt3dkit.api import tiny_scenes
from gt3dkit.fusion import ukf_smoother as us
from gt3dkit.fusion.measurement import Model
from gt3dkit.types import Scene


def _tiny_model() -> tuple[Model, us.Init, us.UKFConfig, float, us.UKFSmoother, Scene]:
    """A 4-frame, 2-person simulated scene's model, initial states and a config with its noise set."""
    scene = tiny_scenes()[0]
    est = us.UKFSmoother()
    model = Model.of(est.prepare(scene))  # the per-frame fits (gt3dkit.fusion.boxlm)
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01)
    return model, us.initial_states(model, cfg), cfg, scene.fps, est, scene


def compile_side() -> None:
    """Compile the joints' chains on a tiny skeleton scene."""
    model, init, cfg, fps, _, _ = _tiny_model()
    scene = tiny_scenes()[1]
    model = Model.of(us.UKFSmoother().prepare(scene))
    cfg = replace(cfg, joint_accel_sd=0.5)
    us.run_filter(model, us.initial_states(model, cfg), cfg, scene.fps, collect=True)


def warm_up() -> float:
    """Compile (or load from numba's disk cache) every compiled function by reconstructing a tiny
    simulated scene; returns the seconds it took. ``make setup`` runs it once, so that a first
    real run does not spend a minute compiling. The joints' chains compile meanwhile in a second
    process (numba compiles on one core)."""
    t0 = time.perf_counter()
    side = subprocess.Popen([sys.executable, "-c", "from gt3dkit.commands.warmup import "
                             "compile_side as f; f()"])
    model, init, cfg, fps, est, scene = _tiny_model()
    est.estimate(scene)  # the linearised noise search, forward, backward
    us.run_filter(model, init, cfg, fps)
    side.wait()
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"gt3dkit: compiled kernels ready ({warm_up():.0f} s)")
