"""Compile every kernel a first run uses, once (``make setup``; the test session's first fixture):
``python -m gt3dkit.commands.warmup``. A first real run then loads machine code from numba's
cache instead of compiling it (:mod:`gt3dkit.geom.kernel_cache` drops stale caches).

The kernels fall in two sets that share little: the boxes' (per-frame box fits, the noise
search, the box filter) and the joints' (triangulation, the joint filter). numba compiles on one
core, so the two sets compile side by side, the joints' in a second process
(:func:`compile_joints`), each saying when it is done."""

from __future__ import annotations

import subprocess
import sys
import time
from dataclasses import replace

from gt3dkit.api import tiny_scenes
from gt3dkit.fusion import ukf_smoother as us
from gt3dkit.fusion.base import ESTIMATORS, make_estimator
from gt3dkit.fusion.measurement import Model


def compile_boxes() -> float:
    """Estimate a 4-frame, 2-person simulated box scene by every estimator (the UKF's per-frame
    fits, noise search, forward and backward; the GTSAM smoother's factors) and run the UKF's
    filter with the noise set; returns the seconds it took."""
    t0 = time.perf_counter()
    scene = tiny_scenes()[0]
    for name in ESTIMATORS:
        make_estimator(name).estimate(scene)
    est = us.UKFSmoother()
    model = Model.of(est.prepare(scene))
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01)
    us.run_filter(model, us.initial_states(model, cfg), cfg, scene.fps)
    return time.perf_counter() - t0


def compile_joints() -> float:
    """Estimate a 3-frame simulated skeleton scene and run its joints' chains with the noise set
    (the filter's collecting pass); returns the seconds it took."""
    t0 = time.perf_counter()
    scene = tiny_scenes()[1]
    est = us.UKFSmoother()
    est.estimate(scene)
    model = Model.of(est.prepare(scene))
    cfg = replace(est.config, accel_sd=0.5, shape_sd=0.01, joint_accel_sd=0.5)
    us.run_filter(model, us.initial_states(model, cfg), cfg, scene.fps, collect=True)
    return time.perf_counter() - t0


def warm_up(say: bool = False) -> float:
    """Compile (or load from numba's disk cache) every compiled function a run uses: the box
    kernels here, the joint kernels meanwhile in a second process. ``say``: print a line as each
    set is ready. Returns the seconds it took."""
    t0 = time.perf_counter()
    side = subprocess.Popen([sys.executable, "-m", "gt3dkit.commands.warmup", "--joints",  # noqa: S603
                             *(["--say"] if say else [])])
    s = compile_boxes()
    if say:
        print(f"  box kernels ready ({s:.0f} s)", flush=True)
    if side.wait() != 0:
        raise RuntimeError("compiling the joint kernels failed (see above)")
    return time.perf_counter() - t0


#: Writes the bytecode of every installed package (``make setup`` installs with ``pip
#: --no-compile``), on every core, at the lowest priority: beside the kernels' compilation it takes
#: the core the joints' process leaves idle, and then both. A file that does not compile (a
#: package's template or test data) is skipped, as pip skips it. All of them: ``import open3d``
#: alone imports dash, plotly, IPython and werkzeug (open3d's web visualiser).
BYTECODE = ("import compileall, os, sysconfig; os.nice(19); "
            "compileall.compile_dir(sysconfig.get_paths()['purelib'], quiet=2, workers=0)")


def main(argv: list[str]) -> None:
    """``python -m gt3dkit.commands.warmup [--joints] [--say] [--bytecode]``: every kernel
    (``make setup``), or the joints' alone (:func:`warm_up`'s second process). ``--bytecode``:
    meanwhile the installed packages' bytecode is written (:data:`BYTECODE`): pip wrote it one
    file after another, 16-20 s before the kernels started; where ``PYTHONDONTWRITEBYTECODE``
    is set (as on CI), nothing else writes it, and every process compiles numpy, scipy, ...
    from source again (the test suite: 254 s -> 366 s)."""
    if "--joints" in argv:
        s = compile_joints()
        if "--say" in argv:
            print(f"  joint kernels ready ({s:.0f} s)", flush=True)
        return
    t0 = time.perf_counter()
    side = (subprocess.Popen([sys.executable, "-c", BYTECODE], stdout=subprocess.DEVNULL)  # noqa: S603
            if "--bytecode" in argv else None)
    also = "; the packages' bytecode meanwhile" if side is not None else ""
    print("gt3dkit: compiling the box and the joint kernels side by side (once: numba keeps them next "
          f"to the package){also}", flush=True)
    print(f"gt3dkit: compiled kernels ready ({warm_up(say=True):.0f} s)", flush=True)
    if side is not None:
        side.wait()  # bytecode only speeds imports up: nothing to stop for
        print(f"gt3dkit: the packages' bytecode written ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main(sys.argv[1:])
