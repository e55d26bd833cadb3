"""Compile every kernel once (``make setup``; the test session's first fixture): ``python -m
gt3dkit.commands.warmup``. A first real run then loads machine code from numba's cache instead of
spending about a minute compiling (:mod:`gt3dkit.geom.kernel_cache` drops stale caches)."""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from gt3dkit.api import load_scene
from gt3dkit.fusion import ukf_smoother as us
from gt3dkit.fusion.boxupdate import linear_forward, rows_update
from gt3dkit.fusion.measurement import Model
from gt3dkit.sim import simulate, write_scene


def compile_side() -> None:
    """Compile :func:`rows_update` (the frame-loop path's update) and :func:`linear_forward` (the
    noise search) by calls on no rows, with the argument types their callers pass."""
    n, m, C = 9, 8, 2
    f, b, i8 = np.zeros, np.bool_, np.int64
    linear_forward(f(0, i8), f(1, i8), f(1, b), f(1), f((1, n)), f((1, n, n)), 1.0, 1.0, f((3, 3)),
                   f((1, m), b), f((1, 6, m)), f((1, m)), f((1, m)), f((1, m)), f(6, i8))
    rows_update(f((1, n)), f((1, n, n)), f((1, m)), f((1, m), b), f((1, m)), f((1, m)), f((1, n)),
                f((1, n, n)), 1, f(6, np.int64), f(12), f(12), 1.0, True, 1.0, 1.0, f((3, 3)), f((C, 3, 3)),
                f((C, 5)), f((C, 3, 3)), f((C, 3)), f(C), 2, f((1, n)), f((1, n, n)), f((1, 5)), f((1, m)),
                f((1, m)), f((1, m)), 0, 0)


def warm_up() -> float:
    """Compile (or load from numba's disk cache) every compiled function of the box path by
    reconstructing a tiny simulated scene; returns the seconds it took. ``make setup`` runs it
    once, so that a first real run does not spend ~60 s compiling. Two of the functions compile
    meanwhile in a second process (numba compiles on one core): ~40 s instead of ~65 s here."""
    t0 = time.perf_counter()
    side = subprocess.Popen([sys.executable, "-c", "from gt3dkit.commands.warmup import "
                             "compile_side as f; f()"])
    with tempfile.TemporaryDirectory() as tmp:
        write_scene(simulate("wildtrack", seed=0, frames=4, people=2, noise_px=1.0), Path(tmp) / "in",
                    "wildtrack")
        scene = load_scene(Path(tmp) / "in")
    est = us.UKFSmoother()
    pre = est.prepare(scene)  # the per-frame fits (gt3dkit.fusion.boxlm)
    est.estimate(scene, pre)  # the linearised noise search, forward, backward
    model = Model.of(pre)
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01)
    init = us.initial_states(model, cfg)
    us.run_filter(model, init, cfg, scene.fps)  # forward, backward, the tangent box
    side.wait()
    us.run_filter(model, init, cfg, scene.fps, compiled=False)  # rows_update (from the cache by now)
    return time.perf_counter() - t0


if __name__ == "__main__":
    print(f"gt3dkit: compiled kernels ready ({warm_up():.0f} s)")
